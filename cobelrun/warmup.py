"""A joblib sweep's worker processes: started while ``cobel run -m`` validates, stopped early.

Hydra's joblib launcher runs jobs on loky worker processes. A fresh worker costs about a
second before its first job runs (interpreter start, importing hydra, numpy, numba, pyarrow and
the agent's modules, loading compiled kernels from numba's cache), and none of that overlaps
with anything: the launcher only starts workers once the sweeper hands it the jobs.

:func:`start` begins that work right after the first job's config is composed, on a background
thread: it calls ``joblib.Parallel`` with exactly the arguments the launcher will use
(``hydra.launcher.*``, backend ``loky``), so loky keeps the executor and the launcher's own
``Parallel`` call later reuses the warm workers (loky reuses an executor whose arguments
match). Each worker rehearses the first job once (one run, one trial per phase, written to a
temporary folder), which loads everything the jobs need. The sweeper calls :func:`wait` before
launching, so only one ``Parallel`` call is ever in flight, and :func:`release_workers` once
every job has returned, so that ``cobel run`` does not wait for idle workers at exit.

Warm-up is an optimisation only: any error in it is ignored (the launcher then starts its
workers as it always would), and it is skipped when the launcher is not joblib, when joblib
would run the jobs in-process (one worker) or when the sweep has a single job.
``COBEL_WARMUP=0`` turns it off.
"""

from __future__ import annotations

import copy
import os
import tempfile
import threading
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict

JOBLIB_TARGET = "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher"

_thread: threading.Thread | None = None
#: pids of the warmed workers (filled when warm-up finishes; for tests and benchmarks)
worker_pids: list[int] = []


def joblib_kwargs(launcher_cfg: DictConfig) -> dict[str, Any]:
    """The ``joblib.Parallel`` arguments Hydra's joblib launcher derives from its config."""
    from hydra_plugins.hydra_joblib_launcher._core import process_joblib_cfg

    kwargs = OmegaConf.to_container(launcher_cfg, resolve=True)
    assert isinstance(kwargs, dict)
    kwargs.pop("_target_", None)
    kwargs["backend"] = "loky"  # the launcher hard-codes loky
    process_joblib_cfg(kwargs)
    return kwargs


def rehearsal_config(job_cfg: DictConfig) -> DictConfig:
    """The job's config cut down to one run with at most one trial per phase."""
    cfg = copy.deepcopy(job_cfg)
    with open_dict(cfg):
        cfg.task.runs = 1
        for phase in OmegaConf.select(cfg, "task.protocol.phases", default=None) or []:
            phase.trials = min(int(phase.trials), 1)
    return cfg


def _warm_worker(job_cfg: DictConfig) -> int:
    """In a worker: rehearse the first job (one run, one trial per phase, into a temporary
    folder), so that its imports, numba's cached kernels and the writers are loaded before the
    first real job. A task with its own ``task.job`` is only built."""
    import hydra_plugins.hydra_joblib_launcher._core  # noqa: F401  (the launcher's job function)

    from cobelrun.config import register_resolvers
    from cobelrun.runner import build_task, execute

    register_resolvers()
    try:
        task = build_task(rehearsal_config(job_cfg))
        if task.job is None:
            with tempfile.TemporaryDirectory(prefix="cobel-warmup-") as tmp:
                execute(task, Path(tmp), background_writes=False)
    except Exception:  # (the job itself will report it)
        pass
    return os.getpid()


def start(cfg: DictConfig, n_jobs_in_sweep: int) -> bool:
    """Warm the joblib launcher's workers in the background; True when warm-up started.

    ``cfg`` is the first job's composed config with its ``hydra`` node.
    """
    global _thread
    if os.environ.get("COBEL_WARMUP", "1") == "0" or n_jobs_in_sweep < 2 or _thread is not None:
        return False
    launcher = OmegaConf.select(cfg, "hydra.launcher")
    if not isinstance(launcher, DictConfig) or launcher.get("_target_") != JOBLIB_TARGET:
        return False
    try:
        import joblib

        kwargs = joblib_kwargs(launcher)
        workers = joblib.effective_n_jobs(kwargs.get("n_jobs", -1))
    except Exception:  # (warm-up is optional)
        return False
    if workers < 2:  # joblib runs the jobs in this process
        return False
    job_cfg = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])

    def warm() -> None:
        try:
            tasks = (joblib.delayed(_warm_worker)(job_cfg) for _ in range(workers))
            worker_pids[:] = sorted(set(joblib.Parallel(**kwargs)(tasks)))
        except Exception:  # (the launcher starts its own workers)
            pass

    _thread = threading.Thread(target=warm, name="cobel-warmup", daemon=True)
    _thread.start()
    return True


def wait() -> None:
    """Block until warm-up (if any) is done, so the launcher finds the warm workers."""
    global _thread
    if _thread is not None:
        _thread.join()
        _thread = None


def release_workers() -> None:
    """Stop the joblib launcher's idle loky workers now that every job has returned.

    Otherwise they are stopped at interpreter exit, where a clean shutdown of each worker
    (Python tearing down numba, pyarrow, ...) holds ``cobel run`` ~0.3 s. Only called by the
    sweeper after the launcher returned, when no job is running.
    """
    try:
        from joblib.externals.loky import reusable_executor
    except ImportError:
        return
    executor = getattr(reusable_executor, "_executor", None)  # loky's reusable executor
    if executor is not None:
        try:
            executor.shutdown(wait=True, kill_workers=True)
        except Exception:  # (exit would stop them anyway)
            pass
