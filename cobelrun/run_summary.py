"""A run's summary per phase: what ``cobel run`` prints at the end and ``Run.summary()``
returns. Plain arrays over a trials table; no composition, no CLI (so the CLI, the API and the
Hydra app can all use it without importing each other). The end of ``cobel run`` reads the
table with pyarrow (:func:`read_phase_rows`), so a run never imports pandas (~0.3 s)."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["LAST_TRIALS", "phase_rows", "read_phase_rows", "summary"]

#: trials over which the summary's "last" columns are averaged
LAST_TRIALS = 10

#: trials-table column -> summary column
MEASURES = {"reward": "reward", "steps": "latency", "response": "response"}


def _floats(values: Any) -> np.ndarray:
    """A column as float64, missing values (None, pandas NA) as NaN."""
    arr = np.asarray(values)
    if arr.dtype != object:
        return arr.astype(np.float64)
    return np.array([_float(v) for v in arr], np.float64)


def _float(value: Any) -> float:
    if value is None:
        return float("nan")
    try:
        return float(value)
    except (TypeError, ValueError):  # pandas.NA and other missing markers
        return float("nan")


def phase_rows(columns: Mapping[str, Any], last: int = LAST_TRIALS) -> list[dict[str, Any]]:
    """Per phase (in protocol order): runs, trials per run, and the means over every run of
    the phase's last ``last`` trials of reward, latency (``steps``) and ``response``, where
    those columns exist (missing values are skipped, as pandas' ``mean`` does).

    Parameters
    ----------
    columns
        A trials table's columns as arrays: ``phase`` (labels, or a ``(names, codes)``
        pair), ``run``, ``trial`` and any of ``reward``, ``steps``, ``response``.
    last
        How many of each phase's last trials the means cover.

    Returns
    -------
    list of dict
        One row per phase: ``phase``, ``runs``, ``trials`` and ``reward``/``latency``/
        ``response`` (``last`` trials' means) where the table has them.
    """
    phase = columns["phase"]
    if isinstance(phase, tuple):  # (names, codes): the phase of row i is names[codes[i]]
        names, codes = list(phase[0]), np.asarray(phase[1], dtype=np.int64)
    else:
        labels, codes = np.unique(np.asarray(phase).astype(str), return_inverse=True)
        names = labels.tolist()
    if codes.size == 0:
        return []
    run = np.asarray(columns["run"], dtype=np.int64)
    trial = np.asarray(columns["trial"], dtype=np.int64)
    used, first = np.unique(codes, return_index=True)
    # phases in the order of the trial number of their first row
    order = sorted(zip(used.tolist(), first.tolist(), strict=True), key=lambda p: trial[p[1]])
    measures = {col: _floats(columns[col]) for col in MEASURES if col in columns}
    rows = []
    for code, _ in order:
        name = names[code]
        sel = codes == code
        runs, trials = run[sel], trial[sel]
        per_run = np.unique(np.stack([runs, trials], axis=1), axis=0)  # (run, trial) pairs
        _, counts = np.unique(per_run[:, 0], return_counts=True)
        tail = trials >= trials.max() - last + 1
        row: dict[str, Any] = {"phase": str(name), "runs": int(np.unique(runs).size),
                               "trials": int(counts.max())}  # fmt: skip
        for col, values in measures.items():
            kept = values[sel][tail]
            kept = kept[~np.isnan(kept)]
            row[MEASURES[col]] = float(kept.mean()) if kept.size else float("nan")
        rows.append(row)
    return rows


def read_phase_rows(path: str | Path, last: int = LAST_TRIALS) -> list[dict[str, Any]]:
    """:func:`phase_rows` of a ``trials.parquet`` file, streamed: two passes over its row
    groups, so memory stays flat however many runs the table holds (a 20,000-run
    job has 4 million rows), and read with pyarrow without pandas (``pyarrow.parquet.read_table``
    and Arrow's ``to_numpy`` import pandas, ~0.3 s). Assumes one row per (run, trial), as every
    trials table cobel writes has."""
    import pyarrow.parquet as pq

    file = pq.ParquetFile(path, read_dictionary=["phase"])
    present = file.schema_arrow.names
    measures = [c for c in MEASURES if c in present]
    first: dict[str, tuple[int, int]] = {}  # phase -> (file row, trial) of its first row
    top: dict[str, int] = {}  # phase -> its last trial
    per_run: dict[str, np.ndarray] = {}  # phase -> rows (trials) per run
    seen = 0
    for batch in _batches(file, ["phase", "run", "trial"]):
        trial = _column(batch.column("trial")).astype(np.int64)
        run = _column(batch.column("run")).astype(np.int64)
        for name, sel in _phases(batch.column("phase")):
            t = trial[sel]
            if name not in first:
                first[name] = (seen + int(np.flatnonzero(sel)[0]), int(t[0]))
            top[name] = max(top.get(name, int(t.max())), int(t.max()))
            counts = np.bincount(run[sel])
            old = per_run.get(name, np.zeros(0, np.int64))
            size = max(old.size, counts.size)
            per_run[name] = np.pad(old, (0, size - old.size)) + np.pad(
                counts, (0, size - counts.size)
            )
        seen += batch.num_rows
    sums = {name: dict.fromkeys(measures, 0.0) for name in first}
    ns = {name: dict.fromkeys(measures, 0) for name in first}
    if measures:
        for batch in _batches(file, ["phase", "trial", *measures]):
            trial = _column(batch.column("trial")).astype(np.int64)
            values = {c: _floats(_column(batch.column(c))) for c in measures}
            for name, sel in _phases(batch.column("phase")):
                keep = sel & (trial >= top[name] - last + 1)
                for c in measures:
                    v = values[c][keep]
                    v = v[~np.isnan(v)]
                    sums[name][c] += float(v.sum())
                    ns[name][c] += int(v.size)
    rows = []
    # phases in the order of the trial number of their first row (as phase_rows)
    for name in sorted(first, key=lambda n: (first[n][1], first[n][0])):
        row: dict[str, Any] = {"phase": name, "runs": int(np.count_nonzero(per_run[name])),
                               "trials": int(per_run[name].max())}  # fmt: skip
        for c in measures:
            row[MEASURES[c]] = sums[name][c] / ns[name][c] if ns[name][c] else float("nan")
        rows.append(row)
    return rows


def _batches(file: Any, columns: list[str]) -> Iterator[Any]:
    """The record batches of ``columns``, one row group at a time. ``ParquetFile.iter_batches``
    with a dictionary column (``phase``) kept memory it never gave back until the reader was
    done: +40 MB of peak RSS for the 16 million rows of an 80,000-run job, growing with the
    table; a reader per row group stays flat (cobel writes 65,536 rows per group)."""
    for i in range(file.metadata.num_row_groups):
        yield from file.read_row_group(i, columns=columns).to_batches()


def _phases(column: Any) -> list[tuple[str, np.ndarray]]:
    """The phase names of a batch's dictionary-encoded ``phase`` column, each with its row mask
    (a name that stands twice in the dictionary gets one mask)."""
    names = [str(v) for v in column.dictionary.to_pylist()]
    codes = _numbers(column.indices).astype(np.int64)
    out: dict[str, np.ndarray] = {}
    for code in np.unique(codes).tolist():
        sel = codes == code
        out[names[code]] = out[names[code]] | sel if names[code] in out else sel
    return list(out.items())


def _numbers(array: Any) -> np.ndarray:
    """An Arrow array of fixed-width numbers without nulls, read from its data buffer."""
    dtype = np.dtype(array.type.to_pandas_dtype())
    if array.null_count:
        raise ValueError("missing values in a column that must have none")
    return np.frombuffer(array.buffers()[1], dtype=dtype, count=len(array),
                         offset=array.offset * dtype.itemsize)  # fmt: skip


def _column(column: Any) -> np.ndarray:
    """An Arrow column as a numpy array: fixed-width numbers without nulls straight from
    their data buffers (the buffer protocol), anything else through Python values."""
    import pyarrow as pa

    kind = column.type
    if (pa.types.is_integer(kind) or pa.types.is_floating(kind)) and column.null_count == 0:
        parts = [_numbers(c) for c in getattr(column, "chunks", [column])]
        return np.concatenate(parts) if parts else np.empty(0, kind.to_pandas_dtype())
    values = np.empty(len(column), dtype=object)
    values[:] = column.to_pylist()
    return values


def summary(trials: pd.DataFrame, last: int = LAST_TRIALS) -> pd.DataFrame:
    """:func:`phase_rows` of a trials DataFrame, as a DataFrame.

    Parameters
    ----------
    trials
        A ``trials`` table (one run folder).
    last
        How many of each phase's last trials the means cover.

    Returns
    -------
    pandas.DataFrame
        Columns ``phase``, ``runs``, ``trials`` and ``reward``/``latency``/``response``
        (``last`` trials' means) where the table has them.
    """
    import pandas as pd

    if trials.empty:
        return pd.DataFrame(columns=["phase", "runs", "trials"])
    cols = [c for c in ("phase", "run", "trial", *MEASURES) if c in trials]
    return pd.DataFrame(phase_rows({c: trials[c].to_numpy() for c in cols}, last))
