"""Agent base class: trial-based training, batch prediction, save/load, declared capabilities."""

from __future__ import annotations

import abc
from collections.abc import Sequence
from pathlib import Path
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from cobelrun.errors import ConfigError
from cobelrun.records import TrialBatch

SeedLike = int | np.random.SeedSequence | None


def as_seed_sequence(seed: SeedLike) -> np.random.SeedSequence:
    """Turn ``seed`` (int, SeedSequence or None) into a SeedSequence."""
    if isinstance(seed, np.random.SeedSequence):
        return seed
    return np.random.SeedSequence(seed)


def check_budget(n_trials: int, max_steps: int) -> None:
    """Raise ConfigError unless ``n_trials >= 0`` and ``max_steps >= 1``."""
    if n_trials < 0 or max_steps < 1:
        raise ConfigError(f"need n_trials >= 0 and max_steps >= 1, got {n_trials}, {max_steps}")


class TrialCallback:
    """Per-step hooks for the opt-in slow path (template-method style, as SB3's callbacks).

    Passing any callback to :meth:`Agent.train` or :meth:`Agent.test` runs trials step by step
    in Python so that the hooks can look at (and change) the agent and environment inside a
    trial. Override the underscore methods; return ``False`` from :meth:`_on_step` to end the
    current trial early.
    """

    def on_trial_start(self, agent: Agent, trial: int, state: int) -> None:
        self._on_trial_start(agent, trial, state)

    def on_step(self, agent: Agent, trial: int, step: int, transition: dict[str, Any]) -> bool:
        return self._on_step(agent, trial, step, transition) is not False

    def on_trial_end(self, agent: Agent, trial: int, record: dict[str, Any]) -> None:
        self._on_trial_end(agent, trial, record)

    def _on_trial_start(self, agent: Agent, trial: int, state: int) -> None:
        """Called after the environment was reset for ``trial`` (0-based within the call)."""

    def _on_step(
        self, agent: Agent, trial: int, step: int, transition: dict[str, Any]
    ) -> bool | None:
        """Called after every step with ``state, action, reward, next_state, terminated``."""
        return True

    def _on_trial_end(self, agent: Agent, trial: int, record: dict[str, Any]) -> None:
        """Called at trial end with ``states, actions, rewards, terminated``."""


class Agent(abc.ABC):
    """Base class of all cobel agents.

    Agents are trial based: :meth:`train` and :meth:`test` run ``n_trials`` whole trials of at
    most ``max_steps`` steps in the agent's environment and return a :class:`TrialBatch`.
    Subclasses declare which observation and action spaces they support; constructing an agent
    on any other space raises :class:`~cobelrun.errors.ConfigError` naming what is allowed.

    Parameters
    ----------
    env
        The gymnasium environment the agent acts in.
    seed
        Seed of the agent's own random draws (exploration, replay sampling, initialisation).
    """

    #: Gymnasium space classes the agent accepts as observation / action space.
    observation_spaces: ClassVar[tuple[type[gym.Space], ...]] = ()
    action_spaces: ClassVar[tuple[type[gym.Space], ...]] = (gym.spaces.Discrete,)

    def __init__(self, env: gym.Env, *, seed: SeedLike = None) -> None:
        self.check_spaces(env)
        self.env = env
        self.seed_sequence = as_seed_sequence(seed)
        self.rng = np.random.default_rng(self.seed_sequence)

    @classmethod
    def check_spaces(cls, env: gym.Env) -> None:
        """Raise ConfigError if ``env``'s spaces are not supported by this agent."""
        for kind, space, allowed in (
            ("observation", env.observation_space, cls.observation_spaces),
            ("action", env.action_space, cls.action_spaces),
        ):
            if allowed and not isinstance(space, allowed):
                names = ", ".join(a.__name__ for a in allowed)
                raise ConfigError(
                    f"agent {cls.__name__} does not support {kind} space "
                    f"{type(space).__name__}; allowed: {names}"
                )

    def train(
        self, n_trials: int, max_steps: int, callbacks: Sequence[TrialCallback] = ()
    ) -> TrialBatch:
        """Run ``n_trials`` trials of at most ``max_steps`` steps with learning on."""
        check_budget(n_trials, max_steps)
        return self._run(n_trials, max_steps, True, callbacks)

    def test(
        self, n_trials: int, max_steps: int, callbacks: Sequence[TrialCallback] = ()
    ) -> TrialBatch:
        """Run ``n_trials`` trials with learning off (the same policy, no updates)."""
        check_budget(n_trials, max_steps)
        return self._run(n_trials, max_steps, False, callbacks)

    @abc.abstractmethod
    def _run(
        self, n_trials: int, max_steps: int, learn: bool, callbacks: Sequence[TrialCallback]
    ) -> TrialBatch:
        """Run trials (arguments already checked); subclasses implement this."""

    @abc.abstractmethod
    def predict(self, observations: np.ndarray) -> np.ndarray:
        """Action values for a batch of observations, shape (n, n_actions)."""

    @abc.abstractmethod
    def save(self, path: str | Path) -> Path:
        """Save the agent's learned state (no pickle) and return the file written."""

    @abc.abstractmethod
    def load(self, path: str | Path) -> None:
        """Restore learned state written by :meth:`save` into this agent."""
