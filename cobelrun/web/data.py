"""What ``cobel serve`` shows, as plain data: the run and sweep folders under a results folder,
one row each, and a run's learning curve read from its table or, while it runs, its parts.

Everything here reads folders through the validated readers (:func:`read_manifest`,
:func:`read_job_file`, :func:`read_sweep`, :func:`check_table`, :mod:`cobelrun.results`);
nothing composes or instantiates a folder's config. The page (:mod:`cobelrun.web.app`) is a
thin view over these functions, which the tests call directly too.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cobelrun.errors import CobelError
from cobelrun.figures.tasks import overrides_of
from cobelrun.io.run_folder import RunFolder

__all__ = [
    "CURVE_COLUMNS",
    "Folder",
    "LiveCurve",
    "check_results_dir",
    "live_trials",
    "overrides_of",
    "scan",
]

#: folders deeper than this under the results folder are not searched
MAX_DEPTH = 6
#: learning-curve measures the page offers, in order of preference: (trials column, label)
CURVE_COLUMNS = {
    "steps": "escape latency [steps]",
    "reward": "reward",
    "cumulative_response": "cumulative responses",
    "latency_s": "escape latency [s]",
    "correct": "correct choice",
}
#: a part bigger than this is not read by the page (a part holds one batch of trials)
MAX_PART_BYTES = 64 << 20
SWEEP_FILE = "sweep.json"


@dataclass
class Folder:
    """One row of the dashboard: a run folder or a sweep folder."""

    path: Path
    kind: str  # "run" or "sweep"
    rel: str
    status: str = ""
    task: str = ""
    seed: int | None = None
    overrides: list[str] = field(default_factory=list)
    duration_s: float | None = None
    started_at: str = ""
    error: str = ""
    swept: list[str] = field(default_factory=list)
    jobs: int = 0

    def row(self) -> dict[str, Any]:
        """The row shown in the page's table (strings and numbers only)."""
        dur = "" if self.duration_s is None else f"{self.duration_s:.1f}"
        return {
            "path": self.rel,
            "kind": self.kind,
            "status": self.status,
            "task": self.task,
            "seed": "" if self.seed is None else self.seed,
            "overrides": " ".join(self.overrides),
            "duration_s": dur,
            "started": self.started_at[:19].replace("T", " "),
            "error": self.error,
        }


def _is_run(path: Path) -> bool:
    folder = RunFolder(path)
    return folder.manifest.is_file() or folder.table("trials").is_file()


def check_results_dir(path: str | os.PathLike[str]) -> Path:
    """``path`` if it is a results folder (holds run or sweep folders, or is one); else a
    one-line :class:`CobelError` naming what is allowed."""
    p = Path(path)
    if not p.exists():
        raise CobelError(f"results folder {p} does not exist")
    if not p.is_dir():
        raise CobelError(f"{p} is not a folder; pass a results folder (default: results/)")
    if _is_run(p) or (p / SWEEP_FILE).is_file():
        return p
    for _ in _walk(p):
        return p
    raise CobelError(
        f"{p} is not a results folder: no run or sweep folder in it (within {MAX_DEPTH} levels); "
        "pass the folder `cobel run` writes to (default: results/)"
    )


def _walk(root: Path) -> Any:
    """Yield ``(path, kind)`` for the run and sweep folders under ``root`` (not inside them)."""
    stack = [(root, 0)]
    while stack:
        d, depth = stack.pop()
        if (d / SWEEP_FILE).is_file():
            yield d, "sweep"
            continue
        if _is_run(d):
            yield d, "run"
            continue
        if depth >= MAX_DEPTH:
            continue
        try:
            subs = sorted(
                (e for e in os.scandir(d) if e.is_dir(follow_symlinks=False)),
                key=lambda e: e.name,
                reverse=True,
            )
        except OSError:
            continue
        stack.extend((Path(e.path), depth + 1) for e in subs if not e.name.startswith("."))


def _run_row(path: Path, rel: str) -> Folder:
    from cobelrun.io.validate import read_job_file, read_manifest

    row = Folder(path=path, kind="run", rel=rel)
    folder = RunFolder(path)
    try:
        if folder.manifest.is_file():
            m = read_manifest(folder.manifest)
            row.status = str(m.get("status") or "")
            row.task = str(m.get("task") or "")
            row.seed = m.get("seed")
            row.overrides = overrides_of(m.get("command"))
            row.duration_s = m.get("duration_s")
            row.started_at = str(m.get("started_at") or "")
            row.error = str(m.get("error") or "")
        if folder.job.is_file():
            job = read_job_file(folder.job)
            row.overrides = list(job.get("overrides") or row.overrides)
            row.status = row.status or str(job.get("status") or "")
        if row.status == "completed" and not folder.done.is_file():
            row.status = "incomplete"
    except CobelError as exc:
        row.status, row.error = "damaged", str(exc)
    return row


def _sweep_row(path: Path, rel: str) -> Folder:
    from cobelrun.io.sweep_folder import read_sweep

    row = Folder(path=path, kind="sweep", rel=rel)
    try:
        s = read_sweep(path)
        row.swept = list(s.get("swept") or [])
        row.jobs = len(s.get("jobs") or [])
        row.overrides = [f"{k} (swept)" for k in row.swept]
        row.started_at = str(s.get("created_at") or "")
        cmd = str(s.get("command") or "")
        task = [a.split("=", 1)[1] for a in cmd.split() if a.startswith("task=")]
        row.task = task[0] if task else ""
        row.status = f"{row.jobs} jobs"
    except CobelError as exc:
        row.status, row.error = "damaged", str(exc)
    return row


def scan(root: str | os.PathLike[str]) -> list[Folder]:
    """Every run and sweep folder under ``root``, newest path first, one validated row each
    (a damaged folder is a row with status ``damaged`` and the reader's one-line error)."""
    root = Path(root)
    out = []
    for path, kind in _walk(root):
        rel = path.relative_to(root).as_posix() or "."
        out.append(_sweep_row(path, rel) if kind == "sweep" else _run_row(path, rel))
    return out


def resolve(root: str | os.PathLike[str], rel: str) -> Path:
    """The folder ``rel`` under ``root``; anything that leaves ``root`` is refused."""
    root_r = Path(root).resolve()
    p = (root_r / rel).resolve()
    if p != root_r and root_r not in p.parents:
        raise CobelError(f"{rel!r} is not inside the results folder")
    if not p.is_dir():
        raise CobelError(f"{rel!r} is not a folder of {root}")
    return p


# -- live curves ------------------------------------------------------------------------------
def _read_part(path: Path) -> pd.DataFrame | None:
    """One complete part (Arrow IPC file) of a running run's table, or None if it is not one."""
    import pyarrow as pa

    try:
        if not path.is_file() or path.stat().st_size > MAX_PART_BYTES:
            return None
        with pa.OSFile(str(path), "rb") as src:
            return pa.ipc.open_file(src).read_all().to_pandas()
    except (OSError, pa.ArrowException):
        return None  # removed (merged) or unreadable: the finished table is read instead


@dataclass
class LiveCurve:
    """A run's trials, read incrementally: the finished table when there is one, else the
    parts the recorder has written so far (each complete part read once)."""

    path: Path
    _parts: dict[str, pd.DataFrame] = field(default_factory=dict)

    def trials(self) -> pd.DataFrame:
        """The trials written so far (empty when none)."""
        folder = RunFolder(self.path)
        if folder.table("trials").is_file():
            from cobelrun.results import load_trials

            try:
                return load_trials(self.path)
            except CobelError:
                pass  # being renamed into place: the parts still tell
        parts_dir = folder.parts("trials")
        names = sorted(p.name for p in parts_dir.glob("part-*.arrow")) if parts_dir.is_dir() else []
        for name in names:
            if name not in self._parts:
                frame = _read_part(parts_dir / name)
                if frame is not None:
                    self._parts[name] = frame
        frames = [self._parts[n] for n in sorted(self._parts)]
        return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def live_trials(path: str | os.PathLike[str]) -> pd.DataFrame:
    """The trials of a run folder so far (finished table or parts)."""
    return LiveCurve(Path(path)).trials()


def curve_points(trials: pd.DataFrame, column: str) -> list[list[float]]:
    """``[[trial, mean over runs], ...]`` of ``column`` (the page's live chart)."""
    if trials.empty or column not in trials or "trial" not in trials:
        return []
    mean = trials.groupby("trial")[column].mean()
    return [[int(t), float(v)] for t, v in mean.items() if np.isfinite(v)]


def curve_column(trials: pd.DataFrame) -> str | None:
    """The first of :data:`CURVE_COLUMNS` the table has."""
    return next((c for c in CURVE_COLUMNS if c in trials), None)
