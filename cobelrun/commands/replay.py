"""``cobel replay RUN [--run R] [--trials A:B] [--video out.mp4|.gif]``: watch a run."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

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
        from cobelrun.figures.replay_video import replay_file

        try:
            path, n = replay_file(run_dir, video, run=run, trials=trials, fps=fps, greedy=greedy)
        except CobelError as exc:
            fail(str(exc))
        typer.echo(f"{path} ({n} frames)")
