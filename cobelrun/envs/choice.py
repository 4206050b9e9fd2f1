"""Non-spatial two-alternative forced choice (the paper's Fig. 9)."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
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
    ``reward`` (1) with probability ``reward_probs[0]`` for picking the correct stimulus (the
    first of its pair) and with probability ``reward_probs[1]`` for picking the other one, else
    0. The default ``[1, 0]`` is the deterministic task of Fig. 9: 1 if correct, 0 otherwise.
    A Bernoulli draw from ``np_random`` is taken only where the chosen side's probability lies
    strictly between 0 and 1, so the deterministic task draws nothing beyond its displays.
    A protocol phase changes the probabilities (``rewards: {correct: 0.2, incorrect: 0.8}``
    reverses the contingency; keys ``correct``/``incorrect`` or ``0``/``1``); a new run restores
    them (:meth:`reset_world`).

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
        Reward of a rewarded choice.
    reward_probs : [float, float]
        Probability of the reward for picking the correct stimulus and for picking the
        incorrect one, each in [0, 1] (default ``[1, 0]``: deterministic).

    ``info`` holds ``state`` (``2 * choice_type + correct_side``: one index per distinct
    display), ``choice_type`` and ``correct`` (the action that picks the pair's first, correct
    stimulus, also after a phase has reversed the reward probabilities). :attr:`observations` lists
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
        reward_probs: Sequence[float] = (1.0, 0.0),
    ) -> None:
        stim = np.eye(4, dtype=np.float32) if stimuli is None else np.array(stimuli, np.float32)
        if stim.ndim != 2 or stim.shape[0] < 2:
            raise ConfigError(f"stimuli must be an (n >= 2, d) array, got shape {stim.shape}")
        pairs = np.array([[0, 1], [2, 3]] if choices is None else choices, dtype=np.int64)
        if pairs.ndim != 2 or pairs.shape[1] != 2 or len(pairs) < 1:
            raise ConfigError("choices must be a list of [correct, incorrect] stimulus pairs")
        if pairs.min() < 0 or pairs.max() >= len(stim):
            raise ConfigError(f"choices name stimuli outside 0..{len(stim) - 1}: {pairs.tolist()}")
        try:
            amount = float(reward)
        except (TypeError, ValueError):
            amount = float("nan")
        if not np.isfinite(amount):
            raise ConfigError(f"env.reward must be a finite number, got {reward!r}")
        probs = _probabilities(reward_probs)
        self._base_probs = probs.copy()
        self.reward_probs = probs
        self.stimuli, self.choices, self.reward = stim, pairs, amount
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

    def apply_changes(
        self,
        rewards: Mapping[Any, float] | None = None,
        terminals: Mapping[Any, bool] | None = None,
        starts: Iterable[Any] | None = None,
    ) -> None:
        """Set reward probabilities (``rewards``: ``correct``/``incorrect`` or ``0``/``1`` ->
        probability); a two-alternative task has no terminals or starts to change."""
        if terminals or starts is not None:
            raise ConfigError("a two_afc phase changes only rewards "
                              "(correct/incorrect -> reward probability)")  # fmt: skip
        probs: dict[int, tuple[str, float]] = {}  # side -> (key, p); all checked, then set
        for ref, p in (rewards or {}).items():
            key = str(ref)
            if key not in _SIDES:
                raise ConfigError(f"unknown two_afc reward key {ref!r}; allowed: correct, "
                                  "incorrect (or 0, 1)")  # fmt: skip
            if isinstance(p, bool) or not isinstance(p, int | float) or not 0.0 <= p <= 1.0:
                raise ConfigError(f"two_afc reward probability of {key!r} must be a number in "
                                  f"[0, 1], got {p!r}")  # fmt: skip
            side = _SIDES[key]
            if side in probs:
                raise ConfigError(f"two_afc rewards name one side twice: {probs[side][0]!r} and "
                                  f"{key!r} (0 is correct, 1 is incorrect); give each once")  # fmt: skip
            probs[side] = (key, float(p))
        for side, (_, p) in probs.items():
            self.reward_probs[side] = p

    def reset_world(self) -> None:
        """Restore the reward probabilities as built."""
        self.reward_probs = self._base_probs.copy()

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
        p = float(self.reward_probs[0 if a == self._state % 2 else 1])
        hit = p >= 1.0 or (p > 0.0 and self.np_random.random() < p)
        reward = self.reward if hit else 0.0
        return self.observations[self._state].copy(), reward, True, False, self._info()


#: a phase's reward keys: the correct stimulus (0) and the incorrect one (1)
_SIDES = {"correct": 0, "incorrect": 1, "0": 0, "1": 1}


def _probabilities(value: Any) -> np.ndarray:
    """``env.reward_probs`` as a float array ``[p_correct, p_incorrect]``, or one ConfigError."""
    allowed = "two probabilities in [0, 1]: [correct, incorrect], e.g. [0.8, 0.2]"
    try:
        probs = np.array(
            [float(x) for x in value if not isinstance(x, bool | str)], dtype=np.float64
        )
        n = len(value)
    except (TypeError, ValueError):
        raise ConfigError(f"env.reward_probs must be {allowed}; got {value!r}") from None
    if n != 2 or len(probs) != 2:
        raise ConfigError(f"env.reward_probs must be {allowed}; got {value!r}")
    if not np.all((probs >= 0.0) & (probs <= 1.0)):  # NaN fails too
        raise ConfigError(f"env.reward_probs must be {allowed}; got {probs.tolist()}")
    return probs
