"""DQN wrapper overhead (issue 4): cobel's trial-based DQNAgent vs stable-baselines3's own learn().

Run on demand (not a test)::

    python benchmarks/bench_dqn.py [--steps N] [--repeat R]

Both sides train the same SB3 DQN (CoBeL-RL defaults: 4 x 64 tanh, batch 32, Adam 1e-3, soft
target 0.01, train every step, warm-up 100 steps, 1 torch thread) for the same number of env
steps on the same environment: a 5 x 5 open field without a goal, so every trial runs exactly
``max_steps`` steps and ``steps / max_steps`` trials make the same step count. SB3's side wraps
the environment in gymnasium's ``TimeLimit(max_steps)`` and calls ``model.learn(steps)``; cobel's
side calls ``DQNAgent.train(steps // max_steps, max_steps)`` (trial recording, RNG isolation,
stop check included). Repeats alternate the two sides (the machine is shared; alternating spreads
load changes over both) and the best of each is reported. Prints a table and writes
``benchmarks/results/bench_dqn.json``.
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
    t = time.perf_counter()
    model.learn(total_timesteps=steps, log_interval=None)
    dt = time.perf_counter() - t
    assert model.num_timesteps == steps
    return steps / dt


def cobel_steps_per_s(steps: int, max_steps: int) -> float:
    from cobelrun.agents.dqn import DQNAgent

    agent = DQNAgent(make_env(), seed=0)  # the same defaults as above
    t = time.perf_counter()
    batch = agent.train(steps // max_steps, max_steps)
    dt = time.perf_counter() - t
    assert batch.n_steps == steps == agent.model.num_timesteps
    return steps / dt


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=5000)
    parser.add_argument("--max-steps", type=int, default=50)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
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
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "bench_dqn.json").write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
