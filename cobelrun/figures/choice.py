"""Fig. 9: two-alternative forced choice, mean reward per trial across agents."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from cobelrun.errors import CobelError


def plot_mean_reward(trials: pd.DataFrame, ax, chance: float = 0.5) -> None:
    """Mean reward per trial over runs, band = standard error of the mean; chance level."""
    if "reward" not in trials:
        raise CobelError("the trials table has no reward column (no reward monitor)")
    g = trials.groupby("trial")["reward"]
    mean, sem = g.mean(), g.std(ddof=1).fillna(0) / np.sqrt(g.count())
    x = mean.index.to_numpy()
    ax.plot(x, mean, color="tab:blue", lw=1.5, label=f"mean of {trials['run'].nunique()} agents")
    ax.fill_between(x, mean - sem, mean + sem, color="tab:blue", alpha=0.25, lw=0)
    ax.axhline(chance, color="0.4", ls="--", lw=1, label="chance")
    ax.set_ylim(0, 1.05)
    ax.set_xlabel("trial")
    ax.set_ylabel("reward")
    ax.legend(frameon=False, fontsize=8, loc="lower right")


def plot_run(run_dir: str | Path, out: str | Path | None = None) -> Path:
    """Draw Fig. 9C for a run folder into ``out`` (default ``RUN_DIR/plot.png``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cobelrun.results import load_trials

    run_dir = Path(run_dir)
    trials = load_trials(run_dir)
    if trials.empty:
        raise CobelError(f"{run_dir}/trials.parquet has no rows to plot")
    fig, ax = plt.subplots(figsize=(4.5, 3.2), constrained_layout=True)
    plot_mean_reward(trials, ax)
    ax.set_title("Two-alternative forced choice (Fig. 9)", fontsize=10)
    ax.spines[["top", "right"]].set_visible(False)
    out = Path(out) if out is not None else run_dir / "plot.png"
    try:
        fig.savefig(out, dpi=150)
    except OSError as exc:
        raise CobelError(f"cannot write {out}: {exc.strerror}") from None
    finally:
        plt.close(fig)
    return out
