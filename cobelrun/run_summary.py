"""A run's summary per phase: what ``cobel run`` prints at the end and ``Run.summary()``
returns. Plain arrays over a trials table; no composition, no CLI (so the CLI, the API and the
Hydra app can all use it without importing each other). The end of ``cobel run`` reads the
table with pyarrow (:func:`read_phase_rows`), so a run never imports pandas (~0.3 s)."""

from __future__ import annotations

from collections.abc import Mapping
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
    """:func:`phase_rows` of a ``trials.parquet`` file, read with pyarrow without pandas
    (``pyarrow.parquet.read_table`` and Arrow's ``to_numpy`` import pandas, ~0.3 s)."""
    import pyarrow.parquet as pq

    file = pq.ParquetFile(path, read_dictionary=["phase"])
    wanted = [c for c in ("phase", "run", "trial", *MEASURES) if c in file.schema_arrow.names]
    table = file.read(columns=wanted)
    columns: dict[str, Any] = {c: _column(table.column(c)) for c in wanted if c != "phase"}
    if "phase" in wanted:  # as (names, codes): no Python string per row
        names: list[str] = []
        codes = []
        for chunk in table.column("phase").chunks:  # codes point into the chunk's dictionary
            base = len(names)
            names += [str(v) for v in chunk.dictionary.to_pylist()]
            codes.append(_numbers(chunk.indices).astype(np.int64) + base)
        # a name in several chunks' dictionaries: one code for it
        first = {}
        for i, n in enumerate(names):
            first.setdefault(n, i)
        remap = np.array([first[n] for n in names], dtype=np.int64)
        all_codes = np.concatenate(codes) if codes else np.empty(0, np.int64)
        columns["phase"] = (names, remap[all_codes] if remap.size else all_codes)
    return phase_rows(columns, last)


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
        parts = [_numbers(c) for c in column.chunks]
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
