"""Run-core benchmark: whole ``cobel run`` processes of this tree vs a reference source tree.

Run on demand (not a test)::

    python benchmarks/bench_runcore.py --reference PATH_TO_OTHER_CHECKOUT [--repeats 7]

Both trees run with this interpreter (``python -m cobelrun.cli``, the tree on ``PYTHONPATH``),
alternating reference / current so that machine load hits both alike. For each setting it
reports the median wall time of the whole process, the run loop's own time from the manifest
(``wall_time_s``), the folder size and file count, and the ratio current / reference. A
reference checkout of an older commit: ``git worktree add --detach /tmp/ref COMMIT``.
Writes ``benchmarks/results/runcore.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent

SETTINGS = {
    "fig6b_100_runs": ["task=tmaze_extinction"],
    "fig6b_1000_runs": ["task=tmaze_extinction", "task.runs=1000"],
    "fig6b_1000_runs_no_steps": [
        "task=tmaze_extinction",
        "task.runs=1000",
        "task.record.steps=false",
        "task.record.mcap=false",
    ],
}


def run_once(tree: Path, args: list[str], out: Path) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": str(tree), "COBEL_RESULTS": str(out.parent)}
    env.pop("HYDRA_FULL_ERROR", None)
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "cobelrun.cli", "run", *args,
                           f"hydra.run.dir={out}"], env=env, capture_output=True, text=True)  # fmt: skip
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{tree}: cobel run failed:\n{proc.stderr}")
    manifest = json.loads((out / "manifest.json").read_text())
    files = [p for p in out.rglob("*") if p.is_file() and ".hydra" not in p.parts]
    return {
        "wall_s": wall,
        "loop_s": float(manifest.get("wall_time_s", float("nan"))),
        "size_mb": sum(p.stat().st_size for p in files) / 1e6,
        "files": len(files),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reference", type=Path, required=True, help="another cobel source tree")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--settings", default=",".join(SETTINGS))
    opts = ap.parse_args()
    trees = {"reference": opts.reference.resolve(), "current": ROOT}
    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in opts.settings.split(","):
            samples: dict[str, list[dict]] = {k: [] for k in trees}
            for i in range(opts.repeats):
                for label, tree in trees.items():
                    out = Path(tmp) / f"{name}_{label}_{i}"
                    samples[label].append(run_once(tree, SETTINGS[name], out))
            row = {}
            for label in trees:
                for key in ("wall_s", "loop_s", "size_mb", "files"):
                    row[f"{label}_{key}"] = statistics.median(s[key] for s in samples[label])
            row["wall_ratio"] = row["current_wall_s"] / row["reference_wall_s"]
            row["loop_ratio"] = row["current_loop_s"] / row["reference_loop_s"]
            results[name] = row
            print(f"{name:28s} wall {row['reference_wall_s']:.2f} -> {row['current_wall_s']:.2f} s "
                  f"(x{row['wall_ratio']:.2f}); loop {row['reference_loop_s']:.2f} -> "
                  f"{row['current_loop_s']:.2f} s (x{row['loop_ratio']:.2f}); folder "
                  f"{row['reference_size_mb']:.1f} -> {row['current_size_mb']:.1f} MB, "
                  f"{row['reference_files']:.0f} -> {row['current_files']:.0f} files", flush=True)  # fmt: skip
    out = HERE / "results" / "runcore.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps({"reference": str(trees["reference"]), "repeats": opts.repeats,
                               "results": results}, indent=2))  # fmt: skip
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
