"""Checkpoint sizes of the deep paper figures (issue 35), from real agents at a small scale.

Builds the agent of a figure's task config (``agent=dqn_fig8`` for Fig. 8, the DQN of
``task=tmaze_extinction_3d_paper`` for Fig. 6A) on a stand-in environment with the figure's
observation space (uint8 camera images of the figure's size; no renderer needed), trains it
for a few trials, writes its checkpoint twice (after ``N1`` and ``N2`` transitions in the
replay memory) and measures the files: the fixed part (weights, Adam moments, generators) and
the bytes per stored transition. The full-run size is *derived* from those two measurements:
fixed + transitions per full replay memory (``agent.buffer_size``) x bytes per transition. A
checkpoint never grows past that bound (the memory holds at most ``buffer_size`` transitions).

Usage::

    python benchmarks/bench_checkpoint_size.py [--out benchmarks/results/checkpoint_size.json]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

HERE = Path(__file__).resolve().parent
FIGURES = {
    # figure: (task, overrides, image (C, H, W) the env gives the agent)
    "fig8": ("place_cells", [], (3, 12, 48)),
    "fig6a": ("tmaze_extinction_3d_paper", [], (3, 84, 84)),
}


class Images(gym.Env):
    """A stand-in with the figure's observation and action spaces: a random image per state of
    a small ring world (what the replay memory stores is the same size as the real views)."""

    def __init__(self, shape: tuple[int, int, int], n_actions: int, seed: int = 0) -> None:
        c, h, w = shape
        self.observation_space = gym.spaces.Box(0, 255, (h, w, c), np.uint8)
        self.action_space = gym.spaces.Discrete(n_actions)
        rng = np.random.default_rng(seed)
        self.views = rng.integers(0, 256, (16, h, w, c), dtype=np.uint8)
        self.s = 0

    def reset(self, *, seed=None, options=None):  # type: ignore[no-untyped-def]
        super().reset(seed=seed)
        self.s = int(self.np_random.integers(16))
        return self.views[self.s].copy(), {}

    def step(self, action):  # type: ignore[no-untyped-def]
        self.s = (self.s + int(action) + 1) % 16
        done = self.s == 0
        return self.views[self.s].copy(), float(done), done, False, {}


def measure(figure: str, n1: int, n2: int) -> dict:
    from omegaconf import OmegaConf

    from cobelrun import api
    from cobelrun import checkpoint as ck
    from cobelrun.config import instantiate

    task, overrides, shape = FIGURES[figure]
    cfg = api.compose(task, overrides)
    node = OmegaConf.to_container(cfg.agent, resolve=True)
    node["device"] = "cpu"
    buffer_size = int(node["buffer_size"])
    n_actions = 12 if figure == "fig8" else 6
    env = Images(shape, n_actions)
    env.np_random = np.random.default_rng(0)
    agent = instantiate("agent", node, env=env, seed=0)
    sizes = {}
    with tempfile.TemporaryDirectory() as tmp:
        for n in (n1, n2):
            while agent.model.replay_buffer.pos < n:
                agent.train(1, 10)
            stored = agent.model.replay_buffer.pos
            arrays, entry = ck.agent_entry(agent)
            t0 = time.perf_counter()
            size = ck.write_checkpoint(Path(tmp) / "c.npz", {"config_hash": "x", "agent": entry},
                                       arrays)  # fmt: skip
            sizes[stored] = (size, time.perf_counter() - t0)
    (a, (sa, _)), (b, (sb, tb)) = sorted(sizes.items())
    per = (sb - sa) / (b - a)
    fixed = sa - per * a
    full = fixed + per * buffer_size
    return {"figure": figure, "task": task, "image_chw": shape, "buffer_size": buffer_size,
            "measured": {str(k): v[0] for k, v in sizes.items()},
            "bytes_per_transition": round(per, 1), "fixed_bytes": round(fixed),
            "derived_full_bytes": round(full), "derived_full_mb": round(full / 2**20, 1),
            "write_seconds_at_largest_measured": round(tb, 3)}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=HERE / "results" / "checkpoint_size.json")
    args = ap.parse_args()
    rows = [measure("fig8", 40, 240), measure("fig6a", 40, 240)]
    for r in rows:
        print(json.dumps(r))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
