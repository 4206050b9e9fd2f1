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
import torch
import torch.nn.functional as F
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

    Once ``quota`` trials are finished, the reset that SB3's vectorised env makes right after
    the last one is not passed on (it returns the last observation and starts no trial): the
    next call's first trial starts with its own reset, so every trial costs one reset, as in
    the base loop, and a phase run in pieces draws the same start states as in one call.
    """

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.max_steps: int | None = None
        self.finished: list[dict[str, Any]] = []
        #: trials of the current call (None: no limit)
        self.quota: int | None = None
        self.callbacks: Sequence[TrialCallback] = ()
        self.agent: Any = None
        self._current: dict[str, Any] | None = None
        self._posed = isinstance(env.unwrapped, Posed)
        self._obs: Any = None
        self._info: dict[str, Any] = {}

    def begin(
        self, max_steps: int, callbacks: Sequence[TrialCallback], agent: Any,
        quota: int | None = None,
    ) -> None:  # fmt: skip
        """Start recording a new batch of (at most ``quota``) trials."""
        self.max_steps, self.callbacks, self.agent = max_steps, callbacks, agent
        self.quota = quota
        self.finished = []
        self._current = None

    def _pose(self) -> np.ndarray:
        return np.array(self.env.unwrapped.agent_pose(), np.float64)

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        if self.quota is not None and len(self.finished) >= self.quota:
            return self._obs, self._info  # after the call's last trial: no trial follows
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
    """SB3 DQN that stops collecting once ``stop_when()`` is true (checked before each step).

    Its gradient step is SB3's ``DQN.train`` with three settings: ``td_loss`` (SB3's Huber loss
    by default; keras-rl's squared error for CoBeL-RL's DQN), ``max_grad_norm`` ``None`` for no
    gradient clipping (keras-rl clips nothing by default) and ``trial_end_updates``.
    """

    stop_when: Callable[[], bool] | None = None
    #: training log on (``DQNAgent.log_training``): also log ``train/q_max``
    log_q: bool = False

    td_loss: Callable[..., torch.Tensor] = staticmethod(F.smooth_l1_loss)
    #: extra gradient steps after the step that ends a trial (keras-rl's fit loop makes one more
    #: backward call on the terminal observation, which trains once more)
    trial_end_updates: int = 0

    def collect_rollouts(self, env, callback, train_freq, replay_buffer, *args, **kwargs):  # type: ignore[override]
        if self.stop_when is not None and self.stop_when():
            return RolloutReturn(0, 0, continue_training=False)
        out = super().collect_rollouts(env, callback, train_freq, replay_buffer, *args, **kwargs)
        self._trial_ended = out.n_episodes > 0
        return out

    def _steps_now(self, gradient_steps: int) -> int:
        """Gradient steps of this call: ``trial_end_updates`` more after a trial's last step."""
        if self.trial_end_updates and getattr(self, "_trial_ended", False):
            return gradient_steps + self.trial_end_updates
        return gradient_steps

    def _record_q_max(self) -> None:
        """Training log on: max Q at the current observation (no RNG draws)."""
        if self.log_q:
            with torch.no_grad():
                obs, _ = self.policy.obs_to_tensor(self._last_obs)
                self.logger.record("train/q_max", float(self.q_net(obs).max()))

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        gradient_steps = self._steps_now(gradient_steps)
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        losses = []
        for _ in range(gradient_steps):
            data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr]
            discounts = data.discounts if data.discounts is not None else self.gamma
            with torch.no_grad():
                next_q, _ = self.q_net_target(data.next_observations).max(dim=1)
                target = data.rewards + (1 - data.dones) * discounts * next_q.reshape(-1, 1)
            current = torch.gather(self.q_net(data.observations), dim=1, index=data.actions.long())
            loss = self.td_loss(current, target)
            losses.append(loss.item())
            self.policy.optimizer.zero_grad()
            loss.backward()
            if self.max_grad_norm is not None:
                torch.nn.utils.clip_grad_norm_(self.policy.parameters(), self.max_grad_norm)
            self.policy.optimizer.step()
        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/loss", np.mean(losses))
        self._record_q_max()
