"""``cobel export``: hand a run's data to the tools of neuroscience (``cobel export nwb RUN_DIR``)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

export_app = typer.Typer(
    help="Export a run folder to other formats (NWB).", no_args_is_help=True, add_completion=False
)


@export_app.command("nwb")
def nwb_cmd(
    run_dir: Annotated[
        Path, typer.Argument(help="A run folder written by `cobel run`.", metavar="RUN_DIR")
    ],
    out: Annotated[
        Path | None,
        typer.Option("--out", "-o", help="Output folder (default: RUN_DIR/nwb)."),
    ] = None,
) -> None:
    """Write one NWB file per run: session, subject (the agent), trials, positions and, for deep
    agents with an activity-map monitor, the activity maps and a unit table (pynwb)."""
    from cobelrun.commands.common import fail
    from cobelrun.errors import CobelError
    from cobelrun.io.nwb import export_run_folder

    try:
        files = export_run_folder(run_dir, out)
    except CobelError as exc:
        fail(str(exc))
    for f in files:
        typer.echo(str(f))


def register(app: typer.Typer) -> None:
    """Add ``export`` to the ``cobel`` app."""
    app.add_typer(export_app, name="export")
