"""Recovery benchmark (issue 36): speed and the acceptance numbers of ``cobel recover``.

Run on demand (not a test)::

    python benchmarks/bench_recover.py [--n 100] [--jobs 1 2] [--skip-acceptance]

Prints and writes ``benchmarks/results/recover.json``:

* speed: wall time of a 100-agent x 3-model recovery (q_learning, rescorla_wagner, wsls; every
  model fitted to every agent: 900 fits plus 900 held-out fits) on the 200-trial
  ``task=reversal_bandit``, in this process (compile time excluded by a warm-up), for each
  ``--jobs``; and ``cobel recover`` end to end (process start, Hydra's launcher, figures) with
  ``jobs=1`` (the basic launcher, in its process) and ``jobs=2`` (the joblib launcher, 2
  worker processes): wall time and CPU time (the process and its children);
* parameter recovery of Q-learning on ``task=two_afc`` with 200 trials (Pearson r, bias,
  95 % interval coverage) and on the reversal bandit;
* model recovery among q_learning, rescorla_wagner, dyna_q, wsls on the reversal bandit
  (200 trials) and on ``protocol=reversal_blocks`` (8 blocks of 50 trials): the confusion
  diagonal by AIC, BIC and held-out log-likelihood;
* ``--long-reversal BLOCKS``: model recovery of the four models with agents that exploit what
  they learn (``prior.agent.beta=loguniform(3,20)``; ``--default-priors``: the defaults) on
  BLOCKS blocks of 50 trials, the better arm (0.8 vs 0.2) switching every block;
* conditioning (``--conditioning``): recovery of ``rw_response``, ``ph_response`` and
  ``td_response`` on ``task=latent_inhibition`` and ``task=second_order``;
* ``--two-afc``: parameter recovery of Q-learning (the default priors, 100 agents x 200
  trials) on the two-alternative task's designs, written to ``results/recover_two_afc.json``;
* ``--short-reversal``: model recovery of the four models (the default priors) on reversal
  designs of 400 trials, written to ``results/recover_short_reversal.json``.

Designs declared before they were measured (2026-11-28, issue 36), each run once with the one
seed 0 and reported whatever it gives. Parameter recovery is a property of the design and of
the prior range (Wilson & Collins 2019, eLife 8:e49547: design the experiment so that the
parameters change the behaviour, and check by simulation that they come back; Spektor & Kellen
2018, Psychon Bull Rev 25:2047: poor recovery from an uninformative design is not rescued by
the estimation method). ``--two-afc``:

* ``two_afc`` (deterministic rewards) and ``two_afc_probabilistic`` (0.8 / 0.2): the task as it
  is, and the acceptance measure with probabilistic rewards;
* ``two_afc_reversal``: 0.8 / 0.2, the better stimulus swapping every 50 trials (3 reversals).
  Why: with stable contingencies an exploiting agent's values settle and its choices saturate
  (an inverse temperature of 5 already gives ~95 % correct at a value difference of 0.6), so
  high inverse temperatures look alike; after each reversal the values cross and choices are
  graded at any inverse temperature, and the speed of relearning is set by the learning rate;
* ``two_afc_reversal env.choices=[[0,1]]``: the same with one stimulus pair. Why: the task's
  displays are separate look-ups for a tabular learner (docs/two_afc.md), so 200 trials over 4
  displays are ~50 learning trials per value; one pair (2 displays, sides still random) gives
  each display ~100 trials, and ~25 per display between reversals instead of ~12.

``--short-reversal`` (item 3 of the acceptance: model recovery among Q-learning,
Rescorla-Wagner, Dyna-Q and WSLS within ~400 trials):

* 16 blocks of 25 trials, 0.8 / 0.2 (15 reversals). Why: Dyna-Q differs from Q-learning in the
  unchosen arm (its replay pulls it to the arm's remembered reward), which shows when an agent
  has to switch back after a reversal; more reversals give more such switches;
* 16 blocks of 25 trials, 0.9 / 0.1. Why: more reliable outcomes make the remembered rewards
  (and so the replayed values) differ more from a slowly learning Q-learner's values.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def _task(overrides: list[str]):
    from cobelrun.config import register_resolvers
    from cobelrun.hydra_app import composer
    from cobelrun.recover import ChoiceTask

    register_resolvers()
    with composer() as compose:
        return ChoiceTask.from_config(compose(overrides))


def _summary(table) -> dict:
    from cobelrun.recover import CRITERIA, confusion, parameter_recovery

    params = parameter_recovery(table)
    diag = {}
    for c in CRITERIA:
        m = confusion(table, c)
        diag[c] = {g: round(float(m.loc[g, g]), 3) for g in m.index}
    return {"parameters": params.round(4).to_dict(orient="records"), "confusion_diagonal": diag}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=100)
    parser.add_argument("--jobs", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--skip-acceptance", action="store_true")
    parser.add_argument("--skip-speed", action="store_true")
    parser.add_argument("--conditioning", action="store_true")
    parser.add_argument("--long-reversal", type=int, default=0, metavar="BLOCKS")
    parser.add_argument("--two-afc", action="store_true", help="the two_afc designs only")
    parser.add_argument("--short-reversal", action="store_true",
                        help="model recovery on the 400-trial reversal designs only")  # fmt: skip
    parser.add_argument(
        "--default-priors",
        action="store_true",
        help="--long-reversal with the default priors (beta logU(1,10))",
    )
    args = parser.parse_args()
    if args.two_afc or args.short_reversal:
        designs(args.n, args.two_afc, args.short_reversal)
        return
    from cobelrun.recover import recover

    out: dict = {"host": platform.node(), "cpus": os.cpu_count(), "n": args.n,
                 "load_before": os.getloadavg()}  # fmt: skip
    reversal = _task(["task=reversal_bandit"])
    three = ["q_learning", "rescorla_wagner", "wsls"]
    recover(reversal, three, 2)  # warm-up: numba caches loaded or compiled
    out["speed"] = {}
    for jobs in [] if args.skip_speed else args.jobs:
        t, c = time.perf_counter(), time.process_time()
        recover(reversal, three, args.n, jobs=jobs)
        wall, cpu = round(time.perf_counter() - t, 1), round(time.process_time() - c, 1)
        # CPU time of this process only (jobs > 1: the workers' time is not counted)
        out["speed"][f"jobs={jobs}"] = {"wall_s": wall, "cpu_s_this_process": cpu}
        print(f"{args.n} agents x 3 models x 3 fits, 200 trials, jobs={jobs}: {wall} s wall, "
              f"{cpu} s CPU in this process", flush=True)  # fmt: skip
    for jobs in () if args.skip_speed else (1, 2):
        with tempfile.TemporaryDirectory() as tmp:
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            t = time.perf_counter()
            proc = subprocess.run([sys.executable, "-m", "cobelrun.cli", "recover",
                                   "task=reversal_bandit",
                                   "models=[q_learning,rescorla_wagner,wsls]", f"n={args.n}",
                                   f"jobs={jobs}", "--out", str(Path(tmp) / "rec")],
                                  capture_output=True, text=True)  # fmt: skip
            wall = round(time.perf_counter() - t, 1)
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu = round(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime, 1)
            if proc.returncode:
                raise SystemExit(proc.stderr)
            launcher = "basic" if jobs == 1 else "joblib"
            out["speed"][f"cli_jobs={jobs}"] = {"wall_s": wall, "cpu_s": cpu, "launcher": launcher}
            print(f"cobel recover end to end, jobs={jobs} ({launcher}): {wall} s wall, "
                  f"{cpu} s CPU", flush=True)  # fmt: skip
    if not args.skip_acceptance:
        two_afc = _task(["task=two_afc", "task.protocol.phases.0.trials=200"])
        out["two_afc_q_learning"] = _summary(recover(two_afc, ["q_learning"], args.n))
        print("two_afc:", json.dumps(out["two_afc_q_learning"]), flush=True)
        prob = _task(["task=two_afc_probabilistic"])
        out["two_afc_probabilistic_q_learning"] = _summary(recover(prob, ["q_learning"], args.n))
        print("two_afc_probabilistic:", json.dumps(out["two_afc_probabilistic_q_learning"]),
              flush=True)  # fmt: skip
        four = ["q_learning", "rescorla_wagner", "dyna_q", "wsls"]
        out["reversal_4_models"] = _summary(recover(reversal, four, args.n))
        print("reversal:", json.dumps(out["reversal_4_models"]), flush=True)
        blocks = _task(["task=reversal_bandit", "protocol=reversal_blocks"])
        out["reversal_blocks_4_models"] = _summary(recover(blocks, four, args.n))
        print("reversal_blocks:", json.dumps(out["reversal_blocks_4_models"]), flush=True)
    if args.long_reversal:
        from cobelrun.recover import Prior

        arms = [("0.8", "0.2"), ("0.2", "0.8")]
        blocks = ",".join(
            f"{{name:b{i + 1},trials:50,rewards:{{0:{arms[i % 2][0]},1:{arms[i % 2][1]}}}}}"
            for i in range(args.long_reversal)
        )
        task = _task(["task=reversal_bandit", f"task.protocol.phases=[{blocks}]"])
        t, c = time.perf_counter(), time.process_time()
        four = ["q_learning", "rescorla_wagner", "dyna_q", "wsls"]
        exploit = {"agent.beta": Prior("loguniform", 3.0, 20.0)}
        table = recover(task, four, args.n, priors={} if args.default_priors else exploit)
        prior = "default_priors" if args.default_priors else "beta_3_20"
        key = f"reversal_{args.long_reversal}_blocks_{prior}"
        out[key] = _summary(table)
        out[key]["seconds"] = round(time.perf_counter() - t, 1)
        out[key]["cpu_s"] = round(time.process_time() - c, 1)
        print(f"{key}:", json.dumps(out[key]), flush=True)
    if args.conditioning:
        models = ["rw_response", "ph_response", "td_response"]
        for name in ("latent_inhibition", "second_order"):
            t = time.perf_counter()
            table = recover(_task([f"task={name}"]), models, args.n)
            out[f"conditioning_{name}"] = _summary(table)
            out[f"conditioning_{name}"]["seconds"] = round(time.perf_counter() - t, 1)
            print(f"{name}:", json.dumps(out[f"conditioning_{name}"]), flush=True)
    out["load_after"] = os.getloadavg()
    (HERE / "results").mkdir(exist_ok=True)
    out["date"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    name = "recover.json" if not args.skip_acceptance else "recover_speed.json"
    (HERE / "results" / name).write_text(json.dumps(out, indent=2) + "\n")


#: ``--two-afc``: (label, overrides) of each design, in the order declared above
TWO_AFC_DESIGNS = [
    ("two_afc (deterministic)", ["task=two_afc", "task.protocol.phases.0.trials=200"]),
    ("two_afc_probabilistic (0.8/0.2)", ["task=two_afc_probabilistic"]),
    ("two_afc_reversal (0.8/0.2, 3 reversals)", ["task=two_afc_reversal"]),
    ("two_afc_reversal, one stimulus pair", ["task=two_afc_reversal", "env.choices=[[0,1]]"]),
]


def _blocks(n_blocks: int, trials: int, good: float, bad: float) -> str:
    """``task.protocol.phases=[...]`` of a bandit whose better arm switches every block."""
    arms = [(good, bad), (bad, good)]
    return (
        "task.protocol.phases=["
        + ",".join(
            f"{{name:b{i + 1},trials:{trials},rewards:{{0:{arms[i % 2][0]},1:{arms[i % 2][1]}}}}}"
            for i in range(n_blocks)
        )
        + "]"
    )


#: ``--short-reversal``: (label, overrides) of each design, in the order declared above
SHORT_REVERSAL_DESIGNS = [
    ("16 blocks of 25, 0.8/0.2", ["task=reversal_bandit", _blocks(16, 25, 0.8, 0.2)]),
    ("16 blocks of 25, 0.9/0.1", ["task=reversal_bandit", _blocks(16, 25, 0.9, 0.1)]),
]


def _diagnostics(table) -> list[dict]:
    """Per generating model and parameter, beside the tool's Pearson r: Spearman's rank r, the
    Pearson r of the logarithms (the inverse temperature's prior is log-uniform) and the
    number of fits within 1e-3 (relative) of a parameter's bound."""
    import numpy as np
    from scipy.stats import pearsonr, spearmanr

    from cobelrun.choice_models import MODELS

    own = table[table["generating"] == table["fitted"]]
    out = []
    for model, part in own.groupby("generating", sort=False):
        specs = [p for p in MODELS[str(model)].params if p.key in MODELS[str(model)].default_keys]
        edge = np.zeros(len(part), bool)  # agents with any fitted parameter at its bound
        for spec in specs:
            est, (lo, hi) = part[f"fit:{spec.key}"].to_numpy(), spec.bounds
            edge |= (est <= lo + 1e-3 * (hi - lo)) | (est >= hi * (1 - 1e-3))
        for spec in specs:
            true = part[f"true:{spec.key}"].to_numpy()
            est = part[f"fit:{spec.key}"].to_numpy()
            lo, hi = spec.bounds
            at_bound = int(np.sum((est <= lo + 1e-3 * (hi - lo)) | (est >= hi * (1 - 1e-3))))
            row = {"model": model, "param": spec.key, "spearman": round(float(
                spearmanr(true, est)[0]), 4), "fits_at_bound": at_bound,
                "r_without_bound_fits": round(float(pearsonr(true[~edge], est[~edge])[0]), 4),
                "agents_without_bound_fits": int((~edge).sum())}  # fmt: skip
            if np.all(est > 0) and np.all(true > 0):
                row["r_log"] = round(float(pearsonr(np.log(true), np.log(est))[0]), 4)
            if spec.key == "agent.learning_rate" and "true:agent.beta" in part:
                beta = part["true:agent.beta"].to_numpy()
                for name, m in (("beta<2", beta < 2), ("beta>=2", beta >= 2)):
                    if m.sum() > 2:
                        row[f"r_{name}"] = round(float(pearsonr(true[m], est[m])[0]), 4)
                        row[f"n_{name}"] = int(m.sum())
            out.append(row)
    return out


def _diagonal_by_rate(table) -> dict:
    """Per generating model with a learning rate: the share of its agents best fitted by their
    own model (BIC) among agents with a true rate below 0.5 and at or above it."""
    import numpy as np

    key = "true:agent.learning_rate"
    if key not in table:
        return {}
    best = table.sort_values("bic").groupby(["generating", "agent"], sort=False).head(1)
    out = {}
    for model, part in best.groupby("generating", sort=False):
        rate = part[key].to_numpy()
        if np.isnan(rate).all():
            continue
        right = (part["fitted"] == model).to_numpy()
        out[str(model)] = {name: {"share": round(float(right[m].mean()), 3), "n": int(m.sum())}
                           for name, m in (("rate<0.5", rate < 0.5), ("rate>=0.5", rate >= 0.5))
                           if m.any()}  # fmt: skip
    return out


#: ``--two-afc``, added after the declared designs were measured (post hoc, so labelled): the
#: one-pair reversal with agents that are neither near random nor saturated, beta logU(2, 10)
#: (the declared rows showed the learning rate hardly identified for beta < 2)
TWO_AFC_POSTHOC = [
    ("post hoc: two_afc_reversal, one stimulus pair, beta logU(2,10)",
     ["task=two_afc_reversal", "env.choices=[[0,1]]"], {"agent.beta": ("loguniform", 2.0, 10.0)}),
]  # fmt: skip


def _rotating(n_blocks: int, trials: int, arms: int, good: float, bad: float) -> list[str]:
    """A ``arms``-armed bandit whose better arm moves to the next arm every block."""
    phases = ",".join(
        f"{{name:b{i + 1},trials:{trials},rewards:{{"
        + ",".join(f"{a}:{good if a == i % arms else bad}" for a in range(arms))
        + "}}"
        for i in range(n_blocks)
    )
    probs = ",".join(str(good if a == 0 else bad) for a in range(arms))
    return [
        "task=reversal_bandit",
        f"env.reward_probs=[{probs}]",
        f"task.protocol.phases=[{phases}]",
    ]


#: ``--short-reversal``, added after the declared designs were measured (post hoc, so
#: labelled): three arms, so that every trial leaves two unchosen arms for Dyna-Q's replay to
#: move (the declared rows left Q-learning and Dyna-Q confused, 0.59-0.69)
SHORT_REVERSAL_POSTHOC = [
    ("post hoc: 3 arms, 8 blocks of 50, 0.8/0.2/0.2, the better arm rotating",
     _rotating(8, 50, 3, 0.8, 0.2), {}),
]  # fmt: skip


def designs(n: int, two_afc: bool, short_reversal: bool) -> None:
    """Run the declared designs (module docstring), then the post-hoc ones, one at a time;
    print and write each."""
    from cobelrun.recover import Prior, confusion, recover

    def run(label: str, overrides: list[str], models: list[str], priors: dict) -> dict:
        task = _task(overrides)
        t, c = time.perf_counter(), time.process_time()
        table = recover(task, models, n, priors={k: Prior(*v) for k, v in priors.items()})
        row = {"overrides": overrides, "priors": {k: f"{v[0]}({v[1]:g},{v[2]:g})"
                                                  for k, v in priors.items()},
               "n_trials": task.n_trials, **_summary(table),
               "diagnostics": _diagnostics(table),
               "bic_diagonal_by_learning_rate": _diagonal_by_rate(table),
               "bic_confusion": confusion(table, "bic").round(3).to_dict(orient="index")}  # fmt: skip
        row["wall_s"] = round(time.perf_counter() - t, 1)
        row["cpu_s"] = round(time.process_time() - c, 1)
        row["load"] = os.getloadavg()
        print(f"{label}:", json.dumps(row), flush=True)
        return row

    (HERE / "results").mkdir(exist_ok=True)
    parts = []
    if two_afc:
        rows = [(label, o, {}) for label, o in TWO_AFC_DESIGNS] + TWO_AFC_POSTHOC
        parts.append(("recover_two_afc.json", rows, ["q_learning"]))
    if short_reversal:
        four = ["q_learning", "rescorla_wagner", "dyna_q", "wsls"]
        rows = [(label, o, {}) for label, o in SHORT_REVERSAL_DESIGNS] + SHORT_REVERSAL_POSTHOC
        parts.append(("recover_short_reversal.json", rows, four))
    for name, rows, models in parts:
        out: dict = {"host": platform.node(), "cpus": os.cpu_count(), "n": n, "seed": 0,
                     "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                     "designs": {}}  # fmt: skip
        for label, overrides, priors in rows:
            out["designs"][label] = run(label, overrides, models, priors)
            (HERE / "results" / name).write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
