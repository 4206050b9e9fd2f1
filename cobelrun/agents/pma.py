"""Prioritized memory access (Mattar & Daw 2018): Q-learning with replay ordered by need x gain.

The algorithm, top to bottom (defaults of the authors' MATLAB code, ``setParams.m``):

1. act in ``s`` with softmax(beta) (or epsilon-greedy) over ``Q[s]``; observe ``r, s'``;
2. Q-learn online: ``Q[s,a] += alpha * (r + gamma * max Q[s'] - Q[s,a])``;
3. update the model: the last ``(r, s')`` of ``(s, a)``, and the state-state transition matrix
   ``T[s] += eta * (onehot(s') - T[s])``;
4. at trial start (before the first action) and on arriving at the goal, replay: up to
   ``n_backups`` times pick the backup with the highest expected value of backup
   ``EVB = need(s_k) * gain(s_k, a_k)`` and apply it. Candidates are every experienced 1-step
   backup plus the last replayed sequence extended by one greedy step (n-step backups).
   ``gain`` is the improvement of the softmax policy in ``s_k`` that the backup causes, floored
   at ``min_gain``; ``need`` is the successor representation row of the agent's state,
   ``M = (I - gamma T)^-1`` (or the stationary distribution of ``T``).

No replay happens before the first reward. The model is pre-explored (every action of every free,
non-terminal state, reward 0) and the goal's row of ``T`` points to the start states, as in the
authors' code. See ``docs/replay.md`` for the equations and the departures from the originals.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any

import gymnasium as gym
import numpy as np

from cobelrun.agents.base import ArraySpec, SeedLike, Transition, state_indices
from cobelrun.agents.policy import check_policy
from cobelrun.agents.replay_log import WHEN_END, WHEN_START, ReplayAgent, empty_replays
from cobelrun.agents.schema import AgentArgs, at_least, interval, number_at_least, validate_args
from cobelrun.errors import check_choice

REPLAY_WHEN = ("start_and_goal", "start", "goal", "off")
NEED = ("sr", "stationary")


def successor_representation(T: np.ndarray, gamma: float) -> np.ndarray:
    """``M = (I - gamma T)^-1``: expected discounted future occupancy of every state."""
    return np.linalg.inv(np.eye(T.shape[0]) - gamma * T)


def stationary_distribution(T: np.ndarray) -> np.ndarray:
    """Left eigenvector of ``T`` with eigenvalue 1 (absolute values, unit 2-norm, as ``eig``)."""
    vals, vecs = np.linalg.eig(T.T)
    v = np.abs(vecs[:, int(np.argmin(np.abs(vals - 1.0)))].real)
    return v / np.linalg.norm(v)


class PMAArgs(AgentArgs):
    """The ranges of the prioritized-memory agent's arguments (checked in this order)."""

    epsilon: Annotated[Any, interval(0.0, 1.0)]
    learning_rate: Annotated[Any, interval(0.0, 1.0)]
    gamma: Annotated[Any, interval(0.0, 0.999999)]
    transition_rate: Annotated[Any, interval(0.0, 1.0)]
    n_backups: Annotated[Any, at_least(0)]
    min_gain: Annotated[Any, number_at_least(0)]
    beta: Annotated[Any, number_at_least(0)]


class PMA(ReplayAgent):
    """Tabular Q-learning with prioritized memory access (Mattar & Daw 2018).

    Parameters
    ----------
    env
        A tabular gridworld (``GridWorldEnv``): the model is pre-explored from its world.
    beta
        Softmax inverse temperature, of behaviour and of the policy the gain is measured under
        (5, ``softmaxInvT``).
    epsilon
        Exploration rate when ``policy`` is ``epsilon_greedy`` (0.05).
    policy
        Behaviour policy: ``softmax`` (default, ``actPolicy``) or ``epsilon_greedy``.
    learning_rate
        Q-learning rate, online and in replay (1.0, ``alpha``).
    gamma
        Discount factor; also the successor representation's discount (0.9).
    n_backups
        Backups per replay bout (20, ``nPlan``).
    min_gain
        Floor of each backup's gain (1e-10, ``baselineGain``).
    extend
        Offer n-step sequences: the last replayed sequence extended by one greedy step
        (true, ``expandFurther``).
    replay
        When to replay: ``start_and_goal`` (default, ``planOnlyAtGorS``), ``start``, ``goal``
        or ``off`` (plain Q-learning).
    need
        ``sr`` (successor representation row of the agent's state, ``online``) or ``stationary``
        (stationary distribution of the learned transitions, ``offline``).
    transition_rate
        Learning rate of the state-state transition matrix (0.9, ``TLearnRate``).
    pre_explore
        Fill the model with every action of every free, non-terminal state before the first
        trial (reward 0), as ``preExplore`` (true).
    goal_to_start
        Let terminal states lead to the start states in ``T`` so the need wraps around
        (true, ``Tgoal2start``).
    replay_before_reward
        Replay even before any reward was experienced (false: the authors skip planning until
        the first reward).
    seed
        Seed of the agent's draws (actions and tie-breaks).
    """

    observation_spaces = (gym.spaces.Discrete,)
    action_spaces = (gym.spaces.Discrete,)
    requires = ("tabular_model",)

    def __init__(
        self,
        env: gym.Env,
        *,
        beta: float = 5.0,
        epsilon: float = 0.05,
        policy: str = "softmax",
        learning_rate: float = 1.0,
        gamma: float = 0.9,
        n_backups: int = 20,
        min_gain: float = 1e-10,
        extend: bool = True,
        replay: str = "start_and_goal",
        need: str = "sr",
        transition_rate: float = 0.9,
        pre_explore: bool = True,
        goal_to_start: bool = True,
        replay_before_reward: bool = False,
        seed: SeedLike = None,
    ) -> None:
        super().__init__(env, seed=seed)
        validate_args(PMAArgs, locals())
        base = env.unwrapped
        self.beta, self.epsilon = float(beta), float(epsilon)
        self.policy = check_policy(policy)
        self.learning_rate, self.gamma = float(learning_rate), float(gamma)
        self.n_backups, self.min_gain = int(n_backups), float(min_gain)
        self.extend = bool(extend)
        self.replay = check_choice("agent.replay", replay, REPLAY_WHEN)
        self.need = check_choice("agent.need", need, NEED)
        self.transition_rate = float(transition_rate)
        self.pre_explore, self.goal_to_start = bool(pre_explore), bool(goal_to_start)
        self.replay_before_reward = bool(replay_before_reward)

        world = base.world
        S, A = int(env.observation_space.n), int(env.action_space.n)
        self.n_states, self.n_actions = S, A
        #: learned state (plain arrays; see :meth:`state_dict`)
        self.Q = np.zeros((S, A))
        self.T = np.zeros((S, S))
        self.model_next = np.full((S, A), -1, np.int64)  # -1: never experienced
        self.model_reward = np.zeros((S, A))
        self.rewarded = np.zeros((), bool)  # a reward was experienced (replay may start)
        self.last_terminal = np.array(-1, np.int64)  # terminal state the last trial ended in
        self._init_model(world)
        self._no_mask = np.ones((1, 1), np.bool_)
        self._trial, self._last = -1, None
        #: replays of the last :meth:`train` call, one entry per backup (``replay_log.REPLAY_FIELDS``)
        self.last_replays: dict[str, np.ndarray] = empty_replays()

    # -- model -----------------------------------------------------------------------------
    def _init_model(self, world: object) -> None:
        """Pre-exploration and goal-to-start wrap of the authors' code (``replaySim.m``)."""
        free = ~world.blocked & ~world.terminal
        if self.pre_explore:
            T_world = world.T
            succ = T_world.argmax(axis=2)  # most likely outcome (the only one if deterministic)
            for s in np.flatnonzero(free):
                self.model_next[s] = succ[s]
                self.model_reward[s] = 0.0
                self.T[s] = T_world[s].mean(axis=0)
        if self.goal_to_start:
            starts = np.asarray(world.starts, np.int64)
            for g in np.flatnonzero(world.terminal & ~world.blocked):
                self.T[g] = 0.0
                self.T[g, starts] = 1.0 / len(starts)

    def _learn_transition(self, s: int, s2: int) -> None:
        row = self.T[s]
        row *= 1.0 - self.transition_rate
        row[s2] += self.transition_rate

    def need_vector(self, state: int) -> np.ndarray:
        """Need of every state for an agent in ``state`` (SR row or stationary distribution)."""
        if self.need == "sr":
            from cobelrun.agents.replay_kernels import sr_row

            return sr_row(self.T, self.gamma, int(state))
        return stationary_distribution(self.T)

    # -- action selection ------------------------------------------------------------------

    # -- trials: the base class's step loop with these hooks --------------------------------

    def begin_trial(self, obs: Any, info: dict[str, Any], learn: bool) -> None:
        """The goal -> start wrap of ``T``, then the trial-start replay."""
        self._trial += 1
        self._last = None
        s = int(obs)
        if learn and self.goal_to_start and self.last_terminal >= 0:
            self._learn_transition(int(self.last_terminal), s)
        if learn and self.replay in ("start_and_goal", "start") and self._may_replay():
            self._bout(s, s, self._trial, WHEN_START)

    def observe(self, transition: Transition, learn: bool) -> None:
        """Online Q-learning and the model (last outcome of ``(s, a)``, transitions ``T``)."""
        s, a, r, s2 = transition.state, transition.action, transition.reward, transition.next_state
        self._last = (s, s2, transition.terminated)
        if not learn:
            return
        from cobelrun.agents.kernels import q_update

        q_update(self.Q, self._no_mask, False, s, a, r, s2, transition.terminated,
                 self.learning_rate, self.gamma)  # fmt: skip
        self.model_next[s, a] = s2
        self.model_reward[s, a] = r
        self._learn_transition(s, s2)
        if r != 0.0:
            self.rewarded[...] = True

    def end_trial(self, learn: bool) -> None:
        """On arriving at the goal: the goal replay (need from the last action's state, as the
        authors plan before moving the agent)."""
        if not (learn and self._last is not None and self._last[2]):
            return
        s, s2, _ = self._last
        self.last_terminal[...] = s2
        if self.replay in ("start_and_goal", "goal") and self._may_replay():
            self._bout(s, s2, self._trial, WHEN_END)

    def _may_replay(self) -> bool:
        return self.n_backups > 0 and (self.replay_before_reward or bool(self.rewarded))

    def _bout(self, need_state: int, agent_state: int, trial: int, when: int) -> None:
        """One replay bout; its backups are appended to the log."""
        from cobelrun.agents.replay_kernels import pma_bout

        n = self.n_backups
        out = {
            "state": np.empty(n, np.int64), "action": np.empty(n, np.int64),
            "next_state": np.empty(n, np.int64), "reward": np.empty(n),
            "gain": np.empty(n), "need": np.empty(n), "length": np.empty(n, np.int64),
        }  # fmt: skip
        candidate = (self.model_next >= 0) & (self.model_next != np.arange(self.n_states)[:, None])
        terminal = np.ascontiguousarray(self.env.unwrapped.world.terminal, np.bool_)
        done = pma_bout(
            self.rng, self.Q, self.model_next, self.model_reward, candidate, terminal,
            np.ascontiguousarray(self.need_vector(need_state)), self.gamma,
            self.learning_rate, self.beta, self.min_gain, n, self.extend,
            out["state"], out["action"], out["next_state"], out["reward"], out["gain"],
            out["need"], out["length"],
        )  # fmt: skip
        self._log.add(trial, when, agent_state, **{k: v[:done] for k, v in out.items()})

    # -- inference and persistence ---------------------------------------------------------
    def predict(self, observations: np.ndarray) -> np.ndarray:
        obs = state_indices(observations, self.n_states)
        return self.Q[obs].copy()

    def hyperparameters(self) -> dict:
        return {
            "beta": self.beta, "epsilon": self.epsilon, "policy": self.policy,
            "learning_rate": self.learning_rate, "gamma": self.gamma,
            "n_backups": self.n_backups, "min_gain": self.min_gain, "extend": self.extend,
            "replay": self.replay, "need": self.need, "transition_rate": self.transition_rate,
            "pre_explore": self.pre_explore, "goal_to_start": self.goal_to_start,
            "replay_before_reward": self.replay_before_reward,
        }  # fmt: skip

    def state_schema(self) -> dict[str, ArraySpec]:
        S, A = self.n_states, self.n_actions
        return {
            "Q": ArraySpec((S, A)), "T": ArraySpec((S, S), low=0.0, high=1.0 + 1e-9),
            "model_next": ArraySpec((S, A), "i", low=-1, high=S),
            "model_reward": ArraySpec((S, A)), "rewarded": ArraySpec((), "b"),
            "last_terminal": ArraySpec((), "i", low=-1, high=S),
        }  # fmt: skip

    def get_state(self) -> dict[str, np.ndarray]:
        """The learned state: plain arrays (see :meth:`state_schema`)."""
        return {
            "Q": self.Q, "T": self.T, "model_next": self.model_next,
            "model_reward": self.model_reward, "rewarded": self.rewarded,
            "last_terminal": self.last_terminal,
        }  # fmt: skip

    def set_state(self, arrays: Mapping[str, np.ndarray]) -> None:
        for key, arr in self.get_state().items():
            arr[...] = arrays[key]
