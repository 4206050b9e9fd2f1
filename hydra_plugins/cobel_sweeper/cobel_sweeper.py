"""cobel's Hydra sweeper: Hydra's cartesian sweep, made resumable and failure-tolerant.

Hydra only instantiates plugins defined under ``hydra_plugins``, hence its home here. Selected in
``conf/config.yaml`` (``override hydra/sweeper: cobel``). It expands the sweep like
Hydra's BasicSweeper (same job order, same override syntax), then, before launching anything:

* writes ``sweep.json`` (command, swept keys, every job's overrides and params);
* skips jobs whose folder is complete for that exact config (done marker + matching config
  hash; only jobs with a done marker are composed here, so a fresh sweep costs no extra
  composition), so re-running a sweep only runs what is missing;
* marks the other jobs ``queued`` and hands only them to the launcher (joblib, submitit, basic,
  ...), each with ``hydra.sweep.subdir=<job number>`` so a job keeps its folder whatever else
  is skipped.

Jobs record their own failures (``job.json``) and return normally, so one failing job never
stops the others; the sweeper shows a progress bar of finished jobs while the launcher works
and rebuilds the index (``jobs.csv``) at the end.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from hydra.plugins.sweeper import Sweeper
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig, OmegaConf

log = logging.getLogger(__name__)

FINAL = ("completed", "failed", "interrupted")


class CobelSweeper(Sweeper):
    """Hydra's cartesian sweep with resume (skip done jobs) and per-job failure records.

    Built on Hydra's public ``Sweeper`` plugin interface (Hydra's ``BasicSweeper`` lives in a
    private module); the jobs and their order are the basic sweeper's
    (:func:`cobelrun.sweep_plan.cartesian`).

    Parameters
    ----------
    max_batch_size : int, optional
        Launch at most this many jobs at a time (None: all pending jobs in one launch).
    params : dict, optional
        Extra sweep overrides from the config (``hydra.sweeper.params``), as in BasicSweeper.
    skip_done : bool
        Skip jobs whose folder is complete for the same config (default True). Set
        ``hydra.sweeper.skip_done=false`` to run every job again.
    """

    def __init__(
        self,
        max_batch_size: int | None = None,
        params: dict[str, str] | None = None,
        skip_done: bool = True,
    ) -> None:
        super().__init__()
        self.max_batch_size = max_batch_size
        self.params = dict(params or {})
        self.skip_done = skip_done
        self.hydra_context: HydraContext | None = None
        self.config: DictConfig | None = None
        self.launcher: Any = None
        #: filled by :meth:`sweep`: job numbers launched and reused in this call
        self.launched: list[int] = []
        self.reused: list[int] = []

    def setup(
        self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig
    ) -> None:
        """Keep Hydra's context and config and instantiate the configured launcher."""
        from hydra.core.plugins import Plugins

        self.hydra_context = hydra_context
        self.config = config
        self.launcher = Plugins.instance().instantiate_launcher(
            hydra_context=hydra_context, task_function=task_function, config=config
        )

    def sweep(self, arguments: list[str]) -> Any:
        from hydra.core.utils import JobStatus

        from cobelrun.config import register_resolvers
        from cobelrun.io.run_folder import RunFolder
        from cobelrun.io.sweep_folder import (
            DONE_MARKER,
            check_job_dir,
            clear_outputs,
            is_complete,
            job_config_hash,
            job_dir,
            job_rows,
            one_line,
            write_job_status,
            write_sweep,
        )
        from cobelrun.sweep import stop_requested
        from cobelrun.sweep_plan import plan

        assert self.config is not None and self.launcher is not None
        assert self.hydra_context is not None
        register_resolvers()
        swept, jobs = plan(arguments, extra=[f"{k}={v}" for k, v in self.params.items()])
        sweep_dir = Path(str(self.config.hydra.sweep.dir))
        for j in jobs:  # a tampered folder: never clear or write through a link
            check_job_dir(job_dir(sweep_dir, j["job"]))
        sweep_dir.mkdir(parents=True, exist_ok=True)
        OmegaConf.save(self.config, sweep_dir / "multirun.yaml")
        command = os.environ.get("COBEL_COMMAND") or " ".join(sys.argv)
        write_sweep(sweep_dir, command=command, swept=swept, jobs=jobs)

        loader = self.hydra_context.config_loader
        broken = self._check_group_choices(jobs, swept)
        pending: list[list[str]] = []
        for j in jobs:
            num, d = j["job"], job_dir(sweep_dir, j["job"])
            if num in broken:
                write_job_status(d, "queued", job=num, overrides=j["overrides"])
                write_job_status(d, "failed", error=broken[num])
                continue
            chash: str | None = None
            if self.skip_done and (d / DONE_MARKER).is_file():
                # only a finished folder can be reused: compose this job to compare hashes
                try:
                    cfg = loader.load_sweep_config(self.config, list(j["overrides"]))
                except Exception as exc:  # composition error in one combination: record, go on
                    write_job_status(d, "queued", job=num, overrides=j["overrides"])
                    write_job_status(d, "failed", error=one_line(exc))
                    continue
                try:
                    chash = job_config_hash(cfg)
                except Exception:  # e.g. interpolations only a running job can resolve
                    chash = None
                if chash is not None and is_complete(d, chash):
                    self.reused.append(num)
                    continue
            if not RunFolder(d).checkpoint.is_file():  # a stopped job resumes (or clears) itself
                clear_outputs(d)
            write_job_status(d, "queued", job=num, overrides=j["overrides"], config_hash=chash)
            pending.append([*j["overrides"], f"hydra.sweep.subdir={num}"])
            self.launched.append(num)

        if self.reused:
            log.info(f"{len(self.reused)} of {len(jobs)} jobs already done, skipped")
        size = self.max_batch_size if self.max_batch_size not in (None, -1) else len(pending)
        batches = [pending[i : i + size] for i in range(0, len(pending), size)] if pending else []
        watcher = _Watcher(
            [job_dir(sweep_dir, n) for n in self.launched], len(jobs), len(self.reused)
        )
        returns = []
        watcher.start()
        try:
            first = 0
            for batch in batches:
                if stop_requested(sweep_dir):  # stopped (Ctrl-C, SIGTERM): launch no more
                    break
                try:
                    with _worker_setup(self.launcher):
                        results = self.launcher.launch(batch, initial_job_idx=first)
                except Exception as exc:  # the launcher itself failed (e.g. a killed SLURM job)
                    if stop_requested(sweep_dir):
                        _fail_unfinished(sweep_dir, self.launched, "the sweep was stopped",
                                         status="interrupted")  # fmt: skip
                    else:
                        log.error(f"launcher error: {one_line(exc)}")
                        _fail_unfinished(sweep_dir, self.launched,
                                         f"launcher error: {one_line(exc)}")  # fmt: skip
                    results = []
                for r in results:
                    if r.status == JobStatus.FAILED:  # raised outside cobel's job function
                        num = _job_num(r)
                        if num is not None:
                            write_job_status(job_dir(sweep_dir, num), "failed", error=_error(r))
                returns.append(results)
                first += len(batch)
            release_joblib_workers()
        finally:
            watcher.stop()
            job_rows(sweep_dir)
        return returns

    def _check_group_choices(self, jobs: list[dict], swept: list[str]) -> dict[int, str]:
        """Compose one job per value of each swept config group (``agent=a,b``).

        Only a group choice can make one combination fail to compose when another composes
        (its keys differ); composing one representative per value finds that cheaply, where
        composing every job (as Hydra's BasicSweeper does) costs ~0.1-0.2 s per job. Returns
        job number -> error for every job with a value that does not compose.
        """
        from cobelrun.io.sweep_folder import one_line

        assert self.hydra_context is not None and self.config is not None
        from cobelrun.config import GROUPS  # a swept choice may change the config's keys

        groups = [k for k in swept if k.split("@")[0] in GROUPS or "/" in k]
        seen: dict[tuple[str, str], str | None] = {}
        broken: dict[int, str] = {}
        for j in jobs:
            for key in groups:
                value = repr(j["params"].get(key))
                if (key, value) not in seen:
                    try:
                        self.hydra_context.config_loader.load_sweep_config(
                            self.config, list(j["overrides"])
                        )
                        seen[key, value] = None
                    except Exception as exc:
                        seen[key, value] = one_line(exc)
                if seen[key, value] is not None:
                    broken[j["job"]] = str(seen[key, value])
        return broken


def _error(r: Any) -> str:
    """One line naming a failed ``JobReturn``'s exception (its public ``return_value`` raises
    it, after writing a line of its own to stderr, which is dropped)."""
    import io

    from cobelrun.io.sweep_folder import one_line

    try:
        with contextlib.redirect_stderr(io.StringIO()):
            r.return_value  # noqa: B018
    except Exception as exc:
        return one_line(exc)
    return "the job failed"


def _job_num(r: Any) -> int | None:
    try:
        return int(str(r.hydra_cfg.hydra.sweep.subdir))
    except Exception:
        return None


def release_joblib_workers() -> None:
    """Stop the joblib launcher's idle loky workers now that every job has returned.

    Otherwise they are stopped at interpreter exit, where each worker's clean shutdown (Python
    tearing down numba, pyarrow, ...) holds ``cobel run`` ~0.3 s. Called only after the
    launcher returned, when no job is running; a no-op for other launchers.
    """
    try:
        from joblib.externals.loky import reusable_executor
    except ImportError:
        return
    # loky (joblib 1.6) has no public way to look at its reusable executor without creating
    # one (get_reusable_executor starts one, and its resource tracker, when there is none);
    # this reads loky's module attribute, only here, and does nothing if it is gone
    executor = getattr(reusable_executor, "_executor", None)
    if executor is not None:
        try:
            executor.shutdown(wait=True, kill_workers=True)
        except Exception:  # (exit would stop them anyway)
            pass


def _fail_unfinished(sweep_dir: Path, nums: list[int], error: str, status: str = "failed") -> None:
    from cobelrun.io.sweep_folder import JOB_FILE, job_dir, write_job_status
    from cobelrun.io.validate import read_json_or_none as read_json

    for n in nums:
        d = job_dir(sweep_dir, n)
        state = read_json(d / JOB_FILE) or {}
        if state.get("status") not in FINAL:
            write_job_status(d, status, error=error)


@contextlib.contextmanager
def _worker_setup(launcher: Any) -> Iterator[None]:
    """For joblib's process pool: each worker runs :func:`cobelrun.sweep.worker_init` (idle
    workers ignore Ctrl-C; workers stop when the launcher dies). Other launchers: nothing.

    Hydra's joblib launcher always asks joblib for the backend named ``loky`` (it builds the
    ``Parallel`` itself), so for the duration of the launch that name gives a loky backend with
    the initializer (joblib's public ``register_parallel_backend``), and the original after.
    """
    if type(launcher).__name__ != "JoblibLauncher":
        yield
        return
    import functools

    from joblib import parallel

    from cobelrun.sweep import LAUNCHER_ENV, worker_init

    os.environ[LAUNCHER_ENV] = str(os.getpid())  # the workers inherit it (worker_init)
    original = parallel.BACKENDS["loky"]
    parallel.register_parallel_backend("loky", functools.partial(original, initializer=worker_init))
    try:
        yield
    finally:
        parallel.register_parallel_backend("loky", original)


class _Watcher:
    """A progress bar of finished jobs, driven by their ``job.json`` files (terminal only)."""

    def __init__(self, dirs: list[Path], total: int, reused: int) -> None:
        self.dirs, self.total, self.reused = dirs, total, reused
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        from cobelrun.progress import progress_enabled

        if self.dirs and progress_enabled():
            self._thread = threading.Thread(target=self._run, daemon=True)
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)

    def _run(self) -> None:
        from cobelrun.io.sweep_folder import JOB_FILE
        from cobelrun.io.validate import read_json_or_none as read_json
        from cobelrun.progress import counter_progress

        with counter_progress("jobs", total=self.total, unit="jobs") as update:
            while True:
                states = [(read_json(d / JOB_FILE) or {}).get("status") for d in self.dirs]
                done = sum(s in FINAL for s in states)
                failed = sum(s == "failed" for s in states)
                note = f"{failed} failed" if failed else ""
                update(self.reused + done, self.total, note)
                if self._stop.wait(0.5):
                    break
