"""The places a trial visited, from a ``steps`` table.

Each step row holds the pose the action was taken in (``x, y, heading``) and, since the steps
table got them, the pose it led to (``next_x, next_y, next_heading``). A trial's path is
its rows' poses followed by its last row's ``next_*``: the arrival (the goal cell of a trial
that reached it). :func:`visited_poses` builds that table; run folders written before the
``next_*`` columns existed give the poses before each step only, and say so.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

__all__ = ["ARRIVAL_COLUMNS", "has_arrivals", "visited_poses"]

#: the columns of the pose after each step
ARRIVAL_COLUMNS = ("next_x", "next_y", "next_heading")


def has_arrivals(steps: pd.DataFrame) -> bool:
    """Whether ``steps`` records the pose after each step (run folders from before the
    ``next_*`` columns do not)."""
    return {"next_x", "next_y"} <= set(steps.columns)


def visited_poses(steps: pd.DataFrame) -> pd.DataFrame:
    """Every pose of every trial in time order: each step's pose, then the trial's arrival.

    Parameters
    ----------
    steps
        A ``steps`` table (``run, trial, step, x, y`` and, where recorded, ``heading`` and
        ``next_x, next_y, next_heading``); extra columns (``job``, swept keys) are kept as
        grouping columns when they are constant within a trial.

    Returns
    -------
    pandas.DataFrame
        Columns ``run, trial, step, x, y, heading`` (and ``job`` where ``steps`` has it),
        sorted by run, trial and step. Where the arrivals are recorded each trial gets one
        row more than it has steps, ``step = last step + 1`` at its last row's ``next_*``
        pose. ``df.attrs["arrivals"]`` says whether they were (False for older run folders:
        the rows are the poses before each step only, so the cell each trial ended in is
        missing).
    """
    keys = [c for c in ("job", "run", "trial") if c in steps.columns]
    cols = [*keys, "step", "x", "y"]
    heading = "heading" in steps.columns
    base = steps[cols + (["heading"] if heading else [])].copy()
    if not heading:
        base["heading"] = np.nan
    arrivals = has_arrivals(steps)
    if arrivals and len(steps):
        order = steps.sort_values([*keys, "step"], kind="stable")
        last = order.groupby(keys, sort=False).tail(1)
        tail = last[[*keys, "step"]].copy()
        tail["step"] = tail["step"].to_numpy() + 1
        tail["x"] = last["next_x"].to_numpy(np.float64)
        tail["y"] = last["next_y"].to_numpy(np.float64)
        tail["heading"] = (
            last["next_heading"].to_numpy(np.float64) if "next_heading" in last else np.nan
        )
        base = pd.concat([base, tail], ignore_index=True)
    out = base.sort_values([*keys, "step"], kind="stable").reset_index(drop=True)
    out["heading"] = out["heading"].astype(np.float64)
    out.attrs["arrivals"] = arrivals
    return out
