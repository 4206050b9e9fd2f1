"""Sweep folders: job status files, the job index, completion checks and ``cobel collect``.

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
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import socket
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from cobelrun.errors import CobelError
from cobelrun.io.manifest import DONE_MARKER, _write_json_atomic, config_hash
from cobelrun.io.repair import pid_alive
from cobelrun.io.run_folder import RunFolder

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


def read_json(path: Path) -> dict[str, Any] | None:
    """A JSON object file's content, or None when it is missing, unreadable or not an object
    (:func:`cobelrun.io.validate.read_json_object`: size bounded, nesting bounded). Callers
    that must tell a damaged file from a missing one use :mod:`cobelrun.io.validate`."""
    from cobelrun.io.validate import read_json_object

    try:
        return read_json_object(path) if path.is_file() else None
    except CobelError:
        return None


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


# -- the sweep definition ---------------------------------------------------------------------


def override_key(override: Any) -> str:
    """Column name for a parsed Hydra override (``agent.epsilon``, ``seed``, ``agent``)."""
    key = str(override.key_or_group)
    return f"{key}@{override.package}" if override.package else key


def is_hydra_key(key: str) -> bool:
    k = key.lstrip("+~")
    return k == "hydra" or k.startswith(("hydra.", "hydra/"))


def plan(overrides: Sequence[str], extra: Sequence[str] = ()) -> tuple[list[str], list[dict]]:
    """Expand sweep overrides into jobs: (swept keys, [{job, overrides, params}, ...]).

    Jobs come in Hydra's BasicSweeper order (cartesian product, last key fastest); ``params``
    holds each job's value of every swept key, typed (int, float, str, bool, None, list, dict).
    """
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    parsed = parser.parse_overrides([*extra, *overrides])
    check_job_count(parsed)
    swept = []
    for o in parsed:
        if o.is_sweep_override() and not is_hydra_key(o.key_or_group):
            swept.append(override_key(o))
    combos = cartesian(parsed)
    jobs = []
    for i, combo in enumerate(combos):
        params: dict[str, Any] = {}
        for o in parser.parse_overrides(list(combo)):
            key = override_key(o)
            if key in swept:
                params[key] = _plain_value(o.value())
        jobs.append({"job": i, "overrides": list(combo), "params": params})
    return swept, jobs


#: the environment variable that raises (or lowers) the largest sweep cobel expands
MAX_JOBS_ENV = "COBEL_MAX_JOBS"
#: default largest number of jobs of one sweep (each job is a folder and a row of sweep.json)
MAX_JOBS = 100_000


def max_jobs() -> int:
    """The largest sweep cobel expands: ``$COBEL_MAX_JOBS`` or :data:`MAX_JOBS`."""
    raw = os.environ.get(MAX_JOBS_ENV, "").strip()
    if not raw:
        return MAX_JOBS
    if not raw.isdigit() or int(raw) < 1:
        raise CobelError(f"{MAX_JOBS_ENV} must be a positive whole number, got {raw!r}")
    return int(raw)


def _n_values(o: Any) -> int:
    """How many values a parsed sweep override takes, counted without listing them."""
    import math as _math

    value = o.value()
    if type(value).__name__ == "RangeSweep":  # hydra.core.override_parser.types.RangeSweep
        start, stop, step = value.start, value.stop, value.step or 1
        return max(0, _math.ceil((stop - start) / step))
    items = getattr(value, "list", None)
    if isinstance(items, list):
        return len(items)
    return 1  # a glob over a config group: a handful of files


def check_job_count(parsed: Sequence[Any]) -> int:
    """The number of jobs of a sweep, counted from its parsed overrides before anything is
    expanded; above :func:`max_jobs` a one-line CobelError names the largest swept key and
    how to raise the limit (``COBEL_MAX_JOBS``)."""
    counts: dict[str, int] = {}
    for o in parsed:
        if o.is_sweep_override() and o.is_discrete_sweep():
            counts[o.get_key_element()] = _n_values(o)
        else:
            counts.pop(o.get_key_element(), None)
    total = 1
    for n in counts.values():
        total *= n
    limit = max_jobs()
    if total > limit:
        key = max(counts, key=lambda k: counts[k])
        raise CobelError(
            f"this sweep has {total:,} jobs ({' x '.join(f'{k}: {n:,}' for k, n in counts.items())}"
            f"), more than the {limit:,} cobel expands; sweep fewer values of {key} or raise the "
            f"limit with {MAX_JOBS_ENV}={total}"
        )
    return total


def cartesian(parsed: Sequence[Any]) -> list[list[str]]:
    """Every job's overrides for parsed Hydra overrides, as Hydra's basic sweeper makes them.

    The cartesian product of the swept values (``a=1,2``, ``range(...)``, ``choice(...)``),
    the last key varying fastest; a key given twice keeps its first position and its last
    value. Only the public ``Override`` API is used (Hydra 1.3's ``BasicSweeper`` lives in a
    private module); ``tests/test_sweep.py`` checks the order against Hydra's.
    """
    import itertools

    from cobelrun.errors import ConfigError

    values: dict[str, list[str]] = {}
    for o in parsed:
        key = o.get_key_element()
        if not o.is_sweep_override():
            values[key] = [f"{key}={o.get_value_element_as_str()}"]
        elif o.is_discrete_sweep():
            values[key] = [f"{key}={v}" for v in o.sweep_string_iterator()]
        else:
            raise ConfigError(
                f"cannot sweep {o.input_line!r} with cobel's sweeper: it takes lists (a=1,2), "
                "range(...) and choice(...); an interval needs a sampling sweeper such as "
                "hydra/sweeper=optuna"
            )
    return [list(c) for c in itertools.product(*values.values())]


def _plain_value(value: Any) -> Any:
    from omegaconf import OmegaConf

    if OmegaConf.is_config(value):
        return OmegaConf.to_container(value)
    if isinstance(value, Mapping):
        return {str(k): _plain_value(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain_value(v) for v in value]
    return value


def sweep_id(jobs: Iterable[Mapping[str, Any]]) -> str:
    """A short hash naming a sweep: the same jobs (overrides, order) give the same id.

    Hydra settings (``hydra.*``, ``hydra/launcher=...``) are left out, so changing the launcher or
    the number of workers resumes the same sweep.
    """
    norm = [sorted(o for o in j["overrides"] if not is_hydra_key(o.split("=", 1)[0])) for j in jobs]
    return hashlib.sha256(json.dumps(norm).encode()).hexdigest()[:10]


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


# -- collect ----------------------------------------------------------------------------------


def _param_type(values: list[Any]):
    import pyarrow as pa

    if any(isinstance(v, list | dict) for v in values):
        return pa.string(), [None if v is None else json.dumps(v) for v in values]
    try:
        arr = pa.array(values)
    except (pa.ArrowInvalid, pa.ArrowTypeError, OverflowError):
        return pa.string(), [None if v is None else str(v) for v in values]
    if pa.types.is_null(arr.type):
        return pa.string(), values
    return arr.type, values


def collect(
    sweep_dir: str | os.PathLike[str],
    tables: Sequence[str] = ("trials", "steps"),
    *,
    out_dir: str | os.PathLike[str] | None = None,
    batch_rows: int = 65_536,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Path]:
    """Stream the tables of every done job into one Parquet file per table.

    The output (``SWEEP_DIR/collected/<table>.parquet``) has ``job`` and one column per swept
    key in front of the run's own columns. Files are read and written in record batches of at
    most ``batch_rows`` rows, so memory stays flat however large the sweep. Jobs that are not
    done are left out (``cobel status`` lists them). Columns missing in some jobs are null there.

    Returns the written files by table name (tables no done job has are skipped).
    """
    from cobelrun.io.atomic import disk_error

    sweep_dir = Path(sweep_dir)
    out = Path(out_dir) if out_dir is not None else sweep_dir / COLLECTED_DIR
    if out_dir is None and (out.is_symlink() or (out.exists() and not out.is_dir())):
        raise CobelError(f"{out} is not a folder of the sweep (a link or a file); remove it or "
                         "give --out")  # fmt: skip
    try:
        return _collect(sweep_dir, tables, out, batch_rows, progress)
    except OSError as exc:  # a full or read-only disk, a folder that cannot be made
        raise CobelError(disk_error(exc, out)) from None


def _collect(
    sweep_dir: Path,
    tables: Sequence[str],
    out: Path,
    batch_rows: int,
    progress: Callable[[int, int], None] | None,
) -> dict[str, Path]:
    import pyarrow as pa
    import pyarrow.parquet as pq

    from cobelrun.io.validate import check_table

    rows = job_rows(sweep_dir)
    sweep = read_sweep(sweep_dir)
    jobs = [int(r["job"]) for r in rows if r["status"] == "done"]
    if not jobs:
        raise CobelError(f"no job of {sweep_dir} is done yet; see `cobel status {sweep_dir}`")
    out.mkdir(parents=True, exist_ok=True)
    params = {j["job"]: j["params"] for j in sweep["jobs"]}
    ptypes: dict[str, Any] = {}
    pvalues: dict[str, dict[int, Any]] = {}
    for key in sweep["swept"]:
        t, vals = _param_type([params[j].get(key) for j in jobs])
        ptypes[key] = t
        pvalues[key] = dict(zip(jobs, vals, strict=True))
    written: dict[str, Path] = {}
    total = sum(
        1 for t in tables for j in jobs if RunFolder(job_dir(sweep_dir, j)).table(t).is_file()
    )
    n = 0
    for table in tables:
        files = [(j, RunFolder(job_dir(sweep_dir, j)).table(table)) for j in jobs]
        files = [(j, f) for j, f in files if f.is_file()]
        if not files:
            continue
        for _, f in files:  # footers and row counts before anything is combined
            check_table(f, columns=[])
        try:
            data_schema = pa.unify_schemas(
                [pq.read_schema(f) for _, f in files], promote_options="permissive"
            )
        except (pa.ArrowInvalid, pa.ArrowTypeError, OSError) as exc:
            raise CobelError(f"cannot combine the {table} tables of {sweep_dir}: {exc}") from None
        taken = set(data_schema.names)
        names = {k: (k if k not in taken and k != "job" else f"param:{k}") for k in ptypes}
        fields = [pa.field("job", pa.int32())]
        fields += [pa.field(names[k], t) for k, t in ptypes.items()]
        fields += [f.with_metadata(None) for f in data_schema]
        schema = pa.schema(fields, metadata={
            b"cobel.swept": json.dumps({names[k]: k for k in ptypes}).encode(),
            b"cobel.sweep_dir": str(sweep_dir.resolve()).encode(),
        })  # fmt: skip
        target = out / f"{table}.parquet"
        tmp = out / f".{table}.parquet.{os.getpid()}.tmp"
        try:
            with pq.ParquetWriter(
                tmp, schema, compression="zstd", write_page_checksum=True
            ) as writer:
                for j, f in files:
                    for batch in _batches(f, batch_rows):
                        rows = batch.num_rows
                        cols = [pa.array([j] * rows, pa.int32())]
                        cols += [pa.array([pvalues[k][j]] * rows, t) for k, t in ptypes.items()]
                        for field in data_schema:
                            i = batch.schema.get_field_index(field.name)
                            if i < 0:
                                cols.append(pa.nulls(rows, field.type))
                            else:
                                cols.append(batch.column(i).cast(field.type))
                        writer.write_batch(pa.RecordBatch.from_arrays(cols, schema=schema))
                    n += 1
                    if progress is not None:
                        progress(n, total)
            os.replace(tmp, target)
        finally:
            if tmp.exists():
                tmp.unlink()
        written[table] = target
    return written


def _batches(path: Path, batch_rows: int) -> Any:
    """Record batches of a job's table; a damaged page is one line naming the file."""
    import pyarrow.parquet as pq

    try:
        pf = pq.ParquetFile(path, page_checksum_verification=True)
        yield from pf.iter_batches(batch_size=batch_rows)
    except Exception as exc:  # ArrowInvalid, Arrow's IOError: a corrupt page, a bad encoding
        if isinstance(exc, OSError) and exc.errno is not None:
            raise  # the disk itself
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CobelError(f"{path} is damaged ({first}); run its job again") from None


# -- stopping a sweep and keeping it to one launcher ----------------------------------------------

#: written by the launcher when it is asked to stop (Ctrl-C, SIGTERM); jobs that start later see
#: it and stop at once, marked ``interrupted``
STOP_FILE = ".stop"
#: the advisory lock (``fcntl.flock``) a launcher holds on its sweep folder; holds its pid
LOCK_FILE = ".lock"


class SweepLock:
    """An exclusive advisory lock on a sweep folder, held while one ``cobel run -m`` launches it.

    A second launcher into the same folder is refused with the holder's pid instead of running
    the same jobs twice (each overwriting the other's files). The lock is the kernel's
    (``fcntl.flock``): it goes away with the process that holds it, also on SIGKILL, so a stale
    lock file never blocks a resume.
    """

    def __init__(self, sweep_dir: str | os.PathLike[str]) -> None:
        self.path = Path(sweep_dir) / LOCK_FILE
        self._fd: int | None = None

    def acquire(self) -> SweepLock:
        import fcntl

        if self.path.parent.is_dir():  # job folders a launcher clears: never through a link
            for entry in self.path.parent.iterdir():
                if entry.name.isdigit():
                    check_job_dir(entry)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = ""
            try:
                holder = os.pread(fd, 200, 0).decode("utf-8", "replace").strip()
            finally:
                os.close(fd)
            pid, _, host = holder.partition(" ")
            who = (f"pid {pid}" + (f" on {host}" if host else "")) if pid else "pid unknown"
            raise CobelError(
                f"sweep folder {self.path.parent} is in use by another `cobel run -m` ({who}); "
                "wait for it to finish or stop it, then run the command again to resume"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()} {socket.gethostname()}\n".encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            import fcntl

            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> SweepLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


def stop_requested(sweep_dir: Path) -> bool:
    """True once the sweep's launcher was asked to stop."""
    return (Path(sweep_dir) / STOP_FILE).exists()


def request_stop(sweep_dir: Path, reason: str) -> None:
    """Tell jobs that have not started yet not to start (idempotent)."""
    path = Path(sweep_dir) / STOP_FILE
    if not path.exists():
        try:
            _write_json_atomic(path, {"reason": reason, "pid": os.getpid(), "at": _now()})
        except OSError:
            pass


def clear_stop(sweep_dir: Path) -> None:
    (Path(sweep_dir) / STOP_FILE).unlink(missing_ok=True)


def running_pids(sweep_dir: Path, jobs: Iterable[int]) -> dict[int, int]:
    """job -> pid of each job whose ``job.json`` says it is running in a live process here."""
    out = {}
    host = socket.gethostname()
    for num in jobs:
        state = read_json(job_dir(sweep_dir, num) / JOB_FILE) or {}
        pid = state.get("pid")
        if state.get("status") == "running" and state.get("host") == host and isinstance(pid, int):
            if pid != os.getpid() and pid_alive(pid):
                out[num] = pid
    return out


def mark_not_started(sweep_dir: Path, jobs: Iterable[int], reason: str) -> int:
    """Mark jobs still ``queued`` as ``interrupted`` (they never started); returns how many."""
    n = 0
    for num in jobs:
        d = job_dir(sweep_dir, num)
        if (read_json(d / JOB_FILE) or {}).get("status") == "queued":
            write_job_status(d, "interrupted", error=reason)
            n += 1
    return n


#: the environment variable through which a sweep's launcher tells its workers its pid
LAUNCHER_ENV = "COBEL_SWEEP_LAUNCHER"
#: the launcher's pid, in a worker process (set by :func:`worker_init`)
_PARENT_PID: int | None = None
#: True while a worker runs a job (:func:`cobelrun.hydra_app.sweep_job`): a signal then is the
#: job's to handle, and the worker does not exit between its files and its ``job.json``
IN_JOB = False


def launcher_gone() -> bool:
    """In a sweep worker: True once the launcher that started it has ended."""
    return _PARENT_PID is not None and os.getppid() != _PARENT_PID


def worker_init() -> None:
    """Initializer of sweep worker processes (joblib/loky).

    * An idle worker ignores SIGINT and SIGTERM: a Ctrl-C in the terminal reaches every process
      of the group, and a worker that died of it between jobs would make the pool kill the
      others while they finish their files. A running job takes the signals itself
      (:class:`cobelrun.recorder.SignalGuard`) and stops cleanly.
    * The worker stops when the launcher ends, however it ends (even SIGKILL), so none is
      orphaned: the launcher's pid comes from :data:`LAUNCHER_ENV` (set before the pool starts),
      so a worker whose launcher died while the worker was still starting exits at once;
      on Linux the kernel sends SIGTERM when the launcher dies (``PR_SET_PDEATHSIG``), and a
      watchdog thread sends it too once the worker's parent is no longer the launcher (the
      kernel's signal is tied to the thread that spawned the worker, and is not sent when that
      thread ends before the launcher). A running job then stops cleanly and its worker exits;
      an idle worker exits at once.
    """
    import signal
    import threading

    global _PARENT_PID
    try:
        _PARENT_PID = int(os.environ[LAUNCHER_ENV])
    except (KeyError, ValueError):
        _PARENT_PID = os.getppid()

    def idle(signum: int, frame: Any) -> None:
        if launcher_gone() and not IN_JOB:  # the launcher is gone: do not linger as an orphan
            os._exit(128 + signum)

    signal.signal(signal.SIGINT, idle)
    signal.signal(signal.SIGTERM, idle)
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        pr_set_pdeathsig = 1
        libc.prctl(pr_set_pdeathsig, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError):
        pass
    if launcher_gone():  # the launcher died before the worker got here
        os._exit(1)
    threading.Thread(target=_watch_launcher, name="cobel-launcher-watch", daemon=True).start()


def _watch_launcher(poll: float = 0.5, grace: float = 300.0) -> None:
    """Worker thread: once the launcher is gone, SIGTERM this process each second (a running
    job closes its files, an idle worker exits); if it still lives ``grace`` seconds later,
    end it.

    Once is not enough: a signal that lands while a job finishes its files is ignored by
    design (:meth:`cobelrun.signals.SignalGuard.closing`), and the job then completes and
    hands its worker back to a pool whose launcher is gone (it would wait for its next job
    until loky's idle timeout, holding the sweep's stdout open)."""
    import signal
    import time

    while not launcher_gone():
        time.sleep(poll)
    deadline = time.monotonic() + grace
    while time.monotonic() < deadline:
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(1.0)
    os._exit(143)
