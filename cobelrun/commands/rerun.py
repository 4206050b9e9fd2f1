"""``cobel rerun RUN_DIR [KEY=VALUE ...]``: run a run folder's saved config again."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cobelrun.commands.common import AllowTarget, allow_targets

HELP = """Run a run folder's saved config again into a new folder (same config + seed = same tables).

\b
Examples:
  cobel rerun results/tmaze_extinction/2026-01-01/12-00-00_ab12cd34
  cobel rerun RUN_DIR seed=4 agent.epsilon=0.2       # key=value overrides of the saved config
  cobel rerun RUN_DIR --out results/again
\b
The saved config.yaml is fully composed, so config groups (agent=NAME) cannot change here;
use `cobel run` for that. `cobel run -cd RUN_DIR/.hydra -cn config` also runs it (through Hydra).
"""


def register(app: typer.Typer) -> None:
    """Add ``cobel rerun`` to ``app``."""

    @app.command("rerun", help=HELP)
    def rerun_cmd(
        run_dir: Annotated[
            Path, typer.Argument(help="A run folder (its config.yaml is read).", show_default=False)
        ],
        overrides: Annotated[
            list[str] | None,
            typer.Argument(help="key=value overrides of the saved config.", show_default=False),
        ] = None,
        out: Annotated[
            Path | None,
            typer.Option("--out", "-o", help="The new run folder (default: a new dated folder)."),
        ] = None,
        quiet: Annotated[bool, typer.Option("--quiet", help="No end-of-run summary.")] = False,
        allow_target: AllowTarget = None,
    ) -> None:
        allow_targets(allow_target)
        from cobelrun.api import rerun
        from cobelrun.commands.common import EXIT_INTERRUPTED, fail
        from cobelrun.errors import CobelError
        from cobelrun.progress import progress_enabled

        try:
            result = rerun(run_dir, overrides or [], out, progress=progress_enabled())
        except CobelError as exc:
            fail(str(exc))
        except KeyboardInterrupt:
            fail("interrupted", EXIT_INTERRUPTED)
        if not quiet:
            from cobelrun.commands.summary import print_run_summary

            print_run_summary(result.path)
        typer.echo(str(result.path))
