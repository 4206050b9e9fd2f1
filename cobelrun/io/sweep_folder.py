"""The sweep folder's format: its file names, ``sweep.json``, each job's ``job.json``, the job
index (``jobs.csv``) and when a job counts as done.

A sweep folder (``cobel run -m ...``) looks like this::

    SWEEP_DIR/
      sweep.json        what the sweep is: command, swept keys, every job's overrides and params
      multirun.yaml     Hydra's sweep config
      jobs.csv          the job index (job, params, status, error, config hash, run dir), rebuilt
                        from the job folders by the launcher and by `cobel status`/`cobel collect`
      0/ 1/ 2/ ...      one run folder per job (config.yaml, manifest.json, trials.parquet, ...)
        job.json        the job's own status file: running / completed / failed (+ error)
        .done           written last by the runner, only when the job completed
      collected/        `cobel collect`: trials.parquet, steps.parquet with params as columns

Every job writes only inside its own folder; ``sweep.json`` is written by the launcher process
before any job starts, and ``jobs.csv`` is (re)built from the folders by one process at a time
(the launcher when the sweep ends, or ``cobel status``). No file has two concurrent writers.

A job counts as *done* when its ``.done`` marker exists and its manifest's ``config_hash``
equals the hash of the job's composed config; re-running the same sweep skips done jobs and
runs the rest.

Combining the jobs' tables (``cobel collect``) is :mod:`cobelrun.io.sweep_collect`; planning a
sweep's jobs from overrides is :mod:`cobelrun.sweep_plan`; the launcher's own runtime (its lock,
stop requests, worker signals) is :mod:`cobelrun.sweep` (orchestration).
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import socket
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from cobelrun.errors import CobelError
from cobelrun.io.manifest import DONE_MARKER, _write_json_atomic, config_hash
from cobelrun.io.repair import pid_alive
from cobelrun.io.run_folder import RunFolder
from cobelrun.io.validate import read_json_or_none as read_json

SWEEP_FILE = "sweep.json"
INDEX_FILE = "jobs.csv"
JOB_FILE = RunFolder.JOB
COLLECTED_DIR = "collected"
#: what a re-run removes from a job folder before starting again (stale outputs)
#: statuses shown by `cobel status`
STATUSES = ("done", "failed", "interrupted", "running", "queued", "missing")


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat()


def one_line(exc: BaseException) -> str:
    """``Type: first line of the message`` (just the message for cobel's own errors)."""
    text = str(exc).strip().splitlines()
    msg = text[0] if text else ""
    if isinstance(exc, CobelError):
        return msg or type(exc).__name__
    return f"{type(exc).__name__}: {msg}" if msg else type(exc).__name__


# -- jobs -------------------------------------------------------------------------------------


def job_config_hash(cfg: Any) -> str:
    """The config hash the runner records for a composed job config (its ``hydra`` node dropped)."""
    from omegaconf import DictConfig, OmegaConf

    if isinstance(cfg, DictConfig):
        if "hydra" in cfg:
            cfg = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
        cfg = OmegaConf.to_container(cfg, resolve=True)
    return config_hash(dict(cfg))


def _read_checked(path: Path, reader: Callable[[Path], dict[str, Any]]) -> tuple[dict, str | None]:
    """(content, None) of a file checked by ``reader``; ({}, None) when missing; ({}, the
    one-line problem) when it is damaged."""
    if not path.is_file() and not path.is_symlink():
        return {}, None
    try:
        return reader(path), None
    except CobelError as exc:
        return {}, str(exc)


def is_complete(
    run_dir: str | os.PathLike[str],
    config_hash: str | None = None,
    manifest: Mapping[str, Any] | None = None,
) -> bool:
    """True when ``run_dir`` holds a completed run (done marker) of the config ``config_hash``.

    ``manifest``: the folder's manifest when the caller has already read it.
    """
    from cobelrun.io.validate import read_manifest

    run_dir = Path(run_dir)
    if not (run_dir / DONE_MARKER).is_file():
        return False
    if manifest is None:
        manifest = _read_checked(RunFolder(run_dir).manifest, read_manifest)[0]
    if manifest is None or manifest.get("status") != "completed":
        return False
    return config_hash is None or manifest.get("config_hash") == config_hash


def clear_outputs(run_dir: Path) -> None:
    """Remove the done marker first, then every output of an earlier attempt (the run folder
    owner knows the layout: tables, MCAP, agents, world, parts)."""
    RunFolder(run_dir).clear()


def write_job_status(run_dir: Path, status: str, **fields: Any) -> dict[str, Any]:
    """Write (atomically) the job's ``job.json``: queued -> running -> completed/failed/interrupted.

    ``queued`` starts a fresh record; later statuses keep the earlier fields (job number,
    overrides, config hash) and add their own.
    """
    run_dir.mkdir(parents=True, exist_ok=True)
    if status == "queued":  # by the launcher: its pid tells `cobel status` if it is gone
        data: dict[str, Any] = {"queued_at": _now(), "launcher_pid": os.getpid(),
                                "launcher_host": socket.gethostname()}  # fmt: skip
    else:
        data = read_json(run_dir / JOB_FILE) or {}
        for stale in ("ended_at", "duration_s", "error", "traceback"):
            data.pop(stale, None)
    if status == "running":
        data.update(started_at=_now(), host=socket.gethostname(), pid=os.getpid())
    elif status != "queued":
        data["ended_at"] = _now()
        if "started_at" in data:
            start = _dt.datetime.fromisoformat(data["started_at"])
            data["duration_s"] = round((_dt.datetime.now(_dt.UTC) - start).total_seconds(), 3)
    data.update(fields)
    data["status"] = status
    _write_json_atomic(run_dir / JOB_FILE, data)
    return data


def write_sweep(sweep_dir: Path, *, command: str, swept: list[str], jobs: list[dict]) -> None:
    """Write ``sweep.json`` (the launcher does this before any job starts)."""
    from cobelrun.io.validate import read_sweep_file

    sweep_dir.mkdir(parents=True, exist_ok=True)
    try:  # an earlier launch's record, if it can be trusted
        old = read_sweep_file(sweep_dir / SWEEP_FILE) if (sweep_dir / SWEEP_FILE).is_file() else {}
    except CobelError:
        old = {}
    data = {
        "command": command,
        "swept": swept,
        "n_jobs": len(jobs),
        "created_at": old.get("created_at", _now()),
        "updated_at": _now(),
        "launches": int(old.get("launches", 0)) + 1,
        "jobs": jobs,
    }
    _write_json_atomic(sweep_dir / SWEEP_FILE, data)


def read_sweep(sweep_dir: str | os.PathLike[str]) -> dict[str, Any]:
    """The sweep definition (``sweep.json``) of a sweep folder."""
    from cobelrun.io.validate import read_sweep_file

    p = Path(sweep_dir)
    if not p.is_dir():
        raise CobelError(f"sweep folder {p} does not exist")
    if not (p / SWEEP_FILE).is_file() and not (p / SWEEP_FILE).is_symlink():
        raise CobelError(
            f"{p} is not a cobel sweep folder (no {SWEEP_FILE}; made by `cobel run -m`)"
        )
    return read_sweep_file(p / SWEEP_FILE)


# -- the index --------------------------------------------------------------------------------


#: why a job that was still ``queued`` when its launcher died is ``interrupted``
NOT_STARTED = "not started: the sweep's launcher (pid {pid}) ended before this job started"


def launcher_alive(job: Mapping[str, Any]) -> bool:
    """True if the launcher that queued ``job`` (its ``job.json``) may still start it: its
    process runs on this host, or it ran on another host (unknown, so treated as alive), or
    the record names no launcher (written by an older cobel)."""
    pid = job.get("launcher_pid")
    if not isinstance(pid, int) or pid <= 0 or job.get("launcher_host") != socket.gethostname():
        return True
    return pid == os.getpid() or pid_alive(pid)


def _job_process_alive(job: Mapping[str, Any]) -> bool:
    """True if the process of a ``running`` job record may still run (as :func:`launcher_alive`)."""
    pid = job.get("pid")
    if not isinstance(pid, int) or pid <= 0 or job.get("host") != socket.gethostname():
        return True
    return pid == os.getpid() or pid_alive(pid)


def job_state(run_dir: Path) -> dict[str, Any]:
    """Status of one job folder: status, error, config_hash, duration_s, started_at.

    A folder left by a killed job is repaired first (tables merged, MCAP finished, manifest
    marked interrupted; :func:`cobelrun.io.repair.repair_run`). A job still ``queued`` whose
    launcher has died (SIGKILL, a crash) is marked ``interrupted`` with :data:`NOT_STARTED`:
    nothing will start it until the sweep is run again."""
    from cobelrun.io.repair import repair_run
    from cobelrun.io.validate import check_table, read_job_file, read_manifest

    if run_dir.is_symlink() or (run_dir.exists() and not run_dir.is_dir()):
        return _damaged(f"job folder {run_dir} is not a folder of the sweep (a link or a file); "
                        "cobel does not follow links out of a sweep folder")  # fmt: skip
    try:
        repaired = repair_run(run_dir)
    except CobelError as exc:
        return _damaged(str(exc))
    job, job_problem = _read_checked(run_dir / JOB_FILE, read_job_file)
    manifest, problem = _read_checked(RunFolder(run_dir).manifest, read_manifest)
    problem = problem or job_problem
    if problem:
        return _damaged(problem, job, manifest)
    if job.get("status") == "running" and (
        repaired.get("status") == "interrupted" or not _job_process_alive(job)
    ):  # killed: after its last file (then it is complete), or before (its manifest repaired)
        job = write_job_status(run_dir, "completed" if is_complete(run_dir) else "interrupted")
    if job.get("status") == "queued" and not launcher_alive(job):
        # the launcher that queued it is gone (SIGKILL, a crash): it will never start
        job = write_job_status(run_dir, "interrupted", error=NOT_STARTED.format(
            pid=job.get("launcher_pid")))  # fmt: skip
    manifest = _read_checked(RunFolder(run_dir).manifest, read_manifest)[0]
    if job.get("status") == "queued":
        status = "queued"
    elif is_complete(run_dir, manifest=manifest):
        status = "done"
        folder = RunFolder(run_dir)
        for table in folder.tables():  # footers and row counts: a table cut short is no result
            try:
                check_table(folder.table(table), columns=[])
            except CobelError as exc:
                return _damaged(str(exc), job, manifest)
    elif job.get("status") == "failed" or manifest.get("status") == "failed":
        status = "failed"
    elif job.get("status") == "interrupted" or manifest.get("status") == "interrupted":
        status = "interrupted"
    elif job or manifest:
        status = "running"
    else:
        status = "missing"
    error = None
    if status == "failed":
        error = job.get("error") or manifest.get("error")
    elif status == "interrupted" and not manifest:  # never started: say why
        error = job.get("error")
    return {
        "status": status,
        "error": error,
        "config_hash": manifest.get("config_hash") or job.get("config_hash"),
        "duration_s": manifest.get("duration_s", job.get("duration_s")),
        "host": job.get("host", manifest.get("hostname")),
        "ended_at": job.get("ended_at", manifest.get("ended_at")),
    }


def _damaged(problem: str, job: Mapping[str, Any] | None = None,
             manifest: Mapping[str, Any] | None = None) -> dict[str, Any]:  # fmt: skip
    """The state of a job whose files cannot be trusted: ``failed``, the problem as its error
    (a job with a damaged file is never ``done``; running the sweep again redoes it)."""
    job, manifest = job or {}, manifest or {}
    return {"status": "failed", "error": problem, "config_hash": None,
            "duration_s": None, "host": job.get("host", manifest.get("hostname")),
            "ended_at": job.get("ended_at", manifest.get("ended_at"))}  # fmt: skip


def job_dir(sweep_dir: Path, job: int) -> Path:
    return sweep_dir / str(job)


def check_job_dir(path: Path) -> Path:
    """``path`` if it is a job folder a launcher may write into (missing, or a real folder);
    a CobelError for a link or a file there: a job's outputs are removed before it runs
    again, and a link would have them removed elsewhere."""
    if path.is_symlink() or (path.exists() and not path.is_dir()):
        raise CobelError(f"job folder {path} is a link or a file, not a folder of the sweep; "
                         "remove it, then run the sweep again")  # fmt: skip
    return path


INDEX_COLUMNS = ("status", "error", "config_hash", "duration_s", "host", "ended_at", "run_dir",
                 "overrides")  # fmt: skip


def job_rows(sweep_dir: str | os.PathLike[str], *, write: bool = True) -> list[dict[str, Any]]:
    """The job index of a sweep folder as rows (and ``jobs.csv`` when ``write``).

    Keys: ``job``, one per swept key, ``status`` (done / failed / interrupted / running /
    queued / missing), ``error``, ``config_hash``, ``duration_s``, ``host``, ``ended_at``,
    ``run_dir``, ``overrides``. Plain Python (no pandas), so a sweep's launcher process and
    ``cobel status`` stay quick; :func:`index` gives the same as a data frame.
    """
    import csv

    sweep_dir = Path(sweep_dir)
    sweep = read_sweep(sweep_dir)
    rows = []
    for j in sweep["jobs"]:
        d = job_dir(sweep_dir, j["job"])
        row: dict[str, Any] = {"job": j["job"]}
        row.update({k: _cell(j["params"].get(k)) for k in sweep["swept"]})
        row.update(job_state(d))
        row["run_dir"] = str(d)
        row["overrides"] = " ".join(j["overrides"])
        rows.append(row)
    if write:
        from cobelrun.io.atomic import atomic_path, disk_error, is_disk_error

        try:
            with atomic_path(sweep_dir / INDEX_FILE) as tmp:
                with tmp.open("w", newline="", encoding="utf-8") as f:
                    fields = ["job", *sweep["swept"], *INDEX_COLUMNS]
                    writer = csv.DictWriter(f, fieldnames=fields)
                    writer.writeheader()
                    writer.writerows(rows)
        except OSError as exc:  # a full or read-only disk: the index is a cache, say so and go on
            if not is_disk_error(exc):
                raise
            print(f"cobel: warning: {disk_error(exc, sweep_dir / INDEX_FILE)}; the job index "
                  "was not rewritten (the status below is read from the job folders)",
                  file=sys.stderr)  # fmt: skip
    return rows


def index(sweep_dir: str | os.PathLike[str], *, write: bool = True):
    """The job index of a sweep folder as a data frame (and ``jobs.csv`` when ``write``).

    Columns: those of :func:`job_rows`, in the same order as ``jobs.csv``.
    """
    import pandas as pd

    rows = job_rows(sweep_dir, write=write)
    swept = read_sweep(Path(sweep_dir))["swept"]
    return pd.DataFrame(rows, columns=["job", *swept, *INDEX_COLUMNS])


def _cell(value: Any) -> Any:
    return json.dumps(value) if isinstance(value, list | dict) else value


def summary(jobs: Any) -> dict[str, int]:
    """Counts of each status in a job index (rows from :func:`job_rows` or its data frame)."""
    statuses = list(jobs["status"]) if hasattr(jobs, "columns") else [r["status"] for r in jobs]
    return {s: statuses.count(s) for s in STATUSES}
