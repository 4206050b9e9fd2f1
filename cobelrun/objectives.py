"""Task objectives: one number a run returns, for sweepers that optimise (Optuna).

A task declares ``task.objective`` (a ``_target_`` that builds a callable taking the run's
``trials`` table and returning a float); the run stores the value in its manifest
(``objective``) and a sweep job returns it, so ``cobel run -m hydra/sweeper=optuna ...``
optimises it (``hydra.sweeper.direction`` says whether to minimise or maximise).

Examples (``conf/task/*.yaml`` or an override)::

    task:
      objective: {_target_: cobelrun.objectives.TrialMean, column: reward, last: 10}

    task:  # model fitting: minimise the negative log-likelihood of recorded choices
      objective:
        _target_: cobelrun.objectives.ChoiceNLL
        data: /data/choices.parquet
        learning_rate: ${agent.learning_rate}
        beta: ${agent.beta}

See docs/getting-started.md ("Objectives, Optuna and fitting").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cobelrun.errors import CobelError, ConfigError

__all__ = ["ChoiceNLL", "TrialMean"]


@dataclass
class TrialMean:
    """Mean of a trials column over the last ``last`` trials (of ``phase``, if given), averaged
    over runs.

    Parameters
    ----------
    column
        A trials column: ``reward``, ``steps`` (escape latency), ``response``, ...
    last
        How many of the last trials count (``None``: every trial).
    phase
        Only trials of this phase (``None``: all phases).
    """

    column: str = "reward"
    last: int | None = 10
    phase: str | None = None

    def __post_init__(self) -> None:
        if self.last is not None and (isinstance(self.last, bool) or int(self.last) < 1):
            raise ConfigError(f"task.objective.last must be an integer >= 1, got {self.last!r}")

    @property
    def name(self) -> str:
        """A short label, e.g. ``mean reward, last 10 trials``."""
        where = f" of {self.phase}" if self.phase else ""
        span = f", last {self.last} trials" if self.last else ""
        return f"mean {self.column}{span}{where}"

    def __call__(self, trials: pd.DataFrame) -> float:
        """The objective's value for a ``trials`` table."""
        if self.column not in trials:
            raise ConfigError(
                f"task.objective.column {self.column!r} is not a trials column; it has: "
                f"{', '.join(map(str, trials.columns))}"
            )
        part = trials if self.phase is None else trials[trials["phase"] == self.phase]
        if part.empty:
            raise ConfigError(f"task.objective.phase {self.phase!r} has no trials")
        if self.last is not None:
            part = part[part["trial"] > part["trial"].max() - int(self.last)]
        return float(np.mean(part[self.column].to_numpy(dtype=float)))


@dataclass
class ChoiceNLL:
    """Negative log-likelihood of recorded choices under the agent's parameters.

    The model is the one ``cobel fit`` fits (:mod:`cobelrun.fit`: softmax Q-learning on
    per-trial choices and rewards), evaluated by the same code
    (:meth:`cobelrun.fit.ChoiceData.nll`). Its parameters come from the config by
    interpolation (``learning_rate: ${agent.learning_rate}``), so an Optuna sweep over
    ``agent.learning_rate`` and ``agent.beta`` with ``hydra.sweeper.direction=minimize`` is a
    maximum-likelihood fit. The value depends only on the data and these parameters, not on
    the simulated run, so a tiny protocol (``task.runs=1``, few trials) is enough.

    Parameters
    ----------
    data
        Parquet or CSV file, one row per trial: ``choice`` (action index), ``reward``, and
        optionally ``state`` and ``session`` (see :func:`cobelrun.fit.load_choices`). A
        relative path is taken from the folder ``cobel`` was started in.
    learning_rate
        Q-learning rate, in [0, 1].
    beta
        Softmax inverse temperature, >= 0.
    n_actions
        Number of actions (default: the largest choice + 1).
    """

    data: str
    learning_rate: float
    beta: float
    n_actions: int | None = None
    _table: Any = field(init=False, repr=False, default=None)

    def __post_init__(self) -> None:
        from cobelrun.fit import ChoiceData, load_choices

        for key, value, low, high in (("learning_rate", self.learning_rate, 0.0, 1.0),
                                      ("beta", self.beta, 0.0, np.inf)):  # fmt: skip
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ConfigError(f"task.objective.{key} must be a number, got {value!r}")
            if not low <= float(value) <= high:
                raise ConfigError(
                    f"task.objective.{key} must lie in [{low}, {high}], got {value!r}"
                )
        try:
            self._table = ChoiceData.from_table(load_choices(self.data), self.n_actions)
        except ConfigError:
            raise
        except CobelError as exc:  # a missing or malformed data file is bad config here
            raise ConfigError(f"task.objective.data: {exc}") from None

    @property
    def name(self) -> str:
        """A short label, e.g. ``nll of choices.parquet (500 trials)``."""
        return f"nll of {Path(self.data).name} ({len(self._table)} trials)"

    def __call__(self, trials: pd.DataFrame | None = None) -> float:
        """The negative log-likelihood of the data at ``learning_rate`` and ``beta`` (the
        run's ``trials`` are not used)."""
        return self._table.nll(float(self.learning_rate), float(self.beta))
