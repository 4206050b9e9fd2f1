"""Tabular Dyna-Q (Sutton 1990) as used for the paper's Fig. 6B.

The update rule, top to bottom (one step):

1. pick ``a`` in ``s`` (epsilon-greedy with random tie-break, or softmax(beta));
2. observe ``r, s'`` and Q-learn online: ``Q[s,a] += lr * (r + gamma * max Q[s'] - Q[s,a])``
   (no bootstrap from terminal states);
3. store the experience in the tabular model memory;
4. replay ``replay_batch`` experiences sampled from the memory with the same update
   (after every step, once at trial end, or never).

On tabular environments (``GridWorldEnv`` and its variants) whole trials run in compiled code
(:func:`cobelrun.agents.kernels.run_trials`); with callbacks, or on other environments with discrete observations,
trials run step by step in Python through the gymnasium API. Both paths call the same compiled
building blocks in the same order, so they give identical results for the same seeds.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import gymnasium as gym
import numpy as np

from cobelrun.agents.base import Agent, SeedLike, TrialCallback
from cobelrun.agents.codes import POLICIES, REPLAY_MODES, REPLAY_STEP, REPLAY_TRIAL_END
from cobelrun.agents.memory import TabularMemory
from cobelrun.errors import ConfigError, allowed_list, suggest
from cobelrun.records import TrialBatch

ENGINES = ("auto", "compiled", "python")


def _choice(kind: str, value: str, allowed: Sequence[str]) -> str:
    if value not in allowed:
        raise ConfigError(
            f"{kind} {value!r} is not known{suggest(value, allowed)}; allowed: {allowed_list(allowed)}"
        )
    return value


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
        for name, value, lo, hi in (
            ("epsilon", epsilon, 0.0, 1.0),
            ("learning_rate", learning_rate, 0.0, 1.0),
            ("gamma", gamma, 0.0, 1.0),
        ):
            if not lo <= value <= hi:
                raise ConfigError(f"agent.{name} must be in [{lo}, {hi}], got {value}")
        if replay_batch < 0:
            raise ConfigError(f"agent.replay_batch must be >= 0, got {replay_batch}")
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
        self.tabular = hasattr(base, "world") and hasattr(base, "action_mask")
        if self.engine == "compiled" and not self.tabular:
            raise ConfigError(
                f"agent.engine 'compiled' needs a tabular environment (GridWorldEnv); "
                f"got {type(base).__name__}; use engine 'auto' or 'python'"
            )
        if self.use_mask and not self.tabular:
            raise ConfigError("agent.action_mask needs a tabular environment (GridWorldEnv)")
        self.Q = np.zeros((self.n_states, self.n_actions))
        self.memory = TabularMemory(
            self.n_states, self.n_actions, reward_rate=memory_reward_rate, sampling=memory_sampling
        )

    # -- helpers -------------------------------------------------------------------------
    def _mask(self) -> np.ndarray:
        if self.use_mask:
            return np.ascontiguousarray(self.env.unwrapped.action_mask(), dtype=np.bool_)
        return np.ones((self.n_states, self.n_actions), dtype=np.bool_)

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
        if callbacks:
            if self.engine == "compiled":
                raise ConfigError("agent.engine 'compiled' cannot run per-step callbacks")
            return False
        return self.tabular

    # -- trials ----------------------------------------------------------------------------
    def _run(
        self, n_trials: int, max_steps: int, learn: bool, callbacks: Sequence[TrialCallback]
    ) -> TrialBatch:
        if self._use_compiled(callbacks):
            return self._run_compiled(n_trials, max_steps, learn)
        return self._run_python(n_trials, max_steps, learn, callbacks)

    def _run_compiled(self, n_trials: int, max_steps: int, learn: bool) -> TrialBatch:
        from cobelrun.agents.kernels import run_trials  # numba: imported on first use

        base = self.env.unwrapped
        world = base.world
        det_table = world.next_state
        deterministic = det_table is not None
        next_state = det_table if deterministic else np.zeros((1, 1), np.int64)
        T_cum = np.zeros((1, 1, 1)) if deterministic else np.cumsum(world.T, axis=2)
        cap = n_trials * max_steps
        out_state = np.empty(cap, np.int64)
        out_action = np.empty(cap, np.int64)
        out_next = np.empty(cap, np.int64)
        out_reward = np.empty(cap, np.float64)
        steps = np.zeros(n_trials, np.int64)
        term = np.zeros(n_trials, np.bool_)
        starts = np.zeros(n_trials, np.int64)
        total = run_trials(
            self.rng, base.np_random, self.Q, self._mask(), self.use_mask,
            *self.memory.arrays(), self.memory.reward_rate,
            deterministic, np.ascontiguousarray(next_state, np.int64), T_cum,
            np.ascontiguousarray(world.rewards, np.float64),
            np.ascontiguousarray(world.terminal, np.bool_),
            np.ascontiguousarray(world.starts, np.int64),
            *self._params(), n_trials, max_steps, learn,
            out_state, out_action, out_next, out_reward, steps, term, starts,
        )  # fmt: skip
        offsets = np.zeros(n_trials + 1, np.int64)
        np.cumsum(steps, out=offsets[1:])
        step_reward = out_reward[:total].copy()
        end = np.where(steps > 0, out_next[np.maximum(offsets[1:] - 1, 0)], starts)
        return TrialBatch(
            start_state=starts,
            end_state=end,
            steps=steps,
            reward=np.add.reduceat(step_reward, offsets[:-1]) if total else np.zeros(n_trials),
            terminated=term,
            offsets=offsets,
            step_state=out_state[:total].copy(),
            step_action=out_action[:total].copy(),
            step_next_state=out_next[:total].copy(),
            step_reward=step_reward,
        )

    def _run_python(
        self, n_trials: int, max_steps: int, learn: bool, callbacks: Sequence[TrialCallback]
    ) -> TrialBatch:
        from cobelrun.agents.kernels import q_update, select_action

        env = self.env
        mask = self._mask()
        (policy, eps, beta, lr, gamma, replay_mode, batch, _sampling) = self._params()
        mem = self.memory
        trials = []
        for trial in range(n_trials):
            s, _ = env.reset()
            s = int(s)
            for cb in callbacks:
                cb.on_trial_start(self, trial, s)
            states, actions, rewards = [s], [], []
            terminated = False
            for step in range(1, max_steps + 1):
                a = int(
                    select_action(self.rng, self.Q[s], mask[s], self.use_mask, policy, eps, beta)
                )
                s2, r, terminated, _, _ = env.step(a)
                s2, r = int(s2), float(r)
                if learn:
                    q_update(self.Q, mask, self.use_mask, s, a, r, s2, terminated, lr, gamma)
                    mem.store(s, a, r, s2, terminated)
                    if replay_mode == REPLAY_STEP:
                        self._replay(mask, batch)
                states.append(s2)
                actions.append(a)
                rewards.append(r)
                transition_info = {
                    "state": s,
                    "action": a,
                    "reward": r,
                    "next_state": s2,
                    "terminated": terminated,
                }
                keep_going = all(
                    [cb.on_step(self, trial, step, transition_info) for cb in callbacks]
                )
                s = s2
                if terminated or not keep_going:
                    break
            if learn and replay_mode == REPLAY_TRIAL_END:
                self._replay(mask, batch)
            record = {"states": states, "actions": actions, "rewards": rewards,
                      "terminated": terminated}  # fmt: skip
            for cb in callbacks:
                cb.on_trial_end(self, trial, record)
            trials.append(record)
        return TrialBatch.from_trials(trials)

    def _replay(self, mask: np.ndarray, n: int) -> None:
        from cobelrun.agents.kernels import replay

        m = self.memory
        replay(self.rng, self.Q, mask, self.use_mask, m.next_state, m.reward, m.terminal,
               m.visited_list, m.n_visited, m.sampling_code, n, self.learning_rate, self.gamma)  # fmt: skip

    # -- inference and persistence ---------------------------------------------------------
    def predict(self, observations: np.ndarray) -> np.ndarray:
        obs = np.asarray(observations, dtype=np.int64).reshape(-1)
        if obs.size and (obs.min() < 0 or obs.max() >= self.n_states):
            raise ValueError(f"observations must be state indices in [0, {self.n_states})")
        return self.Q[obs].copy()

    def hyperparameters(self) -> dict:
        return {
            "epsilon": self.epsilon, "beta": self.beta, "learning_rate": self.learning_rate,
            "gamma": self.gamma, "policy": self.policy, "action_mask": self.use_mask,
            "replay": self.replay, "replay_batch": self.replay_batch,
            "memory_sampling": self.memory.sampling,
            "memory_reward_rate": self.memory.reward_rate,
        }  # fmt: skip

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        if path.suffix != ".npz":
            path = path.with_suffix(".npz")
        np.savez(  # uncompressed: tables are small, and this runs once per run
            path, Q=self.Q, hyperparameters=np.array(json.dumps(self.hyperparameters())),
            **self.memory.state_dict(),
        )  # fmt: skip
        return path

    def load(self, path: str | Path) -> None:
        with np.load(path, allow_pickle=False) as data:
            if data["Q"].shape != self.Q.shape:
                raise ConfigError(
                    f"saved agent {path} has a Q table of shape {data['Q'].shape}, "
                    f"this environment needs {self.Q.shape}"
                )
            self.Q[...] = data["Q"]
            self.memory.load_state_dict({k: data[k] for k in self.memory.state_dict()})
