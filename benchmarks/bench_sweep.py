"""Sweep speed: joblib scaling (1 vs 2 workers) and the per-job overhead of a sweep.

Run on demand (not a test)::

    python benchmarks/bench_sweep.py [--jobs 20] [--runs 100] [--repeats 3]
                                     [--out benchmarks/results/bench_sweep.json]

Measures, through the real CLI in subprocesses:

* ``scaling``: a sweep of ``--jobs`` tmaze_extinction jobs (``task.runs=--runs``, 200 trials each;
  100 runs is the task's default) on 1 and on 2 joblib workers, ``--repeats`` times, the two
  alternating so that both see the same machine; wall times, the speed-up of the medians and of
  each pair;
* ``overhead``: sweeps of 1 and of ``--jobs`` near-empty jobs (1 run of 2 trials) on 1 worker;
  per-job overhead = (wall(N) - wall(1)) / (N - 1): what a job costs beyond its simulation
  (config composition in the sweeper and the worker, job/status files, run folder setup);
* ``process``: wall time of a whole ``cobel run`` of a near-empty task (interpreter start,
  imports, composition, validation): the fixed cost of any command, paid once per sweep with
  joblib (workers are reused) and once per job with submitit.

The load average and the machine's CPU ceiling (speed-up of two pure-CPU processes over one,
ideally 2.0) are recorded: on a shared or oversubscribed machine no 2-worker sweep can beat it.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TINY = ["task.runs=1", "task.protocol.phases.0.trials=1", "task.protocol.phases.1.trials=1"]


def cobel() -> list[str]:
    exe = shutil.which("cobel", path=str(Path(sys.executable).parent)) or shutil.which("cobel")
    return [exe] if exe else [sys.executable, "-m", "cobelrun.cli"]


def timed(args: list[str], results: Path, **env_vars: str) -> float:
    env = {**os.environ, "COBEL_RESULTS": str(results), "COBEL_PROGRESS": "0", **env_vars}
    t0 = time.perf_counter()
    proc = subprocess.run([*cobel(), *args], env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"cobel {' '.join(args)} failed:\n{proc.stderr}")
    return wall


def sweep(tmp: Path, name: str, n_jobs: int, workers: int, extra: list[str], **env: str) -> dict:
    sweep_dir = tmp / name
    shutil.rmtree(sweep_dir, ignore_errors=True)
    seeds = f"seed=range(0,{n_jobs})"
    wall = timed(["run", "-m", "task=tmaze_extinction", seeds, *extra,
                  f"hydra.launcher.n_jobs={workers}", f"hydra.sweep.dir={sweep_dir}"], tmp,
                 **env)  # fmt: skip
    sims = [json.loads((d / "manifest.json").read_text())["wall_time_s"]
            for d in sweep_dir.glob("[0-9]*")]  # fmt: skip
    return {"jobs": n_jobs, "workers": workers, "wall_s": round(wall, 3),
            "simulation_s_sum": round(sum(sims), 3)}  # fmt: skip


def _spin(_: int) -> float:
    t0 = time.perf_counter()
    s = 0
    for i in range(30_000_000):
        s += i
    return time.perf_counter() - t0


def cpu_ceiling() -> float:
    """Speed-up of 2 pure-CPU processes over 1 on this machine right now (ideal: 2.0).

    On shared or oversubscribed machines this is the upper bound for any 2-worker speed-up.
    """
    import multiprocessing as mp

    t0 = time.perf_counter()
    _spin(0)
    one = time.perf_counter() - t0
    with mp.get_context("spawn").Pool(2) as pool:
        pool.map(_spin, [0, 1])  # start the workers
        t0 = time.perf_counter()
        pool.map(_spin, [0, 1])
        two = time.perf_counter() - t0
    return round(2 * one / two, 3)


def _median(xs: list[float]) -> float:
    return float(statistics.median(xs))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=20)
    ap.add_argument("--runs", type=int, default=100, help="task.runs of each scaling job")
    ap.add_argument("--repeats", type=int, default=3, help="1- and 2-worker sweeps, alternating")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/bench_sweep.json")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="cobel-bench-") as t:
        tmp = Path(t)
        timed(
            ["run", "task=tmaze_extinction", *TINY, f"hydra.run.dir={tmp}/warm"], tmp
        )  # numba cache
        load0 = os.getloadavg()
        process = [timed(["run", "task=tmaze_extinction", *TINY, f"hydra.run.dir={tmp}/p{i}"], tmp)
                   for i in range(3)]  # fmt: skip
        small = [f"task.runs={a.runs}"]
        one, two, ceilings = [], [], []
        for r in range(a.repeats):
            ceilings.append(cpu_ceiling())
            one.append(sweep(tmp, "w1", a.jobs, 1, small))
            two.append(sweep(tmp, "w2", a.jobs, 2, small))
            print(f"repeat {r + 1}/{a.repeats}: 1 worker {one[-1]['wall_s']:.2f} s, "
                  f"2 workers {two[-1]['wall_s']:.2f} s, "
                  f"CPU ceiling {ceilings[-1]:.2f}", file=sys.stderr)  # fmt: skip
        ceilings.append(cpu_ceiling())
        o1 = sweep(tmp, "o1", 1, 1, TINY)
        on = sweep(tmp, "on", a.jobs, 1, TINY)
        load1 = os.getloadavg()
    walls = {k: [x["wall_s"] for x in v] for k, v in (("one", one), ("two", two))}
    per_job = (on["wall_s"] - o1["wall_s"]) / (a.jobs - 1)
    sim_per_job = _median([x["simulation_s_sum"] for x in one]) / a.jobs
    result = {
        "benchmark": "bench_sweep",
        "host": platform.node(),
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "loadavg_before": [round(x, 2) for x in load0],
        "loadavg_after": [round(x, 2) for x in load1],
        "scaling": {
            "task": f"tmaze_extinction task.runs={a.runs} (200 trials per run), {a.jobs} jobs",
            "repeats": a.repeats,
            "one_worker": one,
            "two_workers": two,
            "speedup": round(_median(walls["one"]) / _median(walls["two"]), 3),
            "speedup_per_repeat": [
                round(x / y, 3) for x, y in zip(walls["one"], walls["two"], strict=True)
            ],
            "target_speedup": 1.7,
            "cpu_ceiling_speedups": ceilings,
            "cpu_ceiling_median": round(_median(ceilings), 3),
        },
        "overhead": {
            "one_tiny_job": o1,
            "n_tiny_jobs": on,
            "per_job_overhead_s": round(per_job, 4),
            "simulation_per_scaling_job_s": round(sim_per_job, 3),
            "overhead_share_of_scaling_job": round(per_job / (per_job + sim_per_job), 3),
        },
        "process": {"cobel_run_tiny_wall_s": [round(x, 3) for x in process]},
    }
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
