"""A monitor in one class: distance travelled per trial (docs/extending.md)."""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from cobelrun.monitors import Monitor, Table


class PathLengthMonitor(Monitor):
    """Distance travelled per trial, in world units (a column of the trials table)."""

    requires = ("pose",)

    def tables(self) -> list[Table]:
        return [Table("trials", (pa.field("path_length", pa.float64()),))]

    def on_batch(self, batch, info):
        poses = batch.with_poses(info.env).poses()  # each trial: start pose, then one per step
        start = batch.offsets[:-1] + np.arange(batch.n_trials)
        after = np.repeat(start, batch.steps) + batch.step_index()
        step = np.hypot(*(poses[after, :2] - poses[after - 1, :2]).T)
        trial = batch.step_trial_index()
        return {"trials": {"path_length": np.bincount(trial, step, minlength=batch.n_trials)}}
