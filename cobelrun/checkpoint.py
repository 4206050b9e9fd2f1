"""Checkpoints inside a run: everything a stopped run needs to continue where it was.

A checkpoint is one file, ``RUN_DIR/checkpoint.npz`` (:attr:`RunFolder.checkpoint
<cobelrun.io.run_folder.RunFolder.checkpoint>`): an ``.npz`` of plain arrays (no pickle, read
with ``allow_pickle=False`` semantics) plus one JSON header member, ``__checkpoint__``:

- ``format``, ``cobel_version``, ``config_hash``: a checkpoint written by another cobel version
  or for another config is refused in one line (its state would not continue *this* run);
- ``position``: the run, the phase (index and name) and the trial within the phase where the
  run goes on, and the 1-based trial number of that trial;
- ``agent``: the agent's class and its JSON state (:meth:`Checkpointable.checkpoint_state`:
  generator states, counters, optimiser settings); the agent's arrays are the members
  ``agent/<key>`` (network weights, optimiser moments, replay memories with their sum trees,
  episodic memories, tables);
- ``env``: the environment's generator state; its world is rebuilt from the protocol (every
  phase's changes up to the position, then the trial's cycle entries);
- ``monitors``: each monitor's JSON state (e.g. the response monitor's running count);
- ``recorder``: the watermarks of what is durable (rows and parts of every table, the agents
  archive's parts, the MCAP clock): what lies beyond them belongs to trials that the resumed
  run does again, and is dropped.

The file is written to a temporary name, fsynced and renamed (:func:`write_checkpoint`), so a
kill never leaves half a checkpoint; the run folder keeps at most one. It is read back through
:func:`read_checkpoint`: the header first (small, JSON, checked), then every array's ``.npy``
header against the shapes and dtypes the restoring agent declares
(:meth:`Checkpointable.checkpoint_schema`) and against the memory available, before anything
is read. A checkpoint is data from disk: nothing in it is executed or unpickled.

Settings: ``task.checkpoint`` (:class:`CheckpointConfig`; ``conf/checkpoint/default.yaml``).
"""

from __future__ import annotations

import json
import math
import os
import time
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from cobelrun._version import __version__
from cobelrun.errors import CobelError, ConfigError

__all__ = [
    "CHECKPOINT_FORMAT",
    "HEADER_KEY",
    "Checkpoint",
    "CheckpointConfig",
    "CheckpointError",
    "Checkpointable",
    "generator_state",
    "read_checkpoint",
    "read_header",
    "set_generator_state",
    "write_checkpoint",
]

#: version of the checkpoint file layout (the header's keys and the member names)
CHECKPOINT_FORMAT = 1
#: the JSON header member of a checkpoint
HEADER_KEY = "__checkpoint__"
#: largest header accepted (a header is a few kB; this bounds what a crafted file makes us read)
MAX_HEADER_BYTES = 16 << 20
#: the exit status of a run stopped by SIGTERM/SIGUSR1 after writing its checkpoint:
#: ``EX_TEMPFAIL`` (sysexits.h), "try again later" (a SLURM script requeues on it)
REQUEUE_EXIT = 75


class CheckpointError(CobelError):
    """A checkpoint cannot continue this run (other version or config, damaged, foreign)."""


@runtime_checkable
class Checkpointable(Protocol):
    """What can be checkpointed: named arrays (checked against :meth:`checkpoint_schema` before
    they are read) and a JSON-ready state.

    :meth:`restore_checkpoint` gets arrays that already passed the schema's checks (shape,
    dtype kind, ranges, finiteness); it checks what spans several arrays or the JSON state and
    raises ``ValueError`` (nothing changed) if they do not fit.
    """

    def checkpoint_schema(self) -> Mapping[str, Any]: ...

    def checkpoint_state(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]: ...

    def restore_checkpoint(
        self, arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any]
    ) -> None: ...


# -- settings --------------------------------------------------------------------------------


@dataclass(frozen=True)
class CheckpointConfig:
    """When a run writes its checkpoint (``task.checkpoint``).

    Attributes
    ----------
    every_trials
        Write one after every N trials of a run (None: not by trials).
    every_minutes
        Write one when this many minutes passed since the last (None: not by time).
    keep
        Keep the last checkpoint when the run completes (default: removed).
    on_signal
        SIGTERM/SIGUSR1 write a checkpoint at the next trial boundary and exit with
        :data:`REQUEUE_EXIT` (true whenever checkpoints are on).
    """

    every_trials: int | None = None
    every_minutes: float | None = None
    keep: bool = False

    @property
    def enabled(self) -> bool:
        return self.every_trials is not None or self.every_minutes is not None

    @property
    def on_signal(self) -> bool:
        return self.enabled

    #: ``every_minutes`` that ``auto`` gives an agent that checkpoints by default
    AUTO_MINUTES = 10.0

    @classmethod
    def resolve(cls, node: Mapping[str, Any] | None, agent_class: Any) -> CheckpointConfig:
        """The settings of ``task.checkpoint`` for an agent of ``agent_class``: ``auto``
        checkpoints every :attr:`AUTO_MINUTES` minutes for agents whose
        ``checkpoint_by_default`` is true (the deep and episodic agents: their runs last
        minutes to hours) and not at all for the others (tabular runs take milliseconds; their
        phases are cheaper to run again than to save). ``false``/``null`` switches a key off."""
        if hasattr(node, "model_dump"):  # a validated cobelrun.schema.CheckpointSpec
            node = node.model_dump()  # type: ignore[union-attr]
        node = dict(node or {})
        unknown = sorted(set(node) - {"every_trials", "every_minutes", "keep"})
        if unknown:
            raise ConfigError(
                f"task.checkpoint.{unknown[0]} is not a setting; allowed: every_trials, "
                "every_minutes, keep"
            )
        default_on = bool(getattr(agent_class, "checkpoint_by_default", False))
        trials = node.get("every_trials", "auto")
        minutes = node.get("every_minutes", "auto")
        keep = node.get("keep", False)
        if trials == "auto":
            trials = None
        elif trials is False or trials is None:
            trials = None
        elif isinstance(trials, bool) or not isinstance(trials, int) or trials < 1:
            raise ConfigError(
                f"task.checkpoint.every_trials must be auto, null or an integer >= 1, got {trials!r}"
            )
        if minutes == "auto":
            minutes = cls.AUTO_MINUTES if default_on else None
        elif minutes is False or minutes is None:
            minutes = None
        elif (
            isinstance(minutes, bool)
            or not isinstance(minutes, int | float)
            or not math.isfinite(minutes)
            or minutes <= 0
        ):
            raise ConfigError(
                f"task.checkpoint.every_minutes must be auto, null or a number > 0, got {minutes!r}"
            )
        if not isinstance(keep, bool):
            raise ConfigError(f"task.checkpoint.keep must be true or false, got {keep!r}")
        return cls(
            every_trials=None if trials is None else int(trials),
            every_minutes=None if minutes is None else float(minutes),
            keep=keep,
        )


# -- generator states as JSON ----------------------------------------------------------------


def generator_state(rng: np.random.Generator) -> dict[str, Any]:
    """A numpy Generator's bit-generator state as JSON-ready data."""
    return _jsonable(rng.bit_generator.state)


def set_generator_state(rng: np.random.Generator, state: Any, what: str = "generator") -> None:
    """Restore :func:`generator_state` into ``rng`` (ValueError naming ``what`` if it does not
    fit: another bit generator, missing keys, out-of-range integers)."""
    own = rng.bit_generator.state
    if not isinstance(state, dict) or state.get("bit_generator") != own["bit_generator"]:
        raise ValueError(f"{what}: expected a {own['bit_generator']} state")
    try:
        rng.bit_generator.state = state
    except (ValueError, TypeError, KeyError, OverflowError) as exc:
        raise ValueError(f"{what}: not a valid {own['bit_generator']} state ({exc})") from None


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.floating):
        return float(value)
    return value


# -- the file --------------------------------------------------------------------------------


@dataclass
class Checkpoint:
    """A checkpoint in memory: the JSON header and the arrays by member name
    (``agent/<key>`` for the agent's)."""

    header: dict[str, Any]
    arrays: dict[str, np.ndarray]

    def agent_arrays(self) -> dict[str, np.ndarray]:
        return {k[len("agent/") :]: v for k, v in self.arrays.items() if k.startswith("agent/")}


def write_checkpoint(path: str | os.PathLike[str], header: Mapping[str, Any],
                     arrays: Mapping[str, np.ndarray], *, compress: bool = False) -> int:  # fmt: skip
    """Write a checkpoint atomically (temporary file, fsync, rename, fsync of the folder) and
    return its size in bytes. ``header`` gets ``format`` and ``cobel_version``. ``compress``:
    deflate the members (``numpy.savez_compressed``; read back the same way)."""
    from cobelrun.io.atomic import atomic_path

    path = Path(path)
    head = {"format": CHECKPOINT_FORMAT, "cobel_version": __version__, **header}
    if HEADER_KEY in arrays:
        raise ValueError(f"array name {HEADER_KEY!r} is reserved")
    save = np.savez_compressed if compress else np.savez
    with atomic_path(path, fsync=True) as tmp, open(tmp, "wb") as fh:
        save(fh, **{HEADER_KEY: np.array(json.dumps(head, separators=(",", ":")))},
                 **{k: np.asarray(v) for k, v in arrays.items()})  # fmt: skip
    _fsync_dir(path.parent)
    return path.stat().st_size


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def read_header(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The JSON header of a checkpoint, read alone (a CheckpointError if the file is not a
    cobel checkpoint)."""
    from cobelrun.io.validate import nbytes_of, read_npy_header

    path = Path(path)

    def fail(what: str) -> CheckpointError:
        return CheckpointError(f"cannot resume from {path}: {what}")

    try:
        with zipfile.ZipFile(path) as zf:
            member = HEADER_KEY + ".npy"
            if member not in zf.namelist():
                raise fail(f"no {HEADER_KEY!r} entry (not a cobel checkpoint)")
            with zf.open(member) as fh:
                shape, dtype = read_npy_header(fh)
                if dtype.kind != "U" or shape != ():
                    raise fail(f"{HEADER_KEY!r} is not a JSON string")
                n = nbytes_of(shape, dtype)
                if n > MAX_HEADER_BYTES:
                    raise fail(f"its header is {n:,} bytes, more than a checkpoint's header holds")
                data = fh.read(n)
    except CheckpointError:
        raise
    except FileNotFoundError:
        raise fail("no such file") from None
    except Exception as exc:  # not a zip, truncated, a bad npy header
        raise fail(f"not a readable checkpoint ({type(exc).__name__}: {exc})") from None
    if len(data) != n:
        raise fail("its header is cut short")
    try:
        header = json.loads(str(np.frombuffer(bytearray(data), dtype)[0]))
    except ValueError:
        raise fail(f"{HEADER_KEY!r} is not JSON") from None
    if not isinstance(header, dict):
        raise fail(f"{HEADER_KEY!r} is not a JSON object")
    return header


def check_header(header: Mapping[str, Any], path: Path | str, *, config_hash: str) -> None:
    """Refuse (one CheckpointError line) a checkpoint of another file format, cobel version or
    config."""
    where = f"cannot resume from {path}"
    if header.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(
            f"{where}: checkpoint format {header.get('format')!r}, this cobel reads "
            f"{CHECKPOINT_FORMAT}"
        )
    if header.get("cobel_version") != __version__:
        raise CheckpointError(
            f"{where}: it was written by cobel {header.get('cobel_version')!r}, this is "
            f"{__version__}; resume with that version, or start the run again"
        )
    if header.get("config_hash") != config_hash:
        raise CheckpointError(
            f"{where}: it was written for another config (hash "
            f"{str(header.get('config_hash'))[:12]}..., this run's is {config_hash[:12]}...); "
            "resume with the run's own config.yaml, or start the run again"
        )


def read_checkpoint(
    path: str | os.PathLike[str], specs: Mapping[str, Any], *, config_hash: str
) -> Checkpoint:
    """Read and check a checkpoint whole before returning it.

    ``specs`` maps every array member to its :class:`~cobelrun.agents.base.ArraySpec` (shape
    with ``None`` for free axes, dtype kind, value range). Checked in this order, each
    failure one :class:`CheckpointError` line naming the file: the header (format, version,
    config hash); every member's ``.npy`` header (no pickle, known name, declared shape and
    dtype kind); the total size against the memory available; then the values.
    """
    from cobelrun.io.validate import nbytes_of, read_npy_header
    from cobelrun.safety import check_allocation

    path = Path(path)
    header = read_header(path)
    check_header(header, path, config_hash=config_hash)

    def fail(what: str) -> CheckpointError:
        return CheckpointError(f"cannot resume from {path}: {what}")

    arrays: dict[str, np.ndarray] = {}
    try:
        with zipfile.ZipFile(path) as zf:
            plan = {}
            for member in zf.namelist():
                if not member.endswith(".npy"):
                    raise fail(f"member {member!r} is not an .npy array")
                key = member[: -len(".npy")]
                if key == HEADER_KEY:
                    continue
                spec = specs.get(key)
                if spec is None:
                    raise fail(f"unknown array {key!r} (written by another agent or task?)")
                with zf.open(member) as fh:
                    shape, dtype = read_npy_header(fh)
                problem = spec.header_problem(tuple(shape), dtype)
                if problem:
                    raise fail(f"array {key!r}: {problem}")
                plan[member] = (key, tuple(shape), dtype)
            missing = [k for k in specs if k + ".npy" not in plan]
            if missing:
                raise fail(f"array {missing[0]!r} is missing ({len(missing)} missing)")
            need = sum(nbytes_of(s, d) for _, s, d in plan.values())
            check_allocation(str(path), need, "the checkpoint's arrays",
                             "the file is not this run's checkpoint or is damaged")  # fmt: skip
            for member, (key, shape, dtype) in plan.items():
                with zf.open(member) as fh:
                    read_npy_header(fh)
                    n = nbytes_of(shape, dtype)
                    data = fh.read(n)
                if len(data) != n:
                    raise fail(f"array {key!r} is cut short")
                arr = np.frombuffer(bytearray(data), dtype).reshape(shape)
                problem = specs[key].problem(arr)
                if problem:
                    raise fail(f"array {key!r}: {problem}")
                arrays[key] = arr
    except CobelError:
        raise
    except Exception as exc:  # zip damage, a bad npy header, pickle refused
        raise fail(f"not a readable checkpoint ({type(exc).__name__}: {exc})") from None
    return Checkpoint(header=header, arrays=arrays)


def agent_specs(agent: Any) -> dict[str, Any]:
    """The member specs of an agent's arrays in a checkpoint (``agent/<key>``)."""
    return {f"agent/{k}": v for k, v in agent.checkpoint_schema().items()}


def agent_entry(agent: Any) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """An agent's checkpoint arrays (as members) and its header entry."""
    if not isinstance(agent, Checkpointable):
        raise CobelError(f"agent {type(agent).__name__} cannot be checkpointed")
    arrays, meta = agent.checkpoint_state()
    return ({f"agent/{k}": v for k, v in arrays.items()},
            {"class": f"{type(agent).__module__}.{type(agent).__qualname__}", "state": meta})  # fmt: skip


def restore_agent(agent: Any, checkpoint: Checkpoint, path: Path | str) -> None:
    """Restore an agent from a checked checkpoint (a CheckpointError line if it does not fit)."""
    entry = checkpoint.header.get("agent")
    name = f"{type(agent).__module__}.{type(agent).__qualname__}"
    if not isinstance(entry, dict) or entry.get("class") != name:
        got = entry.get("class") if isinstance(entry, dict) else None
        raise CheckpointError(
            f"cannot resume from {path}: it holds agent {got!r}, expected {name!r}"
        )
    try:
        agent.restore_checkpoint(checkpoint.agent_arrays(), entry.get("state") or {})
    except ValueError as exc:
        raise CheckpointError(f"cannot resume from {path}: agent state: {exc}") from None


def env_state(env: Any) -> dict[str, Any]:
    """The JSON state of an environment between trials: its generator (its world is rebuilt
    from the protocol)."""
    return {"np_random": generator_state(env.unwrapped.np_random)}


def restore_env(env: Any, state: Mapping[str, Any]) -> None:
    """Restore :func:`env_state` (ValueError if it does not fit)."""
    if not isinstance(state, Mapping):
        raise ValueError("env: expected a mapping")
    set_generator_state(env.unwrapped.np_random, state.get("np_random"), "env generator")


def now() -> float:
    """The clock of ``every_minutes`` (monotonic seconds)."""
    return time.monotonic()


# -- a run's checkpoints (the run loop's side) -------------------------------------------------


@dataclass(frozen=True)
class Position:
    """Where a run goes on: run ``run``, phase index ``phase`` (its trial ``k``, 0-based) whose
    first trial is trial ``first`` of the run (1-based). ``k = phase = 0``: the run's start."""

    run: int
    phase: int = 0
    k: int = 0
    first: int = 1

    def to_json(self) -> dict[str, int]:
        return {"run": self.run, "phase": self.phase, "k": self.k, "first": self.first}

    @classmethod
    def from_json(cls, data: Any, protocol: Any, runs: int) -> Position:
        """Checked against the task: a position outside its runs, phases or trials is a
        ValueError."""
        if not isinstance(data, dict) or set(data) != {"run", "phase", "k", "first"}:
            raise ValueError("position: expected {run, phase, k, first}")
        if not all(isinstance(v, int) and not isinstance(v, bool) for v in data.values()):
            raise ValueError("position: expected integers")
        pos = cls(**data)
        phases = protocol.phases
        if not 0 <= pos.run < runs or not 0 <= pos.phase < len(phases):
            raise ValueError(f"position {pos.to_json()} is outside the task's runs and phases")
        first = 1 + sum(p.trials for p in phases[: pos.phase])
        if pos.first != first or not 0 <= pos.k < phases[pos.phase].trials:
            raise ValueError(f"position {pos.to_json()} is outside the phase's trials")
        return pos


class RunCheckpoints:
    """A run folder's checkpoints, as the run loop writes and reads them.

    Parameters
    ----------
    folder
        The run folder (:class:`~cobelrun.io.run_folder.RunFolder`).
    config
        When to write them.
    config_hash
        The run's config hash (a checkpoint of another config is refused).
    guard
        The run's :class:`~cobelrun.signals.SignalGuard`: a stop it was asked for is carried
        out at the next boundary (:meth:`boundary`).
    """

    def __init__(self, folder: Any, config: CheckpointConfig, config_hash: str,
                 guard: Any = None) -> None:  # fmt: skip
        self.folder, self.config, self.config_hash = folder, config, config_hash
        self.guard = guard
        self._last = now()
        self._trials = 0
        #: the checkpoint a resumed run started from (its header; None for a new run)
        self.resumed: dict[str, Any] | None = None
        #: sizes (bytes) of the checkpoints written by this process
        self.sizes: list[int] = []

    # -- resuming ------------------------------------------------------------------------------
    def open_resume(self) -> dict[str, Any]:
        """The header of the run folder's checkpoint, checked (format, version, config)."""
        path = self.folder.checkpoint
        if not path.is_file():
            raise CheckpointError(
                f"cannot resume {self.folder.path}: it has no checkpoint ({path.name}); "
                "task.checkpoint.every_trials/every_minutes write one"
            )
        header = read_header(path)
        check_header(header, path, config_hash=self.config_hash)
        self.resumed = header
        return header

    def restore(self, agent: Any, env: Any, monitors: list[Any], run: int) -> bool:
        """Restore ``run``'s agent, environment generator and monitors from the checkpoint
        the run resumes from, if it holds that run's state (True), else False (the run starts
        afresh). A CheckpointError line if it does not fit."""
        header = self.resumed
        if header is None or header.get("agent") is None or header["position"]["run"] != run:
            return False
        path = self.folder.checkpoint
        found = read_checkpoint(path, agent_specs(agent), config_hash=self.config_hash)
        restore_agent(agent, found, path)
        states = header.get("monitors")
        try:
            restore_env(env, header.get("env") or {})
            if not isinstance(states, list) or len(states) != len(monitors):
                raise ValueError(f"monitors: expected {len(monitors)} states")
            for m, state in zip(monitors, states, strict=True):
                m.resume_run(run, agent, state)
        except ValueError as exc:
            raise CheckpointError(f"cannot resume from {path}: {exc}") from None
        return True

    # -- writing -------------------------------------------------------------------------------
    def due(self, trials: int) -> bool:
        """Whether a checkpoint is due after ``trials`` more trials (or a stop was asked for)."""
        self._trials += trials
        if self.guard is not None and self.guard.stop_requested is not None:
            return True
        c = self.config
        return (c.every_trials is not None and self._trials >= c.every_trials) or (
            c.every_minutes is not None and now() - self._last >= 60.0 * c.every_minutes
        )

    def chunk(self, run: int) -> dict[str, Any] | None:
        """The header of the checkpoint a resumed batched chunk starting at run ``run`` goes
        on from, if it was written inside that chunk (None: the chunk starts afresh)."""
        header = self.resumed
        if header is None or header.get("agent") is None or header["position"]["run"] != run:
            return None
        return header

    def save(self, position: Position, recorder: Any, *, agent: Any = None, env: Any = None,
             monitors: list[Any] | None = None,
             chunk: tuple[Any, dict[str, np.ndarray], dict[str, Any]] | None = None) -> int:  # fmt: skip
        """Write the checkpoint of ``position``: the recorder's watermarks (after making its
        rows durable) and, inside a run, the agent, the env's generator and the monitors;
        inside a batched chunk (``chunk``: its learner, more arrays and the header's
        ``batch`` entry; :meth:`cobelrun.batched.BatchedRuns.save`) the batched learner as
        the agent, and every run's env generator, monitors and rows held back.
        Returns its size in bytes."""
        arrays: dict[str, np.ndarray] = {}
        header: dict[str, Any] = {"config_hash": self.config_hash,
                                  "position": position.to_json(), "agent": None}  # fmt: skip
        if agent is not None:
            arrays, header["agent"] = agent_entry(agent)
            header["env"] = env_state(env)
            header["monitors"] = [m.checkpoint_state() for m in monitors or []]
        elif chunk is not None:
            learner, more, header["batch"] = chunk
            arrays, header["agent"] = agent_entry(learner)
            clash = set(arrays) & set(more)
            if clash:
                raise ValueError(f"array names {sorted(clash)[:3]} used twice")
            arrays.update(more)
        header["recorder"] = recorder.durable()
        header["written_unix"] = time.time()
        # a chunk's held-back rows (e.g. activity maps: long tables of repeated grid
        # coordinates) deflate ~5x at ~15 ms per MB; a run's own state is written as it is
        size = write_checkpoint(self.folder.checkpoint, header, arrays,
                                compress=chunk is not None)  # fmt: skip
        self.sizes.append(size)
        self._last, self._trials = now(), 0
        return size

    def stop_if_asked(self) -> None:
        """After a checkpoint: stop the run if a signal asked for it (:class:`Stopped`)."""
        if self.guard is not None and self.guard.stop_requested is not None:
            from cobelrun.signals import Stopped

            raise Stopped(self.guard.stop_requested, self.folder.checkpoint)

    def finish(self) -> None:
        """The run completed: remove its checkpoint unless ``keep``."""
        if not self.config.keep:
            self.folder.checkpoint.unlink(missing_ok=True)
