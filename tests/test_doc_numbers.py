"""Every number in README.md's figure rows and docs/figures/*.md is read from a committed table.

The docs tag results with ``<!-- data: TABLE.csv ...; settings: ... -->`` markers
(:mod:`cobelrun.figures.doc_numbers`); a number that no named table in ``docs/figures/data``
holds at the shown precision fails, and so does a table on a figure page, or a figure row of
README's figure table, left without a marker. On the figure pages the text no marker covers is
checked too: each number must be held by a table the page names (or ``paper.csv``) or be in
:data:`ALLOW`, the reviewed list of settings and constants that need no table.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pandas as pd
import pytest

from cobelrun.figures import doc_numbers

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "docs" / "figures" / "data"
PAGES = sorted((ROOT / "docs" / "figures").glob("*.md"))
README = ROOT / "README.md"
#: other docs that quote a figure's table: their tagged text is checked (untagged text there
#: is the docs' own, e.g. settings and measurements with no committed table, said so in place)
QUOTING = [ROOT / "docs" / name for name in ("replay.md", "water_maze.md", "rendering.md")]
FIGURE_ROW = re.compile(r"^\| (Fig\. \d|Mattar|Russek|Water maze)")
#: numbers on a figure page that no table holds and need none: settings of the method and the
#: paper's constants the page quotes (page -> {number as written: why}). Reviewed; keep small.
ALLOW: dict[str, dict[str, str]] = {
    "fig4.md": {"400": "the paper's steps per repetition (5 x 400)",
                "2,000": "the paper's steps per point (5 x 400)"},
    "fig6a.md": {"90": "the paper's 90-degree turns", "49": "seeds 0-49 (the 50 runs)"},
    "fig7.md": {"0.01": "the paper's soft target update (a setting)"},
    "fig8.md": {"77": "the paper's 77-node graph", "240": "the paper's 240-degree panorama",
                "1e-3": "learning rate (setting)", "3e-5": "learning rate (setting)",
                "1e-4": "learning rate (setting)"},
    "fig9.md": {"299": "seeds 0-299 (the original's 300 agents)"},
    "morris.md": {"493": "Foster et al.'s place cells (setting)", "60": "probe length, s (setting)",
                  "0.40": "tests/test_water_maze.py's threshold, not a result"},
}  # fmt: skip
PROVENANCE = {"table", "source", "command", "cobel_commit", "seeds", "machine", "wall_time_s"}


def test_every_result_number_is_in_a_table():
    problems = doc_numbers.check([*PAGES, README, *QUOTING], DATA, all_tables=PAGES, pages=PAGES,
                                 allow=ALLOW)  # fmt: skip
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("doc", QUOTING, ids=lambda p: p.name)
def test_docs_quoting_a_figure_table_tag_it(doc):
    """Each of these docs quotes a committed table under a marker (so the check above reads
    it): e.g. Replay's revaluation scores are revaluation.csv's, not a second typed copy."""
    tables = {t for c in doc_numbers.covered(doc) for t in c.tables}
    assert tables and all((DATA / t).is_file() for t in tables), (doc.name, tables)


def test_allow_list_is_current():
    """Every allowed number still appears on its page (a stale entry would hide a new one)."""
    for page, entries in ALLOW.items():
        shown = {v for c in doc_numbers.uncovered(ROOT / "docs" / "figures" / page)
                 for _, v, _, _ in doc_numbers.numbers(c.text)}  # fmt: skip
        stale = [
            k
            for k in entries
            if not any(abs(float(k.replace(",", "")) - v) <= 1e-9 * v for v in shown)
        ]
        assert not stale, f"{page}: {stale} no longer on the page"


def test_an_untagged_number_that_drifted_fails(tmp_path):
    """Untagged text on a page is checked against the tables it links and its allow list."""
    (tmp_path / "t.csv").write_text("measure,mean\nlat_91_100,9.224\n")
    (tmp_path / "paper.csv").write_text("figure,measure,value\nx,path,8\n")
    page = tmp_path / "page.md"
    text = (
        "See [`data/t.csv`](data/t.csv).\n\nLatency over trials 91-100: {} steps, max {} steps.\n"
    )
    page.write_text(text.format("9.2", "35"))
    allow = {"page.md": {"35": "max steps (setting)"}}
    assert doc_numbers.check([page], tmp_path, pages=[page], allow=allow) == []
    page.write_text(text.format("9.3", "35"))  # drifted from the table's 9.224
    (problem,) = doc_numbers.check([page], tmp_path, pages=[page], allow=allow)
    assert "'9.3' (untagged) is in no table the page names (t.csv, paper.csv)" in problem
    page.write_text(text.format("9.2", "36"))  # a setting not on the list
    assert "'36'" in doc_numbers.check([page], tmp_path, pages=[page], allow=allow)[0]
    page.write_text(text.format("9.2", "8"))  # the paper's table counts on every page
    assert doc_numbers.check([page], tmp_path, pages=[page], allow=allow) == []
    page.write_text("<!-- data: none -->\n| trials | latency |\n| - | - |\n| 91-100 | 9.3 |\n")
    assert "not a settings table" in doc_numbers.check([page], tmp_path, pages=[page])[0]


def test_a_drifted_number_on_the_real_page_fails(tmp_path):
    """A copy of a real figure page with one number changed in untagged text fails the test."""
    page = ROOT / "docs" / "figures" / "fig6b.md"
    copy = tmp_path / "fig6b.md"
    copy.write_text(page.read_text())
    assert doc_numbers.check([copy], DATA, pages=[copy], allow=ALLOW) == []
    copy.write_text(page.read_text() + "\nThe original's latency was 9.87 steps.\n")
    (problem,) = doc_numbers.check([copy], DATA, pages=[copy], allow=ALLOW)
    assert "'9.87' (untagged)" in problem


def test_readme_figure_rows_have_markers():
    rows = [(k, line) for k, line in enumerate(README.read_text().splitlines(), 1)
            if FIGURE_ROW.match(line)]  # fmt: skip
    assert len(rows) >= 9
    missing = [f"README.md:{k}" for k, line in rows if not doc_numbers.MARKER.search(line)]
    assert not missing, missing


def test_every_table_has_its_provenance():
    tables = sorted(DATA.glob("*.csv"))
    assert tables
    for csv in tables:
        side = csv.with_suffix(".provenance.json")
        assert side.is_file(), f"{csv.name} has no {side.name}"
        prov = json.loads(side.read_text())
        assert PROVENANCE <= set(prov), f"{side.name} lacks {PROVENANCE - set(prov)}"
        assert prov["source"] in {"run", "transcribed"}
        if prov["source"] == "transcribed":
            assert prov.get("transcribed_from"), side.name
        assert len(pd.read_csv(csv)) > 0


@pytest.mark.parametrize(
    ("text", "tables", "ok"),
    [
        (
            "| latency, trials 91-100 | 9.2 steps |",
            {"t.csv": "measure,mean\nlat_91_100,9.224\n"},
            True,
        ),
        (
            "| latency, trials 91-100 | 9.3 steps |",
            {"t.csv": "measure,mean\nlat_91_100,9.224\n"},
            False,
        ),
        ("probe 76% in the target quadrant", {"t.csv": "q,f\ntarget,0.7604\n"}, True),
        ("probe 0.77 in the target quadrant", {"t.csv": "q,f\ntarget,0.7604\n"}, False),
        ("Fig. 6B `cobel run x=3` path 8", {"t.csv": "a\n1\n"}, False),
        ("Mann-Whitney p 6.7e-08", {"t.csv": "p\n6.74785e-08\n"}, True),
        ("Mann-Whitney p 6.8e-08", {"t.csv": "p\n6.74785e-08\n"}, False),
    ],
)
def test_a_drifted_number_fails(tmp_path, text, tables, ok):
    for name, body in tables.items():
        (tmp_path / name).write_text(body)
    doc = tmp_path / "page.md"
    doc.write_text(f"<!-- data: {' '.join(tables)} -->\n{text}\n")
    assert (doc_numbers.check([doc], tmp_path) == []) is ok


def test_settings_and_inline_markers(tmp_path):
    (tmp_path / "t.csv").write_text("x\n0.5\n")
    doc = tmp_path / "page.md"
    doc.write_text("| a | b |\n| - | - |\n| path 8 | 0.5 <!-- data: t.csv; settings: 8 --> |\n")
    assert doc_numbers.check([doc], tmp_path, all_tables=[doc]) == []
    doc.write_text("| a | b |\n| - | - |\n| path 8 | 0.5 |\n")
    assert doc_numbers.check([doc], tmp_path, all_tables=[doc]) == [
        f"{doc}:1: a table without a <!-- data: ... --> marker"
    ]
    doc.write_text("<!-- data: gone.csv -->\n0.5\n")
    assert "not in" in doc_numbers.check([doc], tmp_path)[0]


def test_markers_in_code_are_text_and_bad_settings_fail_clearly(tmp_path):
    from cobelrun.errors import CobelError

    doc = tmp_path / "page.md"
    doc.write_text("Tag with `<!-- data: T.csv; settings: N -->` before a table: 0.5\n")
    assert doc_numbers.check([doc], tmp_path) == []
    doc.write_text("<!-- data: t.csv; settings: N -->\n0.5\n")
    with pytest.raises(CobelError, match="settings must be numbers"):
        doc_numbers.check([doc], tmp_path)


def test_a_number_from_another_row_of_the_table_fails(tmp_path):
    """A table row labelled with numbers (``| 101-110 |``) is read against the table's rows of
    that label: a value the table holds in another row fails."""
    (tmp_path / "t.csv").write_text("measure,mean\nright_81_100,1.0\nright_101_110,0.6625\n"
                                    "right_111_120,0.4875\n")  # fmt: skip
    # p.csv has no row labelled 101-110: read whole (its 0.68 passes)
    (tmp_path / "p.csv").write_text("trials,rate\n1-20,0.68\n")
    doc = tmp_path / "page.md"
    text = "<!-- data: t.csv p.csv -->\n| trials | rate | paper |\n| --- | --- | --- |\n{}\n"
    doc.write_text(text.format("| 101-110 | 0.66 | 0.68 |"))
    assert doc_numbers.check([doc], tmp_path) == []
    doc.write_text(text.format("| 101-110 | 0.49 | 0.68 |"))  # 111-120's value
    (problem,) = doc_numbers.check([doc], tmp_path)
    assert "'0.49' in the row labelled '101-110' is in no row of t.csv with that label" in problem


def test_a_number_moved_to_another_row_of_a_real_page_fails(tmp_path):
    """fig6a.md's Dyna-Q rate over trials 101-110 swapped for its 111-120 one (both in
    fig6a.csv, in different rows)."""
    page = ROOT / "docs" / "figures" / "fig6a.md"
    text = page.read_text()
    row = next(line for line in text.splitlines() if line.startswith("| 101-110 |"))
    later = next(line for line in text.splitlines() if line.startswith("| 111-120 |"))
    dyna, dyna_later = row.split("|")[-2].strip(), later.split("|")[-2].strip()
    assert dyna != dyna_later
    copy = tmp_path / "fig6a.md"
    copy.write_text(text.replace(row, row[: row.rindex(dyna)] + dyna_later + " |"))
    (problem,) = doc_numbers.check([copy], DATA)
    assert f"'{dyna_later}' in the row labelled '101-110'" in problem


def test_a_row_labelled_in_words_is_read_against_that_labels_rows(tmp_path):
    """``| sr_td | ...`` against the rows with a text cell ``sr_td``: another agent's score
    fails; a first cell naming a figure (README's rows) is no label."""
    (tmp_path / "t.csv").write_text("design,agent,score\nreward,sr_td,0.95\nreward,dyna_q,0.8\n"
                                    "transition,sr_td,0\nreward,Fig. 4,0.5\n")  # fmt: skip
    doc = tmp_path / "page.md"
    text = "<!-- data: t.csv -->\n| agent | reward | transition |\n| --- | --- | --- |\n{}\n"
    doc.write_text(text.format("| `sr_td` | 0.95 | 0.00 |"))
    assert doc_numbers.check([doc], tmp_path) == []
    doc.write_text(text.format("| `sr_td` | 0.80 | 0.00 |"))  # dyna_q's score
    (problem,) = doc_numbers.check([doc], tmp_path)
    assert "'0.80' in the row labelled '`sr_td`' is in no row of t.csv" in problem
    doc.write_text(text.format("| Fig. 4 | 0.80 | 0.00 |"))  # a figure's name: the whole table
    assert doc_numbers.check([doc], tmp_path) == []


def test_a_score_moved_to_another_agent_on_the_real_page_fails(tmp_path):
    """revaluation.md with sr_td's reward score replaced by dyna_q (1)'s (both in the CSV)."""
    page = ROOT / "docs" / "figures" / "revaluation.md"
    row = "| sr_td | reward only | 0.95 | 0.00 | 0.00 |"
    assert row in page.read_text()
    copy = tmp_path / "revaluation.md"
    copy.write_text(page.read_text().replace(row, row.replace("0.95", "0.80")))
    (problem,) = doc_numbers.check([copy], DATA)
    assert "'0.80' in the row labelled 'sr_td'" in problem


def test_a_mixed_label_and_every_drift_of_a_block_are_reported_on_their_lines(tmp_path):
    """``| sr_dyna (1) |`` is read as the rows of sr_dyna with a 1 in them (replay budget 1);
    a row's drift is reported on its own line even when another number of the block is in no
    table at all."""
    page = ROOT / "docs" / "figures" / "revaluation.md"
    text = page.read_text()
    row = "| sr_dyna (1) | reward with too little replay | 1.00 | 0.00 | 0.00 |"
    other = "| q_learning | none | 0.00 | 0.00 | 0.00 |"
    assert row in text and other in text
    line = text.splitlines().index(row) + 1
    copy = tmp_path / "revaluation.md"
    copy.write_text(text.replace(row, row.replace("1.00", "0.80")).replace(other, other.replace(
        "| 0.00 | 0.00 | 0.00 |", "| 0.777 | 0.00 | 0.00 |")))  # fmt: skip
    problems = doc_numbers.check([copy], DATA)
    assert any("'0.777' is in no table" in p for p in problems), problems
    assert any(p.startswith(f"{copy}:{line}: '0.80' in the row labelled 'sr_dyna (1)'")
               for p in problems), problems  # fmt: skip
