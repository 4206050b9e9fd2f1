"""Every result number in README.md and docs/figures/*.md is read from a committed table.

The docs tag results with ``<!-- data: TABLE.csv ...; settings: ... -->`` markers
(:mod:`cobelrun.figures.doc_numbers`); a number that no named table in ``docs/figures/data``
holds at the shown precision fails, and so does a table on a figure page, or a figure row of
README's figure table, left without a marker.
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
FIGURE_ROW = re.compile(r"^\| (Fig\. \d|Mattar|Russek|Water maze)")
PROVENANCE = {"table", "source", "command", "cobel_commit", "seeds", "machine", "wall_time_s"}


def test_every_result_number_is_in_a_table():
    problems = doc_numbers.check([*PAGES, README], DATA, all_tables=PAGES)
    assert not problems, "\n".join(problems)


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
