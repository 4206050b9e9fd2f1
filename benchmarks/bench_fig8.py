"""Fig. 8 costs: DQN training speed on the place-cell task and activity-map snapshot time.

Run on demand (not a test)::

    python benchmarks/bench_fig8.py [--steps N] [--train-freq K]

1. Training: ``agent=dqn_fig8`` on ``task=place_cells``'s environment (77-node hexagonal maze,
   12 x 48 panoramas), trials of at most 100 steps until ``--steps`` env steps, rendered online
   (each graph pose once, then reused: ``reuse_views``, the default), online on every step
   (``online_every_step``: ``reuse_views=false``) and read from the render cache; env steps per
   second of wall time and of process CPU time (the machine is shared, CPU time is the steadier
   number), and the rendering alone (pybullet on every view vs the cache).
2. A snapshot of the activity-map monitor (25 x 25 grid x 6 headings = 3,750 views, 50 units):
   producing the views online (pybullet) vs from the render cache, and the forward passes.

The render cache goes to a temporary folder. Prints a table and writes
``benchmarks/results/bench_fig8.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"


#: the rendering modes timed: name -> overrides of ``task=place_cells``
MODES = {
    "online": ["env.observation.render=online"],
    "online_every_step": ["env.observation.render=online", "++env.observation.reuse_views=false"],
    "offline": ["env.observation.render=offline"],
}


def make_env(render: str):
    from cobelrun.commands.render_cache import compose
    from cobelrun.config import instantiate

    cfg = compose(["task=place_cells", *MODES[render]])
    return cfg, instantiate("env", cfg.env)


def make_agent(cfg, env, train_freq: int):
    from omegaconf import OmegaConf

    from cobelrun.config import instantiate

    node = OmegaConf.to_container(cfg.agent, resolve=True)
    node["train_freq"] = train_freq
    return instantiate("agent", node, env=env, seed=0)


def timed(fn):
    w, c = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - w, time.process_time() - c


def training(render: str, steps: int, train_freq: int) -> dict:
    cfg, env = make_env(render)
    env.unwrapped.np_random = np.random.default_rng(0)
    agent = make_agent(cfg, env, train_freq)
    done = 0

    def go():
        nonlocal done
        while done < steps:
            batch = agent.train(10, 100)
            done += int(batch.steps.sum())

    _, wall, cpu = timed(go)
    env.close()
    return {"render": render, "steps": done, "wall_s": wall, "cpu_s": cpu,
            "steps_per_s_wall": done / wall, "steps_per_s_cpu": done / cpu}  # fmt: skip


def render_only(render: str, n: int) -> dict:
    _, env = make_env(render)
    base = env.unwrapped
    rng = np.random.default_rng(1)
    poses = [(int(rng.integers(77)), int(rng.integers(6))) for _ in range(n)]
    base.observe_pose(*poses[0])  # build the scene / load the cache outside the clock
    _, wall, cpu = timed(lambda: [base.observe_pose(p, h) for p, h in poses])
    env.close()
    return {"render": render, "views": n, "ms_per_view_wall": 1e3 * wall / n,
            "ms_per_view_cpu": 1e3 * cpu / n}  # fmt: skip


def snapshot(render: str) -> dict:
    from cobelrun.monitors.maps import ActivityMapMonitor

    cfg, env = make_env(render)
    agent = make_agent(cfg, env, 1)
    mon = ActivityMapMonitor()
    mon.setup(env)
    rows = []
    mon.bind(
        lambda table, cols: rows.append(len(cols["value"])) if table == "activity_maps" else None
    )
    _, wall, cpu = timed(lambda: mon.start_run(0, agent))  # views + first snapshot
    _, wall2, cpu2 = timed(lambda: mon.snapshot(agent, 800))  # views kept: forward passes only
    env.close()
    return {"render": render, "views": int(mon.grid.inside.sum()) * 6, "rows": rows[0],
            "views_s": mon.view_seconds, "first_snapshot_wall_s": wall,
            "first_snapshot_cpu_s": cpu, "later_snapshot_wall_s": wall2,
            "later_snapshot_cpu_s": cpu2}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000, help="env steps per training point")
    parser.add_argument("--train-freq", type=int, default=1, help="gradient step every K steps")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        os.environ["COBEL_CACHE"] = tmp
        from cobelrun.monitors.maps import ActivityMapMonitor
        from cobelrun.render import cache

        with cache.building_mode():
            cfg, env = make_env("offline")
        reqs = [env.unwrapped.observation_module.cache_request()]
        reqs += ActivityMapMonitor().cache_requests(env)
        _, build_wall, _ = timed(lambda: [cache.build(r, jobs=1) for r in reqs])
        del cfg
        result = {
            "machine": {
                "host": platform.node(),
                "cpus": os.cpu_count(),
                "load_avg": os.getloadavg(),
            },
            "cache_build_s_jobs1": build_wall,
            "render": [render_only(m, 500) for m in ("online_every_step", "offline")],
            "training": [training(m, args.steps, args.train_freq) for m in MODES],
            "snapshot": [snapshot(m) for m in ("online", "offline")],
            "train_freq": args.train_freq,
        }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "bench_fig8.json").write_text(json.dumps(result, indent=2) + "\n")
    print(f"render cache (77 x 6 node views + 625 x 6 probe views, 1 process): "
          f"{build_wall:.1f} s")  # fmt: skip
    for r in result["render"]:
        print(f"render {r['render']:17s}: {r['ms_per_view_wall']:.3f} ms/view wall, "
              f"{r['ms_per_view_cpu']:.3f} ms CPU")  # fmt: skip
    for r in result["training"]:
        print(f"training {r['render']:17s}: {r['steps']} steps, {r['steps_per_s_wall']:.0f} "
              f"steps/s wall, {r['steps_per_s_cpu']:.0f} steps/s CPU")  # fmt: skip
    for r in result["snapshot"]:
        print(
            f"snapshot {r['render']:8s}: views {r['views_s']:.2f} s, first snapshot "
            f"{r['first_snapshot_wall_s']:.2f} s wall ({r['first_snapshot_cpu_s']:.2f} CPU), "
            f"later {r['later_snapshot_wall_s']:.2f} s ({r['later_snapshot_cpu_s']:.2f} CPU)"
        )
    print(f"load average {result['machine']['load_avg']}")


if __name__ == "__main__":
    main()
