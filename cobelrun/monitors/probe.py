"""Greedy probes: after every trial, score the agent's greedy choice on fixed probe inputs.

Training rewards of an epsilon-greedy agent mix what it has learnt with its exploration (with
epsilon 0.3 and two actions the expected training reward is capped at 0.7 + 0.3 / 2 = 0.85).
:class:`GreedyProbeMonitor` measures the learnt part on its own: at the end of every trial it
asks the agent for its action values on every probe observation (``agent.predict``), takes
the greedy action (``argmax``; ties go to the lower action) and writes the fraction of probes
where that action is the correct one as a ``trials`` column (default ``greedy_correct``).

The probe neither learns nor acts in the environment: ``predict`` is a forward pass without
gradients, and no random numbers of the agent or the environment are drawn, so a run with the
probe produces the same trials as one without it (``tests/test_probe.py``). Like every
:class:`~cobelrun.agents.base.TrialCallback`, the probe runs at the trial's end hook; for the
SB3 DQN (which trains after each collected step) that is the greedy policy that acted in the
trial, for agents that update inside the trial it includes the trial's updates. Passing a
callback makes tabular agents take their per-step Python path (slower, same results).
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np
import pyarrow as pa

from cobelrun.agents.base import TrialCallback
from cobelrun.envs.base import StateObservations
from cobelrun.errors import ConfigError
from cobelrun.monitors.base import TrialColumnsMonitor
from cobelrun.records import TrialBatch


@runtime_checkable
class HasCorrectActions(Protocol):
    """Choice tasks that name the correct action of each state (``TwoAFCEnv``)."""

    @property
    def correct_actions(self) -> np.ndarray: ...


class GreedyProbeMonitor(TrialColumnsMonitor, TrialCallback):
    """Fraction of probe observations on which the greedy action is correct, every trial.

    Parameters
    ----------
    probes
        (n, ...) probe observations; default: the environment's ``observations`` (one per
        state, e.g. the four displays of ``TwoAFCEnv``).
    correct
        (n,) correct action of each probe; default: the environment's ``correct_actions``.
    column
        Name of the ``trials`` column (default ``greedy_correct``).
    """

    def __init__(self, probes: Any = None, correct: Any = None, column: str = "greedy_correct"):
        self.probes = None if probes is None else np.asarray(probes)
        self.correct = None if correct is None else np.asarray(correct, dtype=np.int64)
        self.column = str(column)
        self._values: list[float] = []

    def setup(self, env: Any) -> None:
        base = env.unwrapped
        if self.probes is None:
            if not isinstance(base, StateObservations):
                raise ConfigError(
                    f"greedy probe: {type(base).__name__} has no per-state observations; "
                    "give probe observations with 'probes'"
                )
            self.probes = np.asarray(base.observations)
        if self.correct is None:
            if not isinstance(base, HasCorrectActions):
                raise ConfigError(
                    f"greedy probe: {type(base).__name__} names no correct actions; "
                    "give one per probe with 'correct'"
                )
            self.correct = np.asarray(base.correct_actions, dtype=np.int64)
        if self.correct.shape != (len(self.probes),):
            raise ConfigError(
                f"greedy probe: {len(self.probes)} probes but {self.correct.size} correct actions"
            )

    def start_run(self, run: int, agent: Any = None) -> None:
        self._values = []

    def callbacks(self, first_trial: int) -> list[Any]:
        self._values = []
        return [self]

    def fields(self) -> list[pa.Field]:
        return [pa.field(self.column, pa.float64())]

    def score(self, agent: Any) -> float:
        """Fraction of probes whose greedy action is the correct one."""
        q = np.asarray(agent.predict(self.probes))
        return float(np.mean(q.argmax(axis=1) == self.correct))

    def _on_trial_end(self, agent: Any, trial: int, record: dict[str, Any]) -> None:
        self._values.append(self.score(agent))

    def columns(self, batch: TrialBatch, env: Any) -> dict[str, np.ndarray]:
        n = batch.n_trials
        if len(self._values) < n:
            raise ConfigError(
                f"greedy probe saw {len(self._values)} trial ends for {n} trials "
                "(the agent did not call its trial callbacks)"
            )
        values, self._values = np.array(self._values[:n], np.float64), []
        return {self.column: values}
