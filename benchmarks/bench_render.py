"""Fig. 4: frame time of online vs offline rendering and without rendering (median, IQR).

A thin wrapper around the ``task=render_benchmark`` job (:mod:`cobelrun.render.benchmark`, which
``cobel run task=render_benchmark`` runs): composes that task with the options below, runs the
job and copies its tables, summary and plot to
``benchmarks/results/render_frame_times{,_summary}.csv``, ``.json``, ``.png`` (``--out``).

    python benchmarks/bench_render.py                                # 5 reps x 1 trial x 200 steps
    python benchmarks/bench_render.py --trials 5 --max-steps 400     # the paper's budget per rep
    python benchmarks/bench_render.py --agents mfec,random --sizes 20x80,75x300
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

KNOWN_AGENTS = ("mfec", "dqn", "random")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--agents", default="mfec,dqn,random", help="random: environment cost only")
    ap.add_argument(
        "--sizes", default="20x80,30x120,45x180,60x240,75x300,16x16,32x32,64x64,128x128,256x256"
    )
    ap.add_argument("--modes", default="online,offline,none")
    ap.add_argument("--repeats", type=int, default=5, help="interleaved repetitions per point")
    ap.add_argument("--trials", type=int, default=1)
    ap.add_argument("--max-steps", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=None, help="cache-building processes")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = ap.parse_args()

    from cobelrun.figures.registry import _composer
    from cobelrun.runner import run

    agents = args.agents.split(",")
    unknown = [a for a in agents if a not in KNOWN_AGENTS]
    if unknown:
        ap.error(f"unknown agents {unknown}; allowed: {', '.join(KNOWN_AGENTS)}")
    sizes = [[int(v) for v in s.split("x")] for s in args.sizes.split(",")]
    overrides = [
        "task=render_benchmark",
        f"seed={args.seed}",
        f"task.job.sizes={json.dumps(sizes).replace(' ', '')}",
        f"task.job.trials={args.trials}",
        f"task.job.modes=[{args.modes}]",
        f"task.job.repeats={args.repeats}",
        f"task.job.steps={args.max_steps}",
        *(["task.job.agents.mfec=null"] if "mfec" not in agents else []),
        *(["task.job.agents.dqn=null"] if "dqn" not in agents else []),
        *(["+task.job.agents.random=random"] if "random" in agents else []),
        *([f"task.job.cache_jobs={args.jobs}"] if args.jobs else []),
    ]
    with _composer() as compose:
        cfg = compose(overrides)
    with tempfile.TemporaryDirectory() as tmp:
        run(cfg, Path(tmp))
        args.out.mkdir(parents=True, exist_ok=True)
        for name in ("frame_times.csv", "frame_times_summary.csv", "frame_times.json",
                     "frame_times.png"):  # fmt: skip
            shutil.copy(Path(tmp) / name, args.out / f"render_{name}")
    summary = json.loads((args.out / "render_frame_times.json").read_text())
    keys = ("offline_over_online", "offline_over_none", "cache_build_s")
    print(json.dumps({k: summary[k] for k in keys}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
