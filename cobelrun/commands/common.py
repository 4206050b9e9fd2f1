"""What every ``cobel`` command shares: exit codes and the one-line error exit.

Kept apart from the app (:mod:`cobelrun.commands.app`) so that command modules
(``commands/*.py``) can use it without importing the app that registers them (no import cycle).
Importing it does not import typer (``cobel run``'s fast path reads its exit codes):
:data:`AllowTarget` is built on first use.
"""

from __future__ import annotations

import os
import sys
from typing import TYPE_CHECKING, Any, NoReturn

if TYPE_CHECKING:
    from typing import Annotated

    import typer

    #: ``--allow-target``: the user's own classes a config may build (docs/reliability.md)
    AllowTarget = Annotated[list[str] | None, typer.Option("--allow-target")]

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


#: exit code of a user error (bad config, name or folder)
EXIT_USER_ERROR = 2
#: exit code of a run stopped by Ctrl-C or SIGTERM
EXIT_INTERRUPTED = 130


def __getattr__(name: str) -> Any:
    """``AllowTarget``, the ``--allow-target`` option type, made when a command module imports
    it (so that importing this module does not import typer)."""
    if name == "AllowTarget":
        from typing import Annotated

        import typer

        option = typer.Option(
            "--allow-target", help=ALLOW_TARGET_HELP, metavar="PATTERN", show_default=False
        )
        allow_target = Annotated[list[str] | None, option]
        globals()["AllowTarget"] = allow_target
        return allow_target
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def debug_enabled() -> bool:
    """``--debug`` (``COBEL_DEBUG=1``) or ``HYDRA_FULL_ERROR=1``: show tracebacks."""
    return os.environ.get("HYDRA_FULL_ERROR") == "1" or os.environ.get("COBEL_DEBUG") == "1"


def fail(message: str, code: int = EXIT_USER_ERROR) -> NoReturn:
    """Print one error line and exit (raise the original error instead when debugging)."""
    import typer

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


def launcher_choice(name: str | None, args: list[str]) -> list[str]:
    """``--launcher NAME --launcher-arg K=V`` (``cobel figure``, ``cobel recover``): the Hydra
    overrides that choose the launcher of the command's sweeps; a malformed argument is one
    line."""
    import re

    from cobelrun.errors import CobelError

    if name is None:
        if args:
            raise CobelError("--launcher-arg needs --launcher NAME (the launcher it configures)")
        return []
    if not re.fullmatch(r"[A-Za-z0-9_][A-Za-z0-9_.-]*", name):
        raise CobelError(f"--launcher {name!r}: give a launcher config name (e.g. slurm, local)")
    out = [f"hydra/launcher={name}"]
    for arg in args:
        key, sep, value = arg.partition("=")
        if not sep or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_.]*", key):
            raise CobelError(f"--launcher-arg {arg!r}: give KEY=VALUE (e.g. partition=gpu)")
        out.append(f"hydra.launcher.{key}={value}")
    return out
