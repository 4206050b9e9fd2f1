"""Fig. 4: frame time of online vs offline rendering over image sizes, MFEC and DQN.

Two ``task=render_benchmark`` runs, one per agent (its job times every repetition x size x mode;
see :mod:`cobelrun.render.benchmark`), so each agent gets its own step budget: an MFEC frame
costs 0.05-26 ms, a DQN frame (a gradient step on 32 images) 9-370 ms (the 2026-11-28 measurement,
docs/figures/data/fig4.csv), so MFEC is timed over 200 steps per repetition and DQN over 50. The figure draws their ``frame_times.csv``: one column
per agent; top, frame time (median and IQR over the interleaved repetitions) online, offline and
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

    table = pd.concat([load_table(ref.run_dir) for refs in data.runs.values() for ref in refs],
                      ignore_index=True)  # fmt: skip
    agents = list(dict.fromkeys(table["agent"]))
    fig, axes = plt.subplots(2, len(agents), figsize=(3.8 * len(agents), 5.4), squeeze=False,
                             sharex=True, constrained_layout=True)  # fmt: skip
    plot_frame_times(table, axes)
    rat = ratios(table)
    for col, agent in enumerate(agents):
        worst = rat.loc[rat["agent"] == agent, "offline_over_none"].max()
        axes[1, col].set_title(f"offline / no-render: max {worst:.3g}", fontsize="small")
    reps = int(table["rep"].nunique())
    budget = ", ".join(f"{str(a).upper()} {int(g['steps'].max())}"
                       for a, g in table.groupby("agent", sort=False))  # fmt: skip
    clock = str(table["clock"].iloc[0]) if "clock" in table else "wall"
    fig.suptitle(f"Fig. 4: frame time ({clock} time per step), online vs offline rendering\n"
                 f"({reps} interleaved repetitions per point, steps per repetition: {budget}; "
                 f"median, IQR)", fontsize="medium")  # fmt: skip
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
    runs={
        "mfec": ["task=render_benchmark", "task.job.agents.dqn=null"],
        "dqn": ["task=render_benchmark", "task.job.agents.mfec=null", "task.job.steps=50"],
    },
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
