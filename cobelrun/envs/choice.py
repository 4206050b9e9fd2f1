"""Non-spatial two-alternative forced choice (the paper's Fig. 9)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from cobelrun.envs.base import check_action
from cobelrun.errors import ConfigError


class TwoAFCEnv(gym.Env[np.ndarray, int]):
    """Two-alternative forced choice between stimuli shown side by side.

    Description
    -----------
    A set of stimuli (one-hot vectors by default) and a set of choice types, each a pair
    ``(correct, incorrect)`` of stimulus indices (default ``[[0, 1], [2, 3]]``, docs/paper-settings.md Fig. 9).
    Each trial draws a choice type uniformly and shows its two stimuli side by side in random
    order; the agent picks a side. One step per trial.

    Action Space
    ------------
    ``Discrete(2)``: 0 = pick the left stimulus, 1 = pick the right one.

    Observation Space
    -----------------
    ``Box(0, 1, (2 * d,), float32)``: the left stimulus vector followed by the right one.

    Rewards
    -------
    ``reward`` (1) for picking the correct stimulus, 0 otherwise.

    Starting State
    --------------
    Choice type ``np_random.integers(0, n_types)``, then the correct side
    ``np_random.integers(0, 2)`` (1 = right).

    Episode End
    -----------
    Terminated after the one choice.

    Arguments
    ---------
    stimuli : (n, d) array, optional
        Stimulus vectors (default: 4 one-hot vectors).
    choices : list of [correct, incorrect], optional
        Choice types (default ``[[0, 1], [2, 3]]``).
    reward : float
        Reward of a correct choice.

    ``info`` holds ``state`` (``2 * choice_type + correct_side``: one index per distinct
    display), ``choice_type`` and ``correct`` (the correct action). :attr:`observations` lists
    the observation of each state (the default probes of activity monitors) and
    :attr:`correct_actions` the correct action of each (the default of the greedy probe,
    :class:`cobelrun.monitors.probe.GreedyProbeMonitor`).
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(
        self,
        stimuli: Any = None,
        choices: Sequence[Sequence[int]] | None = None,
        reward: float = 1.0,
    ) -> None:
        stim = np.eye(4, dtype=np.float32) if stimuli is None else np.array(stimuli, np.float32)
        if stim.ndim != 2 or stim.shape[0] < 2:
            raise ConfigError(f"stimuli must be an (n >= 2, d) array, got shape {stim.shape}")
        pairs = np.array([[0, 1], [2, 3]] if choices is None else choices, dtype=np.int64)
        if pairs.ndim != 2 or pairs.shape[1] != 2 or len(pairs) < 1:
            raise ConfigError("choices must be a list of [correct, incorrect] stimulus pairs")
        if pairs.min() < 0 or pairs.max() >= len(stim):
            raise ConfigError(f"choices name stimuli outside 0..{len(stim) - 1}: {pairs.tolist()}")
        self.stimuli, self.choices, self.reward = stim, pairs, float(reward)
        d = stim.shape[1]
        self.observation_space = spaces.Box(
            low=float(min(stim.min(), 0.0)), high=float(max(stim.max(), 1.0)), shape=(2 * d,),
            dtype=np.float32,
        )  # fmt: skip
        self.action_space = spaces.Discrete(2)
        n_states = 2 * len(pairs)
        obs = np.zeros((n_states, 2 * d), np.float32)
        for s in range(n_states):
            obs[s] = self._display(s)
        obs.setflags(write=False)
        self.observations = obs
        correct = np.arange(n_states, dtype=np.int64) % 2
        correct.setflags(write=False)
        self.correct_actions = correct
        self._state = 0

    def _display(self, s: int) -> np.ndarray:
        correct, wrong = self.choices[s // 2]
        left, right = (wrong, correct) if s % 2 else (correct, wrong)
        return np.concatenate([self.stimuli[left], self.stimuli[right]])

    def _info(self) -> dict[str, Any]:
        return {"state": self._state, "choice_type": self._state // 2, "correct": self._state % 2}

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        kind = int(self.np_random.integers(0, len(self.choices)))
        side = int(self.np_random.integers(0, 2))
        self._state = 2 * kind + side
        return self.observations[self._state].copy(), self._info()

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        a = check_action(action, 2, ("left", "right"))
        reward = self.reward if a == self._state % 2 else 0.0
        return self.observations[self._state].copy(), reward, True, False, self._info()
