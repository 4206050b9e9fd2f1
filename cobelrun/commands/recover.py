"""``cobel recover``: parameter and model recovery of choice models on a task."""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path
from typing import Annotated, Any

import typer

HELP = """Simulate synthetic agents, fit every candidate model to each: parameter recovery (true vs fitted, Pearson r, bias, interval coverage) and model recovery (confusion matrices by AIC, BIC and held-out log-likelihood).

\b
  cobel recover task=reversal_bandit models=\\[q_learning,rescorla_wagner,dyna_q,wsls] n=100
  cobel recover task=two_afc models=\\[q_learning] n=100 task.protocol.phases.0.trials=200
  cobel recover ... prior.agent.beta=loguniform(1,20) starts=3 jobs=2 seed=3 --out DIR

models: q_learning, rescorla_wagner, dyna_q, wsls. Priors (defaults): agent.learning_rate uniform(0.1,0.9), agent.beta loguniform(1,10), agent.epsilon uniform(0.05,0.5). The task must be one choice per trial (two_afc, reversal_bandit); other overrides change it as in cobel run. Writes DIR (default recover-TASK): recovery.parquet (one row per agent and fitted model), parameters.csv, confusion.csv, recover.json, parameter_recovery.png, model_recovery.png. See docs/modelling.md.
"""

SPECIAL = ("models", "n", "starts", "jobs")


def _split(args: list[str]) -> tuple[dict[str, str], dict[str, str], list[str]]:
    special: dict[str, str] = {}
    priors: dict[str, str] = {}
    rest = []
    for a in args:
        key, eq, value = a.partition("=")
        if eq and key in SPECIAL:
            special[key] = value
        elif eq and key.startswith("prior."):
            priors[key.removeprefix("prior.")] = value
        else:
            rest.append(a)
    return special, priors, rest


def _int(special: dict[str, str], key: str, default: int, low: int) -> int:
    from cobelrun.errors import ConfigError

    try:
        value = int(special.get(key, str(default)))
    except ValueError:
        raise ConfigError(f"{key} must be an integer, got {special[key]!r}") from None
    if value < low:
        raise ConfigError(f"{key} must be >= {low}, got {value}")
    return value


def plan(args: list[str]) -> dict[str, Any]:
    """Check every argument and build the task; nothing is written."""
    from cobelrun.choice_models import MODELS
    from cobelrun.config import register_resolvers
    from cobelrun.errors import ConfigError
    from cobelrun.hydra_app import composer
    from cobelrun.recover import (
        RECOVERABLE,
        ChoiceTask,
        check_models,
        default_priors,
        parse_prior,
    )

    special, prior_args, overrides = _split(args)
    raw = special.get("models", "").strip()
    models = [m.strip() for m in raw.strip("[]").split(",") if m.strip()]
    if not models:
        raise ConfigError(f"cobel recover needs models=[...]; models that can be fitted: "
                          f"{', '.join(RECOVERABLE)}")  # fmt: skip
    check_models(models)
    bounds = {p.key: p.bounds for m in MODELS.values() for p in m.params}
    priors = default_priors()
    for key, text in prior_args.items():
        if key not in bounds:
            raise ConfigError(f"prior.{key}: not a parameter of any model; parameters: "
                              f"{', '.join(bounds)}")  # fmt: skip
        priors[key] = parse_prior(key, text, bounds[key])
    n = _int(special, "n", 100, 1)
    starts = _int(special, "starts", 3, 1)
    jobs = _int(special, "jobs", 1, 1)
    register_resolvers()
    with composer() as compose:
        cfg = compose(overrides)
    task = ChoiceTask.from_config(cfg)
    return {"models": models, "priors": priors, "n": n, "starts": starts, "jobs": jobs,
            "seed": int(cfg.get("seed", 0) or 0), "task": task}  # fmt: skip


def write(out: Path, p: dict[str, Any]) -> dict[str, Any]:
    """Run the recovery and write its folder (in a temporary folder renamed at the end)."""
    from cobelrun.figures import save_figure
    from cobelrun.figures.recovery import plot_confusion, plot_parameter_recovery
    from cobelrun.recover import CRITERIA, confusion, parameter_recovery, recover

    start = time.perf_counter()
    table = recover(p["task"], p["models"], p["n"], priors=p["priors"], n_starts=p["starts"],
                    seed=p["seed"], jobs=p["jobs"])  # fmt: skip
    elapsed = time.perf_counter() - start
    params = parameter_recovery(table)
    matrices = {c: confusion(table, c) for c in CRITERIA}
    long = [{"criterion": c, "generating": g, "fitted": f, "share": float(m.loc[g, f])}
            for c, m in matrices.items() for g in m.index for f in m.columns]  # fmt: skip
    summary = {
        "task": p["task"].name,
        "n_trials": p["task"].n_trials,
        "models": p["models"],
        "n": p["n"],
        "seed": p["seed"],
        "starts": p["starts"],
        "jobs": p["jobs"],
        "priors": {k: str(v) for k, v in p["priors"].items()},
        "seconds": round(elapsed, 2),
        "parameters": params.to_dict(orient="records"),
        "confusion_diagonal": {
            c: {g: float(m.loc[g, g]) for g in m.index if g in m.columns}
            for c, m in matrices.items()
        },
    }
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
    try:
        tmp.mkdir(parents=True)
        table.to_parquet(tmp / "recovery.parquet", index=False)
        params.to_csv(tmp / "parameters.csv", index=False)
        import pandas as pd

        pd.DataFrame(long).to_csv(tmp / "confusion.csv", index=False)
        (tmp / "recover.json").write_text(json.dumps(summary, indent=2) + "\n")
        save_figure(plot_parameter_recovery(table, params), tmp / "parameter_recovery.png")
        save_figure(plot_confusion(matrices), tmp / "model_recovery.png")
        if out.exists():
            out.rmdir()  # checked empty before the run
        tmp.rename(out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return summary


def register(app: typer.Typer) -> None:
    """Add ``cobel recover`` to ``app``."""

    @app.command(
        "recover",
        help=HELP,
        context_settings={"allow_extra_args": True, "ignore_unknown_options": True},
    )
    def recover_cmd(
        ctx: typer.Context,
        out: Annotated[
            Path | None,
            typer.Option(
                "--out",
                "-o",
                help="Folder to write (default recover-TASK); must not exist or be empty.",
            ),
        ] = None,
    ) -> None:
        from cobelrun.commands.common import fail
        from cobelrun.errors import CobelError

        try:
            p = plan(list(ctx.args))
            folder = out or Path(f"recover-{p['task'].name}")
            if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
                raise CobelError(f"{folder} exists and is not an empty folder; pick another --out")
            summary = write(folder, p)
        except CobelError as exc:
            fail(str(exc))
        except OSError as exc:
            fail(f"cannot write {out or 'the recovery folder'}: {exc.strerror or exc}")
        for row in summary["parameters"]:
            typer.echo(f"{row['model']:>16} {row['param']:<20} r = {row['r']:.3f}  "
                       f"bias = {row['bias']:+.3g}  coverage = {row['coverage']:.2f}")  # fmt: skip
        for criterion, diag in summary["confusion_diagonal"].items():
            typer.echo(f"model recovery by {criterion}: "
                       + ", ".join(f"{g} {v:.2f}" for g, v in diag.items()))  # fmt: skip
        typer.echo(f"{summary['seconds']:.1f} s; {folder}")
