"""The tabular TD-control family: SARSA, Q(lambda), SARSA(lambda), Monte-Carlo control, the
tabular actor-critic and Dyna actor-critic.

Each agent keeps a table ``Q`` (S, A) (the actor-critics: action preferences ``H`` and state
values ``V``) and acts by the shared policies (epsilon-greedy with a random tie-break, or
softmax; :mod:`cobelrun.agents.policy`, numba twin :func:`cobelrun.agents.kernels.select_action`).
The next action ``a'`` is chosen in ``s'`` before the update, as in Sutton & Barto's (2018)
SARSA box, and is the action then taken. The update rules, top to bottom, are in
:func:`cobelrun.agents.td_kernels.td_step`.

On tabular gridworlds (the ``tabular_model`` contract) whole trials run in compiled code
(:func:`cobelrun.agents.td_kernels.run_td_trials`); with per-step callbacks, noisy rewards,
``engine="python"`` or other environments with discrete observations, the base class's step
loop runs and calls the same compiled building blocks in the same order (identical tables for
the same seeds, tested).

References: Rummery & Niranjan (1994) (SARSA, SARSA(lambda)); Watkins (1989) (Q(lambda));
Singh & Sutton (1996) (replacing traces); Sutton & Barto (2018) (§5.4 Monte-Carlo control,
§6.4 SARSA, §12.7 SARSA(lambda), §12.10 Watkins's Q(lambda), §13.5 actor-critic); Barto,
Sutton & Anderson (1983) (actor-critic); Sutton (1990) (Dyna).
"""

from __future__ import annotations

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
from cobelrun.agents.policy import check_policy
from cobelrun.agents.schema import (
    AgentArgs,
    at_least,
    interval,
    number_at_least,
    one_of,
    validate_args,
)
from cobelrun.envs.base import TabularModel, require, supports
from cobelrun.errors import ConfigError
from cobelrun.records import TrialBatch
from cobelrun.safety import check_allocation
from cobelrun.signals import critical

# algorithm codes and trace kinds of the kernels (cobelrun.agents.td_kernels; kept in step)
SARSA, Q_LAMBDA, SARSA_LAMBDA, MC, AC = 0, 1, 2, 3, 4
TRACES = {"accumulating": 0, "replacing": 1}

_NO_MODEL_NEXT = np.zeros((1, 1), np.int64)
_NO_MODEL_REWARD = np.zeros((1, 1))
_NO_MODEL_TERMINAL = np.zeros((1, 1), np.bool_)
_NO_PAIRS = np.zeros(1, np.int64)


class TabularControlArgs(AgentArgs):
    """The ranges of :class:`TabularControl`'s arguments (checked in this order)."""

    epsilon: Annotated[Any, interval(0, 1.0)]
    beta: Annotated[Any, number_at_least(0)]
    learning_rate: Annotated[Any, interval(0, 1.0)]
    gamma: Annotated[Any, interval(0, 1.0)]


class LambdaArgs(AgentArgs):
    """The ranges of the eligibility-trace agents' own arguments."""

    lam: Annotated[Any, interval(0, 1.0)]
    trace: Annotated[Any, one_of(TRACES)]


class ActorCriticRatesArgs(AgentArgs):
    """The ranges of :class:`TabularActorCritic`'s own arguments."""

    actor_lr: Annotated[Any, interval(0, 1.0)]
    critic_lr: Annotated[Any, interval(0, 1.0)]


class DynaACArgs(AgentArgs):
    """The ranges of :class:`DynaActorCritic`'s own arguments."""

    replay_batch: Annotated[Any, at_least(1)]


class TabularControl(Agent):
    """Base of the TD-control agents: table, policy, engine, the two trial paths, save/load.

    Parameters
    ----------
    env
        Environment with a ``Discrete`` observation space (the state index).
    policy
        ``"epsilon_greedy"`` (random tie-break) or ``"softmax"``.
    epsilon
        Exploration rate of epsilon-greedy (0.1, Sutton & Barto 2018, Example 6.5).
    beta
        Softmax inverse temperature (5).
    learning_rate
        Step size of the update (see each agent).
    gamma
        Discount factor (0.95: shorter paths are worth more; Sutton & Barto's gridworlds use
        -1 per step instead).
    engine
        ``"auto"`` (whole trials compiled on tabular gridworlds unless per-step callbacks or
        noisy rewards), ``"compiled"`` (require it) or ``"python"`` (the step loop; same
        results).
    seed
        Seed of the agent's draws.
    """

    observation_spaces = (gym.spaces.Discrete,)
    action_spaces = (gym.spaces.Discrete,)
    #: the kernel's algorithm code
    algorithm: ClassVar[int] = SARSA

    def __init__(
        self,
        env: gym.Env,
        *,
        policy: str = "epsilon_greedy",
        epsilon: float = 0.1,
        beta: float = 5.0,
        learning_rate: float = 0.5,
        gamma: float = 0.95,
        engine: str = "auto",
        seed: SeedLike = None,
    ) -> None:
        super().__init__(env, seed=seed)
        self.policy = check_policy(policy)
        validate_args(TabularControlArgs, locals())
        self.epsilon, self.beta = float(epsilon), float(beta)
        self.learning_rate, self.gamma = float(learning_rate), float(gamma)
        self.engine = check_engine(engine)
        self.n_states = int(env.observation_space.n)
        self.n_actions = int(env.action_space.n)
        self.tabular = supports(env.unwrapped, TabularModel)
        if self.engine == "compiled":
            require(env, ("tabular_model",), "agent.engine 'compiled' (use 'auto' or 'python')")
        S, A = self.n_states, self.n_actions
        check_allocation("agent", S * A * 8 * 6,
                         f"its tables ({S:,} states x {A} actions)", "use a smaller env")  # fmt: skip
        self.Q = np.zeros((S, A))
        self.V = np.zeros(S)  # the critic (actor-critics only)
        self.E = np.zeros((S, A))  # eligibility traces (lambda agents only), cleared per trial
        self._tables = WorldTables()
        self._policy_code = POLICIES[self.policy]
        self._next: int | None = None
        self._trial: list[tuple[int, int, float]] = []

    # -- what the subclasses set --------------------------------------------------------------
    def _lr2(self) -> float:
        return 0.0

    def _lam(self) -> tuple[float, int]:
        return 0.0, 0

    def _model_args(self) -> tuple[Any, ...]:
        """``model_next, model_reward, model_terminal, pairs, n_pairs, replay_batch``."""
        return (_NO_MODEL_NEXT, _NO_MODEL_REWARD, _NO_MODEL_TERMINAL, _NO_PAIRS,
                np.zeros(1, np.int64), 0)  # fmt: skip

    def _params(self) -> tuple[Any, ...]:
        lam, trace = self._lam()
        return (self.learning_rate, self._lr2(), self.gamma, lam, trace)

    # -- trials -------------------------------------------------------------------------------
    def _run(
        self, n_trials: int, max_steps: int, learn: bool, callbacks: Sequence[TrialCallback]
    ) -> TrialBatch:
        if self.tabular and use_compiled(self.engine, callbacks, self.env):
            return run_trial_by_trial(self, self._run_compiled, n_trials, max_steps, learn,
                                      callbacks)  # fmt: skip
        self._model = self._model_args()  # the Python loop keeps the model arrays' views
        return super()._run(n_trials, max_steps, learn, callbacks)

    def _run_compiled(self, n_trials: int, max_steps: int, learn: bool) -> TrialBatch:
        from cobelrun.agents.td_kernels import run_td_trials  # numba: on first use

        det, next_state, T_cum, R, terminal, starts, env_rng = self._tables.args(self.env)
        out = TrialBuffers(n_trials, max_steps)
        with critical():  # a signal inside the kernel's generator access corrupts it
            total = run_td_trials(
                self.rng, env_rng, self.algorithm, self.Q, self.V, self.E, *self._model_args(),
                det, next_state, T_cum, R, terminal, starts,
                self._policy_code, self.epsilon, self.beta, *self._params(),
                n_trials, max_steps, learn, *out.args(),
            )  # fmt: skip
        return out.batch(total)

    def begin_trial(self, obs: Any, info: dict[str, Any], learn: bool) -> None:
        self.E[...] = 0.0
        self._next = None
        self._trial = []

    def _select(self, s: int) -> int:
        from cobelrun.agents.td_kernels import td_act  # numba: on first use

        return int(td_act(self.rng, self.Q, s, self._policy_code, self.epsilon, self.beta))

    def act(self, obs: Any, info: dict[str, Any], learn: bool) -> int:
        if self._next is not None:  # chosen in this state at the last step
            a, self._next = self._next, None
            return a
        return self._select(int(obs))

    def observe(self, t: Transition, learn: bool) -> None:
        s, s2 = int(t.obs), int(t.next_obs)
        a2 = -1 if t.terminated else self._select(s2)
        self._next = None if t.terminated else a2
        if not learn:
            return
        if self.algorithm == MC:
            self._trial.append((s, t.action, float(t.reward)))
            return
        from cobelrun.agents.td_kernels import td_learn

        td_learn(self.rng, self.algorithm, self.Q, self.V, self.E, s, t.action, float(t.reward),
                 s2, bool(t.terminated), a2, *self._params(), *self._model)  # fmt: skip

    def end_trial(self, learn: bool) -> None:
        if learn and self.algorithm == MC and self._trial:
            from cobelrun.agents.td_kernels import mc_update

            s, a, r = (np.array(x) for x in zip(*self._trial, strict=True))
            mc_update(self.Q, s.astype(np.int64), a.astype(np.int64), r.astype(np.float64),
                      self.gamma, self.learning_rate, np.zeros(self.Q.shape, np.bool_),
                      np.empty(len(self._trial)))  # fmt: skip
        self._trial = []

    # -- inference and persistence --------------------------------------------------------------
    def predict(self, observations: np.ndarray) -> np.ndarray:
        obs = state_indices(observations, self.n_states)
        return self.Q[obs].copy()

    def hyperparameters(self) -> dict[str, Any]:
        return {"policy": self.policy, "epsilon": self.epsilon, "beta": self.beta,
                "learning_rate": self.learning_rate, "gamma": self.gamma}  # fmt: skip

    def state_schema(self) -> dict[str, ArraySpec]:
        return {"Q": ArraySpec((self.n_states, self.n_actions))}

    def get_state(self) -> dict[str, np.ndarray]:
        return {"Q": self.Q}

    def set_state(self, arrays: Mapping[str, np.ndarray]) -> None:
        for key, arr in self.get_state().items():
            arr[...] = arrays[key]


class Sarsa(TabularControl):
    """SARSA (Rummery & Niranjan 1994; Sutton & Barto 2018, §6.4): on-policy TD control,
    ``Q(s,a) += lr (r + gamma Q(s',a') - Q(s,a))`` with ``a'`` the action then taken.

    Defaults: ``learning_rate`` 0.5 and epsilon-greedy 0.1 (Sutton & Barto 2018, Example 6.5);
    see :class:`TabularControl` for the other parameters.
    """

    algorithm = SARSA


class _Lambda(TabularControl):
    """Eligibility-trace parameters shared by Q(lambda) and SARSA(lambda)."""

    def __init__(
        self, env: gym.Env, *, lam: float = 0.9, trace: str = "replacing", **kwargs: Any
    ) -> None:
        super().__init__(env, **kwargs)
        validate_args(LambdaArgs, locals())
        self.lam, self.trace = float(lam), trace

    def _lam(self) -> tuple[float, int]:
        return self.lam, TRACES[self.trace]

    def hyperparameters(self) -> dict[str, Any]:
        return {**super().hyperparameters(), "lam": self.lam, "trace": self.trace}


class QLambda(_Lambda):
    """Watkins's Q(lambda) (Watkins 1989; Sutton & Barto 2018, §12.10): Q-learning with
    eligibility traces, cut to zero after an exploratory (non-greedy) action.

    Parameters
    ----------
    lam
        Trace decay lambda (0.9; Sutton & Barto 2018, Fig. 12.10's best range).
    trace
        ``"replacing"`` (default; Singh & Sutton 1996) or ``"accumulating"``.
    learning_rate
        Step size (0.5, as SARSA's).
    **kwargs
        See :class:`TabularControl`.
    """

    algorithm = Q_LAMBDA


class SarsaLambda(_Lambda):
    """SARSA(lambda) (Rummery & Niranjan 1994; Sutton & Barto 2018, §12.7): SARSA with
    eligibility traces ``E`` decaying by ``gamma lambda`` per step.

    Parameters
    ----------
    lam
        Trace decay lambda (0.9; Sutton & Barto 2018, Fig. 12.10).
    trace
        ``"replacing"`` (default; Singh & Sutton 1996) or ``"accumulating"``.
    learning_rate
        Step size (0.5, as SARSA's).
    **kwargs
        See :class:`TabularControl`.
    """

    algorithm = SARSA_LAMBDA


class MCControl(TabularControl):
    """On-policy first-visit Monte-Carlo control (Sutton & Barto 2018, §5.4) with a constant
    step size (eq. 6.1): at trial end ``Q(s,a) += lr (G - Q(s,a))`` at the first visit of
    each pair, ``G`` the discounted return from there (a trial cut at ``max_steps`` is backed
    up with the rewards it got).

    Defaults: epsilon-greedy 0.1 (an epsilon-soft policy, §5.4); ``learning_rate`` 0.3 (Sutton
    & Barto average the returns instead; a constant step keeps tracking a changing world);
    see :class:`TabularControl`.
    """

    algorithm = MC

    def __init__(self, env: gym.Env, **kwargs: Any) -> None:
        kwargs.setdefault("learning_rate", 0.3)
        super().__init__(env, **kwargs)


class TabularActorCritic(TabularControl):
    """One-step tabular actor-critic (Barto, Sutton & Anderson 1983; Sutton & Barto 2018,
    §13.5): the critic learns ``V`` by TD, the actor's preferences ``H`` follow the TD error,
    ``delta = r + gamma V(s') - V(s)``, ``V(s) += critic_lr delta``, ``H(s,a) += actor_lr
    delta``; the policy is softmax (or epsilon-greedy) over ``H``. :meth:`predict` returns
    ``H``.

    Parameters
    ----------
    actor_lr
        Step size of the preferences (0.1).
    critic_lr
        Step size of the critic (0.1).
    policy
        ``"softmax"`` (default: the actor's Gibbs policy) or ``"epsilon_greedy"``.
    beta
        Softmax inverse temperature (1).
    **kwargs
        ``epsilon``, ``gamma``, ``engine``, ``seed`` (see :class:`TabularControl`).
    """

    algorithm = AC

    def __init__(
        self,
        env: gym.Env,
        *,
        actor_lr: float = 0.1,
        critic_lr: float = 0.1,
        policy: str = "softmax",
        beta: float = 1.0,
        **kwargs: Any,
    ) -> None:
        if "learning_rate" in kwargs:
            raise ConfigError("agent.learning_rate is not a parameter of the actor-critic; "
                              "use agent.actor_lr and agent.critic_lr")  # fmt: skip
        validate_args(ActorCriticRatesArgs, locals())
        super().__init__(env, learning_rate=float(actor_lr), policy=policy, beta=beta, **kwargs)
        self.critic_lr = float(critic_lr)

    def _lr2(self) -> float:
        return self.critic_lr

    def hyperparameters(self) -> dict[str, Any]:
        h = super().hyperparameters()
        h["actor_lr"] = h.pop("learning_rate")
        return {**h, "critic_lr": self.critic_lr}

    def state_schema(self) -> dict[str, ArraySpec]:
        return {"H": ArraySpec((self.n_states, self.n_actions)), "V": ArraySpec((self.n_states,))}

    def get_state(self) -> dict[str, np.ndarray]:
        return {"H": self.Q, "V": self.V}


class DynaActorCritic(TabularActorCritic):
    """Dyna actor-critic (Sutton 1990's Dyna with the actor-critic of
    :class:`TabularActorCritic`, as neuro-nav's ``DynaAC``): after every real step,
    ``replay_batch`` experienced state-action pairs drawn uniformly (with replacement) replay
    their last outcome with the same actor-critic update.

    Parameters
    ----------
    replay_batch
        Experiences replayed after every step (3, neuro-nav's ``num_recall``).
    **kwargs
        See :class:`TabularActorCritic`.
    """

    def __init__(self, env: gym.Env, *, replay_batch: int = 3, **kwargs: Any) -> None:
        super().__init__(env, **kwargs)
        validate_args(DynaACArgs, locals())
        self.replay_batch = replay_batch
        S, A = self.n_states, self.n_actions
        self.model_next = np.full((S, A), -1, np.int64)
        self.model_reward = np.zeros((S, A))
        self.model_terminal = np.zeros((S, A), np.bool_)

    def _model_args(self) -> tuple[Any, ...]:
        seen = np.flatnonzero(self.model_next.reshape(-1) >= 0)
        pairs = np.empty(self.model_next.size, np.int64)
        pairs[: seen.size] = seen
        return (self.model_next, self.model_reward, self.model_terminal, pairs,
                np.array([seen.size], np.int64), self.replay_batch)  # fmt: skip

    def hyperparameters(self) -> dict[str, Any]:
        return {**super().hyperparameters(), "replay_batch": self.replay_batch}

    def state_schema(self) -> dict[str, ArraySpec]:
        S, A = self.n_states, self.n_actions
        return {**super().state_schema(),
                "model_next": ArraySpec((S, A), "i", low=-1, high=S),
                "model_reward": ArraySpec((S, A)), "model_terminal": ArraySpec((S, A), "b")}  # fmt: skip

    def get_state(self) -> dict[str, np.ndarray]:
        return {**super().get_state(), "model_next": self.model_next,
                "model_reward": self.model_reward, "model_terminal": self.model_terminal}  # fmt: skip
