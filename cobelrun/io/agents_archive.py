"""One archive for all agents of a job: ``agents.npz`` with a run axis.

Each state array an agent declares (:meth:`cobelrun.agents.base.Agent.get_state`) is stored
once for the whole job: ``<key>`` holds the runs' arrays raveled and concatenated (so agents
whose arrays differ in size between runs, e.g. MFEC's buffers, fit too) and ``<key>.shape``
their shapes, one row per run; ``runs`` lists the runs and ``__meta__`` holds each run's JSON
metadata (agent class, schema version, hyperparameters). No pickle anywhere.

While a job runs, agents are buffered and written in batches as complete, uncompressed npz
parts under ``.parts-agents/`` (bounded by count, bytes and time, like the tables); at the end
the parts are streamed into ``agents.npz`` (deflate level 1 where an array compresses, stored
where it does not: network weights), one array at a time, so memory stays bounded by one
batch. A job of 20,000 runs leaves one file instead of 20,000, and a killed job keeps every
batch that was written (``cobel status`` merges them).

``+agent.load_from=RUN_DIR`` picks run ``r`` (:func:`read_agent`); the arrays are checked
against the agent's declared schema like any saved agent.
"""

from __future__ import annotations

import json
import os
import shutil
import time
import zipfile
import zlib
from collections.abc import Mapping, Sequence
from copy import deepcopy
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["AgentArchive", "merge_agent_parts", "read_agent", "runs_in"]

RUNS = "runs"
META = "__meta__"
SHAPE = ".shape"


def _pack(batch: Sequence[tuple[int, Mapping[str, np.ndarray], str]]) -> dict[str, np.ndarray]:
    """Arrays of a batch of (run, state, meta JSON) in the archive layout."""
    keys = list(batch[0][1])
    out: dict[str, np.ndarray] = {
        RUNS: np.array([r for r, _, _ in batch], np.int64),
        META: np.array([m for _, _, m in batch]),
    }
    for key in keys:
        arrays = []
        for run, state, _ in batch:
            if set(state) != set(keys):
                raise ValueError(f"agent of run {run} has state keys {sorted(state)}, "
                                 f"the job's first agent {sorted(keys)}")  # fmt: skip
            arrays.append(np.asarray(state[key]))
        dtype = np.result_type(*arrays)
        out[key] = np.concatenate([a.astype(dtype, copy=False).ravel() for a in arrays])
        ndim = {a.ndim for a in arrays}
        if len(ndim) != 1:
            raise ValueError(f"state key {key!r} changes its number of dimensions between runs")
        out[key + SHAPE] = np.array([a.shape for a in arrays], np.int64).reshape(len(arrays), -1)
    return out


class AgentArchive:
    """Buffers agents' states and writes them in batches; :meth:`close` merges the batches.

    Parameters
    ----------
    path
        The final archive (``agents.npz``).
    parts_dir
        Folder for the batches while the job runs.
    flush_seconds, max_bytes
        Write a batch at least this often, or once this many bytes are buffered.
    """

    def __init__(self, path: str | os.PathLike[str], parts_dir: str | os.PathLike[str], *,
                 flush_seconds: float = 2.0, max_bytes: int = 32 << 20) -> None:  # fmt: skip
        self.path, self.parts_dir = Path(path), Path(parts_dir)
        self.flush_seconds, self.max_bytes = float(flush_seconds), int(max_bytes)
        self._pending: list[tuple[int, dict[str, np.ndarray], str]] = []
        self._bytes = 0
        self._last = time.monotonic()
        self._n_parts = 0
        self._closed = False
        self._meta: dict[str, Any] = {}
        self._meta_json: str | None = None

    def add(self, run: int, state: Mapping[str, np.ndarray], meta: Mapping[str, Any]) -> bool:
        """Buffer run ``run``'s state (copied) and metadata; True if a batch is due.

        The runs of a job mostly share their metadata (class, schema, hyperparameters), so it
        is encoded as JSON only when it differs from the previous run's (compared with a deep
        copy of that one): one ``json.dumps`` per job instead of one per agent."""
        copy = {k: np.array(v, copy=True) for k, v in state.items()}
        if self._meta_json is None or meta != self._meta:
            self._meta = deepcopy(dict(meta))
            self._meta_json = json.dumps(meta, separators=(",", ":"))
        self._pending.append((int(run), copy, self._meta_json))
        self._bytes += sum(v.nbytes for v in copy.values())
        return self._bytes >= self.max_bytes or time.monotonic() - self._last >= self.flush_seconds

    def take(self) -> list[tuple[int, dict[str, np.ndarray], str]]:
        batch, self._pending, self._bytes = self._pending, [], 0
        self._last = time.monotonic()
        return batch

    def write_batch(self, batch: Sequence[tuple[int, Mapping[str, np.ndarray], str]]) -> None:
        """Write one batch as a complete npz part (temporary name + rename)."""
        if not batch:
            return
        self.parts_dir.mkdir(parents=True, exist_ok=True)
        path = self.parts_dir / f"part-{self._n_parts:06d}.npz"
        tmp = path.with_name(f".{path.name}.tmp")
        with open(tmp, "wb") as fh:
            np.savez(fh, **_pack(batch))
        os.replace(tmp, path)
        self._n_parts += 1

    def close(self) -> None:
        """Write what is buffered and merge every batch into the archive (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self.write_batch(self.take())
        merge_agent_parts(self.parts_dir, self.path)


def merge_agent_parts(parts_dir: str | os.PathLike[str], path: str | os.PathLike[str]) -> int:
    """Stream the npz parts in ``parts_dir`` (name order) into ``path`` (temporary name +
    rename), one array of one part in memory at a time; remove the parts. Returns the number
    of agents."""
    parts_dir, path = Path(parts_dir), Path(path)
    files = sorted(parts_dir.glob("part-*.npz")) if parts_dir.is_dir() else []
    if not files:
        if parts_dir.is_dir():
            shutil.rmtree(parts_dir)
        return 0
    parts = [np.load(f, allow_pickle=False) for f in files]
    tmp = path.with_name(f".{path.name}.tmp")
    n = 0
    try:
        keys = parts[0].files
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=1,
                             allowZip64=True) as zf:  # fmt: skip
            for key in keys:
                info = [_header(f, key) for f in files]  # shapes and dtypes, no data read
                dtype = np.result_type(*(d for _, d in info))
                shape = (sum(s[0] for s, _ in info), *info[0][0][1:])
                zf.compression = _codec(_sample(files[0], key))
                with zf.open(f"{key}.npy", "w", force_zip64=True) as out:
                    header = {"descr": np.lib.format.dtype_to_descr(dtype),
                              "fortran_order": False, "shape": shape}  # fmt: skip
                    np.lib.format.write_array_header_2_0(out, header)
                    for p in parts:
                        out.write(np.ascontiguousarray(p[key], dtype=dtype).tobytes())
                if key == RUNS:
                    n = shape[0]
        os.replace(tmp, path)
    finally:
        for p in parts:
            p.close()
        if tmp.exists():
            tmp.unlink()
    shutil.rmtree(parts_dir)
    return n


#: deflate an array only if a sample of it shrinks below this fraction: network weights and
#: optimiser moments (float noise) shrink by ~7% at 10x the write time of storing them
DEFLATE_BELOW = 0.8
_SAMPLE_BYTES = 1 << 18


def _codec(sample: bytes) -> int:
    """``ZIP_DEFLATED`` for an array that compresses (Q tables, counts, buffers with zeros),
    ``ZIP_STORED`` for one that does not, judged on a sample of its data at deflate level 1."""
    if len(sample) < 4096:
        return zipfile.ZIP_DEFLATED  # small: the cost is nothing either way
    return (
        zipfile.ZIP_DEFLATED
        if len(zlib.compress(sample, 1)) < DEFLATE_BELOW * len(sample)
        else zipfile.ZIP_STORED
    )


def _header(npz: Path, key: str) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype of member ``key`` of an npz file, from its ``.npy`` header alone."""
    with zipfile.ZipFile(npz) as zf, zf.open(f"{key}.npy") as fh:
        return _read_header(fh)


def _sample(npz: Path, key: str) -> bytes:
    """The first 256 KB of member ``key``'s data (after its ``.npy`` header)."""
    with zipfile.ZipFile(npz) as zf, zf.open(f"{key}.npy") as fh:
        _read_header(fh)
        return fh.read(_SAMPLE_BYTES)


def _read_header(fh: Any) -> tuple[tuple[int, ...], np.dtype]:
    version = np.lib.format.read_magic(fh)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
    else:
        shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
    return shape, dtype


def runs_in(path: str | os.PathLike[str]) -> list[int]:
    """Runs whose agents an archive holds."""
    with np.load(path, allow_pickle=False) as data:
        return sorted(int(r) for r in data[RUNS])


def read_agent(
    path: str | os.PathLike[str], run: int
) -> tuple[dict[str, np.ndarray], dict[str, Any]] | None:
    """Run ``run``'s state arrays and metadata from an archive (None if it lacks the run).

    Raises ValueError if the archive's layout is broken (the caller names the file)."""
    with np.load(path, allow_pickle=False) as data:
        runs = data[RUNS]
        where = np.flatnonzero(runs == int(run))
        if where.size == 0:
            return None
        i = int(where[-1])
        meta = json.loads(str(data[META][i]))
        arrays: dict[str, np.ndarray] = {}
        for key in data.files:
            if key in (RUNS, META) or key.endswith(SHAPE):
                continue
            shapes = data[key + SHAPE]
            if shapes.shape[0] != runs.shape[0]:
                raise ValueError(f"{key}{SHAPE} has {shapes.shape[0]} rows for {runs.size} runs")
            sizes = np.prod(shapes, axis=1) if shapes.shape[1] else np.ones(len(shapes), np.int64)
            start = int(sizes[:i].sum())
            flat = data[key]
            if int(sizes.sum()) != flat.size:
                raise ValueError(
                    f"{key} holds {flat.size} values, its shapes say {int(sizes.sum())}"
                )
            arrays[key] = flat[start : start + int(sizes[i])].reshape(tuple(shapes[i]))
        return arrays, meta
