"""Scale benchmark (issue 19): what a Fig. 6B job of many runs costs and leaves behind.

Run on demand (not a test)::

    python benchmarks/bench_scale.py [--runs 1000,20000,100000] [--before main] [--repeats 1]

For each number of runs it starts ``cobel run task=tmaze_extinction task.runs=N`` as a child
process with the default recording (every trial and step row, the MCAP of the first 10 runs
plus every run's trial table, every agent) and with recording reduced to the trials table
(``task.record.steps=false task.record.mcap=false task.save_agents=none``). It reports wall
time, the run loop's time (manifest ``wall_time_s``), the child's CPU time (user + system, all
threads), peak RSS (``ru_maxrss``), folder size and file count, and the recording cost:
(default - reduced) / reduced, on loop time, on CPU time, and (code that writes the manifest's
``cpu_time_s``) on the simulation thread's CPU time: on a machine with a free core for the
writer thread, that is what recording adds to the wall time.

``--before REF`` also measures the code of git ref ``REF`` (exported with ``git archive`` and
put first on ``PYTHONPATH``; same interpreter and packages), alternating with the working
tree's code run by run, so that both face the same machine load. With ``--repeats K`` each
measurement is taken K times and the one with the shortest loop is kept. Writes
``benchmarks/results/scale.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent

REDUCED = ["task.record.steps=false", "task.record.mcap=false", "task.save_agents=none"]


def measure(runs: int, extra: list[str], out: Path, code: Path | None) -> dict:
    """One child process; its peak RSS and CPU time through a wrapper that reports the
    rusage of its child."""
    wrapper = (
        "import resource, subprocess, sys;"
        "p = subprocess.run(sys.argv[1:]);"
        "r = resource.getrusage(resource.RUSAGE_CHILDREN);"
        "print(r.ru_maxrss, r.ru_utime + r.ru_stime, file=sys.stderr);"
        "sys.exit(p.returncode)"
    )
    cmd = [sys.executable, "-c", wrapper, sys.executable, "-m", "cobelrun.cli", "run",
           "task=tmaze_extinction", f"task.runs={runs}", *extra, f"hydra.run.dir={out}"]  # fmt: skip
    env = {**os.environ, "COBEL_RESULTS": str(out.parent)}
    env.pop("HYDRA_FULL_ERROR", None)
    if code is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(code), env.get("PYTHONPATH", "")]).rstrip(
            os.pathsep
        )
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=out.parent)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"cobel run failed:\n{proc.stderr}")
    rss_kb, cpu = proc.stderr.strip().splitlines()[-1].split()
    manifest = json.loads((out / "manifest.json").read_text())
    files = [p for p in out.rglob("*") if p.is_file() and ".hydra" not in p.parts]
    # the step writer process's own memory at its end (newer code logs it; record.step_writer)
    own = re.search(
        r"step writer process: .* s of CPU, ([0-9.]+) MB", (out / "cobel.log").read_text()
    )
    sizes = {p.name: p.stat().st_size for p in files}
    return {
        "wall_s": round(wall, 2),
        "loop_s": float(manifest["wall_time_s"]),
        "cpu_s": round(float(cpu), 2),
        "thread_cpu_s": manifest.get("cpu_time_s"),  # simulation / writer thread (newer code)
        "peak_rss_mb": round(int(rss_kb) / 1024, 1),  # the largest process (cobel or its child)
        "step_writer_private_mb": float(own.group(1)) if own else None,
        "folder_mb": round(sum(sizes.values()) / 1e6, 2),
        "files": len(files),
        "largest": sorted(sizes.items(), key=lambda kv: -kv[1])[:5],
    }


def export(ref: str, into: Path) -> Path:
    """The package and configs of git ref ``ref`` in ``into`` (``git archive``)."""
    into.mkdir(parents=True)
    archive = subprocess.run(["git", "-C", str(REPO), "archive", ref, "cobelrun", "conf"],
                             check=True, capture_output=True).stdout  # fmt: skip
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    return into


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", default="1000,20000")
    ap.add_argument("--before", default=None, help="git ref to measure too (e.g. main)")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--tmp", type=Path, default=None, help="scratch folder (default: a temp dir)")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "scale.json")
    opts = ap.parse_args()
    head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
                          capture_output=True, text=True).stdout.strip()  # fmt: skip
    results: dict = {}
    with tempfile.TemporaryDirectory(dir=opts.tmp) as tmp:
        versions: dict[str, Path | None] = {}
        if opts.before:
            versions[f"before ({opts.before})"] = export(opts.before, Path(tmp) / "before")
        versions[f"after ({head}, working tree)"] = None
        for code in versions.values():  # compile (and cache) the numba kernels of each version
            for mode, extra in (("default", []), ("trials_only", REDUCED)):
                warm = Path(tmp) / f"warm_{mode}"
                measure(2, extra, warm, code)
                subprocess.run(["rm", "-rf", str(warm)], check=True)
        for runs in (int(r) for r in opts.runs.split(",")):
            best: dict[tuple[str, str], dict] = {}
            for rep in range(opts.repeats):
                for name, code in versions.items():
                    for mode, extra in (("default", []), ("trials_only", REDUCED)):
                        out = Path(tmp) / f"{mode}_{runs}_{rep}_{len(best)}"
                        m = measure(runs, extra, out, code)
                        if (name, mode) not in best or m["loop_s"] < best[name, mode]["loop_s"]:
                            best[name, mode] = m
                        subprocess.run(["rm", "-rf", str(out)], check=True)
            results[runs] = {}
            for name in versions:
                full, reduced = best[name, "default"], best[name, "trials_only"]
                cost = (full["loop_s"] - reduced["loop_s"]) / reduced["loop_s"]
                cost_cpu = (full["cpu_s"] - reduced["cpu_s"]) / reduced["cpu_s"]
                results[runs][name] = {"default": full, "trials_only": reduced,
                                       "recording_cost": round(cost, 3),
                                       "recording_cost_cpu": round(cost_cpu, 3)}  # fmt: skip
                threads = ""
                if full["thread_cpu_s"] and reduced["thread_cpu_s"]:
                    sim, base = (m["thread_cpu_s"]["simulation_thread"] for m in (full, reduced))
                    cost_sim = (sim - base) / base
                    results[runs][name]["recording_cost_simulation_thread"] = round(cost_sim, 3)
                    threads = (f"; simulation thread CPU {sim:.1f} vs {base:.1f} s "
                               f"(+{100 * cost_sim:.0f}%), writer thread "
                               f"{full['thread_cpu_s']['writer_thread']:.1f} s")  # fmt: skip
                    child = full["thread_cpu_s"].get("step_writer_process")
                    if child is not None:
                        threads += (
                            f", step writer process {child:.1f} s "
                            f"({full['step_writer_private_mb']} MB of its own)"
                        )
                print(f"{runs:>7} runs, {name}: loop {full['loop_s']:.1f} s vs trials only "
                      f"{reduced['loop_s']:.1f} s -> recording +{100 * cost:.0f}% "
                      f"(CPU {full['cpu_s']:.1f} vs {reduced['cpu_s']:.1f} s: "
                      f"+{100 * cost_cpu:.0f}%), peak RSS {full['peak_rss_mb']:.0f} MB "
                      f"(trials only {reduced['peak_rss_mb']:.0f} MB), folder "
                      f"{full['folder_mb']:.1f} MB in {full['files']} files; "
                      f"largest {full['largest']}{threads}", flush=True)  # fmt: skip
    out = opts.out
    out.parent.mkdir(exist_ok=True)
    load = os.getloadavg()
    out.write_text(json.dumps({"maxrss_unit": "MB", "python": sys.version.split()[0],
                               "cpus": os.cpu_count(), "load_after": [round(x, 1) for x in load],
                               "repeats": opts.repeats, "results": results}, indent=2))  # fmt: skip
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
