"""Conditioning figure: each paradigm's test predictions side by side for each model.

Functions take trials tables (with :class:`cobelrun.monitors.conditioning.ConditioningMonitor`'s
``trial_type`` and ``V`` columns) and matplotlib axes.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd

from cobelrun.errors import CobelError


def test_predictions(
    trials_by_model: Mapping[str, pd.DataFrame], phase: str = "test"
) -> pd.DataFrame:
    """Mean, standard error and 95 % CI half width (``ci``) over runs of ``V`` per model and
    trial type in ``phase`` (for a task without that phase: the last trial of every phase)."""
    from cobelrun.figures.bands import ci_half_width

    rows = []
    for model, t in trials_by_model.items():
        if "V" not in t:
            raise CobelError("the trials table has no V column (no conditioning monitor)")
        if phase in set(t["phase"]):
            per_run = t[t["phase"] == phase].groupby(["trial_type", "run"])["V"].mean()
            key = "trial_type"
        else:
            per_run = t.groupby(["phase", "run"])["V"].last()
            key = "phase"
        g = per_run.groupby(level=0)
        for name, values in g:
            rows.append({"model": model, "probe": name, "by": key, "V": float(values.mean()),
                         "sem": float(values.std(ddof=1) / np.sqrt(len(values)))
                         if len(values) > 1 else 0.0,
                         "ci": float(ci_half_width(values.std(ddof=1), len(values)))})  # fmt: skip
    return pd.DataFrame(rows)


def plot_predictions(table: pd.DataFrame, ax: Any, title: str) -> None:
    """Grouped bars: one group per probe (trial type), one bar per model (mean and 95% CI
    over runs)."""
    models = list(dict.fromkeys(table["model"]))
    probes = list(dict.fromkeys(table["probe"]))
    width = 0.8 / max(1, len(models))
    for k, model in enumerate(models):
        part = table[table["model"] == model].set_index("probe").reindex(probes)
        x = np.arange(len(probes)) + (k - (len(models) - 1) / 2) * width
        ax.bar(x, part["V"], width, yerr=part["ci"], label=model, capsize=2)
    ax.axhline(0, color="0.4", lw=0.8)
    ax.set_xticks(range(len(probes)), probes, fontsize=8)
    ax.set_title(title, fontsize=9)
    ax.set_ylabel("V (prediction; mean, 95% CI)")
    ax.spines[["top", "right"]].set_visible(False)
