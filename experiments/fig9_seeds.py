"""Fig. 9 over several seeds of 100 agents each: the all-seed means the docs headline.

``fig9_seeds``: the same runs as ``fig9`` (``task=two_afc``, ``agent=dqn_paper``), once per seed
0-3; ``fig9_fast_seeds``: ``fig9_fast``'s (``task=two_afc_fast``) over seeds 0-4. Each figure
draws its agents' mean training reward per trial (band: standard error), and ``python -m
cobelrun.figures.data NAME`` writes the per-agent block means (``NAME_runs.csv``, with the seed)
and their means (``fig9_seeds``: over all agents; ``fig9_fast_seeds``: per seed).
"""

from __future__ import annotations

import functools

from cobelrun.figures.choice import epsilon_of, plot_mean_reward
from cobelrun.figures.data import fig9_compare_note, fig9_original_tables
from cobelrun.figures.registry import Figure, FigureData


def draw(data: FigureData, task: str = "Fig. 9C"):
    import matplotlib.pyplot as plt

    trials = data.trials("dqn")
    trials = trials.assign(run=trials["job"] * (int(trials["run"].max()) + 1) + trials["run"])
    fig, ax = plt.subplots(figsize=(5.2, 3.4), constrained_layout=True)
    table = plot_mean_reward(trials, ax, epsilon=epsilon_of(data.run_dirs("dqn")[0]))
    early = trials[trials["trial"].between(6, 10)]["reward"].mean()
    late = trials[trials["trial"].between(41, 50)]["reward"].mean()
    seeds = sorted({ref.params.get("seed", 0) for ref in data.runs["dqn"]})
    title = (f"{task}, seeds {seeds[0]}-{seeds[-1]} ({trials['run'].nunique()} agents): reward "
             f"over trials 6-10 {early:.3f}, 41-50 {late:.3f}")  # fmt: skip
    original = fig9_original_tables()
    if original is not None and task == "Fig. 9C":  # the original's dynamics: compare
        per_trial = original[1]
        ax.plot(per_trial["trial"], per_trial["reward_mean"], color="k", lw=1.2,
                label=f"original ({int(per_trial['agents'].max())} agents): reward")  # fmt: skip
        ax.legend(frameon=False, fontsize=6.5, loc="lower right")
        title += "\n" + fig9_compare_note(trials, original[0])
    ax.set_title(title, fontsize=8)
    return fig, table


FIGURES = [
    Figure(
        name="fig9_seeds",
        title="Fig. 9 over four seeds of 100 agents (the all-seed mean)",
        runs={"dqn": ["task=two_afc", "seed=range(0,4)"]},
        quick={"*": ["task.runs=10", "seed=range(0,2)"]},
        draw=draw,
    ),
    Figure(
        name="fig9_fast_seeds",
        title="Fig. 9 two_afc_fast over five seeds of 100 agents (the per-seed means)",
        runs={"dqn": ["task=two_afc_fast", "seed=range(0,5)"]},
        quick={"*": ["task.runs=10", "seed=range(0,2)"]},
        draw=functools.partial(draw, task="Fig. 9C two_afc_fast"),
    ),
]
