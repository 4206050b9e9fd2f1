"""Fig. 7 at the paper's budget, in resumable pieces: one job per run.

The same runs as ``fig7`` (20 latent + 20 direct, 100 + 100 / 100 trials of at most 200 steps,
100 replays per step), but each run is its own job (``task.runs=1``, seeds 0-19 per group), so
a build that is stopped keeps every finished run and ``cobel figure fig7_paper`` runs only the
ones still missing. Runs of one group differ by seed (not by run index inside one job), which is
the only difference from ``fig7``'s single 20-run job per group.

Besides the figure's table (``fig7_paper.csv``: 7B and 7C as in ``fig7``) the per-run summary
that the docs quote is :func:`cobelrun.figures.latent_stats.per_run_latency`.
"""

from __future__ import annotations

from cobelrun.figures.latent import draw_fig7, mean_latency_first_rewarded, world_of
from cobelrun.figures.latent_stats import runs_as_jobs
from cobelrun.figures.registry import Figure, FigureData

SEEDS = "range(0,20)"


def draw(data: FigureData):
    groups = {g: runs_as_jobs(data.trials(g)) for g in ("latent", "direct")}
    activity = runs_as_jobs(data.activity("latent"))
    fig, table = draw_fig7(groups, activity, world_of(data.run_dirs("latent")[0]))
    first10 = {g: mean_latency_first_rewarded(t, 10) for g, t in groups.items()}
    fig.suptitle(
        "Fig. 7 at the paper's budget (one job per run); mean latency over the first 10 "
        f"rewarded trials: latent {first10['latent']:.1f}, direct {first10['direct']:.1f}",
        fontsize=9,
    )
    return fig, table


FIGURE = Figure(
    name="fig7_paper",
    title="Fig. 7 at the paper's budget, one job per run (resumable): 20 latent + 20 direct",
    runs={
        "latent": [
            "task=latent_learning",
            "protocol=latent",
            "task.runs=1",
            f"seed={SEEDS}",
            "task.record.steps=false",
        ],
        "direct": [
            "task=latent_learning",
            "protocol=direct",
            "task.runs=1",
            f"seed={SEEDS}",
            "task.record.steps=false",
        ],
    },
    quick={
        "*": ["seed=range(0,2)", "agent.replay_batch=16", "task.monitors.activity.every=10"],
        "latent": ["task.protocol.phases.0.trials=10", "task.protocol.phases.1.trials=10"],
        "direct": ["task.protocol.phases.0.trials=10"],
    },
    draw=draw,
)
