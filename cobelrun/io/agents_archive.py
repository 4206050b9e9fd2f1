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
import math
import os
import shutil
import time
import zipfile
import zlib
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from copy import deepcopy
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["AgentArchive", "iter_agents", "merge_agent_parts", "read_agent", "runs_in"]

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
        self._n_agents = 0
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
        self._n_agents += len(batch)

    @property
    def durable(self) -> int:
        """Agents written in parts so far (buffered ones not counted)."""
        return self._n_agents

    def resume(self, agents: int) -> None:
        """Start from the first ``agents`` agents the run folder already holds (a checkpoint's
        watermark): the finished archive of a stopped job (written again as the first part)
        or the parts of a killed one (kept; later ones removed). ValueError if it holds
        fewer."""
        agents = int(agents)
        files = sorted(self.parts_dir.glob("part-*.npz")) if self.parts_dir.is_dir() else []
        if self.path.is_file() and len(runs_in(self.path)) >= agents:
            if self.parts_dir.is_dir():
                shutil.rmtree(self.parts_dir)
            if agents:
                with np.load(self.path, allow_pickle=False) as npz:
                    first = _first_agents({k: npz[k] for k in npz.files}, agents)
                self._write_packed(first, agents)
            return
        for k, f in enumerate(files):
            if self._n_agents >= agents:
                f.unlink()
                continue
            if f.name != f"part-{k:06d}.npz":
                raise ValueError(f"{self.parts_dir}: part {f.name} is out of sequence")
            with np.load(f, allow_pickle=False) as npz:
                n = len(npz[RUNS])
                if self._n_agents + n > agents:
                    packed = _first_agents({k: npz[k] for k in npz.files}, agents - self._n_agents)
                else:
                    packed = None
            if packed is not None:
                f.unlink()
                self._write_packed(packed, agents - self._n_agents)
            else:
                self._n_parts += 1
                self._n_agents += n
        if self._n_agents < agents:
            raise ValueError(
                f"{self.path.name}: the run folder holds {self._n_agents} agents, the "
                f"checkpoint {agents}"
            )

    def _write_packed(self, packed: Mapping[str, np.ndarray], n: int) -> None:
        self.parts_dir.mkdir(parents=True, exist_ok=True)
        path = self.parts_dir / f"part-{self._n_parts:06d}.npz"
        tmp = path.with_name(f".{path.name}.tmp")
        with open(tmp, "wb") as fh:
            np.savez(fh, **packed)
        os.replace(tmp, path)
        self._n_parts += 1
        self._n_agents += n

    def close(self) -> None:
        """Write what is buffered and merge every batch into the archive (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self.write_batch(self.take())
        merge_agent_parts(self.parts_dir, self.path)


def _first_agents(packed: Mapping[str, np.ndarray], n: int) -> dict[str, np.ndarray]:
    """The first ``n`` agents of arrays in the archive layout (:func:`_pack`)."""
    out = {RUNS: packed[RUNS][:n], META: packed[META][:n]}
    for key, value in packed.items():
        if key in (RUNS, META) or key.endswith(SHAPE):
            continue
        shapes = packed[key + SHAPE][:n]
        size = int(np.prod(shapes, axis=1).sum()) if len(shapes) else 0
        out[key] = value[:size]
        out[key + SHAPE] = shapes
    return out


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
    with zipfile.ZipFile(path) as zf:
        return sorted(int(r) for r in _small(zf, RUNS, "iu", 1))


#: largest bookkeeping member (runs, metadata, shapes) of an archive cobel reads
SMALL_BYTES = 64 << 20
#: bytes read at a time while skipping to a run's values inside a member
_CHUNK = 1 << 20

#: ``check(key, shape, dtype)``: what is wrong with a state array of this shape and dtype
#: (one phrase), or None; called before the array is read
HeaderCheck = Callable[[str, tuple[int, ...], np.dtype], "str | None"]


def _small(zf: zipfile.ZipFile, key: str, kinds: str, ndim: int) -> np.ndarray:
    """A bookkeeping member, its header checked (dtype kind, dimensions, size) before it is
    read."""
    from cobelrun.io.validate import nbytes_of, read_npy_header

    if f"{key}.npy" not in zf.namelist():
        raise ValueError(f"no {key!r} member (not a cobel agents archive)")
    with zf.open(f"{key}.npy") as fh:
        shape, dtype = read_npy_header(fh)
        if dtype.kind not in kinds or len(shape) != ndim:
            raise ValueError(f"member {key!r} is {dtype} with shape {shape}")
        if nbytes_of(shape, dtype) > SMALL_BYTES:
            raise ValueError(f"member {key!r} claims {nbytes_of(shape, dtype):,} bytes")
        data = fh.read(nbytes_of(shape, dtype))
    if len(data) != nbytes_of(shape, dtype):
        raise ValueError(f"member {key!r} is cut short")
    return np.frombuffer(data, dtype).reshape(shape)


def _slice(zf: zipfile.ZipFile, key: str, start: int, count: int, dtype: np.dtype) -> np.ndarray:
    """Values ``start`` to ``start + count`` of a flat member, streamed: what comes before is
    read and dropped in 1 MB pieces, so memory holds one run's array."""
    from cobelrun.io.validate import read_npy_header

    with zf.open(f"{key}.npy") as fh:
        read_npy_header(fh)
        skip = start * dtype.itemsize
        while skip:
            got = len(fh.read(min(skip, _CHUNK)))
            if not got:
                raise ValueError(f"member {key!r} is cut short")
            skip -= got
        want = count * dtype.itemsize
        buf = bytearray(want)
        view, pos = memoryview(buf), 0
        while pos < want:
            got = fh.readinto(view[pos:]) if hasattr(fh, "readinto") else 0
            if not got:
                raise ValueError(f"member {key!r} is cut short")
            pos += got
    return np.frombuffer(buf, dtype)


def read_agent(
    path: str | os.PathLike[str], run: int, check: HeaderCheck | None = None
) -> tuple[dict[str, np.ndarray], dict[str, Any]] | None:
    """Run ``run``'s state arrays and metadata from an archive (None if it lacks the run).

    Nothing is read before it is checked: every member's shape and dtype come from its
    ``.npy`` header (:func:`cobelrun.io.validate.read_npy_header`), the run's shapes from
    ``<key>.shape``, and each array is checked by ``check`` (the agent's declared schema) and
    against the memory available (:func:`cobelrun.safety.check_allocation`) before its values
    are streamed out of the archive (one run's array in memory, not the whole member).
    Raises ValueError if the archive's layout is broken (the caller names the file), a
    ConfigError when an array does not fit the schema or the memory.
    """
    from cobelrun.safety import check_allocation

    with zipfile.ZipFile(path) as zf:
        runs = _small(zf, RUNS, "iu", 1)
        where = np.flatnonzero(runs == int(run))
        if where.size == 0:
            return None
        i = int(where[-1])
        metas = _small(zf, META, "U", 1)
        if metas.shape[0] != runs.shape[0]:
            raise ValueError(f"{META} has {metas.shape[0]} rows for {runs.size} runs")
        meta = json.loads(str(metas[i]))
        if not isinstance(meta, dict):
            raise ValueError(f"{META} of run {run} is not a JSON object")
        plan: dict[str, tuple[int, int, tuple[int, ...], np.dtype]] = {}
        for key, (rows, sizes, dtype) in _plan(zf, runs).items():
            problem = check(key, rows[i], dtype) if check is not None else None
            if problem:
                from cobelrun.errors import ConfigError

                raise ConfigError(f"key {key!r}: {problem}")
            plan[key] = (sum(sizes[:i]), sizes[i], rows[i], dtype)
        need = sum(n * d.itemsize for _, n, _, d in plan.values())
        check_allocation(f"{path} (run {run})", need, "the saved agent's arrays",
                         "this archive was not written for this machine or is damaged")  # fmt: skip
        arrays = {key: _slice(zf, key, start, n, dtype).reshape(shape)
                  for key, (start, n, shape, dtype) in plan.items()}  # fmt: skip
        return arrays, meta


def iter_agents(
    path: str | os.PathLike[str], runs: Collection[int], check: HeaderCheck | None = None
) -> Iterator[tuple[int, dict[str, np.ndarray], dict[str, Any]]]:
    """(run, state arrays, metadata) of every agent in an archive whose run is in ``runs``,
    in one pass over each member (one run's arrays in memory at a time): checking all the
    agents of a 20,000-run job reads the archive once, where :func:`read_agent` per run would
    decompress each member up to that run again. Headers, shapes and ``check`` as
    :func:`read_agent`, for every listed run before any value is read."""
    from cobelrun.safety import check_allocation

    wanted = {int(r) for r in runs}
    with zipfile.ZipFile(path) as zf:
        runs_arr = _small(zf, RUNS, "iu", 1)
        metas = _small(zf, META, "U", 1)
        if metas.shape[0] != runs_arr.shape[0]:
            raise ValueError(f"{META} has {metas.shape[0]} rows for {runs_arr.size} runs")
        plan = _plan(zf, runs_arr)
        picked = [i for i, r in enumerate(runs_arr.tolist()) if int(r) in wanted]
        for i in picked:
            for key, (rows, _, dtype) in plan.items():
                problem = check(key, rows[i], dtype) if check is not None else None
                if problem:
                    from cobelrun.errors import ConfigError

                    raise ConfigError(f"key {key!r} of run {int(runs_arr[i])}: {problem}")
        if picked:
            need = max(sum(math.prod(rows[i]) * d.itemsize for rows, _, d in plan.values())
                       for i in picked)  # fmt: skip
            check_allocation(str(path), need, "one saved agent's arrays",
                             "this archive was not written for this machine or is damaged")  # fmt: skip
        streams = {key: _open_values(zf, key) for key in plan}
        try:
            last = picked[-1] if picked else -1
            for i in range(last + 1):
                arrays = {}
                for key, (rows, sizes, dtype) in plan.items():
                    data = _read_exact(streams[key], sizes[i] * dtype.itemsize, key)
                    arrays[key] = np.frombuffer(data, dtype).reshape(rows[i])
                if int(runs_arr[i]) in wanted:
                    meta = json.loads(str(metas[i]))
                    if not isinstance(meta, dict):
                        raise ValueError(f"{META} of run {int(runs_arr[i])} is not a JSON object")
                    yield int(runs_arr[i]), arrays, meta
        finally:
            for fh in streams.values():
                fh.close()


def _plan(
    zf: zipfile.ZipFile, runs: np.ndarray
) -> dict[str, tuple[list[tuple[int, ...]], list[int], np.dtype]]:
    """Per state key: every run's shape, its number of values and the dtype, from the
    ``<key>.shape`` members and the headers (nothing else read)."""
    from cobelrun.io.validate import read_npy_header

    out = {}
    for name in zf.namelist():
        if not name.endswith(".npy"):
            continue
        key = name[: -len(".npy")]
        if key in (RUNS, META) or key.endswith(SHAPE):
            continue
        shapes = _small(zf, key + SHAPE, "iu", 2)
        if shapes.shape[0] != runs.shape[0]:
            raise ValueError(f"{key}{SHAPE} has {shapes.shape[0]} rows for {runs.size} runs")
        rows = [tuple(int(n) for n in r) for r in shapes.tolist()]
        if any(n < 0 for r in rows for n in r):
            raise ValueError(f"{key}{SHAPE} holds a negative size")
        sizes = [math.prod(r) for r in rows]
        with zf.open(name) as fh:
            flat_shape, dtype = read_npy_header(fh)
        if len(flat_shape) != 1 or flat_shape[0] != sum(sizes):
            raise ValueError(f"{key} holds {flat_shape} values, its shapes say {sum(sizes)}")
        if dtype.kind not in "biuf":
            raise ValueError(f"{key} holds {dtype}, not numbers")
        out[key] = (rows, sizes, dtype)
    return out


def _open_values(zf: zipfile.ZipFile, key: str) -> Any:
    """Member ``key`` opened just past its ``.npy`` header."""
    from cobelrun.io.validate import read_npy_header

    fh = zf.open(f"{key}.npy")
    read_npy_header(fh)
    return fh


def _read_exact(fh: Any, n: int, key: str) -> bytearray:
    buf = bytearray(n)
    view, pos = memoryview(buf), 0
    while pos < n:
        got = fh.readinto(view[pos:])
        if not got:
            raise ValueError(f"member {key!r} is cut short")
        pos += got
    return buf
