"""DQN wrapper overhead (issue 4): cobel's trial-based DQNAgent vs stable-baselines3's own learn().

Run on demand (not a test)::

    python benchmarks/bench_dqn.py [--steps N] [--repeat R]

Both sides train the same SB3 DQN (CoBeL-RL defaults: 4 x 64 tanh, batch 32, Adam 1e-3, soft
target 0.01, train every step, warm-up 100 steps, 1 torch thread) for the same number of env
steps on the same environment: a 5 x 5 open field without a goal, so every trial runs exactly
``max_steps`` steps and ``steps / max_steps`` trials make the same step count. Times are this
thread's CPU time (torch runs on this one thread), so that other processes on a shared machine
do not count. SB3's side wraps
the environment in gymnasium's ``TimeLimit(max_steps)`` and calls ``model.learn(steps)``; cobel's
side calls ``DQNAgent.train(steps // max_steps, max_steps)`` (trial recording, RNG isolation,
stop check included). Repeats alternate the two sides (the machine is shared; alternating spreads
load changes over both) and the best of each is reported. Prints a table and writes
``benchmarks/results/bench_dqn.json``.

Then PER-DQN (``prioritized=True``) on the same task, with the sum tree as it was before issue
18 (``np.unique`` at every level of every update) and as it is now: steps/s and the share of the
step spent in the tree (``--no-per`` skips it).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"


def make_env():
    from cobelrun.envs import DiscreteGridWorldEnv, open_field

    env = DiscreteGridWorldEnv(world=open_field(5, 5))
    env.np_random = np.random.default_rng(0)
    return env


def sb3_steps_per_s(steps: int, max_steps: int) -> float:
    import torch
    from gymnasium.wrappers import TimeLimit
    from stable_baselines3 import DQN

    torch.set_num_threads(1)
    model = DQN(
        "MlpPolicy", TimeLimit(make_env(), max_steps), learning_rate=1e-3, buffer_size=10_000,
        learning_starts=100, batch_size=32, tau=0.01, gamma=0.8, train_freq=1, gradient_steps=1,
        target_update_interval=1, exploration_fraction=1.0, exploration_initial_eps=0.3,
        exploration_final_eps=0.3, policy_kwargs={"net_arch": [64] * 4,
                                                  "activation_fn": torch.nn.Tanh},
        device="cpu", seed=0,
    )  # fmt: skip
    t = time.thread_time()
    model.learn(total_timesteps=steps, log_interval=None)
    dt = time.thread_time() - t
    assert model.num_timesteps == steps
    return steps / dt


def cobel_steps_per_s(steps: int, max_steps: int) -> float:
    from cobelrun.agents.dqn import DQNAgent

    agent = DQNAgent(make_env(), seed=0)  # the same defaults as above
    t = time.thread_time()
    batch = agent.train(steps // max_steps, max_steps)
    dt = time.thread_time() - t
    assert batch.n_steps == steps == agent.model.num_timesteps
    return steps / dt


class _UniqueTree:
    """The sum tree as it was before issue 18 (``np.unique`` at every level), for comparison."""

    def __init__(self, tree) -> None:
        self.tree = tree

    def update(self, idx, values) -> None:
        t = self.tree
        pos = np.asarray(idx, dtype=np.int64) + t.size
        t.sums[pos] = values
        t.mins[pos] = values
        pos = np.unique(pos // 2)
        while pos.size and pos[0] >= 1:
            t.sums[pos] = t.sums[2 * pos] + t.sums[2 * pos + 1]
            t.mins[pos] = np.minimum(t.mins[2 * pos], t.mins[2 * pos + 1])
            if pos[0] == 1:
                break
            pos = np.unique(pos // 2)


def per_tree_share(steps: int, max_steps: int, old_tree: bool = False) -> dict[str, float]:
    """PER-DQN training on the same task: steps/s (thread CPU time) and the share of it spent
    in the sum tree's ``update`` and ``find``; ``old_tree`` swaps in the per-level-unique
    update."""
    from cobelrun.agents.dqn import DQNAgent
    from cobelrun.agents.per import SumTree

    spent = [0.0]
    update, find = SumTree.update, SumTree.find

    def timed(fn):
        def wrapper(self, *args):
            t = time.thread_time()
            try:
                return fn(self, *args)
            finally:
                spent[0] += time.thread_time() - t

        return wrapper

    SumTree.update = timed(
        (lambda self, i, v: _UniqueTree(self).update(i, v)) if old_tree else update
    )
    SumTree.find = timed(find)
    try:
        agent = DQNAgent(make_env(), seed=0, prioritized=True)
        t = time.thread_time()
        agent.train(steps // max_steps, max_steps)
        dt = time.thread_time() - t
    finally:
        SumTree.update, SumTree.find = update, find
    return {"steps_per_s": steps / dt, "tree_share": spent[0] / dt}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=5000)
    parser.add_argument("--max-steps", type=int, default=50)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--no-per", action="store_true", help="skip the PER sum-tree part")
    args = parser.parse_args(argv)
    steps = args.steps - args.steps % args.max_steps
    sb3_steps_per_s(500, args.max_steps)  # warm-up: imports, first allocations
    cobel_steps_per_s(500, args.max_steps)
    sb3, ours = [], []
    for _ in range(args.repeat):
        sb3.append(sb3_steps_per_s(steps, args.max_steps))
        ours.append(cobel_steps_per_s(steps, args.max_steps))
    best_sb3, best_ours = max(sb3), max(ours)
    overhead = best_sb3 / best_ours - 1.0
    result = {
        "benchmark": "bench_dqn",
        "steps": steps,
        "max_steps": args.max_steps,
        "repeat": args.repeat,
        "sb3_learn_steps_per_s": [round(x, 1) for x in sb3],
        "cobel_train_steps_per_s": [round(x, 1) for x in ours],
        "best_sb3_steps_per_s": round(best_sb3, 1),
        "best_cobel_steps_per_s": round(best_ours, 1),
        "overhead": round(overhead, 4),
        "overhead_ok": overhead <= 0.10,
        "host": platform.node(),
        "python": platform.python_version(),
    }
    print(f"{'':24s}{'steps/s (best of ' + str(args.repeat) + ')':>24s}")
    print(f"{'SB3 DQN.learn()':24s}{best_sb3:24.1f}")
    print(f"{'cobel DQNAgent.train()':24s}{best_ours:24.1f}")
    print(f"overhead: {overhead:+.1%} (target <= 10%)")
    if not args.no_per:
        runs = {"new": [], "old": []}
        for _ in range(args.repeat):
            runs["old"].append(per_tree_share(steps, args.max_steps, old_tree=True))
            runs["new"].append(per_tree_share(steps, args.max_steps))
        for name, label in (("old", "per-level np.unique"), ("new", "cobel's sum tree")):
            best = max(runs[name], key=lambda r: r["steps_per_s"])
            result[f"per_{name}"] = best
            print(f"PER-DQN, {label:20s} {best['steps_per_s']:10.1f} steps/s (thread CPU), "
                  f"tree {best['tree_share']:.1%} of the step")  # fmt: skip
        result["per_speedup"] = (result["per_new"]["steps_per_s"]
                                 / result["per_old"]["steps_per_s"])  # fmt: skip
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "bench_dqn.json").write_text(json.dumps(result, indent=2) + "\n")
    return result


if __name__ == "__main__":
    main()
