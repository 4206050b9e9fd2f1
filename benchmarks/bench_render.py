"""Fig. 4: mean frame time of online vs offline rendering (and the render-cache build time).

For each image size (20x80 .. 75x300), agent (MFEC, DQN) and rendering mode (online: pybullet
every step; offline: images from the render cache), compose ``task=render_benchmark`` with those
overrides, let the agent forage for ``--trials`` x ``--max-steps`` steps and take the wall time of
every step (the clock is read at the start of each step, as in the paper, so a frame includes the
agent's action selection and learning and the environment's step with its rendering).

Writes ``benchmarks/results/render_frame_times.{json,csv,png}`` (``--out`` to change) and also
times building the T-maze cache at 75x300 for all nodes and headings.

    python benchmarks/bench_render.py                       # CPU-sized: 2 trials x 200 steps
    python benchmarks/bench_render.py --trials 5 --max-steps 400   # the paper's budget
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

SIZES = ((20, 80), (30, 120), (45, 180), (60, 240), (75, 300))


class FrameClock(gym.Wrapper):
    """Reads the clock at the start of every step; frame = time between consecutive step starts."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.frames: list[float] = []
        self._last: float | None = None

    def reset(self, **kw):
        self._last = None
        return self.env.reset(**kw)

    def step(self, action):
        now = time.perf_counter()
        if self._last is not None:
            self.frames.append(now - self._last)
        self._last = now
        return self.env.step(action)


def compose(overrides: list[str]):
    from cobelrun.commands.render_cache import compose as _compose

    return _compose(overrides)


def measure(
    agent: str, size: tuple[int, int], mode: str, trials: int, max_steps: int, seed: int
) -> dict:
    from cobelrun.config import instantiate
    from cobelrun.render import cache

    h, w = size
    conf_agent = "dqn" if agent == "random" else agent  # random: env-only cost, no agent
    overrides = ["task=render_benchmark", f"agent={conf_agent}", f"env.observation.height={h}",
                 f"env.observation.width={w}", f"env.observation.render={mode}"]  # fmt: skip
    cfg = compose(overrides)
    if mode == "offline":  # build the cache first (excluded from frame time, as in the paper)
        with cache.building_mode():
            env = instantiate("env", cfg.env)
        cache.build(env.observation_module.cache_request())
        env.close()
    env = instantiate("env", cfg.env)
    env.apply_changes(rewards={"left_arm": 1.0, "right_arm": 1.0},
                      terminals={"left_arm": False, "right_arm": False})  # fmt: skip
    timed = FrameClock(env)
    t0 = time.perf_counter()
    if agent == "random":
        rng = np.random.default_rng(seed)
        n_steps = 0
        for t in range(trials):
            timed.reset(seed=seed + t)
            for _ in range(max_steps):
                timed.step(int(rng.integers(timed.action_space.n)))
                n_steps += 1
    else:
        agent_cfg = {k: v for k, v in cfg.agent.items() if k != "load_from"}  # runner-level key
        make = instantiate("agent", agent_cfg, env=timed, _partial_=True)
        ag = make(seed=np.random.SeedSequence(seed))
        t0 = time.perf_counter()
        n_steps = ag.train(trials, max_steps).n_steps
    total = time.perf_counter() - t0
    frames = np.asarray(timed.frames)
    env.close()
    return {
        "agent": agent, "height": h, "width": w, "mode": mode, "steps": int(n_steps),
        "frame_ms_mean": float(frames.mean() * 1e3), "frame_ms_median": float(np.median(frames) * 1e3),
        "frame_ms_std": float(frames.std() * 1e3), "wall_s": round(total, 3),
    }  # fmt: skip


def cache_build_time(jobs: int) -> dict:
    from cobelrun.config import instantiate
    from cobelrun.render import cache

    cfg = compose(
        ["task=render_benchmark", "env.observation.height=75", "env.observation.width=300"]
    )
    with cache.building_mode():
        env = instantiate("env", cfg.env)
    req = env.observation_module.cache_request()
    with tempfile.TemporaryDirectory() as tmp:
        req.cache_dir = Path(tmp)
        t0 = time.perf_counter()
        cache.build(req, jobs=jobs)
        dt = time.perf_counter() - t0
    return {"views": req.n_nodes * req.n_directions, "size": [75, 300], "jobs": jobs,
            "n_cameras": req.camera.n_cameras, "seconds": round(dt, 3)}  # fmt: skip


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    agents = sorted({r["agent"] for r in rows})
    fig, axes = plt.subplots(1, len(agents), figsize=(4.2 * len(agents), 3.4), squeeze=False)
    for ax, agent in zip(axes[0], agents, strict=True):
        for mode, style in (("online", "o-"), ("offline", "s--")):
            sel = sorted((r for r in rows if r["agent"] == agent and r["mode"] == mode),
                         key=lambda r: r["height"] * r["width"])  # fmt: skip
            if not sel:
                continue
            labels = [f"{r['height']}x{r['width']}" for r in sel]
            ax.errorbar(labels, [r["frame_ms_mean"] for r in sel],
                        yerr=[r["frame_ms_std"] for r in sel], fmt=style, capsize=3, label=mode)  # fmt: skip
        ax.set_title(agent.upper())
        ax.set_xlabel("image size (pixels)")
        ax.set_ylabel("mean frame time (ms)")
        ax.tick_params(axis="x", rotation=30)
        ax.legend(frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--agents", default="mfec,dqn,random", help="random: environment cost only")
    ap.add_argument("--sizes", default=",".join(f"{h}x{w}" for h, w in SIZES))
    ap.add_argument("--trials", type=int, default=2)
    ap.add_argument("--max-steps", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = ap.parse_args()
    os.environ.setdefault("COBEL_CACHE", tempfile.mkdtemp(prefix="cobel-bench-cache-"))
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    rows = []
    for agent in args.agents.split(","):
        for size in sizes:
            for mode in ("online", "offline"):
                r = measure(agent, size, mode, args.trials, args.max_steps, args.seed)
                rows.append(r)
                print(f"{agent:5s} {size[0]:3d}x{size[1]:<3d} {mode:8s} {r['frame_ms_mean']:8.3f} ms/frame",
                      file=sys.stderr)  # fmt: skip
    ratios = {}
    for agent in args.agents.split(","):
        for h, w in sizes:
            on = next(
                r
                for r in rows
                if (r["agent"], r["height"], r["width"], r["mode"]) == (agent, h, w, "online")
            )
            off = next(
                r
                for r in rows
                if (r["agent"], r["height"], r["width"], r["mode"]) == (agent, h, w, "offline")
            )
            ratios[f"{agent}_{h}x{w}"] = round(off["frame_ms_mean"] / on["frame_ms_mean"], 4)
    build = cache_build_time(args.jobs)
    from importlib.metadata import version

    result = {
        "benchmark": "render_frame_times",
        "trials": args.trials, "max_steps": args.max_steps,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "platform": platform.platform(), "pybullet": version("pybullet")},
        "rows": rows, "offline_over_online": ratios, "cache_build_75x300": build,
    }  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "render_frame_times.json").write_text(json.dumps(result, indent=1))
    import pandas as pd

    pd.DataFrame(rows).to_csv(args.out / "render_frame_times.csv", index=False)
    plot(rows, args.out / "render_frame_times.png")
    print(json.dumps({"offline_over_online": ratios, "cache_build_75x300": build}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
