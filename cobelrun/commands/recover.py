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
  cobel recover task=acquisition_extinction models=\\[rw_response,ph_response,td_response] n=50
  cobel recover ... prior.agent.beta=loguniform(1,20) starts=3 jobs=2 seed=3 --out DIR
  cobel recover ... jobs=50 --launcher slurm --launcher-arg partition=cpu

Choice tasks (one choice per trial: two_afc, reversal_bandit): models q_learning, rescorla_wagner, dyna_q, wsls. Conditioning tasks (env=sequence; the response at the cue's onset): rw_response, td_response, ph_response. Priors (defaults): agent.learning_rate uniform(0.1,0.9), agent.beta loguniform(1,10), agent.epsilon uniform(0.05,0.5), agent.response_beta loguniform(2,20), agent.associability_rate uniform(0.1,0.9). The agents are split into jobs=N jobs (default 2) of one sweep, run through Hydra's launcher as cobel run -m does: joblib (N workers) by default, or --launcher NAME (submitit_local, slurm, ...); the table does not depend on N. Other overrides change the task as in cobel run. Writes DIR (default recover-TASK): recovery.parquet (one row per agent and fitted model), parameters.csv, confusion.csv, recover.json, parameter_recovery.png, model_recovery.png and jobs/ (the sweep's job folders). See docs/modelling.md.
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


def plan(args: list[str], launcher: list[str] | None = None) -> dict[str, Any]:
    """Check every argument and build the task; nothing is written."""
    from cobelrun.config import register_resolvers
    from cobelrun.errors import ConfigError
    from cobelrun.hydra_app import composer
    from cobelrun.recover import (
        CONDITIONING_MODELS,
        RECOVERABLE,
        ChoiceTask,
        check_setup,
        parse_priors,
    )

    special, prior_args, overrides = _split(args)
    raw = special.get("models", "").strip()
    models = [m.strip() for m in raw.strip("[]").split(",") if m.strip()]
    if not models:
        raise ConfigError(f"cobel recover needs models=[...]; models that can be fitted: "
                          f"{', '.join(RECOVERABLE)} (choice tasks), "
                          f"{', '.join(CONDITIONING_MODELS)} (conditioning tasks)")  # fmt: skip
    items = [f"{k}={v}" for k, v in prior_args.items()]
    parse_priors(items)
    n = _int(special, "n", 100, 1)
    starts = _int(special, "starts", 3, 1)
    jobs = _int(special, "jobs", 2, 1)
    register_resolvers()
    with composer() as compose:
        cfg = compose(overrides)
    task = ChoiceTask.from_config(cfg)
    priors = check_setup(task, models, models, n, parse_priors(items))
    return {"models": models, "priors": priors, "prior_items": items, "n": n, "starts": starts,
            "jobs": min(jobs, n * len(models)), "seed": int(cfg.get("seed", 0) or 0),
            "task": task, "overrides": overrides, "launcher": launcher or []}  # fmt: skip


def _quote(text: str) -> str:
    """A Hydra override string value (single-quoted)."""
    return "'" + text.replace("\\", "\\\\").replace("'", "\\'") + "'"


def sweep_args(p: dict[str, Any], sweep_dir: Path) -> list[str]:
    """``cobel run -m`` arguments of the recovery's sweep: the task with ``task.job`` a
    :class:`cobelrun.recover.RecoveryJob` swept over its chunks, the launcher, the folder."""
    from cobelrun.figures.registry import launcher_overrides

    priors = ",".join(_quote(item) for item in p["prior_items"])
    node = (f"{{_target_:cobelrun.recover.RecoveryJob,models:[{','.join(p['models'])}],"
            f"n:{p['n']},starts:{p['starts']},chunks:{p['jobs']},priors:[{priors}]}}")  # fmt: skip
    launcher = p["launcher"] or launcher_overrides(p["jobs"])
    return ["-m", *p["overrides"], f"+task.job={node}",
            f"+task.job.chunk={','.join(str(k) for k in range(p['jobs']))}", *launcher,
            f"hydra.sweep.dir={_quote(str(sweep_dir))}"]  # fmt: skip


def run_sweep(p: dict[str, Any], sweep_dir: Path) -> Any:
    """Run the recovery's jobs through Hydra's launcher (:func:`cobelrun.hydra_app.launch`, as
    ``cobel figure`` runs a figure's runs) and join their tables; a job that failed is one
    CobelError line naming it."""
    import contextlib
    import logging
    import sys

    import pandas as pd

    from cobelrun.errors import CobelError
    from cobelrun.hydra_app import launch
    from cobelrun.io.sweep_folder import job_rows
    from cobelrun.recover import sort_table

    root_log = logging.getLogger()
    level, handlers = root_log.level, list(root_log.handlers)
    try:
        with contextlib.redirect_stdout(sys.stderr):  # stdout: cobel recover's own lines
            code = launch(sweep_args(p, sweep_dir), quiet=True)
    finally:  # Hydra configured logging for the sweep
        root_log.handlers[:] = handlers
        root_log.setLevel(level)
    if code == 130:
        raise KeyboardInterrupt
    rows = job_rows(sweep_dir, write=False)
    failed = [r for r in rows if r["status"] != "done"]
    if code != 0 or failed or len(rows) != p["jobs"]:
        first = failed[0] if failed else {"job": "?", "status": "failed", "error": ""}
        raise CobelError(f"recovery job {first['job']} {first['status']}"
                         + (f": {first['error']}" if first.get("error") else "")
                         + "; nothing written")  # fmt: skip
    parts = [pd.read_parquet(Path(r["run_dir"]) / "recovery.parquet") for r in rows]
    return sort_table(pd.concat(parts, ignore_index=True), p["models"], p["models"])


def write(out: Path, p: dict[str, Any]) -> dict[str, Any]:
    """Run the recovery and write its folder (in a temporary folder renamed at the end)."""
    from cobelrun.figures import save_figure
    from cobelrun.figures.recovery import plot_confusion, plot_parameter_recovery
    from cobelrun.recover import CRITERIA, confusion, parameter_recovery

    tmp = out.absolute().with_name(f".{out.name}.{os.getpid()}.tmp")
    try:
        tmp.mkdir(parents=True)
        start = time.perf_counter()
        table = run_sweep(p, tmp / "jobs")
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
            "launcher": [
                a
                for a in sweep_args(p, tmp)
                if a.startswith("hydra/launcher=") or a.startswith("hydra.launcher.")
            ],
            "priors": {k: str(v) for k, v in p["priors"].items()},
            "seconds": round(elapsed, 2),
            "parameters": params.to_dict(orient="records"),
            "confusion_diagonal": {
                c: {g: float(m.loc[g, g]) for g in m.index if g in m.columns}
                for c, m in matrices.items()
            },
        }
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
        launcher: Annotated[
            str | None,
            typer.Option(
                "--launcher",
                help="Run the jobs through this Hydra launcher (a name as in `cobel run -m "
                "hydra/launcher=NAME`: submitit_local, slurm, ...); default joblib with jobs= "
                "workers.",
            ),
        ] = None,
        launcher_arg: Annotated[
            list[str] | None,
            typer.Option(
                "--launcher-arg",
                help="KEY=VALUE for the launcher (hydra.launcher.KEY=VALUE), e.g. "
                "partition=cpu; repeatable.",
            ),
        ] = None,
    ) -> None:
        from cobelrun.commands.common import fail, launcher_choice
        from cobelrun.errors import CobelError

        try:
            hydra_launcher = launcher_choice(launcher, launcher_arg or [])
            p = plan(list(ctx.args), hydra_launcher)
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
