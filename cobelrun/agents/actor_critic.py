"""Linear actor-critic on a population code: Foster, Morris & Dayan (2000)'s water-maze agent.

The critic estimates the value of the current position as a weighted sum of place-cell
activities, the actor keeps one weight vector per action (swim direction), and both learn from
the temporal-difference error (FACTS.md, "Water maze")::

    C(p)   = w . f(p)                           critic (value)
    a_j(p) = z_j . f(p)                         actor preference of action j
    P(j)   = exp(beta a_j) / sum_k exp(beta a_k)
    delta  = r + gamma C(p') - C(p)             (C(p') = 0 after a terminal step)
    w     += critic_lr * delta * f(p)
    z_j   += actor_lr  * delta * f(p)   for the action j taken

Nothing here is specific to place cells: the agent works on any ``Box`` observation (the
features ``f``) and ``Discrete`` actions.

The agent is written in the shape of the agent base's step loop (``begin_trial``, ``act``,
``observe``, ``end_trial``; ``state_schema``/``get_state``/``set_state`` for save and load);
:meth:`ActorCritic._run` drives that loop.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any, ClassVar

import gymnasium as gym
import numba
import numpy as np

from cobelrun.agents.base import Agent, SeedLike, TrialCallback
from cobelrun.errors import ConfigError
from cobelrun.records import TrialBatch


@numba.njit(cache=True)
def _sample(z: np.ndarray, f: np.ndarray, beta: float, u: float) -> int:
    """Draw an action from softmax(beta * z @ f) with the uniform number ``u``."""
    n = z.shape[0]
    pref = np.empty(n)
    for j in range(n):
        s = 0.0
        for i in range(f.shape[0]):
            s += z[j, i] * f[i]
        pref[j] = beta * s
    top = pref.max()
    total = 0.0
    for j in range(n):
        pref[j] = np.exp(pref[j] - top)
        total += pref[j]
    target = u * total
    acc = 0.0
    for j in range(n):
        acc += pref[j]
        if target < acc:
            return j
    return n - 1


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
    requires: ClassVar[tuple[str, ...]] = ()

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
        for name, value, lo, hi in (("gamma", gamma, 0.0, 1.0), ("critic_lr", critic_lr, 0.0, None),
                                    ("actor_lr", actor_lr, 0.0, None), ("beta", beta, 0.0, None)):  # fmt: skip
            ok = (
                isinstance(value, int | float)
                and not isinstance(value, bool)
                and np.isfinite(value)
            )
            if not ok or value < lo or (hi is not None and value > hi):
                bound = f"in [{lo}, {hi}]" if hi is not None else f">= {lo}"
                raise ConfigError(f"agent.{name} must be a number {bound}, got {value!r}")
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

    def policy(self, obs: np.ndarray) -> np.ndarray:
        """Softmax action probabilities at one observation."""
        pref = self.beta * (self.z @ obs)
        pref -= pref.max()
        p = np.exp(pref)
        return p / p.sum()

    # ------------------------------------------------------------------ step-loop hooks
    def begin_trial(self, obs: np.ndarray, info: dict[str, Any], learn: bool) -> None:
        """Nothing to reset between trials (no eligibility traces)."""

    def act(self, obs: np.ndarray, info: dict[str, Any], learn: bool) -> int:
        """Draw an action from the softmax policy (in tests too: the policy is stochastic)."""
        return int(_sample(self.z, obs, self.beta, self.rng.random()))

    def observe(self, transition: dict[str, Any], learn: bool) -> None:
        """The TD update of critic and actor after one step (when learning)."""
        if not learn:
            return
        _td_update(self.w, self.z, transition["obs"], transition["next_obs"],
                   int(transition["action"]), float(transition["reward"]), self.gamma,
                   bool(transition["terminated"]), self.critic_lr, self.actor_lr)  # fmt: skip

    def end_trial(self, learn: bool) -> None:
        """Nothing to do at trial end."""

    # ------------------------------------------------------------------ save / load
    def state_schema(self) -> dict[str, tuple[tuple[int, ...], str]]:
        """Arrays saved with the agent: name -> (shape, dtype)."""
        return {"w": ((self.n_features,), "float64"),
                "z": ((self.n_actions, self.n_features), "float64")}  # fmt: skip

    def get_state(self) -> dict[str, np.ndarray]:
        return {"w": self.w.copy(), "z": self.z.copy()}

    def set_state(self, arrays: dict[str, np.ndarray]) -> None:
        for name, (shape, dtype) in self.state_schema().items():
            if name not in arrays:
                raise ConfigError(f"saved ActorCritic has no array {name!r}")
            a = np.asarray(arrays[name])
            if a.shape != shape or a.dtype != np.dtype(dtype):
                raise ConfigError(
                    f"saved ActorCritic array {name!r} has shape {a.shape} ({a.dtype}); "
                    f"this environment needs {shape} ({dtype})"
                )
            if not np.isfinite(a).all():
                raise ConfigError(f"saved ActorCritic array {name!r} has non-finite values")
        self.w[...] = arrays["w"]
        self.z[...] = arrays["z"]

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        if path.suffix != ".npz":
            path = path.with_suffix(".npz")
        np.savez(path, hyperparameters=np.array(json.dumps(self.hyperparameters())),
                 **self.get_state())  # fmt: skip
        return path

    def load(self, path: str | Path) -> None:
        with np.load(path, allow_pickle=False) as data:
            self.set_state({k: data[k] for k in data.files if k != "hyperparameters"})

    # ------------------------------------------------------------------ the step loop
    def _run(
        self, n_trials: int, max_steps: int, learn: bool, callbacks: Sequence[TrialCallback]
    ) -> TrialBatch:
        """Run trials step by step through the hooks above; record states, poses, rewards."""
        env = self.env
        base = env.unwrapped
        posed = hasattr(base, "agent_pose")
        trials = []
        for t in range(n_trials):
            obs, info = env.reset()
            s = int(info.get("state", -1))
            states, actions, rewards = [s], [], []
            poses = [base.agent_pose()] if posed else None
            self.begin_trial(obs, info, learn)
            for cb in callbacks:
                cb.on_trial_start(self, t, s)
            terminated = False
            for step in range(1, max_steps + 1):
                a = self.act(obs, info, learn)
                obs2, r, terminated, truncated, info2 = env.step(a)
                self.observe({"obs": obs, "action": a, "reward": r, "next_obs": obs2,
                              "terminated": terminated, "truncated": truncated, "info": info,
                              "next_info": info2}, learn)  # fmt: skip
                s2 = int(info2.get("state", -1))
                states.append(s2)
                actions.append(a)
                rewards.append(float(r))
                if poses is not None:
                    poses.append(base.agent_pose())
                keep = True
                if callbacks:
                    tr = {"state": states[-2], "action": a, "reward": float(r), "next_state": s2,
                          "terminated": bool(terminated)}  # fmt: skip
                    keep = all([cb.on_step(self, t, step, tr) for cb in callbacks])
                obs, info = obs2, info2
                if terminated or truncated or not keep:
                    break
            self.end_trial(learn)
            record = {"states": states, "actions": actions, "rewards": rewards,
                      "terminated": bool(terminated), "poses": poses}  # fmt: skip
            for cb in callbacks:
                cb.on_trial_end(self, t, record)
            trials.append(record)
        return TrialBatch.from_trials(trials)
