"""Fig. 8 panels: place cells over training, example activity maps, spatial information, RSA.

Functions take tables (and arrays for the maps) and an ``ax``; they never load runs themselves.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd


def summarize_counts(snapshots: pd.DataFrame) -> pd.DataFrame:
    """Mean, SD and run count of place cells (and fraction) per snapshot trial."""
    g = snapshots.groupby("trial")
    return pd.DataFrame({
        "mean": g["place_cells"].mean(),
        "sd": g["place_cells"].std(ddof=1).fillna(0.0),
        "fraction_mean": g["place_cell_fraction"].mean(),
        "runs": g["place_cells"].size(),
    })  # fmt: skip


def spearman_rho(snapshots: pd.DataFrame) -> float:
    """Spearman correlation of the mean place-cell count with the snapshot trial."""
    from scipy.stats import spearmanr

    s = summarize_counts(snapshots)
    if len(s) < 3 or s["mean"].nunique() < 2:
        return float("nan")
    return float(spearmanr(s.index.to_numpy(), s["mean"].to_numpy()).statistic)


def plot_place_cell_counts(snapshots: pd.DataFrame, ax: Any) -> Any:
    """Place cells per snapshot: mean ± SD over runs (runs as thin lines), fraction on the right."""
    s = summarize_counts(snapshots)
    for _, run in snapshots.groupby("run"):
        ax.plot(run["trial"], run["place_cells"], color="0.75", lw=0.7, zorder=1)
    ax.errorbar(s.index, s["mean"], yerr=s["sd"], color="C0", marker="o", ms=3, capsize=2,
                zorder=2, label="mean ± SD")  # fmt: skip
    units = int(snapshots["units"].max())
    ax.set_xlabel("trial")
    ax.set_ylabel("place cells")
    ax.set_ylim(bottom=0)
    right = ax.secondary_yaxis("right", functions=(lambda c: c / units, lambda f: f * units))
    right.set_ylabel(f"fraction of {units} units")
    right.tick_params(labelsize=6)
    right.yaxis.label.set_size(7)
    return ax


def plot_information(units: pd.DataFrame, ax: Any) -> Any:
    """Distribution of the units' spatial information (Skaggs) per snapshot (box plots)."""
    trials = sorted(units["trial"].unique())
    data = [
        units.loc[units["trial"] == t, "spatial_information"].dropna().to_numpy() for t in trials
    ]
    ax.boxplot(data, positions=range(len(trials)), widths=0.6, showfliers=False)
    ax.set_xticks(range(len(trials)), [str(t) for t in trials], rotation=45)
    ax.set_xlabel("trial")
    ax.set_ylabel("spatial information (bits)")
    return ax


def plot_rsa(snapshots: pd.DataFrame, ax: Any) -> Any:
    """RDM correlation (population vs spatial distance) per snapshot, mean ± SD over runs."""
    g = snapshots.groupby("trial")["rsa_spatial"]
    m, sd = g.mean(), g.std(ddof=1).fillna(0.0)
    ax.errorbar(m.index, m.to_numpy(), yerr=sd.to_numpy(), color="C2", marker="o", ms=3, capsize=2)
    ax.set_xlabel("trial")
    ax.set_ylabel("RDM vs distance (Spearman)")
    return ax


def plot_unit_maps(
    maps: np.ndarray,
    explored: np.ndarray,
    headings_deg: Sequence[float],
    axes: Sequence[Any],
    label: str = "",
) -> None:
    """One unit's heading maps and their mean, one ``ax`` each (``len(headings) + 1`` axes)."""
    mean = np.nanmean(np.where(explored, maps, np.nan), axis=0)
    stack = [*maps, mean]
    vals = np.where(explored[None], maps, np.nan)
    lo, hi = np.nanmin(vals), np.nanmax(vals)
    titles = [f"{h:.0f}°" for h in headings_deg] + ["mean"]
    for ax, m, title in zip(axes, stack, titles, strict=True):
        img = np.where(explored, m, np.nan)
        ax.imshow(img, origin="lower", cmap="viridis", vmin=lo, vmax=hi if hi > lo else None,
                  interpolation="nearest")  # fmt: skip
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(title, fontsize=6, pad=2)
    if label:
        axes[0].set_ylabel(label, fontsize=6)


def plot_summary_panels(snapshots: pd.DataFrame, units: pd.DataFrame, axes: Sequence[Any]) -> float:
    """Panels A-C on three ``axes``: place cells per snapshot with the Spearman rho of the mean
    count (A), spatial information (B), population RDM against distance (C), titled and with
    small tick labels. Returns the rho (NaN for fewer than 3 snapshots or a constant count)."""
    ax_count, ax_info, ax_rsa = axes
    rho = spearman_rho(snapshots)
    plot_place_cell_counts(snapshots, ax_count)
    rho_text = f"{rho:.2f}" if np.isfinite(rho) else "undefined (a constant count)"
    n = snapshots["run"].nunique()
    ax_count.set_title(f"A  place cells ({n} run{'s' * (n != 1)}), Spearman ρ = {rho_text}",
                       fontsize=8)  # fmt: skip
    plot_information(units, ax_info)
    ax_info.set_title("B  spatial information", fontsize=8)
    plot_rsa(snapshots, ax_rsa)
    ax_rsa.set_title("C  population RDM vs distance", fontsize=8)
    for ax in axes:
        ax.tick_params(labelsize=6)
        ax.xaxis.label.set_size(7)
        ax.yaxis.label.set_size(7)
    return rho


#: how ``cobel plot`` compares bounding boxes per task (``fig8``'s reading for the original's
#: training, cobel's default otherwise)
BOX_MEASURE_BY_TASK = {"place_cells_original": "area"}


def plot_run(run_dir: str | Path, out: str | Path | None = None) -> Path:
    """``cobel plot RUN_DIR`` for a place-cell task: panels A-C (:func:`plot_summary_panels`)
    of the run folder's runs, into ``out`` (default ``RUN_DIR/plot.png``). The paper figure
    over several seeds, with example maps, is ``cobel figure fig8``."""
    import matplotlib.pyplot as plt

    from cobelrun.analysis.maps import MAPS_TABLE, classify_snapshots, load_activity_maps
    from cobelrun.analysis.place_cells import PlaceCellCriterion
    from cobelrun.errors import CobelError
    from cobelrun.figures import save_figure
    from cobelrun.results import load_manifest

    run_dir = Path(run_dir)
    if not (run_dir / f"{MAPS_TABLE}.parquet").is_file():
        raise CobelError(
            f"{run_dir} has no {MAPS_TABLE}.parquet (no activity-map monitor, or the run has not "
            f"finished); try: cobel plot {run_dir} --kind occupancy"
        )
    task = str(load_manifest(run_dir).get("task", ""))
    measure = BOX_MEASURE_BY_TASK.get(task, "extent")
    df, grid = load_activity_maps(run_dir)
    units, snapshots = classify_snapshots(
        df, grid, criterion=PlaceCellCriterion(box_measure=measure)
    )
    fig, axes = plt.subplots(1, 3, figsize=(9.0, 3.0), layout="constrained")
    plot_summary_panels(snapshots, units, axes)
    fig.suptitle(f"{task}: place cells (boxes by {measure}; cobel figure fig8 for the paper "
                 "figure)", fontsize=9)  # fmt: skip
    return save_figure(fig, Path(out) if out is not None else run_dir / "plot.png")
