"""Fig. 4: mean frame time of online vs offline rendering over image sizes, MFEC and DQN.

One ``task=render_benchmark`` run (its job times every size x agent x mode; see
:mod:`cobelrun.render.benchmark`); the figure draws its ``frame_times.csv``: one panel per agent,
frame time (log scale) over image size, online vs offline, with the offline/online ratio of the
smallest and largest size in the title. The CSV holds every measurement plus the ratios.
"""

from __future__ import annotations

import pandas as pd

from cobelrun.figures.registry import Figure, FigureData
from cobelrun.render.benchmark import load_table, plot_frame_times, ratios


def draw(data: FigureData):
    import matplotlib.pyplot as plt

    (ref,) = data.runs["frame_times"]
    table = load_table(ref.run_dir)
    rat = ratios(table)
    agents = list(dict.fromkeys(table["agent"]))
    fig, axes = plt.subplots(1, len(agents), figsize=(3.3 * len(agents), 2.6),
                             squeeze=False, constrained_layout=True)  # fmt: skip
    plot_frame_times(table, list(axes[0]))
    for ax, agent in zip(axes[0], agents, strict=True):
        r = rat[rat["agent"] == agent].sort_values("height")
        if len(r):
            ends = r.iloc[[0, -1]] if len(r) > 1 else r
            text = ", ".join(f"{h}x{w}: {q:.2g}" for h, w, q in
                             zip(ends["height"], ends["width"], ends["offline_over_online"], strict=True))  # fmt: skip
            ax.set_title(f"{agent.upper()} (offline/online {text})", fontsize="small")
    steps = int(table["steps"].max())
    fig.suptitle(f"Fig. 4: frame time, online vs offline rendering ({steps} steps per point)")
    out = table.merge(rat[["agent", "height", "width", "offline_over_online"]],
                      on=["agent", "height", "width"], how="left")  # fmt: skip
    return fig, pd.DataFrame(out)


FIGURE = Figure(
    name="fig4",
    title="Online vs offline rendering: frame time over image size (MFEC, DQN)",
    runs={"frame_times": ["task=render_benchmark"]},
    quick={"*": ["task.job.sizes=[[20,80],[30,120]]", "task.job.trials=1", "task.job.steps=30"]},
    draw=draw,
)
