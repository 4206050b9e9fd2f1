"""Task objectives: one number a run returns, for sweepers that optimise (Optuna).

A task declares ``task.objective`` (a ``_target_`` that builds a callable taking the run's
``trials`` table and returning a float); the run stores the value in its manifest
(``objective``) and a sweep job returns it, so ``cobel run -m hydra/sweeper=optuna ...``
optimises it (``hydra.sweeper.direction`` says whether to minimise or maximise).

Example (``conf/task/*.yaml`` or an override)::

    task:
      objective: {_target_: cobelrun.objectives.TrialMean, column: reward, last: 10}
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from cobelrun.errors import ConfigError

__all__ = ["TrialMean"]


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
