"""Russek et al. (2017): revaluation score per agent x task, as a bar grid.

Reward (latent learning), transition (detour) and policy revaluation in the two-stage graph
(``cobelrun.revaluation``); Q-learning, Dyna-Q and SR-Dyna at replay budgets 0/1/10/50 per step,
SR-TD, SR-MB and value iteration; 20 runs each. Score: change of the fraction of runs whose
greedy first choice is the newly best branch (1: all revalue, 0: none).
"""

from __future__ import annotations

import pandas as pd

from cobelrun.figures.registry import Figure, FigureData
from cobelrun.figures.replay import plot_revaluation

DESIGNS = ("reward", "transition", "policy")


def draw(data: FigureData):
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(10, 2.8), constrained_layout=True, sharey=True)
    tables = []
    for ax, design in zip(axes, DESIGNS, strict=True):
        scores = pd.concat(
            [pd.read_csv(d / "revaluation_scores.csv") for d in data.run_dirs(design)]
        )
        tables.append(plot_revaluation(scores, design, ax))
    axes[0].set_ylabel("revaluation score")
    fig.suptitle("Revaluation (Russek et al. 2017) in the two-stage graph")
    table = pd.concat(tables, ignore_index=True).drop(columns=["label"])
    return fig, table


FIGURE = Figure(
    name="revaluation",
    title="Russek et al. 2017: reward/transition/policy revaluation score per agent and replay budget",
    runs={design: [f"task={design}_revaluation"] for design in DESIGNS},
    quick={
        "*": ["task.job.runs=3", "task.job.training_trials=100", "task.job.replay_budgets=[0,10]"]
    },
    draw=draw,
)
