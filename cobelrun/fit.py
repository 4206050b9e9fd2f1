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
    "fit_choices",
    "load_choices",
    "q_learning_nll",
    "simulate_choices",
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


def load_choices(path: str | Path) -> pd.DataFrame:
    """Read a choice table (``.parquet`` or ``.csv``) and check its columns."""
    p = Path(path)
    if not p.is_file():
        raise CobelError(f"data file {p} does not exist")
    try:
        data = pd.read_csv(p) if p.suffix == ".csv" else pd.read_parquet(p)
    except Exception as exc:
        raise CobelError(f"cannot read {p}: {exc}") from None
    missing = [c for c in ("choice", "reward") if c not in data]
    if missing:
        raise CobelError(f"{p} has no {', '.join(missing)} column; it needs choice and reward "
                         f"(state and session optional), it has: {', '.join(data.columns)}")  # fmt: skip
    if data.empty:
        raise CobelError(f"{p} has no trials")
    return data


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
    def from_table(cls, data: pd.DataFrame, n_actions: int | None = None) -> ChoiceData:
        """Arrays of a table with ``choice``, ``reward`` (``state``, ``session`` optional).

        Parameters
        ----------
        data
            One row per trial, in order.
        n_actions
            Number of actions (default: the largest choice + 1).
        """
        choices = data["choice"].to_numpy(dtype=np.int64)
        rewards = data["reward"].to_numpy(dtype=np.float64)
        states = (data["state"] if "state" in data else pd.Series(0, index=data.index)).to_numpy(
            np.int64
        )
        sessions = (
            pd.factorize(data["session"])[0] if "session" in data else np.zeros(len(data), np.int64)
        )
        n_actions = int(n_actions or choices.max() + 1)
        if choices.min() < 0 or choices.max() >= n_actions:
            raise CobelError(
                f"choices must lie in 0..{n_actions - 1}, got {choices.min()}..{choices.max()}"
            )
        if states.min() < 0:
            raise CobelError(f"states must be >= 0, got {states.min()}")
        return cls(choices, rewards, states, np.asarray(sessions, np.int64),
                   int(states.max() + 1), n_actions)  # fmt: skip

    def __len__(self) -> int:
        return len(self.choices)

    def nll(self, learning_rate: float, beta: float, q0: float = 0.0) -> float:
        """Negative log-likelihood of the choices (:func:`q_learning_nll`)."""
        return q_learning_nll(learning_rate, beta, self.choices, self.rewards, self.states,
                              self.sessions, self.n_states, self.n_actions, q0)  # fmt: skip


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
    method: str = "scipy",
    n_trials: int = 200,
    seed: int = 0,
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
    table = ChoiceData.from_table(data, n_actions)

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
    return FitResult(
        params=dict(zip(params, estimate, strict=True)),
        nll=value,
        n_trials=len(table),
        method=method,
        fixed={k: v for k, v in values.items() if k not in params},
    )
