"""Conditioning columns of the trials table: trial type, cues shown, the agent's prediction."""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np
import pyarrow as pa

from cobelrun.agents.base import TrialCallback
from cobelrun.errors import ConfigError
from cobelrun.monitors.base import TrialColumnsMonitor
from cobelrun.records import TrialBatch


@runtime_checkable
class HasPrediction(Protocol):
    """Agents that keep the prediction a trial's cues evoked (``agent=rescorla_wagner``,
    ``agent=td_conditioning``)."""

    prediction: float


class ConditioningMonitor(TrialColumnsMonitor, TrialCallback):
    """Per trial: ``trial_type``, ``cues`` (the cues shown, ``+``-joined, context first), ``V``
    (the prediction the trial's cues evoked before the trial's learning: the agent's
    ``prediction``), ``response`` (the action at the first cue's onset: what the
    ``rw_response`` model of ``cobel fit`` describes) and ``responded`` (1 if the agent
    responded at any step).

    Needs a :class:`~cobelrun.envs.sequence.SequenceEnv` and an agent with a ``prediction``
    (``agent=rescorla_wagner``, ``agent=td_conditioning``).
    """

    def __init__(self) -> None:
        self._rows: list[tuple[str, str, float, int, int]] = []
        self._env: Any = None

    def setup(self, env: Any) -> None:
        from cobelrun.envs.sequence import SequenceEnv

        if not isinstance(env.unwrapped, SequenceEnv):
            raise ConfigError(f"monitor ConditioningMonitor needs env=sequence, got "
                              f"{type(env.unwrapped).__name__}")  # fmt: skip
        self._env = env.unwrapped

    def start_run(self, run: int, agent: Any = None) -> None:
        self._rows = []

    def callbacks(self, first_trial: int) -> list[Any]:
        return [self]

    def fields(self) -> list[pa.Field]:
        return [pa.field("trial_type", pa.string()), pa.field("cues", pa.string()),
                pa.field("V", pa.float64()), pa.field("response", pa.int64()),
                pa.field("responded", pa.int64())]  # fmt: skip

    def _on_trial_end(self, agent: Any, trial: int, record: dict[str, Any]) -> None:
        if not isinstance(agent, HasPrediction):
            raise ConfigError(f"monitor ConditioningMonitor needs an agent with a prediction "
                              f"(rescorla_wagner, td_conditioning), got {type(agent).__name__}")  # fmt: skip
        info = self._env.trial_info()
        actions = record["actions"]
        onset = self._env.first_onset()
        response = int(actions[onset]) if onset < len(actions) else 0
        self._rows.append((info["trial_type"], info["cues"], float(agent.prediction), response,
                           int(any(actions))))  # fmt: skip

    def columns(self, batch: TrialBatch, env: Any) -> dict[str, np.ndarray]:
        n = batch.n_trials
        rows, self._rows = self._rows[:n], self._rows[n:]
        if len(rows) < n:
            raise ConfigError(f"conditioning monitor saw {len(rows)} trial ends for {n} trials")
        return {"trial_type": np.array([r[0] for r in rows], object),
                "cues": np.array([r[1] for r in rows], object),
                "V": np.array([r[2] for r in rows], np.float64),
                "response": np.array([r[3] for r in rows], np.int64),
                "responded": np.array([r[4] for r in rows], np.int64)}  # fmt: skip
