"""The replay log of replaying agents: one entry per backup, collected per ``train`` call."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from cobelrun.agents.base import Agent, TrialCallback
from cobelrun.agents.policy import select
from cobelrun.records import TrialBatch

#: fields of an agent's ``last_replays`` (one entry per backup), read by the replays monitor
REPLAY_FIELDS = (
    "trial", "when", "index", "agent_state", "state", "action", "next_state", "reward", "gain",
    "need", "length",
)  # fmt: skip
WHEN_START, WHEN_END = 0, 1
_DTYPES = {"when": np.int8, "reward": np.float64, "gain": np.float64, "need": np.float64}


class ReplayLog:
    """Collects replay bouts during one ``train`` call."""

    def __init__(self) -> None:
        self._bouts: list[dict[str, np.ndarray]] = []

    def add(self, trial: int, when: int, agent_state: int, **columns: np.ndarray) -> None:
        """One bout: per-backup ``state, action, next_state, reward, gain, need, length``."""
        n = len(columns["state"])
        if n == 0:
            return
        entry = {k: np.asarray(v) for k, v in columns.items()}
        entry["trial"] = np.full(n, trial, np.int64)
        entry["when"] = np.full(n, when, np.int8)
        entry["index"] = np.arange(n, dtype=np.int64)
        entry["agent_state"] = np.full(n, agent_state, np.int64)
        self._bouts.append(entry)

    def collect(self) -> dict[str, np.ndarray]:
        """All bouts as one dict of arrays (empty arrays if there were none)."""
        if not self._bouts:
            return empty_replays()
        return {k: np.concatenate([b[k] for b in self._bouts]).astype(_DTYPES.get(k, np.int64))
                for k in REPLAY_FIELDS}  # fmt: skip


def empty_replays() -> dict[str, np.ndarray]:
    """A replay log without entries."""
    return {k: np.zeros(0, _DTYPES.get(k, np.int64)) for k in REPLAY_FIELDS}


class ReplayAgent(Agent):
    """Shared by the tabular replay agents (PMA, SFMA): the behaviour policy over ``Q[s]``
    (``self.policy``, ``epsilon``, ``beta``) and a fresh :class:`ReplayLog` per call of the
    base step loop, whose events end up in :attr:`last_replays` (the replays monitor reads them).
    """

    Q: np.ndarray
    policy: str
    epsilon: float
    beta: float

    def act(self, obs: Any, info: dict[str, Any], learn: bool) -> int:
        """Behaviour policy: epsilon-greedy (random tie-break) or softmax(beta) over ``Q[s]``."""
        return select(self.rng, self.Q[int(obs)], self.policy, self.epsilon, self.beta)

    def _run(
        self, n_trials: int, max_steps: int, learn: bool, callbacks: Sequence[TrialCallback]
    ) -> TrialBatch:
        self._log = ReplayLog()
        self._trial = -1
        batch = super()._run(n_trials, max_steps, learn, callbacks)
        self.last_replays = self._log.collect()
        return batch
