"""``cobel fit``: maximum-likelihood fit of an agent's learning parameters to choice data."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import typer

HELP = """Fit a choice model to behavioural choice data by maximum likelihood, with standard errors, 95 % intervals, AIC/BIC and a held-out log-likelihood.

\b
  cobel fit task=two_afc agent=q_learning data=CHOICES.parquet
  cobel fit task=reversal_bandit model=wsls data=CHOICES.csv
  cobel fit ... params=\\[agent.learning_rate]  # others: config values
  cobel fit ... starts=10 method=optuna n_trials=300
  cobel fit task=blocking agent=rescorla_wagner data=RESPONSES.csv
  cobel fit task=second_order agent=td_conditioning data=RESPONSES.csv

data: one row per trial (Parquet or CSV) with choice (action index), reward, and optionally trial, state, session and learn; no other columns. Choices must use the task's actions, states its states. model: q_learning, rescorla_wagner, dyna_q, wsls, rw_response, td_response or ph_response (default: the agent's own: agent=q_learning, agent=dyna_q; on a conditioning task agent=rescorla_wagner, agent=td_conditioning, agent=pearce_hall). Conditioning data: choice is the response at the cue's onset (the trials table's response column), state the trial type, reward the outcome; learn 0 marks trials without learning (a test phase). Writes fit.json (--out) and prints the estimates. docs/modelling.md has a worked example.
"""

SPECIAL = ("data", "params", "method", "n_trials", "model", "starts")

#: the conditioning agents' likelihood models (by class name)
CONDITIONING_AGENTS = {"RescorlaWagner": "rw_response", "TDConditioning": "td_response",
                       "PearceHall": "ph_response"}  # fmt: skip
#: the agents `cobel fit` fits with their own model
FITTABLE_AGENTS = ("agent=q_learning", "agent=dyna_q", "agent=rescorla_wagner",
                   "agent=td_conditioning", "agent=pearce_hall")  # fmt: skip


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


def _int(special: dict[str, str], key: str, default: int) -> int:
    from cobelrun.errors import ConfigError

    try:
        return int(special.get(key, str(default)))
    except ValueError:
        raise ConfigError(f"{key} must be an integer, got {special[key]!r}") from None


def agent_model(cfg: Any) -> str:
    """The likelihood model of the composed agent (``q_learning`` for Dyna-Q without replay,
    ``dyna_q`` with it); a one-line error naming the fittable agents otherwise."""
    from cobelrun.choice_models import MODELS
    from cobelrun.errors import ConfigError

    target = str(cfg.agent.get("_target_", "")) if cfg.get("agent") is not None else ""
    if target == "cobelrun.agents.DynaQ":
        return "q_learning" if str(cfg.agent.get("replay", "off")) == "off" else "dyna_q"
    name = target.rsplit(".", 1)[-1]
    if target.startswith("cobelrun.agents.") and name in CONDITIONING_AGENTS:
        return CONDITIONING_AGENTS[name]
    raise ConfigError(f"agent {name or 'none'} has no choice likelihood; fittable agents: "
                      f"{', '.join(FITTABLE_AGENTS)}, or name a model= ({', '.join(MODELS)})")  # fmt: skip


def run_fit(args: list[str]) -> tuple[Any, Path]:
    """Compose the config from ``args``, read the data and fit; return (result, data path)."""
    from omegaconf import OmegaConf

    from cobelrun.choice_models import MODELS
    from cobelrun.config import instantiate, register_resolvers
    from cobelrun.errors import ConfigError
    from cobelrun.fit import (
        check_action_set,
        check_choices,
        check_trial_length,
        fit_choices,
        load_choices,
        task_features,
        task_sizes,
    )
    from cobelrun.hydra_app import composer

    special, overrides = _split(args)
    if "data" not in special:
        raise ConfigError("cobel fit needs data=CHOICES.parquet (choice, reward per trial)")
    if "model" in special and special["model"] not in MODELS:
        raise ConfigError(f"unknown model {special['model']!r}; models with a likelihood: "
                          f"{', '.join(MODELS)}")  # fmt: skip
    n_trials, starts = _int(special, "n_trials", 200), _int(special, "starts", 5)
    register_resolvers()
    with composer() as compose:
        cfg = compose(overrides)
    model = special.get("model") or agent_model(cfg)
    keys = MODELS[model].keys
    raw = special.get("params", "").strip()
    params = [p.strip() for p in raw.strip("[]").split(",") if p.strip()] or MODELS[
        model
    ].default_keys
    unknown = [p for p in params if p not in keys]
    if unknown:
        raise ConfigError(f"cannot fit {', '.join(unknown)} with model {model}; fittable: "
                          f"{', '.join(keys)}")  # fmt: skip
    initial = {k: OmegaConf.select(cfg, k) for k in keys}
    env = instantiate("env", cfg.env)
    n_actions, n_states = task_sizes(env)
    features = task_features(env)
    if features is not None and cfg.task.get("protocol") is not None:
        protocol = cfg.task.protocol
        check_trial_length(features, [p.get("max_steps") or protocol.get("max_steps")
                                      for p in protocol.phases], str(cfg.task.get("name")))  # fmt: skip
    data_path = Path(special["data"])
    data = load_choices(data_path)
    check_choices(data, None, n_states, str(data_path))
    check_action_set(data, n_actions, str(cfg.task.get("name", "the task")), str(data_path))
    result = fit_choices(
        data,
        params,
        model=model,
        features=features,
        initial={k: float(v) for k, v in initial.items() if isinstance(v, int | float)},
        n_actions=n_actions,
        n_states=n_states,
        method=special.get("method", "scipy"),
        n_trials=n_trials,
        n_starts=starts,
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
        typer.echo(f"model {result.model}, {result.n_trials} trials, {result.starts} starts")
        for key, value in result.params.items():
            se, ci = result.se.get(key), result.ci.get(key)
            extra = "" if se is None else f" ± {se:.3g}"
            if ci is not None:
                extra += f"  (95 % {result.interval} {ci[0]:.4g} .. {ci[1]:.4g})"
            note = result.notes.get(key)
            typer.echo(f"{key} = {value:.4g}{extra}" + (f"  [{note}]" if note else ""))
        typer.echo(f"nll = {result.nll:.4f}  aic = {result.aic:.2f}  bic = {result.bic:.2f}")
        if result.heldout:
            h = result.heldout
            typer.echo(f"held-out ll = {h['ll']:.3f} ({h['n_test']} trials, {h['split']})")
        typer.echo(str(path))
