"""Batched deep-agent runs (issue 18, item 3): sequential vs ``task.batch_runs`` end to end.

Run on demand (not a test)::

    python benchmarks/bench_batched.py [--runs 100] [--repeat 1] [--task two_afc ...]

For each task it runs the real CLI twice with the same settings and seed, once with
``task.batch_runs=false`` (one run after another, the sequential SB3 path) and once with
``task.batch_runs=true`` (all runs as one batched computation), each as a whole process
(``cobel run ...``: start-up, composing, training, writing the run folder), and prints both
wall times and their ratio, the CPU time of each process (less sensitive to other load on
a shared machine) and the training phase times the manifests record. Repeats
alternate the two sides (the machine is shared) and the best of each is kept. It also checks
that the two folders hold the same trials table schema and how many runs are identical
trial for trial (a batched run follows its sequential twin until a rounding difference
flips a greedy choice). Writes ``benchmarks/results/bench_batched.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"

#: figure settings: (label, cobel run overrides)
TASKS = {
    "two_afc": ("Fig. 9 (task=two_afc, agent=dqn_paper)", ["task=two_afc"]),
    # Fig. 7's latent group with Dyna-DSR; --fig7-trials shortens both phases (the full
    # 100 + 100 trials take ~10-30 min sequentially on the 2 shared cores)
    "latent_learning": (
        "Fig. 7 latent group (task=latent_learning, Dyna-DSR)",
        ["task=latent_learning"],
    ),
}


def cobel() -> list[str]:
    exe = Path(sys.executable).with_name("cobel")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "cobelrun.cli"]


def run_once(overrides: list[str], batch: str, folder: Path) -> tuple[float, dict]:
    if folder.exists():
        shutil.rmtree(folder)
    cmd = [*cobel(), "run", *overrides, f"task.batch_runs={batch}", f"hydra.run.dir={folder}"]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    manifest = json.loads((folder / "manifest.json").read_text())
    manifest["cpu_s"] = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, manifest


def identical_runs(seq: Path, bat: Path) -> tuple[int, int, bool]:
    import pandas as pd

    a, b = pd.read_parquet(seq / "trials.parquet"), pd.read_parquet(bat / "trials.parquet")
    same_schema = list(a.columns) == list(b.columns) and a.dtypes.equals(b.dtypes)
    runs = sorted(a["run"].unique())
    same = sum(a[a.run == r].reset_index(drop=True).equals(b[b.run == r].reset_index(drop=True))
               for r in runs)  # fmt: skip
    return int(same), len(runs), bool(same_schema)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=100)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--task", action="append", choices=sorted(TASKS))
    ap.add_argument("--fig7-runs", type=int, default=20)
    ap.add_argument(
        "--fig7-trials", type=int, default=10, help="trials of each Fig. 7 phase (the paper: 100)"
    )
    args = ap.parse_args()
    rows = []
    tmp = Path(tempfile.mkdtemp(prefix="bench_batched_"))
    try:
        for name in args.task or list(TASKS):
            label, overrides = TASKS[name]
            runs = args.runs
            if name == "latent_learning":
                runs = args.fig7_runs
                t = args.fig7_trials
                overrides = [*overrides, f"task.protocol.phases.0.trials={t}",
                             f"task.protocol.phases.1.trials={t}"]  # fmt: skip
                label += f", {t} + {t} trials"
            overrides = [*overrides, f"task.runs={runs}"]
            best: dict[str, tuple[float, dict]] = {}
            for _ in range(args.repeat):
                for batch in ("false", "true"):
                    wall, manifest = run_once(overrides, batch, tmp / f"{name}_{batch}")
                    if batch not in best or wall < best[batch][0]:
                        best[batch] = (wall, manifest)
            same, n, schema = identical_runs(tmp / f"{name}_false", tmp / f"{name}_true")
            seq, bat = best["false"], best["true"]
            row = {
                "task": name, "label": label, "runs": runs,
                "sequential_s": round(seq[0], 2), "batched_s": round(bat[0], 2),
                "ratio": round(seq[0] / bat[0], 2),
                "sequential_cpu_s": round(seq[1]["cpu_s"], 2),
                "batched_cpu_s": round(bat[1]["cpu_s"], 2),
                "cpu_ratio": round(seq[1]["cpu_s"] / bat[1]["cpu_s"], 2),
                "sequential_training_s": seq[1].get("phase_wall_time_s"),
                "batched_training_s": bat[1].get("phase_wall_time_s"),
                "runs_at_once": bat[1].get("batch_runs", {}).get("runs_at_once"),
                "identical_runs": f"{same}/{n}", "same_schema": schema,
            }  # fmt: skip
            rows.append(row)
            print(f"{label}, {runs} runs: sequential {row['sequential_s']:.1f} s, batched "
                  f"{row['batched_s']:.1f} s, ratio {row['ratio']:.1f}x end to end (CPU time "
                  f"{row['sequential_cpu_s']:.1f} s vs {row['batched_cpu_s']:.1f} s: "
                  f"{row['cpu_ratio']:.1f}x) "
                  f"(training phases {seq[1].get('phase_wall_time_s')} vs "
                  f"{bat[1].get('phase_wall_time_s')}); runs identical trial for trial: "
                  f"{same}/{n}; same trials schema: {schema}")  # fmt: skip
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    RESULTS.mkdir(exist_ok=True)
    out = {"machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                       "load": os.getloadavg()}, "rows": rows}  # fmt: skip
    (RESULTS / "bench_batched.json").write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
