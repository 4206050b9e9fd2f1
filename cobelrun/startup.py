"""The start-up of a single ``cobel run``: the cyclic garbage collector waits for the job.

A short tabular run spent ~0.3 s of its ~2.3 s of CPU in Python's cyclic garbage collector
(docs/speed.md, issue 38) while it imported numpy, Hydra, pyarrow and numba and composed its
config: every collection walked the objects the imports had made, of which almost none is
garbage. ``cobel run`` therefore pauses the collector from its first line
(:func:`pause_gc`) until its job starts (:func:`resume_gc`, called by the Hydra job function,
and by :func:`cobelrun.compose.validate` for a sweep, whose launcher runs long), then moves
what the start-up made into the permanent generation (``gc.freeze``) and turns the collector
back on. This is the pattern of Python's documentation for ``gc.freeze``; the frozen objects
(modules, classes, the composed config) live as long as the process anyway, and no later
collection walks them again, which also shortens the run's own collections.

What stays allocated: the start-up's own cyclic garbage, ~13,000 small objects of a tabular
run (a full collection at the job's start finds them; it would cost ~0.1 s), once per process.

Nothing here imports anything beyond the standard library.
"""

from __future__ import annotations

import gc

_paused = False


def pause_gc() -> bool:
    """Pause the cyclic garbage collector for the start-up (if it runs); return whether this
    call paused it."""
    global _paused
    if _paused or not gc.isenabled():
        return False
    gc.disable()
    _paused = True
    return True


def resume_gc() -> None:
    """End a pause of :func:`pause_gc`: freeze what was made since (``gc.freeze``) and turn the
    collector back on. Does nothing when the collector was not paused here (the Python API,
    tests, a collector someone else turned off)."""
    global _paused
    if not _paused:
        return
    _paused = False
    gc.freeze()
    gc.enable()


def gc_paused() -> bool:
    """Whether :func:`pause_gc` paused the collector and it has not been resumed yet."""
    return _paused
