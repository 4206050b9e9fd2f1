"""A run's summary per phase: what ``cobel run`` prints at the end and ``Run.summary()``
returns. Plain pandas over a trials table; no composition, no CLI (so the CLI, the API and the
Hydra app can all use it without importing each other)."""

from __future__ import annotations

import os
from typing import Any

import pandas as pd

__all__ = ["LAST_TRIALS", "summary", "summary_of_file"]

#: trials over which the summary's "last" columns are averaged
LAST_TRIALS = 10


def summary(trials: pd.DataFrame, last: int = LAST_TRIALS) -> pd.DataFrame:
    """Per phase (in protocol order): runs, trials per run, and the means over every run of
    the phase's last ``last`` trials of reward, latency (``steps``) and ``response``, where
    those columns exist.

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
    if trials.empty:
        return pd.DataFrame(columns=["phase", "runs", "trials"])
    rows = []
    order = trials.drop_duplicates("phase", keep="first").sort_values("trial")["phase"]
    columns = {"reward": "reward", "steps": "latency", "response": "response"}
    for phase in order:
        part = trials[trials["phase"] == phase]
        per_run = part.groupby("run")["trial"].nunique()
        tail_start = part["trial"].max() - last + 1
        tail = part[part["trial"] >= tail_start]
        row: dict[str, Any] = {
            "phase": str(phase),
            "runs": int(part["run"].nunique()),
            "trials": int(per_run.max()),
        }
        for col, name in columns.items():
            if col in tail:
                row[name] = float(tail[col].astype(float).mean())
        rows.append(row)
    return pd.DataFrame(rows)


def summary_of_file(path: str | os.PathLike[str], last: int = LAST_TRIALS) -> pd.DataFrame:
    """:func:`summary` of a ``trials.parquet`` file, read in batches of rows (two passes), so
    memory stays flat however many runs the table holds (a 20,000-run job has 4 million
    rows; loading them whole took ~800 MB)."""
    import numpy as np
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    f = pq.ParquetFile(path)
    names = f.schema_arrow.names
    measures = {c: n for c, n in (("reward", "reward"), ("steps", "latency"),
                                  ("response", "response")) if c in names}  # fmt: skip
    first: dict[str, int] = {}  # phase -> trial of its first row (protocol order)
    top: dict[str, int] = {}  # phase -> last trial
    per_run: dict[str, np.ndarray] = {}  # phase -> rows per run

    def phases(batch: Any) -> list[tuple[str, Any]]:
        col = batch.column("phase")
        return [(str(p), pc.equal(col, p)) for p in pc.unique(col).to_pylist()]

    for batch in f.iter_batches(batch_size=1 << 16, columns=["phase", "run", "trial"]):
        for phase, mask in phases(batch):
            trial = batch.column("trial").filter(mask).to_numpy()
            run = batch.column("run").filter(mask).to_numpy().astype(np.int64)
            first.setdefault(phase, int(trial[0]))
            top[phase] = max(top.get(phase, int(trial.max())), int(trial.max()))
            counts = np.bincount(run, minlength=int(run.max()) + 1)
            old = per_run.get(phase, np.zeros(0, np.int64))
            size = max(old.size, counts.size)
            per_run[phase] = np.pad(old, (0, size - old.size)) + np.pad(
                counts, (0, size - counts.size)
            )
    if not first:
        return pd.DataFrame(columns=["phase", "runs", "trials"])
    sums = {p: dict.fromkeys(measures, 0.0) for p in first}
    ns = {p: dict.fromkeys(measures, 0) for p in first}
    for batch in f.iter_batches(batch_size=1 << 16, columns=["phase", "trial", *measures]):
        for phase, mask in phases(batch):
            tail = pc.greater_equal(batch.column("trial"), top[phase] - last + 1)
            keep = pc.and_(mask, tail)
            for col in measures:
                v = batch.column(col).filter(keep).to_numpy(zero_copy_only=False).astype(float)
                sums[phase][col] += float(np.nansum(v))
                ns[phase][col] += int(np.count_nonzero(~np.isnan(v)))
    rows = []
    for phase in sorted(first, key=first.__getitem__):
        row: dict[str, Any] = {"phase": phase, "runs": int(np.count_nonzero(per_run[phase])),
                               "trials": int(per_run[phase].max())}  # fmt: skip
        for col, name in measures.items():
            row[name] = sums[phase][col] / ns[phase][col] if ns[phase][col] else float("nan")
        rows.append(row)
    return pd.DataFrame(rows)
