"""Stopping a run cleanly: SIGINT and SIGTERM become :class:`Interrupted`, but never inside a
critical section and never while files are being finished.

The runner installs a :class:`SignalGuard` for the run. Code whose interruption would leave
state half-changed wraps it in :func:`critical`: the recorder when it moves rows between
buffers, compiled agents around a kernel call (a signal landing inside numpy's generator
``ctypes`` accessors used to print a PCG64 error and corrupt the draw). A signal inside a
critical section is raised when the section ends.

A signal can arrive before any run has installed its guard: SLURM preempts a job, or sends its
time-limit signal, while Python still imports and the config is being composed. The ``cobel``
CLI therefore calls :func:`hold_early` first: SIGTERM, SIGUSR1 and SIGUSR2 are held, and the
first guard installed afterwards acts on a held signal as if it had just arrived (a run with
checkpoints stops at its first trial boundary with a checkpoint and exits 75). A second early
signal ends the process at once, as without cobel.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
from collections.abc import Iterator
from typing import Any

__all__ = ["Interrupted", "SignalGuard", "Stopped", "critical", "hold_early"]

_ACTIVE: SignalGuard | None = None
#: signals that arrived before a guard was installed (:func:`hold_early`), oldest first
_EARLY: list[int] = []
#: the handlers :func:`hold_early` replaced, put back once a guard has taken over
_ORIGINAL: dict[int, Any] = {}

#: the signals :func:`hold_early` holds: what a scheduler sends to stop or requeue a job
EARLY_SIGNALS = tuple(getattr(signal, n) for n in ("SIGTERM", "SIGUSR1", "SIGUSR2")
                      if hasattr(signal, n))  # fmt: skip

#: Set by the ``cobel`` CLI: once a run was stopped, further SIGINT/SIGTERM are ignored until
#: the process exits (so a late second Ctrl-C cannot turn exit code 130 into a kill). A
#: library caller (notebook) keeps its own handlers back.
HOLD_AFTER_STOP = False


def _hold(signum: int, frame: Any) -> None:
    if _EARLY:  # a second signal before any run started: the default action, now
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)
        return
    _EARLY.append(signum)


def hold_early() -> None:
    """Hold SIGTERM, SIGUSR1 and SIGUSR2 until a :class:`SignalGuard` is installed, which then
    acts on the first one held. Main thread only (else nothing is held)."""
    with contextlib.suppress(ValueError):
        for sig in EARLY_SIGNALS:
            previous = signal.signal(sig, _hold)
            if previous is not _hold:
                _ORIGINAL[sig] = previous


def _release_early(taken: dict[int, Any]) -> None:
    """A guard has taken over: the early signals it does not handle get their original
    handlers back (a run without checkpoints leaves SIGUSR1/SIGUSR2 to their default), and
    those it does handle are restored to the originals, not to the hold, when it ends."""
    with contextlib.suppress(ValueError):
        for sig, original in list(_ORIGINAL.items()):
            if sig in taken:
                if taken[sig] is _hold:
                    taken[sig] = original
            elif signal.getsignal(sig) is _hold:
                signal.signal(sig, original)
    _ORIGINAL.clear()


def early_signal() -> int | None:
    """The signal held by :func:`hold_early` that no guard has taken yet (None: none)."""
    return _EARLY[0] if _EARLY else None


def critical() -> contextlib.AbstractContextManager[None]:
    """A critical section of the active guard (none installed: a no-op)."""
    return _ACTIVE.critical() if _ACTIVE is not None else contextlib.nullcontext()


class SignalGuard:
    """Ctrl-C and SIGTERM as :class:`KeyboardInterrupt`, but never inside a critical section
    and never while files are being closed.

    A signal inside :meth:`critical` is held and raised when the section ends; during
    :meth:`closing` (the files are being finished) further signals are ignored with one
    notice, so a second Ctrl-C cannot cut the shutdown short. Outside the main thread the
    guard installs nothing (signals go to the main thread anyway).
    """

    def __init__(self, *, defer: bool = False) -> None:
        #: a run with checkpoints: the first SIGINT/SIGTERM/SIGUSR1 only asks the run to stop
        #: at its next trial boundary (:attr:`stop_requested`), where it writes a checkpoint
        #: (cobelrun.checkpoint); a second one stops it at once
        self.defer = bool(defer)
        #: the signal that asked a deferring run to stop (None: none yet)
        self.stop_requested: int | None = None
        self._depth = 0
        self._stopped = False
        self._pending: int | None = None
        self._closing = False
        self._noticed = False
        self._previous: dict[int, Any] = {}

    def _handler(self, signum: int, frame: Any) -> None:
        if self._closing:
            if not self._noticed:
                self._noticed = True
                print("cobel: finishing the run's files, please wait", file=sys.stderr)
            return
        if self.defer and self.stop_requested is None:
            self.stop_requested = signum  # the run stops at its next trial boundary
            return
        if self.defer and signum != signal.SIGINT:
            # only a person's second Ctrl-C stops a deferring run at once: a scheduler's or a
            # sweep launcher's SIGTERM (forwarded each second), SIGUSR1 and SIGUSR2 repeat the
            # same request, which must still end in a checkpoint
            return
        if self._depth:
            self._pending = signum
            return
        self._closing = self._stopped = True  # later signals must not cut the shutdown
        raise Interrupted(signum)

    @contextlib.contextmanager
    def installed(self) -> Iterator[SignalGuard]:
        """Handle SIGINT/SIGTERM with this guard (main thread only) and make it the guard of
        :func:`critical` for the duration."""
        global _ACTIVE
        try:
            # SIGUSR1: what SLURM sends ahead of a time limit (sbatch --signal=USR1@90)
            # SIGUSR2: submitit's preemption signal (SUBMITIT_PREEMPT_SIGNAL)
            names = ("SIGUSR1", "SIGUSR2") if self.defer else ()
            extra = tuple(getattr(signal, n) for n in names if hasattr(signal, n))
            for sig in (signal.SIGINT, signal.SIGTERM, *extra):
                self._previous[sig] = signal.signal(sig, self._handler)
        except ValueError:  # not the main thread
            self._previous.clear()
        outer, _ACTIVE = _ACTIVE, self
        try:
            if _EARLY and self._previous:  # held before this guard: act on it now
                signum = _EARLY.pop(0)
                _EARLY.clear()
                if self.defer:  # stop at the first trial boundary, with a checkpoint
                    self.stop_requested = signum
                else:  # raised where the run can close its files: a critical section's end
                    self._pending = signum
            if self._previous:
                _release_early(self._previous)
            yield self
        finally:
            _ACTIVE = outer
            hold = self._stopped and HOLD_AFTER_STOP
            for sig, prev in self._previous.items():
                signal.signal(sig, signal.SIG_IGN if hold else prev)
            self._previous.clear()

    @contextlib.contextmanager
    def critical(self) -> Iterator[None]:
        self._depth += 1
        try:
            yield
        finally:
            self._depth -= 1
        if not self._depth and self._pending is not None and not self._closing:
            signum, self._pending = self._pending, None
            self._closing = self._stopped = True
            raise Interrupted(signum)

    @contextlib.contextmanager
    def closing(self) -> Iterator[None]:
        """Files are being finished: signals are ignored (with one notice) until the end."""
        was, self._closing = self._closing, True
        try:
            yield
        finally:
            self._closing = was
        if self._pending is not None and not was:
            signum, self._pending = self._pending, None
            self._stopped = True
            raise Interrupted(signum)


class Interrupted(KeyboardInterrupt):
    """The run was stopped by SIGINT or SIGTERM."""

    def __init__(self, signum: int = signal.SIGINT) -> None:
        super().__init__(f"received signal {signum}")
        self.signum = signum

    @property
    def signame(self) -> str:
        """The signal's name (``SIGTERM``), or its number when it has none."""
        try:
            return signal.Signals(self.signum).name
        except ValueError:
            return str(self.signum)


class Stopped(Interrupted):
    """A run with checkpoints stopped on a signal after writing its checkpoint: it can be
    resumed (``cobel resume RUN_DIR``); the CLI exits with
    :data:`cobelrun.checkpoint.REQUEUE_EXIT`."""

    def __init__(self, signum: int, checkpoint: Any) -> None:
        super().__init__(signum)
        self.checkpoint = checkpoint
