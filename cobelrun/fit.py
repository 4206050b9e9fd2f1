"""Fit an agent's learning parameters to behavioural choice data by maximum likelihood.

The model is the tabular Q-learner at the heart of cobel's Dyna-Q agent, applied to choice
trials (one decision per trial, as in two-alternative forced choice or bandit tasks): after
choosing action ``a`` in state ``s`` and receiving reward ``r``,
``Q[s, a] += learning_rate * (r - Q[s, a])``; choices follow the softmax policy
``P(a | s) = exp(beta Q[s, a]) / sum_b exp(beta Q[s, b])`` (Sutton & Barto 2018, ch. 2 and 6;
Daw 2011, "Trial-by-trial data analysis using computational models"). The negative
log-likelihood of the observed choices is minimised with scipy (L-BFGS-B from several starts;
the likelihood is smooth in both parameters) or with Optuna's TPE sampler.

Data: a table (Parquet or CSV) with one row per trial, in order: ``choice`` (action index),
``reward`` and optionally ``state`` (default 0) and ``session`` (values reset between
sessions; e.g. runs of a cobel trials table).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numba
import numpy as np
import pandas as pd

from cobelrun.errors import CobelError, ConfigError

__all__ = [
    "PARAMS",
    "ChoiceData",
    "FitResult",
    "check_action_set",
    "check_choices",
    "fit_choices",
    "load_choices",
    "q_learning_nll",
    "simulate_choices",
    "task_sizes",
]

#: fittable parameters: config key -> (model name, default bounds)
PARAMS: dict[str, tuple[str, tuple[float, float]]] = {
    "agent.learning_rate": ("learning_rate", (0.0, 1.0)),
    "agent.beta": ("beta", (1e-3, 50.0)),
}


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
OPTIONAL_COLUMNS = ("trial", "state", "session")
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
        One row per trial: ``choice``, ``reward`` (``trial``, ``state``, ``session`` optional).
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
        ``choices, rewards, states, sessions, n_states, n_actions``.

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
    n_a = int(n_actions) if n_actions is not None else int(choices.max()) + 1
    n_s = int(n_states) if n_states is not None else int(states.max()) + 1
    return choices, rewards, states, sessions, n_s, n_a


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


@dataclass
class FitResult:
    """Maximum-likelihood estimates.

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
    """

    params: dict[str, float]
    nll: float
    n_trials: int
    method: str
    fixed: dict[str, float] = field(default_factory=dict)

    @property
    def bic(self) -> float:
        """Bayesian information criterion: ``2 nll + k ln n``."""
        return 2 * self.nll + len(self.params) * math.log(self.n_trials)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict."""
        return {"params": self.params, "fixed": self.fixed, "nll": self.nll,
                "bic": self.bic, "n_trials": self.n_trials, "method": self.method}  # fmt: skip


def fit_choices(
    data: pd.DataFrame,
    params: Sequence[str],
    *,
    initial: Mapping[str, float] | None = None,
    bounds: Mapping[str, tuple[float, float]] | None = None,
    n_actions: int | None = None,
    n_states: int | None = None,
    method: str = "scipy",
    n_trials: int = 200,
    seed: int = 0,
    source: str = "the data",
) -> FitResult:
    """Fit ``params`` (``agent.learning_rate``, ``agent.beta``) to choice data by maximum
    likelihood; the others stay at ``initial``.

    Parameters
    ----------
    data
        One row per trial: ``choice``, ``reward`` (``state``, ``session`` optional).
    params
        Config keys to fit (see :data:`PARAMS`).
    initial
        Values of every model parameter (the fixed ones and the scipy start), by config key.
    bounds
        Search range per fitted key (default from :data:`PARAMS`).
    n_actions
        Number of actions (default: the largest choice + 1).
    method
        ``scipy`` (L-BFGS-B from 5 starts) or ``optuna`` (TPE, ``n_trials`` evaluations).
    seed
        Seed of the starts / sampler.
    """
    unknown = [p for p in params if p not in PARAMS]
    if unknown or not params:
        raise ConfigError(f"cannot fit {unknown or 'nothing'}; fittable: {', '.join(PARAMS)}")
    if method not in ("scipy", "optuna"):
        raise ConfigError(f"unknown fit method {method!r}; allowed: 'scipy', 'optuna'")
    values = {key: float((initial or {}).get(key, 0.5 if "rate" in key else 1.0)) for key in PARAMS}
    ranges = {key: tuple(map(float, (bounds or {}).get(key, PARAMS[key][1]))) for key in params}
    table = ChoiceData.from_table(data, n_actions, n_states, source)

    def nll(x: Sequence[float]) -> float:
        v = {**values, **dict(zip(params, x, strict=True))}
        return table.nll(v["agent.learning_rate"], v["agent.beta"])

    rng = np.random.default_rng(seed)
    if method == "scipy":
        from scipy.optimize import minimize

        best = None
        for i in range(5):
            x0 = [values[k] if i == 0 else rng.uniform(*ranges[k]) for k in params]
            x0 = [min(max(v, ranges[k][0]), ranges[k][1]) for v, k in zip(x0, params, strict=True)]
            res = minimize(nll, x0, method="L-BFGS-B", bounds=[ranges[k] for k in params])
            if best is None or res.fun < best.fun:
                best = res
        assert best is not None
        estimate, value = [float(v) for v in best.x], float(best.fun)
    else:
        try:
            import optuna
        except ImportError:
            raise CobelError("method=optuna needs optuna: pip install 'cobelrun[fit]'") from None
        optuna.logging.set_verbosity(optuna.logging.WARNING)
        study = optuna.create_study(sampler=optuna.samplers.TPESampler(seed=seed))
        study.optimize(lambda t: nll([t.suggest_float(k, *ranges[k]) for k in params]),
                       n_trials=n_trials)  # fmt: skip
        estimate = [float(study.best_params[k]) for k in params]
        value = float(study.best_value)
    if not (np.all(np.isfinite(estimate)) and math.isfinite(value)):
        raise CobelError(f"the fit of {source} did not converge (estimate {estimate}, nll "
                         f"{value}); nothing written")  # fmt: skip
    return FitResult(
        params=dict(zip(params, estimate, strict=True)),
        nll=value,
        n_trials=len(table),
        method=method,
        fixed={k: v for k, v in values.items() if k not in params},
    )
