"""``cobel replay RUN [--run R] [--trials A:B] [--video out.mp4|.gif]``: watch a run."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

HELP = """Watch a run: the agent moving through the maze or arena, from its recorded steps.

\b
Examples:
  cobel replay RUN_DIR                          # run 0, first trial -> RUN_DIR/replay_run0.gif
  cobel replay RUN_DIR --run 3 --trials 95:100 --video out.mp4
  cobel replay RUN_DIR --greedy --trials 1:3       # the saved agent, 3 greedy episodes
\b
Needs the run's steps (task.record.steps=true) and world.json; videos are encoded by the
ffmpeg inside the imageio-ffmpeg wheel (pip install 'cobelrun[web]').
"""


def register(app: typer.Typer) -> None:
    """Add ``cobel replay`` to ``app``."""

    @app.command("replay", help=HELP)
    def replay_cmd(
        run_dir: Annotated[Path, typer.Argument(help="A run folder.", show_default=False)],
        run: Annotated[int, typer.Option("--run", help="Which run.")] = 0,
        trials: Annotated[
            str | None, typer.Option("--trials", help="Trials A:B (default: the first recorded).")
        ] = None,
        video: Annotated[
            Path | None,
            typer.Option("--video", help="Output .gif or .mp4 (default RUN_DIR/replay_runR.gif)."),
        ] = None,
        fps: Annotated[float, typer.Option("--fps", help="Frames (steps) per second.")] = 10.0,
        greedy: Annotated[
            bool,
            typer.Option(
                "--greedy",
                help="Run the saved agent greedily instead (builds the "
                "env and agent from the folder's config, as cobel rerun does).",
            ),
        ] = False,
    ) -> None:
        from cobelrun.commands.common import fail
        from cobelrun.errors import CobelError
        from cobelrun.figures.learned import parse_trials
        from cobelrun.figures.replay_video import replay_file

        try:
            steps = None
            if greedy:
                first, last = parse_trials(trials)
                episodes = 1 if first is None or last is None else max(1, last - first + 1)
                steps = greedy_steps(run_dir, run, episodes)
            path, n = replay_file(
                run_dir, video, run=run, trials=trials, fps=fps, greedy_steps=steps
            )
        except CobelError as exc:
            fail(str(exc))
        typer.echo(f"{path} ({n} frames)")


def greedy_steps(run_dir: str | Path, run: int, episodes: int = 1) -> Any:
    """Poses of ``episodes`` greedy episodes of run ``run``'s saved agent (argmax of its
    action values, no learning), in the env as the run's config builds it (its first phase), as
    a table of poses (run, trial, step, x, y, heading).

    This builds the env and the agent from the folder's
    ``config.yaml`` (:func:`cobelrun.api.rerun_config`: the same validation and instantiation
    gate as ``cobel rerun``), then loads the saved agent (checked against its schema).
    """
    import numpy as np
    import pandas as pd

    from cobelrun.api import rerun_config
    from cobelrun.envs.base import Posed
    from cobelrun.errors import CobelError
    from cobelrun.runner import build_task, load_saved_agent

    run_dir = Path(run_dir)
    cfg = rerun_config(run_dir)
    task = build_task(cfg)
    if task.job is not None or task.make_agent is None:
        raise CobelError(f"{run_dir}: a custom job ({cfg.task.name}) has no agent to replay")
    env = task.env
    try:
        if not isinstance(env.unwrapped, Posed):
            raise CobelError(f"env {type(env.unwrapped).__name__} has no pose to draw")
        agent = task.make_agent(seed=int(cfg.seed) + run)
        load_saved_agent(agent, str(run_dir), run)
        max_steps = int(cfg.task.protocol.get("max_steps") or 1000)
        rows = []
        for ep in range(episodes):
            obs, _ = env.reset(seed=int(cfg.seed) * 1000 + run * 100 + ep)
            for step in range(max_steps + 1):
                x, y, heading = (float(v) for v in env.unwrapped.agent_pose())
                rows.append((run, ep + 1, step, x, y, heading))
                if step == max_steps:
                    break
                q = np.asarray(agent.predict(np.asarray(obs)[None]))[0]
                obs, _, terminated, truncated, _ = env.step(int(np.argmax(q)))
                if terminated or truncated:
                    x, y, heading = (float(v) for v in env.unwrapped.agent_pose())
                    rows.append((run, ep + 1, step + 1, x, y, heading))  # the arrival
                    break
    finally:
        env.close()
    return pd.DataFrame(rows, columns=["run", "trial", "step", "x", "y", "heading"])
