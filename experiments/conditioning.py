"""Classical conditioning paradigms: Rescorla-Wagner against TD(lambda) over a serial compound.

Each panel shows a task's test predictions ``V`` (mean over 10 runs, bars: standard error) for
each model; acquisition_extinction shows ``V`` at the end of each phase. The expected patterns
are stated in each task's YAML (conf/task/) and checked in tests/test_conditioning.py:
blocking, overshadowing and conditioned inhibition in both models; second-order conditioning
in TD only (RW makes B an inhibitor); ABA renewal only where contexts enter the prediction
(RW with ``agent.context_cues=true``, TD), not in CS-only RW.
"""

from __future__ import annotations

import pandas as pd

from cobelrun.figures.conditioning import plot_predictions, test_predictions
from cobelrun.figures.registry import Figure, FigureData

TASKS = ("acquisition_extinction", "blocking", "overshadowing", "conditioned_inhibition",
         "second_order", "renewal")  # fmt: skip
MODELS = {
    "rescorla_wagner": ["agent=rescorla_wagner"],
    "td_conditioning": ["agent=td_conditioning"],
}
RUNS = {f"{task}-{model}": [f"task={task}", *overrides]
        for task in TASKS for model, overrides in MODELS.items()}  # fmt: skip
RUNS["renewal-rescorla_wagner_contexts"] = ["task=renewal", "agent=rescorla_wagner",
                                            "agent.context_cues=true"]  # fmt: skip


def draw(data: FigureData):
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(12, 6.5), constrained_layout=True)
    tables = []
    for ax, task in zip(axes.flat, TASKS, strict=True):
        labels = [label for label in RUNS if label.startswith(f"{task}-")]
        table = test_predictions({label.removeprefix(f"{task}-"): data.trials(label)
                                  for label in labels})  # fmt: skip
        plot_predictions(table, ax, task.replace("_", " "))
        tables.append(table.assign(task=task))
    axes.flat[0].legend(frameon=False, fontsize=7)
    axes.flat[-1].legend(frameon=False, fontsize=7)
    fig.suptitle("Conditioning: Rescorla-Wagner vs TD(lambda) over a serial compound", fontsize=11)
    return fig, pd.concat(tables, ignore_index=True)


FIGURES = [
    Figure(
        name="conditioning",
        title="Conditioning paradigms: RW vs TD predictions (blocking, renewal, second order, ...)",
        runs=RUNS,
        quick={"*": ["task.runs=3"]},
        draw=draw,
    ),
]
