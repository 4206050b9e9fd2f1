"""The built-in monitors of the ``trials`` table: its key columns (:class:`TrialKeysMonitor`,
always the first monitor), reward, escape latency and response coding."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
import pyarrow as pa

from cobelrun.errors import ConfigError
from cobelrun.monitors.base import BatchInfo, Monitor, Table, TrialColumnsMonitor
from cobelrun.records import TrialBatch

__all__ = ["EscapeLatencyMonitor", "ResponseMonitor", "RewardMonitor", "TrialKeysMonitor"]


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

    #: the running response count, kept by checkpoints
    checkpoint_fields: ClassVar[tuple[str, ...]] = ("_cumulative",)

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
