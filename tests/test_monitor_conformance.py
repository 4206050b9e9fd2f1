"""Monitor conformance: every monitor class cobel ships (found in ``cobelrun.monitors.*``, so a
new one is covered as soon as it exists) is run in a tiny built-in task and checked for

- its lifecycle: ``setup`` before anything else, then per run ``start_run``, the run's trial
  batches in trial order, ``end_run`` with the run's last trial (the recorder's contract,
  ``cobelrun.monitors`` docstring);
- every table it declares written, with the declared Arrow type for each of its columns;
- kill safety: a run stopped (Ctrl-C) in the middle of its first phase leaves every declared
  table readable, with the declared types, holding a prefix of the uninterrupted run's rows.

Runs go one after the other (``task.batch_runs=false``); the batched path, which records each
run through forked monitors, is checked against it in ``tests/test_batched.py``.

A new monitor needs one entry in ``CASES`` (a built-in task that uses it, made tiny);
:func:`test_every_shipped_monitor_has_a_case` fails until it has one.
"""

from __future__ import annotations

import importlib
import inspect
import json
import pkgutil
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from omegaconf import open_dict

import cobelrun.monitors
from cobelrun.monitors.base import Monitor
from cobelrun.recorder import RunRecorder
from tests.conftest import stop_on_call


def shipped_monitors() -> dict[str, type[Monitor]]:
    """Every concrete :class:`Monitor` defined in a module of ``cobelrun.monitors``, by name."""
    found: dict[str, type[Monitor]] = {}
    for info in pkgutil.iter_modules(cobelrun.monitors.__path__):
        module = importlib.import_module(f"cobelrun.monitors.{info.name}")
        for obj in vars(module).values():
            if (
                inspect.isclass(obj)
                and issubclass(obj, Monitor)
                and not inspect.isabstract(obj)
                and obj.__module__ == module.__name__
            ):
                found[obj.__name__] = obj
    return dict(sorted(found.items()))


#: tiny runs that use each monitor: (task, overrides); every phase is cut to FIRST_PHASE /
#: OTHER_PHASES trials and the task to at most RUNS runs (:func:`compose_tiny`)
TMAZE = ("tmaze_extinction", [])
MAPS = (
    "place_cells",
    ["task.runs=1", "task.protocol.max_steps=6", "agent.learning_starts=4", "task.monitors.maps.every=5",
     "task.monitors.maps.grid=[4,4]", "task.monitors.maps.headings=2"],
)  # fmt: skip
CASES: dict[str, tuple[str, list[str]]] = {
    "TrialKeysMonitor": TMAZE,
    "RewardMonitor": TMAZE,
    "EscapeLatencyMonitor": TMAZE,
    "ResponseMonitor": TMAZE,
    "TrajectoryMonitor": TMAZE,
    "ReplayMonitor": ("dyna_maze", []),
    "ActivityMonitor": ("latent_learning", ["task.protocol.max_steps=20"]),
    "ActivityMapMonitor": MAPS,
    "GreedyProbeMonitor": ("two_afc", []),
    "WaterMazeMonitor": ("morris_water_maze", ["task.protocol.max_steps=30"]),
    "ChoiceMonitor": ("reversal_bandit", []),
    "ConditioningMonitor": ("acquisition_extinction", []),
}
RUNS, FIRST_PHASE, OTHER_PHASES = 2, 10, 3
#: monitors whose runs need optional packages
NEEDS = {
    "ActivityMonitor": "stable_baselines3",
    "ActivityMapMonitor": "pybullet",
    "GreedyProbeMonitor": "stable_baselines3",
}
SHIPPED = shipped_monitors()
#: kill checks left to the slow suite (a rendered run: its tables' writers are the same)
SLOW_KILL = {"ActivityMapMonitor"}
#: monitors the runner adds to every task itself (not configured, so ``setup`` is not called:
#: they need nothing from the env)
RUNNER_ADDS = {"TrialKeysMonitor"}


def compose_tiny(name: str) -> Any:
    from cobelrun import api

    if name in NEEDS:
        pytest.importorskip(NEEDS[name])
    task, overrides = CASES[name]
    cfg = api.compose(task, ["seed=5", "task.record.mcap=false", *overrides])
    with open_dict(cfg):
        cfg.task.runs = min(RUNS, int(cfg.task.runs))
        for i, phase in enumerate(cfg.task.protocol.phases):
            phase.trials = min(int(phase.trials), FIRST_PHASE if i == 0 else OTHER_PHASES)
        cfg.task.record.runs = "all"
        cfg.task.record.trial_every = 1
        cfg.task.record.flush_seconds = 1e-9  # a phase is recorded in pieces (kill test)
        # the runs one after the other (the batched path's forks and kills: test_batched.py)
        cfg.task.batch_runs = False
    return cfg


def n_trials(cfg: Any) -> int:
    return sum(int(p.trials) for p in cfg.task.protocol.phases)


def run_tiny(cfg: Any, out: Path) -> Any:
    """Build and run ``cfg`` in this process; the task (its monitors) is returned."""
    from cobelrun.runner import build_task, run

    task = build_task(cfg)
    run(cfg, out, task=task)
    return task


def spy(monkeypatch: pytest.MonkeyPatch, cls: type[Monitor]) -> list[tuple[Any, ...]]:
    """The lifecycle calls of ``cls``'s instances (forks included), in the order they come."""
    calls: list[tuple[Any, ...]] = []

    def wrap(name: str) -> None:
        original = getattr(cls, name)

        def spying(self, *args: Any, **kwargs: Any) -> Any:
            if type(self) is cls:
                if name == "on_batch":
                    batch, info = args
                    n = batch.n_trials
                    calls.append((name, info.runs(n).copy(), info.trials(n).copy()))
                elif name == "setup":
                    calls.append((name,))
                else:  # start_run(run, agent), end_run(run, agent, last_trial)
                    calls.append((name, int(args[0]), *[int(a) for a in args[2:]]))
            return original(self, *args, **kwargs)

        monkeypatch.setattr(cls, name, spying)

    for name in ("setup", "start_run", "on_batch", "end_run"):
        wrap(name)
    return calls


def test_every_shipped_monitor_has_a_case():
    """Discovery finds the built-in monitors, and each has a tiny run here."""
    assert {"RewardMonitor", "TrajectoryMonitor", "ActivityMapMonitor"} <= set(SHIPPED)
    missing = sorted(set(SHIPPED) - set(CASES))
    assert not missing, f"add a tiny run for {missing} to CASES"
    assert not set(CASES) - set(SHIPPED), "CASES names a monitor cobel no longer ships"
    # (each case's task builds its monitor: monitor_of() in the tests below asserts it)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """``get(name)``: the uninterrupted tiny run of monitor ``name``'s case, run once per case
    task with every shipped monitor's lifecycle calls recorded: (config, task, calls by
    monitor class, run folder)."""
    cache: dict[tuple[str, tuple[str, ...]], tuple[Any, Any, dict, Path]] = {}

    def get(name: str) -> tuple[Any, Any, dict, Path]:
        task_name, overrides = CASES[name]
        key = (task_name, tuple(overrides))
        if key not in cache:
            cfg = compose_tiny(name)
            out = tmp_path_factory.mktemp(task_name) / "run"
            with pytest.MonkeyPatch.context() as mp:
                calls = {cls: spy(mp, cls) for cls in SHIPPED.values()}
                task = run_tiny(cfg, out)
            cache[key] = (cfg, task, calls, out)
        return cache[key]

    return get


def check_declared(out: Path, monitor: Monitor) -> dict[str, pd.DataFrame]:
    """Every table ``monitor`` declares is in ``out`` with the declared type of each of its
    columns; the tables, read with pandas."""
    tables = {}
    for table in monitor.tables():
        path = out / f"{table.name}.parquet"
        assert path.is_file(), f"{type(monitor).__name__} declares {table.name}, not written"
        schema = pq.read_schema(path)
        for field in table.fields:
            assert field.name in schema.names, (table.name, field.name)
            assert schema.field(field.name).type == field.type, (table.name, field)
        tables[table.name] = pd.read_parquet(path)
    return tables


@pytest.mark.parametrize("name", list(SHIPPED))
def test_lifecycle_and_declared_tables(name, reference):
    cls = SHIPPED[name]
    cfg, task, by_class, out = reference(name)
    calls = by_class[cls]

    # setup first, once, then each run's start, batches in trial order, end
    if name not in RUNNER_ADDS:
        assert calls and calls[0] == ("setup",), calls[:3]
        assert [c for c in calls if c[0] == "setup"] == [("setup",)]
    total = n_trials(cfg)
    joinable = cls.joinable
    for run in range(int(cfg.task.runs)):
        starts = [i for i, c in enumerate(calls) if c[0] == "start_run" and c[1] == run]
        ends = [i for i, c in enumerate(calls) if c[0] == "end_run" and c[1] == run]
        assert len(starts) == 1 and len(ends) == 1, (run, calls)
        assert starts[0] < ends[0]
        assert calls[ends[0]][2] == total  # end_run(run, agent, last_trial)
        trials = []
        for i, c in enumerate(calls):
            if c[0] != "on_batch":
                continue
            mine = c[1] == run
            if mine.any() and not joinable:  # joinable ones may be called later, on a thread
                assert starts[0] < i < ends[0], (run, i, starts, ends)
            trials.append(c[2][mine])
        trials = np.concatenate(trials) if trials else np.zeros(0, int)
        per = {t.per for t in monitor_of(task, cls).tables()}
        if per & {"trial", "step"}:  # every trial of the run, once, in order
            np.testing.assert_array_equal(trials, np.arange(1, total + 1))
        else:
            assert np.all(np.diff(trials) > 0), trials

    tables = check_declared(out, monitor_of(task, cls))
    for table in monitor_of(task, cls).tables():
        if table.per == "trial":
            assert len(tables[table.name]) == int(cfg.task.runs) * total


def monitor_of(task: Any, cls: type[Monitor]) -> Monitor:
    """The task's monitor of class ``cls`` (a new one for those the runner adds)."""
    if cls.__name__ in RUNNER_ADDS:
        return cls()
    found = [m for m in task.monitors.values() if type(m) is cls]
    assert len(found) == 1, (cls.__name__, list(task.monitors))
    return found[0]


@pytest.mark.parametrize(
    "name",
    [pytest.param(n, marks=[pytest.mark.slow] if n in SLOW_KILL else []) for n in SHIPPED],
)
def test_stopped_run_leaves_readable_declared_tables(name, reference, tmp_path, monkeypatch):
    """Ctrl-C in the middle of run 0's first phase (the 2nd piece handed to the recorder):
    the declared tables are readable, typed as declared, and a prefix of the full run."""
    cfg, task, _, full_dir = reference(name)
    monitor = monitor_of(task, SHIPPED[name])
    full = check_declared(full_dir, monitor)

    stop_on_call(monkeypatch, RunRecorder, "record", 2, KeyboardInterrupt)
    out = tmp_path / "stopped"
    with pytest.raises(KeyboardInterrupt):
        run_tiny(cfg, out)
    monkeypatch.undo()
    assert json.loads((out / "manifest.json").read_text())["status"] == "interrupted"
    assert not (out / ".done").exists()
    trials = pd.read_parquet(out / "trials.parquet")
    assert 0 < len(trials) < int(cfg.task.protocol.phases[0].trials)  # in run 0's first phase
    for table in monitor.tables():
        path = out / f"{table.name}.parquet"
        if not path.exists():  # an event table with no row yet
            assert table.per == "event", table.name
            continue
        schema = pq.read_schema(path)
        for field in table.fields:
            assert schema.field(field.name).type == field.type, (table.name, field)
        kept = pd.read_parquet(path)
        assert len(kept) <= len(full[table.name]), table.name
        if table.per in ("trial", "step"):
            want = full[table.name].iloc[: len(kept)].reset_index(drop=True)
            pd.testing.assert_frame_equal(kept, want, obj=table.name)
