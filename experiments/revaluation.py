"""Russek et al. (2017): revaluation score per agent x task, as a bar grid.

Reward (latent learning), transition (detour) and policy revaluation, in the two-stage graph
(top row, ``cobelrun.revaluation``; replay budgets 0/1/10/50 per step) and in Russek et al.'s
gridworld designs (bottom row, ``task.job.maze=grid``; budgets 0/1/10/100/1000): Q-learning,
Dyna-Q and SR-Dyna at each budget, SR-TD, SR-MB and value iteration; 20 runs each. Scores:
graph, the change of the fraction of runs whose greedy first choice is the newly best branch;
grid, the change of the share of greedy paths from the start that reach the new goal (1: all
revalue, 0: none).
"""

from __future__ import annotations

import pandas as pd

from cobelrun.figures.registry import Figure, FigureData
from cobelrun.figures.replay import plot_revaluation

DESIGNS = ("reward", "transition", "policy")
GRID_BUDGETS = "task.job.replay_budgets=[0,1,10,100,1000]"


def draw(data: FigureData):
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(10, 6), constrained_layout=True, sharey=True)
    tables = []
    for row, (maze, suffix) in enumerate((("graph", ""), ("grid", "_grid"))):
        for ax, design in zip(axes[row], DESIGNS, strict=True):
            scores = pd.concat(
                [pd.read_csv(d / "revaluation_scores.csv") for d in data.run_dirs(design + suffix)]
            )
            table = plot_revaluation(scores, design, ax)
            ax.set_title(f"{design} revaluation ({maze})")
            tables.append(table.assign(maze=maze))
        axes[row][0].set_ylabel("revaluation score")
    fig.suptitle("Revaluation (Russek et al. 2017): two-stage graph (top), gridworlds (bottom)")
    table = pd.concat(tables, ignore_index=True).drop(columns=["label"])
    return fig, table


FIGURE = Figure(
    name="revaluation",
    title="Russek et al. 2017: reward/transition/policy revaluation score per agent and replay budget",
    runs={
        **{design: [f"task={design}_revaluation"] for design in DESIGNS},
        **{
            f"{design}_grid": [f"task={design}_revaluation", "task.job.maze=grid", GRID_BUDGETS]
            for design in DESIGNS
        },
    },
    quick={
        "*": ["task.job.runs=3", "task.job.training_trials=100", "task.job.replay_budgets=[0,10]"]
    },
    draw=draw,
)
