"""Batched runs (``task.batch_runs``): R runs of a deep agent trained as one computation.

The sequential runner (:func:`cobelrun.runner.execute`) builds one agent per run and runs its
phases one after another. For agents with a batched implementation (``Agent.batchable``;
:class:`~cobelrun.agents.dqn.DQNAgent` through :class:`~cobelrun.agents.batched_dqn.BatchedDQN`)
this module instead builds R environments (each seeded as run ``r``'s), one batched learner
for R runs, and advances all of them in lock-step through each phase. Each run keeps its own
seed, replay memory, counters and environment; only the arithmetic is shared.

Recording stays per run: every run records through its own copies of the task's monitors
(:meth:`cobelrun.recorder.RunRecorder.fork`), whose trial-end hooks see that run alone
(:class:`~cobelrun.agents.batched_dqn.DQNRunView`), and the rows are written run by run, so
the run folder has the same tables, rows and order as a sequential run.

``task.batch_runs``:

``auto`` (default)
    batched when the agent and the task allow it (see :func:`why_sequential`), else
    sequential; the manifest says which and why.
``true`` / an integer N
    batched (N runs at a time; ``true``: :data:`DEFAULT_CHUNK`); a task that cannot be
    batched is a one-line error naming the reason.
``false``
    sequential.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from cobelrun.errors import ConfigError

__all__ = ["DEFAULT_CHUNK", "batch_plan", "execute_batched", "why_sequential"]

#: runs trained at once when ``task.batch_runs`` is ``auto`` or ``true``
DEFAULT_CHUNK = 128


def why_sequential(task: Any, template: Any) -> str | None:
    """Why the task's runs cannot be batched (one phrase), or None if they can."""
    if not getattr(type(template), "batchable", False):
        return f"agent {type(template).__name__} has no batched implementation"
    rec = task.record
    if rec.training_log:
        return "task.record.training_log writes SB3's per-run training curves"
    if rec.images:
        return "task.record.images grabs camera frames step by step"
    if task.load_from is not None:
        return "agent.load_from continues saved agents one by one"
    for name, monitor in task.monitors.items():
        probe = monitor.fork(lambda table, cols: None)
        for cb in probe.callbacks(1):
            if not type(cb).trial_end_only():
                return f"monitor {name} needs per-step callbacks"
    return template.batch_unsupported()


def batch_plan(
    setting: Any, task: Any, template_factory: Callable[[], Any]
) -> tuple[int, str | None]:
    """``(runs at once, why not batched)`` for ``task.batch_runs = setting``; 0 runs at once
    means sequential. An explicit request that cannot be met is a ConfigError."""
    if setting is False:
        return 0, "task.batch_runs=false"
    chunk = DEFAULT_CHUNK if setting in ("auto", True) else int(setting)
    if setting == "auto" and task.runs < 2:
        return 0, "a single run"
    template = template_factory()
    why = why_sequential(task, template)
    if why is not None:
        if setting == "auto":
            return 0, why
        raise ConfigError(f"task.batch_runs={str(setting).lower()}: cannot batch this task: {why}")
    return min(chunk, task.runs), None


def _make_envs(
    task: Any, runs: Sequence[int], run_seed: Callable[[int, int], Any]
) -> tuple[list[Any], list[np.random.SeedSequence]]:
    """One environment per run, restored and seeded as the sequential runner does."""
    from cobelrun.envs.base import Changeable, supports

    envs, agent_seeds = [], []
    for r in runs:
        agent_seed, env_seed = run_seed(task.seed, r)
        env = task.make_env()
        base = env.unwrapped
        if supports(base, Changeable):
            base.reset_world()
        base.np_random = np.random.default_rng(env_seed)
        envs.append(env)
        agent_seeds.append(agent_seed)
    return envs, agent_seeds


def execute_batched(
    task: Any,
    recorder: Any,
    chunk: int,
    progress: Any = None,
    phase_times: dict[str, float] | None = None,
    *,
    run_seed: Callable[[int, int], Any],
) -> None:
    """Every run of ``task``, ``chunk`` runs at a time, recorded run by run; ``run_seed(seed,
    run)`` gives a run's (agent, environment) seed sequences
    (:func:`cobelrun.runner.run_seed`)."""
    from cobelrun.envs.base import Changeable, supports

    protocol = task.protocol
    per_run = protocol.n_trials
    steps = sum(int(p.trials) * int(p.max_steps or protocol.max_steps)
                for p in protocol.phases if p.learning)  # fmt: skip
    for start in range(0, task.runs, chunk):
        runs = list(range(start, min(start + chunk, task.runs)))
        envs, seeds = _make_envs(task, runs, run_seed)
        base = task.env.unwrapped  # the recorder's env: phases apply to it as well
        if supports(base, Changeable):
            base.reset_world()
        template = task.make_agent(seed=seeds[0])
        learner = template.batch_learner(seeds, steps, task.make_agent)
        views = [learner.view(i) for i in range(len(runs))]
        forks = [recorder.fork(r) for r in runs]
        try:
            first = _run_chunk(task, envs, learner, views, forks, phase_times)
        except BaseException:
            # Ctrl-C, SIGTERM or an error: keep the phases the chunk's runs finished, as a
            # sequential run keeps its finished phases (the phase under way is lost in both)
            for fork in forks:
                recorder.commit(fork)
            raise
        for run, fork, view in zip(runs, forks, views, strict=True):
            fork.end_run(view, first - 1)
            recorder.commit(fork)
            if run in task.save_agents:
                recorder.save_agent(run, view)
        if progress is not None:
            done = runs[-1] + 1
            progress(done * per_run, task.runs * per_run, run=runs[-1], runs=task.runs)


def _run_chunk(
    task: Any, envs: list[Any], learner: Any, views: list[Any], forks: list[Any],
    phase_times: dict[str, float] | None,
) -> int:  # fmt: skip
    """Every phase of one chunk of runs, each run's batches held by its fork; returns the
    trial number after the last phase."""
    protocol = task.protocol
    for fork, view in zip(forks, views, strict=True):
        fork.start_run(view)
    first = 1
    for phase in protocol.phases:
        for env in (*envs, task.env):
            protocol.apply(phase, env)
        max_steps = phase.max_steps or protocol.max_steps
        callbacks = [fork.phase_callbacks(first) for fork in forks]
        t_phase = time.perf_counter()
        batches = learner.run_phase(envs, phase.trials, max_steps, phase.learning,
                                    callbacks, views)  # fmt: skip
        for fork, batch in zip(forks, batches, strict=True):
            fork.record(phase.name, first, batch)
        if phase_times is not None:
            phase_times[phase.name] = (
                phase_times.get(phase.name, 0.0) + time.perf_counter() - t_phase
            )
        first += phase.trials
    return first
