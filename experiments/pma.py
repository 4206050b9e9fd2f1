"""Mattar & Daw (2018) in Sutton's Dyna maze: prioritized replay (PMA) vs no replay vs random replay.

Steps per trial (median and interquartile range over runs) for PMA, Q-learning without replay and
Dyna-Q with random replay of the same budget (40 backups per trial, at trial end); forward and
reverse replay events (>= 5 experiences) per trial at trial start vs trial end; one start and
one end replay bout of PMA drawn on the maze.
"""

from __future__ import annotations

import pandas as pd

from cobelrun.analysis.replay import replay_events
from cobelrun.figures.registry import Figure, FigureData
from cobelrun.figures.replay import plot_direction, plot_replay_on_maze, plot_steps_per_trial

SHORTEST = 14


def draw(data: FigureData):
    import matplotlib.pyplot as plt

    from cobelrun.config import instantiate
    from cobelrun.results import load_table

    fig, axes = plt.subplots(1, 4, figsize=(10, 2.4), constrained_layout=True)
    columns = {}
    for label, color in (("pma", "tab:red"), ("dyna_q", "tab:blue"), ("q_learning", "0.4")):
        trials = data.trials(label)
        columns[f"{label}_median_steps"] = plot_steps_per_trial(trials, axes[0], label, color)
    axes[0].axhline(SHORTEST, color="k", ls=":", lw=0.8)
    axes[0].legend()
    axes[0].set_title("steps per trial")
    run_dirs = data.run_dirs("pma")
    replays = pd.concat([load_table(d, "replays") for d in run_dirs])
    trials = pd.concat([load_table(d, "trials") for d in run_dirs])
    events = replay_events(replays)
    rate = plot_direction(events, len(trials), axes[1])
    axes[1].set_title("PMA replay direction")
    from omegaconf import OmegaConf

    env = instantiate("env", OmegaConf.load(run_dirs[0] / "config.yaml").env)
    world = env.unwrapped.world
    for ax, when in ((axes[2], "start"), (axes[3], "end")):
        # the longest event of this kind in the first run, drawn with its bout's rows
        first = events[(events["run"] == events["run"].min()) & (events["when"] == when)]
        if not first.empty:
            ev = first.loc[first["length"].idxmax()]
            bout = replays[(replays["run"] == ev["run"]) & (replays["trial"] == ev["trial"])
                           & (replays["when"] == when)].sort_values("index")  # fmt: skip
            plot_replay_on_maze(world, bout.iloc[ev["first"] : ev["first"] + ev["length"]], ax)
            ax.set_title(f"PMA {ev['direction']} replay, trial {when} ({ev['trial']})")
    fig.suptitle(f"Prioritized replay in the Dyna maze ({trials['run'].nunique()} runs)")
    table = pd.DataFrame(columns).reset_index(names="trial")
    for when in ("start", "end"):
        for direction in ("forward", "reverse"):
            table[f"{direction}_per_trial_{when}"] = rate.loc[when, direction]
    return fig, table


FIGURE = Figure(
    name="pma",
    title="Mattar & Daw: PMA vs no replay vs random replay in the Dyna maze; replay direction",
    runs={
        "pma": ["task=dyna_maze"],
        "q_learning": ["task=dyna_maze", "agent=q_learning"],
        "dyna_q": [
            "task=dyna_maze",
            "agent=dyna_q",
            "agent.replay=trial_end",
            "agent.replay_batch=40",
            "agent.memory_sampling=visited",
        ],
    },
    quick={"*": ["task.runs=3", "task.protocol.phases.0.trials=8", "task.record.mcap=false"]},
    draw=draw,
)
