"""Validated readers for the files of run and sweep folders: run folders are data, not code.

Run folders are shared (a colleague reruns yours, a paper's folder sits on a data server), so
every file cobel reads from one is checked before it is used, and a bad one is one
:class:`~cobelrun.errors.CobelError` line naming the file and the problem (never a
traceback, never a silently wrong answer):

* JSON files (``manifest.json``, ``job.json``, ``sweep.json``, ``world.json``): size
  bounded before they are read (:data:`MAX_JSON_BYTES`), parsed, and checked against a schema
  (pydantic models, strict types; fields cobel does not read are kept as they are);
* ``world.json`` (:func:`read_world`): finite coordinates of the right widths, a positive
  cell size, regions with their coordinates, graph edges between existing nodes, and a grid no
  larger than :data:`MAX_GRID_BINS` cells (a plot allocates one bin per cell);
* Parquet tables (:func:`check_table`): the footer is read and checked (row groups add up to
  the file's row count, every column chunk lies inside the file) and what the table would
  take in memory is estimated with :func:`cobelrun.safety.check_allocation` before it is read;
* ``.npy`` members of ``.npz`` archives (:func:`npz_member_header`): shape and dtype from the
  header alone, so a member that would decompress to gigabytes is refused before anything is
  allocated.

Every reader of a run or sweep folder goes through these functions.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import zipfile
from pathlib import Path
from typing import IO, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from cobelrun.errors import CobelError

__all__ = [
    "MAX_GRID_BINS",
    "MAX_JOBS_IN_FILE",
    "MAX_JSON_BYTES",
    "FolderFileError",
    "check_mcap",
    "check_table",
    "npz_member_header",
    "read_job_file",
    "read_json_object",
    "read_manifest",
    "read_sweep_file",
    "read_world",
]

#: largest JSON file of a run or sweep folder cobel reads (a sweep.json of 100,000 jobs is
#: ~40 MB; a manifest a few KB)
MAX_JSON_BYTES = 256 << 20
#: largest number of grid cells a world.json may span (one occupancy bin per cell)
MAX_GRID_BINS = 10_000_000
#: most jobs a sweep.json may list
MAX_JOBS_IN_FILE = 1_000_000
#: nesting deeper than this in a JSON file is refused (Python's parser would recurse)
MAX_JSON_DEPTH = 200


class FolderFileError(CobelError):
    """A file of a run or sweep folder is missing, unreadable or not what cobel wrote."""


def _short(text: str, n: int = 160) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= n else text[: n - 3] + "..."


# -- JSON ---------------------------------------------------------------------------------------
def _depth_ok(text: str) -> bool:
    """False when brackets nest deeper than :data:`MAX_JSON_DEPTH` (checked on the raw text,
    ignoring strings, before the recursive parser sees it)."""
    depth = 0
    in_str = esc = False
    for ch in text:
        if in_str:
            if esc:
                esc = False
            elif ch == "\\":
                esc = True
            elif ch == '"':
                in_str = False
        elif ch == '"':
            in_str = True
        elif ch in "[{":
            depth += 1
            if depth > MAX_JSON_DEPTH:
                return False
        elif ch in "]}":
            depth -= 1
    return True


def _reject_constant(name: str) -> float:
    raise ValueError(f"{name} is not valid JSON")


def read_json_file(path: str | os.PathLike[str], what: str = "") -> Any:
    """The parsed content of a JSON file of a run or sweep folder, or a FolderFileError
    naming the file: missing, not a regular file, larger than :data:`MAX_JSON_BYTES`, not
    UTF-8, not JSON (``NaN``/``Infinity`` included), nested too deep."""
    p = Path(path)
    label = f"{p}" + (f" ({what})" if what else "")
    try:
        if not p.is_file():
            raise FolderFileError(f"{label} is missing or not a regular file")
        size = p.stat().st_size
        if size > MAX_JSON_BYTES:
            raise FolderFileError(
                f"{label} is {size:,} bytes, more than the {MAX_JSON_BYTES:,} a cobel folder's "
                "JSON file may have; it was not written by cobel"
            )
        with open(p, "rb") as f:  # bounded also where the size lies (/proc, a growing file)
            raw = f.read(MAX_JSON_BYTES + 1)
        if len(raw) > MAX_JSON_BYTES:
            raise FolderFileError(f"{label} holds more than {MAX_JSON_BYTES:,} bytes")
    except OSError as exc:
        raise FolderFileError(f"cannot read {label}: {exc.strerror or exc}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise FolderFileError(f"{label} is not UTF-8 text (damaged or not a JSON file)") from None
    if not _depth_ok(text):
        raise FolderFileError(f"{label} nests deeper than {MAX_JSON_DEPTH} levels")
    try:
        return json.loads(text, parse_constant=_reject_constant)
    except (ValueError, RecursionError) as exc:
        where = f" at line {exc.lineno}" if isinstance(exc, json.JSONDecodeError) else ""
        msg = exc.msg if isinstance(exc, json.JSONDecodeError) else str(exc)
        cut = " (the file is cut short)" if not text.strip() or "Expecting" in msg else ""
        raise FolderFileError(f"{label} is not valid JSON{where}: {_short(msg)}{cut}") from None


def read_json_object(path: str | os.PathLike[str], what: str = "") -> dict[str, Any]:
    """:func:`read_json_file` of a file that must hold a JSON object."""
    data = read_json_file(path, what)
    if not isinstance(data, dict):
        raise FolderFileError(
            f"{path} must hold a JSON object, not {_json_kind(data)}"
            + (f" ({what})" if what else "")
        )
    return data


def read_json_or_none(path: str | os.PathLike[str]) -> dict[str, Any] | None:
    """A JSON object file's content, or None when it is missing, unreadable or not an object
    (:func:`read_json_object`: size bounded, nesting bounded). Callers that must tell a damaged
    file from a missing one use :func:`read_json_object` or the file's own reader."""
    p = Path(path)
    try:
        return read_json_object(p) if p.is_file() else None
    except CobelError:
        return None


def _json_kind(value: Any) -> str:
    return {list: "a list", str: "a string", int: "a number", float: "a number",
            bool: "a boolean", type(None): "null"}.get(type(value), type(value).__name__)  # fmt: skip


class _File(BaseModel):
    """Fields cobel reads are typed strictly; others are kept as they are."""

    model_config = ConfigDict(strict=True, extra="allow")


def _iso(value: str | None) -> str | None:
    if value is not None:
        try:
            _dt.datetime.fromisoformat(value)
        except ValueError:
            raise ValueError("must be an ISO 8601 time such as 2024-05-01T12:00:00+00:00") from None
    return value


def _finite_or_text(value: float | str | None) -> float | str | None:
    """A number, or the text cobel writes for NaN/inf (``'nan'``, ``'inf'``, ``'-inf'``)."""
    if isinstance(value, str):
        if value not in ("nan", "inf", "-inf"):
            raise ValueError("must be a number (or 'nan', 'inf', '-inf')")
    elif isinstance(value, float) and not math.isfinite(value):
        raise ValueError("must be finite")
    return value


NonNegative = Field(default=None, ge=0)


class ManifestFile(_File):
    """``manifest.json`` (:class:`cobelrun.io.manifest.Manifest`)."""

    status: Literal["running", "completed", "interrupted", "failed"]
    task: str | None = None
    seed: int | None = None
    config_hash: str | None = None
    config: dict[str, Any] | None = None
    error: str | None = None
    pid: int | None = None
    hostname: str | None = None
    cwd: str | None = None
    command: list[str] | None = None
    started_at: str | None = None
    ended_at: str | None = None
    duration_s: float | None = NonNegative
    wall_time_s: float | None = NonNegative
    objective: float | str | None = None
    objective_name: str | None = None
    phase_wall_time_s: dict[str, float] | None = None
    runs: int | None = NonNegative
    trials: int | None = NonNegative
    killed: bool | None = None

    _iso_times = field_validator("started_at", "ended_at")(_iso)
    _objective = field_validator("objective")(_finite_or_text)


class JobFile(_File):
    """A sweep job's ``job.json`` (:func:`cobelrun.io.sweep_folder.write_job_status`)."""

    status: Literal["queued", "running", "completed", "failed", "interrupted"]
    job: int | None = Field(default=None, ge=0)
    overrides: list[str] | None = None
    config_hash: str | None = None
    pid: int | None = None
    host: str | None = None
    launcher_pid: int | None = None
    launcher_host: str | None = None
    error: str | None = None
    queued_at: str | None = None
    started_at: str | None = None
    ended_at: str | None = None
    duration_s: float | None = NonNegative

    _iso_times = field_validator("queued_at", "started_at", "ended_at")(_iso)


class SweepJob(_File):
    job: int = Field(ge=0, lt=MAX_JOBS_IN_FILE)
    overrides: list[str]
    params: dict[str, Any]


class SweepFile(_File):
    """A sweep folder's ``sweep.json`` (:func:`cobelrun.io.sweep_folder.write_sweep`)."""

    command: str = ""
    swept: list[str]
    jobs: list[SweepJob] = Field(max_length=MAX_JOBS_IN_FILE)
    n_jobs: int | None = NonNegative
    launches: int | None = NonNegative
    created_at: str | None = None
    updated_at: str | None = None

    _iso_times = field_validator("created_at", "updated_at")(_iso)

    @field_validator("jobs")
    @classmethod
    def _unique(cls, jobs: list[SweepJob]) -> list[SweepJob]:
        seen: set[int] = set()
        for j in jobs:
            if j.job in seen:
                raise ValueError(f"job {j.job} is listed twice")
            seen.add(j.job)
        return jobs


def _validated(path: Path, data: dict[str, Any], model: type[_File]) -> dict[str, Any]:
    try:
        model.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"]) or "the file"
        msg = err["msg"]
        if err["type"] == "literal_error":
            msg = f"{msg}, got {_short(repr(err.get('input')), 40)}"
        more = f" ({exc.error_count() - 1} more problems)" if exc.error_count() > 1 else ""
        raise FolderFileError(f"{path}: {where}: {_short(msg)}{more}") from None
    return data


def read_manifest(path: str | os.PathLike[str]) -> dict[str, Any]:
    """A run's ``manifest.json``, validated (a FolderFileError naming the file otherwise)."""
    p = Path(path)
    return _validated(p, read_json_object(p, "the run's manifest"), ManifestFile)


def read_job_file(path: str | os.PathLike[str]) -> dict[str, Any]:
    """A sweep job's ``job.json``, validated."""
    p = Path(path)
    return _validated(p, read_json_object(p, "the job's status"), JobFile)


def read_sweep_file(path: str | os.PathLike[str]) -> dict[str, Any]:
    """A sweep folder's ``sweep.json``, validated (job numbers unique non-negative integers,
    so every job folder is ``SWEEP_DIR/<number>``)."""
    p = Path(path)
    return _validated(p, read_json_object(p, "the sweep's definition"), SweepFile)


# -- world.json ---------------------------------------------------------------------------------
def _points(path: Path, key: str, value: Any, width: int) -> np.ndarray:
    """``value`` as an (n, width) float array of finite numbers, or a FolderFileError."""
    if value is None:
        return np.zeros((0, width))
    if not isinstance(value, list):
        raise FolderFileError(f"{path}: {key} must be a list of [{width} numbers], "
                              f"not {_json_kind(value)}")  # fmt: skip
    for i, row in enumerate(value):
        if (
            not isinstance(row, list)
            or len(row) != width
            or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in row)
        ):
            raise FolderFileError(
                f"{path}: {key}[{i}] must be a list of {width} numbers, got {_short(repr(row), 60)}"
            )
    arr = np.asarray(value, dtype=np.float64).reshape(-1, width)
    if not np.isfinite(arr).all():
        raise FolderFileError(f"{path}: {key} holds a number too large to be a coordinate")
    return arr


def _number(path: Path, key: str, value: Any, *, positive: bool = False) -> float:
    if not isinstance(value, int | float) or isinstance(value, bool):
        raise FolderFileError(f"{path}: {key} must be a number, not {_json_kind(value)}")
    x = float(value)
    if not math.isfinite(x) or (positive and x <= 0):
        raise FolderFileError(
            f"{path}: {key} must be a finite number"
            + (" > 0" if positive else "")
            + f", got {value}"
        )
    return x


def read_world(path: str | os.PathLike[str]) -> Any:
    """A run's ``world.json`` as a checked :class:`cobelrun.envs.base.Geometry`.

    Refused with one line naming the file and the key: wrong kind, bounds that are not four
    finite numbers in order, walls/cells/nodes/outline rows of the wrong width or with
    non-finite values, a cell size that is not a positive number, a grid of more than
    :data:`MAX_GRID_BINS` cells, edges between nodes that do not exist, regions without
    their coordinates, unknown keys.
    """
    from cobelrun.envs.base import Geometry

    p = Path(path)
    data = read_json_object(p, "the run's geometry")
    known = ("kind", "bounds", "walls", "cells", "cell_size", "nodes", "edges", "outline",
             "regions", "doors")  # fmt: skip
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise FolderFileError(f"{p}: unknown key {unknown[0]!r}; allowed: {', '.join(known)}")
    kind = data.get("kind")
    if kind not in Geometry.KINDS:
        raise FolderFileError(
            f"{p}: kind must be one of {', '.join(Geometry.KINDS)}, got {_short(repr(kind), 40)}"
        )
    bounds = _points(p, "bounds", [data.get("bounds")], 4)[0]
    x0, y0, x1, y1 = bounds.tolist()
    if x1 < x0 or y1 < y0:
        raise FolderFileError(
            f"{p}: bounds must be [xmin, ymin, xmax, ymax], got {[x0, y0, x1, y1]}"
        )
    walls = _points(p, "walls", data.get("walls"), 4)
    cells = _points(p, "cells", data.get("cells"), 2)
    nodes = _points(p, "nodes", data.get("nodes"), 2)
    outline = _points(p, "outline", data.get("outline"), 2)
    doors = _points(p, "doors", data.get("doors"), 6)  # absent in older run folders
    if len(doors) and not np.allclose(np.hypot(doors[:, 4], doors[:, 5]), 1.0, atol=1e-6):
        raise FolderFileError(f"{p}: doors must be [x0, y0, x1, y1, dx, dy] rows with (dx, dy) "
                              "a unit direction")  # fmt: skip
    cell_size = _number(p, "cell_size", data.get("cell_size", 1.0), positive=True)
    if len(cells):
        span = cells.max(axis=0) - cells.min(axis=0)
        nx, ny = (float(s) / cell_size + 1 for s in span)
        if nx * ny > MAX_GRID_BINS:
            raise FolderFileError(
                f"{p}: its cells span {nx:,.0f} x {ny:,.0f} cells of size {cell_size:g}, more "
                f"than the {MAX_GRID_BINS:,} a grid may have"
            )
    edges_raw = data.get("edges") or []
    if not isinstance(edges_raw, list) or not all(
        isinstance(e, list) and len(e) == 2 and all(type(i) is int for i in e) for e in edges_raw
    ):
        raise FolderFileError(f"{p}: edges must be a list of [node, node] integer pairs")
    edges = np.asarray(edges_raw, dtype=np.int64).reshape(-1, 2)
    if len(edges) and (edges.min() < 0 or edges.max() >= len(nodes)):
        raise FolderFileError(f"{p}: edges name nodes outside 0..{len(nodes) - 1}")
    regions = data.get("regions") or {}
    if not isinstance(regions, dict):
        raise FolderFileError(f"{p}: regions must be an object of named regions")
    checked: dict[str, dict[str, Any]] = {}
    for name, region in regions.items():
        checked[str(name)] = _region(p, f"regions.{name}", region)
    return Geometry(kind=kind, bounds=(x0, y0, x1, y1), walls=walls, cells=cells,
                    cell_size=cell_size, nodes=nodes, edges=edges, outline=outline,
                    regions=checked, doors=doors)  # fmt: skip


def _region(path: Path, key: str, region: Any) -> dict[str, Any]:
    if not isinstance(region, dict):
        raise FolderFileError(f"{path}: {key} must be an object, not {_json_kind(region)}")
    shape = region.get("shape", "point")
    if shape not in ("point", "circle", "polygon"):
        raise FolderFileError(f"{path}: {key}.shape must be point, circle or polygon, "
                              f"got {_short(repr(shape), 40)}")  # fmt: skip
    out = dict(region)
    if shape == "polygon":
        pts = _points(path, f"{key}.points", region.get("points"), 2)
        if len(pts) < 3:
            raise FolderFileError(f"{path}: {key}.points must hold at least 3 points")
        out["points"] = pts.tolist()
        return out
    for c in ("x", "y"):
        if c not in region:
            raise FolderFileError(f"{path}: {key} ({shape}) has no {c!r}")
        out[c] = _number(path, f"{key}.{c}", region[c])
    if shape == "circle":
        out["radius"] = _number(path, f"{key}.radius", region.get("radius"), positive=True)
    return out


# -- Parquet ------------------------------------------------------------------------------------
#: tables up to this size (uncompressed) are read whole by ``check_table(verify=True)``
VERIFY_BYTES = 256 << 20


def check_table(
    path: str | os.PathLike[str], *, columns: list[str] | None = None, verify: bool = False
) -> int:
    """Check a Parquet table's footer before it is read; returns its row count.

    The footer must parse, its row groups must add up to the file's row count, every column
    chunk must lie inside the file, and what reading ``columns`` (all by default) would take in
    memory must fit (:func:`cobelrun.safety.check_allocation`). A table cut short (a killed
    copy, a full disk) has no footer and is refused here. With ``verify``, a table of up to
    :data:`VERIFY_BYTES` is also read one row group at a time with its page checksums checked
    (cobel writes a CRC-32 per page), so a flipped byte in its data is found too.
    """
    import pyarrow.parquet as pq

    from cobelrun.safety import check_allocation

    p = Path(path)
    if not p.is_file():  # a pipe or a device would block or never end
        raise FolderFileError(f"{p} is missing or not a regular file")
    try:
        size = p.stat().st_size
        meta = pq.read_metadata(p)
    except Exception as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise FolderFileError(f"{p} is not a readable Parquet table ({_short(first)}); "
                              "it was cut short or damaged") from None  # fmt: skip
    try:
        groups = [meta.row_group(i) for i in range(meta.num_row_groups)]
        rows = sum(g.num_rows for g in groups)
        if rows != meta.num_rows or any(g.num_rows < 0 for g in groups):
            raise FolderFileError(f"{p}: its row groups hold {rows:,} rows, its footer says "
                                  f"{meta.num_rows:,}; the file is damaged")  # fmt: skip
        want = None if columns is None else set(columns)
        nbytes = 0
        for g in groups:
            for c in range(g.num_columns):
                col = g.column(c)
                offsets = [o for o in (col.dictionary_page_offset, col.data_page_offset)
                           if o is not None]  # fmt: skip
                start = min(offsets) if offsets else 0
                if start < 0 or start + col.total_compressed_size > size:
                    raise FolderFileError(
                        f"{p}: column {col.path_in_schema!r} lies outside the file "
                        f"({size:,} bytes); the file is damaged"
                    )
                if want is None or col.path_in_schema.split(".")[0] in want:
                    nbytes += max(0, col.total_uncompressed_size)
    except FolderFileError:
        raise
    except Exception as exc:
        raise FolderFileError(f"{p}: its Parquet footer is damaged ({_short(str(exc))})") from None
    check_allocation(str(p), nbytes, "its columns", "read fewer columns or a smaller table")
    total = sum(g.total_byte_size for g in groups)
    if verify and total <= VERIFY_BYTES:
        try:
            pf = pq.ParquetFile(p, page_checksum_verification=True)
            for i in range(meta.num_row_groups):
                pf.read_row_group(i)
        except Exception as exc:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise FolderFileError(f"{p}: its data is damaged ({_short(first)})") from None
    return int(meta.num_rows)


# -- MCAP ---------------------------------------------------------------------------------------
def check_mcap(path: str | os.PathLike[str]) -> None:
    """Check that a run's ``run.mcap`` is a complete MCAP file: the magic at both ends and a
    summary section the indexed reader parses (what Foxglove needs to open it)."""
    from mcap.reader import make_reader

    p = Path(path)
    magic = b"\x89MCAP0\r\n"
    if not p.is_file():
        raise FolderFileError(f"{p} is missing or not a regular file")
    try:
        with open(p, "rb") as f:
            head = f.read(len(magic))
            f.seek(0, os.SEEK_END)
            size = f.tell()
            f.seek(max(0, size - len(magic)))
            tail = f.read(len(magic))
            if head != magic or tail != magic or size < 2 * len(magic):
                raise FolderFileError(f"{p} is not a complete MCAP file (cut short or damaged)")
            f.seek(0)
            make_reader(f).get_summary()
    except FolderFileError:
        raise
    except Exception as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise FolderFileError(f"{p} is not a readable MCAP file ({_short(first)})") from None


# -- npz ----------------------------------------------------------------------------------------
def read_npy_header(fh: IO[bytes]) -> tuple[tuple[int, ...], np.dtype]:
    """(shape, dtype) of an open ``.npy`` stream, from its header alone (numpy's public
    :mod:`numpy.lib.format` readers; object dtypes and Fortran order are refused)."""
    version = np.lib.format.read_magic(fh)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
    elif version in ((2, 0), (3, 0)):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh)
    else:  # pragma: no cover - read_magic accepts only these
        raise ValueError(f"unknown .npy version {version}")
    if dtype.hasobject:
        raise ValueError("it holds Python objects (pickle), which cobel never reads")
    if fortran:
        raise ValueError("it is in Fortran order, which cobel never writes")
    if any(int(n) < 0 for n in shape):
        raise ValueError(f"negative shape {shape}")
    return tuple(int(n) for n in shape), dtype


def npz_member_header(zf: zipfile.ZipFile, key: str) -> tuple[tuple[int, ...], np.dtype]:
    """(shape, dtype) of member ``key`` of an open npz archive, from its header alone."""
    with zf.open(f"{key}.npy") as fh:
        return read_npy_header(fh)


def nbytes_of(shape: tuple[int, ...], dtype: np.dtype) -> int:
    """Bytes an array of ``shape`` and ``dtype`` takes (Python integers: never overflows)."""
    return math.prod(shape) * int(dtype.itemsize)
