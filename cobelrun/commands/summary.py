"""End-of-run summaries that ``cobel run`` prints (to stderr; ``--quiet`` switches them off).

A single run ends with a table per phase (runs, trials, mean reward, latency and response
over the phase's last trials, wall time), the folder and the commands to look at it; a sweep
ends with its job table (status, time, objective when the task declares one).
"""

from __future__ import annotations

import math
import shlex
from pathlib import Path
from typing import Any

from rich.markup import escape

from cobelrun.io.run_folder import RunFolder
from cobelrun.run_summary import LAST_TRIALS, read_phase_rows


def _console() -> Any:
    import sys

    from rich.console import Console

    # logs and pipes get whole lines, not rich's 80-column default
    width = None if sys.stderr.isatty() else 200
    return Console(stderr=True, highlight=False, width=width)


def _num(value: Any, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    return f"{float(value):.{digits}g}" if abs(float(value)) < 1000 else f"{float(value):.0f}"


def _manifest(folder: RunFolder) -> dict[str, Any]:
    """A run's manifest, validated; {} when it is missing or damaged (a summary leaves the
    problem to ``cobel status``)."""
    from cobelrun.errors import CobelError
    from cobelrun.io.validate import read_manifest

    try:
        return read_manifest(folder.manifest) if folder.manifest.is_file() else {}
    except CobelError:
        return {}


def run_summary_table(run_dir: str | Path) -> Any:
    """The rich table of a run folder's phases (``None`` when it has no trials table)."""
    from rich.table import Table

    folder = RunFolder(run_dir)
    if not folder.table("trials").is_file():
        return None
    rows = read_phase_rows(folder.table("trials"))
    manifest = _manifest(folder)
    times = manifest.get("phase_wall_time_s") or {}
    table = Table(
        title=f"{manifest.get('task', 'run')}: last {LAST_TRIALS} trials of each phase",
        title_justify="left",
        box=None,
    )
    table.add_column("phase", style="bold cyan")
    table.add_column("runs", justify="right")
    table.add_column("trials", justify="right")
    measures = [c for c in ("reward", "latency", "response") if rows and c in rows[0]]
    for c in measures:
        table.add_column(f"mean {c}" if c != "latency" else "latency \\[steps]", justify="right")
    table.add_column("wall \\[s]", justify="right")
    for row in rows:
        table.add_row(
            row["phase"],
            str(row["runs"]),
            str(row["trials"]),
            *[_num(row.get(c)) for c in measures],
            _num(times.get(row["phase"]), 2),
        )
    return table


def print_run_summary(run_dir: str | Path) -> None:
    """Print a run's phase table, its folder and the next commands (to stderr)."""
    console = _console()
    folder = RunFolder(run_dir)
    table = run_summary_table(folder.path)
    if table is not None:
        console.print(table)
    manifest = _manifest(folder)
    wall = manifest.get("wall_time_s")
    objective = manifest.get("objective")
    line = f"[bold]done[/] in {wall:.1f} s" if isinstance(wall, int | float) else "[bold]done[/]"
    if objective is not None:
        line += f"; objective {manifest.get('objective_name', '')} = {_num(objective, 5)}"
    console.print(line)
    console.print(f"folder: {folder.path}")
    console.print("next:")
    where = shlex.quote(str(folder.path))  # a results root with spaces: commands to paste
    for cmd, what in (
        (f"cobel plot {where}", "the task's figure"),
        (f"cobel plot {where} --kind occupancy", "where the agents went"),
        (f"cobel rerun {where} seed=1", "the same config, another seed"),
        (f"cobel status {where}", "status and tables"),
    ):
        console.print(f"  {escape(cmd)}    [dim]# {what}[/]")


def print_sweep_summary(sweep_dir: str | Path) -> None:
    """Print a sweep's job table: swept values, status, wall time and objective."""

    from cobelrun.commands.common import STATUS_STYLE
    from cobelrun.io.sweep_folder import job_rows, read_sweep

    sweep_dir = Path(sweep_dir)
    sweep = read_sweep(sweep_dir)
    rows = job_rows(sweep_dir, write=False)
    objectives = {}
    for r in rows:
        m = RunFolder(r["run_dir"]).manifest if r.get("run_dir") else None
        if m is not None and m.is_file():
            objectives[r["job"]] = _manifest(RunFolder(r["run_dir"])).get("objective")
    has_objective = any(v is not None for v in objectives.values())
    table = sweep_table(sweep_dir, sweep["swept"])
    if has_objective:
        table.add_column("objective", justify="right")
    for r in rows:
        dur = r["duration_s"]
        cells = [
            str(r["job"]),
            *[str(r[k]) for k in sweep["swept"]],
            f"[{STATUS_STYLE.get(r['status'], '')}]{r['status']}[/]",
            "" if dur is None or dur != dur else f"{float(dur):.1f}",
        ]
        if has_objective:
            cells.append(_num(objectives.get(r["job"]), 5))
        table.add_row(*cells)
    console = _console()
    console.print(table)
    console.print(f"folder: {sweep_dir}")
    console.print("next:")
    swept = sweep["swept"][0] if sweep["swept"] else None
    hue = f" --hue {shlex.quote(swept)}" if swept else ""
    where = shlex.quote(str(sweep_dir))
    console.print(
        f"  {escape(f'cobel plot {where}{hue}')}    [dim]# one curve per {escape(swept or 'sweep')}[/]"
    )
    console.print(f"  {escape(f'cobel collect {where}')}    [dim]# one Parquet file per table[/]")


def run_status(folder: RunFolder) -> None:
    """``cobel status RUN_DIR``: repair a killed run's files, then print its status and its
    tables; exit 1 unless it completed and every table it lists can be read.

    Every file is checked before it is trusted (:mod:`cobelrun.io.validate`): a damaged
    manifest is one error line naming it; a table cut short or damaged is listed as
    unreadable and the run is not called completed.
    """
    import typer

    from cobelrun.commands.common import fail
    from cobelrun.errors import CobelError
    from cobelrun.io.repair import repair_run
    from cobelrun.io.validate import check_mcap, check_table, read_manifest

    try:
        repaired = repair_run(folder.path)
        manifest = read_manifest(folder.manifest)
    except CobelError as exc:
        fail(str(exc))
    status = manifest["status"]
    unreadable = {}
    tables = folder.tables()
    for table in tables:
        try:
            check_table(folder.table(table), columns=[], verify=True)
        except CobelError as exc:
            unreadable[table] = str(exc)
    if folder.mcap.is_file() and status == "completed":
        try:
            check_mcap(folder.mcap)
        except CobelError as exc:
            unreadable[folder.MCAP] = str(exc)
    shown = status if status != "completed" or not unreadable else "completed, but damaged"
    typer.echo(
        f"{folder.path}: {shown}" + (f" ({manifest['error']})" if manifest.get("error") else "")
    )
    for table, rows in repaired.get("tables", {}).items():
        typer.echo(f"  repaired {folder.table(table).name}: {rows:,} rows kept")
    if repaired.get("mcap"):
        typer.echo(f"  repaired {folder.mcap.name}: summary rewritten, complete messages kept")
    readable = [t for t in tables if t not in unreadable]
    typer.echo(f"  tables: {', '.join(readable) or 'none'}")
    if status in ("running", "interrupted"):
        progress = run_progress(folder, manifest)
        if progress:
            typer.echo(f"  progress: {progress}")
    for problem in unreadable.values():
        typer.echo(f"  unreadable: {problem}")
    if status != "completed" or unreadable:
        raise typer.Exit(1)


def trials_recorded(folder: RunFolder) -> int | None:
    """How many trial rows a run has recorded so far: its table's parts while it runs (a
    resumed run's first part holds the rows up to its checkpoint), else its trials table;
    None when neither can be read."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    parts = sorted(folder.parts("trials").glob("part-*.arrow"))
    try:
        if parts:
            rows = 0
            for path in parts:
                # memory-mapped: counting reads the batches' lengths, allocates no copy of a
                # part (a stranger's folder may hold a huge one)
                with pa.memory_map(str(path), "r") as src:
                    reader = pa.ipc.open_file(src)
                    rows += sum(reader.get_batch(i).num_rows
                                for i in range(reader.num_record_batches))  # fmt: skip
            return rows
        if folder.table("trials").is_file():
            return int(pq.ParquetFile(folder.table("trials")).metadata.num_rows)
    except (OSError, pa.ArrowException):  # a part being merged or replaced: no count this time
        return None
    return None


def _phases(folder: RunFolder) -> list[tuple[str, int]]:
    """(name, trials) of the run's protocol phases, from its config.yaml (read as plain data);
    [] when it cannot be read."""
    import yaml

    try:
        cfg = yaml.safe_load(folder.config.read_text(encoding="utf-8"))
        phases = cfg["task"]["protocol"]["phases"]
        return [(str(ph.get("name", i)), int(ph["trials"])) for i, ph in enumerate(phases)]
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError, AttributeError):
        return []


def _checkpoint_note(folder: RunFolder, now: float) -> str:
    """Where a run's checkpoint is: ``checkpoint: run 0 (of 2), phase 'block_2' (2 of 4)
    after 875 of 2,000 trials, 6 min ago``; for a batched chunk ``runs 0-19 (a batched
    chunk)``."""
    from cobelrun.checkpoint import CheckpointError, read_header

    try:
        header = read_header(folder.checkpoint)
        pos, written = header["position"], float(header["written_unix"])
        run, phase, k = int(pos["run"]), int(pos["phase"]), int(pos["k"])
    except (CheckpointError, KeyError, TypeError, ValueError):
        return "checkpoint: unreadable"
    batch = header.get("batch") if isinstance(header.get("batch"), dict) else None
    chunk = batch.get("runs") if batch else None
    if isinstance(chunk, list) and len(chunk) > 1:
        who = f"runs {chunk[0]}-{chunk[-1]} (a batched chunk)"
    else:
        who = f"run {run}"
    phases = _phases(folder)
    if 0 <= phase < len(phases):
        name, trials = phases[phase]
        where = f"phase {name!r} ({phase + 1} of {len(phases)}) after {k:,} of {trials:,} trials"
    else:
        where = f"phase {phase} after {k:,} trials"
    ago = max(0.0, now - written) / 60
    when = f"{ago:.0f} min ago" if ago < 120 else f"{ago / 60:.1f} h ago"
    return f"checkpoint: {who}, {where}, {when}"


def run_progress(folder: RunFolder, manifest: dict[str, Any], now: float | None = None) -> str:
    """A running or stopped run's progress: ``1,368 of 6,000 trials recorded (22.8 %);
    checkpoint: run 0, phase 'training' (1 of 1) after 1,334 of 6,000 trials, 6 min ago``;
    '' when nothing tells. Run numbers are the tables' (from 0); the trials recorded may run
    past the checkpoint (``cobel resume`` drops those and runs them again); a batched chunk
    writes its rows at its end, so while it runs only its checkpoint tells."""
    import time

    out = []
    done = trials_recorded(folder)
    try:
        total = int(manifest.get("runs", 0)) * int(manifest.get("trials", 0))
    except (TypeError, ValueError):
        total = 0
    if done is not None and total > 0:
        out.append(f"{done:,} of {total:,} trials recorded ({100 * done / total:.1f} %)")
    if folder.checkpoint.is_file():
        out.append(_checkpoint_note(folder, time.time() if now is None else now))
    return "; ".join(out)


def job_progress(run_dir: Path) -> str:
    """:func:`run_progress` of a sweep's job folder ('' without a readable manifest)."""
    folder = RunFolder(run_dir)
    manifest = _manifest(folder)
    return run_progress(folder, manifest) if manifest else ""


def sweep_table(sweep_dir: Path, swept: list[str]) -> Any:
    """The rich table a sweep is listed in (``cobel status SWEEP``, a sweep's summary): a row
    per job with its swept values, status and time; callers add their own last columns."""
    from rich.table import Table

    table = Table(title=f"sweep {sweep_dir}", title_justify="left", box=None)
    table.add_column("job", justify="right")
    for key in swept:
        table.add_column(key, style="cyan")
    table.add_column("status")
    table.add_column("time \\[s]", justify="right")
    return table
