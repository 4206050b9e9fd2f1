"""``cobel fit``: maximum-likelihood fit of an agent's learning parameters to choice data."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import typer

HELP = """Fit agent parameters to behavioural choice data by maximum likelihood.

\b
  cobel fit task=two_afc agent=dyna_q data=CHOICES.parquet params=[agent.learning_rate,agent.beta]
  cobel fit ... method=optuna n_trials=300      # Optuna TPE instead of scipy L-BFGS-B
\b
data: one row per trial (Parquet or CSV) with choice (action index), reward, and optionally
state and session. Parameters not fitted keep the composed config's values (any `cobel run`
override works, e.g. agent.beta=3); the env gives the number of actions. Writes fit.json
(--out) and prints the estimates. Model: softmax Q-learning (see cobelrun.fit).
"""

SPECIAL = ("data", "params", "method", "n_trials")


def _split(args: list[str]) -> tuple[dict[str, str], list[str]]:
    special: dict[str, str] = {}
    rest = []
    for a in args:
        key, eq, value = a.partition("=")
        if eq and key in SPECIAL:
            special[key] = value
        else:
            rest.append(a)
    return special, rest


def run_fit(args: list[str]) -> tuple[Any, Path]:
    """Compose the config from ``args``, read the data and fit; return (result, data path)."""
    from omegaconf import OmegaConf

    from cobelrun.config import instantiate, register_resolvers
    from cobelrun.errors import ConfigError
    from cobelrun.fit import (
        PARAMS,
        check_action_set,
        check_choices,
        fit_choices,
        load_choices,
        task_sizes,
    )
    from cobelrun.hydra_app import composer

    special, overrides = _split(args)
    if "data" not in special:
        raise ConfigError("cobel fit needs data=CHOICES.parquet (choice, reward per trial)")
    raw = special.get("params", "[agent.learning_rate,agent.beta]").strip()
    params = [p.strip() for p in raw.strip("[]").split(",") if p.strip()]
    unknown = [p for p in params if p not in PARAMS]
    if unknown or not params:
        raise ConfigError(f"cannot fit {unknown or 'nothing'}; fittable: {', '.join(PARAMS)}")
    try:
        n_trials = int(special.get("n_trials", "200"))
    except ValueError:
        raise ConfigError(f"n_trials must be an integer, got {special['n_trials']!r}") from None
    register_resolvers()
    with composer() as compose:
        cfg = compose(overrides)
    initial = {k: OmegaConf.select(cfg, k) for k in PARAMS}
    missing = [k for k in params if initial.get(k) is None]
    if missing:
        raise ConfigError(f"the composed agent has no {', '.join(missing)}; pick an agent that "
                          f"has them (e.g. agent=dyna_q)")  # fmt: skip
    env = instantiate("env", cfg.env)
    n_actions, n_states = task_sizes(env)
    data_path = Path(special["data"])
    data = load_choices(data_path)
    check_choices(data, None, n_states, str(data_path))
    check_action_set(data, n_actions, str(cfg.task.get("name", "the task")), str(data_path))
    result = fit_choices(
        data,
        params,
        initial={k: float(v) for k, v in initial.items() if v is not None},
        n_actions=n_actions,
        n_states=n_states,
        method=special.get("method", "scipy"),
        n_trials=n_trials,
        source=str(data_path),
    )
    return result, data_path


def register(app: typer.Typer) -> None:
    """Add ``cobel fit`` to ``app``."""

    @app.command(
        "fit",
        help=HELP,
        context_settings={"allow_extra_args": True, "ignore_unknown_options": True},
    )
    def fit_cmd(
        ctx: typer.Context,
        out: Annotated[
            Path | None,
            typer.Option("--out", "-o", help="Where to write the estimates (default fit.json)."),
        ] = None,
    ) -> None:
        from cobelrun.commands.common import fail
        from cobelrun.errors import CobelError

        try:
            result, _ = run_fit(list(ctx.args))
        except CobelError as exc:
            fail(str(exc))
        path = out or Path("fit.json")
        try:
            path.write_text(json.dumps(result.to_dict(), indent=2) + "\n")
        except OSError as exc:
            fail(f"cannot write {path}: {exc.strerror}")
        for key, value in result.params.items():
            typer.echo(f"{key} = {value:.4g}")
        typer.echo(f"nll = {result.nll:.4f}  bic = {result.bic:.2f}  n = {result.n_trials}")
        typer.echo(str(path))
