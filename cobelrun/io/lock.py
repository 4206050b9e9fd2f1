"""One writer per run folder: an ``fcntl`` lock held while a run (or a sweep job) writes it.

:class:`RunLock` takes an exclusive, non-blocking ``flock`` on ``FOLDER/.lock`` and writes the
holder's process id into it. A second writer is refused at once with one line naming that
process; the kernel drops the lock when the holder exits, also on ``kill -9``, so a lock never
outlives its process (a killed run may leave the empty ``.lock`` file, which means nothing by
itself). The lock is re-entrant within a process: ``cobel run`` takes it before Hydra writes
anything into the folder, and the runner takes it again around its own writes.

:func:`holds_run` says whether a folder already holds a run, which a new run never replaces.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
from pathlib import Path
from types import TracebackType

from cobelrun.errors import CobelError

__all__ = ["LOCK_FILE", "RunLock", "holder", "holds_run", "refuse_existing", "writing"]

#: the lock file inside the folder
LOCK_FILE = ".lock"
#: files whose presence means a folder holds a run: cobel's own
RUN_MARKERS = ("manifest.json", "config.yaml", ".done")
#: and Hydra's record of a job (written by Hydra before cobel's job function starts)
HYDRA_MARKER = ".hydra"

#: folders this process holds: resolved path -> [file descriptor, depth]
_HELD: dict[str, list[int]] = {}


def holds_run(folder: Path, *, hydra: bool = True) -> str | None:
    """The first file that marks ``folder`` as holding a run (``manifest.json``, ...), or None.

    ``hydra``: Hydra's ``.hydra`` folder counts too (not from inside a job, where Hydra has
    just written it)."""
    for name in (*RUN_MARKERS, HYDRA_MARKER) if hydra else RUN_MARKERS:
        if (Path(folder) / name).exists():
            return name
    return None


def holder(folder: Path) -> int | None:
    """The process id written in ``folder``'s lock file, if it can be read."""
    try:
        text = (Path(folder) / LOCK_FILE).read_text(encoding="ascii").strip()
    except (OSError, UnicodeDecodeError):
        return None
    return int(text) if text.isdigit() else None


def writing(folder: Path) -> int | None:
    """The process id of another process that holds ``folder``'s lock now (0 if it cannot
    be read), or None when no one does. Creates nothing."""
    folder = Path(folder)
    key = str(folder.absolute().resolve())
    if key in _HELD:
        return None  # this process
    try:
        fd = os.open(folder / LOCK_FILE, os.O_RDONLY)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        return holder(folder) or 0
    finally:
        os.close(fd)  # closing drops the probe's own lock
    return None


def refuse_existing(folder: Path, what: str, *, hydra: bool = True) -> None:
    """A CobelError if ``folder`` is being written by another process (naming it) or already
    holds a run (a new run never replaces one)."""
    pid = writing(folder)
    if pid is not None:
        who = f"process {pid}" if pid else "another process"
        raise CobelError(
            f"{what} {folder} is being written by {who} (a cobel run); one writer per "
            "folder: wait for it to end or choose another folder"
        )
    found = holds_run(folder, hydra=hydra)
    if found is not None:
        raise CobelError(
            f"{what} {folder} already holds a run ({found}); a new run never replaces one: "
            "choose another folder"
        )


class RunLock:
    """Hold ``folder`` (created if missing) for writing; a CobelError if another process holds
    it (or the folder cannot be written). Use as a context manager.

    Parameters
    ----------
    folder
        The run folder (or a sweep job's folder).
    what
        How the folder is named in the error (``the run folder``).
    """

    def __init__(self, folder: str | os.PathLike[str], what: str = "the run folder") -> None:
        self.folder = Path(folder).expanduser().absolute()
        self.what = what
        self._key = ""

    def __enter__(self) -> RunLock:
        try:
            return self._acquire()
        except OSError as exc:  # a full disk, a read-only folder, a file in the way
            from cobelrun.io.atomic import disk_error

            raise CobelError(disk_error(exc, self.folder)) from None

    def _acquire(self) -> RunLock:
        self.folder.mkdir(parents=True, exist_ok=True)
        self._key = str(self.folder.resolve())
        held = _HELD.get(self._key)
        if held is not None:  # this process holds it already (cobel run, then the runner)
            held[1] += 1
            return self
        path = self.folder / LOCK_FILE
        for _ in range(10):
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                os.close(fd)
                if exc.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                    raise
                pid = holder(self.folder)
                who = f"process {pid}" if pid is not None else "another process"
                raise CobelError(
                    f"{self.what} {self.folder} is being written by {who} (a cobel run); "
                    "one writer per folder: wait for it to end or choose another folder"
                ) from None
            # the holder before us may have removed the file after we opened it: the lock
            # counts only on the file that is still there
            try:
                same = os.stat(path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        else:  # pragma: no cover - a folder whose lock file keeps being replaced
            raise CobelError(f"cannot lock {self.what} {self.folder}: its lock file keeps changing")
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode("ascii"))
        _HELD[self._key] = [fd, 1]
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        held = _HELD.get(self._key)
        if held is None:
            return
        held[1] -= 1
        if held[1] > 0:
            return
        del _HELD[self._key]
        with contextlib.suppress(OSError):  # removed while still held: no one can take it
            os.unlink(self.folder / LOCK_FILE)  # between our removal and release
        os.close(held[0])
