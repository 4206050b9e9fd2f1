"""Dyna-DSR: deep successor representation with Dyna replay (CoBeL-RL, paper section 2.1.3).

Like deep successor RL (Kulkarni et al. 2016) but, as in CoBeL-RL, without a learned feature
layer: the successor features and the reward model work directly on the observations ``o_s``.

- Successor features per action ``M(s, a)`` (one network per action, each ``o -> R^d``) estimate
  the discounted future occupancy of observations after taking ``a`` in ``s``.
- A linear reward model ``R(s') = o_s' . w`` is fitted to the rewards received on arrival.
- Action values are ``Q(s, a) = M(s, a) . w``.

We use the arrival convention of the environments (a step pays the reward of the state it
arrives in), so the successor target of ``(s, a) -> s'`` is
``o_s' + gamma * M_target(s', a*)`` with ``a* = argmax_a' Q_target(s', a')`` (without the
bootstrap term when ``s'`` is terminal, unless ``always_bootstrap``), and ``M . w`` is exactly
the action value. Replay, exploration, action mask and soft target updates are those of
:class:`~cobelrun.agents.dyna_dqn.DynaDeepAgent`.

Fig. 7 settings (docs/paper-settings.md): epsilon 0.3, beta 5, gamma 0.9, action mask on, replay batch 100
per step, target rate 0.01, always bootstrap, dense 64 tanh -> 64 tanh -> linear, Adam, MSE.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from cobelrun.agents.dyna_dqn import DynaDeepAgent, allowed_next
from cobelrun.agents.networks import Network
from cobelrun.errors import ConfigError


class DynaDSR(DynaDeepAgent):
    """Dyna-DSR agent (see the module docstring).

    Parameters
    ----------
    env
        A tabular environment (see :class:`DynaDeepAgent`).
    reward_learning_rate
        Adam learning rate of the linear reward model (default 0.1). It is faster than the
        networks' ``learning_rate`` because a linear weight moves by about one learning rate per
        step: at 1e-3 the goal's weight would need ~10^4 steps to reach a reward of 10.
    **kwargs
        The parameters of :class:`DynaDeepAgent`.
    """

    batched_kind = "successor"

    def __init__(self, env: gym.Env, *, reward_learning_rate: float = 0.1, **kwargs: Any) -> None:
        # keys and types of **kwargs are checked against DynaDeepAgent's signature by
        # cobelrun.config.validate_node (it follows **kwargs into the base class)
        if reward_learning_rate <= 0:
            raise ConfigError(f"agent.reward_learning_rate must be > 0, got {reward_learning_rate}")
        self.reward_learning_rate = float(reward_learning_rate)
        super().__init__(env, **kwargs)

    def build_networks(self) -> None:
        d = self.obs.shape[1]
        self.sr = self.network(d, n_heads=self.n_actions, seed_index=0)
        self.sr_target = self.sr.clone()
        self.reward_model = self.network(
            1, seed_index=1, hidden=[], bias=False, learning_rate=self.reward_learning_rate
        )
        # the reward model starts at zero: no reward is expected before any is seen
        self.reward_model.set_weights({"w0": np.zeros((1, d, 1), np.float32)})

    def networks(self) -> dict[str, Network]:
        return {"sr": self.sr, "reward": self.reward_model}

    def _all_networks(self) -> dict[str, Network]:
        return {"sr": self.sr, "sr_target": self.sr_target, "reward": self.reward_model}

    @property
    def w(self) -> np.ndarray:
        """Reward weights ``w`` (d,)."""
        return self.reward_model.get_weights()["w0"][0, :, 0]

    def q_from_observations(self, obs: np.ndarray) -> np.ndarray:
        m = self.sr.predict(obs)  # (A, n, d)
        return (m @ self.w).T  # (n, A)

    def q_values(self, states: np.ndarray) -> np.ndarray:
        return self.q_from_observations(self.obs[states])

    def successor_representation(self, state_or_obs: int | np.ndarray) -> np.ndarray:
        """``M(s, a)`` for every action, shape (A, d), of a state index or an observation."""
        if isinstance(state_or_obs, int | np.integer):
            obs = self.obs[[int(state_or_obs)]]
        else:
            obs = np.asarray(state_or_obs, dtype=np.float32).reshape(1, -1)
        return self.sr.predict(obs)[:, 0, :]

    def update(self, s, a, r, s2, terminal, mask) -> None:  # type: ignore[override]
        o_next = self.obs[s2]
        w = self.w
        m_next = self.sr_target.predict(o_next)  # (A, n, d)
        q_next = (m_next @ w).T  # (n, A)
        if self.use_mask:
            q_next = np.where(allowed_next(mask, s2), q_next, -np.inf)
        # greedy next action, ties broken at random
        noise = self.rng.random(q_next.shape) * 1e-9
        best = np.argmax(np.where(np.isfinite(q_next), q_next + noise, -np.inf), axis=1)
        cont = np.ones_like(r) if self.always_bootstrap else 1.0 - terminal
        rows = np.arange(len(s))
        target = o_next + self.gamma * cont[:, None] * m_next[best, rows]
        self.sr.train_step(self.obs[s], target, heads=a)
        self.reward_model.train_step(o_next, r[:, None])
        self.sr_target.blend_from(self.sr, self.target_tau)
