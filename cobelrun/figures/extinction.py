"""Fig. 6B-style plots: cumulative response curve and escape latency, mean and spread over runs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from cobelrun.errors import CobelError
from cobelrun.figures import save_figure


def first_run(trials: pd.DataFrame) -> pd.DataFrame:
    """The trials of one run (the first job's first run when ``trials`` spans several jobs)."""
    keys = [k for k in ("job", "run") if k in trials.columns]
    first = trials[keys].drop_duplicates().sort_values(keys).iloc[0]
    mask = np.logical_and.reduce([trials[k] == first[k] for k in keys])
    return trials[mask].sort_values("trial")


def phase_boundaries(trials: pd.DataFrame) -> list[tuple[float, str]]:
    """(x position between trials, next phase name) for every phase change."""
    first = first_run(trials)
    change = first["phase"].ne(first["phase"].shift()) & (first["trial"] > first["trial"].min())
    return [
        (float(t) - 0.5, str(p))
        for t, p in zip(first.loc[change, "trial"], first.loc[change, "phase"], strict=True)
    ]


def summarize(trials: pd.DataFrame, column: str) -> pd.DataFrame:
    """Per trial: mean, std, standard error, 95 % confidence interval (``lo``, ``hi``: t
    distribution, :mod:`cobelrun.figures.bands`) and 25th/75th percentile of ``column`` across
    runs."""
    from cobelrun.figures.bands import ci_half_width

    g = trials.groupby("trial")[column]
    out = pd.DataFrame(
        {
            "mean": g.mean(),
            "std": g.std(ddof=0),
            "sem": g.sem(ddof=1).fillna(0.0),
            "q25": g.quantile(0.25),
            "q75": g.quantile(0.75),
        }
    )
    half = ci_half_width(g.std(ddof=1), g.count())
    out["lo"], out["hi"] = out["mean"] - half, out["mean"] + half
    return out


def _shade(ax, summary: pd.DataFrame, color: str, label: str, column: str) -> None:
    from cobelrun.figures.bands import BAND, clip_to_measure

    x = summary.index.to_numpy()
    ax.plot(x, summary["mean"], color=color, lw=1.5, label=f"{label} (mean, {BAND})")
    # mean and its 95% CI: latencies are bimodal (found the goal or hit max_steps), so a
    # percentile band jumps between the two modes and hides the mean's trend; the band stays
    # inside the measure's range (no negative latencies, no more responses than trials)
    lo, hi = clip_to_measure(column, x, summary["lo"], summary["hi"])
    ax.fill_between(x, lo, hi, color=color, alpha=0.3, lw=0)


def _mark_phases(ax, trials: pd.DataFrame) -> None:
    for x, name in phase_boundaries(trials):
        ax.axvline(x, color="0.3", ls="--", lw=1)
        ax.annotate(name, (x, 1.0), xycoords=("data", "axes fraction"), xytext=(3, -12),
                    textcoords="offset points", fontsize=8, color="0.3")  # fmt: skip


def plot_cumulative_response(trials: pd.DataFrame, ax) -> None:
    """Cumulative response curve (mean and 95% CI across runs), phase boundaries."""
    if "cumulative_response" not in trials:
        raise CobelError("the trials table has no cumulative_response column (no response monitor)")
    _shade(
        ax,
        summarize(trials, "cumulative_response"),
        "tab:blue",
        "cumulative responses",
        "cumulative_response",
    )
    _mark_phases(ax, trials)
    ax.set_xlabel("trial")
    ax.set_ylabel("cumulative responses (mean, 95% CI)")


def plot_escape_latency(trials: pd.DataFrame, ax) -> None:
    """Escape latency in steps (mean and 95% CI across runs), phase boundaries."""
    if "steps" not in trials:
        raise CobelError("the trials table has no steps column (no latency monitor)")
    _shade(ax, summarize(trials, "steps"), "tab:red", "escape latency", "steps")
    _mark_phases(ax, trials)
    ax.set_xlabel("trial")
    ax.set_ylabel("escape latency [steps] (mean, 95% CI)")


def trials_to_extinction(trials: pd.DataFrame, level: float = 0.5) -> float:
    """Trials after the first phase change until the mean response rate first falls below
    ``level`` (NaN if it never does)."""
    bounds = phase_boundaries(trials)
    if not bounds:
        return float("nan")
    switch = bounds[0][0] + 0.5  # first trial of the second phase
    rate = trials.groupby("trial")["response"].mean()
    below = rate[(rate.index >= switch) & (rate < level)]
    return float(below.index[0] - switch + 1) if len(below) else float("nan")


def plot_response_rate(trials: pd.DataFrame, ax, color: str = "tab:green") -> float:
    """Mean right-arm response per trial (band: 95% CI, inside [0, 1]) and per 10-trial block, the 0.5
    level and the first trial after the switch below it. Returns that trial count (:func:`trials_to_extinction`)."""
    from cobelrun.figures.bands import BAND, clip_to_measure

    s = summarize(trials, "response")
    x = s.index.to_numpy()
    ax.plot(x, s["mean"], color=color, lw=0.6, alpha=0.6, label=f"per trial (mean, {BAND})")
    lo, hi = clip_to_measure("response", x, s["lo"], s["hi"])
    ax.fill_between(x, lo, hi, color=color, alpha=0.2, lw=0)
    blocks = s["mean"].groupby((s.index - s.index.min()) // 10).transform("mean")
    ax.step(x, blocks, where="mid", color="k", lw=1, label="10-trial blocks")
    ax.axhline(0.5, color="0.5", ls=":", lw=1)
    for xb, _ in phase_boundaries(trials):
        ax.axvline(xb, color="0.3", ls="--", lw=1)
    n = trials_to_extinction(trials)
    if np.isfinite(n):
        switch = phase_boundaries(trials)[0][0] + 0.5
        ax.axvline(switch + n - 1, color=color, lw=0.8)
        ax.annotate(f"< 0.5 after {n:.0f} trials", (switch + n - 1, 0.9), xytext=(3, 0),
                    textcoords="offset points", fontsize=7, color=color)  # fmt: skip
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel("trial")
    ax.set_ylabel("right-arm response rate")
    return n


def plot_extinction(trials: pd.DataFrame, title: str = ""):
    """Fig. 6B: cumulative response (left) and escape latency (right); returns ``fig, axes``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4), constrained_layout=True)
    plot_cumulative_response(trials, axes[0])
    plot_escape_latency(trials, axes[1])
    n_runs = trials["run"].nunique()
    what = f"{n_runs} runs: mean ± standard error"
    fig.suptitle(f"{title} ({what})" if title else what, fontsize=10)
    for ax in axes:
        ax.spines[["top", "right"]].set_visible(False)
    return fig, axes


def plot_run(run_dir: str | Path, out: str | Path | None = None) -> Path:
    """Draw Fig. 6B for a run folder into ``out`` (default ``RUN_DIR/plot.png``)."""
    from cobelrun.results import load_manifest, load_trials

    run_dir = Path(run_dir)
    trials = load_trials(run_dir)
    if trials.empty:
        raise CobelError(f"{run_dir}/trials.parquet has no rows to plot")
    try:
        title = str(load_manifest(run_dir).get("task", ""))
    except CobelError:
        title = ""
    fig, _ = plot_extinction(trials, title)
    return save_figure(fig, Path(out) if out is not None else run_dir / "plot.png")
