"""Why parameter and model recovery fall short on some designs (issue 36): fit or design?

Run on demand (not a test)::

    python benchmarks/diagnose_recovery.py [--n 100] [--part two_afc|models|all]

``two_afc`` part: Q-learning on ``task=two_afc`` (200 trials, the default priors): parameter
recovery (Pearson r, 95 % interval coverage, bias); whether every fit's likelihood is at least
that of the true parameters (the optimiser found the maximum); 10 starts instead of 3; 1,000
trials; a narrower learning-rate prior; and probabilistic rewards (``env=two_afc_probabilistic
env.reward_probs=[p,q]``: a correct choice rewarded with probability ``p``, a wrong one with
``q``, drawn from the env's generator) at 200 and 400 trials.

``models`` part: Q-learning against Dyna-Q alone on ``protocol=reversal_blocks`` (400 trials):
the BIC confusion diagonal, and per true learning-rate band the share recovered and the median
|BIC difference|; then the same with the 8 blocks run twice (800 trials).

Prints one line per design; docs/modelling.md quotes a run.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _summary(table, label: str) -> None:
    from cobelrun.recover import parameter_recovery

    p = parameter_recovery(table)
    cells = {r.param.split(".")[-1]: f"r {r.r:.3f} coverage {r.coverage:.2f} bias {r.bias:+.3f}"
             for r in p.itertuples()}  # fmt: skip
    print(f"{label}: {cells}", flush=True)


def two_afc(n: int) -> None:
    from bench_recover import _task

    from cobelrun.choice_models import MODELS, model_logp
    from cobelrun.recover import Prior, default_priors, recover

    task = _task(["task=two_afc", "task.protocol.phases.0.trials=200"])
    table = recover(task, ["q_learning"], n)
    _summary(table, "two_afc 200 trials")
    model, priors = MODELS["q_learning"], default_priors()
    own = table[table["fitted"] == "q_learning"].reset_index(drop=True)
    gaps = []
    for i, child in enumerate(np.random.SeedSequence(0).spawn(n)):  # recover()'s seeds
        prior_seed, sim_seed, _ = child.spawn(3)
        rng = np.random.default_rng(prior_seed)
        theta = np.array([priors[k].sample(rng) for k in model.keys])
        data = task.simulate(model, theta, sim_seed)
        logp = model_logp(model, theta, data["choice"].to_numpy(np.int64),
                          data["reward"].to_numpy(np.float64), data["state"].to_numpy(np.int64),
                          np.zeros(len(data), np.int64), *task.sizes)  # fmt: skip
        gaps.append(-logp.sum() - own.loc[i, "nll"])
    gaps = np.array(gaps)
    print(f"nll(true) - nll(fit): min {gaps.min():.3f}, median {np.median(gaps):.3f}; "
          f"fits worse than the truth: {(gaps < -1e-6).sum()} of {n}", flush=True)  # fmt: skip
    _summary(recover(task, ["q_learning"], n, n_starts=10), "two_afc 200 trials, 10 starts")
    _summary(recover(_task(["task=two_afc", "task.protocol.phases.0.trials=1000"]),
                     ["q_learning"], n), "two_afc 1000 trials")  # fmt: skip
    lr = {"agent.learning_rate": Prior("uniform", 0.05, 0.5)}
    _summary(recover(task, ["q_learning"], n, priors=lr), "two_afc 200, lr prior U(0.05,0.5)")

    for probs, trials in (((0.8, 0.2), 200), ((0.8, 0.2), 400), ((0.75, 0.25), 200),
                          ((0.9, 0.1), 200)):  # fmt: skip
        t = _task(["task=two_afc_probabilistic", f"env.reward_probs=[{probs[0]},{probs[1]}]",
                   f"task.protocol.phases.0.trials={trials}"])  # fmt: skip
        _summary(recover(t, ["q_learning"], n), f"two_afc {trials}, rewards {probs}")


def models(n: int) -> None:
    from bench_recover import _task

    from cobelrun.recover import confusion, recover

    blocks = _task(["task=reversal_bandit", "protocol=reversal_blocks"])
    for label in ("400 trials", "800 trials"):
        if label == "800 trials":
            blocks.phases = [*blocks.phases,
                             *(replace(p, name=p.name + "_again") for p in blocks.phases)]  # fmt: skip
        table = recover(blocks, ["q_learning", "dyna_q"], n)
        c = confusion(table, "bic")
        print(f"reversal_blocks {label}, Q vs Dyna-Q, BIC diagonal: "
              f"{ {g: round(float(c.loc[g, g]), 2) for g in c.index} }", flush=True)  # fmt: skip
        bic = table.pivot_table(index=["generating", "agent"], columns="fitted", values="bic")
        own = table[table["fitted"] == table["generating"]].set_index(["generating", "agent"])
        for g, other in (("q_learning", "dyna_q"), ("dyna_q", "q_learning")):
            d = bic.loc[g]
            right = (d[g] <= d[other]).to_numpy()
            lr = own.loc[g, "true:agent.learning_rate"].to_numpy()
            for lo, hi in ((0.1, 0.3), (0.3, 0.5), (0.5, 0.7), (0.7, 0.9)):
                m = (lr >= lo) & (lr < hi)
                if not m.any():
                    continue
                print(f"  {g}, true lr [{lo}, {hi}): recovered {right[m].mean():.2f} (n={m.sum()}),"
                      f" median |BIC difference| {np.median(np.abs((d[g] - d[other]).to_numpy()[m])):.2f}",
                      flush=True)  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=100)
    ap.add_argument("--part", choices=("two_afc", "models", "all"), default="all")
    args = ap.parse_args()
    if args.part in ("two_afc", "all"):
        two_afc(args.n)
    if args.part in ("models", "all"):
        models(args.n)


if __name__ == "__main__":
    main()
