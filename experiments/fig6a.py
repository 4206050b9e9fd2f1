"""Fig. 6A: extinction learning in the rendered 3D T-maze with DQN on camera images.

Cumulative response (right-arm choices) and escape latency over 200 trials, mean ± standard error
over the runs; the reward moves from the right to the left arm after trial 100.
The default budget is ``task=tmaze_extinction_3d`` (CPU-sized); the paper's scale (84 x 84
images, 50 runs) is ``task=tmaze_extinction_3d_paper`` (see docs/rendering.md).
"""

from __future__ import annotations

import pandas as pd

from cobelrun.figures.extinction import (
    phase_boundaries,
    plot_cumulative_response,
    plot_escape_latency,
    summarize,
)
from cobelrun.figures.registry import Figure, FigureData


def draw(data: FigureData):
    import matplotlib.pyplot as plt

    trials = data.trials("dqn")
    fig, axes = plt.subplots(1, 2, figsize=(6.8, 2.4), constrained_layout=True)
    plot_cumulative_response(trials, axes[0])
    plot_escape_latency(trials, axes[1])
    n = trials["run"].nunique()
    axes[0].set_title("DQN: cumulative response")
    axes[1].set_title("DQN: escape latency")
    fig.suptitle(f"Fig. 6A: extinction in the 3D T-maze, camera images ({n} runs, mean ± SEM)")
    resp, lat = summarize(trials, "cumulative_response"), summarize(trials, "steps")
    rate = summarize(trials, "response")["mean"].rename("response_rate")
    phase = trials[trials["run"] == trials["run"].min()].set_index("trial")["phase"]
    table = pd.concat(
        [
            phase.rename("phase"),
            rate,
            resp.add_prefix("cumulative_response_"),
            lat.add_prefix("latency_"),
        ],
        axis=1,
    ).reset_index(names="trial")
    table.insert(1, "runs", n)
    table.attrs["phase_boundaries"] = phase_boundaries(trials)
    return fig, table


FIGURE = Figure(
    name="fig6a",
    title="Extinction in the rendered 3D T-maze with DQN on images (cumulative response, latency)",
    runs={"dqn": ["task=tmaze_extinction_3d"]},
    # CI budget: one run, 5 + 5 trials (the images still go through the CNN and SB3)
    quick={
        "*": [
            "task.runs=1",
            "task.protocol.phases.0.trials=5",
            "task.protocol.phases.1.trials=5",
            "task.record.steps=false",
            "task.record.mcap=false",
        ]
    },
    draw=draw,
)
