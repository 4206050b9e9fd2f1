"""The one kind of uncertainty band cobel draws: the 95 % confidence interval of a mean.

Every learning curve and bar of a mean over runs (``cobel plot``, ``cobel compare``, the task
figures, the dashboard) shows the mean over the independent units (runs; jobs x runs in a
sweep) and its 95 % confidence interval from the t distribution (``mean +- t(0.975, n - 1) *
SE``); the legend or axis label says ``95% CI`` (:data:`BAND`). With one unit there is no
interval (the band is the mean).

At small n the t interval can leave the range the measure can take (a latency below 0 steps,
more cumulative responses than trials); :func:`measure_limits` gives that range and the
band drawn is clipped to it (the numbers returned keep the true interval).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

__all__ = ["BAND", "ci_half_width", "clip_to_measure", "mean_ci", "measure_limits"]

#: what every band and error bar of a mean is, as the legends say it
BAND = "95% CI"


def ci_half_width(sd: np.ndarray | pd.Series, n: np.ndarray | pd.Series) -> np.ndarray:
    """Half width of the 95 % t interval of a mean from the sample SD (ddof=1) and n; 0 where
    n < 2."""
    from scipy import stats

    sd = np.nan_to_num(np.asarray(sd, np.float64))
    n = np.asarray(n, np.float64)
    t = stats.t.ppf(0.975, np.maximum(n - 1, 1))
    return np.where(n > 1, t * sd / np.sqrt(np.maximum(n, 1)), 0.0)


def mean_ci(groups: pd.core.groupby.SeriesGroupBy) -> pd.DataFrame:
    """Per group: ``mean``, ``n``, ``lo``, ``hi`` (the 95 % t interval of the mean)."""
    out = pd.DataFrame({"mean": groups.mean(), "n": groups.count(), "sd": groups.std(ddof=1)})
    half = ci_half_width(out["sd"], out["n"])
    out["lo"], out["hi"] = out["mean"] - half, out["mean"] + half
    return out.drop(columns="sd")


#: measures with a known range: column -> (low, high); ``"trial"``: the trial number (a count
#: over a run's trials cannot exceed the trials so far)
_RANGES: dict[str, tuple[float, float | str]] = {
    "steps": (0.0, np.inf),  # escape latency
    "escape_latency_s": (0.0, np.inf),
    "path_length": (0.0, np.inf),
    "cumulative_response": (0.0, "trial"),
    "response": (0.0, 1.0),
    "greedy_correct": (0.0, 1.0),
    "terminated": (0.0, 1.0),
}


def measure_limits(
    column: str, trials: np.ndarray, observed: pd.Series | np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The range ``column`` can take at each of ``trials`` (trial numbers, 1-based within a
    run): latencies and path lengths >= 0, fractions in [0, 1], cumulative responses in
    [0, trial]. Other columns (reward, unit values, ...): the range the measure took in
    ``observed`` where given, else unbounded."""
    trials = np.asarray(trials, np.float64)
    if column in _RANGES:
        lo, hi = _RANGES[column]
        top = trials if hi == "trial" else np.full(trials.shape, float(hi))
        return np.full(trials.shape, float(lo)), top
    if observed is not None and len(observed):
        v = np.asarray(observed, np.float64)
        return np.full(trials.shape, np.nanmin(v)), np.full(trials.shape, np.nanmax(v))
    return np.full(trials.shape, -np.inf), np.full(trials.shape, np.inf)


def clip_to_measure(
    column: str,
    trials: np.ndarray,
    lo: np.ndarray | pd.Series,
    hi: np.ndarray | pd.Series,
    observed: pd.Series | np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``lo``/``hi`` of a band clipped to :func:`measure_limits`."""
    low, high = measure_limits(column, trials, observed)
    return (np.clip(np.asarray(lo, np.float64), low, high),
            np.clip(np.asarray(hi, np.float64), low, high))  # fmt: skip
