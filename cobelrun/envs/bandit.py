"""Multi-armed bandit with Bernoulli rewards; reversals are protocol phases."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from cobelrun.envs.base import check_action
from cobelrun.errors import ConfigError


class BanditEnv(gym.Env[int, int]):
    """A ``k``-armed bandit: one choice per trial, reward with an arm's probability.

    Description
    -----------
    Each trial the agent picks one of ``k`` arms and receives ``reward`` with the arm's
    probability (Bernoulli), else 0. A protocol phase changes the probabilities
    (``rewards: {0: 0.2, 1: 0.8}`` maps arms to new probabilities), which makes a reversal
    task (``task=reversal_bandit``); a new run restores them (:meth:`reset_world`).

    Action Space
    ------------
    ``Discrete(k)``: the arm.

    Observation Space
    -----------------
    ``Discrete(1)``: the one state, 0 (tabular agents keep one row of values).

    Rewards
    -------
    ``reward`` with probability ``reward_probs[arm]``, else 0; drawn from ``np_random``.

    Starting State
    --------------
    Always 0.

    Episode End
    -----------
    Terminated after the one choice.

    Arguments
    ---------
    reward_probs : list of float
        Reward probability of each arm, in [0, 1] (default ``[0.8, 0.2]``).
    reward : float
        Reward of a rewarded choice.

    ``info`` holds ``state`` (0) and ``best`` (the arm with the highest probability now).
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(self, reward_probs: Sequence[float] = (0.8, 0.2), reward: float = 1.0) -> None:
        probs = np.asarray(reward_probs, dtype=np.float64)
        if probs.ndim != 1 or len(probs) < 2:
            raise ConfigError(
                f"reward_probs must list >= 2 arm probabilities, got {reward_probs!r}"
            )
        if not np.all((probs >= 0) & (probs <= 1)):
            raise ConfigError(f"reward_probs must lie in [0, 1], got {probs.tolist()}")
        if not np.isfinite(reward):
            raise ConfigError(f"reward must be a finite number, got {reward!r}")
        self._base_probs = probs.copy()
        self.reward_probs = probs.copy()
        self.reward = float(reward)
        self.action_space = spaces.Discrete(len(probs))
        self.observation_space = spaces.Discrete(1)
        obs = np.ones((1, 1), np.float32)
        obs.setflags(write=False)
        self.observations = obs
        self._names = tuple(f"arm_{i}" for i in range(len(probs)))

    @property
    def n_states(self) -> int:
        """One state."""
        return 1

    def _arm(self, ref: Any) -> int:
        text = str(ref).removeprefix("arm_")
        if not text.isdigit() or int(text) >= len(self.reward_probs):
            raise ConfigError(f"unknown arm {ref!r}; arms: 0..{len(self.reward_probs) - 1} "
                              f"(or arm_0..arm_{len(self.reward_probs) - 1})")  # fmt: skip
        return int(text)

    def apply_changes(
        self,
        rewards: Mapping[Any, float] | None = None,
        terminals: Mapping[Any, bool] | None = None,
        starts: Iterable[Any] | None = None,
    ) -> None:
        """Set arms' reward probabilities (``rewards``: arm -> probability); a bandit has no
        terminals or starts to change."""
        if terminals or starts is not None:
            raise ConfigError("a bandit phase changes only rewards (arm -> probability)")
        for ref, p in (rewards or {}).items():
            p = float(p)
            if not 0.0 <= p <= 1.0:
                raise ConfigError(f"arm {ref!r}: reward probability must lie in [0, 1], got {p}")
            self.reward_probs[self._arm(ref)] = p

    def reset_world(self) -> None:
        """Restore the probabilities as built."""
        self.reward_probs = self._base_probs.copy()

    def _info(self) -> dict[str, Any]:
        return {"state": 0, "best": int(np.argmax(self.reward_probs))}

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[int, dict[str, Any]]:
        super().reset(seed=seed)
        return 0, self._info()

    def step(self, action: Any) -> tuple[int, float, bool, bool, dict[str, Any]]:
        a = check_action(action, len(self.reward_probs), self._names)
        hit = self.np_random.random() < self.reward_probs[a]
        return 0, (self.reward if hit else 0.0), True, False, self._info()
