"""Classical conditioning paradigms: Rescorla-Wagner, Pearce-Hall attention and TD(lambda) over a
serial compound.

Each panel shows a task's test predictions ``V`` (mean over 10 runs, bars: standard error) for
each model; acquisition_extinction shows ``V`` at the end of each phase. The expected patterns
are stated in each task's YAML (conf/task/) and checked in tests/test_conditioning.py:
blocking, overshadowing and conditioned inhibition in both models; second-order conditioning
in TD only (RW makes B an inhibitor); ABA renewal only where contexts enter the prediction
(RW with ``agent.context_cues=true``, TD), not in CS-only RW; latent inhibition in Pearce-Hall
only (pre-exposure lowers the cue's associability; RW learns A and B alike).
"""

from __future__ import annotations

import pandas as pd

from cobelrun.figures.conditioning import plot_predictions, test_predictions
from cobelrun.figures.registry import Figure, FigureData

TASKS = ("acquisition_extinction", "blocking", "overshadowing", "conditioned_inhibition",
         "second_order", "renewal", "latent_inhibition")  # fmt: skip
MODELS = {
    "rescorla_wagner": ["agent=rescorla_wagner"],
    "pearce_hall": ["agent=pearce_hall"],
    "td_conditioning": ["agent=td_conditioning"],
}
RUNS = {f"{task}-{model}": [f"task={task}", *overrides]
        for task in TASKS for model, overrides in MODELS.items()}  # fmt: skip
RUNS["renewal-rescorla_wagner_contexts"] = ["task=renewal", "agent=rescorla_wagner",
                                            "agent.context_cues=true"]  # fmt: skip


def draw(data: FigureData):
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 4, figsize=(15, 6.5), constrained_layout=True)
    tables = []
    axes.flat[-1].set_axis_off()  # 7 tasks in a 2 x 4 grid
    for ax, task in zip(axes.flat, TASKS, strict=False):
        labels = [label for label in RUNS if label.startswith(f"{task}-")]
        # latent inhibition has no test phase: V of the preexposed A and the novel B, mean over
        # the conditioning phase's trials (A lags B where preexposure lowered its learning)
        phase = "conditioning" if task == "latent_inhibition" else "test"
        table = test_predictions({label.removeprefix(f"{task}-"): data.trials(label)
                                  for label in labels}, phase=phase)  # fmt: skip
        title = task.replace("_", " ") + (" (mean V while conditioning)" if phase != "test" else "")
        plot_predictions(table, ax, title)
        tables.append(table.assign(task=task))
    axes.flat[0].legend(frameon=False, fontsize=7)
    axes.flat[TASKS.index("renewal")].legend(frameon=False, fontsize=7)  # its 4th bar: contexts
    fig.suptitle("Conditioning: Rescorla-Wagner, Pearce-Hall and TD(lambda) over a serial compound",
                 fontsize=11)  # fmt: skip
    return fig, pd.concat(tables, ignore_index=True)


FIGURES = [
    Figure(
        name="conditioning",
        title="Conditioning paradigms: RW, Pearce-Hall and TD predictions (blocking, renewal, ...)",
        runs=RUNS,
        quick={"*": ["task.runs=3"]},
        draw=draw,
    ),
]
