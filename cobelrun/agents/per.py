"""Proportional prioritized experience replay (Schaul et al. 2016) for SB3's DQN.

- :class:`SumTree`: a binary tree over priorities (sums and minima) with vectorised update and
  prefix-sum search, O(log N) per item.
- :class:`BatchedSumTree`: R independent sum trees in one ``(R, 2 size)`` array pair, for the
  batched DQN (:mod:`cobelrun.agents.batched_dqn`): updates, prefix-sum search, totals and
  minima of every run at once, with the same numerics as R :class:`SumTree` objects.
- :class:`PrioritizedReplayBuffer`: an SB3 :class:`~stable_baselines3.common.buffers.ReplayBuffer`
  that samples transition ``i`` with probability ``P(i) = p_i^alpha / sum_k p_k^alpha``
  (stratified: one draw per equal slice of the total), returns importance-sampling weights
  ``w_i = (N P(i))^-beta / max_j w_j`` (the max over the whole buffer, from the minimum
  priority, as in the paper and OpenAI baselines) and anneals ``beta`` linearly to 1.
  New transitions get the largest priority seen so far.
- :class:`PrioritizedDQN`: :class:`~cobelrun.agents.sb3.TrialDQN` whose gradient step weights
  each sample's TD loss (Huber or squared error) by ``w_i`` and sets ``p_i = |TD error_i| + epsilon``.

Draws come from the buffer's own ``numpy.random.Generator`` (seeded by the agent).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer

from cobelrun.agents.sb3 import TrialDQN
from cobelrun.errors import ConfigError


class SumTree:
    """Sums and minima of ``capacity`` non-negative leaf values in a complete binary tree."""

    def __init__(self, capacity: int) -> None:
        self.capacity = int(capacity)
        self.size = 1 << max(int(np.ceil(np.log2(max(capacity, 1)))), 0)
        self.sums = np.zeros(2 * self.size)
        self.mins = np.full(2 * self.size, np.inf)

    @property
    def total(self) -> float:
        return float(self.sums[1])

    @property
    def min(self) -> float:
        return float(self.mins[1])

    def __getitem__(self, idx: np.ndarray) -> np.ndarray:
        return self.sums[np.asarray(idx) + self.size]

    def update(self, idx: np.ndarray, values: np.ndarray) -> None:
        """Set leaves ``idx`` to ``values`` (later duplicates win) and refresh their ancestors.

        Each ancestor is recomputed from its two children, level by level from the leaves up
        (all updated leaves are at the same depth, so they reach the root together). The
        leaves are deduplicated once; a parent shared by several updated leaves is then
        computed several times from the same final children, which writes the same value,
        so no per-level ``np.unique`` is needed. One leaf (every ``add``) takes a scalar path.
        """
        pos = np.asarray(idx, dtype=np.int64).reshape(-1) + self.size
        vals = np.asarray(values, dtype=np.float64).reshape(-1)
        if pos.shape != vals.shape:
            raise ValueError(f"{pos.size} indices but {vals.size} values")
        if pos.size == 0:
            return
        sums, mins = self.sums, self.mins
        if pos.size == 1:
            p, v = int(pos[0]), float(vals[0])
            sums[p] = mins[p] = v
            p >>= 1
            while p:
                left = 2 * p
                sums[p] = sums[left] + sums[left + 1]
                mins[p] = min(mins[left], mins[left + 1])
                p >>= 1
            return
        # the last value given for each leaf: first occurrence in the reversed order
        pos, last = np.unique(pos[::-1], return_index=True)
        sums[pos] = mins[pos] = vals[::-1][last]
        while pos[0] > 1:
            pos = pos >> 1
            left = 2 * pos
            sums[pos] = sums[left] + sums[left + 1]
            mins[pos] = np.minimum(mins[left], mins[left + 1])

    def find(self, u: np.ndarray) -> np.ndarray:
        """Leaf index ``i`` with ``prefix_sum(i) <= u < prefix_sum(i + 1)`` for each ``u``."""
        u = np.array(u, dtype=np.float64)
        node = np.ones(u.shape, dtype=np.int64)
        while node[0] < self.size:
            left = self.sums[2 * node]
            right = u >= left
            u -= left * right
            node = 2 * node + right
        return node - self.size


class BatchedSumTree:
    """R independent :class:`SumTree` s of ``capacity`` leaves, held in one array pair.

    ``sums`` and ``mins`` are ``(R, 2 size)`` arrays, row ``r`` laid out as one
    :class:`SumTree`'s. Every operation works on all runs at once with vectorised numpy (the
    only Python loop runs over the tree's ``log2(size)`` levels) and computes each node exactly
    as :class:`SumTree` does (the same additions, minima and comparisons in the same order), so
    row ``r`` holds bit for bit what a :class:`SumTree` given run ``r``'s updates holds.

    A tree of a smaller (power of two) size than a :class:`SumTree` of ``buffer_size`` leaves
    gives the same totals, minima and searches as long as only its leaves are used: the larger
    tree's extra leaves add exact zeros (``x + 0.0 == x``) and ``inf`` minima.
    """

    def __init__(self, runs: int, capacity: int) -> None:
        self.R = int(runs)
        self.capacity = int(capacity)
        self.size = 1 << max(int(np.ceil(np.log2(max(capacity, 1)))), 0)
        self.depth = self.size.bit_length() - 1  # levels below the root
        self.width = 2 * self.size
        self.sums = np.zeros((self.R, self.width))
        self.mins = np.full((self.R, self.width), np.inf)

    def total(self) -> np.ndarray:
        """Each run's sum of leaves ``(R,)``."""
        return self.sums[:, 1].copy()

    def min(self) -> np.ndarray:
        """Each run's smallest leaf ``(R,)`` (``inf`` for a run with no leaf set)."""
        return self.mins[:, 1].copy()

    def get(self, run_idx: np.ndarray, leaf_idx: np.ndarray) -> np.ndarray:
        """Leaf values ``value[run_idx, leaf_idx]`` (the arguments broadcast together)."""
        run, leaf = np.broadcast_arrays(np.asarray(run_idx), np.asarray(leaf_idx))
        return self.sums[run, leaf + self.size]

    def update(self, run_idx: np.ndarray, leaf_idx: np.ndarray, values: np.ndarray) -> None:
        """Set leaf ``leaf_idx[k]`` of run ``run_idx[k]`` to ``values[k]`` (``run_idx`` and
        ``leaf_idx`` broadcast together; a leaf given twice takes its last value, as in
        :meth:`SumTree.update`) and refresh the ancestors of every changed leaf, all runs at
        once, level by level from the leaves up."""
        run, leaf = np.broadcast_arrays(np.asarray(run_idx, dtype=np.int64),
                                        np.asarray(leaf_idx, dtype=np.int64))  # fmt: skip
        run, leaf = run.reshape(-1), leaf.reshape(-1)
        vals = np.asarray(values, dtype=np.float64).reshape(-1)
        if leaf.shape != vals.shape:
            raise ValueError(f"{leaf.size} indices but {vals.size} values")
        if leaf.size == 0:
            return
        width = self.width
        flat = run * width + (leaf + self.size)
        if flat.size > 1:  # the last value given for each (run, leaf): first in reversed order
            flat, last = np.unique(flat[::-1], return_index=True)
            vals = vals[::-1][last]
        sums, mins = self.sums.reshape(-1), self.mins.reshape(-1)  # views
        sums[flat] = vals
        mins[flat] = vals
        base = (flat // width) * width
        pos = flat - base
        for _ in range(self.depth):  # every changed leaf is at the same depth
            pos >>= 1
            left = base + 2 * pos
            node = base + pos
            sums[node] = sums[left] + sums[left + 1]
            mins[node] = np.minimum(mins[left], mins[left + 1])

    def find(self, u: np.ndarray, runs: np.ndarray | None = None) -> np.ndarray:
        """Leaf index ``i`` with ``prefix_sum(i) <= u < prefix_sum(i + 1)`` in each run's tree.

        ``u``: ``(R, ...)`` values, row ``r`` searched in run ``r``'s tree, or ``(len(runs),
        ...)`` with ``runs`` naming the tree of each row. :meth:`SumTree.find`'s descent for
        every value at once.
        """
        u = np.array(u, dtype=np.float64)
        rows = np.arange(self.R) if runs is None else np.asarray(runs, dtype=np.int64)
        if u.ndim == 0 or u.shape[0] != len(rows):
            raise ValueError(f"find: expected {len(rows)} rows of values, got shape {u.shape}")
        base = (rows * self.width).reshape(-1, *([1] * (u.ndim - 1)))
        sums = self.sums.reshape(-1)
        node = np.ones(u.shape, dtype=np.int64)
        for _ in range(self.depth):
            left = sums[base + 2 * node]
            right = u >= left
            u -= left * right
            node = 2 * node + right
        return node - self.size


class PrioritizedReplayBufferSamples(NamedTuple):
    observations: torch.Tensor
    actions: torch.Tensor
    next_observations: torch.Tensor
    dones: torch.Tensor
    rewards: torch.Tensor
    discounts: torch.Tensor | None
    weights: torch.Tensor
    indices: np.ndarray


class PrioritizedReplayBuffer(ReplayBuffer):
    """Proportional prioritized replay (Schaul et al. 2016, section 3.3) as an SB3 buffer.

    Parameters
    ----------
    buffer_size, observation_space, action_space, device, n_envs, optimize_memory_usage,
    handle_timeout_termination
        As :class:`~stable_baselines3.common.buffers.ReplayBuffer` (one environment only).
    alpha
        Priority exponent (0: uniform; the paper's 0.6).
    beta
        Initial importance-sampling exponent (the paper's 0.4), annealed linearly to 1.
    beta_steps
        Number of :meth:`sample` calls over which beta reaches 1.
    epsilon
        Added to ``|TD error|`` so that no transition gets priority 0.
    seed
        Seed of the buffer's sampling generator.
    """

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        device: torch.device | str = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
        *,
        alpha: float = 0.6,
        beta: float = 0.4,
        beta_steps: int = 10_000,
        epsilon: float = 1e-6,
        seed: int | None = None,
    ) -> None:
        if n_envs != 1:
            raise ConfigError("prioritized replay supports one environment (n_envs=1)")
        if optimize_memory_usage:
            raise ConfigError("prioritized replay does not support optimize_memory_usage")
        super().__init__(buffer_size, observation_space, action_space, device, n_envs,
                         optimize_memory_usage, handle_timeout_termination)  # fmt: skip
        self.alpha, self.beta0, self.beta_steps = float(alpha), float(beta), int(beta_steps)
        self.epsilon = float(epsilon)
        self.tree = SumTree(self.buffer_size)
        self.max_priority = 1.0
        self.n_sampled = 0
        self.rng = np.random.default_rng(seed)

    @property
    def beta(self) -> float:
        frac = min(1.0, self.n_sampled / self.beta_steps)
        return self.beta0 + frac * (1.0 - self.beta0)

    def __len__(self) -> int:
        return self.buffer_size if self.full else self.pos

    def add(self, *args: Any, **kwargs: Any) -> None:
        idx = self.pos
        super().add(*args, **kwargs)
        self.tree.update(np.array([idx]), np.array([self.max_priority**self.alpha]))

    def sample_indices(self, batch_size: int) -> np.ndarray:
        """Stratified proportional draw of ``batch_size`` buffer indices."""
        total = self.tree.total
        u = (np.arange(batch_size) + self.rng.random(batch_size)) * (total / batch_size)
        idx = self.tree.find(np.minimum(u, np.nextafter(total, 0.0)))
        return np.minimum(idx, len(self) - 1)

    def sample(self, batch_size: int, env: Any = None) -> PrioritizedReplayBufferSamples:  # type: ignore[override]
        n = len(self)
        idx = self.sample_indices(batch_size)
        total, beta = self.tree.total, self.beta
        probs = self.tree[idx] / total
        max_weight = (n * self.tree.min / total) ** -beta
        weights = (n * probs) ** -beta / max_weight
        self.n_sampled += 1
        data = self._get_samples(idx, env=env)
        return PrioritizedReplayBufferSamples(
            *data,
            weights=self.to_torch(weights.astype(np.float32).reshape(-1, 1)),
            indices=idx,
        )

    def update_priorities(self, indices: np.ndarray, td_errors: np.ndarray) -> None:
        """Set ``p_i = |delta_i| + epsilon`` for the sampled transitions."""
        p = np.abs(np.asarray(td_errors, dtype=np.float64).reshape(-1)) + self.epsilon
        self.max_priority = max(self.max_priority, float(p.max()))
        self.tree.update(indices, p**self.alpha)


class PrioritizedDQN(TrialDQN):
    """DQN whose gradient step applies PER's importance weights and refreshes priorities.

    Reads top to bottom like :meth:`TrialDQN.train <cobelrun.agents.sb3.TrialDQN.train>`
    (``trial_end_updates`` after a trial's last step included); the differences are the
    per-sample weights on the TD loss and the priority update with ``|TD error|``.
    """

    replay_buffer: PrioritizedReplayBuffer

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        gradient_steps = self._steps_now(gradient_steps)
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        losses = []
        for _ in range(gradient_steps):
            data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)
            discounts = data.discounts if data.discounts is not None else self.gamma
            with torch.no_grad():
                next_q, _ = self.q_net_target(data.next_observations).max(dim=1)
                target = data.rewards + (1 - data.dones) * discounts * next_q.reshape(-1, 1)
            current = torch.gather(self.q_net(data.observations), dim=1, index=data.actions.long())
            td = target - current
            loss = (data.weights * self.td_loss(current, target, reduction="none")).mean()
            losses.append(loss.item())
            self.policy.optimizer.zero_grad()
            loss.backward()
            if self.max_grad_norm is not None:
                torch.nn.utils.clip_grad_norm_(self.policy.parameters(), self.max_grad_norm)
            self.policy.optimizer.step()
            self.replay_buffer.update_priorities(data.indices, td.detach().cpu().numpy())
        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/loss", np.mean(losses))
        self._record_q_max()
