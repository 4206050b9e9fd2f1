"""Revaluation score (see :mod:`cobelrun.revaluation` for the task designs)."""

from __future__ import annotations

import pandas as pd


def revaluation_scores(table: pd.DataFrame) -> pd.DataFrame:
    """Score per design x agent x replay budget.

    ``score = mean(choice_after) - mean(choice_before)``, where a choice is 1 if the greedy
    action at the start is the newly best one (0.5 on a tie). 1: every run revalued; 0: none.

    Parameters
    ----------
    table
        ``revaluation.csv``: ``design, agent, replay_budget, run, choice_before, choice_after``.

    Returns
    -------
    pandas.DataFrame
        ``design, [maze,] agent, replay_budget, runs, before, after, score`` (budget -1 where the agent
        has none).
    """
    df = table.assign(replay_budget=table["replay_budget"].fillna(-1).astype(int))
    keys = ["design", *(["maze"] if "maze" in df else []), "agent", "replay_budget"]
    g = df.groupby(keys, sort=False)
    out = g.agg(runs=("run", "size"), before=("choice_before", "mean"),
                after=("choice_after", "mean")).reset_index()  # fmt: skip
    out["score"] = out["after"] - out["before"]
    return out
