"""Every speed and memory ratio of issue 18 in one run (docs/speed.md shows them).

Run on demand (not a test)::

    python benchmarks/bench_all.py [--quick] [--cobel-v2 PATH --cobel-v2-python EXE]

1. Start-up (``bench_startup.py``): ``cobel run task=tmaze_extinction`` end to end against
   the floors (bare interpreter, ``import cobelrun``, numba's import + one cached function,
   Hydra's import + one composition), with the import and stage breakdown.
2. Tabular kernel (``limit_dyna_q.py``): Fig. 6B steady state and cobel's kernel against the
   minimal compiled loop with the same draws; peak RSS of ``cobel run`` with 100 and 1,000 runs
   (everything recorded) from a sampler of the child's ``VmRSS``.
4. Deep agents (``bench_dqn.py``): DQN wrapper overhead against SB3's own ``learn``; the PER
   sum tree's share of a PER-DQN step, before and after issue 18.
5. With ``--cobel-v2 PATH`` (a CoBeL-RL v2.0.0 source tree) and ``--cobel-v2-python EXE`` (an
   interpreter with v2's requirements, see docs/speed.md): the real v2 Dyna-Q on Fig. 6B
   (``cobel_v2_fig6b.py``, a child process) against cobel's steady state, env steps/s.

Writes ``benchmarks/results/bench_all.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))


def machine() -> dict:
    cpu = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(),
            "platform": platform.platform(), "load_avg_at_start": os.getloadavg()}  # fmt: skip


def peak_rss(runs: int) -> dict[str, float]:
    """Peak resident memory (MB) of ``cobel run task=tmaze_extinction task.runs=RUNS``,
    sampled from ``/proc/PID/status`` every 20 ms, and its wall time."""
    from bench_startup import cobel_cmd

    with tempfile.TemporaryDirectory(prefix="cobel-rss-") as tmp:
        cmd = [*cobel_cmd(), "run", "task=tmaze_extinction", f"task.runs={runs}",
               f"hydra.run.dir={Path(tmp) / 'run'}", "--quiet"]  # fmt: skip
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        peak = 0.0
        while proc.poll() is None:
            try:
                for line in Path(f"/proc/{proc.pid}/status").read_text().splitlines():
                    if line.startswith("VmRSS"):
                        peak = max(peak, int(line.split()[1]) / 1024)
            except OSError:
                pass
            time.sleep(0.02)
        if proc.returncode != 0:
            raise SystemExit(f"{' '.join(cmd)} failed")
        return {"peak_rss_mb": peak, "wall_s": time.perf_counter() - t0}


def cobel_v2(path: Path, python: str, runs: int) -> dict:
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}
    proc = subprocess.run([python, str(HERE / "cobel_v2_fig6b.py"), str(path), "--runs",
                           str(runs)], capture_output=True, text=True, env=env)  # fmt: skip
    if proc.returncode != 0:
        raise SystemExit(f"CoBeL-RL v2 run failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats")
    ap.add_argument("--cobel-v2", type=Path, help="a CoBeL-RL v2.0.0 source tree")
    ap.add_argument("--cobel-v2-python", default=sys.executable,
                    help="the interpreter with CoBeL-RL v2's requirements")  # fmt: skip
    ap.add_argument("--cobel-v2-runs", type=int, default=5)
    opts = ap.parse_args(argv)
    import bench_dqn
    import bench_startup
    import limit_dyna_q

    out: dict = {"machine": machine(), "quick": opts.quick}
    m = out["machine"]
    print(f"machine: {m['cpu']}, {m['cores']} cores, Python {m['python']}, load average at "
          f"start {m['load_avg_at_start'][0]:.1f}\n")  # fmt: skip

    print("== 1. start-up ==")
    out["startup"] = bench_startup.main(["--repeats", "3" if opts.quick else "10"])

    print("\n== 2. tabular kernel ==")
    lim = limit_dyna_q.measure(runs=100, repeat=3 if opts.quick else 7)
    limit_dyna_q.report(lim)
    out["tabular"] = lim
    rss = {n: peak_rss(n) for n in (100, 1000)}
    out["rss"] = rss
    print(f"  peak RSS, cobel run task=tmaze_extinction (all recorded): 100 runs "
          f"{rss[100]['peak_rss_mb']:.0f} MB, 1000 runs {rss[1000]['peak_rss_mb']:.0f} MB "
          f"(ratio {rss[1000]['peak_rss_mb'] / rss[100]['peak_rss_mb']:.2f}; goal < 300 MB)")  # fmt: skip

    print("\n== 4. DQN wrapper and PER sum tree ==")
    steps = "1500" if opts.quick else "5000"
    out["dqn"] = bench_dqn.main(["--steps", steps, "--repeat", "2" if opts.quick else "3"])

    if opts.cobel_v2 is not None:
        print("\n== CoBeL-RL v2.0.0 side by side (Fig. 6B, env steps/s, thread CPU time) ==")
        v2 = cobel_v2(opts.cobel_v2, opts.cobel_v2_python, opts.cobel_v2_runs)
        out["cobel_v2"] = v2
        ratio = lim["steady_steps_per_s"] / v2["steps_per_s_cpu"]
        out["cobel_over_v2"] = ratio
        print(f"  CoBeL-RL v2 DynaQAgent: {v2['steps_per_s_cpu']:,.0f} steps/s ({v2['runs']} runs, "
              f"last-10 latency {v2['last10_latency']})")  # fmt: skip
        print(
            f"  cobel steady state:     {lim['steady_steps_per_s']:,.0f} steps/s = {ratio:,.0f}x v2"
        )

    st = out["startup"]["processes"]
    run = st["cobel run task=tmaze_extinction"]
    print("\n== ratios ==")
    rows = [
        ("cobel run / python -c pass (wall)", run["wall_s"] / st["python -c pass"]["wall_s"]),
        ("cobel run / import cobelrun (wall)", run["wall_s"] / st["import cobelrun"]["wall_s"]),
        ("cobel run / numba floor (wall)", run["wall_s"] / st["numba floor"]["wall_s"]),
        ("cobel run / (numba + hydra floors) (CPU)",
         run["cpu_s"] / (st["numba floor"]["cpu_s"] + st["hydra floor"]["cpu_s"])),
        ("cobel run wall / 0.8 s goal", run["wall_s"] / 0.8),
        ("Fig. 6B steady state / limit", lim["steady_over_limit"]),
        ("Fig. 6B steady state / limit's compiled loop", lim["steady_over_limit_loop"]),
        ("cobel kernel / limit's compiled loop", lim["kernel_over_limit_loop"]),
        ("peak RSS 1000 runs / 100 runs",
         rss[1000]["peak_rss_mb"] / rss[100]["peak_rss_mb"]),
        ("peak RSS 1000 runs / 300 MB goal", rss[1000]["peak_rss_mb"] / 300),
        ("DQN: SB3 learn steps/s / cobel train steps/s - 1", out["dqn"]["overhead"]),
    ]  # fmt: skip
    if "per_speedup" in out["dqn"]:
        rows.append(("PER-DQN steps/s, new tree / per-level unique", out["dqn"]["per_speedup"]))
    if "cobel_over_v2" in out:
        rows.append(("Fig. 6B steady state / CoBeL-RL v2.0.0", out["cobel_over_v2"]))
    for label, value in rows:
        print(f"  {label:52s} {value:10.3f}")
    out["ratios"] = dict(rows)
    path = HERE / "results" / "bench_all.json"
    path.parent.mkdir(exist_ok=True)
    path.write_text(json.dumps(out, indent=2, default=str))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
