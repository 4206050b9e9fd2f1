"""Tabular model memory for Dyna-style replay (the component behind Dyna-Q, Dyna-DQN, Dyna-DSR).

Its compiled store/sample/replay routines live in :mod:`cobelrun.agents.kernels`, next to the
trial loop that inlines them (imported on first use, so building an agent does not load numba).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from cobelrun.agents.base import ArraySpec
from cobelrun.agents.codes import SAMPLING
from cobelrun.errors import ConfigError, allowed_list, suggest

__all__ = ["TabularMemory"]


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
        from cobelrun.agents.kernels import memory_store

        memory_store(*self.arrays(), self.reward_rate, s, a, r, s2, terminal)

    def sample(self, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Draw ``n`` (state, action) pairs as replay does."""
        from cobelrun.agents.kernels import memory_sample_batch

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

    def state_schema(self) -> dict[str, ArraySpec]:
        """What :meth:`state_dict`'s arrays must look like: next states are state indices
        (the compiled kernels index with them unchecked), the visited list holds pair indices."""
        S, A = self.n_states, self.n_actions
        return {
            "memory_next_state": ArraySpec((S, A), "i", 0, S),
            "memory_reward": ArraySpec((S, A), "f"),
            "memory_terminal": ArraySpec((S, A), "b"),
            "memory_visited": ArraySpec((S, A), "b"),
            "memory_visited_list": ArraySpec((S * A,), "i", 0, S * A),
            "memory_n_visited": ArraySpec((1,), "i", 0, S * A + 1),
        }

    def load_state_dict(self, state: Mapping[str, np.ndarray]) -> None:
        for key, arr in self.state_dict().items():
            arr[...] = state[key]
