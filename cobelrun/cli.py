"""The ``cobel`` command line: the console script's entry point (:func:`main`).

A plain ``cobel run`` (Hydra's arguments and ``--quiet``/``--debug``/``--live``) runs without
importing typer and the other commands (:mod:`cobelrun.commands.run`); everything else goes
through the typer app (:mod:`cobelrun.commands.app`; ``from cobelrun.cli import app`` gives
it). ``cobel run`` pauses Python's cyclic garbage collector until its job starts
(:mod:`cobelrun.startup`), and a finished command leaves without the interpreter's teardown
(:func:`exit_now`). User errors print one line and exit 2; add ``--debug`` (or set
HYDRA_FULL_ERROR=1) for the traceback.
"""

from __future__ import annotations

import os
import sys
from typing import Any, NoReturn


def __getattr__(name: str) -> Any:
    """The typer app and its commands (``from cobelrun.cli import app``), imported on use.

    Dunder names are never forwarded: the import system asks every module for ``__path__``
    (``from cobelrun.cli import main``), which must not import the app.
    """
    if name.startswith("__"):
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from cobelrun.commands import app

    try:
        return getattr(app, name)
    except AttributeError:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None


def _shell_completion_args(argv: list[str]) -> list[str] | None:
    """``cobel -sc ...`` (what Hydra's completion script calls) as ``cobel run -sc ...``.

    Hydra's bash/zsh/fish completion scripts call the program named in the completed line
    with ``-sc query=SHELL``; the line's ``run`` word is dropped so that Hydra sees only the
    overrides.
    """
    if not argv or argv[0] not in ("-sc", "--shell-completion"):
        return None
    line = os.environ.get("COMP_LINE")
    if line is not None:
        words = line.split(" ")
        if len(words) > 1 and words[1] == "run":
            os.environ["COMP_LINE"] = " ".join([words[0], *words[2:]])
            point = os.environ.get("COMP_POINT")
            if point is not None and point.isdigit():
                os.environ["COMP_POINT"] = str(max(0, int(point) - len("run ")))
    return ["run", *argv]


def main() -> None:
    """Console-script entry point."""
    # Arrow's default allocator (mimalloc) keeps freed pages in per-thread heaps: the
    # recorder's writer thread then held ~40 MB more at the end of 1,000 Fig. 6B runs. The
    # writes are few and batched, so the C library's malloc costs nothing measurable. Arrow
    # reads this once, before its first allocation; an explicit setting wins.
    os.environ.setdefault("ARROW_DEFAULT_MEMORY_POOL", "system")
    import cobelrun.signals
    from cobelrun import startup

    cobelrun.signals.HOLD_AFTER_STOP = True  # a stopped run exits 130, whatever comes after
    argv = sys.argv[1:]
    if _single_run(argv):
        # a scheduler's SIGTERM/SIGUSR1/SIGUSR2 while Python imports and the config is composed
        # stops the run at its first trial boundary (with a checkpoint: exit 75), not with 143
        cobelrun.signals.hold_early()
    if argv[:1] == ["run"]:
        startup.pause_gc()  # until the job starts (hydra_app.job); see cobelrun.startup
    try:
        code = _command(argv)
    finally:
        startup.resume_gc()  # a run that ended before its job (a bad config, --help)
    exit_now(code)


def _single_run(argv: list[str]) -> bool:
    """``cobel run`` without ``-m`` (a sweep's launcher handles its own signals) or
    ``cobel resume``."""
    if argv[:1] == ["resume"]:
        return True
    return argv[:1] == ["run"] and not any(a in ("-m", "--multirun") for a in argv[1:])


def _command(argv: list[str]) -> Any:
    """Run the command ``argv``; return its exit code (as ``sys.exit`` takes it)."""
    from cobelrun.commands.run import plain_run, run_plain

    plain = plain_run(argv)
    if plain is not None:  # the fast path: no typer
        return run_plain(plain)
    import typer

    from cobelrun.commands.app import app
    from cobelrun.commands.common import EXIT_USER_ERROR, debug_enabled
    from cobelrun.errors import CobelError

    try:
        forwarded = _shell_completion_args(argv)
        app(args=forwarded) if forwarded is not None else app()
    except CobelError as exc:  # errors raised outside a command body
        if debug_enabled():
            raise
        typer.echo(f"cobel: error: {exc}", err=True)
        return EXIT_USER_ERROR
    except SystemExit as exc:  # how click ends every command, successful or not
        return exc.code
    return 0


def exit_now(code: Any) -> NoReturn:
    """End the process with ``code`` (as ``sys.exit`` takes it), skipping the interpreter's
    teardown when nothing needs it.

    Tearing down the modules of a run costs 0.45 s after a tabular run (numba, llvmlite) and
    0.8-1.7 s after a deep one (torch: measured in docs/speed.md) for nothing: cobel's files
    are closed by then. The teardown is kept (``sys.exit``) when something may still need it:
    another non-daemon thread or a child process still alive, a process pool used (a sweep's
    joblib or submitit launcher), a tracer or profiler (coverage writes its data at exit), or
    ``COBEL_FAST_EXIT=0``. Otherwise logging is shut down and the standard streams flushed, as
    the teardown would, and the process ends with ``os._exit``.
    """
    status, message = _exit_status(code)
    if not _teardown_needed():
        import logging

        logging.shutdown()
        if message is not None:
            print(message, file=sys.stderr)
        try:
            sys.stdout.flush()
            sys.stderr.flush()
        except (OSError, ValueError):  # a closed pipe: the teardown would fail the same way
            status = status or 120
        os._exit(status)
    sys.exit(code)


def _exit_status(code: Any) -> tuple[int, str | None]:
    """``sys.exit``'s reading of ``code``: None is 0, an int is itself, anything else is
    printed and gives 1."""
    if code is None:
        return 0, None
    if isinstance(code, int):
        return code & 0xFF, None
    return 1, str(code)


#: process pools (a sweep's launchers) whose exit handlers clean up workers and files
_POOLS = ("joblib", "submitit")


def _teardown_needed() -> bool:
    import threading

    if os.environ.get("COBEL_FAST_EXIT", "1") == "0":
        return True
    if sys.gettrace() is not None or sys.getprofile() is not None or "coverage" in sys.modules:
        return True
    main_thread = threading.main_thread()
    if any(t is not main_thread and not t.daemon and t.is_alive() for t in threading.enumerate()):
        return True
    if any(name in sys.modules for name in _POOLS):
        return True  # their workers and shared-memory folders are cleaned up at exit
    mp = sys.modules.get("multiprocessing")
    return bool(mp is not None and mp.active_children())


if __name__ == "__main__":
    main()
