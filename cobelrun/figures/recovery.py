"""Parameter- and model-recovery figures (``cobel recover``).

Functions take the tables of :mod:`cobelrun.recover` and matplotlib axes, never live objects.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from cobelrun.choice_models import MODELS


def plot_parameter_recovery(table: pd.DataFrame, summary: pd.DataFrame) -> Any:
    """True vs fitted value of every fitted parameter of every generating model (its own fits;
    a model's fixed parameters are not drawn), one panel each, with the identity line and Pearson r / bias in the title. Returns the figure."""
    import matplotlib.pyplot as plt

    own = table[table["generating"] == table["fitted"]]
    panels = [(m, k) for m in dict.fromkeys(own["generating"]) for k in MODELS[m].default_keys]
    cols = min(4, len(panels))
    rows = int(np.ceil(len(panels) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 3.0 * rows), squeeze=False)
    for ax in axes.flat[len(panels) :]:
        ax.set_visible(False)
    for ax, (model, key) in zip(axes.flat, panels, strict=False):
        part = own[own["generating"] == model]
        true, est = part[f"true:{key}"], part[f"fit:{key}"]
        ax.scatter(true, est, s=10, alpha=0.6)
        lo, hi = float(min(true.min(), est.min())), float(max(true.max(), est.max()))
        ax.plot([lo, hi], [lo, hi], color="0.5", lw=1, ls="--")
        if key in ("agent.beta", "agent.response_beta"):  # log-uniform priors
            ax.set_xscale("log")
            ax.set_yscale("log")
        row = summary[(summary["model"] == model) & (summary["param"] == key)].iloc[0]
        ax.set_title(f"{model}: {key.removeprefix('agent.')}\nr = {row['r']:.2f}, "
                     f"bias = {row['bias']:+.3g}", fontsize=9)  # fmt: skip
        ax.set_xlabel("true")
        ax.set_ylabel("fitted")
    fig.tight_layout()
    return fig


def plot_confusion(matrices: dict[str, pd.DataFrame]) -> Any:
    """Model-recovery confusion matrices side by side (one per criterion): rows the generating
    model, columns the best-fitting one, cells the share of agents. Returns the figure."""
    import matplotlib.pyplot as plt

    n = len(matrices)
    fig, axes = plt.subplots(1, n, figsize=(3.6 * n, 3.4), squeeze=False)
    for ax, (criterion, m) in zip(axes.flat, matrices.items(), strict=True):
        ax.imshow(m.to_numpy(), vmin=0, vmax=1, cmap="Blues")
        ax.set_xticks(range(m.shape[1]), [str(c) for c in m.columns], rotation=45, ha="right",
                      fontsize=8)  # fmt: skip
        ax.set_yticks(range(m.shape[0]), [str(i) for i in m.index], fontsize=8)
        for i in range(m.shape[0]):
            for j in range(m.shape[1]):
                v = float(m.iat[i, j])
                ax.text(j, i, f"{v:.2f}", ha="center", va="center", fontsize=8,
                        color="white" if v > 0.6 else "black")  # fmt: skip
        ax.set_title(f"best by {criterion}", fontsize=10)
        ax.set_xlabel("fitted model")
        ax.set_ylabel("generating model")
    fig.tight_layout()
    return fig
