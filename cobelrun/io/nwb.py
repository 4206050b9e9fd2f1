"""Export a run folder to Neurodata Without Borders (NWB) files, one per run (pynwb).

What goes where (NWB's own types, so NWB tools and ``nwbinspector`` read the files):

- session: ``session_description`` (the task's description and the overrides the run was
  made with), ``identifier`` (config hash + run),
  ``session_start_time`` (the manifest's start), ``keywords``, ``notes`` (the resolved
  config as YAML), ``source_script`` (the cobel command);
- ``subject``: the agent (``subject_id`` = agent class + run, ``description`` = its
  parameters; species NCBI taxon 32630 "synthetic construct", since NWB wants a Latin
  binomial or an NCBI taxon link);
- ``trials``: one row per trial with ``start_time``/``stop_time`` on the simulated clock (one
  step = 0.1 s, trials back to back), ``trial``, ``phase``, ``reward``, ``steps``,
  ``start_state``, ``end_state``, ``terminated`` and ``response`` where the run has them;
- ``processing/behavior``: ``Position`` with the ``SpatialSeries`` ``position``, the agent's
  (x, y) when it takes each recorded step (``rate`` = 10 Hz when every step was recorded, else
  timestamps; the first sample of each trial is its start pose at the trial's ``start_time``)
  and ``end_position``, where each trial ended (after its last step, at its ``stop_time``;
  run folders with the steps table's ``next_x``/``next_y``), and the per-step reward as a
  ``TimeSeries`` (each one step after its position sample, when the step arrives);
- ``processing/network`` (deep agents with an activity-map monitor): ``activity_maps_<layer>``, a
  table with one row per (snapshot, unit) whose ``maps`` column holds the (headings, ny, nx)
  map (a ``TimeSeries`` would put the few snapshots first, which nwbinspector rightly flags);
  ``probe_grid`` (one row per grid bin: ix, iy, x, y, explored); ``units_<layer>``, a table
  describing each unit (place cell at the last snapshot, spatial information, head-direction
  MRL); and, with an activity monitor, ``activity_<layer>`` (one row per snapshot and unit).

Tabular runs have no network data; their files hold the session, subject, trials and behaviour.
Needs the ``analysis`` extra (``pip install 'cobelrun[analysis]'``).
"""

from __future__ import annotations

import json
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cobelrun.errors import CobelError
from cobelrun.io.atomic import atomic_write_bytes, disk_error

#: simulated seconds per environment step (as run.mcap's clock)
STEP_SECONDS = 0.1
#: NCBI taxon 32630 "synthetic construct": NWB wants a Latin binomial or an NCBI taxon link as
#: the species, and this is the taxon for things made, not born
SYNTHETIC_SPECIES = "http://purl.obolibrary.org/obo/NCBITaxon_32630"


def _pynwb() -> Any:
    try:
        import pynwb
    except ImportError:
        raise CobelError("NWB export needs pynwb: pip install 'cobelrun[analysis]'") from None
    return pynwb


def _read(run_dir: Path, name: str) -> pd.DataFrame | None:
    from cobelrun.io.validate import check_table

    p = run_dir / f"{name}.parquet"
    if not p.is_file():
        return None
    check_table(p)
    try:
        return pd.read_parquet(p, page_checksum_verification=True)
    except Exception as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CobelError(f"cannot read {p}: {first}") from None


def export_run_folder(run_dir: str | Path, out_dir: str | Path | None = None) -> list[Path]:
    """Write one NWB file per run of ``run_dir``; returns the files (``<out_dir>/run_NNNN.nwb``).

    ``out_dir`` default: ``<run_dir>/nwb``.
    """
    from cobelrun.results import load_manifest, load_trials

    run_dir = Path(run_dir)
    trials = load_trials(run_dir)
    manifest = load_manifest(run_dir)
    if manifest.get("status") != "completed":
        raise CobelError(
            f"{run_dir} did not complete (status {manifest.get('status')!r}); export a finished run"
        )
    config_text = (
        (run_dir / "config.yaml").read_text() if (run_dir / "config.yaml").is_file() else ""
    )
    steps = _read(run_dir, "steps")
    maps = _read_maps(run_dir)
    activity = _read(run_dir, "activity")
    out = Path(out_dir) if out_dir is not None else run_dir / "nwb"
    if out_dir is None and (out.is_symlink() or (out.exists() and not out.is_dir())):
        raise CobelError(f"{out} is not a folder of the run (a link or a file); remove it or "
                         "give --out")  # fmt: skip
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CobelError(disk_error(exc, out)) from None
    files = []
    for run in sorted(trials["run"].unique()):
        path = out / f"run_{int(run):04d}.nwb"
        nwb = build_nwbfile(
            run=int(run),
            trials=trials[trials["run"] == run],
            steps=None if steps is None else steps[steps["run"] == run],
            maps=maps,
            activity=None if activity is None else activity[activity["run"] == run],
            manifest=manifest,
            config_text=config_text,
            overrides=_overrides(run_dir, manifest),
        )
        _write_nwb(nwb, path)
        files.append(path)
    return files


def _write_nwb(nwb: Any, path: Path) -> None:
    """Write one NWB file under a temporary name, then rename it: a full disk or a folder that
    refuses writes is one line, and leaves neither a temporary nor a 0-byte ``.nwb`` file."""
    import io

    import h5py

    # built in memory, then written in one piece: HDF5 that fails to write its file (a full
    # disk) prints a traceback per open object as it is freed, which no caller can silence
    buf = io.BytesIO()
    with h5py.File(buf, "w") as f, _pynwb().NWBHDF5IO(file=f, mode="w") as nwb_io:
        nwb_io.write(nwb)
    try:
        atomic_write_bytes(path, buf.getvalue())
    except OSError as exc:
        raise CobelError(disk_error(exc, path)) from None


def _overrides(run_dir: Path, manifest: dict[str, Any]) -> list[str]:
    """The overrides the run was made with: a sweep job's own (``job.json``), else those of
    the ``cobel run`` command in the manifest (Hydra's ``hydra.*`` settings left out)."""
    from cobelrun.io.run_folder import RunFolder
    from cobelrun.io.validate import read_json_or_none as read_json

    found = (read_json(RunFolder(run_dir).job) or {}).get("overrides")
    if isinstance(found, list):
        return [str(o) for o in found]
    command = [str(c) for c in manifest.get("command") or []]
    args = command[command.index("run") + 1 :] if "run" in command else []
    return [a for a in args if "=" in a and not a.lstrip("+~").startswith("hydra")]


def _read_maps(run_dir: Path) -> tuple[pd.DataFrame, Any] | None:
    if not (run_dir / "activity_maps.parquet").is_file():
        return None
    from cobelrun.analysis.maps import load_activity_maps

    return load_activity_maps(run_dir)


def _session_description(task: dict[str, Any], name: str, overrides: list[str]) -> str:
    text = str(task.get("description") or f"cobel task {name}")
    changed = [o for o in overrides if not o.startswith("task=")]
    return f"{text} Run with: {' '.join(changed)}" if changed else text


def _start_time(manifest: dict[str, Any]) -> datetime:
    raw = manifest.get("started_at")
    try:
        t = datetime.fromisoformat(str(raw))
    except (TypeError, ValueError):
        t = datetime.now(UTC)
    return t if t.tzinfo is not None else t.replace(tzinfo=UTC)


def build_nwbfile(
    *,
    run: int,
    trials: pd.DataFrame,
    steps: pd.DataFrame | None,
    maps: tuple[pd.DataFrame, Any] | None,
    activity: pd.DataFrame | None,
    manifest: dict[str, Any],
    config_text: str,
    overrides: list[str] | None = None,
) -> Any:
    """The in-memory ``pynwb.NWBFile`` of one run (see the module docstring). ``overrides``
    (the run's command-line settings) are named in the session description, which otherwise
    repeats the task's own description."""
    pynwb = _pynwb()
    from pynwb.behavior import Position, SpatialSeries
    from pynwb.file import Subject

    config = manifest.get("config") or {}
    task = config.get("task") or {}
    agent = config.get("agent") or {}
    agent_cls = str(agent.get("_target_", "agent")).rsplit(".", 1)[-1]
    task_name = str(manifest.get("task", task.get("name", "task")))
    chash = str(manifest.get("config_hash", "nohash"))[:16]
    keywords = ["cobel", "CoBeL-RL", "reinforcement learning", "simulation", task_name, agent_cls]
    if maps is not None:
        keywords += ["place cells", "spatial activity maps"]
    nwb = pynwb.NWBFile(
        session_description=_session_description(task, task_name, overrides or []),
        identifier=f"cobel-{task_name}-{chash}-run{run}",
        session_start_time=_start_time(manifest),
        session_id=f"run {run}",
        experiment_description=(
            f"cobel simulation of task {task_name} (seed {manifest.get('seed')}, run {run}); "
            f"time is simulated: one environment step = {STEP_SECONDS} s"
        ),
        keywords=keywords,
        notes=config_text or json.dumps(config),
        source_script=" ".join(map(str, manifest.get("command") or ["cobel"])),
        source_script_file_name="cobel",
        lab="cobel (in silico)",
        institution="cobel (in silico)",
    )
    params = {k: v for k, v in agent.items() if k != "_target_"}
    nwb.subject = Subject(
        subject_id=f"{agent_cls}-run{run}",
        description=(
            f"in silico subject: artificial agent {agent.get('_target_', agent_cls)} "
            f"with parameters {json.dumps(params)}"
        ),
        species=SYNTHETIC_SPECIES,
        sex="U",
        age="P0D",
    )

    # -- trials: back to back on the simulated clock
    t = trials.sort_values("trial")
    n_steps = t["steps"].to_numpy(np.int64) if "steps" in t else np.ones(len(t), np.int64)
    starts = np.concatenate([[0], np.cumsum(n_steps)[:-1]]) * STEP_SECONDS
    stops = starts + np.maximum(n_steps, 1) * STEP_SECONDS
    columns = {
        "trial": "trial number (1-based, across phases)",
        "phase": "protocol phase",
        "reward": "reward collected in the trial",
        "steps": "steps taken (escape latency)",
        "start_state": "start state (node or gridworld state)",
        "end_state": "state the trial ended in",
        "terminated": "ended in a terminal state (else: time-out)",
        "response": "response coding of the task (1 = response)",
    }
    present = [c for c in columns if c in t]
    for c in present:
        nwb.add_trial_column(name=c, description=columns[c])
    for i, row in enumerate(t[present].itertuples(index=False)):
        values = {c: _scalar(v) for c, v in zip(present, row, strict=True)}
        nwb.add_trial(start_time=float(starts[i]), stop_time=float(stops[i]), **values)

    # -- behaviour: positions at every recorded step
    if steps is not None and len(steps) and {"x", "y"} <= set(steps):
        behavior = nwb.create_processing_module(
            name="behavior", description="the agent's position and rewards per step"
        )
        s = steps.sort_values(["trial", "step"] if "step" in steps else ["trial"])
        xy = s[["x", "y"]].to_numpy(np.float64)
        trial_start = dict(zip(t["trial"].to_numpy(), starts, strict=True))
        # step k (1-based) is taken at start + (k - 1) dt from the pose its row holds, so the
        # first sample of each trial is its start pose at the trial's start_time; its reward
        # arrives one step later, at start + k dt (the last one at the trial's stop_time)
        step_in_trial = s["step"].to_numpy() if "step" in s else np.ones(len(s))
        times = np.array([trial_start[tr] for tr in s["trial"].to_numpy()]) + (
            (step_in_trial - 1) * STEP_SECONDS
        )
        regular = len(times) == int(n_steps.sum()) and np.allclose(np.diff(times), STEP_SECONDS)

        def timing(offset: float) -> dict[str, Any]:
            if regular:
                return {"starting_time": float(times[0]) + offset, "rate": 1.0 / STEP_SECONDS}
            return {"timestamps": times + offset}

        frame = ("maze coordinates: x to the right, y up, origin at the lowest-left node; one "
                 "maze unit (a gridworld cell or the graph spacing) is one metre of the "
                 "rendered scene")  # fmt: skip
        position = Position(
            spatial_series=SpatialSeries(
                name="position",
                description="the agent's (x, y) when it takes each step: the first sample of "
                "each trial is its start position at the trial's start_time",
                data=xy,
                reference_frame=frame,
                unit="meters",
                **timing(0.0),
            )
        )
        if {"next_x", "next_y"} <= set(s):  # where each trial ended, at its stop_time
            last = s.groupby("trial", sort=True).tail(1)
            stop_of = dict(zip(t["trial"].to_numpy(), stops, strict=True))
            ends = np.array([stop_of[tr] for tr in last["trial"].to_numpy()], np.float64)
            steps = np.diff(ends)
            # NWB's best practice: a regular series as a start and a rate (nwbinspector)
            if len(ends) > 2 and np.allclose(steps, steps[0]) and steps[0] > 0:
                end_timing = {"starting_time": float(ends[0]), "rate": 1.0 / float(steps[0])}
            else:
                end_timing = {"timestamps": ends}
            position.add_spatial_series(
                SpatialSeries(
                    name="end_position",
                    description="the agent's (x, y) after each trial's last step (the goal "
                    "of a trial that reached it), at the trial's stop_time",
                    data=last[["next_x", "next_y"]].to_numpy(np.float64),
                    reference_frame=frame,
                    unit="meters",
                    **end_timing,
                )
            )
        behavior.add(position)
        if "reward" in s:
            behavior.add(
                pynwb.TimeSeries(
                    name="reward",
                    description="reward received on each step, when the step arrives",
                    data=s["reward"].to_numpy(np.float64),
                    unit="a.u.",
                    **timing(STEP_SECONDS),
                )
            )

    # -- network activity
    if maps is not None or (activity is not None and len(activity)):
        network = nwb.create_processing_module(
            name="network", description="activity of the agent's network units"
        )
        trial_end = dict(zip(t["trial"].to_numpy(), stops, strict=True))
        if maps is not None:
            _add_maps(nwb, network, maps, run, trial_end)
        if activity is not None and len(activity):
            _add_activity(network, activity, trial_end)
    return nwb


def _scalar(v: Any) -> Any:
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, bool):
        return v
    return v


def _snapshot_time(trial: int, trial_end: dict[int, float]) -> float:
    """Snapshot after trial ``trial`` (0: before training) on the simulated clock."""
    return float(trial_end.get(int(trial), 0.0))


def _add_maps(
    nwb: Any, module: Any, maps: tuple[pd.DataFrame, Any], run: int, trial_end: dict
) -> None:
    from hdmf.common import DynamicTable, VectorData

    from cobelrun.analysis.maps import maps_array
    from cobelrun.analysis.place_cells import place_cells

    df, grid = maps
    df = df[df["run"] == run]
    if not len(df):
        return
    ix, iy = np.meshgrid(np.arange(grid.nx), np.arange(grid.ny))
    gx, gy = np.meshgrid(grid.x_centres, grid.y_centres)
    module.add(
        DynamicTable(
            name="probe_grid",
            description="activity-map probe grid: one row per bin (row-major, iy then ix); "
            "explored = inside the maze (probed)",
            columns=[
                VectorData(name="ix", description="bin column", data=ix.ravel().tolist()),
                VectorData(name="iy", description="bin row (0 = lowest y)", data=iy.ravel().tolist()),
                VectorData(name="x", description="bin centre x (maze units)", data=gx.ravel().tolist()),
                VectorData(name="y", description="bin centre y (maze units)", data=gy.ravel().tolist()),
                VectorData(name="explored", description="bin inside the maze", data=grid.inside.ravel().tolist()),
            ],
        )
    )  # fmt: skip
    for layer, ldf in df.groupby("layer", sort=True):
        trials = sorted(ldf["trial"].unique())
        stack, units, heads = [], None, None
        for tr in trials:
            m, _, units, heads = maps_array(ldf[ldf["trial"] == tr], grid)
            stack.append(np.nan_to_num(m, nan=0.0).astype(np.float32))
        data = np.stack(stack)  # (snapshots, units, headings, ny, nx)
        n_snap, n_units = data.shape[:2]
        snap_trial = np.repeat(np.asarray(trials, np.int64), n_units)
        module.add(
            DynamicTable(
                name=f"activity_maps_{layer}",
                description=(
                    f"spatial activity maps of layer {layer!r}, one row per (snapshot, unit); "
                    f"'maps' has dims (heading, iy, ix) with headings "
                    f"{', '.join(f'{h:g}' for h in heads)} deg and the bins of probe_grid "
                    "(0 outside the maze); snapshots after the given trial (0: before training)"
                ),
                columns=[
                    VectorData(name="trial", description="snapshot taken after this trial", data=snap_trial.tolist()),
                    VectorData(name="time", description="end of that trial on the simulated clock (s)", data=[_snapshot_time(tr, trial_end) for tr in snap_trial]),
                    VectorData(name="unit", description="unit index in the layer", data=np.tile(np.asarray(units, np.int64), n_snap).tolist()),
                    VectorData(name="maps", description="activation at each (heading, iy, ix) pose (a.u.)", data=data.reshape(n_snap * n_units, *data.shape[2:])),
                ],
            )
        )  # fmt: skip
        pc = place_cells(stack[-1].astype(np.float64), grid.inside, headings_rad=np.deg2rad(heads))
        module.add(
            DynamicTable(
                name=f"units_{layer}",
                description=(
                    f"units of layer {layer!r} at the last snapshot (trial {int(trials[-1])}): "
                    "place-cell criterion of the paper's Fig. 8 (cobelrun.analysis.place_cells)"
                ),
                columns=[
                    VectorData(name="unit", description="unit index in the layer", data=[int(u) for u in units]),
                    VectorData(name="is_place_cell", description="passes the place-cell criterion", data=pc["is_place_cell"].astype(bool).tolist()),
                    VectorData(name="spatial_information", description="Skaggs information of the mean map (bits)", data=pc["spatial_information"].fillna(0.0).tolist()),
                    VectorData(name="hd_mrl", description="head-direction mean resultant length", data=pc["hd_mrl"].fillna(0.0).tolist()),
                ],
            )
        )  # fmt: skip


def _add_activity(module: Any, activity: pd.DataFrame, trial_end: dict) -> None:
    from hdmf.common import DynamicTable, VectorData

    for layer, ldf in activity.groupby("layer", sort=True):
        trials = sorted(ldf["trial"].unique())
        probes = np.unique(ldf["probe"].to_numpy())
        units = np.unique(ldf["unit"].to_numpy())
        data = np.zeros((len(trials), units.size, probes.size), np.float32)
        data[np.searchsorted(trials, ldf["trial"].to_numpy()),
             np.searchsorted(units, ldf["unit"].to_numpy()),
             np.searchsorted(probes, ldf["probe"].to_numpy())] = ldf["value"].to_numpy()  # fmt: skip
        snap_trial = np.repeat(np.asarray(trials, np.int64), units.size)
        module.add(
            DynamicTable(
                name=f"activity_{layer}",
                description=f"activations of layer {layer!r} for the activity monitor's probe "
                "observations, one row per (snapshot, unit); 'activity' has one value per probe",
                columns=[
                    VectorData(name="trial", description="snapshot taken after this trial", data=snap_trial.tolist()),
                    VectorData(name="time", description="end of that trial on the simulated clock (s)", data=[_snapshot_time(tr, trial_end) for tr in snap_trial]),
                    VectorData(name="unit", description="unit index in the layer", data=np.tile(units.astype(np.int64), len(trials)).tolist()),
                    VectorData(name="activity", description="activation per probe (a.u.)", data=data.reshape(-1, probes.size)),
                ],
            )
        )  # fmt: skip
