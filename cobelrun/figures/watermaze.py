"""Morris water maze figure: learning curves, example paths, probe quadrants, occupancy.

Every function takes tables (``trials`` with the water-maze monitor's columns, ``steps`` with
``x``/``y``) and an ``ax`` and returns the plotted numbers as a DataFrame; the pool and platform
come from the run's :class:`~cobelrun.envs.base.Geometry`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cobelrun.analysis.watermaze import QUADRANTS, add_days
from cobelrun.envs.base import Geometry
from cobelrun.errors import CobelError
from cobelrun.io.validate import read_world

#: phases drawn as learning curves, in order
CURVE_PHASES = ("acquisition", "reversal")


def load_geometry(run_dir: str | Path) -> Geometry:
    """The run's arena: ``world.json`` where the run folder has one, else rebuilt from the
    environment in its ``config.yaml``."""
    run_dir = Path(run_dir)
    for name in ("world.json", "geometry.json"):
        if (run_dir / name).is_file():
            return read_world(run_dir / name)
    from omegaconf import OmegaConf

    from cobelrun.config import instantiate

    cfg = OmegaConf.load(run_dir / "config.yaml")
    env = instantiate("env", cfg.env)
    return env.unwrapped.geometry()


def daily_summary(trials: pd.DataFrame, trials_per_day: int = 4) -> pd.DataFrame:
    """Per phase and day: mean, SD and 95 % CI (``_lo``, ``_hi``) over runs of each run's
    daily mean latency (s) and path length. ``session`` numbers the days across phases
    (acquisition, then reversal)."""
    from cobelrun.figures.bands import ci_half_width

    need = {"escape_latency_s", "path_length", "phase", "run", "trial_in_phase"}
    if not need <= set(trials):
        raise CobelError(
            f"the trials table lacks {sorted(need - set(trials))} (no water-maze monitor)"
        )
    t = add_days(trials[trials["phase"].isin(CURVE_PHASES)], trials_per_day)
    per_run = t.groupby(["phase", "day", "run"])[["escape_latency_s", "path_length"]].mean()
    g = per_run.groupby(["phase", "day"])
    out = pd.concat(
        [g.mean().add_suffix("_mean"), g.std(ddof=1).fillna(0).add_suffix("_sd")], axis=1
    )
    out["runs"] = g.size()
    for c in ("escape_latency_s", "path_length"):
        half = ci_half_width(out[f"{c}_sd"], out["runs"])
        out[f"{c}_lo"], out[f"{c}_hi"] = out[f"{c}_mean"] - half, out[f"{c}_mean"] + half
    out = out.reset_index()
    order = {p: i for i, p in enumerate(CURVE_PHASES)}
    out = out.sort_values(["phase", "day"], key=lambda s: s.map(order) if s.name == "phase" else s)
    out["session"] = np.arange(1, len(out) + 1)
    return out.reset_index(drop=True)


def plot_learning_curve(summary: pd.DataFrame, ax: Any, column: str, label: str) -> None:
    """Mean over runs of ``column`` per day with its 95% CI (never below 0); acquisition and
    reversal in two colours."""
    from cobelrun.figures.bands import BAND

    colors = {"acquisition": "tab:blue", "reversal": "tab:red"}
    for phase, part in summary.groupby("phase", sort=False):
        x = part["session"].to_numpy()
        m = part[f"{column}_mean"].to_numpy()
        lo = np.clip(part[f"{column}_lo"].to_numpy(), 0.0, None)  # latencies, lengths >= 0
        hi = part[f"{column}_hi"].to_numpy()
        ax.plot(x, m, "o-", ms=3, color=colors.get(phase, "k"), label=f"{phase} (mean, {BAND})")
        ax.fill_between(x, lo, hi, color=colors.get(phase, "k"), alpha=0.2, lw=0)
    from matplotlib.ticker import MaxNLocator

    starts = summary.loc[summary["phase"] != summary["phase"].iloc[0], "session"]
    if len(starts):  # where the platform moved
        ax.axvline(starts.iloc[0] - 0.5, color="0.5", ls=":", lw=0.8)
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("day")
    ax.set_ylabel(label)
    ax.set_ylim(bottom=0)
    ax.legend(loc="upper center")


def draw_pool(geometry: Geometry, ax: Any, platforms: tuple[str, ...] = ()) -> None:
    """The pool outline and the named platform regions (dashed: not rewarded)."""
    import matplotlib.patches as mpatches

    outline = np.vstack([geometry.outline, geometry.outline[:1]])
    ax.plot(outline[:, 0], outline[:, 1], color="0.3", lw=1)
    for name in platforms:
        r = geometry.regions.get(name)
        if r and r.get("shape") == "circle":
            ax.add_patch(mpatches.Circle((r["x"], r["y"]), r["radius"], fill=False, lw=1.2,
                                         color="tab:green"))  # fmt: skip
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    for side in ("left", "bottom", "top", "right"):
        ax.spines[side].set_visible(False)


def plot_paths(steps: pd.DataFrame, trials: pd.DataFrame, geometry: Geometry, ax: Any,
               run: int, days: tuple[int, int], trials_per_day: int = 4) -> pd.DataFrame:  # fmt: skip
    """The acquisition paths of ``run`` on the first and last of ``days`` (grey, black), each
    to where its last step led (:func:`cobelrun.analysis.paths.visited_poses`)."""
    from cobelrun.analysis.paths import visited_poses

    t = add_days(
        trials[(trials["phase"] == "acquisition") & (trials["run"] == run)], trials_per_day
    )
    draw_pool(geometry, ax, ("platform",))
    rows = []
    poses = visited_poses(steps[steps["run"] == run])
    for day, color in zip(days, ("0.6", "k"), strict=True):
        for trial in t.loc[t["day"] == day, "trial"]:
            p = poses[poses["trial"] == trial]
            ax.plot(p["x"], p["y"], color=color, lw=0.6, alpha=0.9,
                    label=f"day {day}" if trial == t.loc[t["day"] == day, "trial"].iloc[0] else None)  # fmt: skip
            rows.append({"run": run, "day": day, "trial": int(trial), "points": len(p)})
    ax.legend(loc="lower left", fontsize=6)
    return pd.DataFrame(rows)


def probe_quadrants(trials: pd.DataFrame) -> pd.DataFrame:
    """Probe-phase quadrant occupancy: mean, SD and 95 % CI (``fraction_lo``, ``fraction_hi``)
    over runs per quadrant."""
    from cobelrun.figures.bands import ci_half_width

    probe = trials[trials["phase"] == "probe"]
    if probe.empty:
        raise CobelError("the trials table has no probe phase")
    per_run = probe.groupby("run")[[f"{q}_quadrant_fraction" for q in QUADRANTS]].mean()
    return pd.DataFrame({
        "quadrant": list(QUADRANTS),
        "fraction_mean": per_run.mean().to_numpy(),
        "fraction_sd": per_run.std(ddof=1).fillna(0).to_numpy(),
        "fraction_lo": (per_run.mean() - ci_half_width(per_run.std(ddof=1), len(per_run))).to_numpy(),
        "fraction_hi": (per_run.mean() + ci_half_width(per_run.std(ddof=1), len(per_run))).to_numpy(),
        "runs": len(per_run),
    })  # fmt: skip


def plot_quadrants(table: pd.DataFrame, ax: Any) -> None:
    """Bars of quadrant occupancy (mean and 95% CI, inside [0, 1]) against the 25% chance
    line."""
    x = np.arange(len(table))
    colors = ["tab:green" if q == "target" else "0.6" for q in table["quadrant"]]
    m = table["fraction_mean"].to_numpy()
    lo, hi = np.clip(table["fraction_lo"], 0, 1), np.clip(table["fraction_hi"], 0, 1)
    ax.bar(x, m, yerr=np.vstack([m - lo, hi - m]), color=colors, capsize=2)
    ax.axhline(0.25, color="k", ls="--", lw=0.8, label="chance")
    ax.set_xticks(x, [q.replace("adjacent_", "adj. ") for q in table["quadrant"]], rotation=20)
    ax.set_ylabel("time in quadrant (probe; mean, 95% CI)")
    ax.set_ylim(0, 1)
    ax.legend(loc="upper right")


def plot_occupancy(steps: pd.DataFrame, geometry: Geometry, ax: Any, bins: int = 40) -> np.ndarray:
    """Heat map of the positions in ``steps`` (e.g. the probe trials of every run) over the
    pool (each step's position and each trial's arrival); returns the (bins, bins) fraction
    of positions per bin."""
    from cobelrun.analysis.paths import visited_poses

    x0, y0, x1, y1 = geometry.bounds
    poses = visited_poses(steps)
    h, _, _ = np.histogram2d(poses["x"], poses["y"], bins=bins, range=[[x0, x1], [y0, y1]])
    h = h / max(h.sum(), 1)
    from matplotlib.colors import PowerNorm

    ax.imshow(h.T, origin="lower", extent=(x0, x1, y0, y1), cmap="magma", interpolation="nearest",
              norm=PowerNorm(0.5))  # square-root scale: the rarely visited bins stay visible  # fmt: skip
    draw_pool(geometry, ax, ("platform",))
    return h
