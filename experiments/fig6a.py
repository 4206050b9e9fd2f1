"""Fig. 6: extinction with DQN on rendered images of the 3D T-maze (A) beside tabular Dyna-Q in
the gridworld T-maze (B), as the paper's Fig. 6 shows them.

Columns: cumulative response, escape latency (mean ± standard error over the runs) and the
right-arm response rate per trial with the first extinction trial at which it falls below 0.5
(marked). The reward moves from the right to the left arm after trial 100. Fig. 6A follows the
original's script: only the rewarded arm end ends a trial, so after the switch the old arm is
a dead end, and a response is a trial that ends on the right arm end. The default budget is
``task=tmaze_extinction_3d`` (CPU-sized: 36 x 36 images, 8 runs); the paper's scale (84 x 84
images, 50 runs) is ``task=tmaze_extinction_3d_paper`` (see docs/rendering.md).
"""

from __future__ import annotations

import pandas as pd

from cobelrun.figures.extinction import (
    first_run,
    plot_cumulative_response,
    plot_escape_latency,
    plot_response_rate,
    summarize,
    trials_to_extinction,
)
from cobelrun.figures.registry import Figure, FigureData

PANELS = (("dqn", "A: DQN, 3D T-maze (images)"), ("dyna_q", "B: Dyna-Q, gridworld T-maze"))


def draw(data: FigureData):
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(9.6, 5.0), constrained_layout=True)
    tables = []
    for row, (label, title) in enumerate(PANELS):
        trials = data.trials(label)
        n = len(trials[["job", "run"]].drop_duplicates())  # a seed sweep: one run per job
        plot_cumulative_response(trials, axes[row, 0])
        plot_escape_latency(trials, axes[row, 1])
        plot_response_rate(trials, axes[row, 2])
        axes[row, 0].set_title(f"{title} ({n} runs)", fontsize=9, loc="left")
        for ax in axes[row]:
            ax.spines[["top", "right"]].set_visible(False)
        resp, lat = summarize(trials, "cumulative_response"), summarize(trials, "steps")
        rate = summarize(trials, "response")["mean"].rename("response_rate")
        phase = first_run(trials).set_index("trial")["phase"]  # seed sweeps: every job has run 0
        table = pd.concat(
            [
                phase.rename("phase"),
                rate,
                resp.add_prefix("cumulative_response_"),
                lat.add_prefix("latency_"),
            ],
            axis=1,
        ).reset_index(names="trial")
        table.insert(0, "agent", label)
        table.insert(2, "runs", n)
        table["trials_to_extinction"] = trials_to_extinction(trials)
        tables.append(table)
    fig.suptitle("Fig. 6: extinction, DQN on camera images (A) vs tabular Dyna-Q (B); "
                 "mean, 95% CI", fontsize=10)  # fmt: skip
    return fig, pd.concat(tables, ignore_index=True)


_NO_RECORD = ["task.record.steps=false", "task.record.mcap=false"]

FIGURES = [
    Figure(
        name="fig6a",
        title="Extinction: DQN on rendered 3D T-maze images beside Dyna-Q in the gridworld (Fig. 6)",
        runs={"dqn": ["task=tmaze_extinction_3d"], "dyna_q": ["task=tmaze_extinction"]},
        # CI budget: one DQN run, 5 + 5 trials (the images still go through the CNN and SB3)
        quick={
            "dqn": [
                "task.runs=1",
                "task.protocol.phases.0.trials=5",
                "task.protocol.phases.1.trials=5",
                *_NO_RECORD,
            ],
            "dyna_q": ["task.runs=5", *_NO_RECORD],
        },
        draw=draw,
    )
]

# The paper's scale: 84 x 84 images, 50 runs, one job per seed (3.7 CPU-hours measured;
# `cobel render-cache task=tmaze_extinction_3d_paper` first, so that the jobs need no renderer;
# `cobel run -m` with the same overrides, on all cores or with hydra/launcher=slurm, runs the same
# jobs in parallel, and `cobel figure fig6a_paper --from SWEEP_DIR` takes them).
FIGURES.append(Figure(
    name="fig6a_paper",
    title="Fig. 6 at the paper's scale: DQN on 84 x 84 images, 50 runs (render cache needed)",
    runs={
        "dqn": ["task=tmaze_extinction_3d_paper", "env.observation.render=offline", "task.runs=1",
                "seed=range(0,50)"],
        "dyna_q": ["task=tmaze_extinction"],
    },
    # --quick: Fig. 6A's CI budget, one seed (a later value of a key wins)
    quick={"dqn": [*FIGURES[0].quick["dqn"], "seed=0"], "dyna_q": FIGURES[0].quick["dyna_q"]},
    draw=draw,
))  # fmt: skip
