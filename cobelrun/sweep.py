"""A sweep's launcher at run time (orchestration): the lock that keeps a sweep folder to one
``cobel run -m``, the stop request its jobs see, and the set-up of its worker processes
(signals, the watch on the launcher).

The folder's format (``sweep.json``, ``job.json``, the job index) is
:mod:`cobelrun.io.sweep_folder`, combining its tables :mod:`cobelrun.io.sweep_collect`, and
planning its jobs from overrides :mod:`cobelrun.sweep_plan`.
"""

from __future__ import annotations

import datetime as _dt
import os
import socket
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from cobelrun.errors import CobelError
from cobelrun.io.manifest import _write_json_atomic
from cobelrun.io.repair import pid_alive
from cobelrun.io.sweep_folder import JOB_FILE, check_job_dir, job_dir, write_job_status
from cobelrun.io.validate import read_json_or_none as read_json


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat()


# -- stopping a sweep and keeping it to one launcher ----------------------------------------------

#: written by the launcher when it is asked to stop (Ctrl-C, SIGTERM); jobs that start later see
#: it and stop at once, marked ``interrupted``
STOP_FILE = ".stop"
#: the advisory lock (``fcntl.flock``) a launcher holds on its sweep folder; holds its pid
LOCK_FILE = ".lock"


class SweepLock:
    """An exclusive advisory lock on a sweep folder, held while one ``cobel run -m`` launches it.

    A second launcher into the same folder is refused with the holder's pid instead of running
    the same jobs twice (each overwriting the other's files). The lock is the kernel's
    (``fcntl.flock``): it goes away with the process that holds it, also on SIGKILL, so a stale
    lock file never blocks a resume.
    """

    def __init__(self, sweep_dir: str | os.PathLike[str]) -> None:
        self.path = Path(sweep_dir) / LOCK_FILE
        self._fd: int | None = None

    def acquire(self) -> SweepLock:
        import fcntl

        if self.path.parent.is_dir():  # job folders a launcher clears: never through a link
            for entry in self.path.parent.iterdir():
                if entry.name.isdigit():
                    check_job_dir(entry)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = ""
            try:
                holder = os.pread(fd, 200, 0).decode("utf-8", "replace").strip()
            finally:
                os.close(fd)
            pid, _, host = holder.partition(" ")
            who = (f"pid {pid}" + (f" on {host}" if host else "")) if pid else "pid unknown"
            raise CobelError(
                f"sweep folder {self.path.parent} is in use by another `cobel run -m` ({who}); "
                "wait for it to finish or stop it, then run the command again to resume"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()} {socket.gethostname()}\n".encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            import fcntl

            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> SweepLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


def stop_requested(sweep_dir: Path) -> bool:
    """True once the sweep's launcher was asked to stop."""
    return (Path(sweep_dir) / STOP_FILE).exists()


def request_stop(sweep_dir: Path, reason: str) -> None:
    """Tell jobs that have not started yet not to start (idempotent)."""
    path = Path(sweep_dir) / STOP_FILE
    if not path.exists():
        try:
            _write_json_atomic(path, {"reason": reason, "pid": os.getpid(), "at": _now()})
        except OSError:
            pass


def clear_stop(sweep_dir: Path) -> None:
    (Path(sweep_dir) / STOP_FILE).unlink(missing_ok=True)


def running_pids(sweep_dir: Path, jobs: Iterable[int]) -> dict[int, int]:
    """job -> pid of each job whose ``job.json`` says it is running in a live process here."""
    out = {}
    host = socket.gethostname()
    for num in jobs:
        state = read_json(job_dir(sweep_dir, num) / JOB_FILE) or {}
        pid = state.get("pid")
        if state.get("status") == "running" and state.get("host") == host and isinstance(pid, int):
            if pid != os.getpid() and pid_alive(pid):
                out[num] = pid
    return out


def mark_not_started(sweep_dir: Path, jobs: Iterable[int], reason: str) -> int:
    """Mark jobs still ``queued`` as ``interrupted`` (they never started); returns how many."""
    n = 0
    for num in jobs:
        d = job_dir(sweep_dir, num)
        if (read_json(d / JOB_FILE) or {}).get("status") == "queued":
            write_job_status(d, "interrupted", error=reason)
            n += 1
    return n


#: the environment variable through which a sweep's launcher tells its workers its pid
LAUNCHER_ENV = "COBEL_SWEEP_LAUNCHER"
#: the launcher's pid, in a worker process (set by :func:`worker_init`)
_PARENT_PID: int | None = None
#: True while a worker runs a job (:func:`cobelrun.hydra_app.sweep_job`): a signal then is the
#: job's to handle, and the worker does not exit between its files and its ``job.json``
IN_JOB = False


def launcher_gone() -> bool:
    """In a sweep worker: True once the launcher that started it has ended."""
    return _PARENT_PID is not None and os.getppid() != _PARENT_PID


def worker_init() -> None:
    """Initializer of sweep worker processes (joblib/loky).

    * An idle worker ignores SIGINT and SIGTERM: a Ctrl-C in the terminal reaches every process
      of the group, and a worker that died of it between jobs would make the pool kill the
      others while they finish their files. A running job takes the signals itself
      (:class:`cobelrun.recorder.SignalGuard`) and stops cleanly.
    * The worker stops when the launcher ends, however it ends (even SIGKILL), so none is
      orphaned: the launcher's pid comes from :data:`LAUNCHER_ENV` (set before the pool starts),
      so a worker whose launcher died while the worker was still starting exits at once;
      on Linux the kernel sends SIGTERM when the launcher dies (``PR_SET_PDEATHSIG``), and a
      watchdog thread sends it too once the worker's parent is no longer the launcher (the
      kernel's signal is tied to the thread that spawned the worker, and is not sent when that
      thread ends before the launcher). A running job then stops cleanly and its worker exits;
      an idle worker exits at once.
    """
    import signal
    import threading

    global _PARENT_PID
    try:
        _PARENT_PID = int(os.environ[LAUNCHER_ENV])
    except (KeyError, ValueError):
        _PARENT_PID = os.getppid()

    def idle(signum: int, frame: Any) -> None:
        if launcher_gone() and not IN_JOB:  # the launcher is gone: do not linger as an orphan
            os._exit(128 + signum)

    signal.signal(signal.SIGINT, idle)
    signal.signal(signal.SIGTERM, idle)
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        pr_set_pdeathsig = 1
        libc.prctl(pr_set_pdeathsig, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError):
        pass
    if launcher_gone():  # the launcher died before the worker got here
        os._exit(1)
    threading.Thread(target=_watch_launcher, name="cobel-launcher-watch", daemon=True).start()


def _watch_launcher(poll: float = 0.5, grace: float = 300.0) -> None:
    """Worker thread: once the launcher is gone, SIGTERM this process each second (a running
    job closes its files, an idle worker exits); if it still lives ``grace`` seconds later,
    end it.

    Once is not enough: a signal that lands while a job finishes its files is ignored by
    design (:meth:`cobelrun.signals.SignalGuard.closing`), and the job then completes and
    hands its worker back to a pool whose launcher is gone (it would wait for its next job
    until loky's idle timeout, holding the sweep's stdout open)."""
    import signal
    import time

    while not launcher_gone():
        time.sleep(poll)
    deadline = time.monotonic() + grace
    while time.monotonic() < deadline:
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(1.0)
    os._exit(143)
