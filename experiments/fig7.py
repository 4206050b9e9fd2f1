"""Fig. 7: latent learning in the Blodgett maze with Dyna-DSR.

B: escape latency of the latent group (100 unrewarded exploration trials, then reward) and the
direct group (reward from the first trial), mean and 25th-75th percentile band over 20 runs
each, aligned on the first rewarded trial (0; exploration trials are negative).
C: the successor representation of the start state (Dyna-DSR's ``sr/output`` for the start
state's observation, mean over actions and runs, recorded by the activity monitor) drawn on the
maze at the end of the exploration phase and at the end of training.
"""

from __future__ import annotations

from cobelrun.figures.latent import draw_fig7, mean_latency_first_rewarded, world_of
from cobelrun.figures.registry import Figure, FigureData


def draw(data: FigureData):
    groups = {"latent": data.trials("latent"), "direct": data.trials("direct")}
    latent_dir = data.run_dirs("latent")[0]
    fig, table = draw_fig7(groups, data.activity("latent"), world_of(latent_dir))
    first10 = {g: mean_latency_first_rewarded(t, 10) for g, t in groups.items()}
    fig.suptitle(
        "Fig. 7: latent learning in the Blodgett maze (Dyna-DSR); mean latency over the first "
        f"10 rewarded trials: latent {first10['latent']:.1f}, direct {first10['direct']:.1f}",
        fontsize=9,
    )
    table.attrs["first10"] = first10
    return fig, table


FIGURE = Figure(
    name="fig7",
    title="Latent learning in the Blodgett maze with Dyna-DSR (latency, SR of the start state)",
    runs={
        "latent": ["task=latent_learning", "protocol=latent"],
        "direct": ["task=latent_learning", "protocol=direct"],
    },
    quick={
        "*": [
            "task.runs=2",
            "task.record.steps=false",
            "agent.replay_batch=16",
            "task.monitors.activity.every=10",
        ],
        "latent": ["task.protocol.phases.0.trials=10", "task.protocol.phases.1.trials=10"],
        "direct": ["task.protocol.phases.0.trials=10"],
    },
    draw=draw,
)
