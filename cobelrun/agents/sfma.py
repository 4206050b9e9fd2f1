"""SFMA: spatial structure and frequency-weighted memory access (Diekmann & Cheng 2023).

Tabular Q-learning whose replay reactivates experiences one after another by a priority that
combines how often an experience was made (strength ``C``), how similar its state is to the
last reactivated one (``D``: the default representation of the maze or a Euclidean kernel) and
an inhibition of return (``I``), so that replays form sequences:

1. act, observe ``r, s'``, Q-learn online, store the experience ``(s, a)`` (last ``s'``, running
   average of ``r`` at the learning rate) and increase its strength ``C(s, a) += 1`` (all
   strengths decay by ``decay_strength`` first);
2. at the end of a trial (and optionally at its start) replay ``n_backups`` experiences,
   starting at the agent's state: ``R(e) = C(e) D(s_c, x(e)) (1 - I(s_e))`` with ``x(e) = s_e``
   in the ``default`` mode and ``x(e) = s'_e`` in the ``reverse`` mode; reactivate ``e`` with
   probability proportional to ``exp(beta_replay R / max R) - 1``; back it up with Q-learning;
   inhibit its state. See :func:`cobelrun.agents.replay_kernels.sfma_bout`.

The default representation (Piray & Daw 2021) of a gridworld is the successor representation
of the uniform random walk through its real transitions, ``D = (I - gamma_dr T_rw)^-1``:
CoBeL-RL computes it from an open field's DR with a low-rank update for the walls, which is the
same matrix.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any

import gymnasium as gym
import numpy as np

from cobelrun.agents.base import ArraySpec, SeedLike, Transition, state_indices
from cobelrun.agents.policy import check_policy
from cobelrun.agents.replay_log import WHEN_END, WHEN_START, ReplayAgent, empty_replays
from cobelrun.agents.schema import AgentArgs, at_least, interval, validate_args
from cobelrun.errors import check_choice

MODES = ("default", "reverse")
SIMILARITY = ("dr", "euclidean")
REPLAY_WHEN = ("end", "start_and_end", "off")


def default_representation(T: np.ndarray, gamma: float) -> np.ndarray:
    """(S, S) SR of the uniform random walk through ``T`` (S, A, S): the DR of the maze."""
    T_rw = T.mean(axis=1)
    return np.linalg.inv(np.eye(T.shape[0]) - gamma * T_rw)


def euclidean_similarity(coords: np.ndarray) -> np.ndarray:
    """(S, S) ``exp(-||x_s - x_s'||)`` of the state coordinates."""
    d = np.linalg.norm(coords[:, None, :] - coords[None, :, :], axis=2)
    return np.exp(-d)


class SFMAArgs(AgentArgs):
    """The ranges of :class:`SFMA`'s arguments (checked in this order)."""

    epsilon: Annotated[Any, interval(0, 1.0)]
    learning_rate: Annotated[Any, interval(0, 1.0)]
    gamma: Annotated[Any, interval(0, 0.999999)]
    gamma_dr: Annotated[Any, interval(0, 0.999999)]
    decay_inhibition: Annotated[Any, interval(0, 1.0)]
    decay_strength: Annotated[Any, interval(0, 1.0)]
    threshold: Annotated[Any, interval(0, 1.0)]
    n_backups: Annotated[Any, at_least(0)]


class SFMA(ReplayAgent):
    """Tabular Q-learning with SFMA replay (Diekmann & Cheng 2023).

    Parameters
    ----------
    env
        A tabular gridworld (``GridWorldEnv``): the similarity is computed from its world.
    policy, epsilon, beta
        Behaviour: ``epsilon_greedy`` (default, epsilon 0.1, random tie-break) or ``softmax``
        (inverse temperature ``beta``, 5).
    learning_rate
        Q-learning rate, online and in replay (0.9, CoBeL-RL's default).
    gamma
        Discount factor (0.9).
    n_backups
        Experiences reactivated per replay (20).
    mode
        ``default`` (similarity to the experience's state) or ``reverse`` (to its next state).
    similarity
        ``dr`` (default representation of the maze, discount ``gamma_dr``) or ``euclidean``.
    gamma_dr
        Discount of the default representation (0.9).
    beta_replay
        Inverse temperature of the reactivation probabilities (20).
    decay_inhibition
        Decay of the inhibition after each reactivation (0.9).
    decay_strength
        Decay of all experience strengths at each new experience (1.0: none).
    threshold
        Normalised priorities below this are 0 (1e-6).
    deterministic
        Always reactivate the experience with the highest priority (false).
    replay
        ``end`` (at the end of every trial, default), ``start_and_end`` or ``off``.
    seed
        Seed of the agent's draws (behaviour and reactivation).
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
        learning_rate: float = 0.9,
        gamma: float = 0.9,
        n_backups: int = 20,
        mode: str = "default",
        similarity: str = "dr",
        gamma_dr: float = 0.9,
        beta_replay: float = 20.0,
        decay_inhibition: float = 0.9,
        decay_strength: float = 1.0,
        threshold: float = 1e-6,
        deterministic: bool = False,
        replay: str = "end",
        seed: SeedLike = None,
    ) -> None:
        super().__init__(env, seed=seed)
        base = env.unwrapped
        validate_args(SFMAArgs, locals())
        self.policy = check_policy(policy)
        self.mode = check_choice("agent.mode", mode, MODES)
        self.similarity_kind = check_choice("agent.similarity", similarity, SIMILARITY)
        self.replay = check_choice("agent.replay", replay, REPLAY_WHEN)
        self.epsilon, self.beta = float(epsilon), float(beta)
        self.learning_rate, self.gamma, self.gamma_dr = (
            float(learning_rate),
            float(gamma),
            float(gamma_dr),
        )
        self.n_backups, self.beta_replay = n_backups, float(beta_replay)
        self.decay_inhibition, self.decay_strength = float(decay_inhibition), float(decay_strength)
        self.threshold, self.deterministic = float(threshold), bool(deterministic)
        S, A = int(env.observation_space.n), int(env.action_space.n)
        self.n_states, self.n_actions = S, A
        world = base.world
        self.similarity = (
            default_representation(world.T, self.gamma_dr)
            if self.similarity_kind == "dr"
            else euclidean_similarity(world.coords)
        )
        #: learned state: Q, the model of experiences and their strengths
        self.Q = np.zeros((S, A))
        self.model_next = np.full((S, A), -1, np.int64)
        self.model_reward = np.zeros((S, A))
        self.strength = np.zeros((S, A))
        self._no_mask = np.ones((1, 1), np.bool_)
        self._trial, self._state = -1, -1
        self.last_replays: dict[str, np.ndarray] = empty_replays()

    # -- trials: the base class's step loop with these hooks --------------------------------

    def begin_trial(self, obs: Any, info: dict[str, Any], learn: bool) -> None:
        self._trial += 1
        self._state = int(obs)
        if learn and self.replay == "start_and_end":
            self._bout(self._state, self._trial, WHEN_START)

    def observe(self, transition: Transition, learn: bool) -> None:
        """Online Q-learning; store the experience and strengthen it."""
        s, a, r, s2 = transition.state, transition.action, transition.reward, transition.next_state
        self._state = s2
        if not learn:
            return
        from cobelrun.agents.kernels import q_update

        q_update(self.Q, self._no_mask, False, s, a, r, s2, transition.terminated,
                 self.learning_rate, self.gamma)  # fmt: skip
        self.model_next[s, a] = s2
        # the reward of an experience is a running average (rate = the learning rate), as
        # CoBeL-RL v3's SFMAMemory.store
        self.model_reward[s, a] += self.learning_rate * (r - self.model_reward[s, a])
        self.strength *= self.decay_strength
        self.strength[s, a] += 1.0

    def end_trial(self, learn: bool) -> None:
        """Replay at the end of every trial, from where the agent is."""
        if learn and self.replay != "off":
            self._bout(self._state, self._trial, WHEN_END)

    def _bout(self, state: int, trial: int, when: int) -> None:
        from cobelrun.agents.replay_kernels import sfma_bout

        terminal = np.ascontiguousarray(self.env.unwrapped.world.terminal, np.bool_)
        n = self.n_backups
        out = {"state": np.empty(n, np.int64), "action": np.empty(n, np.int64),
               "next_state": np.empty(n, np.int64), "reward": np.empty(n),
               "gain": np.empty(n)}  # fmt: skip
        done = sfma_bout(
            self.rng, self.Q, self.model_next, self.model_reward, terminal, self.strength,
            self.similarity, state, self.mode == "reverse", self.beta_replay,
            self.decay_inhibition, self.threshold, self.deterministic, n, self.learning_rate,
            self.gamma, out["state"], out["action"], out["next_state"], out["reward"],
            out["gain"],
        )  # fmt: skip
        cols = {k: v[:done] for k, v in out.items()}
        # SFMA has no gain or need: 'gain' holds the reactivation probability, 'need' is NaN
        cols["need"] = np.full(done, np.nan)
        cols["length"] = np.ones(done, np.int64)
        self._log.add(trial, when, state, **cols)

    def predict(self, observations: np.ndarray) -> np.ndarray:
        obs = state_indices(observations, self.n_states)
        return self.Q[obs].copy()

    def hyperparameters(self) -> dict:
        return {
            "policy": self.policy, "epsilon": self.epsilon, "beta": self.beta,
            "learning_rate": self.learning_rate, "gamma": self.gamma, "n_backups": self.n_backups,
            "mode": self.mode, "similarity": self.similarity_kind, "gamma_dr": self.gamma_dr,
            "beta_replay": self.beta_replay, "decay_inhibition": self.decay_inhibition,
            "decay_strength": self.decay_strength, "threshold": self.threshold,
            "deterministic": self.deterministic, "replay": self.replay,
        }  # fmt: skip

    def state_schema(self) -> dict[str, ArraySpec]:
        S, A = self.n_states, self.n_actions
        return {"Q": ArraySpec((S, A)), "model_next": ArraySpec((S, A), "i", low=-1, high=S),
                "model_reward": ArraySpec((S, A)), "strength": ArraySpec((S, A), low=0.0)}  # fmt: skip

    def get_state(self) -> dict[str, np.ndarray]:
        """The learned state: plain arrays (see :meth:`state_schema`)."""
        return {"Q": self.Q, "model_next": self.model_next, "model_reward": self.model_reward,
                "strength": self.strength}  # fmt: skip

    def set_state(self, arrays: Mapping[str, np.ndarray]) -> None:
        for key, arr in self.get_state().items():
            arr[...] = arrays[key]
