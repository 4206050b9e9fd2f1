"""Load results: run folders (``cobel run``), sweeps (``cobel run -m``) and collected sweeps.

``load_run`` (one run), ``load_sweep`` (every done job of a sweep, swept params as columns),
``load_collected`` (the Parquet files of ``cobel collect``), ``load_jobs`` (a sweep's job index).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pandas as pd

from cobelrun.errors import CobelError
from cobelrun.io.run_folder import RunFolder
from cobelrun.io.validate import check_table, read_manifest


def _run_dir(path: str | Path) -> RunFolder:
    folder = RunFolder(path)
    if not folder.path.is_dir():
        raise CobelError(f"run folder {folder.path} does not exist")
    if not folder.table("trials").is_file():
        raise CobelError(f"{folder.path} is not a cobel run folder (no trials table)")
    return folder


def load_table(path: str | Path, table: str = "trials") -> pd.DataFrame:
    """One table of a run folder: ``trials``, ``steps``, ``activity`` or any table a monitor
    declared."""
    folder = _run_dir(path)
    p = folder.table(table)
    if not p.is_file():
        have = ", ".join(folder.tables()) or "none"
        raise CobelError(f"{folder.path} has no '{table}' table; it has: {have}")
    check_table(p)  # footer, row counts and the memory it takes, before it is read
    try:
        return pd.read_parquet(p, page_checksum_verification=True)
    except Exception as exc:  # a damaged page the footer does not show
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CobelError(f"cannot read {p}: {first}") from None


def load_trials(path: str | Path) -> pd.DataFrame:
    """The ``trials`` table of a run folder."""
    return load_table(path, "trials")


def load_steps(path: str | Path) -> pd.DataFrame:
    """The ``steps`` table of a run folder (steps must have been recorded)."""
    return load_table(path, "steps")


def load_activity(path: str | Path) -> pd.DataFrame:
    """The ``activity`` table of a run folder (unit activations written by an activity monitor)."""
    return load_table(path, "activity")


def load_manifest(path: str | Path) -> dict[str, Any]:
    """The run's manifest, validated (:func:`cobelrun.io.validate.read_manifest`)."""
    p = _run_dir(path).manifest
    if not p.is_file():
        raise CobelError(f"{p.parent} has no {p.name}")
    return read_manifest(p)


def load_run(path: str | Path, table: str = "trials") -> pd.DataFrame:
    """One table of a run folder (same as :func:`load_table`).

    Examples
    --------
    >>> trials = load_run("results/tmaze_extinction/2024-05-01/12-00-00_ab12cd34")  # doctest: +SKIP
    """
    return load_table(path, table)


def load_jobs(sweep_dir: str | Path) -> pd.DataFrame:
    """The job index of a sweep folder: job, swept params, status, error, config hash, run dir."""
    from cobelrun.io.sweep_folder import index

    return index(sweep_dir, write=False)


def load_sweep(sweep_dir: str | Path, table: str = "trials") -> pd.DataFrame:
    """One table of every done job of a sweep, with ``job`` and the swept params as columns.

    Reads ``SWEEP_DIR/collected/<table>.parquet`` when it is up to date (written by
    ``cobel collect`` after the last job ended), else combines the job folders in memory.
    For sweeps too large for memory, run ``cobel collect`` and use :func:`load_collected` with
    ``columns`` / ``filters``.
    """
    from cobelrun.io.manifest import DONE_MARKER
    from cobelrun.io.sweep_collect import collect
    from cobelrun.io.sweep_folder import COLLECTED_DIR, index

    sweep_dir = Path(sweep_dir)
    jobs = index(sweep_dir, write=False)
    done = jobs[jobs["status"] == "done"]
    if done.empty:
        raise CobelError(f"no job of {sweep_dir} is done yet; see `cobel status {sweep_dir}`")
    collected = sweep_dir / COLLECTED_DIR / f"{table}.parquet"
    newest = max((Path(d) / DONE_MARKER).stat().st_mtime for d in done["run_dir"])
    if collected.is_file() and collected.stat().st_mtime >= newest:
        frame = pd.read_parquet(collected)
        if set(frame["job"].unique()) == set(done["job"].astype(int)):
            return frame
    import tempfile

    with tempfile.TemporaryDirectory(prefix=".cobel-collect-", dir=sweep_dir) as tmp:
        files = collect(sweep_dir, [table], out_dir=tmp)
        if table not in files:
            raise CobelError(f"no done job of {sweep_dir} has a {table} table")
        return pd.read_parquet(files[table])


def load_collected(
    path: str | Path,
    table: str = "trials",
    *,
    columns: list[str] | None = None,
    filters: Any = None,
) -> pd.DataFrame:
    """A table written by ``cobel collect``: ``path`` is the sweep folder, its ``collected/``
    folder or the Parquet file. ``columns`` and ``filters`` (pyarrow syntax, e.g.
    ``[("seed", "==", 3)]``) read only what is needed."""
    from cobelrun.io.sweep_folder import COLLECTED_DIR

    p = Path(path)
    if p.is_dir() and (p / COLLECTED_DIR).is_dir():
        p = p / COLLECTED_DIR
    if p.is_dir():
        p = p / f"{table}.parquet"
    if not p.is_file():
        raise CobelError(f"{p} does not exist; run `cobel collect SWEEP_DIR` first")
    check_collected(p)
    try:
        return pd.read_parquet(p, columns=columns, filters=filters, page_checksum_verification=True)
    except Exception as exc:  # a column or filter the file lacks, or a damaged file
        raise CobelError(f"cannot read {p}: {str(exc).strip().splitlines()[0]}") from None


def check_collected(path: str | Path) -> dict[str, str]:
    """Check a file written by ``cobel collect`` before trusting it; returns its swept columns.

    It must be a readable Parquet file whose metadata names its swept columns
    (``cobel.swept``), with an int32 ``job`` column first, every swept column present, and
    the key columns of a run table (``run``, ``trial``) as integers. Anything else (a file
    from elsewhere, one cut short, a schema edited by hand) is a one-line CobelError naming
    the file and the command that rewrites it.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    p = Path(path)
    again = f"rewrite it with `cobel collect {p.parent.parent}`"
    try:
        schema = pq.read_schema(p)
    except Exception as exc:
        raise CobelError(f"{p} is not a readable Parquet file ({str(exc).splitlines()[0]}); "
                         f"{again}") from None  # fmt: skip
    meta = schema.metadata or {}
    try:
        swept = json.loads(meta[b"cobel.swept"])
        assert isinstance(swept, dict)
    except (KeyError, ValueError, AssertionError):
        raise CobelError(f"{p} was not written by `cobel collect` (no cobel.swept metadata); "
                         f"{again}") from None  # fmt: skip
    names = schema.names
    if not names or names[0] != "job" or not pa.types.is_int32(schema.field("job").type):
        raise CobelError(f"{p}: the first column must be 'job' (int32); {again}")
    missing = [c for c in swept if c not in names]
    if missing:
        raise CobelError(f"{p} lacks the swept columns {missing}; {again}")
    for key in ("run", "trial"):
        if key in names and not pa.types.is_integer(schema.field(key).type):
            raise CobelError(
                f"{p}: column '{key}' must hold integers, not {schema.field(key).type}; {again}"
            )
    return swept
