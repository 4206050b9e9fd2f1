"""Batched runs (``task.batch_runs``): R runs of a deep agent trained as one computation.

The run loop (:func:`cobelrun.runner.run_phases`) takes runs in cohorts: one run at a time, or,
for agents with a batched implementation (``Agent.batchable``;
:class:`~cobelrun.agents.dqn.DQNAgent` through :class:`~cobelrun.agents.batched_dqn.BatchedDQN`),
a chunk of R runs as one :class:`BatchedRuns`: R environments (each seeded as run ``r``'s), one
batched learner for R runs, all advanced in lock-step through each piece of each phase by the
same loop, with the same pieces and the same per-trial protocol changes. Each run keeps its own
seed, replay memory, counters and environment; only the arithmetic is shared.

Recording stays per run: every run records through its own copies of the task's monitors
(:meth:`cobelrun.recorder.RunRecorder.fork`), whose trial-end hooks see that run alone
(:class:`~cobelrun.agents.batched_dqn.DQNRunView`), and the rows are written run by run, so
the run folder has the same tables, rows and order as a sequential run.

``task.batch_runs``:

``auto`` (default)
    batched when the agent and the task allow it (see :func:`why_sequential`) and the agent
    does not decline (``Agent.batch_auto_declines``: CNN DQNs on a CPU, where batching was
    measured not to pay), else sequential; the manifest says which and why.
``true`` / an integer N
    batched (N runs at a time; ``true``: :data:`DEFAULT_CHUNK`); a task that cannot be
    batched is a one-line error naming the reason.
``false``
    sequential.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from cobelrun.errors import ConfigError

__all__ = ["DEFAULT_CHUNK", "BatchedRuns", "batch_plan", "why_sequential"]

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
    declines = getattr(template, "batch_auto_declines", None)
    if setting == "auto" and declines is not None:
        why = declines()  # batchable, but measured not to pay here (e.g. CNN agents on a CPU)
        if why is not None:
            return 0, why
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


class BatchedRuns:
    """A chunk of runs trained as one computation: the run loop's
    (:func:`cobelrun.runner.run_phases`) cohort for batched runs. Builds one environment per
    run (seeded as run ``r``'s), one batched learner for the chunk and one recorder fork per
    run (:meth:`cobelrun.recorder.RunRecorder.fork`); every piece advances all runs in
    lock-step, and each run's rows are written, in run order, when the chunk ends or stops.

    ``run_seed(seed, run)`` gives a run's (agent, environment) seed sequences
    (:func:`cobelrun.runner.run_seed`).
    """

    def __init__(
        self, task: Any, recorder: Any, runs: list[int], run_seed: Callable[[int, int], Any]
    ) -> None:
        from cobelrun.envs.base import Changeable, supports

        protocol = task.protocol
        steps = sum(int(p.trials) * int(p.max_steps or protocol.max_steps)
                    for p in protocol.phases if p.learning)  # fmt: skip
        envs, seeds = _make_envs(task, runs, run_seed)
        base = task.env.unwrapped  # the recorder's env: phases apply to it as well
        if supports(base, Changeable):
            base.reset_world()
        self.task, self.recorder, self.runs = task, recorder, runs
        self._envs = envs
        self.envs = [*envs, task.env]
        template = task.make_agent(seed=seeds[0])
        self.learner = template.batch_learner(seeds, steps, task.make_agent)
        self.views = [self.learner.view(i) for i in range(len(runs))]
        self.forks = [recorder.fork(r) for r in runs]
        for fork, view in zip(self.forks, self.views, strict=True):
            fork.start_run(view)

    def piece(self, phase: Any, max_steps: int, first: int, k: int, n: int) -> None:
        callbacks = [fork.phase_callbacks(first + k) for fork in self.forks]
        batches = self.learner.run_phase(self._envs, n, max_steps, phase.learning, callbacks,
                                         self.views)  # fmt: skip
        for fork, batch in zip(self.forks, batches, strict=True):
            fork.record(phase.name, first + k, batch, first_in_phase=k + 1)

    def finish(self, last_trial: int) -> None:
        for run, fork, view in zip(self.runs, self.forks, self.views, strict=True):
            fork.end_run(view, last_trial)
            self.recorder.commit(fork)
            if run in self.task.save_agents:
                self.recorder.save_agent(run, view)

    def abort(self) -> None:
        """Keep the pieces the chunk's runs finished (a sequential run keeps them too)."""
        for fork in self.forks:
            self.recorder.commit(fork)
