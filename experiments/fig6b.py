"""Fig. 6B: extinction learning in the gridworld T-maze with tabular Dyna-Q.

Cumulative response (right-arm choices) and escape latency over 200 trials, mean ± standard error
over 100 runs; the reward moves from the right to the left arm after trial 100.
"""

from __future__ import annotations

import pandas as pd

from cobelrun.figures.extinction import (
    first_run,
    phase_boundaries,
    plot_cumulative_response,
    plot_escape_latency,
    summarize,
)
from cobelrun.figures.registry import Figure, FigureData


def draw(data: FigureData):
    import matplotlib.pyplot as plt

    trials = data.trials("dyna_q")
    fig, axes = plt.subplots(1, 2, figsize=(6.8, 2.4), constrained_layout=True)
    plot_cumulative_response(trials, axes[0])
    plot_escape_latency(trials, axes[1])
    n = trials["run"].nunique()
    axes[0].set_title("Dyna-Q: cumulative response")
    axes[1].set_title("Dyna-Q: escape latency")
    fig.suptitle(f"Fig. 6B: extinction in the gridworld T-maze ({n} runs, mean, 95% CI)")
    resp, lat = summarize(trials, "cumulative_response"), summarize(trials, "steps")
    phase = first_run(trials).set_index("trial")["phase"]
    table = pd.concat(
        [
            phase.rename("phase"),
            resp.add_prefix("cumulative_response_"),
            lat.add_prefix("latency_"),
        ],
        axis=1,
    ).reset_index(names="trial")
    table.insert(1, "runs", n)
    table.attrs["phase_boundaries"] = phase_boundaries(trials)
    return fig, table


FIGURE = Figure(
    name="fig6b",
    title="Extinction in the gridworld T-maze with Dyna-Q (cumulative response, escape latency)",
    runs={"dyna_q": ["task=tmaze_extinction"]},
    quick={"*": ["task.runs=5", "task.record.steps=false", "task.record.mcap=false"]},
    draw=draw,
)
