"""Tabular speed benchmark (issue 3): compiled Dyna-Q vs the Python slow path vs a reference.

Run on demand (not a test)::

    python benchmarks/bench_tabular.py [--quick] [--skip-e2e] [--repeat N]

Prints a table and writes ``benchmarks/results/tabular.json``. Measures

* env steps/s of (a) cobel's compiled trial kernel (``agent.engine=auto``), (b) cobel's Python
  step-by-step path (``agent.engine=python``) and (c) the plain-Python reference Dyna-Q in the
  original's style (``benchmarks/reference_dyna_q.py``), on the Fig. 6B T-maze (replay batch 5)
  and on a 10 x 10 open field with replay batch 5 and 100; best of N repeats, compile time
  excluded (one warm-up call first);
* end-to-end wall time (process start included) and peak RSS of ``cobel run
  task=tmaze_extinction`` as a child process (``/usr/bin/time`` when present, else
  ``getrusage(RUSAGE_CHILDREN)`` through a wrapper), for 100 and 1000 runs and with recording
  on, reduced and off; the run folder's manifest gives the time spent in the run loop itself.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from reference_dyna_q import TMAZE_PHASES, run_reference  # noqa: E402

from cobelrun.agents import DynaQ  # noqa: E402
from cobelrun.envs import GridWorldEnv  # noqa: E402
from cobelrun.envs.world import open_field, tmaze_paper  # noqa: E402
from cobelrun.runner import run_seeds  # noqa: E402

AGENT = dict(epsilon=0.1, beta=5.0, learning_rate=0.9, gamma=0.9)


def open_field_10() -> object:
    return open_field(10, 10, starts=[0], goal=99)


SETTINGS = {
    # name: (world factory, phases [(trials, reward changes)], max_steps, replay batch)
    "tmaze_fig6b_b5": (tmaze_paper, TMAZE_PHASES, 35, 5),
    "open_field_b5": (open_field_10, [(30, {})], 100, 5),
    "open_field_b100": (open_field_10, [(30, {})], 100, 100),
}


def run_cobel(world_factory, phases, max_steps, batch, runs, engine) -> tuple[int, float]:
    """Total env steps and seconds of ``runs`` fresh agents through ``phases``."""
    env = GridWorldEnv(world_factory())
    total = 0
    t0 = time.perf_counter()
    for agent_seed, env_seed in run_seeds(0, runs):
        env.reset_world()
        env.np_random = np.random.default_rng(env_seed)
        agent = DynaQ(env, replay_batch=batch, engine=engine, seed=agent_seed, **AGENT)
        for trials, rewards in phases:
            if rewards:
                env.apply_changes(rewards=rewards)
            total += agent.train(trials, max_steps).n_steps
    return total, time.perf_counter() - t0


def run_ref(world_factory, phases, max_steps, batch, runs) -> tuple[int, float]:
    res = run_reference(
        world_factory, phases, runs=runs, max_steps=max_steps, replay_batch=batch, **AGENT_REF
    )
    return res.total_steps, res.seconds


def best_rate(fn, repeat: int) -> dict:
    best = None
    for _ in range(repeat):
        steps, seconds = fn()
        rate = steps / seconds
        if best is None or rate > best["steps_per_s"]:
            best = {"steps": steps, "seconds": round(seconds, 4), "steps_per_s": rate}
    return best


def bench_engines(quick: bool, repeat: int) -> dict:
    # runs per measurement: (compiled, python, reference) per setting
    runs = {
        "tmaze_fig6b_b5": (100, 3, 3) if not quick else (50, 1, 1),
        "open_field_b5": (100, 3, 3) if not quick else (50, 1, 1),
        "open_field_b100": (50, 1, 1),
    }
    out = {}
    for name, (factory, phases, max_steps, batch) in SETTINGS.items():
        r_comp, r_py, r_ref = runs[name]
        run_cobel(factory, phases, max_steps, batch, 1, "auto")  # warm-up: compile/load
        compiled = best_rate(
            partial(run_cobel, factory, phases, max_steps, batch, r_comp, "auto"), repeat
        )
        python = best_rate(
            partial(run_cobel, factory, phases, max_steps, batch, r_py, "python"),
            1 if quick else min(repeat, 2),
        )
        ref = partial(run_ref, factory, phases, max_steps, batch, r_ref)
        reference = best_rate(ref, 1 if quick else min(repeat, 2))
        out[name] = {
            "replay_batch": batch,
            "compiled": compiled,
            "python": python,
            "reference": reference,
            "speedup_compiled": compiled["steps_per_s"] / reference["steps_per_s"],
            "speedup_python": python["steps_per_s"] / reference["steps_per_s"],
        }
        print(
            f"  {name}: compiled {compiled['steps_per_s']:,.0f}/s, python "
            f"{python['steps_per_s']:,.0f}/s, reference {reference['steps_per_s']:,.0f}/s",
            flush=True,
        )
    return out


AGENT_REF = dict(epsilon=0.1, learning_rate=0.9, gamma=0.9)

E2E = {
    "100 runs, record all": ["task.runs=100"],
    "100 runs, record off": ["task.runs=100", "task.record.steps=false", "task.record.mcap=false"],
    "100 runs, record.runs=[0]": ["task.runs=100", "task.record.runs=[0]"],
    "100 runs, record.trial_every=10": ["task.runs=100", "task.record.trial_every=10"],
    "1000 runs, record all": ["task.runs=1000"],
    "1000 runs, record off": [
        "task.runs=1000",
        "task.record.steps=false",
        "task.record.mcap=false",
    ],
}


def run_child(args: list[str], out_dir: Path) -> dict:
    """Run ``cobel run task=tmaze_extinction ARGS`` in a fresh process; wall time and peak RSS."""
    if out_dir.exists():
        shutil.rmtree(out_dir)
    cobel = shutil.which("cobel", path=str(Path(sys.executable).parent)) or "cobel"
    cmd = [cobel, "run", "task=tmaze_extinction", f"hydra.run.dir={out_dir}", *args]
    timer = shutil.which("time", path="/usr/bin")
    with tempfile.NamedTemporaryFile("r", suffix=".time") as tf:
        if timer:
            full = [timer, "-f", "%e %M", "-o", tf.name, *cmd]
        else:  # a wrapper whose RUSAGE_CHILDREN covers only this one child
            code = (
                "import resource,subprocess,sys,time;t=time.perf_counter();"
                "r=subprocess.run(sys.argv[2:]).returncode;w=time.perf_counter()-t;"
                "open(sys.argv[1],'w').write("
                "f'{w} {resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss}');sys.exit(r)"
            )
            full = [sys.executable, "-c", code, tf.name, *cmd]
        t0 = time.perf_counter()
        proc = subprocess.run(full, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr[-2000:]}")
        _, rss_kb = tf.read().split()
    manifest = json.loads((out_dir / "manifest.json").read_text())
    sizes = {p.name: p.stat().st_size for p in out_dir.iterdir() if p.is_file()}
    return {
        "wall_s": wall,
        "peak_rss_mb": int(rss_kb) / 1024,
        "run_loop_s": manifest.get("wall_time_s"),
        "files_mb": {
            k: round(v / 2**20, 2) for k, v in sizes.items() if k.endswith(("parquet", "mcap"))
        },
    }


def bench_e2e(quick: bool, repeat: int) -> dict:
    out = {}
    tmp = Path(tempfile.mkdtemp(prefix="cobel-bench-"))
    try:
        run_child(["task.runs=2"], tmp / "warm")  # numba cache and file-system warm-up
        for name, args in E2E.items():
            if quick and name.startswith("1000") and "off" in name:
                continue
            n = 1 if (quick or name.startswith("1000")) else repeat
            best = None
            for _ in range(n):
                res = run_child(args, tmp / "run")
                if best is None or res["wall_s"] < best["wall_s"]:
                    best = res
            out[name] = best
            print(
                f"  {name}: {best['wall_s']:.2f} s end to end, run loop {best['run_loop_s']} s, "
                f"peak RSS {best['peak_rss_mb']:.0f} MB",
                flush=True,
            )
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def machine() -> dict:
    cpu = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import numba

    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "numba": numba.__version__,
        "platform": platform.platform(),
        "load_avg_at_start": os.getloadavg(),
    }


def print_table(result: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    console = Console(width=150)
    m = result["machine"]
    t = Table(title=f"Tabular Dyna-Q env steps/s ({m['cpu']}, {m['cores']} cores)")
    for col in ("setting", "batch", "compiled", "python path", "reference", "compiled/ref",
                "python/ref"):  # fmt: skip
        t.add_column(col, justify="right")
    for name, r in result["engines"].items():
        t.add_row(
            name,
            str(r["replay_batch"]),
            f"{r['compiled']['steps_per_s']:,.0f}",
            f"{r['python']['steps_per_s']:,.0f}",
            f"{r['reference']['steps_per_s']:,.0f}",
            f"{r['speedup_compiled']:.0f}x",
            f"{r['speedup_python']:.2f}x",
        )
    console.print(t)
    if result.get("e2e"):
        e = Table(title="cobel run task=tmaze_extinction (child process, best of N)")
        for col in ("configuration", "end to end s", "run loop s", "peak RSS MB", "files MB"):
            e.add_column(col, justify="right")
        for name, r in result["e2e"].items():
            files = ", ".join(f"{k} {v}" for k, v in r["files_mb"].items())
            e.add_row(name, f"{r['wall_s']:.2f}", str(r["run_loop_s"]),
                      f"{r['peak_rss_mb']:.0f}", files)  # fmt: skip
        console.print(e)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="fewer runs and repeats")
    p.add_argument("--skip-e2e", action="store_true", help="only the engine comparison")
    p.add_argument("--repeat", type=int, default=3, help="best of N (default 3)")
    p.add_argument("--out", type=Path, default=HERE / "results" / "tabular.json")
    args = p.parse_args()
    repeat = 1 if args.quick else args.repeat
    result = {"machine": machine(), "quick": args.quick, "repeat": repeat}
    print("engines (env steps/s) ...", flush=True)
    result["engines"] = bench_engines(args.quick, repeat)
    if not args.skip_e2e:
        print("end to end ...", flush=True)
        result["e2e"] = bench_e2e(args.quick, repeat)
    print_table(result)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
