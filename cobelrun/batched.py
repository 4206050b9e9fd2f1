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

import dataclasses
import json
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from cobelrun.errors import CobelError, ConfigError

__all__ = ["DEFAULT_CHUNK", "BatchedRuns", "batch_plan", "why_sequential"]

#: runs trained at once when ``task.batch_runs`` is ``auto`` or ``true``
DEFAULT_CHUNK = 128
#: a chunk checkpoint's member holding the structure of its runs' held-back rows (JSON text)
PENDING_INDEX = "pending/index"


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


# -- a chunk's checkpoint: the rows its runs hold back -------------------------------------------
#
# A chunk's runs record through recorder forks that hold every row until the chunk ends (so
# the run folder keeps a sequential run's row order). A checkpoint inside the chunk therefore
# keeps those rows too: every array of every held-back entry goes into one of a few pools (one
# flat array per dtype, members ``pending/<dtype>``) and the entries' structure, with
# ``[pool, offset, shape, dtype]`` in place of each array, into one more member as JSON text
# (``pending/index``, UTF-8 bytes: it grows with the chunk's pieces, and the header is kept
# small). JSON is data: nothing of it is executed.


class _Pools:
    """Arrays packed into one flat array per dtype (strings into one unicode pool)."""

    def __init__(self) -> None:
        self.parts: dict[str, list[np.ndarray]] = {}
        self.sizes: dict[str, int] = {}

    def _add(self, key: str, flat: np.ndarray) -> int:
        at = self.sizes.get(key, 0)
        self.parts.setdefault(key, []).append(flat)
        self.sizes[key] = at + flat.size
        return at

    def put(self, value: Any) -> list[Any]:
        """``[pool, offset, shape, dtype]`` of ``value`` added to its pool; strings as
        ``[pool, offset of the distinct strings, shape, dtype, offset of the codes, count]``
        (a column repeats a few strings, e.g. a layer's name on each of an activity map's
        rows)."""
        a = np.asarray(value)
        dtype = a.dtype.str
        if a.dtype.hasobject:  # monitors' string columns (e.g. the phase's name)
            if not all(isinstance(v, str) for v in a.flat):
                raise CobelError("cannot checkpoint a batched chunk: a monitor's column holds "
                                 "Python objects other than strings")  # fmt: skip
            a, dtype = a.astype(str), "O"
        if a.dtype.kind == "U":
            uniq, codes = np.unique(a.reshape(-1), return_inverse=True)
            at = self._add("U", uniq)
            at_codes = self._add("i4", codes.astype(np.int32).reshape(-1))
            return ["U", at, list(a.shape), dtype, at_codes, int(uniq.size)]
        key = a.dtype.str.lstrip("<>|=")
        return [key, self._add(key, a.reshape(-1)), list(a.shape), dtype]

    def arrays(self) -> dict[str, np.ndarray]:
        return {f"pending/{k}": np.concatenate(v) for k, v in self.parts.items()}


def _cols(pools: _Pools, columns: Any) -> dict[str, Any]:
    return {str(k): pools.put(v) for k, v in columns.items()}


def _pack_batch(pools: _Pools, batch: Any) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for f in dataclasses.fields(batch):
        v = getattr(batch, f.name)
        out[f.name] = _cols(pools, v) if f.name == "extra" else None if v is None else pools.put(v)
    return out


def _pack_grid(pools: _Pools, grid: Any) -> dict[str, Any]:
    return {"name": grid.name, "trial": int(grid.trial),
            "origin": [float(v) for v in grid.origin],
            "cell_size": [float(v) for v in grid.cell_size],
            "fields": _cols(pools, grid.fields),
            "metadata": {str(k): str(v) for k, v in grid.metadata.items()}}  # fmt: skip


def _pack_entry(pools: _Pools, kind: str, payload: Any) -> dict[str, Any]:
    """One held-back entry of a :class:`~cobelrun.recorder.ForkedRun` as JSON + pools."""
    if kind == "event":
        table, columns = payload
        return {"kind": "event", "table": table, "cols": _cols(pools, columns)}
    if kind == "grids":
        run, grids = payload
        return {"kind": "grids", "run": int(run), "grids": [_pack_grid(pools, g) for g in grids]}
    adds, (run, phase, trial, batch, per_trial, grids), joined = payload
    entry = {
        "kind": "rows",
        "adds": [{"table": t, "count": int(c), "cols": _cols(pools, cols)} for t, cols, c in adds],
        "run": int(run), "phase": str(phase), "trial": pools.put(trial),
        "batch": _pack_batch(pools, batch), "per_trial": _cols(pools, per_trial),
        "grids": None if grids is None else [_pack_grid(pools, g) for g in grids],
        "joined": None,
    }  # fmt: skip
    if joined is not None:
        jb, info = joined
        entry["joined"] = {"batch": None if jb is batch else _pack_batch(pools, jb),
                           "first_trial": int(info.first_trial),
                           "first_in_phase": int(info.first_in_phase)}  # fmt: skip
    return entry


class _Unpack:
    """The entries of :func:`_pack_entry` back from the header and the pools (ValueError if
    a reference does not fit its pool)."""

    def __init__(self, pools: dict[str, np.ndarray], env: Any) -> None:
        self.pools, self.env = pools, env

    def _slice(self, key: Any, at: Any, n: int, ref: Any) -> np.ndarray:
        pool = self.pools.get(f"pending/{key}")
        if pool is None or not isinstance(at, int) or not 0 <= at <= at + n <= len(pool):
            raise ValueError(f"pending rows: reference {ref!r} is outside its pool")
        return pool[at : at + n]

    def get(self, ref: Any) -> np.ndarray:
        if not (isinstance(ref, list) and len(ref) in (4, 6)):
            raise ValueError(f"pending rows: bad array reference {ref!r}")
        key, at, shape, dtype = ref[:4]
        if not isinstance(shape, list) or not all(isinstance(n, int) and n >= 0 for n in shape):
            raise ValueError(f"pending rows: bad array reference {ref!r}")
        n = math.prod(shape)
        if len(ref) == 6:  # strings: the distinct ones and a code per element
            uniq = self._slice(key, at, ref[5] if isinstance(ref[5], int) else -1, ref)
            codes = self._slice("i4", ref[4], n, ref)
            if n and (codes.min() < 0 or codes.max() >= len(uniq)):
                raise ValueError(f"pending rows: reference {ref!r} has codes outside its strings")
            a = uniq[codes].reshape(shape)
        else:
            a = self._slice(key, at, n, ref).reshape(shape)
        return a.astype(object) if dtype == "O" else a.astype(np.dtype(dtype), copy=True)

    def cols(self, node: Any) -> dict[str, Any]:
        return {k: self.get(v) for k, v in node.items()}

    def batch(self, node: Any) -> Any:
        from cobelrun.records import TrialBatch

        kw = {k: (self.cols(v) if k == "extra" else None if v is None else self.get(v))
              for k, v in node.items()}  # fmt: skip
        return TrialBatch(**kw)

    def grid(self, node: Any) -> Any:
        from cobelrun.monitors.base import SceneGrid

        return SceneGrid(name=node["name"], trial=int(node["trial"]),
                         origin=tuple(node["origin"]), cell_size=tuple(node["cell_size"]),
                         fields=self.cols(node["fields"]), metadata=dict(node["metadata"]))  # fmt: skip

    def entry(self, node: Any) -> tuple[str, Any]:
        from cobelrun.monitors.base import BatchInfo

        kind = node["kind"]
        if kind == "event":
            return "event", (node["table"], self.cols(node["cols"]))
        if kind == "grids":
            return "grids", (int(node["run"]), [self.grid(g) for g in node["grids"]])
        if kind != "rows":
            raise ValueError(f"pending rows: unknown entry {kind!r}")
        adds = [(a["table"], self.cols(a["cols"]), int(a["count"])) for a in node["adds"]]
        batch = self.batch(node["batch"])
        grids = None if node["grids"] is None else [self.grid(g) for g in node["grids"]]
        mcap = (int(node["run"]), node["phase"], self.get(node["trial"]), batch,
                self.cols(node["per_trial"]), grids)  # fmt: skip
        joined = None
        if node["joined"] is not None:
            j = node["joined"]
            jb = batch if j["batch"] is None else self.batch(j["batch"])
            info = BatchInfo(run=int(node["run"]), phase=node["phase"],
                             first_trial=int(j["first_trial"]), env=self.env,
                             first_in_phase=int(j["first_in_phase"]))  # fmt: skip
            joined = (jb, info)
        return "rows", (adds, mcap, joined)


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
        self,
        task: Any,
        recorder: Any,
        runs: list[int],
        run_seed: Callable[[int, int], Any],
        checkpoints: Any = None,
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
        header = None if checkpoints is None else checkpoints.chunk(runs[0])
        if header is not None:  # a resumed chunk: its state at the checkpoint
            self._restore(checkpoints, header)
        else:
            for fork, view in zip(self.forks, self.views, strict=True):
                fork.start_run(view)

    # -- checkpoints -----------------------------------------------------------------------------
    def save(self, checkpoints: Any, position: Any) -> None:
        """Write the checkpoint of ``position`` inside the chunk: the batched learner (every
        run's networks, optimiser state, counters, replay memory and generators), every
        run's env generator and monitors, and the rows the runs hold back (written when the
        chunk ends; :class:`~cobelrun.recorder.ForkedRun`)."""
        from cobelrun.checkpoint import env_state

        pools = _Pools()
        pending = [[_pack_entry(pools, kind, payload) for kind, payload in fork.pending]
                   for fork in self.forks]  # fmt: skip
        arrays = pools.arrays()
        arrays[PENDING_INDEX] = np.frombuffer(
            json.dumps(pending, separators=(",", ":")).encode(), np.uint8
        )
        batch = {"runs": list(self.runs), "envs": [env_state(e) for e in self._envs],
                 "monitors": [[m.checkpoint_state() for m in fork.monitors]
                              for fork in self.forks],
                 "pools": sorted(pools.parts)}  # fmt: skip
        checkpoints.save(position, self.recorder, chunk=(self.learner, arrays, batch))

    def _restore(self, checkpoints: Any, header: dict[str, Any]) -> None:
        """Go on from a checkpoint written inside this chunk (one CheckpointError line if it
        does not fit: another learner, other runs, damaged)."""
        from cobelrun.agents.base import ArraySpec
        from cobelrun.checkpoint import (
            CheckpointError,
            agent_specs,
            read_checkpoint,
            restore_agent,
            restore_env,
        )

        path = checkpoints.folder.checkpoint

        def fail(what: str) -> CheckpointError:
            return CheckpointError(f"cannot resume from {path}: {what}")

        batch = header.get("batch")
        if not isinstance(batch, dict):
            raise fail("it holds one run's state, this task trains its runs batched "
                       "(task.batch_runs); resume with the settings it was written with")  # fmt: skip
        if batch.get("runs") != list(self.runs):
            raise fail(f"it holds the runs {batch.get('runs')}, this chunk is {self.runs}")
        specs = agent_specs(self.learner)
        specs[PENDING_INDEX] = ArraySpec((None,), "u")
        try:
            for key in batch["pools"]:
                kind = "U" if key == "U" else np.dtype(str(key)).kind
                specs[f"pending/{key}"] = ArraySpec((None,), kind, finite=False)
        except (KeyError, TypeError, ValueError) as exc:
            raise fail(f"its held-back rows are not readable ({exc})") from None
        found = read_checkpoint(path, specs, config_hash=checkpoints.config_hash)
        try:
            pending = json.loads(found.arrays[PENDING_INDEX].tobytes().decode())
        except ValueError as exc:  # UnicodeDecodeError and JSONDecodeError included
            raise fail(f"its held-back rows are not readable ({exc})") from None
        restore_agent(self.learner, found, path)
        try:
            if not isinstance(pending, list):
                raise ValueError("pending rows: expected a list per run")
            unpack = _Unpack(found.arrays, self.recorder.env)
            entries = [[unpack.entry(e) for e in run] for run in pending]
            envs, monitors = batch["envs"], batch["monitors"]
            if len(entries) != len(self.forks) or len(envs) != len(self._envs):
                raise ValueError(f"expected the state of {len(self.forks)} runs")
            for env, state in zip(self._envs, envs, strict=True):
                restore_env(env, state)
            for run, fork, view, states, held in zip(self.runs, self.forks, self.views, monitors,
                                                     entries, strict=True):  # fmt: skip
                if not isinstance(states, list) or len(states) != len(fork.monitors):
                    raise ValueError(f"monitors: expected {len(fork.monitors)} states")
                for m, state in zip(fork.monitors, states, strict=True):
                    m.resume_run(run, view, state)
                fork.pending = held
        except (KeyError, TypeError, ValueError) as exc:
            raise fail(str(exc)) from None

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
