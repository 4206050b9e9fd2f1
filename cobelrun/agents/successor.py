"""Tabular successor-representation agents (Russek et al. 2017) and a value-iteration baseline.

All SR agents value actions as ``Q(s, a) = M(s, a, :) . w`` with one shared core,
:class:`SuccessorCore`:

* ``w(s')`` predicts the reward received on arriving in ``s'``:
  ``w(s') += lr_w (r - w(s'))``;
* ``M(s, a, s')`` is the expected discounted number of future arrivals in ``s'`` after taking
  ``a`` in ``s`` and then following the greedy policy:
  ``M(s, a, :) = E[1_{s_1} + gamma 1_{s_2} + ...]``.

They differ only in how ``M`` is learned:

* :class:`SRTD` (SR-TD): temporal differences on experienced transitions,
  ``M(s,a,:) += lr (1_{s'} + gamma M(s', a*, :) - M(s,a,:))`` with ``a* = argmax_b Q(s', b)``
  (no bootstrap from terminal ``s'``);
* :class:`SRDyna` (SR-Dyna): SR-TD plus, after every step, ``replay_batch`` TD updates on
  experiences sampled uniformly from a model of experienced transitions (the last ``s'`` of
  each experienced ``(s, a)``), with ``a*`` greedy under the current values;
* :class:`SRMB` (SR-MB): computes ``M`` from a learned one-step model ``T(s, a, s')`` and a
  cached policy ``pi(s, .)`` (the greedy policy the last time the agent acted in ``s``: uniform
  over the best actions; uniform over all actions in states never acted in):
  ``M(s, a, :) = T(s, a, :) (I - gamma T_pi)^-1`` with terminal rows of ``T_pi`` zero.

:class:`ValueIteration` learns the same one-step model and ``w`` and plans from scratch by value
iteration before every action: fully model-based, it is the ceiling of the revaluation tasks.

SR-TD, SR-Dyna and SR-MB run whole trials in compiled code on tabular gridworlds
(:func:`cobelrun.agents.sr_kernels.run_sr_trials`,
:func:`cobelrun.agents.srmb_kernels.run_srmb_trials`); with per-step callbacks, noisy rewards
or ``engine="python"`` the base class's step loop runs, and its :meth:`act` / :meth:`learn`
call the same compiled building blocks in the same order, so both give identical tables for
the same seeds. SR-Dyna's replay updates ``M`` (Russek et al. 2017); with ``replay_reward``
it also updates ``w`` from the replayed rewards (as neuro-nav's ``DynaSR``).
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
from cobelrun.agents.codes import POLICIES
from cobelrun.agents.compiled_trials import (
    TrialBuffers,
    WorldTables,
    check_engine,
    run_trial_by_trial,
    use_compiled,
)
from cobelrun.agents.policy import check_policy, select
from cobelrun.agents.schema import (
    AgentArgs,
    at_least,
    boolean,
    interval,
    number_above,
    number_at_least,
    validate_args,
)
from cobelrun.records import TrialBatch
from cobelrun.safety import check_allocation
from cobelrun.signals import critical


class SuccessorCore:
    """The state shared by every SR agent: ``M`` (S, A, S) and ``w`` (S,), plus the update rules.

    Parameters
    ----------
    n_states, n_actions
        Table sizes.
    gamma
        Discount of the SR.
    learning_rate
        Rate of the TD update of ``M``.
    reward_rate
        Rate of the reward weights ``w``.
    """

    def __init__(
        self, n_states: int, n_actions: int, gamma: float, learning_rate: float, reward_rate: float
    ) -> None:
        self.gamma, self.learning_rate, self.reward_rate = gamma, learning_rate, reward_rate
        check_allocation("agent", n_states * n_actions * n_states * 8 * 3,
                         f"its successor representation and one-step model ({n_states:,} x "
                         f"{n_actions} x {n_states:,}, float64)", "use a smaller env")  # fmt: skip
        self.M = np.zeros((n_states, n_actions, n_states))
        self.w = np.zeros(n_states)

    def q(self, s: int) -> np.ndarray:
        """Action values of state ``s``: ``M(s, :, :) @ w``."""
        return self.M[s] @ self.w

    def q_table(self) -> np.ndarray:
        """(S, A) action values of every state."""
        return self.M @ self.w

    def greedy(self, rng: np.random.Generator, s: int) -> int:
        """``argmax_b Q(s, b)`` with random tie-break."""
        q = self.q(s)
        best = np.flatnonzero(q == q.max())
        return int(best[0] if best.size == 1 else best[rng.integers(best.size)])

    def learn_reward(self, s2: int, r: float) -> None:
        """``w(s') += lr_w (r - w(s'))``."""
        self.w[s2] += self.reward_rate * (r - self.w[s2])

    def td(self, s: int, a: int, s2: int, terminal: bool, a2: int) -> None:
        """``M(s,a,:) += lr (1_{s'} + gamma M(s', a2, :) - M(s,a,:))`` (no bootstrap if terminal)."""
        target = np.zeros(self.M.shape[2])
        target[s2] = 1.0
        if not terminal:
            target += self.gamma * self.M[s2, a2]
        self.M[s, a] += self.learning_rate * (target - self.M[s, a])

    def from_model(self, T: np.ndarray, policy: np.ndarray, terminal: np.ndarray) -> None:
        """``M(s, a, :) = T(s, a, :) (I - gamma T_pi)^-1``, ``T_pi(s) = sum_a pi(s, a) T(s, a)``;
        ``policy`` is (S, A) action probabilities or (S,) actions."""
        n = T.shape[0]
        if policy.ndim == 1:
            T_pi = T[np.arange(n), policy].copy()
        else:
            T_pi = np.einsum("sa,sat->st", policy, T)
        T_pi[terminal] = 0.0
        N = np.linalg.inv(np.eye(n) - self.gamma * T_pi)
        self.M[...] = T @ N


class TabularModelArgs(AgentArgs):
    """The ranges of :class:`TabularModelAgent`'s arguments (checked in this order)."""

    epsilon: Annotated[Any, interval(0, 1.0)]
    beta: Annotated[Any, number_at_least(0)]
    gamma: Annotated[Any, interval(0, 0.999999)]


class SRTDArgs(AgentArgs):
    """The ranges of :class:`SRTD`'s own arguments."""

    learning_rate: Annotated[Any, interval(0, 1.0)]
    reward_rate: Annotated[Any, interval(0, 1.0)]


class SRDynaArgs(AgentArgs):
    """The ranges of :class:`SRDyna`'s own arguments."""

    replay_batch: Annotated[Any, at_least(0)]
    replay_reward: Annotated[Any, boolean()]


class ModelRatesArgs(AgentArgs):
    """The ranges of the model-based agents' rates."""

    reward_rate: Annotated[Any, interval(0, 1.0)]
    transition_rate: Annotated[Any, interval(0, 1.0)]


class ValueIterationArgs(ModelRatesArgs):
    """The ranges of :class:`ValueIteration`'s own arguments."""

    tolerance: Annotated[Any, number_above(0)]


class TabularModelAgent(Agent):
    """Trial loop shared by the SR agents and value iteration: act, step, learn, callbacks.

    Subclasses implement :meth:`q_values` (action values of a state) and :meth:`learn` (one
    experienced transition), and list their learned arrays in :meth:`get_state` and
    :meth:`state_schema`; the base class runs the step loop and saves and loads the arrays.

    Parameters
    ----------
    env
        A tabular gridworld (``GridWorldEnv``; the ``TabularModel`` contract).
    policy
        ``epsilon_greedy`` (default, random tie-break) or ``softmax``.
    epsilon
        Exploration rate of epsilon-greedy (0.1).
    beta
        Softmax inverse temperature (5).
    gamma
        Discount factor (0.9).
    seed
        Seed of the agent's draws.
    """

    observation_spaces = (gym.spaces.Discrete,)
    action_spaces = (gym.spaces.Discrete,)
    requires = ("tabular_model",)

    def __init__(
        self,
        env: gym.Env,
        *,
        policy: str = "epsilon_greedy",
        epsilon: float = 0.1,
        beta: float = 5.0,
        gamma: float = 0.9,
        seed: SeedLike = None,
    ) -> None:
        super().__init__(env, seed=seed)
        self.policy = check_policy(policy)
        validate_args(TabularModelArgs, locals())
        self.epsilon, self.beta, self.gamma = float(epsilon), float(beta), float(gamma)
        self.n_states = int(env.observation_space.n)
        self.n_actions = int(env.action_space.n)

    # -- subclass hooks --------------------------------------------------------------------
    def q_values(self, s: int) -> np.ndarray:
        """Action values of state ``s``."""
        raise NotImplementedError

    def learn(self, s: int, a: int, r: float, s2: int, terminal: bool) -> None:
        """Learn from one experienced transition."""
        raise NotImplementedError

    def get_state(self) -> dict[str, np.ndarray]:
        """The learned arrays, saved and loaded by name (see :meth:`state_schema`)."""
        raise NotImplementedError

    def set_state(self, arrays: Mapping[str, np.ndarray]) -> None:
        for key, arr in self.get_state().items():
            arr[...] = arrays[key]

    def hyperparameters(self) -> dict:
        return {"policy": self.policy, "epsilon": self.epsilon, "beta": self.beta,
                "gamma": self.gamma}  # fmt: skip

    # -- acting and learning: the base class's step loop calls these -------------------------
    def act(self, obs: Any, info: dict[str, Any], learn: bool) -> int:
        """Behaviour policy over :meth:`q_values` (``cobelrun.agents.policy``)."""
        return select(self.rng, self.q_values(int(obs)), self.policy, self.epsilon, self.beta)

    def observe(self, transition: Transition, learn: bool) -> None:
        if learn:
            self.learn(transition.state, transition.action, transition.reward,
                       transition.next_state, transition.terminated)  # fmt: skip

    def predict(self, observations: np.ndarray) -> np.ndarray:
        obs = state_indices(observations, self.n_states)
        return np.array([self.q_values(int(s)) for s in obs]).reshape(-1, self.n_actions)


class _CompiledSR(TabularModelAgent):
    """Engine choice of the SR agents: whole trials in compiled code (:mod:`sr_kernels`,
    :mod:`srmb_kernels`), or the base class's step loop (per-step callbacks, noisy rewards,
    ``engine="python"``) whose :meth:`act` and :meth:`learn` call the same compiled building
    blocks in the same order, so both paths give identical results for the same seeds."""

    def __init__(self, env: gym.Env, *, engine: str = "auto", **kwargs) -> None:
        super().__init__(env, **kwargs)
        self.engine = check_engine(engine)
        self._tables = WorldTables()
        self._policy_code = POLICIES[self.policy]

    def _run(
        self, n_trials: int, max_steps: int, learn: bool, callbacks: Sequence[TrialCallback]
    ) -> TrialBatch:
        if use_compiled(self.engine, callbacks, self.env):
            return run_trial_by_trial(self, self._run_compiled, n_trials, max_steps, learn,
                                      callbacks)  # fmt: skip
        return super()._run(n_trials, max_steps, learn, callbacks)

    def _run_compiled(self, n_trials: int, max_steps: int, learn: bool) -> TrialBatch:
        raise NotImplementedError


class SRTD(_CompiledSR):
    """SR-TD (Russek et al. 2017): ``M`` and ``w`` learned by TD from experience only.

    Parameters
    ----------
    learning_rate
        Rate of the TD update of ``M`` (0.3).
    reward_rate
        Rate of the reward weights ``w`` (0.9).
    engine
        ``"auto"`` (whole trials compiled unless per-step callbacks or noisy rewards),
        ``"compiled"`` (require it) or ``"python"`` (the step loop; same results).
    **kwargs
        ``policy``, ``epsilon``, ``beta``, ``gamma``, ``seed`` (see :class:`TabularModelAgent`).
    """

    def __init__(
        self, env: gym.Env, *, learning_rate: float = 0.3, reward_rate: float = 0.9, **kwargs
    ) -> None:
        super().__init__(env, **kwargs)
        validate_args(SRTDArgs, locals())
        self.core = SuccessorCore(self.n_states, self.n_actions, self.gamma,
                                  float(learning_rate), float(reward_rate))  # fmt: skip

    def q_values(self, s: int) -> np.ndarray:
        return self.core.q(s)

    def act(self, obs: Any, info: dict[str, Any], learn: bool) -> int:
        from cobelrun.agents.sr_kernels import sr_act  # numba: on first use

        return int(sr_act(self.rng, self.core.M, self.core.w, int(obs), self._policy_code,
                          self.epsilon, self.beta))  # fmt: skip

    def learn(self, s: int, a: int, r: float, s2: int, terminal: bool) -> None:
        from cobelrun.agents.sr_kernels import sr_step

        c = self.core
        sr_step(self.rng, c.M, c.w, s, a, r, s2, terminal, c.gamma, c.learning_rate,
                c.reward_rate)  # fmt: skip

    def _model_args(self) -> tuple[Any, ...]:
        """``dyna, model_next, model_reward, pairs, n_pairs`` of the trial kernel."""
        return (False, _NO_MODEL_NEXT, _NO_MODEL_REWARD, _NO_PAIRS, np.zeros(1, np.int64))

    def _replay_args(self) -> tuple[int, bool]:
        return 0, False

    def _run_compiled(self, n_trials: int, max_steps: int, learn: bool) -> TrialBatch:
        from cobelrun.agents.sr_kernels import run_sr_trials  # numba: on first use

        det, next_state, T_cum, R, terminal, starts, env_rng = self._tables.args(self.env)
        out = TrialBuffers(n_trials, max_steps)
        c = self.core
        with critical():  # a signal inside the kernel's generator access corrupts it
            total = run_sr_trials(
                self.rng, env_rng, c.M, c.w, *self._model_args(),
                det, next_state, T_cum, R, terminal, starts,
                self._policy_code, self.epsilon, self.beta, c.gamma, c.learning_rate,
                c.reward_rate, *self._replay_args(), n_trials, max_steps, learn, *out.args(),
            )  # fmt: skip
        return out.batch(total)

    def get_state(self) -> dict[str, np.ndarray]:
        return {"M": self.core.M, "w": self.core.w}

    def state_schema(self) -> dict[str, ArraySpec]:
        S, A = self.n_states, self.n_actions
        return {"M": ArraySpec((S, A, S)), "w": ArraySpec((S,))}

    def hyperparameters(self) -> dict:
        return {**super().hyperparameters(), "learning_rate": self.core.learning_rate,
                "reward_rate": self.core.reward_rate}  # fmt: skip


_NO_MODEL_NEXT = np.zeros((1, 1), np.int64)
_NO_MODEL_REWARD = np.zeros((1, 1))
_NO_PAIRS = np.zeros(1, np.int64)


class SRDyna(SRTD):
    """SR-Dyna (Russek et al. 2017): SR-TD plus replayed TD updates of ``M`` after every step.

    Replay draws ``replay_batch`` experienced state-action pairs uniformly (with replacement)
    and replays the last outcome ``s'`` of each with SR-TD's update of ``M`` (Russek et al.
    2017: replayed samples update the successor matrix; ``w`` is learned from experience).
    With ``replay_reward`` a replayed experience also updates ``w(s')`` towards the pair's
    last reward first, as neuro-nav's ``DynaSR`` does: then replay updates both ``M`` and
    ``w``.

    Parameters
    ----------
    replay_batch
        Experiences replayed after every step (10).
    replay_reward
        Replay also updates the reward weights ``w`` (False: only ``M``).
    **kwargs
        See :class:`SRTD`.
    """

    state_version = 2  # 2: + model_reward

    def __init__(
        self, env: gym.Env, *, replay_batch: int = 10, replay_reward: bool = False, **kwargs
    ) -> None:
        super().__init__(env, **kwargs)
        validate_args(SRDynaArgs, locals())
        self.replay_batch = replay_batch
        self.replay_reward = replay_reward
        self.model_next = np.full((self.n_states, self.n_actions), -1, np.int64)
        self.model_reward = np.zeros((self.n_states, self.n_actions))

    def learn(self, s: int, a: int, r: float, s2: int, terminal: bool) -> None:
        super().learn(s, a, r, s2, terminal)
        self.model_next[s, a] = s2
        self.model_reward[s, a] = r
        if self.replay_batch == 0:
            return
        from cobelrun.agents.sr_kernels import sr_replay_step

        pairs = np.flatnonzero(self.model_next.reshape(-1) >= 0)
        terminal = np.ascontiguousarray(self.env.unwrapped.world.terminal, np.bool_)
        c = self.core
        sr_replay_step(self.rng, c.M, c.w, self.model_next, self.model_reward, pairs, pairs.size,
                       terminal, self.replay_batch, c.gamma, c.learning_rate, c.reward_rate,
                       self.replay_reward)  # fmt: skip

    def _model_args(self) -> tuple[Any, ...]:
        seen = np.flatnonzero(self.model_next.reshape(-1) >= 0)
        pairs = np.empty(self.model_next.size, np.int64)
        pairs[: seen.size] = seen
        return (True, self.model_next, self.model_reward, pairs,
                np.array([seen.size], np.int64))  # fmt: skip

    def _replay_args(self) -> tuple[int, bool]:
        return self.replay_batch, self.replay_reward

    def get_state(self) -> dict[str, np.ndarray]:
        return {**super().get_state(), "model_next": self.model_next,
                "model_reward": self.model_reward}  # fmt: skip

    def state_schema(self) -> dict[str, ArraySpec]:
        S, A = self.n_states, self.n_actions
        return {**super().state_schema(), "model_next": ArraySpec((S, A), "i", low=-1, high=S),
                "model_reward": ArraySpec((S, A))}  # fmt: skip

    def hyperparameters(self) -> dict:
        return {**super().hyperparameters(), "replay_batch": self.replay_batch,
                "replay_reward": self.replay_reward}  # fmt: skip


class _OneStepModel:
    """A learned one-step model ``T(s, a, s')`` (delta rule) with unvisited pairs staying put."""

    def __init__(self, n_states: int, n_actions: int, rate: float) -> None:
        self.rate = rate
        self.T = np.zeros((n_states, n_actions, n_states))
        self.T[np.arange(n_states), :, np.arange(n_states)] = 1.0  # unknown: no move

    def learn(self, s: int, a: int, s2: int) -> None:
        row = self.T[s, a]
        row *= 1.0 - self.rate
        row[s2] += self.rate


class SRMB(_CompiledSR):
    """SR-MB (Russek et al. 2017): ``M`` computed from a learned model and a cached policy.

    Acting needs only ``Q(s, :) = T(s, :, :) (I - gamma T_pi)^-1 w``: one linear solve after
    each change of the model, ``w`` or the cached policy (none when a step leaves the cached
    policy as it was: the values solved after the model update still hold); the full ``M``
    is computed when asked for (:meth:`get_state`). Whole trials run in compiled code
    (:func:`cobelrun.agents.srmb_kernels.run_srmb_trials`) unless ``engine="python"`` or
    per-step callbacks ask for the step loop (same results).

    Parameters
    ----------
    transition_rate
        Rate of the one-step model ``T`` (1.0: the last outcome).
    reward_rate
        Rate of the reward weights ``w`` (0.9).
    engine
        ``"auto"``, ``"compiled"`` or ``"python"`` (see :class:`SRTD`).
    **kwargs
        ``policy``, ``epsilon``, ``beta``, ``gamma``, ``seed`` (see :class:`TabularModelAgent`).
    """

    def __init__(
        self, env: gym.Env, *, transition_rate: float = 1.0, reward_rate: float = 0.9, **kwargs
    ) -> None:
        super().__init__(env, **kwargs)
        validate_args(ModelRatesArgs, locals())
        self.core = SuccessorCore(self.n_states, self.n_actions, self.gamma, 0.0,
                                  float(reward_rate))  # fmt: skip
        self.model = _OneStepModel(self.n_states, self.n_actions, float(transition_rate))
        #: (S, A) the greedy policy when the agent last acted in each state (ties split)
        self.cached_policy = np.full((self.n_states, self.n_actions), 1.0 / self.n_actions)
        self.terminal = np.asarray(env.unwrapped.world.terminal, bool).copy()
        self._v: np.ndarray | None = None  # (I - gamma T_pi)^-1 w, None: out of date
        self._q = np.empty(self.n_actions)

    def _values(self) -> np.ndarray:
        """``v = (I - gamma T_pi)^-1 w`` (terminal rows of ``T_pi`` zero)."""
        if self._v is None:
            from cobelrun.agents.srmb_kernels import mb_values  # numba: on first use

            self._v = mb_values(self.model.T, self.cached_policy, self.terminal, self.core.w,
                                self.gamma)  # fmt: skip
        return self._v

    def q_values(self, s: int) -> np.ndarray:
        return self.model.T[s] @ self._values()

    def act(self, obs: Any, info: dict[str, Any], learn: bool) -> int:
        from cobelrun.agents.srmb_kernels import mb_act

        return int(mb_act(self.rng, self.model.T, self._values(), int(obs), self._policy_code,
                          self.epsilon, self.beta))  # fmt: skip

    def learn(self, s: int, a: int, r: float, s2: int, terminal: bool) -> None:
        from cobelrun.agents.srmb_kernels import mb_learn

        v, valid = mb_learn(self.model.T, self.cached_policy, self.terminal, self.core.w, s, a,
                            r, s2, terminal, self.gamma, self.model.rate, self.core.reward_rate,
                            self._q)  # fmt: skip
        self._v = v if valid else None

    def _run_compiled(self, n_trials: int, max_steps: int, learn: bool) -> TrialBatch:
        from cobelrun.agents.srmb_kernels import run_srmb_trials  # numba: on first use

        det, next_state, T_cum, R, terminal, starts, env_rng = self._tables.args(self.env)
        out = TrialBuffers(n_trials, max_steps)
        with critical():
            total = run_srmb_trials(
                self.rng, env_rng, self.model.T, self.cached_policy, self.terminal, self.core.w,
                det, next_state, T_cum, R, terminal, starts,
                self._policy_code, self.epsilon, self.beta, self.gamma, self.model.rate,
                self.core.reward_rate, n_trials, max_steps, learn, *out.args(),
            )  # fmt: skip
        self._v = None
        return out.batch(total)

    def get_state(self) -> dict[str, np.ndarray]:
        self.core.from_model(self.model.T, self.cached_policy, self.terminal)
        return {"M": self.core.M, "w": self.core.w, "T": self.model.T,
                "cached_policy": self.cached_policy, "terminal": self.terminal}  # fmt: skip

    def set_state(self, arrays: Mapping[str, np.ndarray]) -> None:
        super().set_state(arrays)
        self._v = None

    def state_schema(self) -> dict[str, ArraySpec]:
        S, A = self.n_states, self.n_actions
        return {"M": ArraySpec((S, A, S)), "w": ArraySpec((S,)),
                "T": ArraySpec((S, A, S), low=0.0, high=1.0 + 1e-9),
                "cached_policy": ArraySpec((S, A), low=0.0, high=1.0 + 1e-9),
                "terminal": ArraySpec((S,), "b")}  # fmt: skip

    def hyperparameters(self) -> dict:
        return {**super().hyperparameters(), "transition_rate": self.model.rate,
                "reward_rate": self.core.reward_rate}  # fmt: skip


class ValueIteration(TabularModelAgent):
    """Model-based planning: learned ``T`` and ``w``, value iteration before every action.

    Parameters
    ----------
    transition_rate
        Rate of the one-step model ``T`` (1.0: the last outcome).
    reward_rate
        Rate of the arrival rewards ``w`` (0.9).
    tolerance
        Value iteration stops when no value changes by more than this (1e-8).
    **kwargs
        ``policy``, ``epsilon``, ``beta``, ``gamma``, ``seed`` (see :class:`TabularModelAgent`).
    """

    def __init__(
        self,
        env: gym.Env,
        *,
        transition_rate: float = 1.0,
        reward_rate: float = 0.9,
        tolerance: float = 1e-8,
        **kwargs,
    ) -> None:
        super().__init__(env, **kwargs)
        validate_args(ValueIterationArgs, locals())
        self.model = _OneStepModel(self.n_states, self.n_actions, float(transition_rate))
        self.reward_rate = float(reward_rate)
        self.tolerance = float(tolerance)
        self.w = np.zeros(self.n_states)
        self.terminal = np.asarray(env.unwrapped.world.terminal, bool).copy()
        self.Q = np.zeros((self.n_states, self.n_actions))
        self._V = np.zeros(self.n_states)  # warm start of value iteration

    def plan(self) -> None:
        """``Q(s,a) = sum_s' T(s,a,s') (w(s') + gamma V(s'))``, ``V = max_a Q`` (0 if terminal),
        iterated from the last plan's ``V`` (the same fixed point, reached in a few sweeps
        when one experience changed the model)."""
        V = self._V
        for _ in range(10_000):
            self.Q = self.model.T @ (self.w + self.gamma * V)
            V_new = np.where(self.terminal, 0.0, self.Q.max(axis=1))
            if np.max(np.abs(V_new - V)) < self.tolerance:
                break
            V = V_new
        self._V = V_new

    def q_values(self, s: int) -> np.ndarray:
        return self.Q[s]

    def learn(self, s: int, a: int, r: float, s2: int, terminal: bool) -> None:
        self.w[s2] += self.reward_rate * (r - self.w[s2])
        self.model.learn(s, a, s2)
        if terminal:
            self.terminal[s2] = True
        self.plan()

    def get_state(self) -> dict[str, np.ndarray]:
        return {"Q": self.Q, "w": self.w, "T": self.model.T, "terminal": self.terminal}

    def state_schema(self) -> dict[str, ArraySpec]:
        S, A = self.n_states, self.n_actions
        return {"Q": ArraySpec((S, A)), "w": ArraySpec((S,)),
                "T": ArraySpec((S, A, S), low=0.0, high=1.0 + 1e-9),
                "terminal": ArraySpec((S,), "b")}  # fmt: skip

    def hyperparameters(self) -> dict:
        return {**super().hyperparameters(), "transition_rate": self.model.rate,
                "reward_rate": self.reward_rate, "tolerance": self.tolerance}  # fmt: skip
