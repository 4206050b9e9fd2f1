"""Fig. 7 per run: the summaries the docs quote, from the runs' own tables.

- :func:`runs_as_jobs`: runs of a one-run-per-job figure (``fig7_paper``) get their job as run.
- :func:`per_run_latency`: per run, the mean escape latency over the first ``n`` rewarded
  trials (the Fig. 7B comparison) and over the last 10.
- :func:`sr_spread`: per run, how far the start state's SR reaches: the SR-weighted mean
  shortest-path distance from the start (in steps) and the SR at the goal relative to the SR
  at the start, at a snapshot trial.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from cobelrun.errors import CobelError
from cobelrun.figures.latent import aligned_latency


def runs_as_jobs(table: pd.DataFrame) -> pd.DataFrame:
    """``run`` := ``job`` (each job of a one-run-per-job figure holds run 0)."""
    if "job" not in table:
        raise CobelError("the table has no job column (not loaded through a figure)")
    return table.assign(run=table["job"].to_numpy())


def per_run_latency(trials: pd.DataFrame, n: int = 10) -> pd.DataFrame:
    """Per run: ``first{n}`` (mean latency over the first ``n`` rewarded trials) and
    ``last10`` (mean over the last 10 trials), with ``seed`` where the table has it."""
    rows = aligned_latency(trials)
    rewarded = rows[rows["aligned_trial"] >= 0]
    first = rewarded[rewarded["aligned_trial"] < n].groupby("run")["steps"].mean()
    last = rewarded.groupby("run", group_keys=False).apply(
        lambda g: g.nlargest(10, "aligned_trial")["steps"].mean(), include_groups=False
    )
    out = pd.DataFrame({f"first{n}": first, "last10": last}).reset_index()
    if "seed" in trials:
        out.insert(1, "seed", out["run"].map(trials.groupby("run")["seed"].first()))
    return out


def sr_spread(activity: pd.DataFrame, world, trial: int, layer: str = "sr/output") -> pd.DataFrame:
    """Per run, at snapshot ``trial``: ``mean_distance`` (SR-weighted mean shortest-path
    distance of the states from the start, in steps; the SR of the start state, mean over
    actions, negative entries clipped to 0) and ``goal_over_start`` (SR at the goal / SR at
    the start)."""
    start = int(world.starts[0])
    goal = int(world.places["goal"])
    dist = world.distances([start]).astype(float)
    reach = dist >= 0
    rows = activity[(activity["layer"] == layer) & (activity["probe"] == start)
                    & (activity["trial"] == trial)]  # fmt: skip
    if rows.empty:
        raise CobelError(f"no {layer} activity of the start state {start} at trial {trial}")
    out = []
    for run, g in rows.groupby("run"):
        sr = g.groupby("unit")["value"].mean().sort_index().to_numpy()
        sr = sr.reshape(-1, world.n_states).mean(axis=0)
        w = np.clip(sr, 0, None) * reach
        out.append({"run": int(run), "trial": int(trial),
                    "mean_distance": float((w * np.where(reach, dist, 0)).sum() / w.sum()),
                    "goal_over_start": float(sr[goal] / sr[start])})  # fmt: skip
    return pd.DataFrame(out)
