"""Per-run tables of long sweeps, read from their run folders without writing to them.

``python -m cobelrun.figures.data NAME --runs PATH [PATH ...] [--finished-only] [--out DIR]``
reads the run folders of figure ``NAME`` (:data:`IMPORTERS`: ``fig6a``, ``fig6a_paper``,
``fig8``, ``fig8_stable``) from ``PATH``: a sweep folder (``cobel run -m``; its ``sweep.json``
lists the jobs, each job folder is one run folder) or a run folder. The folders may belong to
a sweep that is still running: nothing in them is written, repaired or locked (unlike ``cobel status``, which repairs what it reads), and
a run is *finished* only when it has its done marker and a ``completed`` manifest.

Every job must be finished, or the command says which are not and writes nothing;
``--finished-only`` uses the finished runs and writes the tables as ``TABLE_partial`` (so a
partial sweep never replaces a committed table), their sidecars saying how many runs of how
many were used and which were not (status, last trial: the last of its trials table as it is
on disk; a running run's newest trials may still be in its writer's parts). Fig. 8's per-run
table lists the unfinished runs' snapshots too, and with no run finished it is written alone
(the snapshots so far, no means). Per run, the sidecar holds the
manifest's command, config hash, cobel commit, seed, machine, dates and times; a run resumed
from a checkpoint records the wall time of its last launch only (``resumed_from`` says so).

Tables:

- ``fig6a_runs`` (per run: task, right-arm response rate per block of trials, trials to
  extinction, trials, steps, wall and CPU time of its folder) and ``fig6a`` (per task and
  measure: runs, mean, SD, SE, median; block means over the finished runs, and the figure's
  own extinction trial: where the mean rate over the runs first falls below 0.5); the paper
  scale's as ``fig6a_paper_runs`` and ``fig6a_paper``; a run of another figure's task (e.g. an 84 x 84 run given to ``fig6a``)
  is refused, naming the figure it belongs to;
- ``fig8_runs`` (per run and snapshot: place cells with the original script's box comparison
  by area, live units: units with a blob in some map, units, the median spatial information;
  whether the run is finished and its last trial; unfinished runs are listed with
  ``--finished-only`` but never averaged) and ``fig8``
  (:func:`cobelrun.figures.tables.fig8_summary`: the mean over the finished runs per snapshot,
  dead layers included, Spearman's rho of the mean and the per-run trend test); cobel's
  stabilised training's (``fig8_stable``) as ``fig8_stable_runs`` and ``fig8_stable``, boxes
  compared by extent as its figure does; a run of the other one's task is refused likewise.
"""

from __future__ import annotations

import os
import re
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cobelrun.errors import CobelError, allowed_list, suggest

#: Fig. 6A's blocks of trials (as ``fig6a.csv``): acquisition 1-100, extinction 101-200
FIG6A_BLOCKS = ((1, 20), (21, 40), (81, 100), (101, 110), (111, 120), (121, 140), (141, 160),
                (161, 180), (181, 200))  # fmt: skip
#: Fig. 6A's last acquisition trial: later blocks also get the share of rewarded trials
FIG6A_SWITCH = 100


@dataclass(frozen=True)
class RunInfo:
    """One run folder as found (read-only)."""

    run_dir: Path
    job: int | None
    seed: int | None
    status: str  #: done, running, interrupted, failed, queued or missing (as recorded)
    manifest: Mapping[str, Any] = field(default_factory=dict)
    last_trial: int | None = None
    checkpoint: bool = False

    @property
    def complete(self) -> bool:
        return self.status == "done"


def _read_json(path: Path) -> dict[str, Any]:
    from cobelrun.io.validate import read_json_or_none

    return read_json_or_none(path) or {}


def _last_trial(run_dir: Path) -> int | None:
    """The last trial of the trials table as it is on disk (None: no table yet)."""
    from cobelrun.io.run_folder import RunFolder

    path = RunFolder(run_dir).table("trials")
    if not path.is_file():
        return None
    try:
        trials = pd.read_parquet(path, columns=["trial"])
    except Exception:  # being replaced by the run's writer: no last trial this time
        return None
    return int(trials["trial"].max()) if len(trials) else None


def run_info(run_dir: Path, job: int | None = None, seed: int | None = None) -> RunInfo:
    """What ``run_dir`` holds, read without writing: status, manifest, last trial."""
    from cobelrun.io.run_folder import RunFolder
    from cobelrun.io.sweep_folder import JOB_FILE, is_complete

    manifest = _read_json(RunFolder(run_dir).manifest)
    job_record = _read_json(run_dir / JOB_FILE)
    if is_complete(run_dir, None, manifest or None):
        status = "done"
    elif manifest:
        status = str(manifest.get("status", "running"))
    elif job_record:
        status = str(job_record.get("status", "queued"))
    else:
        status = "missing"
    if seed is None and manifest.get("seed") is not None:
        seed = int(manifest["seed"])
    return RunInfo(run_dir, job, seed, status, manifest, _last_trial(run_dir),
                   RunFolder(run_dir).checkpoint.is_file())  # fmt: skip


def scan(paths: Sequence[Path]) -> tuple[list[RunInfo], list[dict[str, Any]]]:
    """The runs under ``paths`` (sweep folders: every job of ``sweep.json``; run folders: the
    folder) and a description of each sweep (folder, command, jobs)."""
    from cobelrun.io.sweep_folder import SWEEP_FILE, job_dir, read_sweep

    runs, sweeps = [], []
    for path in map(Path, paths):
        if not path.is_dir():
            raise CobelError(f"--runs {path}: no such folder (give a sweep or run folder)")
        if (path / SWEEP_FILE).is_file():
            sweep = read_sweep(path)
            sweeps.append({"folder": str(path), "command": sweep.get("command"),
                           "jobs": len(sweep["jobs"])})  # fmt: skip
            for j in sweep["jobs"]:
                seed = j["params"].get("seed")
                runs.append(run_info(job_dir(path, j["job"]), int(j["job"]),
                                     int(seed) if seed is not None else None))  # fmt: skip
        elif (path / "manifest.json").is_file():
            runs.append(run_info(path))
        else:
            inner = sorted(p.name for p in path.iterdir() if (p / SWEEP_FILE).is_file())
            hint = (f"; it holds the sweeps {', '.join(inner)} (a figure's labels): give "
                    f"them, e.g. --runs {' '.join(str(path / n) for n in inner)}" if inner else "")  # fmt: skip
            raise CobelError(f"--runs {path}: neither a sweep folder (sweep.json) nor a run "
                             f"folder (manifest.json){hint}")  # fmt: skip
    if not runs:
        raise CobelError("--runs: no runs found")
    seen: dict[Path, RunInfo] = {}
    for r in runs:  # a run counted twice would weigh twice in every mean
        key = r.run_dir.resolve()
        if key in seen:
            raise CobelError(f"--runs: the run folder {r.run_dir} is given twice (as "
                             f"{_describe(seen[key])} and {_describe(r)}); give each sweep or "
                             "run folder once")  # fmt: skip
        seen[key] = r
    return runs, sweeps


#: the line a job logs when it starts (cobelrun.hydra_app.log_start) in RUN_DIR/cobel.log
_LAUNCH = re.compile(r"^\[(?P<at>[\d-]+ [\d:,]+)\]\[cobel\]\[INFO\] - task \S+, seed ")


def launches(run_dir: Path) -> list[str]:
    """When each launch of the run started (a resumed run has several), from its
    ``cobel.log`` (empty where there is none): a resumed run's manifest keeps its last launch
    only."""
    log = run_dir / "cobel.log"
    if not log.is_file():
        return []
    with log.open(encoding="utf-8", errors="replace") as f:
        return [m.group("at") for line in f if (m := _LAUNCH.match(line))]


def _describe(info: RunInfo) -> str:
    where = f"job {info.job}" if info.job is not None else str(info.run_dir)
    last = f", trial {info.last_trial}" if info.last_trial is not None else ""
    return f"{where} ({info.status}{last})"


def select(runs: Sequence[RunInfo], finished_only: bool, none_ok: bool = False) -> list[RunInfo]:
    """The finished runs; a CobelError when one is not finished (unless ``finished_only``) or
    none is (unless ``none_ok``: a per-run listing of unfinished runs, with no summary)."""
    done = [r for r in runs if r.complete]
    todo = [r for r in runs if not r.complete]
    if todo and not finished_only:
        shown = ", ".join(_describe(r) for r in todo[:8]) + (", ..." if len(todo) > 8 else "")
        raise CobelError(f"{len(todo)} of {len(runs)} runs are not finished: {shown}; wait for "
                         f"them, or add --finished-only to use the {len(done)} finished ones "
                         "(tables *_partial)")  # fmt: skip
    if not done and not none_ok:
        raise CobelError(f"none of the {len(runs)} runs is finished yet")
    return done


def _cpu(manifest: Mapping[str, Any]) -> float:
    """The run's CPU time on its simulation thread (NaN where the manifest has none)."""
    cpu = manifest.get("cpu_time_s") or {}
    value = cpu.get("simulation_thread") if isinstance(cpu, Mapping) else None
    return float(value) if isinstance(value, int | float) else float("nan")


def _wall(manifest: Mapping[str, Any]) -> float:
    value = manifest.get("wall_time_s")
    return float(value) if isinstance(value, int | float) else float("nan")


def provenance(
    table: str, runs: Sequence[RunInfo], used: Sequence[RunInfo], sweeps: Sequence[Mapping],
    command: str,
) -> dict[str, Any]:  # fmt: skip
    """The sidecar of a table built from ``used`` of ``runs`` (every run listed, with whether
    it was used)."""
    entries, commits, machines, started = [], set(), set(), []
    used_dirs = {r.run_dir for r in used}
    for r in runs:
        m = r.manifest
        git = (m.get("git") or {}).get("cobelrun") or {}
        entry = {"job": r.job, "seed": r.seed, "status": r.status, "used": r.run_dir in used_dirs,
                 "last_trial": r.last_trial, "checkpoint": r.checkpoint,
                 "config_hash": m.get("config_hash"),
                 "cobel_commit": git.get("commit"), "dirty": git.get("dirty"),
                 "command": " ".join(m.get("command") or []), "host": m.get("hostname"),
                 "started_at": m.get("started_at"), "ended_at": m.get("ended_at"),
                 "wall_time_s": m.get("wall_time_s"), "cpu_time_s": m.get("cpu_time_s"),
                 "resumed_from": m.get("resumed_from"), "launches": launches(r.run_dir),
                 "run_dir": str(r.run_dir)}  # fmt: skip
        entries.append(entry)
        if entry["used"]:
            commits.add(f"{git.get('commit')}{' (dirty)' if git.get('dirty') else ''}")
            machines.add(f"{m.get('hostname')} ({m.get('platform')})")
            started.append(m.get("started_at"))
    resumed = [e["job"] for e in entries if e["used"] and e["resumed_from"]]
    unfinished = [{"job": r.job, "seed": r.seed, "status": r.status, "last_trial": r.last_trial}
                  for r in runs if r.run_dir not in used_dirs]  # fmt: skip
    walls = [_wall(r.manifest) for r in used]
    cpus = [_cpu(r.manifest) for r in used]
    starts = [s for s in started if s]
    return {
        "table": table,
        "source": "run",
        "command": command,
        "sweeps": list(sweeps),
        "runs_used": len(used),
        "runs_total": len(runs),
        "partial": len(used) < len(runs),
        "unfinished": unfinished,
        "seeds": sorted({r.seed for r in used if r.seed is not None}),
        "config_hashes": sorted({str(r.manifest.get("config_hash")) for r in used}),
        "cobel_commit": sorted(commits),
        "machine": sorted(machines),
        "runs_started": [min(starts), max(starts)] if starts else [],
        "exported": datetime.now(UTC).isoformat(timespec="seconds"),
        "wall_time_s": round(float(np.nansum(walls)), 1),
        "cpu_time_s": round(float(np.nansum(cpus)), 1),
        "wall_time_note": "sums over the used runs of their manifests' wall_time_s and "
        "cpu_time_s.simulation_thread; a run resumed from a checkpoint records its last "
        f"launch only (resumed: jobs {resumed or 'none'}; each run's launches, from its "
        "cobel.log, are listed with it)",
        "runs": entries,
    }


# -- the reductions ---------------------------------------------------------------------------


def fig6a_runs(runs: Sequence[RunInfo]) -> pd.DataFrame:
    """Per run: the right-arm response rate per block of :data:`FIG6A_BLOCKS`, the share of
    rewarded trials (the left arm's goal reached) per block after :data:`FIG6A_SWITCH`, the mean
    steps per trial per block (``latency_*``), the steps of the acquisition trials, trials to
    extinction (extinction trials until its first left choice; NaN if none), trials, steps,
    and the wall and CPU time of its run folder (all its runs)."""
    from cobelrun.figures.extinction import trials_to_extinction
    from cobelrun.results import load_table

    rows = []
    for info in runs:
        trials = load_table(info.run_dir, "trials")
        if "response" not in trials:
            raise CobelError(f"{info.run_dir}: the trials table has no 'response' column "
                             "(not an extinction task)")  # fmt: skip
        for run, t in trials.groupby("run", sort=True):
            row: dict[str, Any] = {"task": info.manifest.get("task"), "job": info.job,
                                   "seed": info.seed, "run": int(run)}  # fmt: skip
            for lo, hi in FIG6A_BLOCKS:
                row[f"right_{lo}_{hi}"] = t.loc[t["trial"].between(lo, hi), "response"].mean()
            for lo, hi in FIG6A_BLOCKS:  # after the switch: the new (left) arm's reward
                if lo > FIG6A_SWITCH:
                    block = t["trial"].between(lo, hi)
                    row[f"rewarded_{lo}_{hi}"] = float((t.loc[block, "reward"] > 0).mean())
            for lo, hi in FIG6A_BLOCKS:  # mean steps per trial: time-outs (100) after the switch
                row[f"latency_{lo}_{hi}"] = float(t.loc[t["trial"].between(lo, hi), "steps"].mean())
            row["acquisition_steps"] = int(t.loc[t["trial"] <= FIG6A_SWITCH, "steps"].sum())
            row["trials_to_extinction"] = trials_to_extinction(t)
            row["trials"] = int(t["trial"].max())
            row["steps"] = int(t["steps"].sum())
            row["wall_time_s"] = _wall(info.manifest)
            row["cpu_time_s"] = _cpu(info.manifest)
            rows.append(row)
    return pd.DataFrame(rows)


def fig6a_summary(per_run: pd.DataFrame, pooled_extinction: float) -> pd.DataFrame:
    """Per measure of ``per_run`` (the runs of one task): runs (with a value), mean, SD, SE,
    median; and the figure's extinction trial (``pooled_extinction``: where the mean rate over
    the runs first falls below 0.5), the share of runs that chose the left arm in extinction,
    the lowest run's rate over trials 81-100 and the number of runs at or below 0.5 over trials
    181-200 (these last four in ``mean``)."""
    rows = []
    for col in (c for c in per_run.columns if c.startswith(("right_", "rewarded_", "latency_"))
                or c in ("trials_to_extinction", "acquisition_steps", "steps")):  # fmt: skip
        v = per_run[col].dropna()
        rows.append({"measure": col, "runs": len(v), "mean": v.mean(),
                     "sd": v.std(ddof=1) if len(v) > 1 else np.nan,
                     "se": v.std(ddof=1) / np.sqrt(len(v)) if len(v) > 1 else np.nan,
                     "median": v.median()})  # fmt: skip
    n = len(per_run)
    rows.append({"measure": "mean_rate_below_half_after_trials", "runs": n,
                 "mean": pooled_extinction, "sd": np.nan, "se": np.nan, "median": np.nan})  # fmt: skip
    extinct = per_run["trials_to_extinction"].notna()
    rows.append({"measure": "share_of_runs_extinct", "runs": n, "mean": extinct.mean(),
                 "sd": np.nan, "se": np.nan, "median": np.nan})  # fmt: skip
    # the acceptance's per-run reading: every run learnt (its lowest rate over trials 81-100),
    # and how many runs extinguished (at most 0.5 over trials 181-200); counts in 'mean'
    last = per_run[f"right_{FIG6A_BLOCKS[-1][0]}_{FIG6A_BLOCKS[-1][1]}"]
    rows.append({"measure": "lowest_right_81_100", "runs": n,
                 "mean": per_run["right_81_100"].min(), "sd": np.nan, "se": np.nan,
                 "median": np.nan})  # fmt: skip
    rows.append({"measure": "runs_right_181_200_at_most_half", "runs": n,
                 "mean": int((last <= 0.5).sum()), "sd": np.nan, "se": np.nan,
                 "median": np.nan})  # fmt: skip
    return pd.DataFrame(rows)


def import_fig6a(used: Sequence[RunInfo]) -> dict[str, pd.DataFrame]:
    from cobelrun.figures.extinction import trials_to_extinction
    from cobelrun.results import load_table

    per_run = fig6a_runs(used)
    parts = []
    for task, rows in per_run.groupby("task", sort=False):  # DQN and Dyna-Q never mix
        runs = [r for r in used if r.manifest.get("task") == task]
        pooled = pd.concat([load_table(r.run_dir, "trials").assign(job=r.job) for r in runs],
                           ignore_index=True)  # fmt: skip
        summary = fig6a_summary(rows, trials_to_extinction(pooled))
        parts.append(summary.assign(task=task)[["task", *summary.columns]])
    return {"fig6a_runs": per_run, "fig6a": pd.concat(parts, ignore_index=True)}


def fig8_runs(runs: Sequence[RunInfo], box_measure: str = "area") -> pd.DataFrame:
    """Per run and snapshot: place cells (``box_measure``: the original script's box
    comparison by ``area``, as ``fig8`` draws it; ``extent`` as ``fig8_stable`` does), live
    units (a blob in some map), units, the median spatial information; whether the run is
    finished and its last trial. A run without activity maps yet is left out."""
    from cobelrun.analysis.maps import (
        GRID_TABLE,
        MAPS_TABLE,
        classify_snapshots,
        load_activity_maps,
    )
    from cobelrun.analysis.place_cells import PlaceCellCriterion

    frames = []
    for info in runs:
        if not all((info.run_dir / f"{t}.parquet").is_file() for t in (MAPS_TABLE, GRID_TABLE)):
            continue
        df, grid = load_activity_maps(info.run_dir)
        units, snaps = classify_snapshots(df, grid, criterion=PlaceCellCriterion(box_measure=box_measure),
                                          rsa=False)  # fmt: skip
        blobs = [c for c in units.columns if c.startswith("n_blobs_")]
        live = units[blobs].gt(0).any(axis=1).groupby([units["run"], units["trial"]]).sum()
        snaps = snaps.set_index(["run", "trial"]).assign(live_units=live).reset_index()
        frames.append(pd.DataFrame({
            "seed": info.seed, "trial": snaps["trial"], "place_cells": snaps["place_cells"],
            "live_units": snaps["live_units"].astype(int), "units": snaps["units"],
            "job": info.job, "run": snaps["run"],
            "spatial_information_median": snaps["spatial_information_median"],
            "complete": info.complete, "last_trial": info.last_trial,
        }))  # fmt: skip
    if not frames:
        raise CobelError("no run has activity maps yet (activity_maps.parquet)")
    return pd.concat(frames, ignore_index=True)


def import_fig8(
    used: Sequence[RunInfo], listed: Sequence[RunInfo], box_measure: str = "area"
) -> dict[str, pd.DataFrame]:
    from cobelrun.figures.tables import fig8_summary

    per_run = fig8_runs(listed, box_measure)
    return {"fig8_runs": per_run, "fig8": fig8_summary(per_run)}


def _renamed(tables: Mapping[str, pd.DataFrame], old: str, new: str) -> dict[str, pd.DataFrame]:
    return {new + k.removeprefix(old): v for k, v in tables.items()}


#: figure -> (function of (used runs, runs listed in the per-run table), its tables); Fig. 6A's
#: CPU default (``fig6a``: 36 x 36) and paper scale (``fig6a_paper``: 84 x 84, 50 runs) are
#: reduced alike into tables of their own name, so neither import replaces the other's
IMPORTERS: dict[str, Callable[[Sequence[RunInfo], Sequence[RunInfo]], dict[str, pd.DataFrame]]] = {
    "fig6a": lambda used, listed: import_fig6a(used),
    "fig6a_paper": lambda used, listed: _renamed(import_fig6a(used), "fig6a", "fig6a_paper"),
    "fig8": import_fig8,
    "fig8_stable": lambda used, listed: _renamed(
        import_fig8(used, listed, "extent"), "fig8", "fig8_stable"
    ),  # its figure's box comparison
}

#: figures whose runs must be of the figure's own tasks (``task=`` of its run labels): a
#: paper-scale sweep imported as ``fig6a`` would replace the CPU default's tables, and a
#: ``fig8_stable`` sweep imported as ``fig8`` (or the reverse) would replace the other's
CHECKS_TASKS = {"fig6a", "fig6a_paper", "fig8", "fig8_stable"}


def check_tasks(name: str, runs: Sequence[RunInfo]) -> None:
    """A CobelError naming the figure the runs belong to when a run of ``runs`` is not of one
    of figure ``name``'s tasks (only for :data:`CHECKS_TASKS`; runs without a manifest pass)."""
    if name not in CHECKS_TASKS:
        return
    from cobelrun.figures import registry

    def tasks(figure: str) -> set[str]:
        return {o.split("=", 1)[1] for ovs in registry.get(figure).runs.values() for o in ovs
                if o.startswith("task=")}  # fmt: skip

    allowed = tasks(name)
    for r in runs:
        task = r.manifest.get("task")
        if task is None or task in allowed:
            continue
        owner = [f for f in sorted(CHECKS_TASKS) if task in tasks(f)]
        hint = f"; these are {owner[0]}'s runs: give {owner[0]} --runs" if owner else ""
        raise CobelError(f"{name} --runs: {_describe(r)} is a run of task={task}, not of "
                         f"{name}'s tasks ({', '.join(sorted(allowed))}){hint}")  # fmt: skip


#: figures whose per-run table also lists unfinished runs (with ``complete`` false)
LISTS_UNFINISHED = {"fig8", "fig8_stable"}


def import_runs(
    name: str,
    paths: Sequence[Path],
    *,
    out_dir: Path,
    finished_only: bool = False,
) -> list[Path]:
    """Read figure ``name``'s runs under ``paths`` and write its tables and sidecars to
    ``out_dir`` (``TABLE_partial`` where runs are unfinished); returns the CSVs written.
    Everything is checked and computed before anything is written."""
    from cobelrun.figures.tables import write_table

    if name not in IMPORTERS:
        raise CobelError(f"no run import for figure {name!r}{suggest(name, IMPORTERS)}; "
                         f"allowed: {allowed_list(IMPORTERS)}")  # fmt: skip
    runs, sweeps = scan(paths)
    check_tasks(name, runs)
    # fig8's per-run table lists the unfinished runs' snapshots too (flagged, never averaged);
    # with no run finished it is written alone (the snapshots so far, no summary)
    lists = name in LISTS_UNFINISHED
    used = select(runs, finished_only, none_ok=lists)
    partial = len(used) < len(runs)
    listed = runs if lists else used
    tables = IMPORTERS[name](used, listed)
    if not used:
        tables = {k: v for k, v in tables.items() if k.endswith("_runs")}
    command = (f"python -m cobelrun.figures.data {name} --runs {' '.join(map(str, paths))}"
               + (" --finished-only" if finished_only else ""))  # fmt: skip
    if partial:
        what = (f"the means are over the {len(used)} finished ones only" if used else
                "only the per-run table is written (the snapshots so far), no means")  # fmt: skip
        print(f"cobel: warning: {name}: {len(runs) - len(used)} of {len(runs)} runs are not "
              f"finished; {what} (tables *_partial; the slowest runs, e.g. a Fig. 8 run whose "
              "layer died, are left out)", file=sys.stderr)  # fmt: skip
    written = []
    for table, frame in tables.items():
        stem = f"{table}_partial" if partial else table
        prov = provenance(stem, runs, used, sweeps, command)
        prov["export_cpus"] = os.cpu_count()
        written.append(write_table(frame, prov, out_dir, stem))
    return written
