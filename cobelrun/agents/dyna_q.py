"""Tabular Dyna-Q (Sutton 1990) as used for the paper's Fig. 6B.

The update rule, top to bottom (one step):

1. pick ``a`` in ``s`` (epsilon-greedy with random tie-break, or softmax(beta));
2. observe ``r, s'`` and Q-learn online: ``Q[s,a] += lr * (r + gamma * max Q[s'] - Q[s,a])``
   (no bootstrap from terminal states);
3. store the experience in the tabular model memory;
4. replay ``replay_batch`` experiences sampled from the memory with the same update
   (after every step, once at trial end, or never).

On environments with a known model (the ``tabular_model`` contract: ``GridWorldEnv`` and its
variants) whole trials run in compiled code (:func:`cobelrun.agents.kernels.run_trials`); with
callbacks, or on other environments with discrete observations, trials run step by step through
the base class's loop (:meth:`~cobelrun.agents.base.Agent._run`), whose hooks call the same
compiled building blocks in the same order, so both give identical results for the same seeds.
Action selection is :func:`cobelrun.agents.kernels.select_action`, the numba twin of
:func:`cobelrun.agents.policy.select`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Annotated, Any

import gymnasium as gym
import numpy as np

from cobelrun.agents.base import (
    Agent,
    ArraySpec,
    SeedLike,
    Transition,
    TrialCallback,
    state_indices,
)
from cobelrun.agents.codes import POLICIES, REPLAY_MODES, REPLAY_STEP, REPLAY_TRIAL_END
from cobelrun.agents.memory import TabularMemory
from cobelrun.agents.schema import AgentArgs, at_least, interval, number_at_least, validate_args
from cobelrun.envs.base import TabularModel, require, supports
from cobelrun.errors import ConfigError, allowed_list, suggest
from cobelrun.records import TrialBatch
from cobelrun.safety import check_allocation
from cobelrun.signals import critical

ENGINES = ("auto", "compiled", "python")

# placeholders for the table the kernel does not read (deterministic or stochastic worlds)
_NO_NEXT_STATE = np.zeros((1, 1), np.int64)
_NO_T_CUM = np.zeros((1, 1, 1))


def _choice(kind: str, value: str, allowed: Sequence[str]) -> str:
    if value not in allowed:
        raise ConfigError(
            f"{kind} {value!r} is not known{suggest(value, allowed)}; allowed: {allowed_list(allowed)}"
        )
    return value


#: bytes per state-action pair: Q (float64) and the model memory's reward, next state,
#: terminal and visited arrays
TABLE_BYTES_PER_PAIR = 8 + 8 + 8 + 1 + 1 + 8
#: bytes per experience of a replay batch (sampled index, state, action, reward, target)
REPLAY_BYTES_PER_SAMPLE = 64


class DynaQArgs(AgentArgs):
    """The ranges of :class:`DynaQ`'s arguments (checked in this order)."""

    epsilon: Annotated[Any, interval(0.0, 1.0)]
    learning_rate: Annotated[Any, interval(0.0, 1.0)]
    gamma: Annotated[Any, interval(0.0, 1.0)]
    beta: Annotated[Any, number_at_least(0)]
    replay_batch: Annotated[Any, at_least(0)]


class DynaQ(Agent):
    """Tabular Dyna-Q agent.

    Parameters
    ----------
    env
        Environment with a ``Discrete`` observation space (the state index).
    epsilon
        Exploration rate of the epsilon-greedy policy (CoBeL-RL default 0.3; Fig. 6B: 0.1).
    beta
        Inverse temperature of the softmax policy (default 5).
    learning_rate
        Q-learning rate (default 0.9).
    gamma
        Discount factor (default 0.99; Fig. 6B: 0.9).
    policy
        ``"epsilon_greedy"`` (default) or ``"softmax"``.
    action_mask
        If true, drop actions that cannot move the agent (walls) from choice and from max.
    replay
        ``"step"`` (replay after every step, default), ``"trial_end"`` or ``"off"``.
    replay_batch
        Experiences replayed each time (Fig. 6B: 5; default 20).
    memory_sampling
        ``"all"``: uniformly over all state-action pairs, as the original (default);
        ``"visited"``: only over experienced pairs.
    memory_reward_rate
        Rate of the model memory's running reward average (0.9 in the original).
    engine
        ``"auto"`` (compiled trial loop when the env is tabular and no callbacks are given),
        ``"compiled"`` (require it) or ``"python"`` (always step by step).
    seed
        Seed of the agent's draws (exploration and replay sampling).
    """

    observation_spaces = (gym.spaces.Discrete,)
    action_spaces = (gym.spaces.Discrete,)

    def __init__(
        self,
        env: gym.Env,
        *,
        epsilon: float = 0.3,
        beta: float = 5.0,
        learning_rate: float = 0.9,
        gamma: float = 0.99,
        policy: str = "epsilon_greedy",
        action_mask: bool = False,
        replay: str = "step",
        replay_batch: int = 20,
        memory_sampling: str = "all",
        memory_reward_rate: float = 0.9,
        engine: str = "auto",
        seed: SeedLike = None,
    ) -> None:
        super().__init__(env, seed=seed)
        validate_args(DynaQArgs, locals())
        self.epsilon, self.beta = float(epsilon), float(beta)
        self.learning_rate, self.gamma = float(learning_rate), float(gamma)
        self.policy = _choice("agent.policy", policy, list(POLICIES))
        self.replay = _choice("agent.replay", replay, list(REPLAY_MODES))
        self.engine = _choice("agent.engine", engine, ENGINES)
        self.replay_batch = int(replay_batch)
        self.use_mask = bool(action_mask)

        base = env.unwrapped
        self.n_states = int(env.observation_space.n)
        self.n_actions = int(env.action_space.n)
        self.tabular = supports(base, TabularModel)  # remembered per env (~25 us each)
        self._all_allowed: np.ndarray | None = None
        if self.engine == "compiled":
            require(env, ("tabular_model",), "agent.engine 'compiled' (use 'auto' or 'python')")
        if self.use_mask:
            require(env, ("tabular_model",), "agent.action_mask")
        n_pairs = self.n_states * self.n_actions
        check_allocation("agent", n_pairs * TABLE_BYTES_PER_PAIR,
                         f"its Q table and model memory ({self.n_states:,} states x "
                         f"{self.n_actions} actions)", "use a smaller env")  # fmt: skip
        check_allocation("agent.replay_batch", self.replay_batch * REPLAY_BYTES_PER_SAMPLE,
                         f"a batch of {self.replay_batch:,} replayed experiences",
                         "lower agent.replay_batch")  # fmt: skip
        self.Q = np.zeros((self.n_states, self.n_actions))
        self.memory = TabularMemory(
            self.n_states, self.n_actions, reward_rate=memory_reward_rate, sampling=memory_sampling
        )

    # -- helpers -------------------------------------------------------------------------
    def _mask(self) -> np.ndarray:
        if self.use_mask:
            return np.ascontiguousarray(self.env.unwrapped.action_mask(), dtype=np.bool_)
        if self._all_allowed is None:  # read by the kernels only when use_mask is on
            self._all_allowed = np.ones((self.n_states, self.n_actions), dtype=np.bool_)
        return self._all_allowed

    def _params(self) -> tuple:
        return (
            POLICIES[self.policy],
            self.epsilon,
            self.beta,
            self.learning_rate,
            self.gamma,
            REPLAY_MODES[self.replay],
            self.replay_batch,
            self.memory.sampling_code,
        )

    def _use_compiled(self, callbacks: Sequence[TrialCallback]) -> bool:
        if self.engine == "python":
            return False
        if callbacks and not all(cb.trial_end_only() for cb in callbacks):
            if self.engine == "compiled":
                raise ConfigError("agent.engine 'compiled' cannot run per-step callbacks")
            return False
        if self.tabular and self.env.unwrapped.world.reward_sd > 0.0:
            # the trial kernel reads exact rewards; noisy ones come from the env's step
            if self.engine == "compiled":
                raise ConfigError(
                    "agent.engine 'compiled' needs exact rewards (env.world.reward_sd = 0); "
                    "use 'auto' or 'python'"
                )
            return False
        return self.tabular

    # -- trials ----------------------------------------------------------------------------
    def _run(
        self, n_trials: int, max_steps: int, learn: bool, callbacks: Sequence[TrialCallback]
    ) -> TrialBatch:
        if self._use_compiled(callbacks):
            if not callbacks:
                return self._run_compiled(n_trials, max_steps, learn)
            # trial-end hooks only (activity snapshots, greedy probes): compiled trial by
            # trial, the hooks between trials; the same draws as one call, so the same results
            batches = []
            for trial in range(n_trials):
                b = self._run_compiled(1, max_steps, learn)
                record = {"states": [int(b.start_state[0]), *b.step_next_state.tolist()],
                          "actions": b.step_action.tolist(), "rewards": b.step_reward.tolist(),
                          "terminated": bool(b.terminated[0])}  # fmt: skip
                for cb in callbacks:
                    cb.on_trial_end(self, trial, record)
                batches.append(b)
            return TrialBatch.concat(batches)
        # the Python engine: the base step loop with the same compiled building blocks, called
        # in the same order as run_trials, so both engines give identical results
        import cobelrun.agents.kernels as kernels

        self._k = kernels
        self._loop_mask = self._mask()
        self._loop_params = self._params()
        return super()._run(n_trials, max_steps, learn, callbacks)

    def _run_compiled(self, n_trials: int, max_steps: int, learn: bool) -> TrialBatch:
        from cobelrun.agents.kernels import run_trials  # numba: imported on first use

        base = self.env.unwrapped
        world = base.world
        det_table = world.next_state
        deterministic = det_table is not None
        starts = np.ascontiguousarray(world.starts, np.int64)
        if deterministic:
            next_state, T_cum = det_table, _NO_T_CUM
        else:
            next_state, T_cum = _NO_NEXT_STATE, self._cumulative(world.T)
        # a deterministic world with one start state draws nothing from the env's generator:
        # leave it out (handing a Generator to compiled code costs ~10-30 us per call)
        env_rng = None if deterministic and starts.shape[0] <= 1 else base.np_random
        cap = n_trials * max_steps
        step_ints = np.empty((3, cap), np.int64)  # state, action, next state
        step_reward = np.empty(cap, np.float64)
        trial_ints = np.empty((3, n_trials), np.int64)  # steps, start, end
        reward = np.empty(n_trials, np.float64)
        term = np.empty(n_trials, np.bool_)
        offsets = np.zeros(n_trials + 1, np.int64)
        with critical():  # a signal inside the kernel's generator access corrupts it
            total = run_trials(
                self.rng, env_rng, self.Q, self._mask(), self.use_mask,
                *self.memory.arrays(), self.memory.reward_rate,
                deterministic, next_state, T_cum,
                np.ascontiguousarray(world.rewards, np.float64),
                np.ascontiguousarray(world.terminal, np.bool_), starts,
                *self._params(), n_trials, max_steps, learn,
                step_ints[0], step_ints[1], step_ints[2], step_reward,
                trial_ints[0], term, trial_ints[1], trial_ints[2], reward, offsets,
            )  # fmt: skip
        steps = step_ints[:, :total].copy()
        return TrialBatch(
            start_state=trial_ints[1],
            end_state=trial_ints[2],
            steps=trial_ints[0],
            reward=reward,
            terminated=term,
            offsets=offsets,
            step_state=steps[0],
            step_action=steps[1],
            step_next_state=steps[2],
            step_reward=step_reward[:total].copy(),
        )

    def _cumulative(self, T: np.ndarray) -> np.ndarray:
        """Cumulative transition probabilities of a stochastic world, kept while ``T`` is
        the same (read-only) array."""
        cached = getattr(self, "_T_cum", None)
        if cached is None or cached[0] is not T:
            cached = (T, np.cumsum(T, axis=2))
            self._T_cum = cached
        return cached[1]

    def act(self, obs: Any, info: dict[str, Any], learn: bool) -> int:
        s = int(obs)
        policy, eps, beta = self._loop_params[:3]
        return int(
            self._k.select_action(self.rng, self.Q[s], self._loop_mask[s], self.use_mask,
                                  policy, eps, beta)
        )  # fmt: skip

    def observe(self, t: Transition, learn: bool) -> None:
        if not learn:
            return
        s, s2 = int(t.obs), int(t.next_obs)
        self._k.q_update(self.Q, self._loop_mask, self.use_mask, s, t.action, t.reward, s2,
                         t.terminated, self.learning_rate, self.gamma)  # fmt: skip
        self.memory.store(s, t.action, t.reward, s2, t.terminated)
        if self._loop_params[5] == REPLAY_STEP:
            self._replay(self._loop_mask, self.replay_batch)

    def end_trial(self, learn: bool) -> None:
        if learn and self._loop_params[5] == REPLAY_TRIAL_END:
            self._replay(self._loop_mask, self.replay_batch)

    def _replay(self, mask: np.ndarray, n: int) -> None:
        from cobelrun.agents.kernels import replay

        m = self.memory
        replay(self.rng, self.Q, mask, self.use_mask, m.next_state, m.reward, m.terminal,
               m.visited_list, m.n_visited, m.sampling_code, n, self.learning_rate, self.gamma)  # fmt: skip

    # -- inference and persistence ---------------------------------------------------------
    def predict(self, observations: np.ndarray) -> np.ndarray:
        obs = state_indices(observations, self.n_states)
        return self.Q[obs].copy()

    def hyperparameters(self) -> dict[str, Any]:
        return {
            "epsilon": self.epsilon, "beta": self.beta, "learning_rate": self.learning_rate,
            "gamma": self.gamma, "policy": self.policy, "action_mask": self.use_mask,
            "replay": self.replay, "replay_batch": self.replay_batch,
            "memory_sampling": self.memory.sampling,
            "memory_reward_rate": self.memory.reward_rate,
        }  # fmt: skip

    def state_schema(self) -> dict[str, ArraySpec]:
        S, A = self.n_states, self.n_actions
        return {"Q": ArraySpec((S, A), "f"), **self.memory.state_schema()}

    def get_state(self) -> dict[str, np.ndarray]:
        return {"Q": self.Q, **self.memory.state_dict()}

    def set_state(self, arrays: Mapping[str, np.ndarray]) -> None:
        self.Q[...] = arrays["Q"]
        self.memory.load_state_dict(arrays)
