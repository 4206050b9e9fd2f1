"""Does batching the CNN agents of several runs pay on this CPU? (issue 18, Fig. 6A / Fig. 8)

Run on demand (not a test)::

    python benchmarks/bench_cnn_batch.py [--runs 1,5,25] [--steps 40] [--device cpu]

The batched deep agents (``task.batch_runs``) gain on small MLPs because one call then does the
work of R calls whose cost was mostly per-call overhead. A CNN step is different: one DQN
gradient step of Fig. 8's network (conv 32@5x5/1 -> 64@4x4/2 -> 64@3x3/2 -> dense 50 ReLU ->
dropout 0.35 -> 12 Q values on 12 x 48 x 3 panoramas) or Fig. 6A's (conv 16@8x8/4 -> 32@4x4/2
-> dense 256 -> 6 Q values on 84 x 84 x 3) is arithmetic. This measures, for R runs, one DQN
step of every run (the online network forward and backward on a batch of 32, the target
network forward on the 32 next observations, Adam) done three ways:

- *sequential*: R networks (cobel's ``ConvFeatures`` and a linear head, as the DQN agent builds
  them), one after another, one ``torch.optim.Adam`` each;
- *grouped*: one network whose convolutions have ``groups=R`` (R runs' filters side by side)
  and whose dense layers are batched matrix products (``torch.bmm``), one Adam;
- *vmap*: R networks' parameters stacked (``torch.func.stack_module_state``) and the loss's
  gradient vectorised over runs (``torch.func.vmap(torch.func.grad(...))``), one Adam over
  the stacked parameters.

This times one gradient step only; ``benchmarks/bench_cnn_runs.py`` times the whole
training of 8 runs with the batched CNN path that was built on these findings
(:class:`~cobelrun.agents.batched_cnn.BatchedCNNDQN`: a plain convolution per run on the CPU).

Thread CPU time per step of all R runs (torch on 1 thread, as cobel sets it), the best of
``--repeats`` rounds; ``--device cuda`` times wall clock with synchronisation instead. Prints a
table and writes ``benchmarks/results/bench_cnn_batch.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"

#: (C, H, W), convolutions [channels, kernel, stride], dense units, dropout, actions
SETTINGS = {
    "fig8": ((3, 12, 48), [[32, 5, 1], [64, 4, 2], [64, 3, 2]], 50, 0.35, 12),
    "fig6a": ((3, 84, 84), [[16, 8, 4], [32, 4, 2]], 256, 0.0, 6),
}
BATCH = 32


def sequential_net(setting: str):
    """One run's network as the DQN agent builds it: ``ConvFeatures`` + linear Q head."""
    import gymnasium as gym
    import torch

    from cobelrun.agents.dqn import ConvFeatures

    shape, convs, dense, dropout, actions = SETTINGS[setting]
    space = gym.spaces.Box(0.0, 1.0, shape, np.float32)
    features = ConvFeatures(space, convs=convs, features_dim=dense, dropout=dropout)
    return torch.nn.Sequential(features, torch.nn.Linear(dense, actions))


class GroupedNet:
    """R runs' networks as one module: convolutions with ``groups=R``, dense layers as
    ``bmm`` over a run axis."""

    def __init__(self, setting: str, runs: int, device: str) -> None:
        import torch

        shape, convs, dense, dropout, actions = SETTINGS[setting]
        c, h, w = shape
        layers: list[torch.nn.Module] = []
        for out, k, st in convs:
            layers += [torch.nn.Conv2d(c * runs, out * runs, k, st, groups=runs), torch.nn.ReLU()]
            c, h, w = out, (h - k) // st + 1, (w - k) // st + 1
        self.runs, self.flat = runs, c * h * w
        self.cnn = torch.nn.Sequential(*layers).to(device)
        scale = 1.0 / np.sqrt(self.flat)
        self.w1 = torch.nn.Parameter(torch.randn(runs, self.flat, dense, device=device) * scale)
        self.b1 = torch.nn.Parameter(torch.zeros(runs, 1, dense, device=device))
        self.w2 = torch.nn.Parameter(torch.randn(runs, dense, actions, device=device) * 0.1)
        self.b2 = torch.nn.Parameter(torch.zeros(runs, 1, actions, device=device))
        self.dropout = torch.nn.Dropout(dropout) if dropout > 0 else torch.nn.Identity()

    def parameters(self) -> list:
        return [*self.cnn.parameters(), self.w1, self.b1, self.w2, self.b2]

    def __call__(self, x):  # x: (B, R * C, H, W) -> (R, B, actions)
        import torch

        b = x.shape[0]
        h = self.cnn(x).reshape(b, self.runs, self.flat).transpose(0, 1)
        h = self.dropout(torch.relu(torch.baddbmm(self.b1, h, self.w1)))
        return torch.baddbmm(self.b2, h, self.w2)


def timed(step, n: int, device: str) -> float:
    """Seconds per call of ``step`` (thread CPU on the CPU, synchronised wall on CUDA)."""
    import torch

    for _ in range(3):
        step()
    if device == "cuda":
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        for _ in range(n):
            step()
        torch.cuda.synchronize()
        return (time.perf_counter() - t0) / n
    t0 = time.thread_time()
    for _ in range(n):
        step()
    return (time.thread_time() - t0) / n


def measure(setting: str, runs: int, steps: int, device: str) -> dict[str, float]:
    import torch
    from torch.func import functional_call, grad, stack_module_state, vmap

    shape, *_ = SETTINGS[setting]
    gen = torch.Generator(device="cpu").manual_seed(runs)
    obs = torch.rand(runs, BATCH, *shape, generator=gen).to(device)
    nxt = torch.rand(runs, BATCH, *shape, generator=gen).to(device)
    target_q = torch.rand(runs, BATCH, generator=gen).to(device)

    nets = [sequential_net(setting).to(device) for _ in range(runs)]
    targets = [sequential_net(setting).to(device) for _ in range(runs)]
    opts = [torch.optim.Adam(n.parameters(), lr=1e-4) for n in nets]

    def sequential() -> None:
        for r in range(runs):
            with torch.no_grad():
                y = 0.8 * targets[r](nxt[r]).max(1).values + target_q[r]
            loss = (nets[r](obs[r])[:, 0] - y).pow(2).mean()
            opts[r].zero_grad()
            loss.backward()
            opts[r].step()

    grouped, grouped_target = GroupedNet(setting, runs, device), GroupedNet(setting, runs, device)
    g_opt = torch.optim.Adam(grouped.parameters(), lr=1e-4)

    def side_by_side(x):  # (R, B, C, H, W) -> (B, R * C, H, W)
        return x.transpose(0, 1).reshape(BATCH, runs * shape[0], *shape[1:])

    g_obs, g_nxt = side_by_side(obs), side_by_side(nxt)

    def grouped_step() -> None:
        with torch.no_grad():
            y = 0.8 * grouped_target(g_nxt).max(2).values + target_q
        loss = (grouped(g_obs)[:, :, 0] - y).pow(2).mean(1).sum()
        g_opt.zero_grad()
        loss.backward()
        g_opt.step()

    params, buffers = stack_module_state(nets)
    t_params, t_buffers = stack_module_state(targets)
    base = sequential_net(setting).to("meta")
    v_params = {k: torch.nn.Parameter(v.detach()) for k, v in params.items()}
    v_opt = torch.optim.Adam(list(v_params.values()), lr=1e-4)

    def td_loss(p, b, x, y):
        return (functional_call(base, (p, b), (x,))[:, 0] - y).pow(2).mean()

    def q_next(p, b, x):
        return functional_call(base, (p, b), (x,)).max(1).values

    grad_all = vmap(grad(td_loss), randomness="different")
    next_all = vmap(q_next, randomness="different")

    def vmap_step() -> None:
        with torch.no_grad():
            y = 0.8 * next_all(t_params, t_buffers, nxt) + target_q
        grads = grad_all(v_params, buffers, obs, y)
        for k, p in v_params.items():
            p.grad = grads[k]
        v_opt.step()

    return {
        "sequential_ms": 1e3 * timed(sequential, steps, device),
        "grouped_ms": 1e3 * timed(grouped_step, steps, device),
        "vmap_ms": 1e3 * timed(vmap_step, steps, device),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", default="1,5,25", help="numbers of runs R, comma-separated")
    ap.add_argument("--steps", type=int, default=40, help="timed DQN steps per measurement")
    ap.add_argument("--repeats", type=int, default=2, help="rounds; the best is kept")
    ap.add_argument("--setting", default="fig8,fig6a", help="fig8 and/or fig6a")
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--out", type=Path, default=RESULTS / "bench_cnn_batch.json")
    args = ap.parse_args()

    import torch

    from cobelrun.agents.networks import set_torch_threads

    set_torch_threads(1)
    rows = []
    for setting in args.setting.split(","):
        if setting not in SETTINGS:
            raise SystemExit(f"unknown --setting '{setting}'; allowed: {', '.join(SETTINGS)}")
        for runs in (int(r) for r in args.runs.split(",")):
            best: dict[str, float] = {}
            for _ in range(args.repeats):
                for k, v in measure(setting, runs, args.steps, args.device).items():
                    best[k] = min(v, best.get(k, float("inf")))
            row = {"setting": setting, "runs": runs, **best,
                   "grouped_speedup": best["sequential_ms"] / best["grouped_ms"],
                   "vmap_speedup": best["sequential_ms"] / best["vmap_ms"]}  # fmt: skip
            rows.append(row)
            print(f"{setting:6s} R={runs:3d}: sequential {best['sequential_ms']:8.1f} ms, "
                  f"grouped {best['grouped_ms']:8.1f} ms ({row['grouped_speedup']:.2f}x), "
                  f"vmap {best['vmap_ms']:8.1f} ms ({row['vmap_speedup']:.2f}x) "
                  "per DQN step of all runs", flush=True)  # fmt: skip
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({
        "machine": platform.platform(), "processor": platform.processor(),
        "torch": torch.__version__, "device": args.device, "batch": BATCH, "rows": rows,
    }, indent=2))  # fmt: skip
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
