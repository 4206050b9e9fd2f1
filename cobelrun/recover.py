"""Parameter and model recovery: simulate synthetic agents, fit every candidate model to each.

Before fitting animals, a modeller shows that the fitted parameters come back from data the
model generated (parameter recovery) and that the model that generated a data set fits it best
(model recovery, a confusion matrix) (Wilson & Collins 2019, eLife 8:e49547, rules 5-6;
Palminteri et al. 2017, TICS 21:425).

:func:`recover` draws each synthetic agent's parameters from stated priors, lets the model
choose in the task's own environment through the task's protocol (one choice per trial),
fits every candidate model to the choices (:func:`cobelrun.fit.fit_choices`) and returns one
row per (agent, fitted model). :func:`parameter_recovery` and :func:`confusion` summarise it.
On a conditioning task (``env=sequence``) the agents are conditioning models (``rw_response``,
``td_response``, ``ph_response``) and the choice is the response at the cue's onset.

Every agent has its own seed from :class:`numpy.random.SeedSequence`, so the table does not
depend on how the agents are split: ``cobel recover`` runs them as the jobs of a sweep
(:class:`RecoveryJob`, a ``task.job``) through Hydra's launchers (joblib locally, submitit on
SLURM), as ``cobel run -m`` and ``cobel figure`` do.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from cobelrun.choice_models import CONDITIONING, MODELS, ChoiceModel, ModelAgent
from cobelrun.envs.base import Changeable, supports
from cobelrun.errors import ConfigError

__all__ = [
    "CRITERIA",
    "ChoiceTask",
    "Prior",
    "RecoveryJob",
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
    U(0.05, 0.5); conditioning models: response slope logU(2, 20), associability rate
    U(0.1, 0.9)."""
    return {
        "agent.learning_rate": Prior("uniform", 0.1, 0.9),
        "agent.beta": Prior("loguniform", 1.0, 10.0),
        "agent.epsilon": Prior("uniform", 0.05, 0.5),
        "agent.response_beta": Prior("loguniform", 2.0, 20.0),
        "agent.associability_rate": Prior("uniform", 0.1, 0.9),
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
    #: the trial types' arrays of a conditioning task (:func:`cobelrun.fit.task_features`)
    script: Any = None

    @property
    def conditioning(self) -> bool:
        """Whether the task is a conditioning task (a response per scripted trial)."""
        return self.script is not None

    @classmethod
    def from_config(cls, cfg: Any) -> ChoiceTask:
        """Build the env and protocol of a composed config; refuse tasks that are not one choice
        per trial (``max_steps`` 1) or have phases without learning, unless they are
        conditioning tasks (``env=sequence``: one response per trial, test phases allowed)."""
        from omegaconf import OmegaConf

        from cobelrun.config import instantiate
        from cobelrun.fit import task_features, task_sizes
        from cobelrun.protocol import Protocol

        name = str(cfg.task.get("name", "task"))
        spec = OmegaConf.to_container(cfg.task.protocol, resolve=True)
        protocol = Protocol.from_config(spec)
        env = instantiate("env", cfg.env)
        script = task_features(env)
        if script is not None:
            from cobelrun.fit import check_trial_length

            check_trial_length(script, [p.max_steps or protocol.max_steps
                                        for p in protocol.phases], name)  # fmt: skip
            protocol.check(env)
            return cls(name, env, list(protocol.phases), protocol, script)
        steps = {p.max_steps or protocol.max_steps for p in protocol.phases}
        if steps != {1}:
            raise ConfigError(f"cobel recover needs one choice per trial (task.protocol.max_steps "
                              f"1); task {name} has max_steps {sorted(steps)}")  # fmt: skip
        off = [p.name for p in protocol.phases if not p.learning]
        if off:
            raise ConfigError(f"cobel recover needs phases that learn; task {name}'s phase(s) "
                              f"{', '.join(off)} have learning off")  # fmt: skip
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
        """The choices of one synthetic agent: ``trial``, ``state``, ``choice``, ``reward``
        (and ``learn`` on a conditioning task).

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
        if (model.code in CONDITIONING) != self.conditioning:
            raise ConfigError(f"model {model.name} does not fit task {self.name}; models that "
                              f"can: {', '.join(self.models)}")  # fmt: skip
        agent = ModelAgent(model, theta, n_states, n_actions, np.random.default_rng(choice_seed),
                           self.script)  # fmt: skip
        base = self.env.unwrapped
        if supports(base, Changeable):
            base.reset_world()
        if self.conditioning:
            return self._condition(agent, env_seed)
        rows = np.zeros((self.n_trials, 3))
        t = 0
        for _phase, s in self._trial_starts(env_seed):
            a = agent.act(s)
            _, r, _, _, _ = self.env.step(a)
            agent.learn(s, a, float(r))
            rows[t] = (s, a, r)
            t += 1
        return pd.DataFrame({"trial": np.arange(1, t + 1), "state": rows[:, 0].astype(np.int64),
                             "choice": rows[:, 1].astype(np.int64), "reward": rows[:, 2]})  # fmt: skip

    def _condition(self, agent: ModelAgent, env_seed: Any) -> pd.DataFrame:
        """Conditioning trials: each trial is played through the env (its outcome is the
        rewards it delivers; responses do not change a scripted trial), the model responds at
        the cue's onset and learns from the trial if its phase learns."""
        rows = np.zeros((self.n_trials, 4))
        t = 0
        for phase, s in self._trial_starts(env_seed):
            outcome, done = 0.0, False
            while not done:
                _, r, terminated, truncated, _ = self.env.step(0)
                outcome += float(r)
                done = terminated or truncated
            a = agent.trial(s, outcome, bool(phase.learning))
            rows[t] = (s, a, outcome, float(phase.learning))
            t += 1
        return pd.DataFrame({"trial": np.arange(1, t + 1), "state": rows[:, 0].astype(np.int64),
                             "choice": rows[:, 1].astype(np.int64), "reward": rows[:, 2],
                             "learn": rows[:, 3].astype(np.int64)})  # fmt: skip

    def _trial_starts(self, env_seed: Any) -> Iterator[tuple[Any, int]]:
        """The protocol's trials in order: each phase and trial change applied and the env
        reset for the trial (the first reset seeded from ``env_seed``); yields the phase and
        the trial's start state."""
        first = True
        for phase in self.phases:
            self.protocol.apply(phase, self.env)
            for k in range(phase.trials):
                self.protocol.apply_trial(phase, k, self.env)
                seed_now = int(env_seed.generate_state(1)[0]) if first else None
                _, info = self.env.reset(seed=seed_now)
                first = False
                yield phase, int(info.get("state", 0))

    @property
    def models(self) -> list[str]:
        """The models that can be recovered on this task."""
        return CONDITIONING_MODELS if self.conditioning else RECOVERABLE


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
    theta = generating_theta(model, priors, rng)
    data = task.simulate(model, theta, sim_seed)
    n_states, n_actions = task.sizes
    table = ChoiceData.from_table(data, n_actions, n_states)
    rows = []
    for candidate in candidates:
        fit = fit_choices(table, model=candidate, features=task.script, n_starts=n_starts,
                          heldout=True, uncertainty=candidate == generating,
                          seed=int(fit_seed.generate_state(1)[0]))  # fmt: skip
        row: dict[str, Any] = {"generating": generating, "agent": agent, "fitted": candidate,
                               "nll": fit.nll, "aic": fit.aic, "bic": fit.bic,
                               "heldout_ll": fit.heldout["ll"] if fit.heldout else math.nan}  # fmt: skip
        for k, v in zip(model.keys, theta, strict=True):
            if k in model.default_keys:
                row[f"true:{k}"] = float(v)
        for k, v in fit.params.items():
            row[f"fit:{k}"] = v
            se, ci = fit.se.get(k), fit.ci.get(k)
            row[f"se:{k}"] = math.nan if se is None else se
            row[f"lo:{k}"] = math.nan if ci is None else ci[0]
            row[f"hi:{k}"] = math.nan if ci is None else ci[1]
        rows.append(row)
    return rows


def generating_theta(model: ChoiceModel, priors: Mapping[str, Prior],
                     rng: np.random.Generator) -> np.ndarray:  # fmt: skip
    """A synthetic agent's parameters: the fitted ones drawn from their priors, the fixed ones
    at the model's defaults (the agents' config defaults)."""
    return np.array([priors[p.key].sample(rng) if p.key in model.default_keys
                     else float(p.default if p.default is not None else 1.0)
                     for p in model.params])  # fmt: skip


#: most synthetic agents per model of one recovery (a config asking for more is refused before
#: any agent's seed is spawned: each agent is a fit of every candidate model)
MAX_AGENTS = 100_000


def work_items(models: Sequence[str], n: int, seed: int) -> list[tuple[str, int, Any]]:
    """Every synthetic agent as ``(model, agent, SeedSequence)``: agent ``i`` of model ``j``
    gets child ``j * n + i`` of ``SeedSequence(seed)``."""
    children = np.random.SeedSequence(seed).spawn(len(models) * n)
    return [(m, i, children[j * n + i]) for j, m in enumerate(models) for i in range(n)]


def check_setup(task: ChoiceTask, models: Sequence[str], candidates: Sequence[str], n: int,
                priors: Mapping[str, Prior]) -> dict[str, Prior]:  # fmt: skip
    """Check models, candidates, ``n`` and priors against the task; the priors completed with
    the defaults."""
    check_models(models, task)
    check_models(candidates, task)
    if not 1 <= n <= MAX_AGENTS:
        raise ConfigError(f"n must be 1..{MAX_AGENTS:,} synthetic agents per model, got {n}")
    full = {**default_priors(), **(priors or {})}
    missing = sorted({k for m in models for k in MODELS[m].default_keys} - set(full))
    if missing:
        raise ConfigError(f"no prior for {', '.join(missing)}; give prior.KEY=uniform(low,high)")
    return full


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
    candidates = list(candidates or models)
    priors = check_setup(task, models, candidates, n, priors or {})
    work = work_items(models, n, seed)
    if jobs == 1:
        rows = _chunk(task, work, candidates, priors, n_starts)
    else:
        from joblib import Parallel, delayed

        chunks = [work[k::jobs] for k in range(jobs) if work[k::jobs]]
        parts = Parallel(n_jobs=jobs)(delayed(_chunk)(task, c, candidates, priors, n_starts)
                                      for c in chunks)  # fmt: skip
        rows = [r for part in parts for r in part]
    return sort_table(pd.DataFrame(rows), models, candidates)


def sort_table(table: pd.DataFrame, models: Sequence[str],
               candidates: Sequence[str]) -> pd.DataFrame:  # fmt: skip
    """The recovery table in the generating models' and candidates' order, then by agent."""
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


#: models of one-choice tasks
RECOVERABLE = [m for m, spec in MODELS.items() if spec.code not in CONDITIONING]
#: models of conditioning tasks (``env=sequence``)
CONDITIONING_MODELS = [m for m, spec in MODELS.items() if spec.code in CONDITIONING]


def check_models(models: Sequence[str], task: ChoiceTask | None = None) -> None:
    """Refuse names without a likelihood on the task's kind (choice or conditioning tasks),
    naming the models that have one."""
    conditioning = task is not None and task.conditioning
    allowed = CONDITIONING_MODELS if conditioning else RECOVERABLE
    kind = "conditioning tasks" if conditioning else "choice tasks"
    unknown = [m for m in models if m not in allowed]
    if unknown or not models:
        raise ConfigError(f"model(s) {', '.join(unknown) or 'none given'} have no likelihood on "
                          f"{kind}; models that can be fitted: {', '.join(allowed)}")  # fmt: skip


def parameter_recovery(table: pd.DataFrame) -> pd.DataFrame:
    """Per generating model and parameter, from its own fits: ``n``, Pearson ``r`` of true vs
    fitted, ``bias`` (mean fitted - true), ``rmse`` and ``coverage`` (share of 95 % intervals
    holding the true value, among fits that have one)."""
    from scipy.stats import pearsonr

    own = table[table["generating"] == table["fitted"]]
    out = []
    for model, part in own.groupby("generating", sort=False):
        for key in MODELS[str(model)].default_keys:
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


@dataclass
class RecoveryJob:
    """One job of ``cobel recover``'s sweep (a ``task.job``): fit the synthetic agents of
    chunk ``chunk`` of ``chunks`` and write their rows to ``recovery.parquet`` in the job's
    folder.

    ``cobel recover`` runs the chunks as a sweep through Hydra's launcher, so the agents are
    fitted in parallel wherever the launcher runs jobs (joblib workers, SLURM jobs through
    submitit). Agent ``i`` of model ``j`` has child ``j * n + i`` of ``SeedSequence(seed)``
    (the config's one ``seed``) whichever chunk fits it, so the joined table does not depend on
    the number of chunks.

    Parameters
    ----------
    models
        Generating models.
    n
        Synthetic agents per generating model.
    candidates
        Models fitted to every agent (default: ``models``).
    priors
        ``KEY=uniform(low,high)`` or ``KEY=loguniform(low,high)`` per parameter (others: the
        defaults of :func:`default_priors`).
    starts
        Optimiser starts per fit.
    chunk, chunks
        This job's share: work items ``chunk``, ``chunk + chunks``, ...
    """

    models: Sequence[str]
    n: int
    candidates: Sequence[str] | None = None
    priors: Sequence[str] = ()
    starts: int = 3
    chunk: int = 0
    chunks: int = 1

    def __post_init__(self) -> None:
        self.models = [str(m) for m in self.models]
        self.candidates = [str(m) for m in (self.candidates or self.models)]
        for key, value, low in (("n", self.n, 1), ("starts", self.starts, 1),
                                ("chunks", self.chunks, 1), ("chunk", self.chunk, 0)):  # fmt: skip
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ConfigError(f"task.job.{key} must be an integer >= {low}, got {value!r}")
        if self.n > MAX_AGENTS:  # checked before the agents' seeds are spawned
            raise ConfigError(f"task.job.n must be 1..{MAX_AGENTS:,} synthetic agents per model, "
                              f"got {self.n}")  # fmt: skip
        if self.chunk >= self.chunks:
            raise ConfigError(f"task.job.chunk must lie in 0..{self.chunks - 1}, got {self.chunk}")
        self._priors = parse_priors([str(p) for p in self.priors])

    def __call__(self, config: Any, run_dir: Any, progress: Any = None) -> dict[str, Any]:
        from pathlib import Path

        task = ChoiceTask.from_config(config)
        candidates = list(self.candidates or self.models)
        priors = check_setup(task, self.models, candidates, self.n, self._priors)
        work = work_items(self.models, self.n, int(config.get("seed", 0) or 0))
        mine = work[self.chunk :: self.chunks]
        rows = _chunk(task, mine, candidates, priors, self.starts)
        out = Path(run_dir) / "recovery.parquet"
        tmp = out.with_name(f".{out.name}.tmp")
        pd.DataFrame(rows).to_parquet(tmp, index=False)
        tmp.replace(out)
        return {"agents": len(mine), "rows": len(rows)}


def parse_priors(items: Sequence[str]) -> dict[str, Prior]:
    """``KEY=uniform(low,high)`` items as priors, each checked against its parameter's range
    (:func:`parse_prior`); a key that is no model's parameter is one line naming them."""
    bounds = {p.key: p.bounds for m in MODELS.values() for p in m.params}
    out: dict[str, Prior] = {}
    for item in items:
        key, eq, text = item.partition("=")
        key = key.strip().removeprefix("prior.")
        if not eq:
            raise ConfigError(f"prior {item!r}: give KEY=uniform(low,high)")
        if key not in bounds:
            raise ConfigError(f"prior.{key}: not a parameter of any model; parameters: "
                              f"{', '.join(bounds)}")  # fmt: skip
        out[key] = parse_prior(key, text, bounds[key])
    return out
