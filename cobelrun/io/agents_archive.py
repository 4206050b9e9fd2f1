"""One archive for all agents of a job: ``agents.zip``.

Each member is one run's agent exactly as :meth:`cobelrun.agents.base.Agent.save` would write
it (an npz, compressed), named ``run_0007.npz``; the archive itself stores the members as they
are. While a job runs, agents are buffered and written in batches as complete zip parts under
``.parts-agents/`` (bounded by count, bytes and time, like the tables); at the end the parts
are merged into ``agents.zip``, so a job of 20,000 runs leaves one file instead of 20,000, and
a killed job keeps every batch that was written (``cobel status`` merges them).

``+agent.load_from=RUN_DIR`` picks run ``r``'s member; it is checked against the agent's
declared schema like any saved agent.
"""

from __future__ import annotations

import os
import shutil
import time
import zipfile
from collections.abc import Sequence
from pathlib import Path

__all__ = ["AgentArchive", "member_name", "merge_agent_parts", "read_agent", "runs_in"]


def member_name(run: int) -> str:
    return f"run_{int(run):04d}.npz"


def _write_zip(path: Path, members: Sequence[tuple[str, bytes]]) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
        for name, data in members:
            zf.writestr(name, data)
    os.replace(tmp, path)


class AgentArchive:
    """Buffers agents (as bytes) and writes them in batches; :meth:`close` merges the batches.

    Parameters
    ----------
    path
        The final archive (``agents.zip``).
    parts_dir
        Folder for the batches while the job runs.
    flush_seconds, max_bytes
        Write a batch at least this often, or once this many bytes are buffered.
    """

    def __init__(self, path: str | os.PathLike[str], parts_dir: str | os.PathLike[str], *,
                 flush_seconds: float = 2.0, max_bytes: int = 32 << 20) -> None:  # fmt: skip
        self.path, self.parts_dir = Path(path), Path(parts_dir)
        self.flush_seconds, self.max_bytes = float(flush_seconds), int(max_bytes)
        self._pending: list[tuple[str, bytes]] = []
        self._bytes = 0
        self._last = time.monotonic()
        self._n_parts = 0
        self.saved = 0
        self._closed = False

    def add(self, run: int, data: bytes) -> bool:
        """Buffer run ``run``'s agent; True if a batch is due (call :meth:`flush`)."""
        self._pending.append((member_name(run), data))
        self._bytes += len(data)
        return self._bytes >= self.max_bytes or time.monotonic() - self._last >= self.flush_seconds

    def take(self) -> list[tuple[str, bytes]]:
        batch, self._pending, self._bytes = self._pending, [], 0
        self._last = time.monotonic()
        return batch

    def write_batch(self, batch: Sequence[tuple[str, bytes]]) -> None:
        """Write one batch as a complete zip part (temporary name + rename)."""
        if not batch:
            return
        self.parts_dir.mkdir(parents=True, exist_ok=True)
        _write_zip(self.parts_dir / f"part-{self._n_parts:06d}.zip", batch)
        self._n_parts += 1
        self.saved += len(batch)

    def close(self) -> None:
        """Write what is buffered and merge every batch into the archive (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self.write_batch(self.take())
        merge_agent_parts(self.parts_dir, self.path)


def merge_agent_parts(parts_dir: str | os.PathLike[str], path: str | os.PathLike[str]) -> int:
    """Merge the zip parts in ``parts_dir`` (name order; a later member of the same run wins)
    into ``path`` (temporary name + rename), then remove them. Returns the number of agents."""
    parts_dir, path = Path(parts_dir), Path(path)
    parts = sorted(parts_dir.glob("part-*.zip")) if parts_dir.is_dir() else []
    if not parts:
        if parts_dir.is_dir():
            shutil.rmtree(parts_dir)
        return 0
    members: dict[str, bytes] = {}
    for part in parts:
        try:
            with zipfile.ZipFile(part) as zf:
                for name in zf.namelist():
                    members[name] = zf.read(name)
        except zipfile.BadZipFile:
            continue  # not possible for a renamed part; skip rather than lose the rest
    _write_zip(path, sorted(members.items()))
    shutil.rmtree(parts_dir)
    return len(members)


def runs_in(path: str | os.PathLike[str]) -> list[int]:
    """Runs whose agents an archive holds."""
    with zipfile.ZipFile(path) as zf:
        return sorted(
            int(n[4:-4]) for n in zf.namelist() if n.startswith("run_") and n.endswith(".npz")
        )


def read_agent(path: str | os.PathLike[str], run: int) -> bytes | None:
    """Run ``run``'s saved agent from an archive (None if the archive lacks it)."""
    with zipfile.ZipFile(path) as zf:
        try:
            return zf.read(member_name(run))
        except KeyError:
            return None
