"""RunRecorder: routes monitor rows to table writers and poses/trial events to the MCAP stream.

The recorder knows no table by name: monitors declare their tables
(:class:`~cobelrun.monitors.Table`), and per-trial columns of several monitors are joined side
by side. Rows are buffered and handed to :class:`~cobelrun.io.parquet.PartedTableWriter` in
parts, bounded by rows *and* time (``record.flush_seconds``, default 2 s), so a killed process
loses at most the last couple of seconds; at the end the parts are merged into one Parquet file
per table. Buffer changes run inside :meth:`SignalGuard.critical`, so Ctrl-C or SIGTERM never
drops rows that were already taken from a buffer.

Per-step tables are the bulk of a job (a 20,000-run Fig. 6B job has 60 million step rows), so
monitors that declare themselves :attr:`~cobelrun.monitors.Monitor.joinable` (the trajectory
monitor) are not called per batch: the recorder keeps the batches (the agent's arrays, no
copy) and, every ~260,000 steps or ``flush_seconds``, joins them and has the monitor build the
columns of all of them at once, on the writer thread. The simulation thread then spends a list
append per batch on the step table.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from cobelrun.errors import ConfigError
from cobelrun.io.agents_archive import AgentArchive
from cobelrun.io.parquet import PartedTableWriter
from cobelrun.io.run_folder import RunFolder
from cobelrun.monitors import BatchInfo, Monitor, Table
from cobelrun.records import TrialBatch
from cobelrun.signals import Interrupted, SignalGuard
from cobelrun.step_writer import StepWriterProcess

__all__ = ["Interrupted", "RecordConfig", "RunRecorder", "SignalGuard"]
from cobelrun.schema import RecordSpec, validate

#: simulated time per step in the MCAP stream (100 ms)
STEP_NS = 100_000_000
#: how long a monitor's path (a replay event) stays drawn in the MCAP viewer: 10 steps
PATH_LIFETIME_NS = 10 * STEP_NS
#: Parquet key/value metadata schema version of cobel's tables
SCHEMA_VERSION = "2"


@dataclass(frozen=True)
class RecordConfig:
    """What to write, and how often.

    Attributes
    ----------
    steps
        Write per-step tables (``steps.parquet``; needs a trajectory monitor).
    mcap
        Write ``run.mcap`` (maze scene, pose stream, trial events).
    runs
        ``"all"`` or a list of run indices (0-based) whose steps are recorded.
    trial_every
        Record the steps of every N-th trial (1 = every trial). Trial 1 is always recorded.
    mcap_runs
        Poses and trial events of the first N runs go into ``run.mcap`` (``"all"``: every
        run). ``trials.parquet`` holds every trial; events of 20,000 runs would make the
        viewer file ~230 MB.
    flush_seconds
        Hand buffered rows to disk at least this often (bounds what a SIGKILL can lose).
    images
        Also write the env's camera frames (``env.render()``, ``rgb_array``) of the MCAP runs
        as ``foxglove.RawImage`` (``/run_0007/camera``); per-step hooks make compiled agents
        take their Python path.
    training_log
        Deep (SB3) agents log their training curves (loss, max Q at the current observation,
        epsilon, mean trial return) through SB3's logger as CSV, and TensorBoard when installed,
        into ``training/run_NNNN/``.
    step_writer
        Where the per-step tables are built and written: ``"thread"`` (the writer thread) or
        ``"process"`` (a child process forked when the recorder starts: its Python work never
        waits for the simulation's GIL; Linux, main thread, background writes, else the
        thread). The process pays only with a core to spare for it: on 2 cores it was slower
        (docs/speed.md).
    mcap_timeline
        ``"sequential"``: runs follow each other on ``run.mcap``'s log clock (100 ms per
        pose); ``"per_run"``: every run's clock starts at the file's start, so that runs can be
        watched side by side.
    live
        Also stream what ``run.mcap`` gets (and the per-trial series) to a live view:
        foxglove-sdk's WebSocket server on ``live_host:live_port`` (:mod:`cobelrun.io.live`).
        A port in use is one line; the run goes on.
    live_port, live_host
        Where the live view listens (port 0: any free port).
    live_wait
        Seconds to wait for a live client before the first trial (0: start at once).
    """

    steps: bool = True
    mcap: bool = True
    runs: str | Sequence[int] = "all"
    trial_every: int = 1
    mcap_runs: int | str = 10
    flush_seconds: float = 2.0
    images: bool = False
    training_log: bool = False
    step_writer: str = "thread"
    mcap_timeline: str = "sequential"
    live: bool = False
    live_port: int = 8765
    live_host: str = "127.0.0.1"
    live_wait: float = 0.0

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any] | None, where: str = "task.record") -> RecordConfig:
        """Build from a plain mapping (``task.record``; ``None``: the defaults), validated by
        :class:`cobelrun.schema.RecordSpec` (errors are one-line ConfigErrors)."""
        return cls.from_spec(validate(RecordSpec, {} if cfg is None else cfg, where))

    @classmethod
    def from_spec(cls, spec: RecordSpec) -> RecordConfig:
        """Build from a validated :class:`cobelrun.schema.RecordSpec`."""
        return cls(
            steps=spec.steps,
            mcap=spec.mcap,
            runs=spec.runs if spec.runs == "all" else tuple(spec.runs),
            trial_every=spec.trial_every,
            mcap_runs=spec.mcap_runs,
            flush_seconds=float(spec.flush_seconds),
            images=spec.images,
            training_log=spec.training_log,
            step_writer=spec.step_writer,
            mcap_timeline=spec.mcap_timeline,
            live=spec.live,
            live_port=spec.live_port,
            live_host=spec.live_host,
            live_wait=float(spec.live_wait),
        )

    def records_run(self, run: int) -> bool:
        return self.runs == "all" or run in self.runs

    def mcap_run(self, run: int) -> bool:
        return self.mcap_runs == "all" or run < int(self.mcap_runs)


class WriterThread:
    """Runs write calls in submission order on one background thread.

    The simulation hands finished rows over and goes on (Arrow's Parquet encoder releases the
    GIL). At most ``max_pending`` calls wait; an exception in a write is raised in the calling
    thread at the next :meth:`submit` or at :meth:`close`. With ``enabled=False`` calls run
    immediately in the calling thread.
    """

    def __init__(self, *, enabled: bool = True, max_pending: int = 8) -> None:
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="cobel-writer") if enabled else None
        self._pending: collections.deque[Future] = collections.deque()
        self._max_pending = max_pending
        #: CPU seconds the background thread spent in write calls (0 when disabled)
        self.cpu_s = 0.0

    def _timed(self, fn: Callable[..., Any], *args: Any) -> None:
        t0 = time.thread_time()
        try:
            fn(*args)
        finally:
            self.cpu_s += time.thread_time() - t0

    def submit(self, fn: Callable[..., Any], *args: Any) -> None:
        if self._pool is None:
            fn(*args)
            return
        while self._pending and (
            self._pending[0].done() or len(self._pending) >= self._max_pending
        ):
            self._pending.popleft().result()
        self._pending.append(self._pool.submit(self._timed, fn, *args))

    def drain(self) -> None:
        """Wait until every submitted call has run (raising the first error)."""
        while self._pending:
            self._pending.popleft().result()

    def close(self) -> None:
        """Wait for pending calls (raising the first error) and stop the thread."""
        try:
            while self._pending:
                self._pending.popleft().result()
        finally:
            if self._pool is not None:
                self._pool.shutdown(wait=True, cancel_futures=False)


class _TableSink:
    """Buffered rows of one table, handed to its writer in parts (by rows or by time)."""

    def __init__(self, writer: PartedTableWriter, rows: int, seconds: float) -> None:
        self.writer = writer
        self._rows, self._seconds = rows, seconds
        self._parts: list[Mapping[str, Any]] = []
        self._pending = 0
        self._last = time.monotonic()

    def add(self, columns: Mapping[str, Any], n: int) -> bool:
        """Buffer rows; True if a flush is due."""
        if n:
            self._parts.append(columns)
            self._pending += n
        return self._pending >= self._rows or (
            self._pending and time.monotonic() - self._last >= self._seconds
        )

    def take(self) -> list[Mapping[str, Any]] | None:
        """The buffered column batches (emptied inside the caller's critical section; joined
        and converted to Arrow on the writer thread)."""
        self._last = time.monotonic()
        if not self._parts:
            return None
        parts, self._parts, self._pending = self._parts, [], 0
        return parts


class _FrameGrabber:
    """Grabs ``env.render()`` at each trial start and after each step (the poses' times)."""

    def __init__(self, env: Any) -> None:
        from cobelrun.agents.base import TrialCallback

        grabber = self

        class Hook(TrialCallback):
            def _on_trial_start(self, agent: Any, trial: int, state: int) -> None:
                grabber.grab()

            def _on_step(self, agent: Any, trial: int, step: int, transition: Any) -> bool:
                grabber.grab()
                return True

        self.env, self.hook, self.frames = env, Hook(), []

    def grab(self) -> None:
        frame = self.env.render()
        if frame is not None:
            self.frames.append(np.ascontiguousarray(frame, dtype=np.uint8))

    def take(self, n: int) -> list[np.ndarray]:
        frames, self.frames = self.frames[:n], self.frames[n:]
        return frames


def _write_columns(writer: PartedTableWriter, parts: list[Mapping[str, Any]]) -> None:
    """Join column batches and write them as one part (runs on the writer thread)."""
    if len(parts) == 1:
        writer.write_part(parts[0])
        return
    names = parts[0].keys()
    writer.write_part({k: np.concatenate([np.asarray(p[k]) for p in parts]) for k in names})


class RunRecorder:
    """Feeds trial batches to the monitors and streams their tables to the run folder.

    Parameters
    ----------
    folder
        The run folder.
    env
        The environment (monitors and poses ask its contracts).
    monitors
        The task's monitors, in order (the trial-key monitor first).
    record
        What to write.
    metadata
        Key/value metadata for every Parquet table (version, config hash, seed).
    guard
        The run's :class:`SignalGuard` (a fresh one if not given).
    background
        Write on a second thread (sweeps switch it off: their jobs already fill the cores).
    mcap_factory
        Builds the MCAP writer: ``factory(path, geometry=..., start_ns=...)``.
    """

    #: rows per part of a table (and per Parquet row group of per-trial and event tables)
    ROW_GROUP_ROWS = 1 << 16
    #: steps of joined batches per part of a per-step table (every flush is held in up to
    #: four forms at once: the runs' batches, their join, the columns, the Arrow part; at
    #: 1 << 18 the peak RSS of 1,000 Fig. 6B runs was 318-333 MB, at 1 << 17 286-290 MB)
    JOIN_STEPS = 1 << 17
    #: Parquet row group of per-step tables (262,144 rows, Polars' default; ~15 MB of Arrow
    #: buffers before encoding)
    STEP_ROW_GROUP_ROWS = 1 << 18
    #: MCAP trial tables handed to the writer thread together
    MCAP_TABLES = 64

    def __init__(
        self,
        folder: RunFolder,
        env: Any,
        monitors: Sequence[Monitor],
        record: RecordConfig,
        *,
        metadata: Mapping[str, str] | None = None,
        guard: SignalGuard | None = None,
        background: bool = True,
        geometry: Any = None,
        save_agents: bool = False,
        resume: Mapping[str, Any] | None = None,
        checkpoints: bool = False,
    ) -> None:
        self.folder = folder
        self.env = env
        self.monitors = list(monitors)
        self.record_cfg = record
        self.guard = guard or SignalGuard()
        self.tables = self._declared_tables()
        self._sinks: dict[str, _TableSink] = {}
        for name, (per, fields) in self.tables.items():
            if per == "step" and not record.steps:
                continue
            writer = PartedTableWriter(
                folder.table(name), folder.parts(name), pa.schema(fields),
                metadata={**(metadata or {}), "cobel.table": name, "cobel.rows": per,
                          "cobel.schema_version": SCHEMA_VERSION},
                row_group_rows=self.STEP_ROW_GROUP_ROWS if per == "step" else self.ROW_GROUP_ROWS,
            )  # fmt: skip
            self._sinks[name] = _TableSink(writer, self.ROW_GROUP_ROWS, record.flush_seconds)
        for m in self.monitors:
            m.bind(self._emit)
        self._joinable = self._joinable_monitors() if record.steps else []
        self._joined: list[tuple[TrialBatch, BatchInfo]] = []  # batches awaiting step rows
        self._joined_steps = 0
        self._mcap_tables: list[tuple[Any, ...]] = []  # trial tables awaiting the MCAP
        self._last_pending = time.monotonic()
        self.start_ns = time.time_ns() if resume is None else int(resume["start_ns"])
        #: the MCAP written before a resume, joined with this one's at close (trimmed to
        #: the checkpoint's clock)
        self._mcap_before: tuple[Path, Any] | None = None
        if record.mcap and resume is not None and folder.mcap.is_file():
            from cobelrun.io.mcap_repair import repair_mcap

            before = folder.mcap_before_resume
            if not before.is_file():  # a resume that was stopped itself moved it already
                folder.mcap.replace(before)
            repair_mcap(before)
            if record.mcap_timeline == "per_run":  # each run cut at its own clock
                from cobelrun.io.mcap import per_run_cut

                clocks = resume.get("run_clocks_ns") or {}
                until: Any = per_run_cut(self.start_ns, clocks)
            else:
                until = self.start_ns + int(resume.get("clock_ns", 0))
            self._mcap_before = (before, until)
        self.mcap = self._foxglove_stream(record, geometry, metadata)
        self._active: dict[bool, list[Monitor]] = {}
        self._clock = 0  # simulated ns since the start
        self._clocks: dict[int, int] = {}  # mcap_timeline=per_run: each run's own clock
        self._writer = WriterThread(enabled=background)
        self._frames = _FrameGrabber(env) if self.mcap is not None and record.images else None
        self.agents = (
            AgentArchive(
                folder.agents_archive, folder.agent_parts, flush_seconds=record.flush_seconds
            )
            if save_agents
            else None
        )
        self._agents_merge: Future | None = None
        self._steps: StepWriterProcess | None = None
        joined = sorted({t.name for m in self._joinable for t in m.tables()})
        # a run with checkpoints writes its step rows on the thread: durable() waits for it
        if joined and not checkpoints and self._step_process(background):
            self._steps = StepWriterProcess(joined, self._write_forked, self._finish_table)
        if resume is not None:
            self._resume(resume)

    def _foxglove_stream(
        self, record: RecordConfig, geometry: Any, metadata: Mapping[str, str] | None
    ) -> Any:
        """``run.mcap`` and/or the live view: one :class:`~cobelrun.io.mcap.FoxgloveStream`
        feeding both (None when neither is on)."""
        live = []
        if record.live:
            from cobelrun.io.live import LiveSink

            sink = LiveSink.start(record.live_host, record.live_port)
            if sink is not None:
                live.append(sink)
        meta = dict(metadata or {})
        if record.mcap_timeline != "sequential":
            meta["timeline"] = record.mcap_timeline
        stream: Any = None
        if record.mcap:
            from cobelrun.io.mcap import McapRecorder

            stream = McapRecorder(self.folder.mcap, geometry=geometry, start_ns=self.start_ns,
                                  metadata=meta, live=live)  # fmt: skip
        elif live:
            from cobelrun.io.mcap import FoxgloveStream

            stream = FoxgloveStream(live, geometry=geometry, start_ns=self.start_ns, metadata=meta)
        if live and record.live_wait > 0:  # the channels are advertised: wait for a viewer
            live[0].wait_for_client(record.live_wait)
        return stream

    def _write_forked(self, batch: TrialBatch, info: BatchInfo) -> None:
        """In the step writer process: build and write a joined flush's step rows."""
        self._write_joined([(batch, dataclasses.replace(info, env=self.env))])

    def _finish_table(self, name: str) -> None:
        """In the step writer process: finish one step table (its parts merged)."""
        self._sinks[name].writer.close()

    def _step_process(self, background: bool) -> bool:
        """Whether the per-step tables go to a child process (``record.step_writer``)."""
        return (
            self.record_cfg.step_writer == "process"
            and background
            and sys.platform.startswith("linux")
            and threading.current_thread() is threading.main_thread()
        )

    def _declared_tables(self) -> dict[str, tuple[str, list[pa.Field]]]:
        tables: dict[str, tuple[str, list[pa.Field]]] = {}
        for m in self.monitors:
            for t in m.tables():
                if not isinstance(t, Table):
                    raise ConfigError(f"monitor {type(m).__name__}.tables() must return Tables")
                per, fields = tables.setdefault(t.name, (t.per, []))
                if per != t.per:
                    raise ConfigError(
                        f"table '{t.name}' is declared with rows per {per} and per {t.per}"
                    )
                if per == "event" and fields:
                    raise ConfigError(f"two monitors write the event table '{t.name}'")
                fields += list(t.fields)
        for name, (_, fields) in tables.items():
            names = [f.name for f in fields]
            dup = sorted({n for n in names if names.count(n) > 1})
            if dup:
                raise ConfigError(f"two monitors write the same column(s) of '{name}': "
                                  f"{', '.join(dup)}")  # fmt: skip
        return tables

    def _joinable_monitors(self) -> list[Monitor]:
        """Joinable monitors whose tables are per-step tables written only by joinable,
        per-step-only monitors (their rows can then be built later, in bulk)."""

        def step_only(m: Monitor) -> bool:
            names = [t.name for t in m.tables()]
            return bool(names) and all(self.tables[n][0] == "step" for n in names)

        candidates = [m for m in self.monitors if m.joinable and step_only(m)]
        ids = {id(m) for m in candidates}
        writers: dict[str, set[int]] = {}
        for m in self.monitors:
            for t in m.tables():
                writers.setdefault(t.name, set()).add(id(m))
        return [m for m in candidates if all(writers[t.name] <= ids for t in m.tables())]

    # -- checkpoints ---------------------------------------------------------------------------
    def durable(self) -> dict[str, Any]:
        """Hand everything recorded so far to disk, wait until it is written and return the
        watermarks a checkpoint keeps: the rows of every table and the agents in the
        agents archive (all in complete parts), the MCAP clock."""
        assert self._steps is None, "a recorder with checkpoints writes steps on its thread"
        with self.guard.critical():
            for table in self._sinks:
                self._flush(table)
            self._flush_pending()
            if self.agents is not None:
                self._writer.submit(self.agents.write_batch, self.agents.take())
            self._writer.drain()
            if self.mcap is not None:
                self.mcap.flush()
        return {
            "tables": {name: int(sink.writer.rows_written) for name, sink in self._sinks.items()},
            "agents": 0 if self.agents is None else self.agents.durable,
            "clock_ns": int(self._clock),
            "run_clocks_ns": {str(run): int(ns) for run, ns in self._clocks.items()},
            "start_ns": int(self.start_ns),
        }

    def _resume(self, marks: Mapping[str, Any]) -> None:
        """Take up the rows a checkpoint's watermarks say are durable (:meth:`durable`)."""
        tables = marks.get("tables")
        if not isinstance(tables, Mapping) or set(tables) != set(self._sinks):
            raise ValueError(
                f"recorder: the checkpoint has the tables {sorted(tables or {})}, this run "
                f"writes {sorted(self._sinks)}"
            )
        for name, sink in self._sinks.items():
            sink.writer.resume(int(tables[name]))
        if self.agents is not None:
            self.agents.resume(int(marks.get("agents", 0)))
        self._clock = int(marks.get("clock_ns", 0))
        clocks = marks.get("run_clocks_ns") or {}
        if isinstance(clocks, Mapping):
            self._clocks = {int(run): int(ns) for run, ns in clocks.items()}

    # -- lifecycle -----------------------------------------------------------------------------
    def start_run(self, run: int, agent: Any) -> None:
        for m in self.monitors:
            m.start_run(run, agent)
        if self.mcap is not None and self.mcap.live and self.record_cfg.mcap_run(run):
            # advertised now, so that a live client subscribes before the run's first batch
            self._writer.submit(self.mcap.prepare_run, run, self._frames is not None)

    def phase_callbacks(self, first_trial: int, run: int = 0) -> list[Any]:
        """Trial callbacks the monitors need for a phase starting at ``first_trial`` (empty for
        most tasks, so that compiled agents keep their fast path), plus the camera grabber of
        ``record.images``."""
        callbacks = [cb for m in self.monitors for cb in m.callbacks(first_trial)]
        if self._frames is not None and self.record_cfg.mcap_run(run):
            callbacks.append(self._frames.hook)
        return callbacks

    def end_run(self, run: int, agent: Any, last_trial: int) -> None:
        for m in self.monitors:
            m.end_run(run, agent, last_trial)
        with self.guard.critical():
            self._write_grids(run, [g for m in self.monitors for g in m.scene_grids()])

    def _run_clock(self, run: int) -> int:
        """Run ``run``'s log time now: its last recorded trial's end (its last pose)."""
        clock = (
            self._clocks.get(run, 0) if self.record_cfg.mcap_timeline == "per_run" else self._clock
        )
        return self.start_ns + max(clock - STEP_NS, 0)

    def _write_grids(
        self, run: int, grids: list[Any], times: list[int] | None = None
    ) -> None:  # fmt: skip
        """Monitors' maps (:class:`~cobelrun.monitors.SceneGrid`) to run.mcap and the live
        view, at ``times`` (default: the run's clock now); only for the runs the MCAP keeps."""
        if not grids or self.mcap is None or not self.record_cfg.mcap_run(run):
            return
        if times is None:
            times = [self._run_clock(run)] * len(grids)
        self._writer.submit(self.mcap.write_grids, run, times, grids)

    def save_agent(self, run: int, agent: Any) -> None:
        """Add run ``run``'s trained agent to the job's ``agents.npz`` (written in batches)."""
        assert self.agents is not None, "the recorder was built without save_agents"
        with self.guard.critical():
            if self.agents.add(run, agent.get_state(), agent.saved_meta()):
                self._writer.submit(self.agents.write_batch, self.agents.take())

    def _emit(self, table: str, columns: Mapping[str, Any]) -> None:
        if table not in self.tables:
            raise ConfigError(f"a monitor wrote to undeclared table '{table}'")
        if table in self._sinks:
            n = len(next(iter(columns.values()))) if columns else 0
            self._add(table, columns, n)

    def _add(self, table: str, columns: Mapping[str, Any], n: int) -> None:
        sink = self._sinks[table]
        with self.guard.critical():
            if sink.add(columns, n):
                self._flush(table)

    def _flush(self, table: str) -> None:
        sink = self._sinks[table]
        parts = sink.take()
        if parts is not None:
            self._writer.submit(_write_columns, sink.writer, parts)

    # -- batches -------------------------------------------------------------------------------
    def record(
        self, run: int, phase: str, first_trial: int, batch: TrialBatch, first_in_phase: int = 1
    ) -> None:
        """Hand a batch of trials (1-based ``first_trial``; ``first_in_phase`` its first trial's
        position in the phase) to every monitor and buffer the rows.

        All tables of a batch are buffered in one critical section: a signal never leaves a
        batch's trials without its steps."""
        with self.guard.critical():
            self._record(run, phase, first_trial, batch, first_in_phase)

    def _batch_monitors(
        self, steps_recorded: bool, monitors: Sequence[Monitor] | None = None
    ) -> list[Monitor]:
        """Monitors whose batch rows are written: a monitor that fills only per-step tables
        is skipped when steps are not recorded (``record.steps=false`` or a run outside
        ``record.runs``); monitors without trial/step tables (event tables, hooks) always run
        (their ``on_batch`` may keep state)."""
        if monitors is not None and monitors is not self.monitors:
            own = self._batch_monitors(steps_recorded)
            return [m for m, mine in zip(monitors, self.monitors, strict=True) if mine in own]
        key = steps_recorded
        if key not in self._active:
            active = []
            joinable = {id(m) for m in self._joinable}
            for m in self.monitors:
                if id(m) in joinable:
                    continue  # rows built in bulk (_write_joined)
                kinds = {self.tables[t.name][0]: t.name for t in m.tables()}
                rows = [name for per, name in kinds.items() if per in ("trial", "step")]
                written = [name for name in rows if name in self._sinks
                           and (steps_recorded or self.tables[name][0] != "step")]  # fmt: skip
                if written or not rows:
                    active.append(m)
            self._active[key] = active
        return self._active[key]

    def _record(
        self, run: int, phase: str, first_trial: int, batch: TrialBatch, first_in_phase: int = 1
    ) -> None:
        rows = self._rows(run, phase, first_trial, batch, self.monitors, first_in_phase)
        if rows is not None:
            self._commit_rows(*rows)

    def _rows(
        self, run: int, phase: str, first_trial: int, batch: TrialBatch,
        monitors: Sequence[Monitor], first_in_phase: int = 1,
    ) -> tuple[list[tuple[str, dict[str, Any], int]], Any, Any] | None:  # fmt: skip
        """The monitors' rows of a batch: ``([(table, columns, n_rows)], mcap arguments,
        (batch, info) for the joinable monitors' bulk-built step rows or None)``;
        ``first_in_phase`` is the batch's first trial's position in its phase (1-based)."""
        n = batch.n_trials
        if n == 0:
            return None
        info = BatchInfo(run=run, phase=phase, first_trial=first_trial, env=self.env,
                         first_in_phase=first_in_phase)  # fmt: skip
        merged: dict[str, dict[str, Any]] = {}
        for m in self._batch_monitors(self.record_cfg.records_run(run), monitors):
            for table, cols in m.on_batch(batch, info).items():
                if table not in self.tables or self.tables[table][0] == "event":
                    raise ConfigError(
                        f"monitor {type(m).__name__} returned rows for '{table}', which is not "
                        "one of its trial/step tables"
                    )
                merged.setdefault(table, {}).update(cols)
        trial = info.trials(n)
        every = self.record_cfg.trial_every
        keep = None if every == 1 else (trial - 1) % every == 0
        records_run = self.record_cfg.records_run(run)
        step_keep = None if keep is None else np.repeat(keep, batch.steps)
        adds = []
        for table, cols in merged.items():
            if table not in self._sinks:
                continue
            if self.tables[table][0] == "step":
                if not records_run:
                    continue
                if step_keep is not None:
                    cols = {k: np.asarray(v)[step_keep] for k, v in cols.items()}
                    count = int(step_keep.sum())
                else:
                    count = batch.n_steps
            else:
                count = n
            adds.append((table, cols, count))
        per_trial = {k: v for name, cols in merged.items() if self.tables[name][0] == "trial"
                     for k, v in cols.items()}  # fmt: skip
        joined = (batch, info) if self._joinable and records_run else None
        return adds, (run, phase, trial, batch, per_trial), joined

    def _commit_rows(
        self, adds: list[tuple[str, dict[str, Any], int]], mcap: Any,
        joined: tuple[TrialBatch, BatchInfo] | None,
    ) -> None:  # fmt: skip
        for table, cols, count in adds:
            self._add(table, cols, count)
        self._write_mcap(*mcap)
        if joined is not None:  # step rows of joinable monitors, built in bulk later
            self._joined.append(joined)
            self._joined_steps += joined[0].n_steps
            if self._joined_steps >= self.JOIN_STEPS:
                self._flush_joined()
        if time.monotonic() - self._last_pending >= self.record_cfg.flush_seconds:
            self._flush_pending()

    def fork(self, run: int) -> ForkedRun:
        """Run ``run`` recorded while other runs advance at the same time (batched runs): its
        own copies of the monitors (:meth:`Monitor.fork`), whose rows and events are kept
        until :meth:`commit` writes them, so that the run folder holds the same rows in the
        same order as when the runs are recorded one after another."""
        return ForkedRun(self, run)

    def commit(self, fork: ForkedRun) -> None:
        """Write what a forked run recorded (call in run order)."""
        with self.guard.critical():
            for kind, payload in fork.pending:
                if kind == "event":
                    self._emit(*payload)
                elif kind == "grids":
                    self._write_grids(*payload)
                else:
                    self._commit_rows(*payload)
            fork.pending = []

    def _flush_joined(self) -> None:
        batches, self._joined, self._joined_steps = self._joined, [], 0
        if batches:
            if self._steps is not None:
                self._steps.submit(batches)
            else:
                self._writer.submit(self._write_joined, batches)

    def _flush_mcap_tables(self) -> None:
        tables, self._mcap_tables = self._mcap_tables, []
        if tables and self.mcap is not None:
            self._writer.submit(self._write_mcap_tables, self.mcap, tables)

    def _flush_pending(self) -> None:
        """Hand the joined batches and MCAP trial tables to the writer thread (by time)."""
        self._last_pending = time.monotonic()
        self._flush_joined()
        self._flush_mcap_tables()

    @staticmethod
    def _write_mcap_tables(mcap: Any, tables: list[tuple[Any, ...]]) -> None:
        for args in tables:
            mcap.write_trial_table(*args)

    def _write_joined(self, batches: list[tuple[TrialBatch, BatchInfo]]) -> None:
        """Step rows of joined batches from the joinable monitors (on the writer thread)."""
        joined = TrialBatch.concat([b for b, _ in batches]) if len(batches) > 1 else batches[0][0]
        info = BatchInfo.joined([i for _, i in batches], [b.n_trials for b, _ in batches])
        merged: dict[str, dict[str, Any]] = {}
        for m in self._joinable:
            for table, cols in m.on_batch(joined, info).items():
                if table not in self.tables or self.tables[table][0] != "step":
                    raise ConfigError(f"monitor {type(m).__name__} returned rows for '{table}', "
                                      "which is not one of its step tables")  # fmt: skip
                merged.setdefault(table, {}).update(cols)
        every = self.record_cfg.trial_every
        step_keep = None
        if every != 1:
            keep = (info.trials(joined.n_trials) - 1) % every == 0
            step_keep = np.repeat(keep, joined.steps)
        for table, cols in merged.items():
            if step_keep is not None:
                cols = {k: np.asarray(v)[step_keep] for k, v in cols.items()}
            self._sinks[table].writer.write_part(cols)

    def _write_mcap(
        self, run: int, phase: str, trial: np.ndarray, batch: TrialBatch, trial_cols: dict,
        grids: list[Any] | None = None,
    ) -> None:  # fmt: skip
        """The batch's poses, trial events and table, frames, paths and maps (``grids``: a
        forked run's, taken when it recorded the batch; default: the monitors' now)."""
        n = batch.n_trials
        n_poses = batch.n_steps + n
        if self.record_cfg.mcap_timeline == "per_run":
            clock = self._clocks.get(run, 0)
            self._clocks[run] = clock + n_poses * STEP_NS
        else:
            clock = self._clock
            self._clock += n_poses * STEP_NS
        t0 = self.start_ns + clock
        if self.mcap is None:
            return
        response = trial_cols.get("response")
        # every run's trials, one protobuf message per run and phase or piece (issue 19)
        self._mcap_tables.append((
            run, phase, int(trial[0]), t0, batch.steps, batch.reward, batch.start_state,
            batch.end_state, batch.terminated, None if response is None else np.asarray(response),
        ))  # fmt: skip
        if not self.record_cfg.mcap_run(run):
            if len(self._mcap_tables) >= self.MCAP_TABLES:
                self._flush_mcap_tables()
            return  # poses and per-trial events of the first mcap_runs runs only
        self._flush_mcap_tables()
        t = t0 + np.arange(n_poses, dtype=np.int64) * STEP_NS
        start_pos = batch.offsets[:-1] + np.arange(n)
        end_pos = start_pos + batch.steps
        with self.guard.critical():
            poses = batch.with_poses(self.env).poses()
            if poses is not None:
                self._writer.submit(self.mcap.write_poses, run, t, poses, end_pos)
            if self._frames is not None:
                for t_ns, image in zip(t, self._frames.take(n_poses), strict=False):
                    self._writer.submit(self.mcap.write_image, run, int(t_ns), image)
            self._writer.submit(
                self.mcap.write_trial_events, run, trial, phase, t[start_pos], t[end_pos],
                batch.start_state, batch.end_state, batch.steps, batch.reward,
                None if response is None else np.asarray(response),
            )  # fmt: skip
            info = BatchInfo(run=run, phase=phase, first_trial=int(trial[0]), env=self.env)
            if grids is None:
                grids = [g for m in self.monitors for g in m.scene_grids()]
            if grids:  # at the end of the trial they follow (before the first: its start)
                ends, first = t[end_pos], int(trial[0])
                at = [int(t0 if g.trial < first else ends[min(g.trial - first, n - 1)])
                      for g in grids]  # fmt: skip
                self._write_grids(run, grids, at)
            for m in self.monitors:
                paths = m.scene_paths(batch, info)
                if paths:
                    times = [int((t[start_pos] if p.at == "start" else t[end_pos])[p.trial])
                             for p in paths]  # fmt: skip
                    self._writer.submit(self.mcap.write_paths, run, times, paths,
                                        PATH_LIFETIME_NS)  # fmt: skip

    @property
    def writer_cpu_s(self) -> float:
        """CPU seconds spent on the background writer thread so far (Arrow's own compression
        threads not included)."""
        return self._writer.cpu_s

    @property
    def step_process_cpu_s(self) -> float | None:
        """CPU seconds of the step writer process (after :meth:`close`; None without one)."""
        return self._steps.cpu_s if self._steps is not None else None

    @property
    def step_process_private_mb(self) -> float | None:
        """Memory of the step writer process not shared with this one, when it closed (MB)."""
        return self._steps.private_mb if self._steps is not None else None

    # -- closing -------------------------------------------------------------------------------
    def close(self) -> None:
        """Write what is buffered, wait for the writer thread, finish every file (further
        signals are held off until the files are complete)."""
        with self.guard.closing():
            child = set(self._steps.tables) if self._steps is not None else set()
            steps = [*(functools.partial(self._flush, t) for t in self._sinks),
                     self._flush_pending, self._writer.close, self._close_agents,
                     *([self._steps.close] if self._steps is not None else []),
                     *(sink.writer.close for name, sink in self._sinks.items()
                       if name not in child)]  # fmt: skip
            if self.mcap is not None:
                steps.append(self.mcap.close)
                if self._mcap_before is not None:
                    steps.append(self._join_mcap)
            if self.agents is not None:
                steps.append(self._agents_closed)
            first: BaseException | None = None
            for step in steps:  # every file is finished even when another one fails (full disk)
                try:
                    step()
                except BaseException as exc:
                    first = first or exc
            if first is not None:
                raise first

    def _join_mcap(self) -> None:
        """After a resume: the MCAP up to the checkpoint, then this process's, as one file."""
        from cobelrun.io.mcap_repair import join_mcap

        assert self._mcap_before is not None
        before, until_ns = self._mcap_before
        join_mcap(before, self.folder.mcap, self.folder.mcap, until_ns)
        before.unlink()

    def _close_agents(self) -> None:
        """Start merging the agents' batches into ``agents.npz`` on a thread of its own, while
        this thread finishes the tables and the MCAP (both mostly compress, without the GIL);
        :meth:`_agents_closed` waits for it."""
        if self.agents is not None and self._agents_merge is None:
            pool = ThreadPoolExecutor(1, thread_name_prefix="cobel-agents")
            self._agents_merge = pool.submit(self.agents.close)
            pool.shutdown(wait=False)

    def _agents_closed(self) -> None:
        if self._agents_merge is None:
            self._close_agents()
        assert self._agents_merge is not None
        self._agents_merge.result()


class ForkedRun:
    """One run of a batch, recorded through its own monitor copies (see
    :meth:`RunRecorder.fork`): the recorder's run lifecycle for this run, with every row and
    event held until :meth:`RunRecorder.commit`."""

    def __init__(self, recorder: RunRecorder, run: int) -> None:
        self.recorder, self.run = recorder, run
        self.pending: list[tuple[str, Any]] = []
        shared = [recorder.env, getattr(recorder.env, "unwrapped", None)]
        self.monitors = [m.fork(self._event, shared=shared) for m in recorder.monitors]

    def _event(self, table: str, columns: Mapping[str, Any]) -> None:
        if table not in self.recorder.tables:
            raise ConfigError(f"a monitor wrote to undeclared table '{table}'")
        self.pending.append(("event", (table, columns)))

    def start_run(self, agent: Any) -> None:
        for m in self.monitors:
            m.start_run(self.run, agent)

    def phase_callbacks(self, first_trial: int) -> list[Any]:
        return [cb for m in self.monitors for cb in m.callbacks(first_trial)]

    def record(
        self, phase: str, first_trial: int, batch: TrialBatch, first_in_phase: int = 1
    ) -> None:
        rows = self.recorder._rows(self.run, phase, first_trial, batch, self.monitors,
                                   first_in_phase)  # fmt: skip
        if rows is not None:
            adds, mcap, joined = rows
            grids = [g for m in self.monitors for g in m.scene_grids()]
            self.pending.append(("rows", (adds, (*mcap, grids), joined)))

    def end_run(self, agent: Any, last_trial: int) -> None:
        for m in self.monitors:
            m.end_run(self.run, agent, last_trial)
        self.pending.append(("grids", (self.run, [g for m in self.monitors
                                                  for g in m.scene_grids()])))  # fmt: skip
