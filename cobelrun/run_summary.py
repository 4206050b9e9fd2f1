"""A run's summary per phase: what ``cobel run`` prints at the end and ``Run.summary()``
returns. Plain pandas over a trials table; no composition, no CLI (so the CLI, the API and the
Hydra app can all use it without importing each other)."""

from __future__ import annotations

from typing import Any

import pandas as pd

__all__ = ["LAST_TRIALS", "summary"]

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
