"""Morris water maze with Foster, Morris & Dayan (2000)'s place-cell actor-critic.

Four panels from ``task=morris_water_maze`` (8 runs): escape latency and path length per day
(mean and 95% CI over runs; acquisition, then reversal with the platform in the opposite
quadrant); the paths of one agent on day 1 and on the last acquisition day; the probe trial's
quadrant occupancy (60 s, platform removed) against the 25% chance line; and the probe's
occupancy heat map over all runs. The numbers in the CSV are the learning curves and the
quadrant bars.
"""

from __future__ import annotations

import pandas as pd

from cobelrun.figures.registry import Figure, FigureData
from cobelrun.figures.watermaze import (
    daily_summary,
    load_geometry,
    plot_learning_curve,
    plot_occupancy,
    plot_paths,
    plot_quadrants,
    probe_quadrants,
)


def draw(data: FigureData):
    import matplotlib.pyplot as plt

    trials = data.trials("actor_critic")
    steps = data.steps("actor_critic")
    geometry = load_geometry(data.run_dirs("actor_critic")[0])
    summary = daily_summary(trials)
    quads = probe_quadrants(trials)
    fig, axes = plt.subplots(2, 3, figsize=(9.0, 5.6), constrained_layout=True)
    plot_learning_curve(summary, axes[0, 0], "escape_latency_s", "escape latency (s)")
    plot_learning_curve(summary, axes[0, 1], "path_length", "path length (m)")
    last = int(summary.loc[summary["phase"] == "acquisition", "day"].max())
    plot_paths(steps, trials, geometry, axes[0, 2], run=0, days=(1, last))
    axes[0, 2].set_title(f"run 0: day 1 (grey) vs day {last} (black)")
    plot_quadrants(quads, axes[1, 0])
    probe_trials = trials.loc[trials["phase"] == "probe", ["run", "trial"]]
    probe_steps = steps.merge(probe_trials, on=["run", "trial"])
    plot_occupancy(probe_steps, geometry, axes[1, 1])
    axes[1, 1].set_title("probe occupancy (all runs)")
    axes[1, 2].axis("off")
    acq = summary[summary["phase"] == "acquisition"]
    rev = summary[summary["phase"] == "reversal"]
    lines = [
        f"runs: {int(summary['runs'].max())}",
        f"latency day 1: {acq['escape_latency_s_mean'].iloc[0]:.1f} s",
        f"latency day {last}: {acq['escape_latency_s_mean'].iloc[-1]:.1f} s",
        f"probe target quadrant: {quads['fraction_mean'].iloc[0]:.2f} (chance 0.25)",
    ]
    if len(rev):
        lines.append(f"reversal day 1: {rev['escape_latency_s_mean'].iloc[0]:.1f} s")
    axes[1, 2].text(
        0.0, 0.9, "\n".join(lines), va="top", fontsize=8, transform=axes[1, 2].transAxes
    )
    fig.suptitle("Morris water maze: place-cell actor-critic (Foster, Morris & Dayan 2000)")
    table = pd.concat(
        [summary.assign(table="daily"), quads.assign(table="probe")], ignore_index=True
    )
    return fig, table


FIGURE = Figure(
    name="morris",
    title="Morris water maze: latency/path per day, example paths, probe quadrants, occupancy",
    runs={"actor_critic": ["task=morris_water_maze"]},
    quick={
        "*": ["task.runs=2", "task.protocol.phases.0.trials=8", "task.protocol.phases.2.trials=4"]
    },
    draw=draw,
)
