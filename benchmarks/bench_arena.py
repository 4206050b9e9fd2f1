"""Continuous arena speed (issue 13): cobel's Continuous2DEnv vs RatInABox, and the water maze.

Run on demand (not a test)::

    python benchmarks/bench_arena.py [--steps N] [--repeat R] [--no-task]

1. Env step rate with a place-cell observation: cobel's ``Continuous2DEnv.step`` (8 swim
   directions, 493 Gaussian place cells of width 0.16 m, circular pool of radius 1 m drawn as
   the same 128-gon both sides use for walls) against RatInABox's own loop on the same arena
   and cell count: ``Agent.update(dt=0.1)`` + ``PlaceCells.update()`` (Euclidean fields, as
   ours; RatInABox's default history saving left on, as its users run it). Actions on cobel's
   side are drawn from a generator beforehand, so the loop measures the env alone.
2. For scale, the actor-critic's whole step loop on the same pool (policy, env step, TD update,
   trial records).
3. The wall time (and the CPU time of the process) of the default task
   ``cobel run task=morris_water_maze`` (8 runs x 49 trials), run in-process through the
   runner with the files written as usual.

Repeats alternate the two sides (the machine is shared) and the best of each is reported.
Prints a table and writes ``benchmarks/results/bench_arena.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
N_CELLS, SIGMA, RADIUS, SIDES = 493, 0.16, 1.0, 128


def pool_polygon() -> list[list[float]]:
    a = np.linspace(0, 2 * np.pi, SIDES, endpoint=False)
    return np.c_[RADIUS * np.cos(a), RADIUS * np.sin(a)].tolist()


def cobel_steps_per_s(steps: int) -> float:
    from cobelrun.envs import Continuous2DEnv

    env = Continuous2DEnv(
        arena={"shape": "polygon", "points": pool_polygon()}, starts={"c": [0.0, 0.0]},
        n_directions=8, speed=0.3, dt=0.1,
        observation=[{"kind": "place_cells", "n": N_CELLS, "sigma": SIGMA}],
    )  # fmt: skip
    env.reset(seed=0)
    actions = np.random.default_rng(0).integers(0, 8, steps).tolist()
    step = env.step
    t = time.perf_counter()
    for a in actions:
        step(a)
    return steps / (time.perf_counter() - t)


def agent_loop_steps_per_s(steps: int) -> float:
    """The actor-critic's whole step loop (policy draw, env step, TD update, recording) in
    trials of ``steps`` steps in a pool without a platform."""
    from cobelrun.agents.actor_critic import ActorCritic
    from cobelrun.envs import Continuous2DEnv

    env = Continuous2DEnv(
        arena={"shape": "polygon", "points": pool_polygon()}, starts={"c": [0.0, 0.0]},
        n_directions=8, speed=0.3, dt=0.1,
        observation=[{"kind": "place_cells", "n": N_CELLS, "sigma": SIGMA}],
    )  # fmt: skip
    env.np_random = np.random.default_rng(0)
    agent = ActorCritic(env, seed=0)
    t = time.perf_counter()
    batch = agent.train(1, steps)
    return batch.n_steps / (time.perf_counter() - t)


def ratinabox_steps_per_s(steps: int) -> float:
    import ratinabox
    from ratinabox.Agent import Agent
    from ratinabox.Environment import Environment
    from ratinabox.Neurons import PlaceCells

    ratinabox.verbose = False
    env = Environment(params={"boundary": pool_polygon()})
    agent = Agent(env, params={"dt": 0.1, "speed_mean": 0.3})
    cells = PlaceCells(agent, params={"n": N_CELLS, "widths": SIGMA, "description": "gaussian",
                                      "wall_geometry": "euclidean"})  # fmt: skip
    t = time.perf_counter()
    for _ in range(steps):
        agent.update(dt=0.1)
        cells.update()
    return steps / (time.perf_counter() - t)


def task_time() -> dict[str, float]:
    import pandas as pd
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from cobelrun.config import builtin_conf_dir, register_resolvers
    from cobelrun.runner import run

    register_resolvers()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(builtin_conf_dir()), version_base="1.3"):
        cfg = compose("config", overrides=["task=morris_water_maze"])
    with tempfile.TemporaryDirectory() as tmp:
        wall, cpu = time.perf_counter(), time.process_time()
        run(cfg, Path(tmp) / "run")
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        trials = pd.read_parquet(Path(tmp) / "run" / "trials.parquet")
    return {
        "wall_s": wall,
        "cpu_s": cpu,
        "trials": len(trials),
        "steps": int(trials["steps"].sum()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=20_000, help="cobel steps per repeat")
    parser.add_argument("--ratinabox-steps", type=int, default=2_000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--no-task", action="store_true", help="skip the default task's time")
    args = parser.parse_args()

    cobel_steps_per_s(1000)  # compile the kernels (cached on disk after the first run)
    best = {"cobel": 0.0, "ratinabox": 0.0, "actor_critic_loop": 0.0}
    for _ in range(args.repeat):
        best["cobel"] = max(best["cobel"], cobel_steps_per_s(args.steps))
        best["ratinabox"] = max(best["ratinabox"], ratinabox_steps_per_s(args.ratinabox_steps))
        loop = agent_loop_steps_per_s(args.steps // 2)
        best["actor_critic_loop"] = max(best["actor_critic_loop"], loop)
    ratio = best["cobel"] / best["ratinabox"]
    print(f"{'env step + 493 place cells':32s} {'steps/s':>12s}")
    print(f"{'cobel Continuous2DEnv.step':32s} {best['cobel']:12,.0f}")
    print(f"{'RatInABox Agent + PlaceCells':32s} {best['ratinabox']:12,.0f}")
    print(f"{'ratio':32s} {ratio:12.1f}x")
    print(f"{'actor-critic + env, whole loop':32s} {best['actor_critic_loop']:12,.0f}")
    result = {"step_rate": {**best, "ratio": ratio, "steps": args.steps,
                            "ratinabox_steps": args.ratinabox_steps, "repeat": args.repeat}}  # fmt: skip
    if not args.no_task:
        t = task_time()
        print(f"task=morris_water_maze: {t['wall_s']:.1f} s wall, {t['cpu_s']:.1f} s CPU, "
              f"{t['trials']} trials, {t['steps']:,} steps")  # fmt: skip
        result["task"] = t
    result["host"] = {"python": platform.python_version(), "machine": platform.machine()}
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "bench_arena.json").write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
