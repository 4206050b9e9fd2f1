"""run.mcap writer speed and size: McapRecorder (foxglove-sdk, protobuf) vs the JSON writer it
replaced (``McapStreamWriter`` of ``--old-ref``, loaded from git).

Run on demand (not a test)::

    python benchmarks/bench_mcap.py [--poses 200000] [--repeats 3] [--old-ref 84af8c3]
                                    [--out benchmarks/results/bench_mcap.json]

Workload: random walks on the paper's 7 x 7 T-maze (Fig. 6B) with 20 steps per trial, so the
poses repeat a few dozen (cell, heading) pairs as a real run's do. Measured per writer, each in a
file of its own (best of ``--repeats``, zstd, CRCs on, 64k poses per call as the recorder does):

* ``poses``: poses/s and bytes/pose on disk (whole file / poses);
* ``trial events``: events/s (start + end per trial) and bytes/event, the old writer's time
  including the JSON formatting the recorder did for it (``Recorder._write_trial_events``).

The old writer builds JSON text with numpy and appends it to chunks through private internals
of ``mcap`` < 1.7; the new one makes one foxglove message object and one ``log`` call per
message (Rust serialisation and compression).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cobelrun.envs.gridworld import ACTION_HEADING, START_HEADING  # noqa: E402
from cobelrun.envs.world import tmaze_paper  # noqa: E402
from cobelrun.io.mcap import McapRecorder  # noqa: E402

STEP_NS = 100_000_000
BATCH = 1 << 16
STEPS_PER_TRIAL = 20
START_NS = 1_763_900_000_000_000_000


def walk(n_poses: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Random walks on the T-maze: (state, action) per pose, trials of STEPS_PER_TRIAL steps."""
    w = tmaze_paper()
    rng = np.random.default_rng(seed)
    nxt = np.argmax(w.T, axis=2)  # (S, A) main outcome
    start = int(w.starts[0])
    states = np.empty(n_poses, np.int64)
    actions = np.full(n_poses, -1, np.int64)  # -1: trial start
    s = start
    for i in range(n_poses):
        if i % (STEPS_PER_TRIAL + 1) == 0:
            s = start
        else:
            a = int(rng.integers(4))
            s = int(nxt[s, a])
            actions[i] = a
        states[i] = s
    heading = np.where(actions >= 0, ACTION_HEADING[np.maximum(actions, 0)], START_HEADING)
    poses = np.column_stack([w.coords[states], heading])
    n_trials = n_poses // (STEPS_PER_TRIAL + 1)
    t = START_NS + np.arange(n_poses, dtype=np.int64) * STEP_NS
    first = np.arange(n_trials) * (STEPS_PER_TRIAL + 1)
    return {
        "t": t,
        "states": states,
        "codes": np.where(actions >= 0, actions, 4),
        "poses": poses,
        "coords": w.coords,
        "trial": np.arange(1, n_trials + 1),
        "t_start": t[first],
        "t_end": t[first + STEPS_PER_TRIAL],
        "start_state": states[first],
        "end_state": states[first + STEPS_PER_TRIAL],
        "steps": np.full(n_trials, STEPS_PER_TRIAL),
        "reward": (states[first + STEPS_PER_TRIAL] == 6).astype(float),
        "response": (states[first + STEPS_PER_TRIAL] == 6).astype(np.int8),
    }


def load_old(ref: str) -> ModuleType | None:
    """The JSON writer module of git ``ref`` (None if git or the file is not there)."""
    try:
        src = subprocess.run(["git", "show", f"{ref}:cobelrun/io/mcap.py"], cwd=ROOT,
                             capture_output=True, text=True, check=True).stdout  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        return None
    if "class McapStreamWriter" not in src or "_BulkAppender" not in src:
        return None
    path = Path(tempfile.mkdtemp()) / "old_mcap.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("cobel_old_mcap", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def old_events(d: dict[str, np.ndarray], phase: str = "acquisition") -> tuple[np.ndarray, list]:
    """The recorder's JSON for the old writer (Recorder._write_trial_events on main)."""
    tail = ',"run":%d,"trial":%d,"phase":' + json.dumps(phase).replace("%", "%%") + "}"
    start_fmt = '{"event":"start","start_state":%d' + tail
    end_fmt = '{"event":"end","steps":%d,"reward":%r,"end_state":%d' + tail
    n = len(d["trial"])
    runs = [0] * n
    trials = d["trial"].tolist()
    starts = "\n".join([start_fmt] * n) % tuple(
        x for row in zip(d["start_state"].tolist(), runs, trials, strict=True) for x in row
    )
    ends = "\n".join([end_fmt] * n) % tuple(
        x
        for row in zip(
            d["steps"].tolist(),
            d["reward"].tolist(),
            d["end_state"].tolist(),
            runs,
            trials,
            strict=True,
        )
        for x in row
    )
    messages: list[Any] = [None] * (2 * n)
    messages[0::2] = starts.encode().split(b"\n")
    messages[1::2] = ends.encode().split(b"\n")
    times = np.empty(2 * n, np.int64)
    times[0::2] = d["t_start"]
    times[1::2] = d["t_end"]
    return times, messages


def bench_new(d: dict[str, np.ndarray], tmp: Path) -> dict[str, float]:
    n = len(d["t"])
    f = tmp / "new_poses.mcap"
    t0 = time.perf_counter()
    with McapRecorder(f, start_ns=START_NS) as rec:
        for i in range(0, n, BATCH):
            rec.write_poses(0, d["t"][i : i + BATCH], d["poses"][i : i + BATCH])
    poses_s = time.perf_counter() - t0
    size_poses = f.stat().st_size
    g = tmp / "new_events.mcap"
    t0 = time.perf_counter()
    with McapRecorder(g, start_ns=START_NS) as rec:
        rec.write_trial_events(0, d["trial"], "acquisition", d["t_start"], d["t_end"],
                               d["start_state"], d["end_state"], d["steps"], d["reward"],
                               d["response"])  # fmt: skip
    events_s = time.perf_counter() - t0
    return {"poses_s": poses_s, "bytes_poses": size_poses, "events_s": events_s,
            "bytes_events": g.stat().st_size}  # fmt: skip


def bench_old(mod: ModuleType, d: dict[str, np.ndarray], tmp: Path) -> dict[str, float]:
    n = len(d["t"])
    coords = d["coords"]
    headings = np.append(ACTION_HEADING, START_HEADING)
    table = (np.repeat(coords[:, 0], 5), np.repeat(coords[:, 1], 5), np.tile(headings, len(coords)))
    pose_id = d["states"] * 5 + d["codes"]
    f = tmp / "old_poses.mcap"
    t0 = time.perf_counter()
    with mod.McapStreamWriter(f) as w:
        for i in range(0, n, BATCH):
            w.write_indexed_poses(d["t"][i : i + BATCH], pose_id[i : i + BATCH], *table)
    poses_s = time.perf_counter() - t0
    size_poses = f.stat().st_size
    g = tmp / "old_events.mcap"
    t0 = time.perf_counter()
    times, messages = old_events(d)
    with mod.McapStreamWriter(g) as w:
        w.write_json_batch(w.TRIAL_TOPIC, times, messages)
    events_s = time.perf_counter() - t0
    return {"poses_s": poses_s, "bytes_poses": size_poses, "events_s": events_s,
            "bytes_events": g.stat().st_size}  # fmt: skip


def summarise(runs: list[dict[str, float]], n_poses: int, n_events: int) -> dict[str, float]:
    best_p = min(r["poses_s"] for r in runs)
    best_e = min(r["events_s"] for r in runs)
    return {
        "poses_per_s": round(n_poses / best_p),
        "bytes_per_pose": round(runs[0]["bytes_poses"] / n_poses, 2),
        "trial_events_per_s": round(n_events / best_e),
        "bytes_per_trial_event": round(runs[0]["bytes_events"] / n_events, 2),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=200_000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--old-ref", default="84af8c3", help="git ref with the JSON writer")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/bench_mcap.json")
    args = ap.parse_args()
    d = walk(args.poses)
    n_events = 2 * len(d["trial"])
    old = load_old(args.old_ref)
    result: dict[str, Any] = {
        "poses": args.poses,
        "trial_events": n_events,
        "repeats": args.repeats,
        "host": platform.node(),
        "cpus": os.cpu_count(),
        "load_avg": os.getloadavg()[0],
        "python": platform.python_version(),
    }
    with tempfile.TemporaryDirectory() as tmp:
        new_runs, old_runs = [], []
        for _ in range(args.repeats):  # alternate, so both see the same machine load
            new_runs.append(bench_new(d, Path(tmp)))
            if old is not None:
                old_runs.append(bench_old(old, d, Path(tmp)))
    result["new (foxglove-sdk, protobuf)"] = summarise(new_runs, args.poses, n_events)
    if old_runs:
        result[f"old (JSON, {args.old_ref})"] = summarise(old_runs, args.poses, n_events)
    else:
        result["old"] = f"not measured: no JSON writer at git ref {args.old_ref}"
    print(json.dumps(result, indent=2))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
