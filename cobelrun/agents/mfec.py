"""Model-free episodic control (Blundell et al. 2016), as CoBeL-RL's MFEC agent (docs/paper-settings.md).

- Observations are flattened and projected to ``projection_dim`` dimensions with a fixed
  Gaussian random matrix (entries N(0, 1 / projection_dim)); ``projection: none`` keeps them.
- One episodic buffer per action holds (key, value) pairs, at most ``capacity`` of them.
- Estimate of ``Q(o, a)``: the stored value if the key is already in buffer ``a`` (exact match);
  else the mean value of its ``k`` nearest keys (Euclidean, ``scipy.spatial.cKDTree``); if the
  buffer holds fewer than ``k`` keys the estimate is 0 (as the original; with non-negative
  rewards an untried action is then never preferred over one that has paid).
- Action: epsilon-greedy over the estimates, ties broken at random.
- Learning, at the end of each trial: discounted returns ``R_t = r_t + gamma * R_{t+1}``
  (computed backwards over the trial; a truncated trial is not bootstrapped); for each visited
  ``(o_t, a_t)`` an existing key keeps ``max(old, R_t)``, a new key is inserted, evicting the
  *oldest inserted* key when the buffer is full.

Where this differs from a literal port, on purpose (documented, not copied):

- Exact matches are found through a hash of the key bytes, which is always current; the
  KD-tree is only used for the k-NN estimate and is rebuilt lazily, the first time a buffer is
  queried after it changed. A stale tree can therefore never produce duplicate keys.
- Eviction is strictly first-in-first-out over insertion time; updating a key's value does not
  make it "new". (Least-recently-used eviction is a variant of Blundell et al.; docs/paper-settings.md says
  the oldest entry is evicted.)
- A key that occurs twice within one trial is updated with the larger of its returns, in
  one pass, whatever the order.

Speed (exact: the same actions, values and buffers as without it, bit for bit):

- Projected keys are memoised by a 128-bit BLAKE2b digest of the observation's bytes
  (``memo`` entries at most; the memo is emptied when full), so each distinct image is
  projected once. Environments with finitely many views (topology envs, online or offline)
  then pay the ``obs_dim x projection_dim`` product only the first time a view is seen.
- Each buffer memoises its estimates by the same digest until it next changes (learning
  happens at trial end only, so within a trial a revisited view costs a dict lookup).
- ``memo: 0`` switches both off (every step projects and queries, as a literal port).

Numpy and scipy only; no torch.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from typing import Annotated, Any

import gymnasium as gym
import numpy as np
from scipy.spatial import cKDTree

from cobelrun.agents.base import Agent, ArraySpec, SeedLike, Transition
from cobelrun.agents.policy import epsilon_greedy
from cobelrun.agents.schema import (
    AgentArgs,
    at_least,
    int_at_least_or_none,
    interval,
    one_of,
    validate_args,
)

PROJECTIONS = ("gaussian", "none")


class EpisodicBuffer:
    """Keys and values of one action; FIFO eviction; exact-match hash; lazily rebuilt KD-tree."""

    def __init__(self, capacity: int, dim: int) -> None:
        self.capacity, self.dim = capacity, dim
        self.keys = np.zeros((capacity, dim))
        self.values = np.zeros(capacity)
        self.times = np.zeros(capacity, np.int64)  # insertion time (for FIFO eviction)
        self.size = 0
        self.clock = 0
        self.index: dict[bytes, int] = {}
        self._tree: cKDTree | None = None
        self._estimates: dict[bytes, float] = {}  # observation digest -> estimate, until a change

    def lookup(self, key: np.ndarray) -> int | None:
        return self.index.get(key.tobytes())

    def estimate(self, key: np.ndarray, k: int, tag: bytes | None = None) -> float:
        """Estimate for ``key``; ``tag`` (the observation's digest) memoises it until the next
        change of this buffer."""
        if tag is not None:
            value = self._estimates.get(tag)
            if value is not None:
                return value
        slot = self.lookup(key)
        if slot is not None:
            value = float(self.values[slot])
        elif self.size < k:
            value = 0.0
        else:
            if self._tree is None:
                self._tree = cKDTree(self.keys[: self.size])
            _, idx = self._tree.query(key, k=k)
            value = float(np.mean(self.values[np.atleast_1d(idx)]))
        if tag is not None:
            self._estimates[tag] = value
        return value

    def update(self, key: np.ndarray, value: float) -> None:
        slot = self.lookup(key)
        if slot is not None:
            if value > self.values[slot]:
                self.values[slot] = value
                self._estimates.clear()
            return
        self._estimates.clear()
        if self.size < self.capacity:
            slot = self.size
            self.size += 1
        else:
            slot = int(np.argmin(self.times))
            del self.index[self.keys[slot].tobytes()]
        self.keys[slot] = key
        self.values[slot] = value
        self.times[slot] = self.clock
        self.clock += 1
        self.index[self.keys[slot].tobytes()] = slot
        self._tree = None

    def state(self) -> dict[str, np.ndarray]:
        return {"keys": self.keys[: self.size], "values": self.values[: self.size],
                "times": self.times[: self.size], "clock": np.array(self.clock)}  # fmt: skip

    def load(self, state: Mapping[str, np.ndarray]) -> None:
        """Restore :meth:`state` (checked by :meth:`MFEC.check_state`)."""
        n = len(state["values"])
        self.size = n
        self.keys[:n], self.values[:n], self.times[:n] = (
            state["keys"],
            state["values"],
            state["times"],
        )
        self.clock = int(state["clock"])
        self.index = {self.keys[i].tobytes(): i for i in range(n)}
        self._tree = None
        self._estimates.clear()


class MFECArgs(AgentArgs):
    """The ranges of :class:`MFEC`'s arguments (checked in this order)."""

    epsilon: Annotated[Any, interval(0, 1)]
    gamma: Annotated[Any, interval(0, 1)]
    k: Annotated[Any, at_least(1)]
    capacity: Annotated[Any, at_least(1)]
    projection_dim: Annotated[Any, at_least(1)]
    memo: Annotated[Any, at_least(0)]
    blas_threads: Annotated[Any, int_at_least_or_none(1)]
    projection: Annotated[Any, one_of(PROJECTIONS)]


class MFEC(Agent):
    """Model-free episodic control agent.

    Parameters
    ----------
    env
        Environment with ``Box`` (any shape, flattened) or ``Discrete`` (one-hot coded)
        observations and ``Discrete`` actions.
    epsilon
        Exploration rate (docs/paper-settings.md: 0.1).
    gamma
        Discount factor of the returns (0.97).
    k
        Nearest neighbours averaged for an unseen key (3).
    capacity
        Keys per action buffer (2000); the oldest is evicted when full.
    projection
        ``"gaussian"`` random projection (default) or ``"none"``.
    projection_dim
        Dimension of the projected keys (256).
    memo
        Distinct observations whose projected key is remembered (4096; ``0``: no memo, no
        estimate memo). Exact: it changes no result, only the time (module docstring).
    blas_threads
        Threads of numpy's OpenBLAS, set when the agent is built (1; ``None`` leaves it): one
        projection per step is memory-bound and a second thread on shared cores slows it down
        (:mod:`cobelrun.agents.blas`; the results do not depend on it). Process-wide, like
        DQN's ``torch_threads``.
    seed
        Seed of the projection matrix and of exploration.
    """

    observation_spaces = (gym.spaces.Box, gym.spaces.Discrete)
    action_spaces = (gym.spaces.Discrete,)

    def __init__(
        self,
        env: gym.Env,
        *,
        epsilon: float = 0.1,
        gamma: float = 0.97,
        k: int = 3,
        capacity: int = 2000,
        projection: str = "gaussian",
        projection_dim: int = 256,
        memo: int = 4096,
        blas_threads: int | None = 1,
        seed: SeedLike = None,
    ) -> None:
        super().__init__(env, seed=seed)
        validate_args(MFECArgs, locals())
        if blas_threads is not None:
            from cobelrun.agents.blas import set_blas_threads

            set_blas_threads(blas_threads)
        self.epsilon, self.gamma, self.k, self.capacity = float(epsilon), float(gamma), k, capacity
        self.projection = projection
        space = env.observation_space
        self.discrete_obs = isinstance(space, gym.spaces.Discrete)
        self.obs_dim = int(space.n) if self.discrete_obs else int(np.prod(space.shape))
        self.n_actions = int(env.action_space.n)
        proj_rng = np.random.default_rng(self.seed_sequence.spawn(1)[0])
        if projection == "gaussian":
            self.matrix = proj_rng.normal(0.0, 1.0 / np.sqrt(projection_dim),
                                          size=(self.obs_dim, projection_dim))  # fmt: skip
            self.key_dim = projection_dim
        else:
            self.matrix = None
            self.key_dim = self.obs_dim
        self.buffers = [EpisodicBuffer(capacity, self.key_dim) for _ in range(self.n_actions)]
        self.memo = memo
        self._keys: dict[bytes, np.ndarray] = {}  # observation digest -> projected key

    def hyperparameters(self) -> dict[str, Any]:
        return {"epsilon": self.epsilon, "gamma": self.gamma, "k": self.k,
                "capacity": self.capacity, "projection": self.projection,
                "key_dim": self.key_dim}  # fmt: skip

    # -- keys and estimates ---------------------------------------------------------------------
    def keys(self, observations: Any) -> np.ndarray:
        """Projected keys ``(n, key_dim)`` of a batch of observations."""
        if self.discrete_obs:
            idx = np.asarray(observations, dtype=np.int64).reshape(-1)
            x = np.zeros((idx.size, self.obs_dim))
            x[np.arange(idx.size), idx] = 1.0
        else:
            x = np.asarray(observations, dtype=np.float64).reshape(-1, self.obs_dim)
        return x @ self.matrix if self.matrix is not None else x

    def key(self, observation: Any) -> tuple[np.ndarray, bytes | None]:
        """Projected key of one observation and its digest (``None`` without memo).

        The key is computed exactly as by :meth:`keys` (same product, same bits) the first time
        an observation is seen and then reused; it is read-only.
        """
        if self.memo == 0 or self.discrete_obs:
            return self.keys(observation)[0], None
        x = np.ascontiguousarray(observation)
        tag = hashlib.blake2b(x.view(np.uint8), digest_size=16).digest()
        key = self._keys.get(tag)
        if key is None:
            key = self.keys(x)[0]
            key.flags.writeable = False
            if len(self._keys) >= self.memo:
                self._keys.clear()
            self._keys[tag] = key
        return key, tag

    def _q(self, key: np.ndarray, tag: bytes | None = None) -> np.ndarray:
        return np.array([b.estimate(key, self.k, tag) for b in self.buffers])

    def predict(self, observations: np.ndarray) -> np.ndarray:
        """Q estimates ``(n, A)`` of a batch of observations."""
        return np.array([self._q(key) for key in self.keys(observations)])

    # -- trials (the base loop) ------------------------------------------------------------------
    def begin_trial(self, obs: Any, info: dict[str, Any], learn: bool) -> None:
        self._trial: list[tuple[np.ndarray, int, float]] = []  # (key, action, reward) per step
        self._key: np.ndarray | None = None

    def act(self, obs: Any, info: dict[str, Any], learn: bool) -> int:
        """Epsilon-greedy over the estimates, ties broken at random."""
        key, tag = self.key(obs)
        self._key = key
        return epsilon_greedy(self.rng, self._q(key, tag), self.epsilon)

    def observe(self, t: Transition, learn: bool) -> None:
        assert self._key is not None
        self._trial.append((self._key, t.action, t.reward))

    def end_trial(self, learn: bool) -> None:
        """Learn from the trial's discounted returns (module docstring)."""
        if learn:
            ret = 0.0
            for key, a, r in reversed(self._trial):
                ret = r + self.gamma * ret
                self.buffers[a].update(key, ret)
        self._trial = []

    # -- persistence ------------------------------------------------------------------------------
    def state_schema(self) -> dict[str, ArraySpec]:
        """The projection (if any) and every buffer's keys, values, insertion times and clock."""
        schema: dict[str, ArraySpec] = {}
        if self.matrix is not None:
            schema["projection"] = ArraySpec(self.matrix.shape, "f")
        for a in range(self.n_actions):
            schema[f"a{a}.keys"] = ArraySpec((None, self.key_dim), "f")
            schema[f"a{a}.values"] = ArraySpec((None,), "f")
            schema[f"a{a}.times"] = ArraySpec((None,), "i", low=0)
            schema[f"a{a}.clock"] = ArraySpec((), "i", low=0)
        return schema

    def get_state(self) -> dict[str, np.ndarray]:
        arrays: dict[str, np.ndarray] = {}
        if self.matrix is not None:
            arrays["projection"] = self.matrix
        for a, buf in enumerate(self.buffers):
            arrays.update({f"a{a}.{k}": v for k, v in buf.state().items()})
        return arrays

    def check_state(self, arrays: Mapping[str, np.ndarray]) -> None:
        for a in range(self.n_actions):
            keys, n = arrays[f"a{a}.keys"], len(arrays[f"a{a}.values"])
            if len(keys) != n or len(arrays[f"a{a}.times"]) != n:
                raise ValueError(f"buffer a{a}: keys, values and times differ in length")
            if n > self.capacity:
                raise ValueError(f"buffer a{a} holds {n} keys, capacity is {self.capacity}")
            if len({k.tobytes() for k in keys}) != n:
                raise ValueError(f"buffer a{a} holds duplicate keys")

    def set_state(self, arrays: Mapping[str, np.ndarray]) -> None:
        if self.matrix is not None:
            self.matrix = np.array(arrays["projection"], dtype=np.float64)
            self._keys.clear()
        for a, buf in enumerate(self.buffers):
            buf.load({k: arrays[f"a{a}.{k}"] for k in ("keys", "values", "times", "clock")})
