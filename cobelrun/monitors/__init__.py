"""Monitors collect measurements from trial batches; writers persist them.

Every monitor declares the tables it writes (:class:`Table`: a name, Arrow fields and a row
kind) and gets one lifecycle from the recorder:

``setup(env)``
    once, after composition: resolve place names, check the environment's contracts.
``start_run(run, agent)``
    before each independent agent's first trial.
``on_batch(batch, info)``
    after each phase's trials: return columns per table (``{table: {column: array}}``).
``end_run(run, agent, last_trial)``
    after the run's last trial.

Rows of ``per="trial"`` tables (one per trial) and ``per="step"`` tables (one per step, which
``task.record`` may thin out) from several monitors are joined side by side, so each adds
columns; ``per="event"`` tables get whole rows from one monitor, whenever it calls the
``emit(table, columns)`` function it was bound to (activity snapshots, replay events).
Monitors never do I/O, and the recorder knows no table by name: a new monitor is one class
and one YAML entry.
"""

from __future__ import annotations

import abc
import copy
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import pyarrow as pa

from cobelrun.envs.base import DiscreteStates, require, supports
from cobelrun.errors import ConfigError
from cobelrun.records import TrialBatch

__all__ = [
    "BatchInfo",
    "EscapeLatencyMonitor",
    "Monitor",
    "ResponseMonitor",
    "RewardMonitor",
    "ScenePath",
    "Table",
    "TrajectoryMonitor",
    "TrialKeysMonitor",
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

    def end_run(self, run: int, agent: Any, last_trial: int) -> None:  # noqa: B027
        """The run's last trial is over."""


class TrialKeysMonitor(Monitor):
    """The key columns of the ``trials`` table: run, trial (1-based across phases), phase,
    trial within the phase, start and end state, terminated. Always the first monitor."""

    def tables(self) -> list[Table]:
        return [Table("trials", (
            pa.field("run", pa.int32()), pa.field("trial", pa.int32()),
            pa.field("phase", pa.string()), pa.field("trial_in_phase", pa.int32()),
            pa.field("start_state", pa.int64()), pa.field("end_state", pa.int64()),
            pa.field("terminated", pa.bool_()),
        ))]  # fmt: skip

    def on_batch(self, batch: TrialBatch, info: BatchInfo) -> dict[str, dict[str, np.ndarray]]:
        n = batch.n_trials
        return {"trials": {
            "run": np.full(n, info.run, np.int32), "trial": info.trials(n),
            "phase": np.full(n, info.phase),  # fixed-width str: cheap to join and compare
            "trial_in_phase": np.arange(info.first_in_phase, info.first_in_phase + n,
                                        dtype=np.int32),
            "start_state": batch.start_state, "end_state": batch.end_state,
            "terminated": batch.terminated,
        }}  # fmt: skip


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


class RewardMonitor(TrialColumnsMonitor):
    """Reward collected per trial (sum over the trial's steps)."""

    def fields(self) -> list[pa.Field]:
        return [pa.field("reward", pa.float64())]

    def columns(self, batch: TrialBatch, env: Any) -> dict[str, np.ndarray]:
        return {"reward": batch.reward}


class EscapeLatencyMonitor(TrialColumnsMonitor):
    """Escape latency per trial, written to the ``steps`` column.

    Parameters
    ----------
    definition
        ``"steps"`` (default): the number of steps taken. ``"original"``: CoBeL-RL's logged
        value, steps taken - 1 (kept for comparison with the original's numbers).
    """

    def __init__(self, definition: str = "steps") -> None:
        if definition not in ("steps", "original"):
            raise ConfigError(
                f"latency definition {definition!r} is not known; allowed: 'steps', 'original'"
            )
        self.offset = 0 if definition == "steps" else 1

    def fields(self) -> list[pa.Field]:
        return [pa.field("steps", pa.int64())]

    def columns(self, batch: TrialBatch, env: Any) -> dict[str, np.ndarray]:
        return {"steps": batch.steps - self.offset}


class ResponseMonitor(TrialColumnsMonitor):
    """Response coding: 1 if a trial ended in one of ``states``, else 0; and its running sum.

    Parameters
    ----------
    states
        States that code a response: indices, place names (``right_arm``) or ``[row, col]``.
    before
        Optional competing states (e.g. ``[left_arm]``). Given, a trial codes 1 if it arrives in
        one of ``states`` before any of ``before`` (the first choice), wherever it ends. When
        both are terminal this is the same as the end-state coding.
    """

    def __init__(self, states: Sequence[Any], before: Sequence[Any] | None = None) -> None:
        if isinstance(states, (str, int)):
            states = [states]
        if isinstance(before, (str, int)):
            before = [before]
        if not states:
            raise ConfigError("response monitor needs at least one state in 'states'")
        self.refs = list(states)
        self.before_refs = list(before or [])
        self.states = np.zeros(0, np.int64)
        self.before = np.zeros(0, np.int64)
        self._is_response: np.ndarray | None = None
        self._cumulative = 0

    requires = ("discrete_states",)

    def setup(self, env: Any) -> None:
        super().setup(env)
        base = env.unwrapped
        self.states = np.array([base.state_index(r) for r in self.refs], dtype=np.int64)
        self.before = np.array([base.state_index(r) for r in self.before_refs], dtype=np.int64)
        # response states as a lookup table: one take per batch instead of np.isin
        self._is_response = np.zeros(int(base.n_states), np.int8)
        self._is_response[self.states] = 1

    def start_run(self, run: int, agent: Any = None) -> None:
        self._cumulative = 0

    def fields(self) -> list[pa.Field]:
        return [pa.field("response", pa.int8()), pa.field("cumulative_response", pa.int64())]

    def columns(self, batch: TrialBatch, env: Any) -> dict[str, np.ndarray]:
        if self.before.size:
            response = self._first_choice(batch)
        else:
            response = (
                np.isin(batch.end_state, self.states).astype(np.int8)
                if self._is_response is None
                else self._is_response[batch.end_state]
            )
        cumulative = self._cumulative + np.cumsum(response, dtype=np.int64)
        if cumulative.size:
            self._cumulative = int(cumulative[-1])
        return {"response": response, "cumulative_response": cumulative}

    def _first_choice(self, batch: TrialBatch) -> np.ndarray:
        """1 where a trial reaches ``states`` before ``before`` (step order within the trial)."""
        n, never = batch.n_trials, np.iinfo(np.int64).max
        trial = batch.step_trial_index()
        step = np.arange(batch.n_steps, dtype=np.int64)
        first = []
        for targets in (self.states, self.before):
            hit = np.isin(batch.step_next_state, targets)
            at = np.full(n, never, np.int64)
            np.minimum.at(at, trial[hit], step[hit])
            first.append(at)
        return ((first[0] < first[1]) & (first[0] != never)).astype(np.int8)


class TrajectoryMonitor(Monitor):
    """Every step: run, trial, step, state, pose (x, y, heading), action, reward and next state
    (the ``steps`` table). Positions come from the env's pose contract (``x``/``y`` of the state
    the action was taken in); envs without poses write NaN. Joinable: the recorder builds the
    table from many batches at once, on its writer thread."""

    joinable = True

    def tables(self) -> list[Table]:
        return [Table("steps", (
            pa.field("run", pa.int32()), pa.field("trial", pa.int32()),
            pa.field("step", pa.int32()), pa.field("state", pa.int64()),
            pa.field("x", pa.float64()), pa.field("y", pa.float64()),
            pa.field("heading", pa.float32()), pa.field("action", pa.int16()),
            pa.field("reward", pa.float64()), pa.field("next_state", pa.int64()),
        ), per="step")]  # fmt: skip

    def on_batch(self, batch: TrialBatch, info: BatchInfo) -> dict[str, dict[str, np.ndarray]]:
        n = batch.n_trials
        base = info.env.unwrapped
        if batch.step_pose is None and supports(base, DiscreteStates):
            # the pose each action was taken in: its state, reached by the previous action
            prev = np.empty_like(batch.step_action)
            prev[1:] = batch.step_action[:-1]
            prev[batch.offsets[:-1][batch.steps > 0]] = -1
            before = base.poses_of(batch.step_state, prev)
        elif (poses := batch.with_poses(info.env).poses()) is not None:
            last = batch.offsets[1:] + np.arange(n)  # drop each trial's final pose
            keep = np.ones(poses.shape[0], bool)
            keep[last] = False
            before = poses[keep]
        else:
            before = np.full((batch.n_steps, 3), np.nan)
        return {"steps": {
            "run": np.repeat(info.runs(n), batch.steps),
            "trial": np.repeat(info.trials(n), batch.steps),
            "step": batch.step_index().astype(np.int32),
            "state": batch.step_state,
            "x": before[:, 0], "y": before[:, 1], "heading": before[:, 2].astype(np.float32),
            "action": batch.step_action.astype(np.int16),
            "reward": batch.step_reward,
            "next_state": batch.step_next_state,
        }}  # fmt: skip
