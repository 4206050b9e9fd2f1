"""Trial records: what an agent hands to monitors after running trials.

Agents run whole trials (in compiled code where they can) and return a :class:`TrialBatch`:
per-trial summaries plus flat per-step arrays, indexed through ``offsets``. Monitors turn
batches into table columns; writers persist them. No per-step Python is needed on this path.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class TrialBatch:
    """Records of ``n`` consecutive trials of one agent.

    Attributes
    ----------
    start_state, end_state : (n,) int64
        State at trial start and the state the trial ended in.
    steps : (n,) int64
        Number of steps (actions) taken in each trial ("escape latency").
    reward : (n,) float64
        Sum of rewards received in each trial.
    terminated : (n,) bool
        True if the trial ended in a terminal state, False if it hit ``max_steps``.
    offsets : (n + 1,) int64
        Trial ``i``'s steps are ``step_*[offsets[i]:offsets[i + 1]]``.
    step_state, step_action, step_next_state : (total_steps,) int64
        State in which each action was taken, the action, and the state it led to.
    step_reward : (total_steps,) float64
        Reward received on arriving in ``step_next_state``.
    extra : dict
        Agent-specific per-trial arrays (e.g. ``loss``), each of shape (n,).
    start_pose : (n, 3) float64 or None
        Pose ``(x, y, heading)`` at each trial's start (world units, heading in radians).
    step_pose : (total_steps, 3) float64 or None
        Pose after each step. Agents that run the Python step loop fill both from the env's
        pose contract; compiled tabular agents leave them None and :meth:`with_poses` derives
        them from the states (``DiscreteStates.poses_of``) when a consumer asks.
    """

    start_state: np.ndarray
    end_state: np.ndarray
    steps: np.ndarray
    reward: np.ndarray
    terminated: np.ndarray
    offsets: np.ndarray
    step_state: np.ndarray
    step_action: np.ndarray
    step_next_state: np.ndarray
    step_reward: np.ndarray
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    start_pose: np.ndarray | None = None
    step_pose: np.ndarray | None = None

    @property
    def n_trials(self) -> int:
        return int(self.steps.shape[0])

    @property
    def n_steps(self) -> int:
        return int(self.offsets[-1])

    def step_trial_index(self) -> np.ndarray:
        """Index (0-based, within this batch) of the trial each step belongs to."""
        return np.repeat(np.arange(self.n_trials, dtype=np.int64), self.steps)

    def step_index(self) -> np.ndarray:
        """1-based step number of each step within its trial."""
        idx = np.arange(self.n_steps, dtype=np.int64)
        return idx - np.repeat(self.offsets[:-1], self.steps) + 1

    def with_poses(self, env: Any) -> TrialBatch:
        """This batch with ``start_pose``/``step_pose`` filled in from ``env``'s
        :class:`~cobelrun.envs.base.DiscreteStates` contract where they are missing (the
        batch is changed in place and returned). Envs without poses leave them None."""
        from cobelrun.envs.base import DiscreteStates, supports

        base = getattr(env, "unwrapped", env)
        if self.step_pose is None and supports(base, DiscreteStates):
            self.start_pose = base.poses_of(self.start_state)
            self.step_pose = base.poses_of(self.step_next_state, self.step_action)
        return self

    def poses(self) -> np.ndarray | None:
        """(n_steps + n, 3) poses in time order: each trial's start pose, then its steps'."""
        if self.start_pose is None or self.step_pose is None:
            return None
        n = self.n_trials
        out = np.empty((self.n_steps + n, 3))
        start_pos = self.offsets[:-1] + np.arange(n)
        is_start = np.zeros(out.shape[0], bool)
        is_start[start_pos] = True
        out[is_start] = self.start_pose
        out[~is_start] = self.step_pose
        return out

    @classmethod
    def concat(
        cls, batches: list[TrialBatch],
        alloc: Callable[[tuple[int, ...], np.dtype], np.ndarray] | None = None,
    ) -> TrialBatch:  # fmt: skip
        """Consecutive batches as one (poses kept only if every batch has them);
        ``alloc(shape, dtype)``, when given, provides the joined arrays (e.g. views of a
        reused buffer) instead of fresh ones."""
        if not batches:
            return cls.from_trials([])
        offsets = [np.zeros(1, np.int64)]
        total = 0
        for b in batches:
            offsets.append(b.offsets[1:] + total)
            total += b.n_steps

        def cat(name: str) -> np.ndarray:
            parts = [getattr(b, name) for b in batches]
            if alloc is None:
                return np.concatenate(parts)
            shape = (sum(p.shape[0] for p in parts), *parts[0].shape[1:])
            dtype = np.result_type(*parts)
            return np.concatenate(parts, out=alloc(shape, dtype))

        poses = all(b.step_pose is not None for b in batches)
        extra_keys = set(batches[0].extra).intersection(*(b.extra for b in batches[1:]))
        return cls(
            start_state=cat("start_state"), end_state=cat("end_state"), steps=cat("steps"),
            reward=cat("reward"), terminated=cat("terminated"), offsets=np.concatenate(offsets),
            step_state=cat("step_state"), step_action=cat("step_action"),
            step_next_state=cat("step_next_state"), step_reward=cat("step_reward"),
            extra={k: np.concatenate([b.extra[k] for b in batches]) for k in extra_keys},
            start_pose=cat("start_pose") if poses else None,
            step_pose=cat("step_pose") if poses else None,
        )  # fmt: skip

    @classmethod
    def from_trials(cls, trials: list[dict[str, Any]]) -> TrialBatch:
        """Build a batch from per-trial dicts with keys ``states`` (n_steps + 1), ``actions``,
        ``rewards`` (n_steps each) and ``terminated`` (bool), and optionally ``poses``
        ((n_steps + 1, 3), the start pose then the pose after each step): the slow path's
        format."""
        steps = np.array([len(t["actions"]) for t in trials], dtype=np.int64)
        offsets = np.zeros(len(trials) + 1, dtype=np.int64)
        np.cumsum(steps, out=offsets[1:])

        def cat(key: str, sl: slice, dtype: type) -> np.ndarray:
            parts = [np.asarray(t[key], dtype=dtype)[sl] for t in trials]
            return np.concatenate(parts) if parts else np.zeros(0, dtype=dtype)

        return cls(
            start_state=np.array([t["states"][0] for t in trials], dtype=np.int64),
            end_state=np.array([t["states"][-1] for t in trials], dtype=np.int64),
            steps=steps,
            reward=np.array([float(np.sum(t["rewards"])) for t in trials], dtype=np.float64),
            terminated=np.array([bool(t["terminated"]) for t in trials], dtype=bool),
            offsets=offsets,
            step_state=cat("states", slice(0, -1), np.int64),
            step_action=cat("actions", slice(None), np.int64),
            step_next_state=cat("states", slice(1, None), np.int64),
            step_reward=cat("rewards", slice(None), np.float64),
            **_poses(trials),
        )


def _poses(trials: list[dict[str, Any]]) -> dict[str, np.ndarray]:
    """``start_pose``/``step_pose`` of per-trial dicts that all carry ``poses``."""
    if not trials or not all(t.get("poses") is not None for t in trials):
        return {}
    poses = [np.asarray(t["poses"], np.float64).reshape(-1, 3) for t in trials]
    return {
        "start_pose": np.stack([p[0] for p in poses]),
        "step_pose": np.concatenate([p[1:] for p in poses]),
    }
