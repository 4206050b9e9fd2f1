"""The ``replays`` table: one row per backup an agent replays (``replays.parquet``).

Agents that replay (:class:`~cobelrun.agents.pma.PMA`) keep the backups of their last
``train``/``test`` call in ``last_replays`` (arrays, one entry per backup). This monitor turns
them into rows of its own table after every batch of trials: ``run``, ``trial`` (1-based across
phases, as in ``trials.parquet``), ``when`` (``start``: before the trial's first action,
``end``: on arriving at the goal), ``index`` (position in the replay event), the agent's state,
the replayed ``state, action, next_state, reward``, its ``gain``, ``need`` and the ``length`` of
the (n-step) backup. Agents that do not replay give no rows. Events (direction, length,
distance) are derived by :func:`cobelrun.analysis.replay.replay_events`.

In ``run.mcap`` every replay bout of a kept run is drawn on ``/run_NNNN/replay`` (a
:class:`~cobelrun.monitors.ScenePath`): one line strip per replay event through the replayed
states in the order they were replayed, coloured by direction, at the trial's start or end.
"""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np
import pyarrow as pa

from cobelrun.errors import ConfigError
from cobelrun.monitors.base import BatchInfo, Monitor, ScenePath, Table
from cobelrun.records import TrialBatch

WHEN_NAMES = np.array(["start", "end"], dtype=object)


class ReplayMonitor(Monitor):
    """Every replayed experience of agents that replay (the ``replays`` table, per event)."""

    requires = ("tabular_model", "discrete_states")

    def __init__(self) -> None:
        self._agent: Any = None

    def tables(self) -> list[Table]:
        return [Table("replays", (
            pa.field("run", pa.int32()), pa.field("trial", pa.int32()),
            pa.field("when", pa.string()), pa.field("index", pa.int32()),
            pa.field("agent_state", pa.int64()), pa.field("state", pa.int64()),
            pa.field("action", pa.int16()), pa.field("next_state", pa.int64()),
            pa.field("reward", pa.float64()), pa.field("gain", pa.float64()),
            pa.field("need", pa.float64()), pa.field("length", pa.int32()),
        ), per="event")]  # fmt: skip

    def start_run(self, run: int, agent: Any = None) -> None:
        """The run's agent: its ``last_replays`` are read after every batch."""
        replays = getattr(agent, "last_replays", None)
        if replays is not None and not isinstance(replays, dict):
            raise ConfigError(f"replays monitor: {type(agent).__name__}.last_replays is no dict")
        self._agent = agent

    def resume_run(self, run: int, agent: Any, state: Any) -> None:
        """A run continued from a checkpoint: its agent, as :meth:`start_run`."""
        super().resume_run(run, agent, state)
        self.start_run(run, agent)

    def end_run(self, run: int, agent: Any, last_trial: int) -> None:
        self._agent = None

    def on_batch(self, batch: TrialBatch, info: BatchInfo) -> dict[str, dict[str, np.ndarray]]:
        rep = getattr(self._agent, "last_replays", None)
        if not rep or rep["trial"].size == 0:
            return {}
        n = rep["trial"].size
        self.emit("replays", {
            "run": np.full(n, info.run, np.int32),
            "trial": (rep["trial"] + info.first_trial).astype(np.int32),
            "when": WHEN_NAMES[rep["when"].astype(np.int64)],
            "index": rep["index"].astype(np.int32),
            "agent_state": rep["agent_state"].astype(np.int64),
            "state": rep["state"].astype(np.int64),
            "action": rep["action"].astype(np.int16),
            "next_state": rep["next_state"].astype(np.int64),
            "reward": rep["reward"].astype(np.float64),
            "gain": rep["gain"].astype(np.float64),
            "need": rep["need"].astype(np.float64),
            "length": rep["length"].astype(np.int32),
        })  # fmt: skip
        return {}

    def scene_paths(self, batch: TrialBatch, info: BatchInfo) -> list[ScenePath]:
        """Each replay bout of the batch as a path on ``/run_NNNN/replay``: one segment per
        event (:func:`~cobelrun.analysis.replay.split_events`) through the states' positions."""
        from cobelrun.analysis.replay import event_path, split_events

        rep = getattr(self._agent, "last_replays", None)
        if not rep or rep["trial"].size == 0:
            return []
        base = info.env.unwrapped
        bounds = [*np.flatnonzero(rep["index"] == 0).tolist(), rep["trial"].size]
        paths = []
        for lo, hi in itertools.pairwise(bounds):
            s, s2 = rep["state"][lo:hi], rep["next_state"][lo:hi]
            segments, kinds = [], []
            for a, b, direction in split_events(s, s2):
                for states in event_path(s[a : b + 1], s2[a : b + 1], direction):
                    segments.append(base.poses_of(states)[:, :2])
                    kinds.append(direction)
            when = str(WHEN_NAMES[int(rep["when"][lo])])
            trial = int(rep["trial"][lo])
            meta = {"trial": str(trial + info.first_trial), "when": when,
                    "agent_state": str(int(rep["agent_state"][lo])), "backups": str(hi - lo)}  # fmt: skip
            paths.append(ScenePath("replay", trial, when, tuple(segments), tuple(kinds), meta))
        return paths
