"""Monitors collect measurements from trial batches; writers persist them.

A monitor contributes columns to the ``trials`` table (one row per trial) or the ``steps``
table (one row per step). Monitors never do I/O.
"""

from __future__ import annotations

import abc
from collections.abc import Sequence
from typing import Any

import numpy as np
import pyarrow as pa

from cobelrun.errors import ConfigError
from cobelrun.records import TrialBatch

__all__ = [
    "EscapeLatencyMonitor",
    "Monitor",
    "ResponseMonitor",
    "RewardMonitor",
    "TrajectoryMonitor",
]


class Monitor(abc.ABC):
    """Base class. Subclasses set ``table`` and implement :meth:`fields` and :meth:`columns`."""

    #: ``"trials"`` or ``"steps"``
    table: str = "trials"

    def setup(self, env: Any) -> None:  # noqa: B027 (optional hook)
        """Resolve anything that depends on the environment (e.g. place names)."""

    def start_run(self, run: int) -> None:  # noqa: B027 (optional hook)
        """Reset per-run state (called before each independent agent)."""

    @abc.abstractmethod
    def fields(self) -> list[pa.Field]:
        """The columns this monitor writes (Arrow fields)."""

    @abc.abstractmethod
    def columns(self, batch: TrialBatch, env: Any) -> dict[str, np.ndarray]:
        """This monitor's columns for a batch of trials."""


class RewardMonitor(Monitor):
    """Reward collected per trial (sum over the trial's steps)."""

    def fields(self) -> list[pa.Field]:
        return [pa.field("reward", pa.float64())]

    def columns(self, batch: TrialBatch, env: Any) -> dict[str, np.ndarray]:
        return {"reward": batch.reward}


class EscapeLatencyMonitor(Monitor):
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


class ResponseMonitor(Monitor):
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
        self._cumulative = 0

    def setup(self, env: Any) -> None:
        world = env.unwrapped.world
        self.states = np.array([world.state(r) for r in self.refs], dtype=np.int64)
        self.before = np.array([world.state(r) for r in self.before_refs], dtype=np.int64)

    def start_run(self, run: int) -> None:
        self._cumulative = 0

    def fields(self) -> list[pa.Field]:
        return [pa.field("response", pa.int8()), pa.field("cumulative_response", pa.int64())]

    def columns(self, batch: TrialBatch, env: Any) -> dict[str, np.ndarray]:
        if self.before.size:
            response = self._first_choice(batch)
        else:
            response = np.isin(batch.end_state, self.states).astype(np.int8)
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
    """Every step: state, position, action, reward and next state (the ``steps`` table)."""

    table = "steps"

    def fields(self) -> list[pa.Field]:
        return [
            pa.field("step", pa.int32()),
            pa.field("state", pa.int64()),
            pa.field("x", pa.float64()),
            pa.field("y", pa.float64()),
            pa.field("action", pa.int16()),
            pa.field("reward", pa.float64()),
            pa.field("next_state", pa.int64()),
        ]

    def columns(self, batch: TrialBatch, env: Any) -> dict[str, np.ndarray]:
        coords = env.unwrapped.world.coords
        xy = coords[batch.step_state]
        return {
            "step": batch.step_index().astype(np.int32),
            "state": batch.step_state,
            "x": xy[:, 0],
            "y": xy[:, 1],
            "action": batch.step_action.astype(np.int16),
            "reward": batch.step_reward,
            "next_state": batch.step_next_state,
        }
