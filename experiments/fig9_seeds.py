"""Fig. 9 over four seeds (0-3) of 100 agents each: the all-seed mean the docs headline.

The same runs as ``fig9`` (``task=two_afc``, ``agent=dqn_paper``), once per seed; the figure
draws the 400 agents' mean training reward per trial (band: standard error), and
``python -m cobelrun.figures.data fig9_seeds`` writes the per-agent block means
(``fig9_seeds_runs.csv``, with the seed) and their means over all 400 agents.
"""

from __future__ import annotations

from cobelrun.figures.choice import epsilon_of, plot_mean_reward
from cobelrun.figures.registry import Figure, FigureData


def draw(data: FigureData):
    import matplotlib.pyplot as plt

    trials = data.trials("dqn")
    trials = trials.assign(run=trials["job"] * (int(trials["run"].max()) + 1) + trials["run"])
    fig, ax = plt.subplots(figsize=(5.2, 3.4), constrained_layout=True)
    table = plot_mean_reward(trials, ax, epsilon=epsilon_of(data.run_dirs("dqn")[0]))
    early = trials[trials["trial"].between(6, 10)]["reward"].mean()
    late = trials[trials["trial"].between(41, 50)]["reward"].mean()
    ax.set_title(f"Fig. 9C, seeds 0-3 ({trials['run'].nunique()} agents): reward over trials "
                 f"6-10 {early:.3f}, 41-50 {late:.3f}", fontsize=9)  # fmt: skip
    return fig, table


FIGURE = Figure(
    name="fig9_seeds",
    title="Fig. 9 over four seeds of 100 agents (the all-seed mean)",
    runs={"dqn": ["task=two_afc", "seed=range(0,4)"]},
    quick={"*": ["task.runs=10", "seed=range(0,2)"]},
    draw=draw,
)
