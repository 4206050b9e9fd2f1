"""Two-sample comparison of per-run summaries (cobel vs the original, latent vs direct, ...).

One function, :func:`two_sample`: the difference of means with Welch's 95 % interval, the
Mann-Whitney U test (two-sided), and the probability of superiority ``P(a > b) + P(a = b) / 2``
(the common-language effect size, ``U / (n_a n_b)``) with a seeded bootstrap 95 % interval.
All from :mod:`scipy.stats`.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import numpy as np

from cobelrun.errors import CobelError

#: keys of the dict :func:`two_sample` returns, in order (also the CSV columns of a comparison)
FIELDS = (
    "n_a", "n_b", "mean_a", "mean_b", "diff", "diff_lo", "diff_hi", "welch_p",
    "mw_u", "mw_p", "p_superiority", "ps_lo", "ps_hi",
)  # fmt: skip


def two_sample(
    a: Sequence[float], b: Sequence[float], *, seed: int = 0, resamples: int = 2000
) -> dict[str, float]:
    """Compare two independent samples of per-run summaries.

    Parameters
    ----------
    a, b
        Per-run values (at least 2 each, finite).
    seed
        Seed of the bootstrap of the probability of superiority.
    resamples
        Bootstrap resamples.

    Returns
    -------
    dict
        :data:`FIELDS`: sizes, means, ``diff = mean_a - mean_b`` with Welch's 95 % interval
        (``diff_lo``, ``diff_hi``) and p value, Mann-Whitney ``U`` of ``a`` and its two-sided p,
        ``p_superiority = U / (n_a n_b)`` with a percentile bootstrap 95 % interval.
    """
    from scipy import stats

    x = np.asarray(a, dtype=float)
    y = np.asarray(b, dtype=float)
    for name, v in (("a", x), ("b", y)):
        if v.ndim != 1 or v.size < 2 or not np.isfinite(v).all():
            raise CobelError(f"two_sample: sample {name} needs 2 or more finite values, got {v}")
    with warnings.catch_warnings():  # constant samples (e.g. every run 1.0): handled below
        warnings.simplefilter("ignore", RuntimeWarning)
        welch = stats.ttest_ind(x, y, equal_var=False)
    ci = welch.confidence_interval(0.95)
    if not np.isfinite(welch.pvalue):  # both samples constant: no spread to test against
        diff = float(x.mean() - y.mean())
        ci_lo = ci_hi = diff
        welch_p = 1.0 if diff == 0 else 0.0
    else:
        ci_lo, ci_hi, welch_p = float(ci.low), float(ci.high), float(welch.pvalue)
    mw = stats.mannwhitneyu(x, y, alternative="two-sided")

    def ps(xs: np.ndarray, ys: np.ndarray, axis: int = -1) -> np.ndarray:
        u = stats.mannwhitneyu(xs, ys, axis=axis, method="asymptotic").statistic
        return u / (xs.shape[axis] * ys.shape[axis])

    boot = stats.bootstrap((x, y), ps, vectorized=True, paired=False, n_resamples=resamples,
                           method="percentile", rng=np.random.default_rng(seed))  # fmt: skip
    return {
        "n_a": int(x.size),
        "n_b": int(y.size),
        "mean_a": float(x.mean()),
        "mean_b": float(y.mean()),
        "diff": float(x.mean() - y.mean()),
        "diff_lo": ci_lo,
        "diff_hi": ci_hi,
        "welch_p": welch_p,
        "mw_u": float(mw.statistic),
        "mw_p": float(mw.pvalue),
        "p_superiority": float(mw.statistic / (x.size * y.size)),
        "ps_lo": float(boot.confidence_interval.low),
        "ps_hi": float(boot.confidence_interval.high),
    }


def welch_from_stats(
    mean_a: float, sd_a: float, n_a: int, mean_b: float, sd_b: float, n_b: int
) -> dict[str, float]:
    """Welch's test and 95 % interval of ``mean_a - mean_b`` from summary statistics alone
    (where one sample's per-run values were not kept, e.g. the original's Fig. 9 agents).

    Returns ``diff``, ``diff_lo``, ``diff_hi``, ``welch_p``, ``df`` and Hedges-free Cohen's
    ``d`` (pooled SD).
    """
    from scipy import stats

    if min(n_a, n_b) < 2 or min(sd_a, sd_b) < 0:
        raise CobelError("welch_from_stats: needs n >= 2 and SD >= 0 in both samples")
    res = stats.ttest_ind_from_stats(mean_a, sd_a, n_a, mean_b, sd_b, n_b, equal_var=False)
    va, vb = sd_a**2 / n_a, sd_b**2 / n_b
    se = float(np.sqrt(va + vb))
    df = (va + vb) ** 2 / (va**2 / (n_a - 1) + vb**2 / (n_b - 1))
    half = float(stats.t.ppf(0.975, df)) * se
    diff = mean_a - mean_b
    pooled = np.sqrt(((n_a - 1) * sd_a**2 + (n_b - 1) * sd_b**2) / (n_a + n_b - 2))
    return {"diff": float(diff), "diff_lo": float(diff - half), "diff_hi": float(diff + half),
            "welch_p": float(res.pvalue), "df": float(df),
            "cohens_d": float(diff / pooled) if pooled > 0 else float("nan")}  # fmt: skip
