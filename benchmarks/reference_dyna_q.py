# ruff: noqa: NPY002  (the legacy global RNG is the point: the original used it)
"""A plain-Python Dyna-Q in the style of the original CoBeL-RL, for speed comparisons only.

Written here (not copied) to mirror how the original runs tabular Dyna-Q (paper/FACTS.md,
"Tabular Dyna-Q" and "Speed of the original"): experiences are dicts, the agent does per-step
numpy scalar work, the environment steps in Python and draws its next state with
``np.random.choice`` over the transition row, the model memory is sampled with
``np.random.randint`` over all state-action pairs (visited or not; unvisited pairs point to
themselves with reward 0 and count as terminal) and replay is a Python loop over a list of
experience dicts. Same algorithm and settings as :class:`cobelrun.agents.DynaQ` (one online
Q update, store, replay ``replay_batch`` experiences after every step), but not the same draws:
it uses numpy's global legacy RNG like the original.

``python benchmarks/reference_dyna_q.py`` runs Fig. 6B (T-maze extinction) with it and with
cobel's compiled Dyna-Q and prints both behaviours side by side (the fairness check).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cobelrun.envs.world import World


class ReferenceGridworld:
    """Gridworld interface as in the original: transition row lookup + ``np.random.choice``."""

    def __init__(self, world: World) -> None:
        self.sas = np.array(world.T)
        self.rewards = np.array(world.rewards)
        self.terminals = np.array(world.terminal)
        self.starting_states = np.array(world.starts)
        self.n_states = self.sas.shape[0]
        self.states = np.arange(self.n_states)
        self.current_state = 0

    def set_rewards(self, changes: dict[int, float]) -> None:
        for s, r in changes.items():
            self.rewards[s] = r

    def reset(self) -> int:
        self.current_state = int(np.random.choice(self.starting_states))
        return self.current_state

    def step(self, action: int) -> tuple[int, float, bool]:
        probs = self.sas[self.current_state][action]
        self.current_state = int(np.random.choice(self.states, p=probs))
        reward = self.rewards[self.current_state]
        end_trial = bool(self.terminals[self.current_state])
        return self.current_state, reward, end_trial


class ReferenceMemory:
    """Tabular model memory (the original's ``MemoryTabular``)."""

    def __init__(self, n_states: int, n_actions: int, learning_rate: float = 0.9) -> None:
        self.n_states, self.n_actions = n_states, n_actions
        self.learning_rate = learning_rate
        self.rewards = np.zeros((n_states, n_actions))
        self.states = np.tile(np.arange(n_states).reshape(n_states, 1), n_actions)
        self.terminals = np.zeros((n_states, n_actions))  # 0 = terminal (stored as 1 - end)

    def store(self, experience: dict) -> None:
        s, a = experience["state"], experience["action"]
        self.rewards[s][a] += self.learning_rate * (experience["reward"] - self.rewards[s][a])
        self.states[s][a] = experience["next_state"]
        self.terminals[s][a] = experience["terminal"]

    def retrieve_batch(self, batch_size: int = 32) -> list[dict]:
        idx = np.random.randint(0, self.n_states * self.n_actions, batch_size)
        experiences = []
        for exp in idx:
            state, action = int(exp / self.n_actions), exp % self.n_actions
            experiences += [
                {
                    "state": state,
                    "action": action,
                    "reward": self.rewards[state][action],
                    "next_state": self.states[state][action],
                    "terminal": self.terminals[state][action],
                }
            ]
        return experiences


class ReferenceDynaQ:
    """Dyna-Q agent in the original's style (epsilon-greedy with random tie-break)."""

    def __init__(
        self,
        env: ReferenceGridworld,
        n_actions: int = 4,
        epsilon: float = 0.1,
        learning_rate: float = 0.9,
        gamma: float = 0.9,
    ) -> None:
        self.env = env
        self.n_actions = n_actions
        self.epsilon, self.learning_rate, self.gamma = epsilon, learning_rate, gamma
        self.Q = np.zeros((env.n_states, n_actions))
        self.M = ReferenceMemory(env.n_states, n_actions)

    def select_action(self, state: int) -> int:
        qs = self.Q[state]
        if np.random.rand() < self.epsilon:
            return int(np.random.randint(self.n_actions))
        return int(np.random.choice(np.flatnonzero(qs == np.amax(qs))))

    def update_Q(self, experience: dict) -> None:
        td = experience["reward"]
        td += self.gamma * experience["terminal"] * np.amax(self.Q[experience["next_state"]])
        td -= self.Q[experience["state"]][experience["action"]]
        self.Q[experience["state"]][experience["action"]] += self.learning_rate * td

    def replay(self, batch_size: int) -> None:
        for experience in self.M.retrieve_batch(batch_size):
            self.update_Q(experience)

    def train(self, n_trials: int, max_steps: int, replay_batch: int) -> dict[str, list]:
        log: dict[str, list] = {"steps": [], "end_state": []}
        for _ in range(n_trials):
            state = self.env.reset()
            steps = 0
            for _ in range(max_steps):
                action = self.select_action(state)
                next_state, reward, end_trial = self.env.step(action)
                experience = {
                    "state": state,
                    "action": action,
                    "reward": reward,
                    "next_state": next_state,
                    "terminal": 1 - end_trial,
                }
                self.update_Q(experience)
                self.M.store(experience)
                if replay_batch:
                    self.replay(replay_batch)
                state = next_state
                steps += 1
                if end_trial:
                    break
            log["steps"].append(steps)
            log["end_state"].append(state)
        return log


@dataclass
class ReferenceResult:
    steps: np.ndarray  # (runs, trials) steps per trial
    end_state: np.ndarray  # (runs, trials)
    seconds: float

    @property
    def total_steps(self) -> int:
        return int(self.steps.sum())

    @property
    def steps_per_s(self) -> float:
        return self.total_steps / self.seconds


def run_reference(
    world_factory,
    phases: Sequence[tuple[int, dict[int, float]]],
    *,
    runs: int,
    max_steps: int,
    replay_batch: int,
    seed: int = 0,
    epsilon: float = 0.1,
    learning_rate: float = 0.9,
    gamma: float = 0.9,
) -> ReferenceResult:
    """Run ``runs`` fresh agents through ``phases`` = [(trials, reward changes), ...]."""
    np.random.seed(seed)
    steps, ends = [], []
    t0 = time.perf_counter()
    for _ in range(runs):
        env = ReferenceGridworld(world_factory())
        agent = ReferenceDynaQ(env, epsilon=epsilon, learning_rate=learning_rate, gamma=gamma)
        s_run: list[int] = []
        e_run: list[int] = []
        for trials, rewards in phases:
            env.set_rewards(rewards)
            log = agent.train(trials, max_steps, replay_batch)
            s_run += log["steps"]
            e_run += log["end_state"]
        steps.append(s_run)
        ends.append(e_run)
    seconds = time.perf_counter() - t0
    return ReferenceResult(np.array(steps), np.array(ends), seconds)


TMAZE_PHASES = [(100, {6: 1.0, 0: 0.0}), (100, {6: 0.0, 0: 1.0})]


def main() -> None:
    from cobelrun.agents import DynaQ
    from cobelrun.envs import GridWorldEnv
    from cobelrun.envs.world import tmaze_paper
    from cobelrun.runner import run_seeds

    runs = 20
    ref = run_reference(tmaze_paper, TMAZE_PHASES, runs=runs, max_steps=35, replay_batch=5)
    ours_steps, ours_end = [], []
    env = GridWorldEnv(tmaze_paper())
    for agent_seed, env_seed in run_seeds(0, runs):
        env.reset_world()
        env.np_random = np.random.default_rng(env_seed)
        agent = DynaQ(env, epsilon=0.1, beta=5.0, learning_rate=0.9, gamma=0.9, replay_batch=5,
                      seed=agent_seed)  # fmt: skip
        s, e = [], []
        for trials, rewards in TMAZE_PHASES:
            env.apply_changes(rewards=rewards)
            b = agent.train(trials, 35)
            s.append(b.steps)
            e.append(b.end_state)
        ours_steps.append(np.concatenate(s))
        ours_end.append(np.concatenate(e))
    for name, st, en in (
        ("reference", ref.steps, ref.end_state),
        ("cobel", np.array(ours_steps), np.array(ours_end)),
    ):
        right = (en == 6).mean(axis=0)
        cum = np.cumsum(right)
        print(
            f"{name:>9}: latency trials 1-5 {st[:, :5].mean():5.1f}, 21-100 {st[:, 20:100].mean():5.1f}, "
            f"101-105 {st[:, 100:105].mean():5.1f}, 121-200 {st[:, 120:].mean():5.1f} | "
            f"cum. right responses @100 {cum[99]:5.1f}, @110 {cum[109]:5.1f}, @200 {cum[199]:5.1f}"
        )
    print(f"reference speed: {ref.steps_per_s:,.0f} env steps/s ({ref.total_steps} steps)")


if __name__ == "__main__":
    main()
