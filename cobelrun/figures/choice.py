"""Fig. 9: two-alternative forced choice, mean reward per trial across agents.

The training reward of an epsilon-greedy agent with two actions cannot exceed
``1 - epsilon / 2`` in expectation (0.85 at the paper's epsilon 0.3), so the figure draws that
ceiling and, where the run recorded it (``GreedyProbeMonitor``), the fraction of the four
displays on which the greedy policy after each trial picks the correct stimulus.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from cobelrun.errors import CobelError
from cobelrun.figures import save_figure

PROBE = "greedy_correct"


def choice_summary(trials: pd.DataFrame) -> pd.DataFrame:
    """Per trial: agents, mean, standard error and 95 % CI (``_lo``, ``_hi``: t distribution)
    of ``reward`` (and ``greedy_correct``)."""
    from cobelrun.figures.bands import ci_half_width

    if "reward" not in trials:
        raise CobelError("the trials table has no reward column (no reward monitor)")
    cols = ["reward", *([PROBE] if PROBE in trials else [])]
    g = trials.groupby("trial")
    out = pd.DataFrame({"runs": g["run"].nunique()})
    for col in cols:
        out[f"{col}_mean"] = g[col].mean()
        out[f"{col}_sem"] = g[col].std(ddof=1).fillna(0) / np.sqrt(g[col].count())
        half = ci_half_width(g[col].std(ddof=1), g[col].count())
        out[f"{col}_lo"], out[f"{col}_hi"] = out[f"{col}_mean"] - half, out[f"{col}_mean"] + half
    return out.reset_index()


def plot_mean_reward(
    trials: pd.DataFrame, ax, chance: float = 0.5, epsilon: float | None = None
) -> pd.DataFrame:
    """Mean reward per trial over agents (band: 95% CI, inside [0, 1]), chance level, the
    epsilon-greedy ceiling ``1 - epsilon / 2`` and the greedy probe if recorded.
    Returns the plotted numbers (:func:`choice_summary`)."""
    from cobelrun.figures.bands import BAND

    s = choice_summary(trials)
    x = s["trial"].to_numpy()
    n = int(s["runs"].max())
    series = [("reward", "tab:blue", f"training reward (mean of {n} agents, {BAND})")]
    if f"{PROBE}_mean" in s:
        series.append((PROBE, "tab:green", f"greedy choice correct (4 displays, {BAND})"))
    for col, color, label in series:
        ax.plot(x, s[f"{col}_mean"], color=color, lw=1.5, label=label)
        lo, hi = np.clip(s[f"{col}_lo"], 0.0, 1.0), np.clip(s[f"{col}_hi"], 0.0, 1.0)
        ax.fill_between(x, lo, hi, color=color, alpha=0.25, lw=0)
    ax.axhline(chance, color="0.4", ls="--", lw=1, label="chance")
    if epsilon is not None and epsilon > 0:
        ceiling = 1 - epsilon / 2
        ax.axhline(ceiling, color="tab:blue", ls=":", lw=1,
                   label=f"training ceiling 1 - ε/2 (ε = {epsilon:g})")  # fmt: skip
        ax.annotate(
            f"ceiling {ceiling:.2f}: a fraction ε = {epsilon:g} of training choices is random\n"
            f"(right half the time), so even a perfect agent earns {1 - epsilon:g} + {epsilon:g}/2",
            (0.25, 0.45), xycoords=("axes fraction", "data"), va="top", fontsize=6,
            color="tab:blue",
        )  # fmt: skip
    ax.set_ylim(0, 1.05)
    ax.set_xlabel("trial")
    ax.set_ylabel("reward / fraction correct")
    ax.legend(frameon=False, fontsize=7, loc="lower right")
    return s


def epsilon_of(run_dir: str | Path) -> float | None:
    """The agent's training epsilon from a run folder's ``config.yaml`` (None if it has none)."""
    from omegaconf import OmegaConf

    path = Path(run_dir) / "config.yaml"
    if not path.is_file():
        return None
    eps = OmegaConf.load(path).get("agent", {}).get("epsilon")
    return None if eps is None else float(eps)


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
    plot_mean_reward(trials, ax, epsilon=epsilon_of(run_dir))
    ax.set_title("Two-alternative forced choice (Fig. 9)", fontsize=10)
    ax.spines[["top", "right"]].set_visible(False)
    return save_figure(fig, Path(out) if out is not None else run_dir / "plot.png")
