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

``<!-- data: none -->`` marks a table that holds no results (e.g. settings). :func:`check`
returns one message per number no table holds, per marker naming a missing table, and per
results table left without a marker (see :func:`needs_marker`).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from cobelrun.errors import CobelError

CODE = re.compile(r"`[^`]*`")
MARKER = re.compile(r"<!--\s*data:\s*(?P<body>.*?)\s*-->")
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
    """Every number of a CSV: numeric cells, and numbers inside text cells and column names."""
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
    return np.abs(np.asarray(values, dtype=float))


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


def check(docs: Iterable[Path], data_dir: Path, *, all_tables: Iterable[Path] = ()) -> list[str]:
    """One message per problem: a number no named table holds, a named table that does not
    exist, a results table without a marker (``all_tables``: docs whose every table needs
    one)."""
    problems = []
    cache: dict[str, np.ndarray] = {}
    for doc in docs:
        for c in covered(doc):
            if not c.tables and not c.settings:  # <!-- data: none -->: no results here
                continue
            pools = []
            for name in c.tables:
                path = data_dir / name
                if not path.is_file():
                    problems.append(f"{doc}:{c.line}: marker names {name}, not in {data_dir}")
                    continue
                if name not in cache:
                    cache[name] = table_values(path)
                pools.append(cache[name])
            pool = np.concatenate([*pools, np.abs(np.asarray(c.settings, float))])
            for shown, value, half, pct in numbers(c.text):
                if not held(value, half, pct, pool):
                    problems.append(
                        f"{doc}:{c.line}: {shown!r} is in no table of {', '.join(c.tables)}"
                    )
    for doc in all_tables:
        for line in needs_marker(doc):
            problems.append(f"{doc}:{line}: a table without a <!-- data: ... --> marker")
    return problems
