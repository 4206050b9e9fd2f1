"""Fig. 9C: two-alternative forced choice with DQN (100 agents x 50 one-step trials).

``task=two_afc`` runs ``agent=dqn_paper``: the original's learning dynamics (keras-rl's DQN as
CoBeL-RL v2 set it up: squared TD error, soft target updates 0.01, Adam 1e-3, a gradient step
from the first step on and one more at every trial end, no gradient clipping).

Mean training reward per trial over agents (band: standard error) with the chance level 0.5.
With training epsilon 0.3 and two actions the expected training reward is capped at
1 - 0.3 / 2 = 0.85, so the figure also draws that ceiling and the greedy probe
(``greedy_correct``: after every trial, the fraction of the four displays on which the greedy
action is correct; measured without learning or environment draws, see
``cobelrun/monitors/probe.py``), which shows what the agents have learnt. Black: the original's
mean per trial (``choice/simulation_choice.py`` of the paper's simulations on CoBeL-RL v2.0.0 with
keras-rl2, run by ``benchmarks/original_fig9_runs.py``; solid reward, dashed greedy), read from
the committed tables ``docs/figures/data/fig9_original_runs*.csv`` where the source checkout has
them, and the title gives the two-sample comparison of the figure's agents with the original's
over trials 6-10 (:func:`~cobelrun.figures.twosample.two_sample`: difference of means with
Welch's 95 % interval, probability of superiority).
"""

from __future__ import annotations

import functools

from cobelrun.figures.choice import epsilon_of, plot_mean_reward
from cobelrun.figures.data import fig9_compare_note, fig9_original_tables
from cobelrun.figures.registry import Figure, FigureData


def draw(data: FigureData, heading: str = "Fig. 9C: two-alternative forced choice (DQN)"):
    import matplotlib.pyplot as plt

    trials = data.trials("dqn")
    eps = epsilon_of(data.run_dirs("dqn")[0])
    fig, ax = plt.subplots(figsize=(5.2, 3.4), constrained_layout=True)
    table = plot_mean_reward(trials, ax, epsilon=eps)
    original = fig9_original_tables()
    if original is not None:
        per_trial = original[1]
        n = int(per_trial["agents"].max())
        ax.plot(per_trial["trial"], per_trial["reward_mean"], color="k", lw=1.2,
                label=f"original (CoBeL-RL v2 + keras-rl2, {n} agents): reward")  # fmt: skip
        ax.plot(per_trial["trial"], per_trial["greedy_mean"], color="k", lw=1.2, ls="--",
                label="original: greedy")  # fmt: skip
    ax.legend(frameon=False, fontsize=6.5, loc="lower right")
    early, late = trials[trials["trial"].between(6, 10)], trials[trials["trial"].between(41, 50)]
    note = f"reward: trials 6-10 {early['reward'].mean():.3f}, 41-50 {late['reward'].mean():.3f}"
    if "greedy_correct" in late:
        note += (f"; greedy: {early['greedy_correct'].mean():.2f}, "
                 f"{late['greedy_correct'].mean():.2f}")  # fmt: skip
    if original is not None:
        note += "\n" + fig9_compare_note(trials, original[0])
    ax.set_title(f"{heading}\n{note}", fontsize=8)
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
