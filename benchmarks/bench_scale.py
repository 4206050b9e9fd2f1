"""Scale benchmark (issue 19): what a Fig. 6B job of many runs costs and leaves behind.

Run on demand (not a test)::

    python benchmarks/bench_scale.py [--runs 1000,20000,100000] [--repeats 1]

For each number of runs it starts ``cobel run task=tmaze_extinction task.runs=N`` twice as a
child process: with the default recording (every trial and step row, the MCAP of the first 10
runs, every agent) and with recording reduced to the trials table (``task.record.steps=false
task.record.mcap=false task.save_agents=none``). It reports wall time, the run loop's time
(manifest ``wall_time_s``), peak RSS (``ru_maxrss`` of the child), folder size and file count,
and the recording cost: (default - reduced) / reduced loop time. Writes
``benchmarks/results/scale.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

REDUCED = ["task.record.steps=false", "task.record.mcap=false", "task.save_agents=none"]


def measure(runs: int, extra: list[str], out: Path) -> dict[str, float]:
    """One child process; its peak RSS through a wrapper that reports ru_maxrss of its child."""
    wrapper = (
        "import resource, subprocess, sys;"
        "p = subprocess.run(sys.argv[1:]);"
        "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, file=sys.stderr);"
        "sys.exit(p.returncode)"
    )
    cmd = [sys.executable, "-c", wrapper, sys.executable, "-m", "cobelrun.cli", "run",
           "task=tmaze_extinction", f"task.runs={runs}", *extra, f"hydra.run.dir={out}"]  # fmt: skip
    env = {**os.environ, "COBEL_RESULTS": str(out.parent)}
    env.pop("HYDRA_FULL_ERROR", None)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"cobel run failed:\n{proc.stderr}")
    rss_kb = int(proc.stderr.strip().splitlines()[-1])
    manifest = json.loads((out / "manifest.json").read_text())
    files = [p for p in out.rglob("*") if p.is_file() and ".hydra" not in p.parts]
    sizes = {p.name: p.stat().st_size for p in files}
    return {
        "wall_s": round(wall, 2),
        "loop_s": float(manifest["wall_time_s"]),
        "peak_rss_mb": round(rss_kb / 1024, 1),
        "folder_mb": round(sum(sizes.values()) / 1e6, 2),
        "files": len(files),
        "largest": sorted(sizes.items(), key=lambda kv: -kv[1])[:4],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", default="1000,20000")
    ap.add_argument("--tmp", type=Path, default=None, help="scratch folder (default: a temp dir)")
    opts = ap.parse_args()
    results = {}
    with tempfile.TemporaryDirectory(dir=opts.tmp) as tmp:
        for runs in (int(r) for r in opts.runs.split(",")):
            full = measure(runs, [], Path(tmp) / f"full_{runs}")
            reduced = measure(runs, REDUCED, Path(tmp) / f"reduced_{runs}")
            cost = (full["loop_s"] - reduced["loop_s"]) / reduced["loop_s"]
            results[runs] = {"default": full, "trials_only": reduced, "recording_cost": cost}
            print(f"{runs:>7} runs: wall {full['wall_s']:.1f} s (trials only {reduced['wall_s']:.1f} s), "
                  f"loop {full['loop_s']:.1f} vs {reduced['loop_s']:.1f} s -> recording +{100 * cost:.0f}%, "
                  f"peak RSS {full['peak_rss_mb']:.0f} MB (trials only {reduced['peak_rss_mb']:.0f} MB), "
                  f"folder {full['folder_mb']:.1f} MB in {full['files']} files; largest {full['largest']}",
                  flush=True)  # fmt: skip
    out = HERE / "results" / "scale.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps({"maxrss_unit": "MB", "python": sys.version.split()[0],
                               "cpus": os.cpu_count(), "results": results}, indent=2))  # fmt: skip
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
