"""Linear actor-critic on a population code: Foster, Morris & Dayan (2000)'s water-maze agent.

The critic estimates the value of the current position as a weighted sum of place-cell
activities, the actor keeps one weight vector per action (swim direction), and both learn from
the temporal-difference error (docs/paper-settings.md, "Water maze")::

    C(p)   = w . f(p)                           critic (value)
    a_j(p) = z_j . f(p)                         actor preference of action j
    P(j)   = exp(beta a_j) / sum_k exp(beta a_k)
    delta  = r + gamma C(p') - C(p)             (C(p') = 0 after a terminal step)
    w     += critic_lr * delta * f(p)
    z_j   += actor_lr  * delta * f(p)   for the action j taken

Nothing here is specific to place cells: the agent works on any ``Box`` observation (the
features ``f``) and ``Discrete`` actions.

The agent base runs the step loop (:meth:`act` draws from the softmax of
:mod:`cobelrun.agents.policy`, :meth:`observe` makes the TD update in a small numba kernel) and
saves ``w`` and ``z`` through the declared :meth:`state_schema`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any, ClassVar

import gymnasium as gym
import numba
import numpy as np

from cobelrun.agents import policy
from cobelrun.agents.base import Agent, ArraySpec, SeedLike, Transition
from cobelrun.agents.schema import AgentArgs, interval, number_at_least, validate_args
from cobelrun.errors import ConfigError


@numba.njit(cache=True)
def _td_update(w: np.ndarray, z: np.ndarray, f: np.ndarray, f2: np.ndarray, a: int, r: float,
               gamma: float, terminal: bool, critic_lr: float, actor_lr: float) -> float:  # fmt: skip
    """One actor-critic TD step in place; returns the TD error."""
    v = 0.0
    v2 = 0.0
    for i in range(f.shape[0]):
        v += w[i] * f[i]
        v2 += w[i] * f2[i]
    delta = r + (0.0 if terminal else gamma * v2) - v
    cd = critic_lr * delta
    ad = actor_lr * delta
    for i in range(f.shape[0]):
        w[i] += cd * f[i]
        z[a, i] += ad * f[i]
    return delta


class ActorCriticArgs(AgentArgs):
    """The ranges of :class:`ActorCritic`'s arguments (checked in this order)."""

    gamma: Annotated[Any, interval(0.0, 1.0)]
    critic_lr: Annotated[Any, number_at_least(0.0)]
    actor_lr: Annotated[Any, number_at_least(0.0)]
    beta: Annotated[Any, number_at_least(0.0)]


class ActorCritic(Agent):
    """Foster, Morris & Dayan (2000)'s actor-critic on a feature (place-cell) code.

    Parameters
    ----------
    env
        Environment with a ``Box`` observation (the features, e.g. 493 place cells) and a
        ``Discrete`` action space (e.g. 8 swim directions).
    gamma
        Discount per step (Foster et al.: 0.9975 at 0.1 s steps).
    critic_lr
        Critic learning rate (scaled by nothing: with 493 cells of width 0.16 m in a 1 m pool
        about 25 cells are active at once, so the effective step is ~25x this).
    actor_lr
        Actor learning rate.
    beta
        Inverse temperature of the softmax over actor preferences (Foster et al.: 2).
    seed
        Seed of the action draws.
    """

    observation_spaces: ClassVar[tuple[type[gym.Space], ...]] = (gym.spaces.Box,)
    action_spaces: ClassVar[tuple[type[gym.Space], ...]] = (gym.spaces.Discrete,)

    def __init__(
        self,
        env: gym.Env,
        *,
        gamma: float = 0.9975,
        critic_lr: float = 0.01,
        actor_lr: float = 0.01,
        beta: float = 2.0,
        seed: SeedLike = None,
    ) -> None:
        super().__init__(env, seed=seed)
        shape = env.observation_space.shape
        if shape is None or len(shape) != 1:
            raise ConfigError(
                f"agent ActorCritic needs a flat feature vector observation, got shape {shape}"
            )
        validate_args(ActorCriticArgs, locals())
        self.gamma, self.critic_lr, self.actor_lr, self.beta = (
            float(gamma), float(critic_lr), float(actor_lr), float(beta))  # fmt: skip
        self.n_features = int(shape[0])
        self.n_actions = int(env.action_space.n)  # type: ignore[attr-defined]
        self.w = np.zeros(self.n_features)
        self.z = np.zeros((self.n_actions, self.n_features))

    def hyperparameters(self) -> dict[str, float]:
        return {"gamma": self.gamma, "critic_lr": self.critic_lr, "actor_lr": self.actor_lr,
                "beta": self.beta}  # fmt: skip

    # ------------------------------------------------------------------ policy and values
    def value(self, observations: np.ndarray) -> np.ndarray:
        """Critic values ``C`` of a batch of observations, shape (n,)."""
        return np.atleast_2d(observations) @ self.w

    def predict(self, observations: np.ndarray) -> np.ndarray:
        """Actor preferences ``a_j`` of a batch of observations, shape (n, n_actions)."""
        return np.atleast_2d(np.asarray(observations, np.float64)) @ self.z.T

    def action_probabilities(self, obs: np.ndarray) -> np.ndarray:
        """Softmax action probabilities at one observation."""
        pref = self.beta * (self.z @ np.asarray(obs, np.float64))
        p = np.exp(pref - pref.max())
        return p / p.sum()

    # ------------------------------------------------------------------ step-loop hooks
    def act(self, obs: np.ndarray, info: dict[str, Any], learn: bool) -> int:
        """Draw an action from the softmax policy (in tests too: the policy is stochastic)."""
        return policy.softmax(self.rng, self.z @ obs, self.beta)

    def observe(self, transition: Transition, learn: bool) -> None:
        """The TD update of critic and actor after one step (when learning)."""
        if not learn:
            return
        t = transition
        _td_update(self.w, self.z, t.obs, t.next_obs, t.action, t.reward, self.gamma,
                   t.terminated, self.critic_lr, self.actor_lr)  # fmt: skip

    # ------------------------------------------------------------------ save / load
    def state_schema(self) -> dict[str, ArraySpec]:
        """Critic weights ``w`` (features,) and actor weights ``z`` (actions, features)."""
        return {"w": ArraySpec((self.n_features,)),
                "z": ArraySpec((self.n_actions, self.n_features))}  # fmt: skip

    def get_state(self) -> dict[str, np.ndarray]:
        return {"w": self.w.copy(), "z": self.z.copy()}

    def set_state(self, arrays: Mapping[str, np.ndarray]) -> None:
        self.w[...] = arrays["w"]
        self.z[...] = arrays["z"]
