"""Fig. 6B's runs with the original CoBeL-RL v2.0.0 Dyna-Q, as per-run data for cobel's tables.

The driver imports CoBeL-RL v2.0.0 from a source tree you provide (nothing of it is vendored
here) and writes, per run, the same block summaries as ``docs/figures/data/fig6b_runs.csv``
(right-arm response rate per block, cumulative responses at trials 100 and 200, mean escape
latency per block), so that ``python -m cobelrun.figures.data --derive`` can compare the two
samples run by run (``fig6b_compare.csv``: Welch interval, Mann-Whitney U, probability of
superiority with a bootstrap interval).

Set-up (once; Python 3.11, a throwaway venv, the versions v2.0.0 runs with)::

    git clone https://github.com/sencheng/CoBeL-RL /tmp/cobel-rl && git -C /tmp/cobel-rl checkout v2.0.0
    python3.11 -m venv /tmp/v2venv
    /tmp/v2venv/bin/pip install "numpy<2" gym==0.26.2 scipy pyqtgraph PyQt5
    QT_QPA_PLATFORM=offscreen /tmp/v2venv/bin/python benchmarks/original_fig6b_runs.py \\
        /tmp/cobel-rl --runs 100 --out docs/figures/data/fig6b_original_runs.csv

The task is the paper's (as ``benchmarks/cobel_v2_fig6b.py`` builds it): v2's
``make_gridworld`` 7 x 7 T-maze (the free cells of Fig. 6B, terminals 0 and 6, start 38),
v2's ``DynaQAgent`` with epsilon 0.1, beta 5, learning rate 0.9, gamma 0.9, 5 replays per
step, 100 trials rewarded at the right arm end (6), then 100 at the left (0), 35 steps at
most. A trial's response is 1 when it ends on the right arm end; its latency is the steps
taken (v2 logs steps - 1). v2 draws from numpy's global generator: run ``r`` is seeded with
``np.random.seed(r)`` (the original script seeds nothing).
"""

from __future__ import annotations

import argparse
import csv
import json
import platform
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

FREE = [0, 1, 2, 3, 4, 5, 6, 10, 17, 24, 31, 38]
RIGHT, LEFT, START = 6, 0, 38
BLOCKS_RIGHT = ((91, 100), (101, 110), (111, 120), (191, 200))
BLOCKS_LATENCY = ((11, 20), (21, 30), (91, 100), (191, 200))


def one_run(run: int) -> dict[str, float]:
    """One v2 Dyna-Q run of 200 trials; its block summaries."""
    import numpy as np
    from cobel.agents.dyna_q import DynaQAgent
    from cobel.interfaces.gridworld import InterfaceGridworld
    from cobel.misc.gridworld_tools import make_gridworld

    np.random.seed(run)  # noqa: NPY002 (v2 draws from numpy's global generator)
    walls = [s for s in range(49) if s not in FREE]
    world = make_gridworld(7, 7, terminals=[LEFT, RIGHT],
                           rewards=np.array([[RIGHT, 1.0], [LEFT, 0.0]]), goals=[RIGHT],
                           starting_states=[START], invalid_states=walls)  # fmt: skip
    modules: dict = {}
    iface = InterfaceGridworld(modules, world, False, None)
    modules["rl_interface"] = iface
    response: list[int] = []
    latency: list[int] = []

    def on_trial_end(logs: dict) -> None:
        response.append(int(iface.current_state == RIGHT))
        latency.append(int(logs["steps"]) + 1)

    agent = DynaQAgent(interface_OAI=iface, epsilon=0.1, beta=5, learning_rate=0.9, gamma=0.9,
                       custom_callbacks={"on_trial_end": [on_trial_end]})  # fmt: skip
    iface.rl_agent = agent
    for right, left in ((1.0, 0.0), (0.0, 1.0)):
        world["rewards"][RIGHT], world["rewards"][LEFT] = right, left
        agent.train(100, 35, replay_batch_size=5)
    resp, lat = np.asarray(response, float), np.asarray(latency, float)
    out: dict[str, float] = {"run": run}
    for lo, hi in BLOCKS_RIGHT:
        out[f"right_{lo}_{hi}"] = float(resp[lo - 1 : hi].mean())
    for t in (100, 200):
        out[f"cumulative_{t}"] = float(resp[:t].sum())
    for lo, hi in BLOCKS_LATENCY:
        out[f"latency_{lo}_{hi}"] = float(lat[lo - 1 : hi].mean())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("path", help="a CoBeL-RL v2.0.0 source tree (the folder holding cobel/)")
    ap.add_argument("--runs", type=int, default=100)
    ap.add_argument("--out", type=Path, required=True, help="per-run CSV to write")
    ap.add_argument("--source-label", default="",
                    help="version of the tree when it is no git checkout, e.g. 'v2.0.0 (78bf654)'")  # fmt: skip
    opts = ap.parse_args()
    sys.path.insert(0, opts.path)
    t0, started = time.perf_counter(), datetime.now(UTC).isoformat(timespec="seconds")
    rows = [one_run(r) for r in range(opts.runs)]
    wall = time.perf_counter() - t0
    with opts.out.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    tree = subprocess.run(["git", "-C", opts.path, "describe", "--tags", "--always"],
                          capture_output=True, text=True, check=False).stdout.strip()  # fmt: skip
    commit = subprocess.run(["git", "-C", opts.path, "rev-parse", "HEAD"],
                            capture_output=True, text=True, check=False).stdout.strip()  # fmt: skip
    prov = {
        "table": opts.out.stem, "source": "run", "figure": "fig6b (the original)",
        "command": "QT_QPA_PLATFORM=offscreen python benchmarks/original_fig6b_runs.py "
                   f"COBEL_RL_V2 --runs {opts.runs} --out {opts.out.name}",
        "original": f"CoBeL-RL {opts.source_label or f'{tree} ({commit})'}", "cobel_commit": "n/a (the original's code)",
        "seeds": list(range(opts.runs)), "seeding": "np.random.seed(run) per run",
        "machine": f"{platform.node()} ({platform.platform()})", "python": sys.version.split()[0],
        "exported": started, "wall_time_s": round(wall, 1),
    }  # fmt: skip
    opts.out.with_suffix(".provenance.json").write_text(json.dumps(prov, indent=1) + "\n")
    print(opts.out)


if __name__ == "__main__":
    main()
