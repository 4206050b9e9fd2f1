"""What every ``cobel`` command shares: exit codes and the one-line error exit.

Kept apart from :mod:`cobelrun.cli` so that command modules (``commands/*.py``) can use it
without importing the app that registers them (no import cycle).
"""

from __future__ import annotations

import os
import sys
from typing import Annotated, NoReturn

import typer

#: rich styles of job statuses in status tables
STATUS_STYLE = {
    "done": "green",
    "failed": "bold red",
    "interrupted": "yellow",
    "running": "cyan",
    "queued": "cyan",
    "missing": "dim",
}

#: help of ``--allow-target`` (the user's own classes a config may build)
ALLOW_TARGET_HELP = (
    "Allow configs to build this class or function (a dotted path, or a package with .*, "
    "e.g. mypkg.envs.*); repeatable. Also: COBEL_ALLOW_TARGETS."
)

#: ``--allow-target``: the user's own classes a config may build (see docs/reliability.md)
AllowTarget = Annotated[
    list[str] | None,
    typer.Option("--allow-target", help=ALLOW_TARGET_HELP, metavar="PATTERN", show_default=False),
]

#: exit code of a user error (bad config, name or folder)
EXIT_USER_ERROR = 2
#: exit code of a run stopped by Ctrl-C or SIGTERM
EXIT_INTERRUPTED = 130


def debug_enabled() -> bool:
    """``--debug`` (``COBEL_DEBUG=1``) or ``HYDRA_FULL_ERROR=1``: show tracebacks."""
    return os.environ.get("HYDRA_FULL_ERROR") == "1" or os.environ.get("COBEL_DEBUG") == "1"


def fail(message: str, code: int = EXIT_USER_ERROR) -> NoReturn:
    """Print one error line and exit (raise the original error instead when debugging)."""
    if debug_enabled() and sys.exc_info()[0] is not None:
        raise
    typer.echo(f"cobel: error: {message}", err=True)
    raise typer.Exit(code)


def allow_targets(patterns: list[str] | None) -> None:
    """Add ``--allow-target`` patterns to the instantiation gate (this process and the
    processes it starts, through ``COBEL_ALLOW_TARGETS``); a malformed one is one line."""
    from cobelrun.errors import CobelError
    from cobelrun.targets import allow

    try:
        allow(patterns or [])
    except CobelError as exc:
        fail(str(exc))
