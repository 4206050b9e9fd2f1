"""Fig. 6B: extinction learning in the gridworld T-maze with tabular Dyna-Q.

Cumulative response (right-arm choices) and escape latency over 200 trials, mean and 95 %
confidence interval over 100 runs; the reward moves from the right to the left arm after trial
100. Black: the original's runs (CoBeL-RL v2.0.0's own Dyna-Q on the same task, 100 runs, run by
``benchmarks/original_fig6b_runs.py``), read from the committed per-run table
``docs/figures/data/fig6b_original_runs.csv`` where the source checkout has it: its mean and
95 % interval of the cumulative responses at trials 100 and 200 and of the latency per block of
trials (the blocks its table holds); the title gives the two-sample comparison of the figure's
runs with the original's (:func:`~cobelrun.figures.data.fig6b_compare_note`: difference of
means with Welch's 95 % interval, probability of superiority).
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


def plot_original(original: pd.DataFrame, axes) -> None:
    """The original's per-run block measures as black points with their 95 % interval (t):
    cumulative responses at trials 100 and 200 (``axes[0]``), latency per block at the block's
    middle (``axes[1]``)."""
    from cobelrun.figures.bands import ci_half_width
    from cobelrun.figures.data import FIG6B_CUMULATIVE_AT, FIG6B_LATENCY_BLOCKS

    label = f"original (CoBeL-RL v2, {len(original)} runs)"
    cum = [original[f"cumulative_{t}"] for t in FIG6B_CUMULATIVE_AT]
    lat = [original[f"latency_{lo}_{hi}"] for lo, hi in FIG6B_LATENCY_BLOCKS]
    for ax, xs, cols in ((axes[0], FIG6B_CUMULATIVE_AT, cum),
                         (axes[1], [(lo + hi) / 2 for lo, hi in FIG6B_LATENCY_BLOCKS], lat)):  # fmt: skip
        means = [c.mean() for c in cols]
        half = [float(ci_half_width(c.std(ddof=1), len(c))) for c in cols]
        ax.errorbar(xs, means, yerr=half, fmt="o", color="k", ms=3, capsize=2, lw=1,
                    label=label, zorder=5)  # fmt: skip
    axes[0].legend(frameon=False, fontsize=6.5, loc="lower right")  # one legend for both panels


def draw(data: FigureData):
    import matplotlib.pyplot as plt

    from cobelrun.figures.data import fig6b_compare_note, fig6b_original_table, fig6b_per_run

    trials = data.trials("dyna_q")
    fig, axes = plt.subplots(1, 2, figsize=(6.8, 2.9), constrained_layout=True)
    plot_cumulative_response(trials, axes[0])
    plot_escape_latency(trials, axes[1])
    n = trials["run"].nunique()
    axes[0].set_title("Dyna-Q: cumulative response")
    axes[1].set_title("Dyna-Q: escape latency")
    title = f"Fig. 6B: extinction in the gridworld T-maze ({n} runs, mean, 95% CI)"
    original = fig6b_original_table()
    if original is not None:
        plot_original(original, axes)
        title += "\n" + fig6b_compare_note(fig6b_per_run(trials), original)
    fig.suptitle(title, fontsize=8 if original is not None else None)
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
