"""Run a composed task: build its parts, loop over runs and phases, hand batches to the recorder.

The loop is short and does no I/O itself (acme's environment-loop style): agents run whole
trials, the recorder (monitors + writers) persists them, the manifest records status.
"""

from __future__ import annotations

import functools
import logging
import shlex
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from omegaconf import DictConfig, OmegaConf

from cobelrun._version import __version__
from cobelrun.checkpoint import CheckpointConfig, CheckpointError, Position, RunCheckpoints
from cobelrun.config import factory, instantiate
from cobelrun.envs.base import Changeable, HasGeometry, supports
from cobelrun.errors import CobelError, ConfigError
from cobelrun.io.atomic import atomic_write_text, disk_error, is_disk_error
from cobelrun.io.lock import RunLock, refuse_existing
from cobelrun.io.manifest import Manifest, _write_json_atomic, config_hash
from cobelrun.io.run_folder import RunFolder
from cobelrun.monitors import Monitor, TrialKeysMonitor
from cobelrun.protocol import Phase
from cobelrun.protocol import Protocol as TaskProtocol
from cobelrun.recorder import Interrupted, RecordConfig, RunRecorder, SignalGuard
from cobelrun.safety import check_memory, check_name, memory_plan, trim_memory
from cobelrun.schema import RunSpec, validate_run

__all__ = ["Interrupted", "Task", "build_task", "execute", "run", "run_seed"]

#: the run's log lines (Hydra's job logging: RUN_DIR/cobel.log; warnings also on stderr)
LOG = logging.getLogger("cobel")


@dataclass
class Task:
    """A composed task: env + agent factory + protocol + monitors."""

    name: str
    env: Any
    make_agent: Callable[..., Any]
    protocol: TaskProtocol
    monitors: dict[str, Monitor]
    record: RecordConfig
    runs: int
    seed: int
    load_from: str | None = None
    #: runs whose trained agents go into ``agents.npz``
    save_agents: frozenset[int] = frozenset()
    #: A custom job (``task.job``) that replaces the protocol loop: ``job(config, run_dir,
    #: progress=...) -> dict | None`` (the dict goes into the manifest).
    job: Any = None
    config: Any = None
    #: ``task.objective``: ``objective(trials) -> float``, stored in the manifest
    objective: Any = None
    #: builds another instance of the task's environment (batched runs need one per run)
    make_env: Callable[[], Any] | None = None
    #: runs trained at once (``task.batch_runs``, :mod:`cobelrun.batched`); 0: one by one
    batch: int = 0
    #: why the runs are not batched (None when they are)
    batch_note: str | None = None
    #: when the run writes checkpoints (``task.checkpoint``, :mod:`cobelrun.checkpoint`)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)


def build_task(cfg: DictConfig, *, probe_agent: bool = False) -> Task:
    """Instantiate a composed config's parts, validating everything before any run starts.

    With ``probe_agent`` one agent is constructed and dropped, so that errors in the agent's
    parameters are reported before anything is written. The memory each part estimates for
    itself before allocating (:func:`cobelrun.safety.check_allocation`) adds up to the run's
    estimate, checked against the memory available.
    """
    with memory_plan():
        return _build_task(cfg, probe_agent=probe_agent)


def _build_task(cfg: DictConfig, *, probe_agent: bool) -> Task:
    _check_resolves(cfg)
    spec = validate_run(cfg)
    check_name("task.name", spec.task.name)  # it names the output folder
    if spec.task.protocol is not None:
        check_memory(spec.task.protocol)
    objective = None
    if cfg.task.get("objective") is not None:
        objective = instantiate("task.objective", cfg.task.objective)
        if not callable(objective):
            raise ConfigError("task.objective must build a callable objective(trials) -> float")
    if spec.task.job is not None:
        return build_job(cfg, spec)
    assert spec.task.protocol is not None  # TaskSpec requires one unless there is a job
    protocol = TaskProtocol.from_spec(spec.task.protocol)
    env = instantiate("env", cfg.env)
    protocol.check(env)  # every phase's changes once: bad state names fail before any output
    agent_node = OmegaConf.to_container(cfg.agent, resolve=True)
    assert isinstance(agent_node, dict)
    load_from = agent_node.pop("load_from", None)  # handled here, not by the agent
    if load_from is not None and not Path(str(load_from).replace("{run}", "0")).exists():
        raise ConfigError(f"agent.load_from {load_from!r} does not exist")
    from cobelrun.agents.base import check_load_from

    deferred = instantiate("agent", agent_node, env=env, _partial_=True)
    # a plain partial: Hydra's deferred target re-checks its target policy on every call,
    # which costs ~0.5 ms per run; the target was validated and imported above
    make_agent = functools.partial(deferred.func, *deferred.args, **deferred.keywords)
    monitors: dict[str, Monitor] = {}
    for name, node in (spec.task.monitors or {}).items():
        if node is None:
            continue  # a monitor switched off with task.monitors.NAME=null
        monitor = instantiate(f"task.monitors.{name}", node)
        if not isinstance(monitor, Monitor):
            raise ConfigError(f"task.monitors.{name} does not build a Monitor")
        monitor.setup(env)
        monitors[str(name)] = monitor
    record = RecordConfig.from_spec(spec.task.record)
    checks = [m for m in monitors.values() if callable(getattr(m, "check_agent", None))]
    probe = None  # run 0's agent, built to check it (and reused by the batch plan)
    if probe_agent or record.training_log or checks:
        probe = _first_agent(make_agent, spec.seed)
        for monitor in checks:  # e.g. the layers an activity monitor records exist
            monitor.check_agent(probe)
        if record.training_log and not callable(getattr(probe, "log_training", None)):
            raise ConfigError(
                f"task.record.training_log needs a deep (SB3) agent such as agent=dqn; "
                f"{type(probe).__name__} has no training curves"
            )
    if load_from is not None:  # every saved agent checked before any folder exists
        probe = probe if probe is not None else _first_agent(make_agent, spec.seed)
        check_load_from(probe, str(load_from), spec.task.runs)
    if record.images and record.mcap and getattr(env.unwrapped, "render_mode", None) != "rgb_array":
        raise ConfigError(
            "task.record.images needs an env that renders camera images (render_mode "
            "rgb_array: the 3D mazes with +env.render_mode=rgb_array)"
        )
    task = Task(
        name=spec.task.name,
        env=env,
        make_agent=make_agent,
        protocol=protocol,
        monitors=monitors,
        record=record,
        runs=spec.task.runs,
        seed=spec.seed,
        load_from=None if load_from is None else str(load_from),
        save_agents=agents_to_save(spec.task.save_agents, spec.task.runs),
        objective=objective,
        make_env=factory("env", cfg.env),
        checkpoint=CheckpointConfig.resolve(
            spec.task.checkpoint, getattr(make_agent, "func", None)
        ),
    )
    _plan_batches(task, spec.task.batch_runs, probe)
    return task


def _plan_batches(task: Task, setting: Any, probe: Any = None) -> None:
    """Decide ``task.batch`` / ``task.batch_note`` from ``task.batch_runs`` (building one agent
    only for agents that have a batched implementation, unless ``probe``, run 0's agent built
    to check the config, is given)."""
    from cobelrun.batched import batch_plan

    agent_class = getattr(task.make_agent, "func", None)
    if setting is False or not getattr(agent_class, "batchable", False):
        if setting not in (False, "auto"):
            name = getattr(agent_class, "__name__", "this agent")
            raise ConfigError(
                f"task.batch_runs={str(setting).lower()}: agent {name} has no batched implementation "
                "(batchable: DQNAgent, DynaDQN, DynaDSR); use task.batch_runs=auto or false"
            )
        task.batch_note = (
            "task.batch_runs=false"
            if setting is False
            else "the agent has no batched implementation"
        )
        return

    def template() -> Any:
        return probe if probe is not None else _first_agent(task.make_agent, task.seed)

    task.batch, task.batch_note = batch_plan(setting, task, template)


def _first_agent(make_agent: Callable[..., Any], seed: int) -> Any:
    """Run 0's agent, built to check the config before any output: a constructor error is a
    one-line ConfigError."""
    try:
        return make_agent(seed=run_seed(seed, 0)[0])
    except (CobelError, MemoryError):  # a MemoryError is a missing memory estimate
        raise
    except Exception as exc:  # a value the agent's own checks did not anticipate
        raise ConfigError(f"cannot build agent: {type(exc).__name__}: {_first_line(exc)}") from exc


def _check_resolves(cfg: Any) -> None:
    """Every interpolation (``${...}``) of the config resolves; else one line naming the key."""
    from omegaconf.errors import OmegaConfBaseException

    if not isinstance(cfg, DictConfig):
        return
    try:
        OmegaConf.to_container(cfg, resolve=True)
    except OmegaConfBaseException as exc:
        key = getattr(exc, "full_key", None)
        where = f"{key}: " if key else ""
        raise ConfigError(f"{where}cannot resolve the value: {_first_line(exc)}") from None


def _first_line(exc: BaseException) -> str:
    lines = str(exc).strip().splitlines()
    return lines[0] if lines else ""


def build_job(cfg: DictConfig, spec: RunSpec) -> Task:
    """A task with a custom ``task.job``: a ``_target_`` built with its nested nodes left as
    plain config (the job builds the environments and agents it needs from them and from the
    composed config it is called with)."""
    job = instantiate("task.job", spec.task.job or {}, _recursive_=False)
    if not callable(job):
        raise ConfigError("task.job must build a callable job(config, run_dir, progress=None)")
    protocol = None if spec.task.protocol is None else TaskProtocol.from_spec(spec.task.protocol)
    return Task(name=spec.task.name, env=None, make_agent=None, protocol=protocol,  # type: ignore[arg-type]
                monitors={}, record=RecordConfig(), runs=1, seed=spec.seed,
                save_agents=frozenset(), job=job, config=cfg)  # fmt: skip


def run_seed(seed: int, run: int) -> tuple[np.random.SeedSequence, np.random.SeedSequence]:
    """(agent, environment) seed sequences of run ``run``, derived from the one ``seed``.

    Identical to ``SeedSequence(seed).spawn(runs)[run].spawn(2)`` (a child's spawn key is its
    parent's plus its index) but O(1) per run, and made directly (~5 us each).
    """
    seq = np.random.SeedSequence
    return seq(seed, spawn_key=(run, 0)), seq(seed, spawn_key=(run, 1))


def run_seeds(seed: int, runs: int) -> list[tuple[np.random.SeedSequence, np.random.SeedSequence]]:
    """(agent, environment) seed sequences of every run."""
    return [run_seed(seed, r) for r in range(runs)]


def load_saved_agent(agent: Any, load_from: str, run: int) -> None:
    """Continue run ``run`` from a saved agent: ``load_from`` is a file (``{run}`` is replaced
    by the run index) or a run folder (run ``run`` of its ``agents.npz``, or an older layout's
    agent file). The state is checked against the agent's schema before anything changes."""
    from cobelrun.io.agents_archive import read_agent

    path = Path(load_from.replace("{run}", str(run)))
    if path.is_dir():
        folder = RunFolder(path)
        if folder.agents_archive.is_file():
            try:
                found = read_agent(folder.agents_archive, run)
            except Exception as exc:  # a damaged archive: zip, npy header, layout
                raise ConfigError(
                    f"cannot load agent from {folder.agents_archive}: {exc}"
                ) from None
            if found is not None:
                agent.load_state(*found, source=f"{folder.agents_archive} (run {run})")
                return
        legacy = folder.legacy_agent(run)
        if legacy is None:
            raise ConfigError(
                f"agent.load_from: {path} has no saved agent for run {run} "
                "(task.save_agents decides which runs are saved)"
            )
        path = legacy
    elif not path.is_file():
        raise ConfigError(f"agent.load_from: {path} does not exist")
    agent.load(path)


def kept(task: Task) -> dict[str, Any]:
    """What the run folder will hold, for the manifest: every trial row always; step rows,
    MCAP poses/events (``runs``: the first N runs in full; ``trial_tables``: every run's
    trials on ``/trials``) and agents as ``task.record`` and ``task.save_agents`` say."""
    rec = task.record
    step_runs = (
        list(range(task.runs)) if rec.runs == "all" else [r for r in rec.runs if r < task.runs]
    )
    mcap_runs = task.runs if rec.mcap_runs == "all" else min(int(rec.mcap_runs), task.runs)
    return {
        "trials": "all",
        "steps": {"runs": len(step_runs) if rec.steps else 0, "trial_every": rec.trial_every},
        "mcap": {
            "runs": mcap_runs if rec.mcap else 0,
            "trial_tables": task.runs if rec.mcap else 0,
            "images": rec.images,
        },
        "agents": sorted(task.save_agents)
        if len(task.save_agents) <= 20
        else f"{len(task.save_agents)} runs",
    }


def agents_to_save(spec: Any, runs: int) -> frozenset[int]:
    """Runs whose agents ``task.save_agents`` keeps: ``all`` (or true), ``last``, ``none`` (or
    false, or null) or a list of run indices (validated by :class:`cobelrun.schema.TaskSpec`)."""
    if spec is True or spec == "all":
        return frozenset(range(runs))
    if spec is False or spec is None or spec == "none":
        return frozenset()
    if spec == "last":
        return frozenset({runs - 1})
    return frozenset(spec)


class PhasePacer:
    """How many trials the runner hands an agent at once: a phase in pieces of about
    ``seconds`` each, so that a long phase (a deep agent's thousands of trials) is recorded as
    it goes (a stopped run keeps the trials it finished, a killed one those of its last flush)
    and its progress shows, while a fast phase (Dyna-Q's hundred trials in a millisecond)
    stays one call.

    Every agent gives the same trials however a phase is split (``train(8)`` equals
    ``train(3)`` then ``train(5)``: tests/test_agent_conformance.py), so the pieces change
    when rows are written, never what they hold. The size comes from the last piece's time per
    trial of the same phase (name), at most 4x the last piece; the first piece of a phase
    never seen is ``FIRST`` trials.
    """

    #: trials in the first piece of a phase not timed yet
    FIRST = 8
    #: growth limit from one piece to the next
    GROWTH = 4

    def __init__(self, seconds: float) -> None:
        self.seconds = float(seconds)
        self._last: dict[str, tuple[int, float]] = {}  # phase -> (trials, seconds) of a piece

    def next(self, phase: str, remaining: int) -> int:
        """Trials of the next piece of ``phase`` (``remaining`` left in it)."""
        last = self._last.get(phase)
        if last is None:
            return min(remaining, self.FIRST)
        n, dt = last
        fit = remaining if dt <= 0 else int(self.seconds * n / dt)
        if fit >= remaining:  # the rest of the phase fits in one piece
            return remaining
        return max(1, min(fit, n * self.GROWTH))

    def observe(self, phase: str, trials: int, seconds: float) -> None:
        """The time a piece of ``trials`` trials of ``phase`` took."""
        self._last[phase] = (trials, seconds)


def execute(
    task: Task,
    run_dir: Path,
    progress: Any = None,
    *,
    background_writes: bool = True,
    guard: SignalGuard | None = None,
    metadata: Mapping[str, str] | None = None,
    phase_times: dict[str, float] | None = None,
    cpu_times: dict[str, float] | None = None,
    checkpoints: RunCheckpoints | None = None,
) -> Any:
    """Run every (run, phase) of ``task`` and stream the records into ``run_dir``.

    ``checkpoints`` (:class:`cobelrun.checkpoint.RunCheckpoints`) writes checkpoints as the
    run goes, and, when it holds the checkpoint the run resumes from, the run goes on there.

    ``phase_times``, when given, is filled with each phase's wall time in seconds (summed over
    runs; recording included); ``cpu_times`` with the CPU seconds of the simulation thread
    (``simulation_thread``: the loop, recording on it included) and of the recorder's
    background writer (``writer_thread``).
    """
    if task.job is not None:
        return task.job(task.config, run_dir, progress=progress)
    folder = RunFolder(run_dir)
    env = task.env
    base = env.unwrapped
    geometry = base.geometry() if isinstance(base, HasGeometry) else None
    if geometry is not None:
        _write_json_atomic(folder.world, geometry.to_dict())
    monitors = [TrialKeysMonitor(), *task.monitors.values()]
    resumed = None if checkpoints is None else checkpoints.resumed
    try:
        recorder = RunRecorder(folder, env, monitors, task.record, metadata=metadata,
                               guard=guard, background=background_writes, geometry=geometry,
                               save_agents=bool(task.save_agents),
                               resume=None if resumed is None else resumed["recorder"],
                               checkpoints=checkpoints is not None)  # fmt: skip
    except (ValueError, KeyError, TypeError) as exc:  # watermarks the folder cannot meet
        if resumed is None:
            raise
        raise CheckpointError(f"cannot resume from {folder.checkpoint}: {exc}") from None
    cpu0 = time.thread_time()
    try:
        run_phases(task, recorder, folder, progress, phase_times, checkpoints)
    finally:
        recorder.close()
        if cpu_times is not None:
            cpu_times["simulation_thread"] = time.thread_time() - cpu0
            cpu_times["writer_thread"] = recorder.writer_cpu_s
            if recorder.step_process_cpu_s is not None:
                cpu_times["step_writer_process"] = recorder.step_process_cpu_s
                LOG.info(
                    "step writer process: %.1f s of CPU, %s MB of its own memory at the end",
                    recorder.step_process_cpu_s,
                    recorder.step_process_private_mb,
                )


class Cohort(Protocol):
    """Runs that advance through the protocol together: one run (:class:`OneRun`, the
    sequential path) or a chunk of runs trained as one computation
    (:class:`cobelrun.batched.BatchedRuns`). Built when its runs start (agents made, monitors'
    ``start_run`` called); :func:`run_phases` then hands it the protocol's pieces."""

    #: the runs it holds, ascending
    runs: list[int]
    #: every environment the protocol's changes apply to
    envs: list[Any]

    def piece(self, phase: Phase, max_steps: int, first: int, k: int, n: int) -> None:
        """Run (and record) trials ``k .. k+n-1`` (0-based, in ``phase``) of every run;
        ``first`` is the phase's first trial number in the run (1-based)."""

    def finish(self, last_trial: int) -> None:
        """The runs are over (``last_trial`` trials each): end them, save their agents."""

    def abort(self) -> None:
        """Stopped or failed: keep what the finished pieces recorded."""

    def save(self, checkpoints: RunCheckpoints, position: Position) -> None:
        """Write the checkpoint of ``position`` (inside the cohort's runs)."""


class OneRun:
    """One run of the sequential path: the task's env re-seeded, a fresh agent."""

    def __init__(self, task: Task, recorder: RunRecorder, folder: RunFolder, run: int,
                 checkpoints: RunCheckpoints | None = None) -> None:  # fmt: skip
        agent_seed, env_seed = run_seed(task.seed, run)
        base = task.env.unwrapped
        if supports(base, Changeable):
            base.reset_world()
        base.np_random = np.random.default_rng(env_seed)
        self.task, self.recorder, self.run = task, recorder, run
        self.runs, self.envs = [run], [task.env]
        self.agent = agent = task.make_agent(seed=agent_seed)
        agent.prepare()  # compiled agents load their trial kernel now, not in the first phase
        if task.record.training_log:
            notes = agent.log_training(folder.training_log(run))
            for note in (notes or []) if run == 0 else []:
                LOG.warning(note)  # e.g. TensorBoard skipped: once per task, not per run
        if task.load_from is not None:
            load_saved_agent(agent, task.load_from, run)
        if checkpoints is None or not checkpoints.restore(agent, task.env, recorder.monitors, run):
            recorder.start_run(run, agent)

    def save(self, checkpoints: RunCheckpoints, position: Position) -> None:
        """Write the checkpoint of ``position`` inside this run."""
        checkpoints.save(position, self.recorder, agent=self.agent, env=self.task.env,
                         monitors=self.recorder.monitors)  # fmt: skip

    def piece(self, phase: Phase, max_steps: int, first: int, k: int, n: int) -> None:
        go = self.agent.train if phase.learning else self.agent.test
        callbacks = self.recorder.phase_callbacks(first + k, self.run)
        batch = go(n, max_steps, callbacks) if callbacks else go(n, max_steps)
        self.recorder.record(self.run, phase.name, first + k, batch, first_in_phase=k + 1)

    def finish(self, last_trial: int) -> None:
        self.recorder.end_run(self.run, self.agent, last_trial)
        if self.run in self.task.save_agents:
            self.recorder.save_agent(self.run, self.agent)

    def abort(self) -> None:
        """Nothing held back: the pieces were recorded as they ended."""


def cohorts(task: Task, recorder: RunRecorder, folder: RunFolder, start: int = 0,
            checkpoints: RunCheckpoints | None = None) -> Iterator[Cohort]:  # fmt: skip
    """The task's runs from run ``start`` on, in the order they are trained: one at a time, or
    ``task.batch`` at a time as one computation (``task.batch_runs``). With ``checkpoints``,
    a checkpoint is written before a cohort when one is due (before every batched cohort:
    a batched chunk is checkpointed at its start, a few kB; inside it between pieces, as a
    sequential run), and a stop asked for by a signal happens there. A resumed chunk goes
    on from the checkpoint written inside it."""
    if task.batch:
        from cobelrun.batched import BatchedRuns

        for first in range(start, task.runs, task.batch):
            runs = list(range(first, min(first + task.batch, task.runs)))
            inside = checkpoints is not None and checkpoints.chunk(first) is not None
            if checkpoints is not None and not inside:
                checkpoints.save(Position(first), recorder)
                checkpoints.stop_if_asked()
            yield BatchedRuns(task, recorder, runs, run_seed, checkpoints)
    else:
        for run in range(start, task.runs):
            if checkpoints is not None and run > start and checkpoints.due(0):
                checkpoints.save(Position(run), recorder)
                checkpoints.stop_if_asked()
            yield OneRun(task, recorder, folder, run, checkpoints)


def run_phases(
    task: Task,
    recorder: RunRecorder,
    folder: RunFolder,
    progress: Any = None,
    phase_times: dict[str, float] | None = None,
    checkpoints: RunCheckpoints | None = None,
) -> None:
    """The run loop: every cohort of runs through every phase of the protocol, each phase in
    pieces (:class:`PhasePacer`; one trial at a time where the phase has a per-trial cycle),
    the protocol's changes applied to every env of the cohort. Sequential and batched runs
    differ only in their :class:`Cohort`.

    With ``checkpoints`` a cohort (a sequential run or a batched chunk) writes a checkpoint
    after a piece when one is due (and stops there when a signal asked it to); a resumed run
    starts at its checkpoint's position: the runs before it are done, the world of its run
    (of every run of its chunk) is rebuilt by applying the protocol's changes up to it."""
    protocol = task.protocol
    per_run = protocol.n_trials
    total = task.runs * per_run
    trimmed = time.monotonic()
    pacer = PhasePacer(task.record.flush_seconds)
    at = Position(0)
    if checkpoints is not None and checkpoints.resumed is not None:
        try:
            at = Position.from_json(checkpoints.resumed.get("position"), protocol, task.runs)
        except ValueError as exc:
            raise CobelError(f"cannot resume from {folder.checkpoint}: {exc}") from None
    for cohort in cohorts(task, recorder, folder, at.run, checkpoints):
        runs = cohort.runs
        resume = at if runs[0] == at.run else Position(runs[0])

        def report(done: int, runs: list[int] = runs) -> None:  # trials over all runs
            if progress is not None:
                progress(runs[0] * per_run + len(runs) * done, total, run=runs[-1],
                         runs=task.runs)  # fmt: skip

        first = resume.first
        try:
            for p, phase in enumerate(protocol.phases):
                if p < resume.phase:
                    for env in cohort.envs:  # a resumed run: the world as it was
                        protocol.apply(phase, env)
                    continue
                for env in cohort.envs:
                    protocol.apply(phase, env)
                max_steps = phase.max_steps or protocol.max_steps
                t_phase = time.perf_counter()
                k = resume.k if p == resume.phase else 0
                for j in range(max(0, k - len(phase.cycle)), k):  # the cycle's last changes
                    for env in cohort.envs:
                        protocol.apply_trial(phase, j, env)
                while k < phase.trials:
                    # a phase with a per-trial cycle runs (and records) one trial at a time; a
                    # long one in pieces of ~flush_seconds
                    n = 1 if phase.cycle else pacer.next(phase.name, phase.trials - k)
                    for env in cohort.envs:
                        protocol.apply_trial(phase, k, env)
                    t_piece = time.perf_counter()
                    cohort.piece(phase, max_steps, first, k, n)
                    pacer.observe(phase.name, n, time.perf_counter() - t_piece)
                    k += n
                    if checkpoints is not None:
                        _boundary(checkpoints, cohort, protocol, p, k, first, n)
                    if k < phase.trials:
                        report(first - 1 + k)
                if phase_times is not None:
                    phase_times[phase.name] = (
                        phase_times.get(phase.name, 0.0) + time.perf_counter() - t_phase
                    )
                first += phase.trials
                report(first - 1)  # phases are the finest grain every run reports
        except BaseException:
            # Ctrl-C, SIGTERM or an error: keep the pieces the cohort finished
            cohort.abort()
            raise
        cohort.finish(first - 1)
        if time.monotonic() - trimmed >= TRIM_SECONDS:
            trim_memory()
            trimmed = time.monotonic()


def _boundary(checkpoints: RunCheckpoints, cohort: Cohort, protocol: TaskProtocol, p: int,
              k: int, first: int, n: int) -> None:  # fmt: skip
    """After a piece: a cohort (one run or a batched chunk) writes its checkpoint when one
    is due (at the next trial: the end of a phase is the start of the next), and stops there
    when a signal asked for it; the cohort's last piece leaves it to the boundary before the
    next cohort."""
    due = checkpoints.due(n)
    phases = protocol.phases
    if k >= phases[p].trials:  # the next trial is the next phase's (with trials) first
        first, p, k = first + phases[p].trials, p + 1, 0
        while p < len(phases) and phases[p].trials == 0:
            p += 1
        if p == len(phases):
            return  # the run is over: its end is written first (cohorts() goes on)
    if due:
        cohort.save(checkpoints, Position(cohort.runs[0], p, k, first))
        checkpoints.stop_if_asked()


#: seconds between two :func:`trim_memory` calls (between runs). Every 50 runs, as before,
#: was ~20 times a second for Fig. 6B: each call hands back the pages the writer thread freed,
#: which the next runs fault in again
TRIM_SECONDS = 1.0


def run(
    cfg: DictConfig,
    run_dir: Path,
    *,
    progress: Any = None,
    background_writes: bool = True,
    task: Task | None = None,
    replace: bool = False,
    resume: bool = False,
) -> Path:
    """Build and execute a task into ``run_dir``; write config, manifest and done marker.

    ``resume``: go on from the run folder's checkpoint (:mod:`cobelrun.checkpoint`; one
    CheckpointError line if it has none or it was written by another cobel version or for
    another config).

    Returns the run folder. On Ctrl-C or SIGTERM the files written so far are closed properly,
    the manifest says ``interrupted`` and :class:`KeyboardInterrupt` propagates.
    ``background_writes`` writes files on a second thread, overlapping simulation and I/O on a
    free core; sweeps switch it off, since their parallel jobs already use every core.
    ``task`` is the task :func:`build_task` already built from ``cfg`` (built here if None).

    The folder is locked while written (:class:`cobelrun.io.lock.RunLock`: a second writer is
    refused naming this process), and a folder that already holds a run is refused unless
    ``replace`` (a sweep job rerunning its own folder after clearing it).
    """
    run_dir = Path(run_dir)
    resolved = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(resolved, Mapping)
    if task is None:
        task = build_task(cfg)  # everything is checked before the folder is touched
    if not (replace or resume):
        _check_new(run_dir)
    with RunLock(run_dir):
        if not (replace or resume):
            _check_new(run_dir)  # again, now that no one else can write it
        checkpoints = None
        if task.job is None and (task.checkpoint.enabled or resume):
            checkpoints = RunCheckpoints(RunFolder(run_dir), task.checkpoint,
                                         config_hash(resolved))  # fmt: skip
            if resume:
                if RunFolder(run_dir).done.exists():
                    raise CobelError(f"cannot resume {run_dir}: the run completed already")
                checkpoints.open_resume()  # checked before anything is written
        return _run(cfg, run_dir, resolved, task, progress, background_writes, checkpoints)


def _check_new(run_dir: Path) -> None:
    """A CobelError if ``run_dir`` is being written or already holds a run."""
    # Hydra's .hydra/ is written before the job function starts: not counted here
    refuse_existing(run_dir, "the run folder", hydra=False)


def _run(cfg: DictConfig, run_dir: Path, resolved: Mapping[str, Any], task: Task,
         progress: Any, background_writes: bool,
         checkpoints: RunCheckpoints | None = None) -> Path:  # fmt: skip
    folder = RunFolder(run_dir)
    manifest = Manifest(run_dir)
    extra = (
        {"job": str(cfg.task.job._target_)}
        if task.job is not None
        else {"runs": task.runs, "trials": task.protocol.n_trials, "kept": kept(task),
              "batch_runs": {"runs_at_once": task.batch, "why_not": task.batch_note},
              "checkpoint": {"every_trials": task.checkpoint.every_trials,
                             "every_minutes": task.checkpoint.every_minutes,
                             "keep": task.checkpoint.keep}}
    )  # fmt: skip
    if checkpoints is not None and checkpoints.resumed is not None:
        extra["resumed_from"] = checkpoints.resumed.get("position")
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_text(folder.config, OmegaConf.to_yaml(OmegaConf.create(resolved)))
        manifest.start(config=dict(resolved), seed=task.seed, task=task.name, extra=extra)
    except OSError as exc:
        raise CobelError(disk_error(exc, run_dir)) from None
    metadata = {"cobel.version": __version__, "cobel.seed": str(task.seed),
                "cobel.config_hash": config_hash(resolved)}  # fmt: skip
    t0 = time.perf_counter()
    guard = SignalGuard(defer=checkpoints is not None)
    if checkpoints is not None:
        checkpoints.guard = guard
    phase_times: dict[str, float] = {}
    cpu_times: dict[str, float] = {}
    with guard.installed():
        try:
            result = execute(task, run_dir, progress=progress, background_writes=background_writes,
                             guard=guard, metadata=metadata, phase_times=phase_times,
                             cpu_times=cpu_times, checkpoints=checkpoints)  # fmt: skip
        except KeyboardInterrupt:
            with guard.closing():
                manifest.finish("interrupted", **_checkpoint_note(checkpoints))
            raise
        except BaseException as exc:
            disk = is_disk_error(exc)
            error = disk_error(exc, run_dir) if disk else f"{type(exc).__name__}: {exc}"
            with guard.closing():
                _finish_failed(manifest, error)
            if disk:  # a full disk or a read-only folder is not a bug: one line, no traceback
                raise CobelError(f"{error}; {_kept(folder)}") from exc
            raise
        try:
            with guard.closing():
                summary = {"job_result": result} if isinstance(result, Mapping) else {}
                if phase_times:
                    summary["phase_wall_time_s"] = {k: round(v, 3) for k, v in phase_times.items()}
                if cpu_times:
                    summary["cpu_time_s"] = {k: round(v, 3) for k, v in cpu_times.items()}
                if task.objective is not None:
                    import pandas as pd

                    summary["objective"] = float(
                        task.objective(pd.read_parquet(folder.table("trials")))
                    )
                    summary["objective_name"] = str(getattr(task.objective, "name", "objective"))
                if checkpoints is not None:
                    summary.update(_checkpoint_note(checkpoints))
                    checkpoints.finish()
                manifest.finish(
                    "completed", wall_time_s=round(time.perf_counter() - t0, 3), **summary
                )
                folder.done.write_text("completed\n")
        except OSError as exc:
            error = disk_error(exc, run_dir)
            with guard.closing():
                _finish_failed(manifest, error)
            raise CobelError(f"{error}; {_kept(folder)}") from exc
    return run_dir


def _checkpoint_note(checkpoints: RunCheckpoints | None) -> dict[str, Any]:
    """For the manifest: the checkpoints this process wrote (how many, the largest)."""
    if checkpoints is None or not checkpoints.sizes:
        return {}
    return {"checkpoints": {"written": len(checkpoints.sizes),
                            "largest_bytes": max(checkpoints.sizes),
                            "file": checkpoints.folder.checkpoint.name}}  # fmt: skip


def _finish_failed(manifest: Manifest, error: str) -> None:
    """Mark the manifest failed; on a disk that cannot take even that, the manifest keeps
    saying ``running`` and ``cobel status`` marks it when it repairs the folder."""
    try:
        manifest.finish("failed", error=error)
    except OSError:
        pass


def _kept(folder: RunFolder) -> str:
    """What a failed run left readable (for the one-line error)."""
    tables = folder.tables()
    parts = folder.unfinished_tables()
    what = []
    if tables:
        what.append(f"tables {', '.join(tables)}")
    if parts:
        what.append(
            f"parts of {', '.join(parts)} (once the disk takes writes again, `cobel status "
            f"{shlex.quote(str(folder.path))}` merges them)"
        )
    return "kept: " + ("; ".join(what) if what else "nothing was written yet")
