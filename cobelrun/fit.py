"""Fit choice models to behavioural choice data by maximum likelihood, with uncertainty.

The models (:mod:`cobelrun.choice_models`: softmax Q-learning, Rescorla-Wagner over compound
cues, Dyna-Q with replay, noisy win-stay/lose-shift) give the probability of each observed
choice given the trials before it (Daw 2011, "Trial-by-trial data analysis using computational
models"; Wilson & Collins 2019, eLife 8:e49547). :func:`fit_choices` minimises the negative
log-likelihood with scipy's L-BFGS-B from several starts in a transformed space (logit for
rates, log for inverse temperatures), or with Optuna's TPE sampler, and reports standard
errors from a numerical Hessian at the optimum (delta method), 95 % intervals, AIC/BIC and
the held-out log-likelihood of a session split.

Data: a table (Parquet or CSV) with one row per trial, in order: ``choice`` (action index),
``reward`` and optionally ``trial``, ``state`` (default 0) and ``session`` (values reset
between sessions; e.g. runs of a cobel trials table). :func:`check_choices` validates it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numba
import numpy as np
import pandas as pd

from cobelrun.errors import CobelError, ConfigError

__all__ = [
    "ChoiceData",
    "FitResult",
    "check_action_set",
    "check_choices",
    "fit_choices",
    "load_choices",
    "q_learning_nll",
    "simulate_choices",
    "task_features",
    "task_sizes",
]


@numba.njit(cache=True)
def _nll_kernel(
    lr, beta, choices, rewards, states, sessions, n_states, n_actions, q0
):  # pragma: no cover
    q = np.full((n_states, n_actions), q0)
    nll = 0.0
    for t in range(choices.shape[0]):
        if t > 0 and sessions[t] != sessions[t - 1]:
            q[:, :] = q0
        s, a = states[t], choices[t]
        m = beta * q[s, 0]
        for b in range(1, n_actions):
            m = max(m, beta * q[s, b])
        total = 0.0
        for b in range(n_actions):
            total += math.exp(beta * q[s, b] - m)
        nll -= beta * q[s, a] - m - math.log(total)
        q[s, a] += lr * (rewards[t] - q[s, a])
    return nll


def q_learning_nll(
    learning_rate: float,
    beta: float,
    choices: np.ndarray,
    rewards: np.ndarray,
    states: np.ndarray,
    sessions: np.ndarray,
    n_states: int,
    n_actions: int,
    q0: float = 0.0,
) -> float:
    """Negative log-likelihood of ``choices`` under softmax Q-learning (compiled with numba).

    Parameters
    ----------
    learning_rate, beta
        Q-learning rate and softmax inverse temperature.
    choices, rewards, states, sessions
        Per-trial arrays in trial order; Q values restart at ``q0`` when ``sessions`` changes
        (integer session codes).
    n_states, n_actions
        Table size.
    q0
        Initial Q value.
    """
    return float(_nll_kernel(float(learning_rate), float(beta),
                             np.ascontiguousarray(choices, np.int64),
                             np.ascontiguousarray(rewards, np.float64),
                             np.ascontiguousarray(states, np.int64),
                             np.ascontiguousarray(sessions, np.int64),
                             int(n_states), int(n_actions), float(q0)))  # fmt: skip


def simulate_choices(
    n_trials: int,
    learning_rate: float,
    beta: float,
    *,
    reward_probs: Sequence[float] = (0.8, 0.2),
    reversal_every: int | None = 100,
    seed: int = 0,
) -> pd.DataFrame:
    """Synthetic choice data of a softmax Q-learner on a (reversal) bandit.

    Parameters
    ----------
    n_trials
        Number of trials.
    learning_rate, beta
        The generating parameters.
    reward_probs
        Reward probability of each action; reversed (order flipped) every ``reversal_every``
        trials (``None``: never).
    seed
        Seed of the simulation.

    Returns
    -------
    pandas.DataFrame
        Columns ``trial`` (1-based), ``state`` (0), ``choice``, ``reward``.
    """
    rng = np.random.default_rng(seed)
    probs = np.asarray(reward_probs, dtype=float)
    q = np.zeros(len(probs))
    rows = []
    for t in range(n_trials):
        if reversal_every and t > 0 and t % reversal_every == 0:
            probs = probs[::-1].copy()
        z = beta * q
        p = np.exp(z - z.max())
        p /= p.sum()
        a = int(rng.choice(len(q), p=p))
        r = float(rng.random() < probs[a])
        q[a] += learning_rate * (r - q[a])
        rows.append((t + 1, 0, a, r))
    return pd.DataFrame(rows, columns=["trial", "state", "choice", "reward"])


#: columns a choice table may have: required, then optional
REQUIRED_COLUMNS = ("choice", "reward")
OPTIONAL_COLUMNS = ("trial", "state", "session", "learn")
#: largest state count accepted when the task does not say how many states it has
MAX_STATES = 100_000


def load_choices(path: str | Path) -> pd.DataFrame:
    """Read a choice table (``.parquet`` or ``.csv``) and check its columns and values
    (:func:`check_choices`)."""
    p = Path(path)
    if not p.is_file():
        raise CobelError(f"data file {p} does not exist")
    try:
        data = pd.read_csv(p) if p.suffix == ".csv" else pd.read_parquet(p)
    except Exception as exc:
        raise CobelError(f"cannot read {p}: {exc}") from None
    check_columns(data, str(p))
    return data


def check_columns(data: pd.DataFrame, source: str = "the data") -> None:
    """Refuse a table without ``choice``/``reward``, with unknown columns, or without rows."""
    cols = [str(c) for c in data.columns]
    missing = [c for c in REQUIRED_COLUMNS if c not in cols]
    if missing:
        raise CobelError(f"{source} has no {', '.join(missing)} column; it needs choice and reward "
                         f"({', '.join(OPTIONAL_COLUMNS)} optional), it has: "
                         f"{', '.join(cols) or 'no columns'}")  # fmt: skip
    extra = [c for c in cols if c not in REQUIRED_COLUMNS + OPTIONAL_COLUMNS]
    if extra:
        raise CobelError(f"{source} has unknown column(s) {', '.join(extra)}; allowed: "
                         f"{', '.join(REQUIRED_COLUMNS + OPTIONAL_COLUMNS)} (drop or rename them)")  # fmt: skip
    if data.empty:
        raise CobelError(f"{source} has no trials")


def _show(value: Any) -> str:
    """A cell value as an error shows it (``nan``, ``0.7``, ``'left'``)."""
    return repr(value.item() if isinstance(value, np.generic) else value)


def _integer_column(data: pd.DataFrame, column: str, source: str, low: int, high: int | None,
                    what: str) -> np.ndarray:  # fmt: skip
    """The column as int64, refusing non-numbers, non-integers, non-finite values and values
    outside ``low..high`` (``high`` inclusive; ``None``: no upper limit)."""
    values = pd.to_numeric(data[column], errors="coerce").to_numpy(dtype=np.float64)
    bad = ~np.isfinite(values)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise CobelError(f"{source}: {column} must be a finite integer {what}, got "
                         f"{_show(data[column].iloc[i])} in row {i}")  # fmt: skip
    frac = values != np.round(values)
    if frac.any():
        i = int(np.flatnonzero(frac)[0])
        raise CobelError(f"{source}: {column} must be an integer {what}, got {_show(values[i])} "
                         f"in row {i}")  # fmt: skip
    out_of_range = (values < low) | (values > high if high is not None else False)
    if np.any(out_of_range):
        i = int(np.flatnonzero(out_of_range)[0])
        allowed = f"{low}..{high}" if high is not None else f">= {low}"
        raise CobelError(f"{source}: {column} must lie in {allowed}, got {values[i]:g} in row {i}")
    return values.astype(np.int64)


def check_choices(
    data: pd.DataFrame,
    n_actions: int | None = None,
    n_states: int | None = None,
    source: str = "the data",
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int, int]:
    """Validate a choice table and return its arrays.

    Parameters
    ----------
    data
        One row per trial: ``choice``, ``reward`` (``trial``, ``state``, ``session`` and
        ``learn`` optional; ``learn`` 0 marks trials the subject does not learn from, e.g. a
        test phase with learning off).
    n_actions
        The task's number of actions; choices must lie in ``0..n_actions - 1`` (default: the
        largest choice + 1).
    n_states
        The task's number of states; states must lie in ``0..n_states - 1`` (default: the
        largest state + 1, at most :data:`MAX_STATES`).
    source
        How errors name the table (e.g. its file).

    Returns
    -------
    tuple
        ``choices, rewards, states, sessions, n_states, n_actions, learns``.

    Raises
    ------
    CobelError
        One line naming the column, the bad value, its row and what is allowed.
    """
    check_columns(data, source)
    high = None if n_actions is None else int(n_actions) - 1
    choices = _integer_column(data, "choice", source, 0, high, "(an action index)")
    rewards = pd.to_numeric(data["reward"], errors="coerce").to_numpy(dtype=np.float64)
    bad = ~np.isfinite(rewards)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise CobelError(f"{source}: reward must be a finite number, got "
                         f"{_show(data['reward'].iloc[i])} in row {i}")  # fmt: skip
    if "state" in data:
        high = (int(n_states) if n_states is not None else MAX_STATES) - 1
        states = _integer_column(data, "state", source, 0, high, "(a state index)")
    else:
        states = np.zeros(len(data), np.int64)
    sessions = (
        pd.factorize(data["session"])[0].astype(np.int64)
        if "session" in data
        else np.zeros(len(data), np.int64)
    )
    learns = (
        _integer_column(data, "learn", source, 0, 1, "(1: learns from the trial, 0: not)") > 0
        if "learn" in data
        else np.ones(len(data), np.bool_)
    )
    n_a = int(n_actions) if n_actions is not None else int(choices.max()) + 1
    n_s = int(n_states) if n_states is not None else int(states.max()) + 1
    return choices, rewards, states, sessions, n_s, n_a, learns


@dataclass(frozen=True)
class ChoiceData:
    """A choice table as the per-trial arrays the likelihood needs, checked once.

    Build it with :meth:`from_table`; :meth:`nll` is the negative log-likelihood of the
    choices under softmax Q-learning (:func:`q_learning_nll`). ``cobel fit``
    (:func:`fit_choices`) and the ``task.objective`` :class:`cobelrun.objectives.ChoiceNLL`
    both evaluate it.
    """

    choices: np.ndarray
    rewards: np.ndarray
    states: np.ndarray
    sessions: np.ndarray
    n_states: int
    n_actions: int
    learns: np.ndarray | None = None
    features: Any = None

    @classmethod
    def from_table(
        cls,
        data: pd.DataFrame,
        n_actions: int | None = None,
        n_states: int | None = None,
        source: str = "the data",
    ) -> ChoiceData:
        """Arrays of a table with ``choice``, ``reward`` (``trial``, ``state``, ``session``
        optional), validated by :func:`check_choices`.

        Parameters
        ----------
        data
            One row per trial, in order.
        n_actions, n_states
            The task's numbers of actions and states (default: the largest value + 1).
        source
            How errors name the table.
        """
        return cls(*check_choices(data, n_actions, n_states, source))

    def __len__(self) -> int:
        return len(self.choices)

    def nll(self, learning_rate: float, beta: float, q0: float = 0.0) -> float:
        """Negative log-likelihood of the choices (:func:`q_learning_nll`)."""
        return q_learning_nll(learning_rate, beta, self.choices, self.rewards, self.states,
                              self.sessions, self.n_states, self.n_actions, q0)  # fmt: skip


def task_sizes(env: Any) -> tuple[int | None, int | None]:
    """``(n_actions, n_states)`` of a composed env (``None`` where it does not say)."""
    from cobelrun.envs.base import DiscreteStates, StateObservations

    n_actions = getattr(env.action_space, "n", None)
    base = getattr(env, "unwrapped", env)
    n_states: int | None = None
    if isinstance(base, DiscreteStates):
        n_states = int(base.n_states)
    elif isinstance(base, StateObservations):
        n_states = len(base.observations)
    return (None if n_actions is None else int(n_actions)), n_states


def task_features(env: Any) -> Any:
    """The trial types of a conditioning env (the ``trial_script`` contract) as the arrays the
    conditioning models need (:class:`cobelrun.choice_models.ScriptArrays`), else None.

    Each trial type is played once through the env's public interface (a phase's ``starts``
    and ``rewards``, then ``reset`` and ``step``) on the env given, which is restored after
    (``reset_world``): the TD model's features are the observations the agent sees, the
    outcome's step is where a unit outcome arrives.
    """
    from cobelrun.choice_models import ScriptArrays
    from cobelrun.envs.base import TrialScript

    base = getattr(env, "unwrapped", env)
    if not isinstance(base, TrialScript):
        return None
    names = list(getattr(base, "type_names", []))
    n_cs = int(base.n_cs)
    cues = np.array([base.trial_cues(i)[:n_cs] for i in range(len(names))], np.float64)
    rows, onset, us = [], np.full(len(names), -1, np.int64), np.zeros(len(names), np.int64)
    for i, name in enumerate(names):
        base.apply_changes(starts=[name], rewards={name: 1.0})
        obs, _ = base.reset()
        seen, t, done = [], 0, False
        while not done:
            x = np.asarray(obs, np.float64).copy()
            if onset[i] < 0 and np.any(x[:n_cs]):
                onset[i] = t
            x[:n_cs] = 0.0  # the TD agent's features: serial compound and contexts
            seen.append(x)
            obs, r, done, truncated, _ = base.step(0)
            done = done or truncated
            if r != 0.0:
                us[i] = t
            t += 1
        rows.append(np.array(seen))
    base.reset_world()
    length = max(len(r) for r in rows)
    steps = np.zeros((len(names), length, rows[0].shape[1]))
    for i, r in enumerate(rows):
        steps[i, : len(r)] = r
    return ScriptArrays(cues, steps, onset, us)


def check_trial_length(script: Any, max_steps: Sequence[int | None], task: str) -> None:
    """Refuse a conditioning task whose protocol cuts its trials short (``max_steps`` below
    the trial's length): the conditioning models replay whole trials."""
    length = int(script.steps.shape[1])
    short = sorted({int(m) for m in max_steps if m is not None and int(m) < length})
    if short:
        raise ConfigError(f"task {task}'s protocol stops trials after {short[0]} steps, but its "
                          f"trials last {length} (env.length); the conditioning models need "
                          f"whole trials: set task.protocol.max_steps to {length}")  # fmt: skip


def check_action_set(data: pd.DataFrame, n_actions: int | None, task: str,
                     source: str = "the data") -> None:  # fmt: skip
    """Refuse choice data whose action set differs from the task's: choices outside
    ``0..n_actions - 1``, or fewer actions than the task has (e.g. 2-choice data against the
    T-maze's 4 actions)."""
    if n_actions is None:
        return
    values = pd.to_numeric(data["choice"], errors="coerce")
    if not values.notna().all():
        return  # check_choices names the bad value
    top = int(values.max())
    if top != n_actions - 1:
        raise CobelError(f"{source} has choices 0..{top} ({top + 1} actions) but task {task}'s env "
                         f"has {n_actions} actions (0..{n_actions - 1}); fit it with a task of "
                         f"{top + 1} actions")  # fmt: skip


def _finite_or_none(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


@dataclass
class FitResult:
    """Maximum-likelihood estimates with their uncertainty.

    Attributes
    ----------
    params
        Fitted value of each parameter (by config key, e.g. ``agent.learning_rate``).
    nll
        Negative log-likelihood at the estimate.
    n_trials
        Number of choices fitted.
    method
        ``scipy`` or ``optuna``.
    fixed
        Values of the model's parameters that were not fitted.
    model
        The choice model (:data:`cobelrun.choice_models.MODELS`).
    se
        Standard error of each estimate (delta method from the inverse Hessian of the
        negative log-likelihood in the transformed space); ``None`` where it is not defined
        (an estimate on its bound, or a Hessian that is not positive definite).
    ci
        95 % interval of each parameter. ``interval="profile"`` (default): the profile
        likelihood's, where the negative log-likelihood minimised over the other parameters
        rises 1.92 (chi-square(1) 95 % / 2) above its minimum, or the bound where it never
        does; right where the likelihood is flat or skewed. ``interval="wald"``:
        ``estimate ± 1.96 se`` in the transformed space (logit / log), mapped back; ``None``
        like ``se``.
    heldout
        Held-out log-likelihood of a session split (``ll``, ``n_train``, ``n_test``, ``split``),
        the model fitted to the training part only; ``None`` when not asked for.
    starts
        Number of optimiser starts (the first from the config's values, then random ones).
    notes
        Why an ``se`` is missing, per parameter.
    interval
        How ``ci`` was computed: ``profile`` or ``wald``.
    """

    params: dict[str, float]
    nll: float
    n_trials: int
    method: str
    fixed: dict[str, float] = field(default_factory=dict)
    model: str = "q_learning"
    se: dict[str, float | None] = field(default_factory=dict)
    ci: dict[str, tuple[float, float] | None] = field(default_factory=dict)
    heldout: dict[str, Any] | None = None
    starts: int = 1
    notes: dict[str, str] = field(default_factory=dict)
    interval: str = "profile"

    @property
    def k(self) -> int:
        """Number of fitted parameters."""
        return len(self.params)

    @property
    def aic(self) -> float:
        """Akaike information criterion: ``2 nll + 2 k``."""
        return 2 * self.nll + 2 * self.k

    @property
    def bic(self) -> float:
        """Bayesian information criterion: ``2 nll + k ln n``."""
        return 2 * self.nll + self.k * math.log(self.n_trials)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (non-finite numbers become ``null``)."""
        return {
            "model": self.model,
            "params": self.params,
            "se": {k: _finite_or_none(v) for k, v in self.se.items()},
            "ci95": {
                k: (None if v is None else [float(v[0]), float(v[1])]) for k, v in self.ci.items()
            },
            "fixed": self.fixed,
            "nll": self.nll,
            "aic": self.aic,
            "bic": self.bic,
            "k": self.k,
            "n_trials": self.n_trials,
            "heldout": self.heldout,
            "starts": self.starts,
            "method": self.method,
            "interval": self.interval,
            "notes": self.notes,
        }


# ---------------------------------------------------------------- transformed parameter space
#: logit-space limit: a rate within ~5e-5 of its bound counts as on the bound
_LOGIT_LIMIT = 10.0


class _Space:
    """Maps a model's fitted parameters between their natural range and an unbounded space
    (scaled logit or log), where the optimiser searches and the Hessian is taken."""

    def __init__(self, specs: Sequence[Any], bounds: Mapping[str, tuple[float, float]]) -> None:
        self.keys = [p.key for p in specs]
        self.lo = np.array([bounds[k][0] for k in self.keys], np.float64)
        self.hi = np.array([bounds[k][1] for k in self.keys], np.float64)
        self.log = np.array([p.transform == "log" and bounds[p.key][0] > 0 for p in specs])
        self.phi_lo = np.where(self.log, np.log(np.maximum(self.lo, 1e-300)), -_LOGIT_LIMIT)
        self.phi_hi = np.where(self.log, np.log(np.maximum(self.hi, 1e-300)), _LOGIT_LIMIT)

    def to_natural(self, phi: np.ndarray) -> np.ndarray:
        phi = np.asarray(phi, np.float64)
        sig = 1.0 / (1.0 + np.exp(-phi))
        return np.where(self.log, np.exp(phi), self.lo + (self.hi - self.lo) * sig)

    def to_phi(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, np.float64)
        u = np.clip((x - self.lo) / (self.hi - self.lo), 1e-12, 1 - 1e-12)
        phi = np.where(self.log, np.log(np.maximum(x, 1e-300)), np.log(u / (1 - u)))
        return np.clip(phi, self.phi_lo, self.phi_hi)

    def jacobian(self, phi: np.ndarray) -> np.ndarray:
        """``dx/dphi`` per parameter."""
        sig = 1.0 / (1.0 + np.exp(-np.asarray(phi, np.float64)))
        return np.where(self.log, np.exp(phi), (self.hi - self.lo) * sig * (1 - sig))

    def on_bound(self, phi: np.ndarray) -> np.ndarray:
        tol = 1e-3 * np.maximum(1.0, np.abs(self.phi_hi - self.phi_lo))
        return (phi <= self.phi_lo + tol) | (phi >= self.phi_hi - tol)

    def random(self, rng: np.random.Generator) -> np.ndarray:
        """A random start: log-uniform on a log scale, uniform on the middle 90 % otherwise."""
        u = rng.uniform(0.05, 0.95, len(self.keys))
        return np.where(self.log, self.phi_lo + u * (self.phi_hi - self.phi_lo),
                        np.log(u / (1 - u)))  # fmt: skip


def hessian(f: Any, x: np.ndarray, step: float = 1e-3) -> np.ndarray:
    """Central-difference Hessian of a smooth scalar function ``f`` at ``x`` (2k^2 + 1 calls)."""
    x = np.asarray(x, np.float64)
    k = len(x)
    h = step * np.maximum(1.0, np.abs(x))
    f0 = f(x)
    H = np.empty((k, k))
    for i in range(k):
        ei = np.zeros(k)
        ei[i] = h[i]
        H[i, i] = (f(x + ei) - 2 * f0 + f(x - ei)) / h[i] ** 2
        for j in range(i):
            ej = np.zeros(k)
            ej[j] = h[j]
            H[i, j] = H[j, i] = (f(x + ei + ej) - f(x + ei - ej) - f(x - ei + ej)
                                 + f(x - ei - ej)) / (4 * h[i] * h[j])  # fmt: skip
    return H


#: half the chi-square(1) 95 % quantile: the rise of the profile negative log-likelihood that
#: bounds a 95 % profile-likelihood interval
PROFILE_RISE = 1.920729410347062


def profile_interval(
    profile: Any, c0: float, f0: float, lo: float, hi: float, step: float
) -> tuple[float, float]:
    """95 % profile-likelihood interval of one parameter in the transformed space.

    ``profile(c, warm)`` is the negative log-likelihood minimised over the other parameters
    with this one at ``c`` (``warm``: a one-item list holding the last minimiser, a warm
    start it updates); ``c0`` the estimate, ``f0`` the minimum, ``[lo, hi]`` the search range
    and ``step`` a first step (the Wald standard error). Each side steps out from ``c0``
    (steps growing 1.6-fold) until the profile rises :data:`PROFILE_RISE` above ``f0``, then
    bisects to the crossing (to 1e-4); where it never rises that far the bound is the end.
    """

    def rise(c: float, warm: list[Any]) -> float:
        v = profile(c, warm)
        return v - f0 - PROFILE_RISE if math.isfinite(v) else 1e300

    ends = []
    for direction, bound in ((-1.0, lo), (1.0, hi)):
        warm: list[Any] = [None]
        inner, s, end = float(c0), max(float(step), 0.05), float(bound)
        for _ in range(40):
            outer = inner + direction * s
            at_bound = (outer - bound) * direction >= 0
            outer = float(bound) if at_bound else outer
            if rise(outer, warm) > 0:  # bisect: the profile is below at inner, above here
                a, b = inner, outer
                while abs(b - a) > 1e-4:
                    mid = 0.5 * (a + b)
                    if rise(mid, warm) > 0:
                        b = mid
                    else:
                        a = mid
                end = 0.5 * (a + b)
                break
            if at_bound:
                break
            inner, s = outer, s * 1.6
        ends.append(end)
    return ends[0], ends[1]


def heldout_split(table: ChoiceData) -> tuple[np.ndarray, str]:
    """Boolean mask of the held-out trials: every second session when there are several
    (sessions 2, 4, ... by order of appearance), else the second half of the trials (predicted
    with the first half's history)."""
    codes = np.asarray(table.sessions)
    if len(np.unique(codes)) >= 2:
        return (codes % 2) == 1, "every second session"
    test = np.zeros(len(codes), bool)
    test[len(codes) // 2 :] = True
    return test, "second half of the trials"


def fit_choices(
    data: pd.DataFrame | ChoiceData,
    params: Sequence[str] | None = None,
    *,
    model: str = "q_learning",
    features: Any = None,
    initial: Mapping[str, float] | None = None,
    bounds: Mapping[str, tuple[float, float]] | None = None,
    n_actions: int | None = None,
    n_states: int | None = None,
    method: str = "scipy",
    n_trials: int = 200,
    n_starts: int = 5,
    heldout: bool = True,
    uncertainty: bool = True,
    polish: bool = True,
    interval: str = "profile",
    seed: int = 0,
    source: str = "the data",
) -> FitResult:
    """Fit a choice model's parameters by maximum likelihood, with standard errors, 95 %
    intervals, AIC/BIC and a held-out log-likelihood.

    Parameters
    ----------
    data
        One row per trial: ``choice``, ``reward`` (``trial``, ``state``, ``session``
        optional), or a checked :class:`ChoiceData`.
    params
        Config keys to fit (default: all of the model's); the others stay at ``initial``.
    model
        A model of :data:`cobelrun.choice_models.MODELS`.
    features
        The trial types of a conditioning task, for the conditioning models (``rw_response``,
        ``td_response``, ``ph_response``): :func:`task_features` of its env (an ``(n_states,
        k)`` cue array does for ``rw_response`` and ``ph_response``; default: the table's).
    initial
        Values of every model parameter (the fixed ones and the first start), by config key.
    bounds
        Search range per fitted key (default: the model's).
    n_actions, n_states
        The task's numbers of actions and states (default: the largest value + 1).
    method
        ``scipy``: compiled damped-Newton searches (Levenberg-Marquardt, numerical
        derivatives) in the transformed space from ``n_starts`` starts, the best polished by
        scipy's L-BFGS-B; ``optuna``: the first start is the best point of a TPE search
        (``n_trials`` evaluations).
    n_starts
        Optimiser starts: the first from ``initial``, the others random (seeded).
    heldout
        Also fit the training part of a session split (:func:`heldout_split`) and report the
        held-out trials' log-likelihood.
    uncertainty
        Compute standard errors and intervals (a numerical Hessian).
    polish
        Polish the best start with scipy's L-BFGS-B (``cobel recover`` skips it for speed).
    interval
        ``profile`` (default): 95 % profile-likelihood intervals; ``wald``: ``estimate ±
        1.96 se`` in the transformed space (see :class:`FitResult`).
    seed
        Seed of the random starts / sampler.
    source
        How errors name the data.
    """
    from scipy.optimize import minimize

    from cobelrun.choice_models import (
        CONDITIONING,
        MODELS,
        TD_RESPONSE,
        ScriptArrays,
        as_script,
        model_logp,
        newton_fit,
    )

    if model not in MODELS:
        raise ConfigError(f"unknown model {model!r}; models with a likelihood: "
                          f"{', '.join(MODELS)}")  # fmt: skip
    spec = MODELS[model]
    params = list(spec.default_keys if params is None else params)
    unknown = [p for p in params if p not in spec.keys]
    if unknown or not params:
        raise ConfigError(f"cannot fit {unknown or 'nothing'} with model {model}; its "
                          f"parameters: {', '.join(spec.keys)}")  # fmt: skip
    if method not in ("scipy", "optuna"):
        raise ConfigError(f"unknown fit method {method!r}; allowed: 'scipy', 'optuna'")
    if n_starts < 1:
        raise ConfigError(f"starts must be >= 1, got {n_starts}")
    if interval not in ("profile", "wald"):
        raise ConfigError(f"unknown interval {interval!r}; allowed: 'profile', 'wald'")
    ranges: dict[str, tuple[float, float]] = {}
    for p in spec.params:
        lo, hi = map(float, (bounds or {}).get(p.key, p.bounds))
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ConfigError(f"bounds of {p.key} must be finite with low < high, got [{lo}, {hi}]")
        ranges[p.key] = (lo, hi)
    defaults = {p.key: p.default if p.default is not None
                else 0.5 * (p.bounds[0] + p.bounds[1]) if p.transform == "logit" else 1.0
                for p in spec.params}  # fmt: skip
    values = {k: float((initial or {}).get(k, defaults[k])) for k in spec.keys}
    bad = [k for k, v in values.items() if not math.isfinite(v)]
    if bad:
        raise ConfigError(f"{', '.join(bad)} must be finite, got {values[bad[0]]}")
    table = (data if isinstance(data, ChoiceData)
             else ChoiceData.from_table(data, n_actions, n_states, source))  # fmt: skip
    fitted = [p for p in spec.params if p.key in params]
    space = _Space(fitted, ranges)
    index = [spec.keys.index(p.key) for p in fitted]
    base = np.array([values[k] for k in spec.keys], np.float64)
    if features is None:
        features = table.features
    if spec.code in CONDITIONING:
        if features is None or (
            spec.code == TD_RESPONSE and not isinstance(features, ScriptArrays)
        ):
            raise ConfigError(f"model {spec.name} needs the cues of every trial type: fit it "
                              f"with a conditioning task (env=sequence)")  # fmt: skip
        if table.n_actions != 2:
            raise ConfigError(f"model {spec.name} fits respond / no response (2 actions), the "
                              f"data have {table.n_actions}")  # fmt: skip
    script = as_script(features, table.n_states)
    if script[0].shape[0] != table.n_states:
        raise ConfigError(f"features must have one row per state ({table.n_states}), got "
                          f"{script[0].shape[0]}")  # fmt: skip
    learns = (np.ones(len(table), np.bool_) if table.learns is None
              else np.ascontiguousarray(table.learns, np.bool_))  # fmt: skip
    args = (table.choices, table.rewards, table.states, table.sessions, learns, table.n_states,
            table.n_actions)  # fmt: skip

    def logp(phi: np.ndarray) -> np.ndarray:
        theta = base.copy()
        theta[index] = space.to_natural(phi)
        return model_logp(
            spec,
            theta,
            table.choices,
            table.rewards,
            table.states,
            table.sessions,
            table.n_states,
            table.n_actions,
            features,
            learns,
        )

    islog = space.log.astype(np.bool_)
    idx = np.array(index, np.int64)

    def optimise(weights: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, float]:
        def f(phi: np.ndarray) -> float:
            return -float(logp(phi) @ weights)

        best: tuple[np.ndarray, float] | None = None
        starts = [space.to_phi([values[k] for k in params])]
        if method == "optuna":
            starts = [_optuna_start(f, space, n_trials, seed)]
        starts += [space.random(rng) for _ in range(n_starts - 1)]
        for x0 in starts:
            x, fx, _ = newton_fit(spec.code, np.asarray(x0, np.float64), space.phi_lo,
                                  space.phi_hi, idx, base, space.lo, space.hi, islog, weights,
                                  spec.n_memory, *args, script, 100)  # fmt: skip
            if math.isfinite(fx) and (best is None or fx < best[1]):
                best = (np.asarray(x, np.float64), float(fx))
        if best is None:
            raise CobelError(f"the fit of {source} did not converge (no start gave a finite "
                             f"likelihood); nothing written")  # fmt: skip
        if polish:
            box = list(zip(space.phi_lo, space.phi_hi, strict=True))
            res = minimize(f, best[0], method="L-BFGS-B", bounds=box)
            if math.isfinite(res.fun) and res.fun < best[1]:
                best = (np.asarray(res.x, np.float64), float(res.fun))
        return best

    def profile(i: int, c: float, warm: list[Any]) -> float:
        """The negative log-likelihood minimised over the other fitted parameters (the
        compiled Newton search, warm-started) with fitted parameter ``i`` at ``c``."""
        x = phi.copy()
        x[i] = c
        if len(phi) == 1:
            return -float(logp(x).sum())
        sel = np.array([j for j in range(len(phi)) if j != i], np.int64)
        fixed = base.copy()
        fixed[idx[i]] = space.to_natural(x)[i]
        start = x[sel] if warm[0] is None else warm[0]
        y, fy, _ = newton_fit(spec.code, np.asarray(start, np.float64), space.phi_lo[sel],
                              space.phi_hi[sel], idx[sel], fixed, space.lo[sel], space.hi[sel],
                              islog[sel], all_trials, spec.n_memory, *args, script, 100)  # fmt: skip
        if math.isfinite(fy):
            warm[0] = np.asarray(y, np.float64)
        return float(fy)

    all_trials = np.ones(len(table))
    phi, value = optimise(all_trials, np.random.default_rng(seed))
    estimate = space.to_natural(phi)
    if not (np.all(np.isfinite(estimate)) and math.isfinite(value)):
        raise CobelError(f"the fit of {source} did not converge (estimate {estimate.tolist()}, "
                         f"nll {value}); nothing written")  # fmt: skip
    se: dict[str, float | None] = {}
    ci: dict[str, tuple[float, float] | None] = {}
    notes: dict[str, str] = {}
    if uncertainty:
        H = hessian(lambda x: -float(logp(x).sum()), phi)
        edge = space.on_bound(phi)
        free = ~edge
        cov = np.full((len(phi), len(phi)), np.nan)
        if free.any():
            try:
                sub = H[np.ix_(free, free)]
                np.linalg.cholesky(sub)
                cov[np.ix_(free, free)] = np.linalg.inv(sub)
            except np.linalg.LinAlgError:
                for k in np.flatnonzero(free):
                    notes[space.keys[k]] = "Hessian not positive definite (flat likelihood)"
        jac = space.jacobian(phi)
        for i, key in enumerate(space.keys):
            sd = math.sqrt(cov[i, i]) if cov[i, i] > 0 else math.nan
            if edge[i]:
                notes[key] = "estimate on its bound"
            se[key] = float(abs(jac[i]) * sd) if math.isfinite(sd) else None
            if interval == "profile":
                ends = profile_interval(partial(profile, i), float(phi[i]), value,
                                        float(space.phi_lo[i]), float(space.phi_hi[i]),
                                        sd if math.isfinite(sd) else 0.5)  # fmt: skip
                lo_hi = space.to_natural(np.array([np.where(np.arange(len(phi)) == i, e, phi)
                                                   for e in ends]))  # fmt: skip
                ci[key] = (float(lo_hi[0][i]), float(lo_hi[1][i]))
            elif math.isfinite(sd):
                lo_hi = space.to_natural(np.array([phi - 1.96 * sd * np.eye(len(phi))[i],
                                                   phi + 1.96 * sd * np.eye(len(phi))[i]]))  # fmt: skip
                ci[key] = (float(lo_hi[0][i]), float(lo_hi[1][i]))
            else:
                ci[key] = None
    held: dict[str, Any] | None = None
    if heldout and len(table) >= 4:
        test, split = heldout_split(table)
        phi_train, _ = optimise((~test).astype(np.float64), np.random.default_rng(seed + 1))
        ll = float(logp(phi_train)[test].sum())
        held = {"ll": ll, "ll_per_trial": ll / int(test.sum()), "n_train": int((~test).sum()),
                "n_test": int(test.sum()), "split": split}  # fmt: skip
    return FitResult(
        params={k: float(v) for k, v in zip(space.keys, estimate, strict=True)},
        nll=value,
        n_trials=len(table),
        method=method,
        fixed={k: v for k, v in values.items() if k not in params},
        model=model,
        se=se,
        ci=ci,
        heldout=held,
        starts=n_starts,
        notes=notes,
        interval=interval,
    )


def _optuna_start(f: Any, space: _Space, n_trials: int, seed: int) -> np.ndarray:
    """The best point of an Optuna TPE search in the transformed space."""
    try:
        import optuna
    except ImportError:
        raise CobelError("method=optuna needs optuna: pip install 'cobelrun[fit]'") from None
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(sampler=optuna.samplers.TPESampler(seed=seed))
    keys = [f"x{i}" for i in range(len(space.keys))]
    study.optimize(lambda t: f(np.array([t.suggest_float(k, lo, hi) for k, lo, hi
                                         in zip(keys, space.phi_lo, space.phi_hi, strict=True)])),
                   n_trials=n_trials)  # fmt: skip
    return np.array([study.best_params[k] for k in keys])
