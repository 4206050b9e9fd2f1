"""Tabular model memory for Dyna-style replay (the component behind Dyna-Q, Dyna-DQN, Dyna-DSR)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numba import njit

from cobelrun.agents.kernels import SAMPLE_ALL, SAMPLING, q_update
from cobelrun.errors import ConfigError, allowed_list, suggest


class TabularMemory:
    """Per (state, action): the last next-state, a running average of reward, and terminality.

    As in CoBeL-RL's ``MemoryTabular``: unvisited entries point to their own state with reward 0
    and count as terminal. ``sampling="all"`` (the original's, used for the paper's figures)
    draws uniformly over all state-action pairs, visited or not; ``sampling="visited"`` draws
    only pairs that were experienced.

    Parameters
    ----------
    n_states, n_actions
        Table size.
    reward_rate
        Rate of the running reward average (0.9 in the original).
    sampling
        ``"all"`` or ``"visited"``.
    """

    def __init__(
        self, n_states: int, n_actions: int, *, reward_rate: float = 0.9, sampling: str = "all"
    ) -> None:
        if sampling not in SAMPLING:
            raise ConfigError(
                f"memory sampling {sampling!r} is not known{suggest(sampling, SAMPLING)}; "
                f"allowed: {allowed_list(SAMPLING)}"
            )
        if not 0.0 < reward_rate <= 1.0:
            raise ConfigError(f"memory reward_rate must be in (0, 1], got {reward_rate}")
        self.n_states, self.n_actions = n_states, n_actions
        self.reward_rate = float(reward_rate)
        self.sampling = sampling
        self.next_state = np.repeat(np.arange(n_states, dtype=np.int64)[:, None], n_actions, 1)
        self.reward = np.zeros((n_states, n_actions))
        self.terminal = np.ones((n_states, n_actions), dtype=np.bool_)
        self.visited = np.zeros((n_states, n_actions), dtype=np.bool_)
        self.visited_list = np.zeros(n_states * n_actions, dtype=np.int64)
        self.n_visited = np.zeros(1, dtype=np.int64)

    @property
    def sampling_code(self) -> int:
        return SAMPLING[self.sampling]

    def arrays(self) -> tuple[np.ndarray, ...]:
        """The arrays the compiled kernels read and write, in kernel argument order."""
        return (
            self.next_state,
            self.reward,
            self.terminal,
            self.visited,
            self.visited_list,
            self.n_visited,
        )

    def store(self, s: int, a: int, r: float, s2: int, terminal: bool) -> None:
        memory_store(*self.arrays(), self.reward_rate, s, a, r, s2, terminal)

    def sample(self, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Draw ``n`` (state, action) pairs as replay does."""
        idx = memory_sample_batch(
            rng,
            self.visited_list,
            self.n_visited,
            self.n_states * self.n_actions,
            self.sampling_code,
            n,
        )
        return idx // self.n_actions, idx % self.n_actions

    def state_dict(self) -> dict[str, np.ndarray]:
        return {
            "memory_next_state": self.next_state,
            "memory_reward": self.reward,
            "memory_terminal": self.terminal,
            "memory_visited": self.visited,
            "memory_visited_list": self.visited_list,
            "memory_n_visited": self.n_visited,
        }

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        for key, arr in self.state_dict().items():
            arr[...] = state[key]

    def save(self, path: str | Path) -> None:
        np.savez(path, **self.state_dict())


@njit(cache=True)
def memory_store(
    m_next, m_reward, m_terminal, visited, visited_list, n_visited, rate, s, a, r, s2, terminal
):
    m_next[s, a] = s2
    m_reward[s, a] += rate * (r - m_reward[s, a])
    m_terminal[s, a] = terminal
    if not visited[s, a]:
        visited[s, a] = True
        visited_list[n_visited[0]] = s * m_next.shape[1] + a
        n_visited[0] += 1


@njit(cache=True)
def memory_sample(rng, visited_list, n_visited, n_pairs, sampling):
    if sampling == SAMPLE_ALL or n_visited[0] == 0:
        return rng.integers(0, n_pairs)
    return visited_list[rng.integers(0, n_visited[0])]


@njit(cache=True)
def memory_sample_batch(rng, visited_list, n_visited, n_pairs, sampling, n):
    out = np.empty(n, np.int64)
    for i in range(n):
        out[i] = memory_sample(rng, visited_list, n_visited, n_pairs, sampling)
    return out


@njit(cache=True)
def replay(
    rng,
    Q,
    mask,
    use_mask,
    m_next,
    m_reward,
    m_terminal,
    visited_list,
    n_visited,
    sampling,
    n,
    lr,
    gamma,
):
    """``n`` sequential Q updates from experiences sampled out of the model memory."""
    n_actions = Q.shape[1]
    n_pairs = Q.shape[0] * n_actions
    for _ in range(n):
        idx = memory_sample(rng, visited_list, n_visited, n_pairs, sampling)
        s = idx // n_actions
        a = idx % n_actions
        q_update(Q, mask, use_mask, s, a, m_reward[s, a], m_next[s, a], m_terminal[s, a], lr, gamma)
