"""Hydra glue for ``cobel run``: the job function, run and sweep folders, Hydra's command line.

Arguments reach Hydra unchanged. Before Hydra launches anything, the config is composed and
validated by :mod:`cobelrun.compose` (overrides parsed, names checked with close-match
suggestions, every ``_target_`` through the instantiation gate, every part built once), so bad
input fails with one line before any output folder is created.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

# the composer's names, re-exported for callers that import them from here
from cobelrun.compose import (  # noqa: F401
    _check_choices,
    _explain_compose_error,
    _parse,
    _writable_root,
    composer,
    foreign_sweeper,
    user_config_dir,
    validate,
    yaml_error,
)
from cobelrun.config import builtin_conf_dir, register_resolvers
from cobelrun.errors import CobelError, ConfigError
from cobelrun.io.lock import RunLock, refuse_existing
from cobelrun.safety import check_folder, check_inside, results_root


def job(cfg: DictConfig, task: Any = None) -> str:
    """The Hydra task function: run one job into Hydra's output folder (``task``: the task
    already built from ``cfg`` by the up-front validation of a single run)."""
    from hydra.core.hydra_config import HydraConfig

    from cobelrun.checkpoint import REQUEUE_EXIT
    from cobelrun.progress import run_progress
    from cobelrun.runner import run
    from cobelrun.signals import Stopped
    from cobelrun.startup import resume_gc

    resume_gc()  # the start-up is over (cobel run paused the garbage collector for it)
    hc = HydraConfig.get()
    run_dir = Path(hc.runtime.output_dir)
    log_start(cfg, run_dir, list(hc.overrides.task))
    if str(hc.mode) == "RunMode.MULTIRUN":
        result = sweep_job(cfg, hc, run_dir)
        log_end(run_dir)
        return result
    try:
        with run_progress(f"{cfg.task.name}") as progress:
            run(cfg, run_dir, progress=progress, task=task)
    except CobelError as exc:
        LOG.info("failed: %s", exc)
        print(f"cobel: error: {exc}", file=sys.stderr)
        sys.exit(2)
    except Stopped as exc:  # a run with checkpoints, stopped by a signal: resumable
        LOG.info("stopped by %s; checkpoint written", exc.signame)
        print(f"cobel: stopped by {exc.signame}; checkpoint written; continue with "
              f"`cobel resume {run_dir}`", file=sys.stderr)  # fmt: skip
        sys.exit(REQUEUE_EXIT)
    except KeyboardInterrupt:
        LOG.info("interrupted")
        print(f"cobel: interrupted; partial results in {run_dir}", file=sys.stderr)
        sys.exit(130)
    log_end(run_dir)
    if SUMMARY:
        from cobelrun.commands.summary import print_run_summary

        print_run_summary(run_dir)
    print(run_dir)
    return str(run_dir)


#: print the end-of-run summary (``cobel run --quiet`` sets it to False)
SUMMARY = True

#: the job's log lines (Hydra's job logging writes them to RUN_DIR/cobel.log)
LOG = logging.getLogger("cobel")


def log_start(cfg: DictConfig, run_dir: Path, overrides: list[str]) -> None:
    """Log what the job runs: task, seed, overrides, folder."""
    LOG.info("task %s, seed %s, folder %s", cfg.task.name, cfg.seed, run_dir)
    LOG.info("overrides: %s", " ".join(overrides) or "(none)")


def log_end(run_dir: Path) -> None:
    """Log how the job ended and each phase's summary row (from the run folder)."""
    import json

    from cobelrun.io.run_folder import RunFolder

    folder = RunFolder(run_dir)
    if not folder.manifest.is_file():
        return
    manifest = json.loads(folder.manifest.read_text())
    wall = manifest.get("wall_time_s")  # an interrupted run records none
    LOG.info("status %s%s%s", manifest.get("status"),
             f", wall time {wall} s" if wall is not None else "",
             f", error {manifest['error']}" if manifest.get("error") else "")  # fmt: skip
    if "objective" in manifest:
        LOG.info("objective (%s) = %s", manifest.get("objective_name"), manifest["objective"])
    if folder.table("trials").is_file() and manifest.get("status") == "completed":
        from cobelrun.run_summary import read_phase_rows

        for row in read_phase_rows(folder.table("trials")):
            LOG.info("phase %s: %s", row.pop("phase"),
                     ", ".join(f"{k} {v:.4g}" for k, v in row.items()))  # fmt: skip


def sweep_job(cfg: DictConfig, hc: Any, run_dir: Path) -> str:
    """One job of a sweep: skip it when done, else run it; record failures, never raise them.

    The job's ``job.json`` says running / completed / failed (with the error and traceback) /
    interrupted. Errors are recorded and the function returns normally, so the launcher runs
    every other job; ``cobel run`` then reports how many failed.
    """
    import cobelrun.sweep as sweep

    subdir = str(hc.sweep.subdir)
    num = int(subdir) if subdir.isdigit() else int(hc.job.num)
    fields = {"job": num, "overrides": list(hc.overrides.task)}
    sweep_dir = Path(str(hc.sweep.dir))
    wants_number = cfg.task.get("objective") is not None  # optimising sweepers need a float
    sweep.IN_JOB = True
    try:
        return _sweep_job(cfg, run_dir, sweep_dir, num, fields, wants_number)
    finally:
        sweep.IN_JOB = False


def _sweep_job(cfg: DictConfig, run_dir: Path, sweep_dir: Path, num: int, fields: dict,
               wants_number: bool) -> Any:  # fmt: skip
    import traceback

    import cobelrun.sweep as sweep
    from cobelrun.checkpoint import REQUEUE_EXIT
    from cobelrun.io.sweep_folder import clear_outputs, is_complete, job_config_hash, one_line
    from cobelrun.io.sweep_folder import write_job_status as status
    from cobelrun.runner import run
    from cobelrun.signals import Stopped
    from cobelrun.targets import check_config

    try:
        check_config(cfg)  # each job's own composition (its swept values) through the gate
        chash = job_config_hash(cfg)
        if is_complete(run_dir, chash):  # a sweeper other than cobel's may hand us done jobs
            return job_result(run_dir, wants_number)
        if sweep.stop_requested(sweep_dir):  # the sweep is stopping: do not start
            status(run_dir, "interrupted", error="the sweep was stopped before this job started",
                   **fields)  # fmt: skip
            return float("nan") if wants_number else "interrupted"
        with RunLock(run_dir, "the sweep job's folder"):  # one writer, also across sweeps
            resume = resumable(cfg, run_dir)
            if not resume:
                clear_outputs(run_dir)
            status(run_dir, "running", config_hash=chash, **fields)
            # jobs in parallel already fill the cores; a job reruns its own folder, or goes on
            # from its checkpoint (a stopped or requeued job: cobelrun.checkpoint)
            run(cfg, run_dir, background_writes=False, replace=True, resume=resume)
    except Stopped as exc:
        # stopped by a signal after writing its checkpoint: the next sweep command (or the
        # cluster's requeue) resumes it; under submitit its own preemption handler requeues
        status(run_dir, "interrupted", error=f"stopped by {exc.signame}; checkpoint "
               "written (the sweep resumes it)", **fields)  # fmt: skip
        _hand_to_submitit(exc.signum)
        sweep.request_stop(sweep_dir, "a job was stopped")
        if sweep.launcher_gone():
            os._exit(REQUEUE_EXIT)
        return float("nan") if wants_number else "interrupted"
    except KeyboardInterrupt:
        # the files are closed and the manifest says interrupted; later jobs must not start
        # (in-process launchers run them in this process), and the launcher reports it
        status(run_dir, "interrupted", **fields)
        sweep.request_stop(sweep_dir, "a job was interrupted")
        if sweep.launcher_gone():
            os._exit(130)  # the launcher is gone: this worker must not linger
        return float("nan") if wants_number else "interrupted"
    except Exception as exc:
        status(run_dir, "failed", error=one_line(exc), traceback=traceback.format_exc(), **fields)
        print(f"cobel: job {num} failed: {one_line(exc)}", file=sys.stderr)
        return float("nan") if wants_number else "failed"
    status(run_dir, "completed", **fields)
    return job_result(run_dir, wants_number)


def resumable(cfg: DictConfig, run_dir: Path) -> bool:
    """Whether a sweep job's folder holds a checkpoint this job can go on from: same cobel
    version and config, the run not completed. Another one is dropped with the folder (the job
    runs again from its start), with a log line saying why."""
    from cobelrun.checkpoint import CheckpointError, check_header, read_header
    from cobelrun.io.manifest import config_hash
    from cobelrun.io.run_folder import RunFolder

    folder = RunFolder(run_dir)
    if not folder.checkpoint.is_file() or folder.done.exists():
        return False
    try:
        resolved = OmegaConf.to_container(cfg, resolve=True)
        check_header(read_header(folder.checkpoint), folder.checkpoint,
                     config_hash=config_hash(resolved))  # type: ignore[arg-type]  # fmt: skip
    except CheckpointError as exc:
        LOG.warning("%s; the job runs again from its start", exc)
        return False
    return True


def _hand_to_submitit(signum: int) -> None:
    """Inside a submitit job, after the checkpoint: submitit's own handler of its preemption
    signal (SUBMITIT_PREEMPT_SIGNAL, USR2 by default) requeues the job (``scontrol requeue``,
    or a restart under submitit_local) and exits; the requeued job resumes the checkpoint."""
    import signal

    name = "SIG" + os.environ.get("SUBMITIT_PREEMPT_SIGNAL", "USR2")
    if getattr(signal, name, None) != signum:
        return
    handler = signal.getsignal(signum)
    if callable(handler) and getattr(handler, "__self__", None).__class__.__module__.startswith(
        "submitit"
    ):
        handler(signum, None)


def job_result(run_dir: Path, objective: bool) -> Any:
    """What a sweep job returns: the task's objective (a float) when it declares one, so that
    optimising sweepers (Optuna) can use it, else the run folder."""
    if not objective:
        return str(run_dir)
    import json

    from cobelrun.io.run_folder import RunFolder

    value = json.loads(RunFolder(run_dir).manifest.read_text()).get("objective")
    return float("nan") if value is None else float(value)


def _quote(value: str) -> str:
    """Quote a string for a Hydra override value."""
    return "'" + value.replace("\\", "\\\\").replace("'", "\\'") + "'"


def _joblib_available() -> bool:
    import importlib.util

    return importlib.util.find_spec("hydra_plugins.hydra_joblib_launcher") is not None


def default_launcher(overrides: list[str]) -> list[str]:
    """``hydra/launcher=joblib`` (one worker per core) unless a launcher is chosen or joblib
    is not installed (then Hydra's basic launcher runs the jobs one after another)."""
    keys = {o.split("=", 1)[0].lstrip("+~") for o in overrides}
    if "hydra/launcher" not in keys and _joblib_available():
        return ["hydra/launcher=joblib"]
    return []


def sweep_folder(overrides: list[str], cfg: DictConfig, jobs: list[dict]) -> tuple[list[str], Path]:
    """The sweep folder, and the override that sets it when the user did not.

    Unless ``hydra.sweep.dir`` is given, it is ``$COBEL_RESULTS/<task>/sweeps/<id>`` where
    ``<id>`` hashes the jobs' overrides (``cobelrun.sweep.sweep_id``), so the same sweep
    command always uses the same folder and resumes it.
    """
    from cobelrun.sweep_plan import sweep_id

    keys = {o.split("=", 1)[0].lstrip("+~") for o in overrides}
    if "hydra.sweep.dir" in keys:
        given = str(OmegaConf.select(cfg, "hydra.sweep.dir") or "")
        if not given.strip():
            raise ConfigError("hydra.sweep.dir must name a folder, got an empty string")
        return [], check_folder(Path(given), "the sweep folder")
    root = results_root()
    sweep_dir = check_inside(root / str(cfg.task.name) / "sweeps" / sweep_id(jobs), root,
                             "the sweep folder")  # fmt: skip
    return [f"hydra.sweep.dir={_quote(str(sweep_dir))}"], sweep_dir


def run_folder(
    overrides: list[str], cfg: DictConfig, cobel_default: bool = False
) -> tuple[list[str], Path]:
    """A single run's folder, absolute and resolved, and the override that pins it.

    Unless ``hydra.run.dir`` is given, the folder must stay inside the results root
    (``$COBEL_RESULTS`` or ``./results``), also through symlinks; a given one may be anywhere
    but the file system's root. ``cobel_default``: the config (a ``-cd`` folder's, such as a
    saved run's ``.hydra``) does not name a folder itself, so the run gets cobel's usual
    ``$COBEL_RESULTS/<task>/<date>/<time>_<id>`` rather than Hydra's ``outputs/...``.
    """
    keys = {o.split("=", 1)[0].lstrip("+~") for o in overrides}
    out = Path(str(OmegaConf.select(cfg, "hydra.run.dir"))).expanduser()
    if "hydra.run.dir" in keys:
        path = check_folder(out)
    else:
        if cobel_default:
            from cobelrun.api import default_run_dir

            out = default_run_dir(str(cfg.task.name))
        path = check_folder(check_inside(out, results_root()))
    return [f"hydra.run.dir={_quote(str(path))}"], path


def check_new_run(run_dir: Path) -> None:
    """A CobelError if ``run_dir`` is being written or already holds a run: ``cobel run``
    never replaces one (leave hydra.run.dir out for a new dated folder)."""
    refuse_existing(run_dir, "hydra.run.dir")


def has_defaults(config_dir: Path, config_name: str) -> bool:
    """Whether a user's primary config file has a defaults list (a saved run's has none)."""
    from cobelrun.compose import load_config

    path = config_dir / f"{config_name.removesuffix('.yaml')}.yaml"
    return not path.is_file() or "defaults" in load_config(path)


def names_run_dir(config_dir: Path, config_name: str) -> bool:
    """Whether a user's primary config file (``-cd DIR -cn NAME``) sets ``hydra.run.dir``."""
    from cobelrun.compose import load_config

    path = config_dir / f"{config_name.removesuffix('.yaml')}.yaml"
    if not path.is_file():
        return True  # Hydra composes it from elsewhere: leave its folder as it says
    return OmegaConf.select(load_config(path), "hydra.run.dir") is not None


def report_sweep(sweep_dir: Path) -> int:
    """Print the sweep's outcome; return the exit code (1 when a job failed or is missing)."""
    from cobelrun.io.sweep_folder import job_rows, summary
    from cobelrun.io.validate import read_json_or_none as read_json

    try:
        rows = job_rows(sweep_dir, write=False)  # the sweeper has just written jobs.csv
    except CobelError as exc:
        print(f"cobel: error: {exc}", file=sys.stderr)
        return 1
    counts = summary(rows)
    total = len(rows)
    bad = total - counts["done"]
    launched = (read_json(sweep_dir / "sweep.json") or {}).get("launches", 1)
    if bad:
        what = f"{counts['failed']} of {total} jobs failed" if counts["failed"] else ""
        other = bad - counts["failed"]
        if other:
            what = (what + "; " if what else "") + f"{other} of {total} jobs did not finish"
        print(f"cobel: error: {what}; see cobel status {sweep_dir}", file=sys.stderr)
        return 1
    note = f" (launch {launched})" if launched > 1 else ""
    if SUMMARY:
        from cobelrun.commands.summary import print_sweep_summary

        print_sweep_summary(sweep_dir)
    print(f"cobel: {total} of {total} jobs done{note}", file=sys.stderr)
    print(sweep_dir)
    return 0


def basic_sweeper(cfg: DictConfig, overrides: list[str]) -> bool:
    """Whether ``cfg`` runs Hydra's basic sweeper without the user having chosen a sweeper
    (a ``-cd`` folder whose config does not select cobel's, e.g. a saved run's ``.hydra``)."""
    keys = {o.split("=", 1)[0].lstrip("+~") for o in overrides}
    target = str(OmegaConf.select(cfg, "hydra.sweeper._target_", default="") or "")
    return "hydra/sweeper" not in keys and target.endswith(".BasicSweeper")


def report_foreign_sweep(sweep_dir: Path) -> int:
    """Print what a sweeper other than cobel's left (Optuna's best parameters and value)."""
    results = sweep_dir / "optimization_results.yaml"
    if SUMMARY and results.is_file():
        print(results.read_text().rstrip(), file=sys.stderr)
    print(sweep_dir)
    return 0


def launch(args: list[str], *, quiet: bool = False) -> int:
    """Run Hydra on ``args`` (what follows ``cobel run``); return the exit code.

    ``quiet`` leaves out the end-of-run summary.
    """
    import shlex

    global SUMMARY
    SUMMARY = not quiet

    parsed = cli_parser().parse_args(args)
    # ./conf is put first on the search path by hydra_plugins/cobel_searchpath. A user's
    # -cd/-cp folder becomes the primary config folder (so -cd RUN/.hydra -cn config runs the
    # saved config), with the built-in configs searched after it.
    user_dir = user_config_dir(parsed.config_dir or parsed.config_path)
    config_name = parsed.config_name or "config"
    config_dir, overrides = user_dir or builtin_conf_dir(), list(parsed.overrides)
    if user_dir is not None:
        parsed.config_path = None
        parsed.config_dir = str(builtin_conf_dir())  # searched after the user's folder
    informational = (
        parsed.help or parsed.hydra_help or parsed.cfg or parsed.info or parsed.shell_completion
    )
    multirun = bool(parsed.multirun)
    sweep_dir: Path | None = None
    if multirun:
        overrides = [*default_launcher(overrides), *overrides]
        parsed.overrides = overrides
    keys = {o.split("=", 1)[0].lstrip("+~") for o in overrides}
    if user_dir is not None and "hydra/job_logging" not in keys:
        if not has_defaults(user_dir, config_name):
            # a saved run's .hydra/config.yaml has no defaults list: log as cobel run does
            # (RUN_DIR/cobel.log, warnings on the terminal), not with Hydra's default logging
            overrides = [*overrides, "hydra/job_logging=cobel"]
            parsed.overrides = overrides
    if not informational:
        results_root()  # COBEL_RESULTS="" is refused before anything is composed
        built: dict[str, Any] = {}
        cfg, jobs = validate(overrides, multirun, user_dir, config_name, built)
        if multirun and user_dir is not None and basic_sweeper(cfg, overrides):
            # a saved run's .hydra/config.yaml has no defaults list, so Hydra's basic sweeper
            # would run the jobs without cobel's sweep folder, index and resume
            overrides = [*overrides, "hydra/sweeper=cobel"]
            parsed.overrides = overrides
            cfg, jobs = validate(overrides, multirun, user_dir, config_name)
        if multirun and foreign_sweeper(overrides):
            keys = {o.split("=", 1)[0].lstrip("+~") for o in overrides}
            if "hydra.sweep.dir" not in keys:
                root = results_root()
                name = f"{foreign_sweeper(overrides)}_{time.strftime('%Y-%m-%d_%H-%M-%S')}"
                sweep_dir = (root / str(cfg.task.name) / "sweeps" / name).absolute()
                parsed.overrides = [*overrides, f"hydra.sweep.dir={_quote(str(sweep_dir))}"]
            else:
                sweep_dir = Path(str(OmegaConf.select(cfg, "hydra.sweep.dir"))).absolute()
            _writable_root(sweep_dir)
            run_hydra(parsed, config_dir, config_name)
            return report_foreign_sweep(sweep_dir)
        if multirun:
            extra, sweep_dir = sweep_folder(overrides, cfg, jobs)
            _writable_root(sweep_dir)
            parsed.overrides = [*overrides, *extra]
            os.environ["COBEL_COMMAND"] = shlex.join(["cobel", "run", *args])
        else:
            default = user_dir is not None and not names_run_dir(user_dir, config_name)
            extra, run_dir = run_folder(overrides, cfg, cobel_default=default)
            # one writer per folder, from before Hydra writes anything into it (.hydra/,
            # cobel.log) until the run ends; a folder that holds a run is never replaced
            check_new_run(run_dir)
            with RunLock(run_dir):
                check_new_run(run_dir)
                return run_composed(cfg, extra, user_dir, config_name, built.get("task"))
    if sweep_dir is None:
        run_hydra(parsed, config_dir, config_name)
        return 0
    from cobelrun.sweep import SweepLock, clear_stop

    with SweepLock(sweep_dir), SweepStopper(sweep_dir, jobs) as stopper:
        clear_stop(sweep_dir)
        try:
            run_hydra(parsed, config_dir, config_name)
        except KeyboardInterrupt:
            if stopper.signum is None:
                raise
            _release_workers()  # the third signal: the pool's workers are killed
        finally:
            stopper.finish()
        if stopper.stopped:
            return stopper.report()
    return report_sweep(sweep_dir)


#: Hydra 1.3's command-line flags (``hydra.main``): (flags, dest, argparse keywords)
HYDRA_FLAGS: list[tuple[tuple[str, ...], str, dict[str, Any]]] = [
    (("--help", "-h"), "help", {"action": "store_true"}),
    (("--hydra-help",), "hydra_help", {"action": "store_true"}),
    (("--cfg", "-c"), "cfg", {"choices": ["job", "hydra", "all"]}),
    (("--resolve",), "resolve", {"action": "store_true"}),
    (("--package", "-p"), "package", {}),
    (("--run", "-r"), "run", {"action": "store_true"}),
    (("--multirun", "-m"), "multirun", {"action": "store_true"}),
    (("--shell-completion", "-sc"), "shell_completion", {"action": "store_true"}),
    (("--config-path", "-cp"), "config_path", {}),
    (("--config-name", "-cn"), "config_name", {}),
    (("--config-dir", "-cd"), "config_dir", {}),
    (("--experimental-rerun",), "experimental_rerun", {}),
    (("--info", "-i"), "info", {"const": "all", "nargs": "?", "choices": [
        "all", "config", "defaults", "defaults-tree", "plugins", "searchpath"]}),
]  # fmt: skip


def cli_parser() -> Any:
    """A parser of ``cobel run``'s arguments: Hydra's command line (:data:`HYDRA_FLAGS`, the
    flags of ``hydra.main``), read before Hydra runs so that cobel can check them first.

    Hydra 1.3 builds its own parser in a private module; ``tests/test_hydra_public.py``
    checks that this one has the same flags.
    """
    import argparse

    import hydra

    parser = argparse.ArgumentParser(prog="cobel run", add_help=False, description="Hydra")
    for i, (flags, dest, kwargs) in enumerate(HYDRA_FLAGS):
        if i == 2:  # in Hydra's order, so that a usage error lists them as Hydra would
            parser.add_argument("--version", action="version", version=f"Hydra {hydra.__version__}")
            parser.add_argument("overrides", nargs="*")
        parser.add_argument(*flags, dest=dest, **kwargs)
    return parser


def run_hydra(parsed: Any, config_dir: Path, config_name: str) -> None:
    """Run Hydra's command line (``hydra.main``, its public entry point) on ``parsed``.

    ``hydra.main`` reads ``sys.argv``: for the call it holds the command ``cobel`` (so
    Hydra's help and shell completion name the real command; ``cobel -sc`` is forwarded to
    ``cobel run -sc``) and ``parsed`` written back as flags. ``--experimental-rerun`` is not
    passed on (``cobel rerun`` reruns a run).
    """
    from hydra import main

    argv = ["cobel"]
    for flags, dest, _ in HYDRA_FLAGS:
        value = getattr(parsed, dest)
        if dest == "experimental_rerun" or value in (None, False):
            continue
        argv.append(flags[0] if value is True else f"{flags[0]}={value}")
    argv.extend(parsed.overrides)
    before = sys.argv
    sys.argv = argv
    try:
        main(config_path=str(config_dir), config_name=config_name, version_base="1.3")(job)()
    finally:
        sys.argv = before


class HydraCallbacks:
    """The callbacks of ``hydra.callbacks`` (Hydra's public ``Callback`` interface) for a
    single run: each is instantiated from the config and told of the run's and the job's start
    and end, the ends in reverse order; a callback that raises is reported as a warning.
    This is what Hydra's own run does, whose class for it lives in a private module."""

    def __init__(self, cfg: DictConfig) -> None:
        from hydra.utils import instantiate

        from cobelrun.targets import check_config

        nodes = OmegaConf.select(cfg, "hydra.callbacks") or {}
        check_config(nodes, "hydra.callbacks")  # checked when composed; again before building
        self.callbacks = [instantiate(node) for node in nodes.values()]

    def _notify(self, name: str, reverse: bool = False, **kwargs: Any) -> None:
        import warnings

        for c in reversed(self.callbacks) if reverse else self.callbacks:
            try:
                getattr(c, name)(**kwargs)
            except Exception as exc:
                warnings.warn(f"Callback {type(c).__name__}.{name} raised "
                              f"{type(exc).__name__}: {exc}", stacklevel=2)  # fmt: skip

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        self._notify("on_run_start", config=config, **kwargs)

    def on_run_end(self, config: DictConfig, **kwargs: Any) -> None:
        self._notify("on_run_end", reverse=True, config=config, **kwargs)

    def on_job_start(self, config: DictConfig, *, task_function: Any, **kwargs: Any) -> None:
        self._notify("on_job_start", config=config, task_function=task_function, **kwargs)

    def on_job_end(self, config: DictConfig, job_return: Any, **kwargs: Any) -> None:
        self._notify("on_job_end", reverse=True, config=config, job_return=job_return, **kwargs)


def report_unexpected(func: Callable[[], Any]) -> Any:
    """Run ``func``; an exception it raises (a bug, not bad input) is reported as Hydra's own
    run reports it: the traceback from the job function on (without the frames above Hydra's
    ``run_job`` and OmegaConf's at the bottom), a hint, exit code 1. With
    ``HYDRA_FULL_ERROR=1`` (``cobel run --debug``) or under a debugger it is raised whole."""
    import traceback

    from hydra.errors import CompactHydraException
    from omegaconf.errors import OmegaConfBaseException

    try:
        return func()
    except Exception as exc:
        if os.environ.get("HYDRA_FULL_ERROR") == "1" or sys.gettrace() is not None:
            raise
        if isinstance(exc, CompactHydraException):
            sys.stderr.write(f"{exc}{os.linesep}")
            if isinstance(exc.__cause__, OmegaConfBaseException):
                sys.stderr.write(f"{exc.__cause__}{os.linesep}")
        else:
            te = traceback.TracebackException.from_exception(exc)
            frames = list(te.stack)
            starts = [i for i, f in enumerate(frames[:10]) if f.name == "run_job"]
            if not starts:  # not from the job: the whole traceback
                traceback.print_exc()
                sys.exit(1)
            frames = frames[starts[0] + 1 :]
            end = next((i for i, f in enumerate(frames)
                        if f"{os.sep}omegaconf{os.sep}" in f.filename), len(frames))  # fmt: skip
            te.stack = traceback.StackSummary.from_list(frames[: max(end, 1)])
            sys.stderr.write("".join(te.format()))
        sys.stderr.write(
            "\nSet the environment variable HYDRA_FULL_ERROR=1 for a complete stack trace.\n"
        )
        sys.exit(1)


def run_composed(
    cfg: DictConfig,
    extra: list[str],
    config_dir: Path | None,
    config_name: str,
    task: Any = None,
) -> int:
    """Run one job on the config that :func:`validate` composed; return the exit code.

    Hydra's own ``run`` composes the config twice more (once to find the run mode, once to
    run), ~0.1 s each; this does what it does after composing, on the one composition:
    ``extra`` (``hydra.run.dir=...``, from :func:`run_folder`) and ``hydra.mode=RUN`` are
    applied and recorded among the Hydra overrides as Hydra would, Hydra's logging is
    configured, and the job runs through Hydra's ``run_job`` (output folder, ``.hydra/``
    files, job logging, callbacks) with Hydra's error reporting. ``task``: the task
    :func:`validate` built from ``cfg``, run as it is (not built a second time).
    """
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.utils import configure_log, run_job
    from hydra.types import HydraContext, RunMode
    from omegaconf import open_dict, read_write

    applied = [*extra, "hydra.mode=RUN"]
    with read_write(cfg), open_dict(cfg):
        for o in _parse(extra):
            OmegaConf.update(cfg, o.key_or_group, o.value(), merge=False)
        cfg.hydra.mode = RunMode.RUN
        cfg.hydra.overrides.hydra.extend(applied)

    def _run() -> None:
        with composer(config_dir, config_name):
            configure_log(cfg.hydra.hydra_logging, cfg.hydra.verbose)
            callbacks = HydraCallbacks(cfg)
            callbacks.on_run_start(config=cfg, config_name=config_name)
            ret = run_job(
                hydra_context=HydraContext(config_loader=GlobalHydra.instance().config_loader(),
                                           callbacks=callbacks),  # type: ignore[arg-type]
                task_function=functools.partial(job, task=task), config=cfg,
                job_dir_key="hydra.run.dir",
                job_subdir_key=None, configure_logging=True,
            )  # fmt: skip
            callbacks.on_run_end(config=cfg, config_name=config_name, job_return=ret)
            _ = ret.return_value  # raises the job's exception, as Hydra's run does

    report_unexpected(_run)
    return 0


def _release_workers() -> None:
    try:
        from hydra_plugins.cobel_sweeper.cobel_sweeper import release_joblib_workers
    except ImportError:
        return
    release_joblib_workers()


class SweepStopper:
    """Ctrl-C and SIGTERM in a sweep's launcher: stop every job cleanly, orphan nothing.

    The first signal writes the sweep's stop file (jobs that start later see it and stop at
    once) and sends SIGTERM to the process of every running job (again each second until it
    has stopped, in case it was between jobs), so each job closes its files and says
    ``interrupted``; the launcher then gets every job's result as usual, its workers are shut
    down, and the jobs that never started are marked ``interrupted``. Further signals only
    print that the sweep is stopping.
    """

    def __init__(self, sweep_dir: Path, jobs: list[dict]) -> None:
        import threading

        self.sweep_dir = sweep_dir
        self.jobs = [int(j["job"]) for j in jobs]
        self.signum: int | None = None
        self._noticed = False
        self._count = 0
        self._previous: dict[int, Any] = {}
        self._done = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def stopped(self) -> bool:
        from cobelrun.sweep import stop_requested

        return self.signum is not None or stop_requested(self.sweep_dir)

    def __enter__(self) -> SweepStopper:
        import signal

        for sig in (signal.SIGINT, signal.SIGTERM):
            self._previous[sig] = signal.signal(sig, self._handler)
        return self

    def __exit__(self, *exc: object) -> None:
        import signal

        self.finish()
        for sig, prev in self._previous.items():
            signal.signal(sig, prev)
        self._previous.clear()

    def _handler(self, signum: int, frame: Any) -> None:
        import threading

        from cobelrun.sweep import request_stop

        if self.signum is not None:
            self._count += 1
            if self._count >= 3:  # a job does not stop: the third signal stops them all now
                print("cobel: stopping the sweep's workers now", file=sys.stderr)
                raise KeyboardInterrupt
            if not self._noticed:
                self._noticed = True
                print("cobel: stopping the sweep, please wait (a third signal kills the jobs)",
                      file=sys.stderr)  # fmt: skip
            return
        self._count = 1
        self.signum = signum
        request_stop(self.sweep_dir, f"signal {signum}")
        print("cobel: stopping the sweep: running jobs close their files, the others do not "
              "start", file=sys.stderr)  # fmt: skip
        self._thread = threading.Thread(target=self._forward, daemon=True)
        self._thread.start()

    def _forward(self) -> None:
        import signal

        from cobelrun.sweep import running_pids

        while not self._done.is_set():
            for pid in running_pids(self.sweep_dir, self.jobs).values():
                with contextlib.suppress(OSError):
                    os.kill(pid, signal.SIGTERM)
            self._done.wait(1.0)

    def finish(self) -> None:
        self._done.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None

    def report(self) -> int:
        """Mark jobs that never started, rebuild the index, print one line; exit code 130."""
        from cobelrun.io.sweep_folder import job_rows, summary
        from cobelrun.io.validate import read_json_or_none as read_json
        from cobelrun.sweep import clear_stop, mark_not_started

        mark_not_started(self.sweep_dir, self.jobs, "the sweep was stopped before this job started")
        clear_stop(self.sweep_dir)
        try:
            counts = summary(job_rows(self.sweep_dir))
        except CobelError:
            counts = {}
        command = (read_json(self.sweep_dir / "sweep.json") or {}).get("command", "")
        done = counts.get("done", 0)
        print(f"cobel: interrupted; {done} of {len(self.jobs)} jobs done; resume with: {command}",
              file=sys.stderr)  # fmt: skip
        return 130


register_resolvers()  # also in worker processes that unpickle `job`
# a log file that cannot be written (a full disk, a read-only folder) must not print a
# traceback per message: the run itself fails with one line that names the problem
logging.raiseExceptions = False
