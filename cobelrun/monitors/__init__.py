"""Monitors collect measurements from trial batches; writers persist them.

Every monitor declares the tables it writes (:class:`Table`: a name, Arrow fields and a row
kind) and gets one lifecycle from the recorder:

``setup(env)``
    once, after composition: resolve place names, check the environment's contracts.
``start_run(run, agent)``
    before each independent agent's first trial.
``on_batch(batch, info)``
    after each phase's trials: return columns per table (``{table: {column: array}}``).
``end_run(run, agent, last_trial)``
    after the run's last trial.

Rows of ``per="trial"`` tables (one per trial) and ``per="step"`` tables (one per step, which
``task.record`` may thin out) from several monitors are joined side by side, so each adds
columns; ``per="event"`` tables get whole rows from one monitor, whenever it calls the
``emit(table, columns)`` function it was bound to (activity snapshots, replay events).
Monitors never do I/O, and the recorder knows no table by name: a new monitor is one class
and one YAML entry.

The protocol lives in :mod:`cobelrun.monitors.base`; the built-in monitors each in their own
module (:mod:`~cobelrun.monitors.trials`, :mod:`~cobelrun.monitors.trajectory`,
:mod:`~cobelrun.monitors.activity`, :mod:`~cobelrun.monitors.maps`, ...). The protocol and the
``trials``/``steps`` monitors are exported here too (``cobelrun.monitors.RewardMonitor``, the
name configs use).
"""

from __future__ import annotations

from cobelrun.monitors.base import (
    PATH_KINDS,
    ROW_KINDS,
    BatchInfo,
    Emit,
    Monitor,
    SceneGrid,
    ScenePath,
    Table,
    TrialColumnsMonitor,
)
from cobelrun.monitors.trajectory import TrajectoryMonitor
from cobelrun.monitors.trials import (
    EscapeLatencyMonitor,
    ResponseMonitor,
    RewardMonitor,
    TrialKeysMonitor,
)

__all__ = [
    "PATH_KINDS",
    "ROW_KINDS",
    "BatchInfo",
    "Emit",
    "EscapeLatencyMonitor",
    "Monitor",
    "ResponseMonitor",
    "RewardMonitor",
    "SceneGrid",
    "ScenePath",
    "Table",
    "TrajectoryMonitor",
    "TrialColumnsMonitor",
    "TrialKeysMonitor",
]
