"""Fig. 9C: two-alternative forced choice with DQN (100 agents x 50 one-step trials).

``task=two_afc`` runs ``agent=dqn_paper``: the original's learning dynamics (keras-rl's DQN as
CoBeL-RL v2 set it up: squared TD error, soft target updates 0.01, Adam 1e-3, a gradient step
from the first step on and one more at every trial end, no gradient clipping).

Mean training reward per trial over agents (band: standard error) with the chance level 0.5.
With training epsilon 0.3 and two actions the expected training reward is capped at
1 - 0.3 / 2 = 0.85, so the figure also draws that ceiling and the greedy probe
(``greedy_correct``: after every trial, the fraction of the four displays on which the greedy
action is correct; measured without learning or environment draws, see
``cobelrun/monitors/probe.py``), which shows what the agents have learnt. Black bars: the
original's means over trials 6-10 and 41-50 (``choice/simulation_choice.py`` of the paper's
simulations on CoBeL-RL v2.0.0 with keras-rl2, 200 agents, run here; docs/two_afc.md).
"""

from __future__ import annotations

import functools

from cobelrun.figures.choice import epsilon_of, plot_mean_reward
from cobelrun.figures.registry import Figure, FigureData

#: the original's means (trials, training reward, greedy choice correct), 200 agents
ORIGINAL = (((6, 10), 0.616, 0.699), ((41, 50), 0.839, 0.961))


def draw(data: FigureData, heading: str = "Fig. 9C: two-alternative forced choice (DQN)"):
    import matplotlib.pyplot as plt

    trials = data.trials("dqn")
    eps = epsilon_of(data.run_dirs("dqn")[0])
    fig, ax = plt.subplots(figsize=(5.2, 3.4), constrained_layout=True)
    table = plot_mean_reward(trials, ax, epsilon=eps)
    for k, ((lo, hi), reward, greedy) in enumerate(ORIGINAL):
        for value, ls in ((reward, "-"), (greedy, "--")):
            ax.hlines(value, lo - 0.4, hi + 0.4, color="k", lw=2.2, ls=ls,
                      label=("original (CoBeL-RL v2, 200 agents): reward" if ls == "-" else
                             "original: greedy") if k == 0 else None)  # fmt: skip
    ax.legend(frameon=False, fontsize=6.5, loc="lower right")
    early, late = trials[trials["trial"].between(6, 10)], trials[trials["trial"].between(41, 50)]
    note = f"reward: trials 6-10 {early['reward'].mean():.3f}, 41-50 {late['reward'].mean():.3f}"
    if "greedy_correct" in late:
        note += (f"; greedy: {early['greedy_correct'].mean():.2f}, "
                 f"{late['greedy_correct'].mean():.2f}")  # fmt: skip
    ax.set_title(f"{heading}\n{note}", fontsize=9)
    ax.spines[["top", "right"]].set_visible(False)
    return fig, table


FIGURES = [
    Figure(
        name="fig9",
        title="Two-alternative forced choice with DQN (mean reward per trial, greedy probe)",
        runs={"dqn": ["task=two_afc"]},
        quick={"*": ["task.runs=10"]},
        draw=draw,
    ),
    # the paper's "learn the task within a couple of trials": task=two_afc_fast (Q starting at
    # 0.5, 4 gradient steps per step; docs/two_afc.md), beside the original's means
    Figure(
        name="fig9_fast",
        title="Fig. 9 learning in a couple of trials (two_afc_fast: Q from 0.5, 4 updates/step)",
        runs={"dqn": ["task=two_afc_fast"]},
        quick={"*": ["task.runs=10"]},
        draw=functools.partial(
            draw, heading="Fig. 9C, two_afc_fast: Q starts at 0.5, 4 gradient steps per step"
        ),
    ),
]
