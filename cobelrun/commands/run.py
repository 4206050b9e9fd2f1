"""``cobel run``: what the command does, and its plain form read without typer.

:func:`launch_run` is the command's body, shared by the typer command
(:func:`cobelrun.commands.app.run_cmd`) and by the console script's fast path
(:func:`cobelrun.cli.main`): a plain ``cobel run`` (Hydra's arguments and the flags
``--quiet``, ``--debug``, ``--live``; :func:`plain_run`) is read here without importing typer,
click or the other commands, which cost ~0.1 s of a short run's ~2 s (docs/speed.md). Any
other form (``--port``, ``--allow-target``, ``--help``, ``--``, a flag spelled otherwise) goes
through typer as before. ``tests/test_startup_cli.py`` checks that both read the same
arguments the same way.

Importing this module imports nothing beyond the standard library (and the typer-free
:mod:`cobelrun.commands.common`).
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass, field

from cobelrun.commands.common import EXIT_INTERRUPTED, EXIT_USER_ERROR, debug_enabled

#: ``cobel run``'s own flags that take no value: read by :func:`plain_run` as typer reads them
FLAGS = {"--debug": "debug", "--quiet": "quiet", "--live": "live"}
#: words that only typer reads: ``cobel run``'s options with a value, ``--help``, and any other
#: spelling of the flags (``--quiet=1`` is typer's error)
TYPER_ONLY = ("--debug", "--quiet", "--live", "--port", "--allow-target", "--help")


@dataclass
class PlainRun:
    """A plain ``cobel run``: the words for Hydra, in order, and the flags."""

    args: list[str] = field(default_factory=list)
    debug: bool = False
    quiet: bool = False
    live: bool = False


def plain_run(argv: list[str]) -> PlainRun | None:
    """``argv`` (the words after ``cobel``) as a plain ``cobel run``, or None when typer must
    read it: not ``run``, or a word that only typer reads (:data:`TYPER_ONLY`, ``--``).

    Reads what typer's ``run`` command reads (``context_settings`` ``allow_extra_args`` and
    ``ignore_unknown_options``): its flags anywhere among the words, every other word passed
    to Hydra unchanged and in order.
    """
    if not argv or argv[0] != "run":
        return None
    plain = PlainRun()
    for word in argv[1:]:
        if word in FLAGS:
            setattr(plain, FLAGS[word], True)
        elif word == "--" or word.startswith(TYPER_ONLY):
            return None
        else:
            plain.args.append(word)
    return plain


def launch_run(
    args: list[str],
    *,
    debug: bool = False,
    quiet: bool = False,
    live: bool = False,
    port: int | None = None,
) -> int:
    """Run ``cobel run ARGS`` (``args``: Hydra's words); return the exit code. Bad input
    raises :class:`~cobelrun.errors.CobelError`, Ctrl-C :class:`KeyboardInterrupt`."""
    if debug:
        os.environ["COBEL_DEBUG"] = "1"
        os.environ["HYDRA_FULL_ERROR"] = "1"
    from cobelrun.hydra_app import launch

    args = list(args)
    extra = []  # the record keys, so that config.yaml says how the run ran
    if live or port is not None:
        extra.append("task.record.live=true")
    if port is not None:
        extra.append(f"task.record.live_port={port}")
    if extra:
        # Hydra's parser takes the overrides only as one unbroken run of words: put these at
        # its start (the user's own task.record.live_port=... comes later and wins)
        at = next((i for i, a in enumerate(args) if "=" in a and not a.startswith("-")), 0)
        args[at:at] = extra
    return launch(args, quiet=quiet)


def run_plain(plain: PlainRun) -> int:
    """The fast path: run ``plain`` and return the exit code, with the typer command's error
    handling (one ``cobel: error:`` line and exit code 2, or 130 when interrupted; the
    exception itself with ``--debug``)."""
    import errno

    from cobelrun.errors import CobelError

    try:
        return launch_run(plain.args, debug=plain.debug, quiet=plain.quiet, live=plain.live)
    except CobelError as exc:
        if debug_enabled():
            raise
        return _error(str(exc), EXIT_USER_ERROR)
    except KeyboardInterrupt:
        if debug_enabled():
            return EXIT_INTERRUPTED  # typer ends an interrupted command with 130, no message
        return _error("interrupted", EXIT_INTERRUPTED)
    except OSError as exc:
        if exc.errno == errno.EPIPE:  # a closed pipe: as typer, exit code 1
            return 1
        raise


def _error(message: str, code: int) -> int:
    print(f"cobel: error: {message}", file=sys.stderr, flush=True)
    return code
