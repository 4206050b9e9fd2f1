"""The per-step tables' writer process: a child forked by the recorder that builds and writes
the step tables, fed through shared-memory slots (``mmap``) so its work never holds the
simulation's GIL.

:class:`StepWriterProcess` is the parent's side (fork, slots, sending, errors, close);
``_step_child`` the child's loop. What is written is the recorder's business: the child calls
the ``write`` and ``finish`` callables it was forked with (:class:`cobelrun.recorder.RunRecorder`
routes the rows). ``record.step_writer: process`` selects it (Linux, main thread).
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import os
import pickle
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import pyarrow as pa

from cobelrun.monitors import BatchInfo
from cobelrun.records import TrialBatch
from cobelrun.safety import trim_memory

__all__ = ["StepWriterProcess"]


class StepWriterProcess:
    """The per-step tables built and written in a child process.

    The child is forked when the recorder starts (before its writer thread exists), so it has
    the recorder's monitors, env and step-table writers as they are then, and owns those
    writers from then on. Batches travel through shared memory mapped before the fork:
    ``SLOTS`` slots of ``SLOT_BYTES``; the simulation joins a flush's batches straight into a
    free slot (one copy) and sends the slot's number and the batch's layout (a small pickle,
    arrays out of band) through a socket; the child copies the arrays out, hands the slot
    back, and calls ``write(batch, info)`` (the recorder builds the rows and writes them: parts
    and Parquet, as its writer thread would); ``close`` has it call ``finish(table)`` for each
    table. Its work holds its own GIL, never the simulation's.
    A flush larger than a slot goes through the socket instead. ``close`` waits for the child
    to finish the tables. The child ignores SIGINT/SIGTERM (the parent stops the run and closes
    it) and dies with the parent (``PR_SET_PDEATHSIG``): a SIGKILLed run leaves parts, as
    before. An error in the child (a full disk) is raised in the parent at the next send or at
    ``close``.
    """

    SLOTS = 3
    #: a joined flush of 131,072 steps (RunRecorder.JOIN_STEPS) is ~4.3 MB
    SLOT_BYTES = 12 << 20

    def __init__(
        self,
        tables: list[str],
        write: Callable[[TrialBatch, BatchInfo], None],
        finish: Callable[[str], None],
    ) -> None:
        import mmap
        import multiprocessing

        ctx = multiprocessing.get_context("fork")
        self._conn, child = ctx.Pipe(duplex=True)
        self.tables = tables
        self.cpu_s = 0.0
        #: the child's own memory (not shared with the parent) when it closed, MB
        self.private_mb: float | None = None
        self._closed = False
        self._shm = mmap.mmap(-1, self.SLOTS * self.SLOT_BYTES)  # MAP_SHARED | MAP_ANONYMOUS
        self._free = list(range(self.SLOTS))
        self._proc = ctx.Process(target=_step_child,
                                 args=(write, finish, child, tables, os.getpid(), self._shm),
                                 name="cobel-steps", daemon=True)  # fmt: skip
        # the parent's objects out of the child's garbage collections: a collection writes to
        # every object it scans, and each write copies a shared page (the Python docs' advice
        # for fork without exec)
        gc.freeze()
        try:
            self._proc.start()
        finally:
            gc.unfreeze()
        child.close()

    def submit(self, batches: list[tuple[TrialBatch, BatchInfo]]) -> None:
        """Join ``batches`` into a free slot and tell the child."""
        self._read_reports(block=False)
        parts = [b for b, _ in batches]
        info = dataclasses.replace(
            BatchInfo.joined([i for _, i in batches], [b.n_trials for b, _ in batches]), env=None
        )
        slot = None
        if sum(_nbytes(b) for b in parts) + 32 * _Arena.ALIGN <= self.SLOT_BYTES:
            while not self._free:  # the child is SLOTS flushes behind: wait for it
                self._read_reports(block=True)
            slot = self._free.pop()
            view = np.frombuffer(self._shm, np.uint8, self.SLOT_BYTES, slot * self.SLOT_BYTES)
            joined = TrialBatch.concat(parts, alloc=_Arena(view))
        else:
            joined = TrialBatch.concat(parts) if len(parts) > 1 else parts[0]
        try:
            _send(self._conn, ("write", joined, info), slot, self._shm)
        except (BrokenPipeError, EOFError, ConnectionResetError):
            self._read_reports(block=False)
            raise RuntimeError(
                f"the step writer process ended unexpectedly (exit code {self._proc.exitcode})"
            ) from None

    def _read_reports(self, block: bool) -> None:
        """Take the child's messages: freed slots, errors (raised here)."""
        while block or self._conn.poll():
            kind, value = self._conn.recv()
            if kind == "error":
                raise value
            if kind == "free":
                self._free.append(value)
                block = False

    def close(self) -> None:
        """Have the child finish the step tables; raise its first error."""
        if self._closed:
            return
        self._closed = True
        try:
            _send(self._conn, ("close",), None, self._shm)
            error = None
            while True:
                kind, value = self._conn.recv()
                if kind == "error":
                    error = error or value
                elif kind == "closed":
                    self.cpu_s, self.private_mb = float(value["cpu_s"]), value["private_mb"]
                    break
            if error is not None:
                raise error
        except (BrokenPipeError, EOFError, ConnectionResetError):
            raise RuntimeError(
                f"the step writer process ended unexpectedly (exit code {self._proc.exitcode}); "
                "its parts are on disk: `cobel status RUN_DIR` merges them"
            ) from None
        finally:
            self._conn.close()
            self._proc.join(timeout=60)
            with contextlib.suppress(BufferError):  # a view still alive: the GC unmaps it
                self._shm.close()


class _Arena:
    """Arrays carved from one buffer (a shared-memory slot)."""

    ALIGN = 64

    def __init__(self, buf: np.ndarray) -> None:
        self._buf = buf
        self._used = 0

    def __call__(self, shape: tuple[int, ...], dtype: Any) -> np.ndarray:
        dtype = np.dtype(dtype)
        start = -(-self._used // self.ALIGN) * self.ALIGN
        n = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        if start + n > self._buf.nbytes:  # not after _nbytes said it fits; a fresh array then
            return np.empty(shape, dtype)
        self._used = start + n
        return self._buf[start : start + n].view(dtype).reshape(shape)


def _nbytes(batch: TrialBatch) -> int:
    """Bytes of a batch's arrays."""
    arrays = [v for v in vars(batch).values() if isinstance(v, np.ndarray)]
    return sum(a.nbytes for a in arrays) + sum(v.nbytes for v in batch.extra.values())


def _send(conn: Any, message: tuple[Any, ...], slot: int | None, shm: Any) -> None:
    """Pickle ``message`` with its arrays out of band: those in the shared memory as
    (offset, size), the others sent after the header as they are in memory."""
    buffers: list[pickle.PickleBuffer] = []
    head = pickle.dumps(message, protocol=5, buffer_callback=buffers.append)
    base = np.frombuffer(shm, np.uint8).ctypes.data
    where: list[tuple[int, int] | None] = []
    inline = []
    for buf in buffers:
        raw = buf.raw()
        addr = np.frombuffer(raw, np.uint8).ctypes.data if raw.nbytes else 0
        if slot is not None and raw.nbytes and base <= addr < base + len(shm):
            where.append((addr - base, raw.nbytes))
        else:
            where.append(None)
            inline.append(raw)
    conn.send_bytes(pickle.dumps((slot, where)))
    conn.send_bytes(head)
    for raw in inline:
        conn.send_bytes(raw)


def _receive(conn: Any, shm: Any) -> tuple[tuple[Any, ...], int | None]:
    """A message of :func:`_send`, its arrays copied out of the shared memory (the slot can be
    reused at once), and the slot it used."""
    slot, where = pickle.loads(conn.recv_bytes())
    head = conn.recv_bytes()
    buffers = [
        conn.recv_bytes() if w is None else bytearray(shm[w[0] : w[0] + w[1]]) for w in where
    ]
    return pickle.loads(head, buffers=buffers), slot


def _private_mb() -> float | None:
    """This process's private memory in MB (``/proc/self/smaps_rollup``; None elsewhere)."""
    try:
        with open("/proc/self/smaps_rollup", encoding="ascii") as fh:
            kb = sum(int(line.split()[1]) for line in fh if line.startswith("Private_"))
    except (OSError, ValueError, IndexError):
        return None
    return round(kb / 1024, 1)


def _step_child(
    write: Callable[[TrialBatch, BatchInfo], None],
    finish: Callable[[str], None],
    conn: Any,
    tables: list[str],
    parent: int,
    shm: Any,
) -> None:
    """The step writer process (see :class:`StepWriterProcess`)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent:  # the parent died before the line above
        os._exit(1)
    try:  # Arrow's allocator hands freed pages back at once (its default keeps them 1 s+)
        pa.jemalloc_set_decay_ms(0)
    except NotImplementedError:  # another allocator
        pass
    failed = False
    trimmed = time.monotonic()
    while True:
        if time.monotonic() - trimmed >= 1.0:
            trim_memory()
            trimmed = time.monotonic()
        try:
            (kind, *payload), slot = _receive(conn, shm)
        except (EOFError, OSError):  # the parent is gone: leave the parts, as a kill would
            os._exit(1)
        if slot is not None:
            conn.send(("free", slot))
        if kind == "write":
            if failed:
                continue
            batch, info = payload
            try:
                write(batch, info)
            except BaseException as exc:  # a full disk: the parent raises it
                failed = True
                conn.send(("error", exc))
            continue
        for name in tables:  # close: every table is finished even when another one fails
            try:
                finish(name)
            except BaseException as exc:
                if not failed:
                    failed = True
                    conn.send(("error", exc))
        conn.send(("closed", {"cpu_s": time.process_time(), "private_mb": _private_mb()}))
        os._exit(0)  # no atexit handlers, no inherited buffers flushed
