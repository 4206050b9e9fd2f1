"""Numbers in the docs against the committed tables (``docs/figures/data``).

A result in the docs is tagged with a marker naming the tables that hold it::

    <!-- data: fig6b.csv paper.csv; settings: 8 35 -->

- on a line of its own, the marker covers the next block (the lines up to the next blank line:
  a paragraph or a whole table);
- at the end of a line (e.g. in a table's last cell), it covers that line alone.

Every number in a covered text must be *held* by one of the named tables, at the precision the
doc shows it (``0.76`` is held by a cell 0.7604; ``76%`` by 0.7604 too), or be listed after
``settings:`` (a number that is a setting, not a result: a budget, a path length). Cells are
read as numbers, and the numbers inside text cells and column names count too (so ``trials
91-100`` is held by a measure named ``right_91_100``). Not read as numbers: inline code,
link targets, HTML comments, ``Fig. 6B``-style references, dates and years, version numbers.

**Rows.** A row of a markdown table is read against the rows of the named tables that carry
its label (its first cell): a label with numbers (``| 101-110 | ...``) against the rows whose
text cells hold those numbers (``right_101_110``, ``101-110``), a label in words (``| sr_td |
...``) against the rows with a text cell equal to it (markup and case aside), a mixed label
(``| dyna_q (1) |``) against the rows with a text cell equal to its words and its numbers in any
cell (``replay_budget`` 1). Each number of the row must be held by such a row (any of its
cells: a drift to its SD or median, or to another measure of the same label, still passes),
so a number that drifted to another row's value fails although the table holds it. A named
table with no row of that label (the paper's numbers, a table of scalars) is read whole, as
above; a first cell naming a figure (README's ``| Fig. 4 |``) is no label.

``<!-- data: none -->`` marks a table that holds no results: only a table of settings (its header
starts ``| setting |``, e.g. a departures table) may carry it. :func:`check` returns one message
per number no table holds, per marker naming a missing table, per ``none`` marker on anything
else, and per results table left without a marker (see :func:`needs_marker`).

**Every number of a page** (``pages``): on a figure page the text that no marker covers is
checked too, against the summary tables the page names (its markers' tables and every
``data/NAME.csv`` it links, per-run ``*_runs.csv`` tables only where a marker names them), the
paper's numbers (``paper.csv``) and the
page's allowlist (``allow``: a number that is a setting, a count of the method or a quoted
constant, with the reason it needs no table). So a result typed into a paragraph without a
marker fails as soon as no table holds it.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from cobelrun.errors import CobelError

CODE = re.compile(r"`[^`]*`")
MARKER = re.compile(r"<!--\s*data:\s*(?P<body>.*?)\s*-->")
#: a table a page links (``[...](data/fig9.csv)``)
LINKED = re.compile(r"\(data/(?P<name>[\w.-]+\.csv)\)")
#: the numbers of a table's provenance sidecar that count as the table's
SIDECAR_TIMES = ("wall_time_s", "cpu_time_s", "export_wall_time_s")
#: the paper's numbers (transcribed), part of every page's tables
PAPER = "paper.csv"
FENCE = re.compile(r"^\s*(```|~~~)")
NUMBER = re.compile(
    r"(?<![\w.])(\d{1,3}(?:,\d{3})+|\d+)(\.\d+)?(?:[eE](?P<exp>[-+]?\d+))?(?P<pct>\s?%)?"
)
#: text that holds digits but no result
NOT_NUMBERS = [
    re.compile(r"<!--.*?-->"),
    re.compile(r"`[^`]*`"),
    re.compile(r"\]\([^)]*\)"),  # link targets
    re.compile(r"https?://\S+"),
    re.compile(r"\bFig(?:ure)?s?\.?\s*\d+[A-Z]?(?:/[A-Z])?(?:\s*and\s*\d+[A-Z]?)?"),
    re.compile(r"\b\d{4}-\d{2}-\d{2}\b"),  # dates
    re.compile(r"\b(?:19|20)\d{2}\b"),  # years
    re.compile(r"\bv\d+(?:\.\d+)*\b"),  # versions
    re.compile(r"\b\d+\.\d+\.\d+\b"),  # versions x.y.z (TensorFlow 2.15.1)
    re.compile(r"\b[A-Za-z]+\d+\b"),  # names with digits (keras-rl2, H100, issue refs)
    re.compile(r"\b[23]D\b"),  # 2D, 3D
]


@dataclass(frozen=True)
class Covered:
    """A text of a doc that a marker covers."""

    doc: Path
    line: int  # 1-based, the first line covered
    text: str
    tables: tuple[str, ...]
    settings: tuple[float, ...]


def parse_marker(body: str) -> tuple[tuple[str, ...], tuple[float, ...]]:
    """``"a.csv b.csv; settings: 8 35"`` -> (("a.csv", "b.csv"), (8.0, 35.0))."""
    tables_part, _, rest = body.partition(";")
    tables = tuple(t for t in tables_part.split() if t != "none")
    settings: tuple[float, ...] = ()
    if rest.strip().startswith("settings:"):
        words = rest.strip()[len("settings:") :].split()
        try:
            settings = tuple(float(x) for x in words)
        except ValueError:
            raise CobelError(
                f"data marker {body!r}: settings must be numbers, got {words}"
            ) from None
    return tables, settings


def covered(doc: Path) -> Iterator[Covered]:
    """The texts of ``doc`` that markers cover."""
    lines = doc.read_text().splitlines()
    k = 0
    while k < len(lines):
        line = lines[k]
        # a marker written inside inline code (e.g. in these docs) is text, not a marker
        m = MARKER.search(CODE.sub(lambda c: " " * len(c.group(0)), line))
        if m and not line[: m.start()].strip() and not line[m.end() :].strip():
            tables, settings = parse_marker(m.group("body"))
            j = k + 1
            while j < len(lines) and lines[j].strip():
                j += 1
            yield Covered(doc, k + 2, "\n".join(lines[k + 1 : j]), tables, settings)
            k = j
            continue
        if m:
            tables, settings = parse_marker(m.group("body"))
            yield Covered(doc, k + 1, line, tables, settings)
        k += 1


def numbers(text: str) -> list[tuple[str, float, float, bool]]:
    """The numbers of ``text`` as (as written, value, half a unit of its last digit, percent);
    ``6.7e-08`` is read with its exponent."""
    for pattern in NOT_NUMBERS:
        text = pattern.sub(" ", text)
    out = []
    for m in NUMBER.finditer(text):
        whole, frac = m.group(1).replace(",", ""), m.group(2) or ""
        exp = int(m.group("exp") or 0)
        half = 0.5 * 10.0 ** (exp - max(len(frac) - 1, 0))
        out.append((m.group(0).strip(), float(whole + frac) * 10.0**exp, half,
                    bool(m.group("pct"))))  # fmt: skip
    return out


def table_values(path: Path) -> np.ndarray:
    """Every number of a CSV: numeric cells, numbers inside text cells and column names, and
    the times of its provenance sidecar (:data:`SIDECAR_TIMES`)."""
    frame = pd.read_csv(path)
    values: list[float] = []
    for col in frame.columns:
        values += [v for _, v, _, _ in numbers(str(col).replace("_", " "))]
        series = frame[col]
        if pd.api.types.is_numeric_dtype(series):
            values += series.dropna().astype(float).tolist()
        else:
            for cell in series.dropna().astype(str).unique():
                values += [v for _, v, _, _ in numbers(cell.replace("_", " "))]
    side = path.with_name(f"{path.stem}.provenance.json")
    if side.is_file():  # the run's times (a page says how long its figure took)
        prov = json.loads(side.read_text())
        values += [float(prov[k]) for k in SIDECAR_TIMES if isinstance(prov.get(k), int | float)]
    return np.abs(np.asarray(values, dtype=float))


@dataclass(frozen=True)
class TableRow:
    """A CSV row as the doc check reads it."""

    numbers: frozenset[float]  # the numbers inside its text cells (``right_101_110``: 101, 110)
    texts: frozenset[str]  # its text cells, as :func:`label_text` writes them
    values: np.ndarray  # every number of the row


def label_text(text: str) -> str:
    """A label as compared: without markup (``` ` ```, ``*``), trimmed, lower case."""
    return re.sub(r"[`*]", "", text).strip().lower()


def table_rows(path: Path) -> list[TableRow]:
    """Each row of a CSV as a :class:`TableRow`."""
    frame = pd.read_csv(path)
    rows = []
    for record in frame.itertuples(index=False):
        labels: list[float] = []
        values: list[float] = []
        texts = set()
        for cell in record:
            if isinstance(cell, str):
                labels += [v for _, v, _, _ in numbers(cell.replace("_", " "))]
                texts.add(label_text(cell))
            elif pd.notna(cell) and isinstance(cell, int | float | np.number):
                values.append(float(cell))
        values_arr = np.abs(np.asarray(values + labels, dtype=float))
        rows.append(TableRow(frozenset(labels), frozenset(texts), values_arr))
    return rows


@dataclass(frozen=True)
class RowLabel:
    """The first cell of a markdown table row, and the text of its other cells."""

    shown: str  # as written
    numbers: tuple[float, ...]  # its numbers (a numeric label: ``101-110``)
    text: str  # :func:`label_text` of it (a word label: ``sr_td``)
    words: str  # its text without the numbers (``dyna_q (1)``: ``dyna_q``)
    rest: str

    def matches(self, row: TableRow, *, words: bool) -> bool:
        """Does ``row`` carry this label? ``words``: a mixed label (``dyna_q (1)``) is read
        as its words plus its numbers anywhere in the row (``agent`` dyna_q, ``replay_budget``
        1); else as its numbers in the row's text cells (``right_101_110``)."""
        if not self.numbers:
            return self.text in row.texts
        if words and self.words:
            return self.words in row.texts and all(
                np.any(np.isclose(row.values, x)) for x in self.numbers
            )
        return all(x in row.numbers for x in self.numbers)


#: a first cell that names a figure (README's figure rows): a heading, not a row's label
FIGURE_LABEL = re.compile(r"^fig(?:ure)?s?\.?\s*\d", re.I)


def row_label(line: str) -> RowLabel | None:
    """A markdown table row's label; None for other lines, a header's rule, a row with one
    cell, an empty first cell and a first cell that names a figure."""
    text = line.strip()
    if not text.startswith("|") or set(text) <= set("|-: "):
        return None
    cells = text.strip("|").split("|")
    first = cells[0].strip()
    if len(cells) < 2 or not label_text(first) or FIGURE_LABEL.match(label_text(first)):
        return None
    found = tuple(v for _, v, _, _ in numbers(first))
    words = label_text(NUMBER.sub(" ", first)).strip(" ()[],;:-")
    words = re.sub(r"\s+", " ", words)
    return RowLabel(first, found, label_text(first), words, "|".join(cells[1:]))


def held(value: float, half: float, percent: bool, pool: np.ndarray) -> bool:
    """Does a table value, rounded to the doc's last digit (``half`` a unit of it), read
    ``value``?"""
    half = half * (1 + 1e-9) + 1e-15
    if np.any(np.abs(pool - value) <= half):
        return True
    return bool(percent and np.any(np.abs(pool * 100 - value) <= half))


def needs_marker(doc: Path) -> list[int]:
    """1-based first lines of the markdown tables in ``doc`` that no marker covers."""
    lines = doc.read_text().splitlines()
    cov: set[int] = set()
    for c in covered(doc):
        cov.update(range(c.line, c.line + c.text.count("\n") + 1))
    out = []
    for k, line in enumerate(lines):
        if line.startswith("|") and (k == 0 or not lines[k - 1].startswith("|")):
            rows = range(k, k + next((n for n, x in enumerate(lines[k:]) if not x.startswith("|")),
                                     len(lines) - k))  # fmt: skip
            body = [r for r in rows if r >= k + 2]  # below the header and its rule
            if any(r + 1 not in cov for r in body):
                out.append(k + 1)
    return out


def uncovered(doc: Path) -> Iterator[Covered]:
    """The blocks of ``doc`` (lines up to a blank line) that no marker covers, outside fenced
    code, with the line each starts on (``tables`` and ``settings`` empty)."""
    lines = doc.read_text().splitlines()
    cov: set[int] = set()
    for c in covered(doc):
        cov.update(range(c.line, c.line + c.text.count("\n") + 1))
    block: list[str] = []
    start, fenced = 0, False
    for k, line in enumerate([*lines, ""], 1):
        if FENCE.match(line):
            fenced = not fenced
        skip = fenced or FENCE.match(line) or k in cov  # a marker's own line: a comment
        if skip or not line.strip():
            if block:
                yield Covered(doc, start, "\n".join(block), (), ())
            block = []
            continue
        if not block:
            start = k
        block.append(line)


def page_tables(doc: Path) -> list[str]:
    """The summary tables ``doc`` names: its markers' tables and the ``data/NAME.csv`` it
    links, without per-run tables (``*_runs.csv``) that no marker names."""
    text = doc.read_text()
    named = {t for c in covered(doc) for t in c.tables}
    linked = {m.group("name") for m in LINKED.finditer(text)}
    return sorted(named | {t for t in linked if not t.endswith("_runs.csv")})


def is_settings_table(text: str) -> bool:
    """Is ``text`` a markdown table whose header starts ``| setting |``?"""
    first = text.lstrip().splitlines()[0] if text.strip() else ""
    return bool(re.match(r"^\|\s*setting\s*\|", first))


def check(
    docs: Iterable[Path],
    data_dir: Path,
    *,
    all_tables: Iterable[Path] = (),
    pages: Iterable[Path] = (),
    allow: Mapping[str, Mapping[str, str]] | None = None,
) -> list[str]:
    """One message per problem: a number no named table holds, a named table that does not
    exist, a ``none`` marker on a block that is not a settings table, a results table without
    a marker (``all_tables``: docs whose every table needs one), and, on ``pages``, a number in
    text no marker covers that neither the page's tables (:func:`page_tables`) nor the page's
    ``allow`` list (page file name -> {number as written: why it needs no table}) holds."""
    problems = []
    cache: dict[str, np.ndarray] = {}
    rows_cache: dict[str, list[TableRow]] = {}

    def labelled(doc: Path, c: Covered) -> None:
        """The rows of a covered markdown table against the tables' rows of the same label
        (the tables that carry it) and the tables that carry no such label, read whole."""
        for i, line in enumerate(c.text.splitlines()):
            label = row_label(line)
            if label is None:
                continue
            tables = [n for n in c.tables if (data_dir / n).is_file()]  # others: pool_of says
            for name in tables:
                if name not in rows_cache:
                    rows_cache[name] = table_rows(data_dir / name)
            # a mixed label (``dyna_q (1)``) by its words when a table has a row of them
            words = bool(label.numbers and label.words) and any(
                label.words in r.texts for n in tables for r in rows_cache[n]
            )
            same = {n: [r.values for r in rows_cache[n] if label.matches(r, words=words)]
                    for n in tables}  # fmt: skip
            matched = [n for n in tables if same[n]]
            if not matched:
                continue  # no table labels its rows so: read whole (above)
            # a table that does not carry the label (the paper's numbers, a table of scalars)
            # is read whole: its numbers may sit in any labelled row
            pool = np.concatenate([np.abs(np.asarray([*c.settings, *label.numbers], float)),
                                   *(v for n in matched for v in same[n]),
                                   *(cache[n] for n in tables if not same[n])])  # fmt: skip
            for shown, value, half, pct in numbers(label.rest):
                if not held(value, half, pct, pool):
                    problems.append(
                        f"{doc}:{c.line + i}: {shown!r} in the row labelled {label.shown!r} is "
                        f"in no row of {', '.join(matched)} with that label"
                    )

    def pool_of(doc: Path, line: int, tables: Iterable[str]) -> list[np.ndarray]:
        pools = []
        for name in tables:
            path = data_dir / name
            if not path.is_file():
                problems.append(f"{doc}:{line}: marker names {name}, not in {data_dir}")
                continue
            if name not in cache:
                cache[name] = table_values(path)
            pools.append(cache[name])
        return pools

    for doc in docs:
        for c in covered(doc):
            if not c.tables and not c.settings:  # <!-- data: none -->: no results here
                if not is_settings_table(c.text):
                    problems.append(f"{doc}:{c.line}: 'data: none' on a block that is not a "
                                    "settings table (header '| setting | ...')")  # fmt: skip
                continue
            pool = np.concatenate(
                [*pool_of(doc, c.line, c.tables), np.abs(np.asarray(c.settings, float))]
            )
            for shown, value, half, pct in numbers(c.text):
                if not held(value, half, pct, pool):
                    problems.append(
                        f"{doc}:{c.line}: {shown!r} is in no table of {', '.join(c.tables)}"
                    )
            labelled(doc, c)  # and each table row against its label's rows
    for doc in pages:
        allowed = (allow or {}).get(doc.name, {})
        try:
            listed = np.abs(np.asarray([float(k.replace(",", "")) for k in allowed], float))
        except ValueError:
            raise CobelError(
                f"allow list of {doc.name}: keys must be numbers, got {list(allowed)}"
            ) from None
        tables = page_tables(doc)
        if PAPER not in tables and (data_dir / PAPER).is_file():
            tables.append(PAPER)  # the paper's own settings and numbers, for every page
        for c in uncovered(doc):
            pool = np.concatenate([*pool_of(doc, c.line, tables), np.zeros(0)])
            for shown, value, half, pct in numbers(c.text):
                if np.any(np.isclose(listed, value, rtol=1e-9, atol=0)) or held(
                    value, half, pct, pool
                ):
                    continue
                problems.append(
                    f"{doc}:{c.line}: {shown!r} (untagged) is in no table the page names "
                    f"({', '.join(tables) or 'none'}) nor in its allow list"
                )
    for doc in all_tables:
        for line in needs_marker(doc):
            problems.append(f"{doc}:{line}: a table without a <!-- data: ... --> marker")
    return problems
