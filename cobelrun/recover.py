"""Parameter and model recovery: simulate synthetic agents, fit every candidate model to each.

Before fitting animals, a modeller shows that the fitted parameters come back from data the
model generated (parameter recovery) and that the model that generated a data set fits it best
(model recovery, a confusion matrix) (Wilson & Collins 2019, eLife 8:e49547, rules 5-6;
Palminteri et al. 2017, TICS 21:425).

:func:`recover` draws each synthetic agent's parameters from stated priors, lets the model
choose in the task's own environment through the task's protocol (one choice per trial),
fits every candidate model to the choices (:func:`cobelrun.fit.fit_choices`) and returns one
row per (agent, fitted model). :func:`parameter_recovery` and :func:`confusion` summarise it.
Agents run in parallel through joblib; every agent has its own seed from
:class:`numpy.random.SeedSequence`, so the table does not depend on the number of jobs.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from cobelrun.choice_models import MODELS, ChoiceModel, ModelAgent
from cobelrun.envs.base import Changeable, supports
from cobelrun.errors import ConfigError

__all__ = [
    "CRITERIA",
    "ChoiceTask",
    "Prior",
    "confusion",
    "default_priors",
    "parameter_recovery",
    "parse_prior",
    "recover",
]

#: model-selection criteria of the confusion matrix: column, whether lower is better
CRITERIA: dict[str, tuple[str, bool]] = {
    "aic": ("aic", True),
    "bic": ("bic", True),
    "heldout": ("heldout_ll", False),
}


@dataclass(frozen=True)
class Prior:
    """A prior of one parameter: ``uniform(low, high)`` or ``loguniform(low, high)``."""

    kind: str
    low: float
    high: float

    def sample(self, rng: np.random.Generator) -> float:
        if self.kind == "loguniform":
            return float(math.exp(rng.uniform(math.log(self.low), math.log(self.high))))
        return float(rng.uniform(self.low, self.high))

    def __str__(self) -> str:
        return f"{self.kind}({self.low:g},{self.high:g})"


_PRIOR = re.compile(r"^\s*(uniform|loguniform)\s*\(\s*([^,]+?)\s*,\s*([^)]+?)\s*\)\s*$")


def parse_prior(key: str, text: str, bounds: tuple[float, float]) -> Prior:
    """A prior from ``uniform(a,b)`` / ``loguniform(a,b)``; its support must be non-empty and
    inside the parameter's ``bounds``."""
    m = _PRIOR.match(text)
    if not m:
        raise ConfigError(f"prior of {key}: expected uniform(low,high) or loguniform(low,high), "
                          f"got {text!r}")  # fmt: skip
    try:
        low, high = float(m.group(2)), float(m.group(3))
    except ValueError:
        raise ConfigError(f"prior of {key}: low and high must be numbers, got {text!r}") from None
    if not (math.isfinite(low) and math.isfinite(high)) or low >= high:
        raise ConfigError(f"prior of {key} has an empty support: {text} (need low < high)")
    if m.group(1) == "loguniform" and low <= 0:
        raise ConfigError(f"prior of {key}: loguniform needs low > 0, got {text}")
    if low < bounds[0] or high > bounds[1]:
        raise ConfigError(f"prior of {key}: {text} leaves the parameter's range "
                          f"[{bounds[0]:g}, {bounds[1]:g}]")  # fmt: skip
    return Prior(m.group(1), low, high)


def default_priors() -> dict[str, Prior]:
    """Default priors: learning rate U(0.1, 0.9), inverse temperature logU(1, 10), WSLS noise
    U(0.05, 0.5)."""
    return {
        "agent.learning_rate": Prior("uniform", 0.1, 0.9),
        "agent.beta": Prior("loguniform", 1.0, 10.0),
        "agent.epsilon": Prior("uniform", 0.05, 0.5),
    }


@dataclass
class ChoiceTask:
    """A one-choice-per-trial task: the env and its protocol's phases.

    Parameters
    ----------
    name
        The task's name (for tables).
    env
        The composed gymnasium env (one step per trial; ``info['state']`` the state index).
    phases
        The protocol's phases (:class:`cobelrun.protocol.Phase`); each must learn.
    protocol
        The :class:`cobelrun.protocol.Protocol` that applies each phase's changes.
    """

    name: str
    env: Any
    phases: Sequence[Any]
    protocol: Any

    @classmethod
    def from_config(cls, cfg: Any) -> ChoiceTask:
        """Build the env and protocol of a composed config; refuse tasks that are not one choice
        per trial (``max_steps`` 1) or have phases without learning."""
        from omegaconf import OmegaConf

        from cobelrun.config import instantiate
        from cobelrun.fit import task_sizes
        from cobelrun.protocol import Protocol

        name = str(cfg.task.get("name", "task"))
        spec = OmegaConf.to_container(cfg.task.protocol, resolve=True)
        protocol = Protocol.from_config(spec)
        steps = {p.max_steps or protocol.max_steps for p in protocol.phases}
        if steps != {1}:
            raise ConfigError(f"cobel recover needs one choice per trial (task.protocol.max_steps "
                              f"1); task {name} has max_steps {sorted(steps)}")  # fmt: skip
        off = [p.name for p in protocol.phases if not p.learning]
        if off:
            raise ConfigError(f"cobel recover needs phases that learn; task {name}'s phase(s) "
                              f"{', '.join(off)} have learning off")  # fmt: skip
        env = instantiate("env", cfg.env)
        n_actions, n_states = task_sizes(env)
        if n_actions is None or n_states is None:
            raise ConfigError(f"cobel recover needs discrete actions and states; task {name}'s "
                              f"env has {n_actions} actions, {n_states} states")  # fmt: skip
        protocol.check(env)
        return cls(name, env, list(protocol.phases), protocol)

    @property
    def sizes(self) -> tuple[int, int]:
        """``(n_states, n_actions)``."""
        from cobelrun.fit import task_sizes

        n_actions, n_states = task_sizes(self.env)
        assert n_actions is not None and n_states is not None
        return n_states, n_actions

    @property
    def n_trials(self) -> int:
        return int(sum(p.trials for p in self.phases))

    def simulate(self, model: ChoiceModel, theta: np.ndarray, seed: Any) -> pd.DataFrame:
        """The choices of one synthetic agent: ``trial``, ``state``, ``choice``, ``reward``.

        Parameters
        ----------
        model, theta
            The generating model and its parameters.
        seed
            Seed (an int or :class:`numpy.random.SeedSequence`) of the env and the choices.
        """
        env_seed, choice_seed = (
            np.random.SeedSequence(seed).spawn(2) if isinstance(seed, int) else seed.spawn(2)
        )
        n_states, n_actions = self.sizes
        agent = ModelAgent(model, theta, n_states, n_actions, np.random.default_rng(choice_seed))
        base = self.env.unwrapped
        if supports(base, Changeable):
            base.reset_world()
        rows = np.zeros((self.n_trials, 3))
        t = 0
        first = True
        for phase in self.phases:
            self.protocol.apply(phase, self.env)
            for k in range(phase.trials):
                self.protocol.apply_trial(phase, k, self.env)
                seed_now = int(env_seed.generate_state(1)[0]) if first else None
                _, info = self.env.reset(seed=seed_now)
                first = False
                s = int(info.get("state", 0))
                a = agent.act(s)
                _, r, _, _, _ = self.env.step(a)
                agent.learn(s, a, float(r))
                rows[t] = (s, a, r)
                t += 1
        return pd.DataFrame({"trial": np.arange(1, t + 1), "state": rows[:, 0].astype(np.int64),
                             "choice": rows[:, 1].astype(np.int64), "reward": rows[:, 2]})  # fmt: skip


def _agent_rows(
    task: ChoiceTask,
    generating: str,
    agent: int,
    seed: np.random.SeedSequence,
    candidates: Sequence[str],
    priors: Mapping[str, Prior],
    n_starts: int,
) -> list[dict[str, Any]]:
    from cobelrun.fit import ChoiceData, fit_choices

    model = MODELS[generating]
    prior_seed, sim_seed, fit_seed = seed.spawn(3)
    rng = np.random.default_rng(prior_seed)
    theta = np.array([priors[k].sample(rng) for k in model.keys])
    data = task.simulate(model, theta, sim_seed)
    n_states, n_actions = task.sizes
    table = ChoiceData.from_table(data, n_actions, n_states)
    rows = []
    for candidate in candidates:
        fit = fit_choices(table, model=candidate, n_starts=n_starts, heldout=True,
                          uncertainty=candidate == generating,
                          seed=int(fit_seed.generate_state(1)[0]))  # fmt: skip
        row: dict[str, Any] = {"generating": generating, "agent": agent, "fitted": candidate,
                               "nll": fit.nll, "aic": fit.aic, "bic": fit.bic,
                               "heldout_ll": fit.heldout["ll"] if fit.heldout else math.nan}  # fmt: skip
        for k, v in zip(model.keys, theta, strict=True):
            row[f"true:{k}"] = float(v)
        for k, v in fit.params.items():
            row[f"fit:{k}"] = v
            se, ci = fit.se.get(k), fit.ci.get(k)
            row[f"se:{k}"] = math.nan if se is None else se
            row[f"lo:{k}"] = math.nan if ci is None else ci[0]
            row[f"hi:{k}"] = math.nan if ci is None else ci[1]
        rows.append(row)
    return rows


def recover(
    task: ChoiceTask,
    models: Sequence[str],
    n: int,
    *,
    priors: Mapping[str, Prior] | None = None,
    candidates: Sequence[str] | None = None,
    n_starts: int = 3,
    seed: int = 0,
    jobs: int = 1,
) -> pd.DataFrame:
    """Simulate ``n`` synthetic agents of each generating model and fit every candidate.

    Parameters
    ----------
    task
        The task the agents choose in (:class:`ChoiceTask`).
    models
        Generating models (names of :data:`cobelrun.choice_models.MODELS`).
    n
        Synthetic agents per generating model.
    priors
        Prior of each parameter by config key (default :func:`default_priors`).
    candidates
        Models fitted to every agent (default: ``models``).
    n_starts
        Optimiser starts per fit.
    seed
        The one seed: agent ``i`` of model ``m`` gets child ``m * n + i`` of its SeedSequence.
    jobs
        Parallel workers (joblib; 1 runs in this process).

    Returns
    -------
    pandas.DataFrame
        One row per (generating model, agent, fitted model): ``nll``, ``aic``, ``bic``,
        ``heldout_ll``, ``true:KEY``, ``fit:KEY``, ``se:KEY``, ``lo:KEY``, ``hi:KEY`` (95 %
        interval; standard errors only for the generating model's own fit).
    """
    check_models(models)
    candidates = list(candidates or models)
    check_models(candidates)
    if n < 1:
        raise ConfigError(f"n must be >= 1 synthetic agents, got {n}")
    priors = {**default_priors(), **(priors or {})}
    missing = sorted({k for m in models for k in MODELS[m].keys} - set(priors))
    if missing:
        raise ConfigError(f"no prior for {', '.join(missing)}; give prior.KEY=uniform(low,high)")
    children = np.random.SeedSequence(seed).spawn(len(models) * n)
    work = [(m, i, children[j * n + i]) for j, m in enumerate(models) for i in range(n)]
    if jobs == 1:
        rows = [r for m, i, s in work for r in _agent_rows(task, m, i, s, candidates, priors,
                                                             n_starts)]  # fmt: skip
    else:
        from joblib import Parallel, delayed

        chunks = [work[k :: jobs * 4] for k in range(jobs * 4) if work[k :: jobs * 4]]
        parts = Parallel(n_jobs=jobs)(delayed(_chunk)(task, c, candidates, priors, n_starts)
                                      for c in chunks)  # fmt: skip
        rows = [r for part in parts for r in part]
    table = pd.DataFrame(rows)
    gen_order = {m: i for i, m in enumerate(models)}
    fit_order = {m: i for i, m in enumerate(candidates)}
    keys = {"generating": gen_order, "fitted": fit_order}
    return table.sort_values(["generating", "agent", "fitted"],
                             key=lambda c: c.map(keys[c.name]) if c.name in keys else c
                             ).reset_index(drop=True)  # fmt: skip


def _chunk(task: ChoiceTask, work: Sequence[tuple[str, int, Any]], candidates: Sequence[str],
           priors: Mapping[str, Prior], n_starts: int) -> list[dict[str, Any]]:  # fmt: skip
    return [r for m, i, s in work for r in _agent_rows(task, m, i, s, candidates, priors,
                                                         n_starts)]  # fmt: skip


#: models of one-choice tasks (``rw_response`` is fitted to conditioning tasks by cobel fit)
RECOVERABLE = [m for m in MODELS if m != "rw_response"]


def check_models(models: Sequence[str]) -> None:
    """Refuse names without a likelihood on choice tasks, naming the models that have one."""
    unknown = [m for m in models if m not in RECOVERABLE]
    if unknown or not models:
        raise ConfigError(f"model(s) {', '.join(unknown) or 'none given'} have no likelihood on "
                          f"choice tasks; models that can be fitted: {', '.join(RECOVERABLE)}")  # fmt: skip


def parameter_recovery(table: pd.DataFrame) -> pd.DataFrame:
    """Per generating model and parameter, from its own fits: ``n``, Pearson ``r`` of true vs
    fitted, ``bias`` (mean fitted - true), ``rmse`` and ``coverage`` (share of 95 % intervals
    holding the true value, among fits that have one)."""
    from scipy.stats import pearsonr

    own = table[table["generating"] == table["fitted"]]
    out = []
    for model, part in own.groupby("generating", sort=False):
        for key in MODELS[str(model)].keys:
            true, est = part[f"true:{key}"].to_numpy(), part[f"fit:{key}"].to_numpy()
            lo, hi = part[f"lo:{key}"].to_numpy(), part[f"hi:{key}"].to_numpy()
            has = np.isfinite(lo) & np.isfinite(hi)
            r = float(pearsonr(true, est)[0]) if len(true) > 2 and np.std(est) > 0 else math.nan
            out.append({"model": model, "param": key, "n": len(part), "r": r,
                        "bias": float(np.mean(est - true)),
                        "rmse": float(np.sqrt(np.mean((est - true) ** 2))),
                        "coverage": float(np.mean((lo[has] <= true[has]) & (true[has] <= hi[has])))
                        if has.any() else math.nan, "with_interval": int(has.sum())})  # fmt: skip
    return pd.DataFrame(out)


def confusion(table: pd.DataFrame, criterion: str = "bic") -> pd.DataFrame:
    """Model-recovery confusion matrix: rows the generating model, columns the fitted one, each
    cell the share of agents whose best fit (by ``criterion``: ``aic``, ``bic`` or
    ``heldout``) is that column."""
    if criterion not in CRITERIA:
        raise ConfigError(f"unknown criterion {criterion!r}; allowed: {', '.join(CRITERIA)}")
    column, lower = CRITERIA[criterion]
    score = table[column] if lower else -table[column]
    best = table.assign(_s=score).sort_values("_s").groupby(["generating", "agent"],
                                                            sort=False).head(1)  # fmt: skip
    generating = list(dict.fromkeys(table["generating"]))
    # the generating models first, in their order, so that the diagonal is the diagonal
    fitted = [m for m in generating if m in set(table["fitted"])]
    fitted += [m for m in dict.fromkeys(table["fitted"]) if m not in fitted]
    counts = pd.crosstab(best["generating"], best["fitted"]).reindex(
        index=generating, columns=fitted, fill_value=0
    )
    return counts.div(counts.sum(axis=1), axis=0)
