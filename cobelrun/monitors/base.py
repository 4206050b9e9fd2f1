"""The monitor protocol: :class:`Monitor` (its lifecycle), the tables it declares
(:class:`Table`), where a batch belongs (:class:`BatchInfo`), the paths it may draw
(:class:`ScenePath`) and maps it may show (:class:`SceneGrid`), and :class:`TrialColumnsMonitor`, the base of monitors that add columns to
the ``trials`` table. The lifecycle is described in :mod:`cobelrun.monitors`."""

from __future__ import annotations

import abc
import copy
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import pyarrow as pa

from cobelrun.envs.base import require
from cobelrun.records import TrialBatch

__all__ = [
    "PATH_KINDS",
    "ROW_KINDS",
    "BatchInfo",
    "Emit",
    "Monitor",
    "SceneGrid",
    "ScenePath",
    "Table",
    "TrialColumnsMonitor",
]

#: row kinds of a table
ROW_KINDS = ("trial", "step", "event")


@dataclass(frozen=True)
class Table:
    """A table a monitor writes: ``<name>.parquet`` in the run folder.

    Attributes
    ----------
    name
        Table name (``trials``, ``steps``, ``activity``, ...).
    fields
        The monitor's columns (Arrow fields).
    per
        ``"trial"``: one row per trial; ``"step"``: one row per recorded step;
        ``"event"``: rows the monitor emits itself.
    """

    name: str
    fields: tuple[pa.Field, ...]
    per: str = "trial"

    def __post_init__(self) -> None:
        if self.per not in ROW_KINDS:
            raise ValueError(f"table {self.name!r}: per={self.per!r}; allowed: {ROW_KINDS}")
        object.__setattr__(self, "fields", tuple(self.fields))


@dataclass(frozen=True)
class BatchInfo:
    """Where a batch of trials belongs: run, phase and the 1-based trial numbers.

    A batch the recorder joined from several batches (for :attr:`Monitor.joinable` monitors)
    spans runs and phases: then ``trial_runs`` and ``trial_numbers`` hold each trial's run and
    trial number, and ``run``, ``phase`` and ``first_trial`` are those of its first trial. Use
    :meth:`runs` and :meth:`trials`, which are right in both cases.
    """

    run: int
    phase: str
    first_trial: int
    env: Any
    trial_runs: np.ndarray | None = None
    trial_numbers: np.ndarray | None = None
    #: position of the batch's first trial in its phase (1-based; >1 when a phase with a
    #: per-trial ``cycle`` is recorded trial by trial)
    first_in_phase: int = 1

    def trials(self, n: int) -> np.ndarray:
        """(n,) int32: the 1-based trial number of each trial of the batch."""
        if self.trial_numbers is not None:
            return self.trial_numbers
        return np.arange(self.first_trial, self.first_trial + n, dtype=np.int32)

    def runs(self, n: int) -> np.ndarray:
        """(n,) int32: the run of each trial of the batch."""
        if self.trial_runs is not None:
            return self.trial_runs
        return np.full(n, self.run, np.int32)

    @classmethod
    def joined(cls, infos: Sequence[BatchInfo], n_trials: Sequence[int]) -> BatchInfo:
        """The info of batches joined in this order (``n_trials[i]`` trials in batch ``i``);
        one info is its own join (it may be a join already)."""
        if len(infos) == 1:
            return infos[0]
        first = infos[0]
        counts = np.asarray(n_trials, np.int64)
        starts = np.repeat(np.array([i.first_trial for i in infos], np.int32), counts)
        begin = np.repeat(np.cumsum(counts) - counts, counts)
        within = np.arange(int(counts.sum()), dtype=np.int32) - begin.astype(np.int32)
        return cls(
            run=first.run, phase=first.phase, first_trial=first.first_trial, env=first.env,
            trial_runs=np.repeat(np.array([i.run for i in infos], np.int32), counts),
            trial_numbers=starts + within,
        )  # fmt: skip


Emit = Callable[[str, Mapping[str, Any]], None]

#: kinds of :class:`ScenePath` segments (drawn in different colours)
PATH_KINDS = ("forward", "reverse", "mixed", "none")


@dataclass(frozen=True)
class ScenePath:
    """A path a monitor draws over the maze in ``run.mcap`` at the start or end of a trial
    (e.g. a replay event: a second, highlighted path beside the agent's pose).

    Attributes
    ----------
    name
        Topic suffix: the path goes on ``/run_NNNN/<name>`` (a ``foxglove.SceneUpdate``).
    trial
        Position of the trial in the batch (0-based).
    at
        ``"start"`` (logged with the trial's first pose) or ``"end"`` (with its last pose).
    segments
        Polylines, each ``(k, 2)`` points ``x, y`` in world units, in the order they are run.
    kinds
        One of :data:`PATH_KINDS` per segment (its colour).
    metadata
        Key/value strings written with the scene entity.
    """

    name: str
    trial: int
    at: str
    segments: tuple[np.ndarray, ...]
    kinds: tuple[str, ...]
    metadata: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.at not in ("start", "end"):
            raise ValueError(f"ScenePath.at must be 'start' or 'end', got {self.at!r}")
        if len(self.kinds) != len(self.segments) or not set(self.kinds) <= set(PATH_KINDS):
            raise ValueError(f"ScenePath.kinds: one of {PATH_KINDS} per segment")


class Monitor(abc.ABC):
    """Base class: declare :meth:`tables`, fill them in :meth:`on_batch` (or emit rows)."""

    #: env contracts (names in :data:`cobelrun.envs.base.CONTRACTS`) this monitor needs
    requires: ClassVar[tuple[str, ...]] = ()

    #: True if :meth:`on_batch` depends only on the batch, ``info.runs()``/``info.trials()``
    #: and the env's fixed layout (no agent, no state kept between batches). The recorder may
    #: then call it later, on its writer thread, with many batches joined into one
    #: (:meth:`TrialBatch.concat`, :meth:`BatchInfo.joined`): per-step tables cost a few numpy
    #: calls per ~65,000 rows instead of per batch. Only used for monitors that write per-step
    #: tables alone.
    joinable: ClassVar[bool] = False

    #: attributes (JSON values: numbers, strings, lists of them, None) that carry a run's state
    #: from one batch to the next; a checkpoint saves them (:mod:`cobelrun.checkpoint`)
    checkpoint_fields: ClassVar[tuple[str, ...]] = ()

    _emit: Emit | None = None

    @abc.abstractmethod
    def tables(self) -> list[Table]:
        """The tables (and this monitor's columns in them)."""

    def setup(self, env: Any) -> None:
        """Check the env's contracts, resolve what depends on it (place names, probes)."""
        require(env, self.requires, f"monitor {type(self).__name__}")

    def bind(self, emit: Emit) -> None:
        """The recorder's sink for rows of this monitor's ``per="event"`` tables."""
        self._emit = emit

    def emit(self, table: str, columns: Mapping[str, Any]) -> None:
        if self._emit is None:
            raise RuntimeError(f"{type(self).__name__} is not bound to a recorder")
        self._emit(table, columns)

    def fork(self, emit: Emit, shared: Sequence[Any] = ()) -> Monitor:
        """An independent copy with its own per-run state, bound to ``emit``, for a run that is
        recorded while other runs of a batch advance (``task.batch_runs``). Objects in
        ``shared`` (the environment) are referenced, not copied. Override if a monitor holds
        state that must not be copied."""
        memo: dict[int, Any] = {id(obj): obj for obj in shared if obj is not None}
        if self._emit is not None:
            memo[id(self._emit)] = None
        twin = copy.deepcopy(self, memo)
        twin.bind(emit)
        return twin

    def start_run(self, run: int, agent: Any = None) -> None:  # noqa: B027 (optional hook)
        """A new independent agent starts (reset per-run state)."""

    def callbacks(self, first_trial: int) -> list[Any]:
        """Per-step/trial-end hooks (``TrialCallback``) this monitor needs during a phase that
        starts at trial ``first_trial``; none by default (agents then keep compiled paths)."""
        return []

    def on_batch(self, batch: TrialBatch, info: BatchInfo) -> dict[str, dict[str, np.ndarray]]:
        """Columns for the batch's rows, by table name."""
        return {}

    def scene_paths(self, batch: TrialBatch, info: BatchInfo) -> list[ScenePath]:
        """Paths to draw in ``run.mcap`` for this batch (asked after :meth:`on_batch`, only
        for the runs the MCAP keeps); none by default."""
        return []

    def scene_grids(self) -> list[SceneGrid]:
        """Maps to show over the maze in ``run.mcap`` and the live view, taken since the last
        call (asked after each batch and at the end of each run; only the runs the MCAP keeps
        show them); none by default."""
        return []

    def end_run(self, run: int, agent: Any, last_trial: int) -> None:  # noqa: B027
        """The run's last trial is over."""

    # -- checkpoints -----------------------------------------------------------------------------
    def checkpoint_state(self) -> dict[str, Any]:
        """The run's state between batches (the :attr:`checkpoint_fields`), JSON-ready."""
        return {name: _json_value(getattr(self, name)) for name in self.checkpoint_fields}

    def resume_run(self, run: int, agent: Any, state: Mapping[str, Any]) -> None:
        """Go on with run ``run`` from a checkpoint: restore :meth:`checkpoint_state` instead
        of :meth:`start_run` (whose rows, e.g. a trial-0 snapshot, are written already).
        ValueError if ``state`` does not fit (nothing changed)."""
        if not isinstance(state, Mapping) or set(state) != set(self.checkpoint_fields):
            raise ValueError(
                f"monitor {type(self).__name__}: expected the fields {list(self.checkpoint_fields)}"
            )
        for name in self.checkpoint_fields:
            value, own = state[name], getattr(self, name)
            if not _same_kind(value, own):
                raise ValueError(f"monitor {type(self).__name__}.{name}: got {value!r}")
        for name in self.checkpoint_fields:
            setattr(self, name, state[name])


@dataclass(frozen=True)
class SceneGrid:
    """Maps over the maze that a monitor shows in ``run.mcap`` and the live view: one
    ``foxglove.Grid`` on ``/run_NNNN/<name>`` with a float field per map, all on the same bins
    (e.g. the activity of a layer's units, one field each; Foxglove's 3D panel colours the grid
    by the field you pick).

    Attributes
    ----------
    name
        Topic suffix: ``/run_NNNN/<name>``.
    trial
        The trial after which the maps were taken (1-based; 0: before the first trial); the
        grid is logged at that trial's end (0: at the first trial's start).
    origin
        ``(x, y)`` of the lower-left corner of bin (0, 0), world units.
    cell_size
        ``(dx, dy)`` of a bin, world units.
    fields
        Field name -> ``(ny, nx)`` float array, row 0 at the lowest ``y``; NaN: no value there.
    metadata
        Key/value strings (e.g. layer, units); not written to the grid message.
    """

    name: str
    trial: int
    origin: tuple[float, float]
    cell_size: tuple[float, float]
    fields: Mapping[str, np.ndarray]
    metadata: Mapping[str, str] = field(default_factory=dict)

    def stacked(self) -> np.ndarray:
        """The fields as one ``(ny, nx, n_fields)`` float32 array (field order kept)."""
        arrays = [np.asarray(v, dtype=np.float32) for v in self.fields.values()]
        if not arrays or any(a.ndim != 2 or a.shape != arrays[0].shape for a in arrays):
            raise ValueError(f"SceneGrid {self.name!r}: fields must be equal (ny, nx) arrays")
        return np.stack(arrays, axis=2)


class TrialColumnsMonitor(Monitor):
    """A monitor that adds columns to the ``trials`` table: define :meth:`fields` and
    :meth:`columns`."""

    @abc.abstractmethod
    def fields(self) -> list[pa.Field]:
        """This monitor's columns."""

    @abc.abstractmethod
    def columns(self, batch: TrialBatch, env: Any) -> dict[str, np.ndarray]:
        """Its values for a batch of trials."""

    def tables(self) -> list[Table]:
        return [Table("trials", tuple(self.fields()))]

    def on_batch(self, batch: TrialBatch, info: BatchInfo) -> dict[str, dict[str, np.ndarray]]:
        return {"trials": self.columns(batch, info.env)}


def _json_value(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, tuple | list):
        return [_json_value(v) for v in value]
    return value


def _same_kind(value: Any, own: Any) -> bool:
    """Whether a restored field ``value`` is of the kind of the live ``own`` (None fits any)."""
    if value is None or own is None:
        return value is None or isinstance(value, str | int | float | list)
    if isinstance(own, bool) or isinstance(value, bool):
        return isinstance(value, bool) and isinstance(own, bool)
    if isinstance(own, int | np.integer):
        return isinstance(value, int)
    if isinstance(own, float):
        return isinstance(value, int | float)
    if isinstance(own, str):
        return isinstance(value, str)
    if isinstance(own, list | tuple):
        return isinstance(value, list) and all(isinstance(v, str | int | float) for v in value)
    return False
