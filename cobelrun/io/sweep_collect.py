"""``cobel collect``: the tables of a sweep's done jobs streamed into one Parquet file per
table (``SWEEP_DIR/collected/<table>.parquet``), with ``job`` and the swept values as columns.

Reads the sweep folder through :mod:`cobelrun.io.sweep_folder` (which jobs are done) and each
job's tables through :mod:`cobelrun.io.validate` (footers, page checksums) before combining.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from cobelrun.errors import CobelError
from cobelrun.io.run_folder import RunFolder
from cobelrun.io.sweep_folder import COLLECTED_DIR, job_dir, job_rows, read_sweep


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
