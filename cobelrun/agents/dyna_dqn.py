"""Dyna-DQN: Dyna-Q's structure with a neural Q-function (CoBeL-RL, paper section 2.1.3).

The agent acts in a tabular environment (a :class:`~cobelrun.envs.GridWorldEnv` or one of its
variants) but sees each state through an observation vector: the environment's
``observations`` matrix (``DiscreteGridWorldEnv``; one-hot by default) or, for an environment
that only gives state indices, a one-hot code generated here (as the original did when no
observations were given). Experience goes into a :class:`~cobelrun.agents.memory.TabularMemory`
(the Dyna model); learning replays batches from it.

One step, top to bottom:

1. pick ``a`` in ``s`` from ``Q(o_s)`` (epsilon-greedy with random tie-break, or softmax(beta);
   optionally only among actions that move the agent);
2. observe ``r, s'``; store ``(s, a) -> (r, s', terminal)`` in the model memory;
3. replay: the current experience plus ``replay_batch`` experiences sampled from the memory,
   one gradient step on ``(y - Q(o_s)[a])^2`` with ``y = r + gamma * max_a' Q_target(o_s')[a']``
   (no bootstrap from terminal states unless ``always_bootstrap``);
4. soft target update ``theta_target <- tau * theta + (1 - tau) * theta_target``.

:class:`DynaDeepAgent` holds what Dyna-DQN and Dyna-DSR share (trial loop, memory, policy,
observations, persistence); subclasses implement :meth:`~DynaDeepAgent.q_values` and
:meth:`~DynaDeepAgent.update`.
"""

from __future__ import annotations

import abc
from collections.abc import Mapping, Sequence
from typing import Annotated, Any, ClassVar

import gymnasium as gym
import numpy as np

from cobelrun.agents.base import (
    Agent,
    ArraySpec,
    SeedLike,
    Transition,
    TrialCallback,
    layer_sizes,
)
from cobelrun.agents.dyna_q import TABLE_BYTES_PER_PAIR
from cobelrun.agents.memory import TabularMemory
from cobelrun.agents.networks import Network, build_network, set_torch_threads
from cobelrun.agents.policy import allowed_next, check_policy, select
from cobelrun.agents.schema import AgentArgs, at_least, interval, validate_args
from cobelrun.envs.base import StateObservations
from cobelrun.errors import ConfigError
from cobelrun.records import TrialBatch
from cobelrun.safety import check_allocation


class DynaDeepArgs(AgentArgs):
    """The ranges of :class:`DynaDeepAgent`'s arguments (checked in this order)."""

    epsilon: Annotated[Any, interval(0.0, 1.0)]
    gamma: Annotated[Any, interval(0.0, 1.0)]
    target_tau: Annotated[Any, interval(0.0, 1.0)]
    replay_batch: Annotated[Any, at_least(0)]


class DynaDeepAgent(Agent):
    """Shared machinery of the deep Dyna agents (see the module docstring).

    Parameters
    ----------
    env
        A tabular environment (has ``world``): ``Discrete`` (state index) or ``Box``
        (``DiscreteGridWorldEnv``) observations.
    epsilon, beta, policy
        Exploration: epsilon-greedy (default) or softmax with inverse temperature ``beta``.
    gamma
        Discount factor.
    learning_rate
        Adam learning rate of the networks.
    hidden, activation
        Hidden layers of the networks (Fig. 7: [64, 64], tanh).
    target_tau
        Soft target update rate (Fig. 7: 0.01); 1 copies the online network every step.
    replay_batch
        Experiences replayed from the model memory per step, besides the current one.
    always_bootstrap
        Bootstrap from terminal states too (Fig. 7's Dyna-DSR does).
    action_mask
        Choose only among actions that can move the agent.
    memory_sampling, memory_reward_rate
        :class:`~cobelrun.agents.memory.TabularMemory` settings (``"all"``: the original's).
    observations
        (S, d) observation of each state; default: the environment's, else one-hot.
    backend
        Network backend (:data:`cobelrun.agents.networks.BACKENDS`; ``"torch"``).
    torch_threads
        torch intra-op threads (default 1).
    seed
        Seed of exploration, replay sampling and weight initialisation.
    """

    observation_spaces = (gym.spaces.Discrete, gym.spaces.Box)
    action_spaces = (gym.spaces.Discrete,)
    requires = ("tabular_model",)
    batchable = True
    #: what the batched learner stacks (:mod:`cobelrun.agents.batched_dyna`): a Q network
    #: (``"q"``) or successor features plus a reward model (``"successor"``)
    batched_kind: ClassVar[str] = "q"

    def __init__(
        self,
        env: gym.Env,
        *,
        epsilon: float = 0.3,
        beta: float = 5.0,
        policy: str = "epsilon_greedy",
        gamma: float = 0.9,
        learning_rate: float = 1e-3,
        hidden: Sequence[int] = (64, 64),
        activation: str = "tanh",
        target_tau: float = 0.01,
        replay_batch: int = 32,
        always_bootstrap: bool = False,
        action_mask: bool = False,
        memory_sampling: str = "all",
        memory_reward_rate: float = 0.9,
        observations: Any = None,
        backend: str = "torch",
        torch_threads: int | None = 1,
        seed: SeedLike = None,
    ) -> None:
        super().__init__(env, seed=seed)
        base = env.unwrapped
        validate_args(DynaDeepArgs, locals())
        check_policy(policy)
        set_torch_threads(torch_threads)
        self.epsilon, self.beta, self.policy = float(epsilon), float(beta), policy
        self.gamma, self.learning_rate = float(gamma), float(learning_rate)
        self.hidden, self.activation = layer_sizes("agent.hidden", hidden), activation
        self.target_tau, self.replay_batch = float(target_tau), int(replay_batch)
        self.always_bootstrap, self.use_mask = bool(always_bootstrap), bool(action_mask)
        self.backend = backend
        self.n_states = int(base.world.n_states)
        self.n_actions = int(env.action_space.n)
        check_allocation("agent", self.n_states * self.n_actions * TABLE_BYTES_PER_PAIR,
                         f"its model memory ({self.n_states:,} states x {self.n_actions} actions)",
                         "use a smaller env")  # fmt: skip
        self.obs = self._observation_matrix(env, observations)
        self.memory = TabularMemory(
            self.n_states, self.n_actions, reward_rate=memory_reward_rate, sampling=memory_sampling
        )
        self._net_seeds = [int(s) for s in self.seed_sequence.generate_state(4)]
        self.build_networks()
        width = self.obs.shape[1] + sum(self.hidden) + self.n_actions
        check_allocation("agent.replay_batch", (self.replay_batch + 1) * width * 4 * 6,
                         f"a batch of {self.replay_batch + 1:,} replayed experiences through "
                         f"layers of {width:,} units (observations, activations, gradients)",
                         "lower agent.replay_batch or agent.hidden")  # fmt: skip

    # -- construction helpers ----------------------------------------------------------------
    def _observation_matrix(self, env: gym.Env, observations: Any) -> np.ndarray:
        base = env.unwrapped
        if observations is None and isinstance(base, StateObservations):
            observations = base.observations
        if observations is None:
            check_allocation("agent.observations", self.n_states**2 * 4,
                             f"one-hot observations of {self.n_states:,} states",
                             "use a smaller env or give agent.observations")  # fmt: skip
            return np.eye(self.n_states, dtype=np.float32)
        obs = np.asarray(observations, dtype=np.float32)
        if obs.ndim != 2 or obs.shape[0] != self.n_states:
            raise ConfigError(
                f"agent.observations must have shape (S={self.n_states}, d), got {obs.shape}"
            )
        return obs

    def network(self, output_dim: int, n_heads: int = 1, seed_index: int = 0, **kw: Any) -> Network:
        """A network of the agent's backend, hidden layers and learning rate."""
        kwargs: dict[str, Any] = {"hidden": self.hidden, "activation": self.activation,
                                  "learning_rate": self.learning_rate, "n_heads": n_heads,
                                  "seed": self._net_seeds[seed_index]}  # fmt: skip
        kwargs.update(kw)
        return build_network(self.backend, self.obs.shape[1], output_dim, **kwargs)

    def _mask(self) -> np.ndarray:
        if self.use_mask:
            return np.asarray(self.env.unwrapped.action_mask(), dtype=bool)
        return np.ones((self.n_states, self.n_actions), dtype=bool)

    # -- what subclasses define ---------------------------------------------------------------
    @abc.abstractmethod
    def build_networks(self) -> None:
        """Create the online and target networks."""

    @abc.abstractmethod
    def q_values(self, states: np.ndarray) -> np.ndarray:
        """Action values ``(n, A)`` of states (indices)."""

    @abc.abstractmethod
    def update(
        self, s: np.ndarray, a: np.ndarray, r: np.ndarray, s2: np.ndarray, terminal: np.ndarray,
        mask: np.ndarray,
    ) -> None:  # fmt: skip
        """One learning step on a batch of experiences (state indices)."""

    @abc.abstractmethod
    def networks(self) -> dict[str, Network]:
        """The agent's networks by name (saved, and used for activations)."""

    # -- trials (the base loop) ----------------------------------------------------------------
    def _run(
        self, n_trials: int, max_steps: int, learn: bool, callbacks: Sequence[TrialCallback]
    ) -> TrialBatch:
        self._loop_mask = self._mask()
        return super()._run(n_trials, max_steps, learn, callbacks)

    def act(self, obs: Any, info: dict[str, Any], learn: bool) -> int:
        """Epsilon-greedy with random tie-break, or softmax(beta), over the allowed actions."""
        s = int(info["state"])
        q = self.q_values(np.array([s]))[0]
        allowed = self._loop_mask[s] if self.use_mask else None
        return select(self.rng, q, self.policy, self.epsilon, self.beta, allowed)

    def observe(self, t: Transition, learn: bool) -> None:
        """Store the step in the model memory and replay (when learning)."""
        if learn:
            self.memory.store(t.state, t.action, t.reward, t.next_state, t.terminated)
            self._learn(t.state, t.action, self._loop_mask)

    def _learn(self, s: int, a: int, mask: np.ndarray) -> None:
        """Replay the current experience plus ``replay_batch`` from the model memory."""
        mem = self.memory
        rs, ra = mem.sample(self.rng, self.replay_batch)
        S = np.concatenate([[s], rs]).astype(np.int64)
        A = np.concatenate([[a], ra]).astype(np.int64)
        self.update(S, A, mem.reward[S, A], mem.next_state[S, A], mem.terminal[S, A], mask)

    # -- batched runs ----------------------------------------------------------------------------
    def batch_unsupported(self) -> str | None:
        from cobelrun.agents.batched_dyna import unsupported

        return unsupported(self)

    def batch_learner(
        self, seeds: Sequence[np.random.SeedSequence], steps: int, make: Any = None
    ) -> Any:
        """:class:`~cobelrun.agents.batched_dyna.BatchedDyna`: one agent per seed (built with
        ``make``), networks stacked."""
        from cobelrun.agents.batched_dyna import BatchedDyna

        if make is None:
            raise ValueError("batched Dyna runs need make(seed=...) to build each run's agent")
        agents = [self if i == 0 and s is self.seed_sequence else make(seed=s)
                  for i, s in enumerate(seeds)]  # fmt: skip
        return BatchedDyna(agents, successor=self.batched_kind == "successor")

    # -- inference -------------------------------------------------------------------------------
    def _states_of(self, observations: np.ndarray) -> np.ndarray | None:
        obs = np.asarray(observations)
        if obs.ndim == 1 and np.issubdtype(obs.dtype, np.integer):
            return obs.astype(np.int64)
        return None

    def predict(self, observations: np.ndarray) -> np.ndarray:
        """Q values ``(n, A)`` of a batch of observation vectors (or state indices)."""
        states = self._states_of(observations)
        if states is not None:
            return self.q_values(states)
        return self.q_from_observations(np.asarray(observations, dtype=np.float32).reshape(
            -1, self.obs.shape[1]))  # fmt: skip

    @abc.abstractmethod
    def q_from_observations(self, obs: np.ndarray) -> np.ndarray:
        """Action values ``(n, A)`` of observation vectors."""

    def layer_names(self) -> list[str]:
        return [f"{net}/{layer}" for net, n in self.networks().items() for layer in n.layer_names()]

    def activations(self, observations: np.ndarray, layers: Sequence[str]) -> dict[str, np.ndarray]:
        """Layer outputs ``(n, units)`` of the named layers (``"NETWORK/LAYER"``)."""
        states = self._states_of(observations)
        x = self.obs[states] if states is not None else np.asarray(observations, np.float32)
        nets = self.networks()
        out = {}
        for name in layers:
            net, _, layer = name.partition("/")
            if net not in nets or layer not in nets[net].layer_names():
                raise ConfigError(
                    f"unknown layer {name!r}; allowed: {', '.join(self.layer_names())}"
                )
            out[name] = nets[net].activations(x, [layer])[layer]
        return out

    # -- persistence -------------------------------------------------------------------------------
    def hyperparameters(self) -> dict[str, Any]:
        return {
            "epsilon": self.epsilon, "beta": self.beta, "policy": self.policy, "gamma": self.gamma,
            "learning_rate": self.learning_rate, "hidden": self.hidden,
            "activation": self.activation, "target_tau": self.target_tau,
            "replay_batch": self.replay_batch, "always_bootstrap": self.always_bootstrap,
            "action_mask": self.use_mask, "memory_sampling": self.memory.sampling,
        }  # fmt: skip

    def _all_networks(self) -> dict[str, Network]:
        """Networks to save: :meth:`networks` plus their targets."""
        return self.networks()

    def state_schema(self) -> dict[str, ArraySpec]:
        """Every network weight (its current shape, finite) and the model memory."""
        schema = {
            f"{name}.{k}": ArraySpec(v.shape, "f")
            for name, net in self._all_networks().items()
            for k, v in net.get_weights().items()
        }
        return {**schema, **self.memory.state_schema()}

    def get_state(self) -> dict[str, np.ndarray]:
        arrays = {
            f"{name}.{k}": v
            for name, net in self._all_networks().items()
            for k, v in net.get_weights().items()
        }
        return {**arrays, **self.memory.state_dict()}

    def set_state(self, arrays: Mapping[str, np.ndarray]) -> None:
        for name, net in self._all_networks().items():
            prefix = f"{name}."
            net.set_weights(
                {k[len(prefix) :]: v for k, v in arrays.items() if k.startswith(prefix)}
            )
        self.memory.load_state_dict(arrays)


class DynaDQN(DynaDeepAgent):
    """Dyna-DQN: a Q network over observations, trained by replay from a tabular model memory.

    Parameters are those of :class:`DynaDeepAgent`.
    """

    def build_networks(self) -> None:
        self.q_net = self.network(self.n_actions, seed_index=0)
        self.q_target = self.q_net.clone()

    def networks(self) -> dict[str, Network]:
        return {"q": self.q_net}

    def _all_networks(self) -> dict[str, Network]:
        return {"q": self.q_net, "q_target": self.q_target}

    def q_from_observations(self, obs: np.ndarray) -> np.ndarray:
        return self.q_net.predict(obs)[0]

    def q_values(self, states: np.ndarray) -> np.ndarray:
        return self.q_net.predict(self.obs[states])[0]

    def update(self, s, a, r, s2, terminal, mask) -> None:  # type: ignore[override]
        q_next = self.q_target.predict(self.obs[s2])[0]
        if self.use_mask:
            q_next = np.where(allowed_next(mask, s2), q_next, -np.inf)
        cont = np.ones_like(r) if self.always_bootstrap else 1.0 - terminal
        y = r + self.gamma * q_next.max(axis=1) * cont
        self.q_net.train_step(self.obs[s], y, columns=a)
        self.q_target.blend_from(self.q_net, self.target_tau)
