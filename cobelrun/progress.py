"""Progress bars (rich) that stay quiet when output is not a terminal.

Three bars: trials of a run (``run_progress``, driven by the runner after every phase of every
run), jobs of a sweep and runs of a figure (``counter_progress``). All go to stderr, vanish when
done (transient) and are switched off when stderr is not a terminal or ``COBEL_PROGRESS=0``.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Callable, Iterator


def progress_enabled() -> bool:
    """True when stderr is a terminal and ``COBEL_PROGRESS`` is not ``0``."""
    return sys.stderr.isatty() and os.environ.get("COBEL_PROGRESS", "1") != "0"


def _columns(unit: str):
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    return (
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn(unit),
        TextColumn("{task.fields[note]}"),
        TimeElapsedColumn(),
        TextColumn("eta"),
        TimeRemainingColumn(),
    )


@contextlib.contextmanager
def run_progress(label: str, *, enabled: bool = True) -> Iterator[Callable[..., None] | None]:
    """Yield ``update(trials_done, trials_total, run=r, runs=R)`` for a trials bar, or None.

    The runner calls it after every piece of a phase (cobelrun.runner.PhasePacer) of every
    run: the bar counts trials over all runs of the task and notes the current run.
    """
    if not enabled or not progress_enabled():
        yield None
        return
    from rich.progress import Progress

    with Progress(*_columns("trials"), transient=True) as bar:
        task_id = bar.add_task(label, total=None, note="")

        def update(done: int, total: int, *, run: int | None = None, runs: int | None = None):
            note = f"run {run + 1}/{runs}" if run is not None and runs else ""
            bar.update(task_id, completed=done, total=total, note=note)

        yield update


@contextlib.contextmanager
def counter_progress(
    label: str, *, total: int, unit: str = "", enabled: bool = True
) -> Iterator[Callable[..., None]]:
    """Yield ``update(done, total=None, note="")`` for a counting bar (a no-op when quiet)."""
    if not enabled or not progress_enabled():
        yield lambda *args, **kwargs: None
        return
    from rich.progress import Progress

    with Progress(*_columns(unit), transient=True) as bar:
        task_id = bar.add_task(label, total=total, note="")

        def update(done: int, total: int | None = None, note: str = "") -> None:
            bar.update(task_id, completed=done, total=total, note=note)

        yield update
