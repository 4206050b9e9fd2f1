"""Batched deep-agent runs (issue 18, item 3): sequential vs ``task.batch_runs`` end to end.

Run on demand (not a test)::

    python benchmarks/bench_batched.py [--runs 100] [--repeat 1] [--task two_afc ...]
    python benchmarks/bench_batched.py --task two_afc_per --per-runs 20   # PER-DQN, Fig. 9
    python benchmarks/bench_batched.py --tree-only                        # the sum tree's cost

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

With prioritized replay (``two_afc_per``) it also measures what the batched sum tree costs
per gradient step (:func:`tree_cost`): the tree operations of one batched PER step of R runs
(stratified draws, search, priority update) against R sequential ``SumTree`` s doing the same,
and a whole batched gradient step with prioritized against uniform replay.
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
    "two_afc_per": (
        "Fig. 9 with prioritized replay (task=two_afc, agent.prioritized=true)",
        ["task=two_afc", "agent.prioritized=true"],
    ),
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


def _per_learner(runs: int, prioritized: bool, steps: int, seed: int = 0) -> object:
    """A batched Fig. 9 DQN learner of ``runs`` runs whose buffers hold ``steps`` random
    transitions each (two_afc's 4 one-hot stimuli, 2 actions)."""
    import numpy as np

    from cobelrun.api import compose
    from cobelrun.runner import build_task, run_seed

    task = build_task(compose(None, ["task=two_afc", f"agent.prioritized={prioritized}",
                                     f"task.runs={runs}", "task.batch_runs=false"]))  # fmt: skip
    seeds = [run_seed(0, r)[0] for r in range(runs)]
    learner = task.make_agent(seed=seeds[0]).batch_learner(seeds, steps)
    rng = np.random.default_rng(seed)
    eye = np.eye(learner.obs_dim, dtype=np.float32)
    every = np.arange(runs)
    for _ in range(steps):
        s = rng.integers(learner.obs_dim, size=runs)
        learner._store(every, eye[s], eye[s], rng.integers(2, size=runs),
                       (rng.random(runs) < 0.5).astype(float), np.ones(runs, bool))  # fmt: skip
    return learner


def tree_cost(runs: int = 20, batch: int = 32, capacity: int = 100, reps: int = 2000) -> dict:
    """Microseconds per gradient step of R runs: the sum tree's part of prioritized replay
    (draws, stratified search, weights, priority update) batched vs R sequential SumTrees,
    and a whole batched gradient step with prioritized vs uniform replay."""
    import numpy as np
    import torch

    from cobelrun.agents.per import SumTree

    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    init = rng.random((runs, capacity))
    trees = [SumTree(capacity) for _ in range(runs)]
    for t, p in zip(trees, init, strict=True):
        t.update(np.arange(capacity), p)
    gens = [np.random.default_rng(r) for r in range(runs)]
    new = rng.random((reps, runs, batch)) + 1e-6

    def sequential(k: int) -> None:
        for r, t in enumerate(trees):  # PrioritizedReplayBuffer.sample + update_priorities
            total = t.total
            u = (np.arange(batch) + gens[r].random(batch)) * (total / batch)
            idx = np.minimum(t.find(np.minimum(u, np.nextafter(total, 0.0))), capacity - 1)
            w = (capacity * t[idx] / total) ** -0.4 / (capacity * t.min / total) ** -0.4
            w.astype(np.float32)
            t.update(idx, new[k, r] ** 0.6)

    learner = _per_learner(runs, True, capacity)
    learner.tree.update(np.arange(runs)[:, None], np.arange(capacity), init)
    every = np.arange(runs)

    def batched(k: int) -> None:
        idx, _w = learner._sample_prioritized(every)
        learner.tree.update(every[:, None], idx, new[k] ** 0.6)

    out = {"runs": runs, "batch": batch, "capacity": capacity}
    for name, fn in (("sequential_trees_us", sequential), ("batched_tree_us", batched)):
        t0 = time.perf_counter()
        for k in range(reps):
            fn(k)
        out[name] = round((time.perf_counter() - t0) / reps * 1e6, 1)
    train = np.ones(runs, bool)
    for prioritized in (False, True):
        lrn = learner if prioritized else _per_learner(runs, False, capacity)
        n = reps // 4
        lrn._gradient_step(train)
        t0 = time.perf_counter()
        for _ in range(n):
            lrn._gradient_step(train)
        key = "per_gradient_step_us" if prioritized else "uniform_gradient_step_us"
        out[key] = round((time.perf_counter() - t0) / n * 1e6, 1)
    out["tree_share_of_per_step"] = round(out["batched_tree_us"] / out["per_gradient_step_us"], 3)
    print(f"sum tree per gradient step of {runs} runs (batch {batch}, {capacity} leaves): "
          f"batched {out['batched_tree_us']} us vs {runs} sequential SumTrees "
          f"{out['sequential_trees_us']} us; whole batched gradient step: prioritized "
          f"{out['per_gradient_step_us']} us vs uniform {out['uniform_gradient_step_us']} us "
          f"(the tree part: {out['tree_share_of_per_step']:.0%})")  # fmt: skip
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=100)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--task", action="append", choices=sorted(TASKS))
    ap.add_argument("--fig7-runs", type=int, default=20)
    ap.add_argument("--per-runs", type=int, default=20, help="runs of the two_afc_per case")
    ap.add_argument("--tree-only", action="store_true", help="only the sum tree's cost")
    ap.add_argument(
        "--fig7-trials", type=int, default=10, help="trials of each Fig. 7 phase (the paper: 100)"
    )
    args = ap.parse_args()
    rows = []
    tree = None
    names = [] if args.tree_only else (args.task or list(TASKS))
    if args.tree_only or "two_afc_per" in names:
        tree = tree_cost(runs=args.per_runs)
    tmp = Path(tempfile.mkdtemp(prefix="bench_batched_"))
    try:
        for name in names:
            label, overrides = TASKS[name]
            runs = args.runs
            if name == "latent_learning":
                runs = args.fig7_runs
                t = args.fig7_trials
                overrides = [*overrides, f"task.protocol.phases.0.trials={t}",
                             f"task.protocol.phases.1.trials={t}"]  # fmt: skip
                label += f", {t} + {t} trials"
            if name == "two_afc_per":
                runs = args.per_runs
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
                       "load": os.getloadavg()}, "rows": rows, "sum_tree": tree}  # fmt: skip
    (RESULTS / "bench_batched.json").write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
