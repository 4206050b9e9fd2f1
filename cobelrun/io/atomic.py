"""Atomic file writes: write to a temporary name in the same folder, then rename.

A reader (``cobel plot``, ``cobel collect``, a figure script, a second process) never sees a
half-written file: either the old file or the complete new one. A failed write (a full disk, a
read-only folder, Ctrl-C) removes its temporary file and leaves the old file in place.

    with atomic_path(out / "fig.csv") as tmp:
        table.to_csv(tmp, index=False)

``disk_error`` turns ``ENOSPC``/``EDQUOT``/``EROFS``/``EACCES`` into one-line messages.
"""

from __future__ import annotations

import contextlib
import errno
import os
from collections.abc import Iterator
from pathlib import Path

__all__ = ["atomic_path", "atomic_write_bytes", "atomic_write_text", "disk_error", "is_disk_error"]

#: errors that say "this folder cannot take more data", not "the program is wrong"
DISK_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG)


def tmp_name(path: Path) -> Path:
    """``.name.<pid>.tmp`` next to ``path`` (hidden; same filesystem, so the rename is atomic)."""
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str], *, fsync: bool = False) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it to ``path`` when the block succeeds.

    The suffix of ``path`` is kept at the end of the temporary name (``.x.csv.123.tmp.csv``) so
    that writers that pick a format from the suffix (matplotlib) still work.
    """
    path = Path(path)
    tmp = tmp_name(path).with_suffix(".tmp" + path.suffix) if path.suffix else tmp_name(path)
    try:
        yield tmp
        if fsync and tmp.exists():
            fd = os.open(tmp, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes, *, fsync: bool = False) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path, fsync=fsync) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(path: str | os.PathLike[str], text: str, *, fsync: bool = False) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    atomic_write_bytes(path, text.encode("utf-8"), fsync=fsync)


def is_disk_error(exc: BaseException) -> bool:
    """True for an OSError that a full, read-only or forbidden folder raises (also when it is
    wrapped in another exception's cause or context, as pyarrow's writers do)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, OSError) and exc.errno in DISK_ERRNOS:
            return True
        text = str(exc)
        if "No space left on device" in text or "Read-only file system" in text:
            return True
        exc = exc.__cause__ or exc.__context__  # type: ignore[assignment]
    return False


def disk_error(exc: BaseException, where: str | os.PathLike[str]) -> str:
    """One line for a disk error while writing under ``where``."""
    code = None
    cur: BaseException | None = exc
    while cur is not None and code is None:
        if isinstance(cur, OSError) and cur.errno in DISK_ERRNOS:
            code = cur.errno
        cur = cur.__cause__ or cur.__context__
    text = str(exc)
    if code is None and "No space left on device" in text:
        code = errno.ENOSPC
    if code is None and "Read-only file system" in text:
        code = errno.EROFS
    reason = {
        errno.ENOSPC: "the disk is full (no space left on device)",
        errno.EDQUOT: "the disk quota is exceeded",
        errno.EROFS: "the file system is read-only",
        errno.EACCES: "permission denied",
        errno.EPERM: "operation not permitted",
        errno.EFBIG: "a file grew larger than the file system allows",
    }.get(code or 0, text.splitlines()[0] if text else type(exc).__name__)
    return f"cannot write to {where}: {reason}"
