"""A linear track: the worked example of docs/extending.md (one module + one YAML).

Place it next to your ``conf/`` folder (or anywhere on ``PYTHONPATH``) and point an env YAML's
``_target_`` at ``linear_track.LinearTrackEnv``.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import gymnasium as gym
import numpy as np

from cobelrun.envs.base import Geometry, check_action, point_region
from cobelrun.errors import ConfigError


class LinearTrackEnv(gym.Env):
    """A track of ``length`` places between two reward wells.

    Description
    -----------
    The agent steps left or right along the track; the ends are terminal.

    Action Space
    ------------
    ``Discrete(2)``: 0 = left, 1 = right.

    Observation Space
    -----------------
    ``Discrete(length)``: the place index (0 = left end).

    Rewards
    -------
    ``rewards[place]`` on arriving at a place (default 1 at the right end).

    Starting State
    --------------
    The middle of the track.

    Episode End
    -----------
    Terminated at either end.

    Arguments
    ---------
    length : int
        Number of places (>= 3).
    spacing : float
        Distance between places in metres (poses and geometry are in metres).
    """

    metadata = {"render_modes": []}  # noqa: RUF012

    def __init__(self, length: int = 9, spacing: float = 0.1) -> None:
        if isinstance(length, bool) or not isinstance(length, int) or length < 3:
            raise ConfigError(f"env.length must be an integer >= 3, got {length!r}")
        self.length, self.spacing = length, float(spacing)
        self.action_space = gym.spaces.Discrete(2)
        self.observation_space = gym.spaces.Discrete(length)
        self._base_rewards = np.zeros(length)
        self._base_rewards[-1] = 1.0
        self.reset_world()
        self._pos, self._heading = length // 2, 0.0

    # -- contract: Changeable (protocol phases move the reward) -------------------------------
    def reset_world(self) -> None:
        self.rewards = self._base_rewards.copy()
        self.starts = [self.length // 2]

    def apply_changes(
        self,
        rewards: Mapping[Any, float] | None = None,
        terminals: Mapping[Any, bool] | None = None,
        starts: Iterable[Any] | None = None,
    ) -> None:
        for ref, value in (rewards or {}).items():
            self.rewards[self.state_index(ref)] = float(value)
        if terminals:
            raise ConfigError(
                "the linear track's terminals are its two ends; a phase cannot change them "
                f"(got terminals {dict(terminals)!r})"
            )
        if starts is not None:
            self.starts = [self.state_index(s) for s in starts]

    # -- contract: DiscreteStates (named places, poses of states) -----------------------------
    @property
    def n_states(self) -> int:
        return self.length

    def state_index(self, ref: Any) -> int:
        named = {"left_end": 0, "right_end": self.length - 1}
        s = named.get(ref, ref)
        if isinstance(s, bool) or not isinstance(s, int | np.integer) or not 0 <= s < self.length:
            raise ConfigError(
                f"unknown place {ref!r}; allowed: left_end, right_end, 0..{self.length - 1}"
            )
        return int(s)

    def poses_of(self, states: np.ndarray, actions: np.ndarray | None = None) -> np.ndarray:
        states = np.asarray(states, np.int64)
        heading = (
            np.zeros(states.shape)
            if actions is None
            else np.where(np.asarray(actions) == 0, np.pi, 0.0)
        )
        return np.stack([states * self.spacing, np.zeros(states.shape), heading], axis=1)

    # -- contract: Posed ----------------------------------------------------------------------
    def agent_pose(self) -> np.ndarray:
        return np.array([self._pos * self.spacing, 0.0, self._heading])

    # -- contract: HasGeometry ----------------------------------------------------------------
    def geometry(self) -> Geometry:
        x = np.arange(self.length) * self.spacing
        return Geometry(
            kind="graph",
            bounds=(-self.spacing, -self.spacing, x[-1] + self.spacing, self.spacing),
            nodes=np.stack([x, np.zeros_like(x)], axis=1),
            edges=np.stack([np.arange(self.length - 1), np.arange(1, self.length)], axis=1),
            regions={"left_end": point_region(x[0], 0.0), "right_end": point_region(x[-1], 0.0)},
        )

    # -- gymnasium ----------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._pos = int(self.starts[self.np_random.integers(0, len(self.starts))])
        self._heading = 0.0
        return self._pos, {"state": self._pos}

    def step(self, action: Any):
        a = check_action(action, 2, ("left", "right"))
        self._pos += 1 if a == 1 else -1
        self._heading = 0.0 if a == 1 else np.pi
        terminated = self._pos in (0, self.length - 1)
        return self._pos, float(self.rewards[self._pos]), terminated, False, {"state": self._pos}
