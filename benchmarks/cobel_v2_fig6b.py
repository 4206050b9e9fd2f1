"""Fig. 6B with the real CoBeL-RL v2.0.0 Dyna-Q (its own code, unchanged), for speed ratios.

Runs under CoBeL-RL v2's own interpreter (numpy < 2, gym, scipy, pyqtgraph, PyQt5; see
``docs/speed.md``) and imports nothing from cobel::

    /tmp/cobel-v2-venv/bin/python benchmarks/cobel_v2_fig6b.py /tmp/cobel-v2 --runs 5

``benchmarks/bench_all.py --cobel-v2 PATH --cobel-v2-python EXE`` runs it as a child process.
The T-maze is built with v2's ``make_gridworld`` (7 x 7, the free cells of Fig. 6B, every other
cell an invalid state, terminals 0 and 6, start 38); the agent is v2's ``DynaQAgent`` with
epsilon 0.1, beta 5, learning rate 0.9, gamma 0.9, trained 100 trials with the reward at state 6,
then 100 trials with it at state 0, 35 steps at most, 5 replayed experiences per step, no GUI.
v2 draws from numpy's global generator, seeded per run. Prints one JSON line: env steps, this
thread's CPU seconds and wall seconds of the training calls, and per phase the mean steps of
its last 10 trials (the behaviour check: ~8-10 steps in both phases).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

FREE = [0, 1, 2, 3, 4, 5, 6, 10, 17, 24, 31, 38]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("path", help="a CoBeL-RL v2.0.0 source tree (the folder holding cobel/)")
    ap.add_argument("--runs", type=int, default=5)
    opts = ap.parse_args()
    sys.path.insert(0, opts.path)
    import numpy as np
    from cobel.agents.dyna_q import DynaQAgent
    from cobel.interfaces.gridworld import InterfaceGridworld
    from cobel.misc.gridworld_tools import make_gridworld

    steps = 0
    cpu = wall = 0.0
    latency: dict[str, list[float]] = {"acquisition": [], "extinction": []}
    for run in range(opts.runs):
        np.random.seed(run)  # noqa: NPY002 (v2 draws from numpy's global generator)
        walls = [s for s in range(49) if s not in FREE]
        world = make_gridworld(7, 7, terminals=[0, 6], rewards=np.array([[6, 1.0], [0, 0.0]]),
                               goals=[6], starting_states=[38], invalid_states=walls)  # fmt: skip
        modules: dict = {}
        iface = InterfaceGridworld(modules, world, False, None)
        modules["rl_interface"] = iface
        trial_steps: list[int] = []
        agent = DynaQAgent(interface_OAI=iface, epsilon=0.1, beta=5, learning_rate=0.9,
                           gamma=0.9,
                           custom_callbacks={"on_trial_end": [
                               lambda logs, out=trial_steps: out.append(int(logs["steps"]) + 1)]})  # fmt: skip
        iface.rl_agent = agent
        step = iface.step
        count = [0]

        def counted(action, step=step, count=count):
            count[0] += 1
            return step(action)

        iface.step = counted
        for phase, (right, left) in (("acquisition", (1.0, 0.0)), ("extinction", (0.0, 1.0))):
            world["rewards"][6], world["rewards"][0] = right, left
            c0, w0 = time.thread_time(), time.perf_counter()
            agent.train(100, 35, replay_batch_size=5)
            cpu += time.thread_time() - c0
            wall += time.perf_counter() - w0
            latency[phase].append(float(np.mean(trial_steps[-10:])))
        steps += count[0]
    print(json.dumps({
        "runs": opts.runs, "env_steps": steps, "cpu_s": cpu, "wall_s": wall,
        "steps_per_s_cpu": steps / cpu, "steps_per_s_wall": steps / wall,
        "last10_latency": {k: float(np.mean(v)) for k, v in latency.items()},
    }))  # fmt: skip


if __name__ == "__main__":
    main()
