"""The stable-baselines3 plumbing that DQN (:mod:`cobelrun.agents.dqn`) and prioritized replay
(:mod:`cobelrun.agents.per`) share: a trial-recording wrapper and a DQN that stops on request.

Kept apart so that ``dqn`` imports ``per`` and both import this module, without a cycle.
Importing it imports stable-baselines3 (the ``deep`` extra).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3 import DQN
from stable_baselines3.common.type_aliases import RolloutReturn

from cobelrun.agents.base import Transition, TrialCallback, state_of
from cobelrun.envs.base import Posed
from cobelrun.records import TrialBatch

__all__ = ["TrialDQN", "TrialRecorder"]


class TrialRecorder(gym.Wrapper):
    """Caps episodes (trials) at ``max_steps`` and records them, for SB3's own rollout loop.

    Records what the base loop (:meth:`cobelrun.agents.base.Agent._run`) records: per trial the
    states (:func:`~cobelrun.agents.base.state_of`), actions, rewards, whether it ended in a
    terminal state and, for :class:`~cobelrun.envs.base.Posed` environments, the start pose and
    the pose after each step. :class:`TrialCallback` hooks run here too; returning ``False``
    from ``on_step`` truncates the trial.
    """

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.max_steps: int | None = None
        self.finished: list[dict[str, Any]] = []
        self.callbacks: Sequence[TrialCallback] = ()
        self.agent: Any = None
        self._current: dict[str, Any] | None = None
        self._posed = isinstance(env.unwrapped, Posed)
        self._obs: Any = None
        self._info: dict[str, Any] = {}

    def begin(self, max_steps: int, callbacks: Sequence[TrialCallback], agent: Any) -> None:
        """Start recording a new batch of trials."""
        self.max_steps, self.callbacks, self.agent = max_steps, callbacks, agent
        self.finished = []
        self._current = None

    def _pose(self) -> np.ndarray:
        return np.array(self.env.unwrapped.agent_pose(), np.float64)

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        s = state_of(obs, info)
        self._current = {"states": [s], "actions": [], "rewards": [], "terminated": False,
                         "poses": [self._pose()] if self._posed else None}  # fmt: skip
        self._obs, self._info = obs, info
        for cb in self.callbacks:
            cb.on_trial_start(self.agent, len(self.finished), s)
        return obs, info

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        cur = self._current
        assert cur is not None, "step() before reset()"
        s = cur["states"][-1]
        s2 = state_of(obs, info)
        a = int(np.asarray(action).reshape(-1)[0])
        cur["states"].append(s2)
        cur["actions"].append(a)
        cur["rewards"].append(float(reward))
        if cur["poses"] is not None:
            cur["poses"].append(self._pose())
        n = len(cur["actions"])
        if self.max_steps is not None and n >= self.max_steps:
            truncated = True
        if self.callbacks:
            t = Transition(self._obs, a, float(reward), obs, bool(terminated), bool(truncated),
                           self._info, info, s, s2)  # fmt: skip
            trial = len(self.finished)
            keep = all([cb.on_step(self.agent, trial, n, t) for cb in self.callbacks])
            truncated = truncated or not keep
        self._obs, self._info = obs, info
        if terminated or truncated:
            cur["terminated"] = bool(terminated)
            self.finished.append(cur)
            self._current = None
            for cb in self.callbacks:
                cb.on_trial_end(self.agent, len(self.finished) - 1, cur)
        return obs, reward, terminated, truncated, info

    def batch(self) -> TrialBatch:
        return TrialBatch.from_trials(self.finished)


class TrialDQN(DQN):
    """SB3 DQN that stops collecting once ``stop_when()`` is true (checked before each step)."""

    stop_when: Callable[[], bool] | None = None

    def collect_rollouts(self, env, callback, train_freq, replay_buffer, *args, **kwargs):  # type: ignore[override]
        if self.stop_when is not None and self.stop_when():
            return RolloutReturn(0, 0, continue_training=False)
        return super().collect_rollouts(env, callback, train_freq, replay_buffer, *args, **kwargs)
