"""Batched CNN runs, whole training (issue 35, item 4): 8 runs of Fig. 6A and Fig. 8, batched vs
sequential, as whole ``cobel run`` processes.

Run on demand (not a test)::

    python benchmarks/bench_cnn_runs.py [--repeat 2] [--setting fig6a,fig8] [--runs 8]

For each setting it runs the real CLI with the same settings and seed, once with
``task.batch_runs=false`` (one run after another: SB3's DQN) and once with
``task.batch_runs=true`` (the runs as one :class:`~cobelrun.agents.batched_cnn.BatchedCNNDQN`),
alternating the two (the machine is shared) and keeping the best of each. It reports the CPU
time of each process (user + system of the child: steadier than wall time on a shared
machine), the simulation thread's CPU time the manifest records (the run loop without start-up
and writing), wall time, the training phases' wall times from the manifests, the ratios, and
how many runs are identical trial for trial. Writes ``benchmarks/results/bench_cnn_runs.json``.

Settings (the tasks' own agents and environments, fewer trials):

- ``fig6a``: ``task=tmaze_extinction_3d`` (Fig. 6A, 36 x 36 camera images, conv 16@8x8/4 ->
  32@4x4/2 -> dense 256 -> 6), acquisition and extinction shortened to ``--fig6a-trials`` each;
- ``fig8``: ``task=place_cells_original`` (Fig. 8, 12 x 48 panoramas, conv 32@5x5/1 ->
  64@4x4/2 -> 64@3x3/2 -> dense 50 -> dropout 0.35 -> 12), ``--fig8-trials`` trials, activity
  maps on a 6 x 6 grid x 2 headings every 2 trials.

``--device cuda`` adds ``agent.device=cuda`` to both sides (on a GPU machine).
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def settings(args: argparse.Namespace) -> dict[str, tuple[str, list[str]]]:
    n6, n8 = args.fig6a_trials, args.fig8_trials
    return {
        "fig6a": ("Fig. 6A (task=tmaze_extinction_3d, 36x36 images)",
                  ["task=tmaze_extinction_3d", f"task.protocol.phases.0.trials={n6}",
                   f"task.protocol.phases.1.trials={n6}", "task.record.mcap=false"]),
        "fig8": ("Fig. 8 (task=place_cells_original, 12x48 panoramas, dropout 0.35)",
                 ["task=place_cells_original", f"task.protocol.phases=[{{name: training, trials: {n8}}}]",
                  "task.monitors.maps.grid=[6,6]", "task.monitors.maps.headings=2",
                  "task.monitors.maps.every=2"]),
    }  # fmt: skip


def cobel() -> list[str]:
    exe = Path(sys.executable).with_name("cobel")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "cobelrun.cli"]


def run_once(overrides: list[str], batch: str, folder: Path) -> dict:
    """One whole ``cobel run`` process: its wall and CPU seconds and its manifest."""
    if folder.exists():
        shutil.rmtree(folder)
    cmd = [*cobel(), "run", *overrides, f"task.batch_runs={batch}", f"hydra.run.dir={folder}"]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    manifest = json.loads((folder / "manifest.json").read_text())
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    phases = manifest.get("phase_wall_time_s") or {}
    sim = (manifest.get("cpu_time_s") or {}).get("simulation_thread")
    return {"wall_s": wall, "cpu_s": cpu, "sim_cpu_s": sim, "batch_runs": manifest.get("batch_runs"),
            "phases_s": float(sum(phases.values())) if phases else None}  # fmt: skip


def identical_runs(seq: Path, bat: Path) -> tuple[int, int, bool]:
    import pandas as pd

    a, b = pd.read_parquet(seq / "trials.parquet"), pd.read_parquet(bat / "trials.parquet")
    same_schema = list(a.columns) == list(b.columns) and a.dtypes.equals(b.dtypes)
    runs = sorted(a["run"].unique())
    same = sum(a[a.run == r].reset_index(drop=True).equals(b[b.run == r].reset_index(drop=True))
               for r in runs)  # fmt: skip
    return int(same), len(runs), bool(same_schema)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--setting", default="fig6a,fig8", help="fig6a and/or fig8")
    ap.add_argument("--runs", type=int, default=8, help="runs per task (one batch)")
    ap.add_argument("--repeat", type=int, default=2, help="alternating rounds; best kept")
    ap.add_argument("--fig6a-trials", type=int, default=6, help="trials per Fig. 6A phase")
    ap.add_argument("--fig8-trials", type=int, default=3, help="Fig. 8 training trials")
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--out", type=Path, default=RESULTS / "bench_cnn_runs.json")
    args = ap.parse_args()
    table = settings(args)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_cnn_runs_") as tmp:
        for name in args.setting.split(","):
            if name not in table:
                raise SystemExit(f"unknown --setting '{name}'; allowed: {', '.join(table)}")
            label, overrides = table[name]
            overrides = [*overrides, f"task.runs={args.runs}", "task.save_agents=none",
                         f"agent.device={args.device}"]  # fmt: skip
            best: dict[str, dict] = {}
            for rep in range(args.repeat):
                for side, batch in (("sequential", "false"), ("batched", "true")):
                    got = run_once(overrides, batch, Path(tmp) / name / side)
                    print(f"{name} round {rep + 1} {side:10s}: {got['cpu_s']:7.1f} s CPU "
                          f"(simulation thread {got['sim_cpu_s']} s), {got['wall_s']:7.1f} s wall, "
                          f"phases {got['phases_s']} s", flush=True)  # fmt: skip
                    if side not in best or got["cpu_s"] < best[side]["cpu_s"]:
                        best[side] = got
            same, n, schema = identical_runs(Path(tmp) / name / "sequential",
                                             Path(tmp) / name / "batched")  # fmt: skip
            s, b = best["sequential"], best["batched"]
            row = {"setting": name, "label": label, "runs": args.runs, "sequential": s,
                   "batched": b, "cpu_ratio": s["cpu_s"] / b["cpu_s"],
                   "wall_ratio": s["wall_s"] / b["wall_s"],
                   "phases_ratio": (s["phases_s"] / b["phases_s"]
                                    if s["phases_s"] and b["phases_s"] else None),
                   "sim_cpu_ratio": (s["sim_cpu_s"] / b["sim_cpu_s"]
                                     if s["sim_cpu_s"] and b["sim_cpu_s"] else None),
                   "identical_runs": f"{same}/{n}", "same_schema": schema}  # fmt: skip
            rows.append(row)
            print(f"{label}: {args.runs} runs, CPU {s['cpu_s']:.1f} s vs {b['cpu_s']:.1f} s "
                  f"({row['cpu_ratio']:.2f}x), wall {row['wall_ratio']:.2f}x, identical runs "
                  f"{same}/{n}", flush=True)  # fmt: skip
    import torch

    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({
        "machine": platform.platform(), "processor": platform.processor(),
        "torch": torch.__version__, "device": args.device, "rows": rows,
    }, indent=2))  # fmt: skip
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
