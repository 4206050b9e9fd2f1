"""The choice of each trial, so that a run's trials table is a choice table for ``cobel fit``."""

from __future__ import annotations

from typing import Any

import numpy as np
import pyarrow as pa

from cobelrun.monitors.base import TrialColumnsMonitor
from cobelrun.records import TrialBatch


class ChoiceMonitor(TrialColumnsMonitor):
    """``choice``: the first action of every trial (-1 for a trial without steps).

    With the trials table's ``start_state`` and ``reward`` this is what ``cobel fit`` reads
    (docs/modelling.md: ``trials.rename(columns={"start_state": "state", "run": "session"})``).
    """

    def fields(self) -> list[pa.Field]:
        return [pa.field("choice", pa.int64())]

    def columns(self, batch: TrialBatch, env: Any) -> dict[str, np.ndarray]:
        first = batch.offsets[:-1]
        has = batch.offsets[1:] > first
        choice = np.full(batch.n_trials, -1, np.int64)
        choice[has] = batch.step_action[first[has]]
        return {"choice": choice}
