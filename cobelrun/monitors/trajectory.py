"""The built-in monitor of the ``steps`` table: every step's state, pose, action and reward."""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from cobelrun.envs.base import DiscreteStates, supports
from cobelrun.monitors.base import BatchInfo, Monitor, Table
from cobelrun.records import TrialBatch

__all__ = ["TrajectoryMonitor"]


class TrajectoryMonitor(Monitor):
    """Every step: run, trial, step, state, pose (x, y, heading), action, reward, next state
    and the pose after the step (next_x, next_y, next_heading): the ``steps`` table.

    Positions come from the env's pose contract: ``x``/``y``/``heading`` where the action was
    taken, ``next_*`` where it led, so a trial's path is its rows' poses followed by the last
    row's ``next_*`` (the arrival: goal cells are visited). Envs without poses write NaN.
    Joinable: the recorder builds the table from many batches at once, on its writer thread.
    Run folders written before ``next_*`` existed lack those columns
    (:func:`cobelrun.analysis.paths.visited_poses` falls back to the poses before each step).
    """

    joinable = True

    def tables(self) -> list[Table]:
        return [Table("steps", (
            pa.field("run", pa.int32()), pa.field("trial", pa.int32()),
            pa.field("step", pa.int32()), pa.field("state", pa.int64()),
            pa.field("x", pa.float64()), pa.field("y", pa.float64()),
            pa.field("heading", pa.float32()), pa.field("action", pa.int16()),
            pa.field("reward", pa.float64()), pa.field("next_state", pa.int64()),
            pa.field("next_x", pa.float64()), pa.field("next_y", pa.float64()),
            pa.field("next_heading", pa.float32()),
        ), per="step")]  # fmt: skip

    def on_batch(self, batch: TrialBatch, info: BatchInfo) -> dict[str, dict[str, np.ndarray]]:
        n = batch.n_trials
        base = info.env.unwrapped
        if batch.step_pose is None and supports(base, DiscreteStates):
            # the pose each action was taken in: its state, reached by the previous action
            prev = np.empty_like(batch.step_action)
            prev[1:] = batch.step_action[:-1]
            prev[batch.offsets[:-1][batch.steps > 0]] = -1
            before = base.poses_of(batch.step_state, prev)
            # where a step led is where the trial's next step starts; only each trial's last
            # step needs its own look-up
            after = np.empty_like(before)
            after[:-1] = before[1:]
            last = batch.offsets[1:][batch.steps > 0] - 1
            after[last] = base.poses_of(batch.step_next_state[last], batch.step_action[last])
        elif (poses := batch.with_poses(info.env).poses()) is not None:
            last = batch.offsets[1:] + np.arange(n)  # drop each trial's final pose
            keep = np.ones(poses.shape[0], bool)
            keep[last] = False
            before = poses[keep]
            after = batch.step_pose
        else:
            before = after = np.full((batch.n_steps, 3), np.nan)
        return {"steps": {
            "run": np.repeat(info.runs(n), batch.steps),
            "trial": np.repeat(info.trials(n), batch.steps),
            "step": batch.step_index().astype(np.int32),
            "state": batch.step_state,
            "x": before[:, 0], "y": before[:, 1], "heading": before[:, 2].astype(np.float32),
            "action": batch.step_action.astype(np.int16),
            "reward": batch.step_reward,
            "next_state": batch.step_next_state,
            "next_x": after[:, 0], "next_y": after[:, 1],
            "next_heading": after[:, 2].astype(np.float32),
        }}  # fmt: skip
