"""Fig. 4's offline overhead, measured without the agent's noise: cost of an observation step
offline (the render cache) vs the no-render baseline, and what the per-step copy used to cost.

Run on demand (not a test)::

    python benchmarks/bench_offline_path.py [--sizes 16x16,20x80,...] [--steps N] [--repeat R]

For every image size it builds the 3D T-maze (``task=render_benchmark``'s environment) three
ways, all reading the same render cache (built first, into a temporary folder):

- ``none``: the frame-time job's no-render baseline (:class:`NoRenderObservation`: the views
  loaded into memory, handed out as read-only array views);
- ``offline``: ``env.observation.render=offline`` as every offline run uses it;
- ``offline_copy``: the offline path as it was before (a copy of the view every step), kept
  here as the reference the change is measured against.

Two loops per mode: ``env``, ``steps`` environment steps with uniformly random actions (the
observation path and the environment alone), and ``mfec``, MFEC foraging the paper's budget
(5 trials x 400 steps: its projections memoised, so a step is the agent's steady-state cost),
timed per step on the process's CPU clock. Repetitions alternate the mode order and the best
(minimum) of each is reported: on a shared machine the minimum is the cost without
interference. Prints a table and writes ``benchmarks/results/bench_offline_path.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from cobelrun.envs.observations import ImageObservation

RESULTS = Path(__file__).resolve().parent / "results"
MODES = ("none", "offline", "offline_copy")


class CopyingObservation(ImageObservation):
    """The offline path before: a copy of the cached view every step."""

    def observe(self, node: int, heading: int, rng: np.random.Generator) -> np.ndarray:
        return super().observe(node, heading, rng).copy()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="16x16,32x32,20x80,64x64,75x300,256x256")
    ap.add_argument("--steps", type=int, default=2000, help="environment steps per env loop")
    ap.add_argument("--repeat", type=int, default=7, help="alternating repetitions (best kept)")
    ap.add_argument("--out", type=Path, default=RESULTS / "bench_offline_path.json")
    args = ap.parse_args()

    from cobelrun.config import instantiate
    from cobelrun.figures.registry import _composer
    from cobelrun.render import benchmark as B

    with _composer() as compose:
        cfg = compose(["task=render_benchmark"])
    agents = B._plain(cfg.task.job.agents)
    _, _, phase = B.FrameTimeBenchmark(agents=agents, trials=5, steps=400).budget(cfg)
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for h, w in sizes:
            B.build_caches(B.sized_env_config(cfg.env, h, w, "offline", tmp), jobs=1)
            configs = {m: B.sized_env_config(cfg.env, h, w, "none" if m == "none" else "offline",
                                             tmp) for m in MODES}  # fmt: skip
            configs["offline_copy"]["observation"]["_target_"] = (
                f"{CopyingObservation.__module__}.{CopyingObservation.__qualname__}"
            )
            best: dict[tuple[str, str], float] = {}
            for rep in range(args.repeat):
                for mode in MODES if rep % 2 == 0 else MODES[::-1]:
                    env = instantiate("env", configs[mode])
                    try:
                        env.reset(seed=0)
                        acts = np.random.default_rng(rep).integers(
                            env.action_space.n, size=args.steps
                        )
                        t0 = time.process_time()
                        for a in acts:
                            _, _, term, trunc, _ = env.step(int(a))
                            if term or trunc:
                                env.reset()
                        us = (time.process_time() - t0) / args.steps * 1e6
                    finally:
                        env.close()
                    best[("env", mode)] = min(best.get(("env", mode), np.inf), us)
                    r = B.measure(configs[mode], agents["mfec"], trials=5, steps=400, seed=0,
                                  phase=phase, label="mfec", rep=rep, clock="cpu")  # fmt: skip
                    us = r["frame_ms_mean"] * 1e3
                    best[("mfec", mode)] = min(best.get(("mfec", mode), np.inf), us)
            for loop in ("env", "mfec"):
                row = {"size": f"{h}x{w}", "loop": loop,
                       **{f"{m}_us": round(best[(loop, m)], 2) for m in MODES}}  # fmt: skip
                row["offline_over_none"] = round(best[(loop, "offline")] / best[(loop, "none")], 3)
                row["copy_over_none"] = round(
                    best[(loop, "offline_copy")] / best[(loop, "none")], 3
                )
                rows.append(row)
                print(json.dumps(row), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({
        "benchmark": "offline_path", "steps": args.steps, "repeat": args.repeat,
        "mfec_budget": "5 x 400", "clock": "cpu (process_time), best of the repetitions",
        "machine": {"python": platform.python_version(), "platform": platform.platform()},
        "rows": rows,
    }, indent=1))  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
