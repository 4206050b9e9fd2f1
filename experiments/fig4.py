"""Fig. 4: frame time of online vs offline rendering over image sizes, MFEC and DQN.

One ``task=render_benchmark`` run (its job times every repetition x size x agent x mode; see
:mod:`cobelrun.render.benchmark`); the figure draws its ``frame_times.csv``: one column per
agent; top, frame time (median and IQR over the interleaved repetitions) online, offline and
without rendering over image size (pixels), with the paper's published frame times; bottom,
offline/online with the paper's two ratios (20x80: 0.089, 75x300: 0.71). The CSV holds one row
per agent and size: median and IQR per mode, offline/online and offline/no-render.
"""

from __future__ import annotations

import pandas as pd

from cobelrun.figures.registry import Figure, FigureData
from cobelrun.render.benchmark import load_table, plot_frame_times, ratios, summarize


def draw(data: FigureData):
    import matplotlib.pyplot as plt

    (ref,) = data.runs["frame_times"]
    table = load_table(ref.run_dir)
    agents = list(dict.fromkeys(table["agent"]))
    fig, axes = plt.subplots(2, len(agents), figsize=(3.8 * len(agents), 5.4), squeeze=False,
                             sharex=True, constrained_layout=True)  # fmt: skip
    plot_frame_times(table, axes)
    rat = ratios(table)
    for col, agent in enumerate(agents):
        worst = rat.loc[rat["agent"] == agent, "offline_over_none"].max()
        axes[1, col].set_title(f"offline / no-render: max {worst:.3g}", fontsize="small")
    reps, steps = int(table["rep"].nunique()), int(table["steps"].max())
    clock = str(table["clock"].iloc[0]) if "clock" in table else "wall"
    fig.suptitle(f"Fig. 4: frame time ({clock} time per step), online vs offline rendering "
                 f"({reps} repetitions of {steps} steps per point; median, IQR)",
                 fontsize="medium")  # fmt: skip
    points = summarize(table)
    wide = points.pivot_table(index=["agent", "height", "width", "pixels"], columns="mode",
                              values=["median_ms", "q25_ms", "q75_ms"], sort=False)  # fmt: skip
    wide.columns = [f"{mode}_{stat}" for stat, mode in wide.columns]
    out = wide.reset_index().merge(
        rat[["agent", "height", "width", "offline_over_online", "offline_over_none", "render_ms"]],
        on=["agent", "height", "width"],
    )
    out.insert(4, "reps", reps)
    return fig, pd.DataFrame(out.sort_values(["agent", "pixels"]))


FIGURE = Figure(
    name="fig4",
    title="Online vs offline rendering: frame time over image size (MFEC, DQN), median and IQR",
    runs={"frame_times": ["task=render_benchmark"]},
    quick={
        "*": [
            "task.job.sizes=[[20,80],[32,32]]",
            "task.job.repeats=2",
            "task.job.trials=1",
            "task.job.steps=30",
        ]
    },
    draw=draw,
)
