"""Fig. 7: latent learning in the Blodgett maze (Dyna-DSR).

- 7B: escape latency of the latent and the direct group, aligned on the first rewarded trial.
- 7C: the successor representation of the start state drawn on the maze, at the end of the
  exploration phase and at the end of training (from the ``sr/output`` layer recorded by the
  activity monitor: ``M(s_start, a)`` for every action, averaged over actions).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pandas as pd

from cobelrun.errors import CobelError
from cobelrun.figures import save_figure
from cobelrun.io.run_folder import RunFolder

REWARDED = "rewarded"
GROUP_COLORS = {"latent": "tab:blue", "direct": "tab:orange"}


def aligned_latency(trials: pd.DataFrame, phase: str = REWARDED) -> pd.DataFrame:
    """Trials with ``aligned_trial``: 0 = the first ``phase`` trial of each run, earlier
    trials (the latent group's exploration) negative, as on the x axis of Fig. 7B."""
    if "steps" not in trials:
        raise CobelError("the trials table has no steps column (no latency monitor)")
    rows = trials[trials["phase"] == phase]
    if rows.empty:
        raise CobelError(f"the trials table has no {phase!r} phase to align on")
    first = rows.groupby("run")["trial"].min()
    return trials.assign(aligned_trial=trials["trial"] - trials["run"].map(first).to_numpy())


def latency_summary(groups: Mapping[str, pd.DataFrame]) -> pd.DataFrame:
    """Per group and aligned trial: runs, mean, 25th and 75th percentile of the latency."""
    frames = []
    for name, trials in groups.items():
        g = aligned_latency(trials).groupby("aligned_trial")["steps"]
        stats = {"runs": g.count(), "mean": g.mean(), "q25": g.quantile(0.25),
                 "q75": g.quantile(0.75)}  # fmt: skip
        frames.append(pd.DataFrame(stats).reset_index().assign(group=name))
    return pd.concat(frames, ignore_index=True)


def mean_latency_first_rewarded(trials: pd.DataFrame, n: int = 10) -> float:
    """Mean escape latency over the first ``n`` rewarded trials (all runs)."""
    rows = aligned_latency(trials)
    return float(rows.loc[rows["aligned_trial"].between(0, n - 1), "steps"].mean())


def plot_latency_groups(groups: Mapping[str, pd.DataFrame], ax) -> None:
    """Fig. 7B: mean latency (band: 25th-75th percentile over runs), aligned on the first
    rewarded trial (0); the latent group's exploration trials are negative."""
    summary = latency_summary(groups)
    for name, rows in summary.groupby("group", sort=False):
        color = GROUP_COLORS.get(str(name))
        x = rows["aligned_trial"].to_numpy()
        ax.plot(x, rows["mean"], lw=1.2, color=color,
                label=f"{name} ({int(rows['runs'].max())} runs)")  # fmt: skip
        ax.fill_between(x, rows["q25"], rows["q75"], alpha=0.2, lw=0, color=color)
    ax.axvline(-0.5, color="0.5", lw=0.8, ls=":")
    ax.set_xlabel("trial (0 = first rewarded trial)")
    ax.set_ylabel("escape latency [steps]")
    ax.legend(frameon=False, fontsize=8)


def start_state_sr(
    activity: pd.DataFrame, probe: int, trial: int, n_states: int, layer: str = "sr/output"
) -> np.ndarray:
    """SR of ``probe`` at ``trial`` (mean over runs and actions), shape (n_states,)."""
    rows = activity[
        (activity["layer"] == layer) & (activity["probe"] == probe) & (activity["trial"] == trial)
    ]
    if rows.empty:
        raise CobelError(f"no {layer} activity of probe {probe} at trial {trial}")
    per_unit = rows.groupby("unit")["value"].mean().sort_index().to_numpy()
    return per_unit.reshape(-1, n_states).mean(axis=0)


def maze_walls(world) -> list[tuple[tuple[float, float], tuple[float, float], bool]]:
    """Wall segments between neighbouring cells, in image coordinates (x = column, y = row):
    ``((x0, y0), (x1, y1), one_way)``; ``one_way`` where only one direction is open."""
    ns = world.next_state
    if ns is None:
        return []
    h, w = world.height, world.width
    segs = []
    for r in range(h):
        for c in range(w):
            a = r * w + c
            for dr, dc in ((0, 1), (1, 0)):
                r2, c2 = r + dr, c + dc
                if r2 >= h or c2 >= w:
                    continue
                b = r2 * w + c2
                ab, ba = b in ns[a], a in ns[b]
                if ab and ba:
                    continue
                if dc:  # vertical segment between columns c and c + 1
                    seg = ((c + 0.5, r - 0.5), (c + 0.5, r + 0.5))
                else:
                    seg = ((c - 0.5, r + 0.5), (c + 0.5, r + 0.5))
                segs.append((*seg, ab != ba))
    return segs


def plot_sr_on_maze(sr: np.ndarray, world, ax, title: str = "", mask: np.ndarray | None = None):
    """Draw a per-state vector on the maze grid (masked cells grey, walls black, one-way doors
    dotted, start S and goal G marked). Returns the image."""
    import matplotlib as mpl

    h, w = world.height, world.width
    mask = world.blocked if mask is None else mask
    grid = np.ma.masked_array(sr.reshape(h, w), mask=np.asarray(mask).reshape(h, w))
    cmap = mpl.colormaps["viridis"].copy()
    cmap.set_bad("0.75")
    im = ax.imshow(grid, cmap=cmap, interpolation="nearest")
    for (x0, y0), (x1, y1), one_way in maze_walls(world):
        ax.plot([x0, x1], [y0, y1], color="k", lw=0.6 if one_way else 1.6,
                ls=":" if one_way else "-")  # fmt: skip
    ax.plot([-0.5, w - 0.5, w - 0.5, -0.5, -0.5], [-0.5, -0.5, h - 0.5, h - 0.5, -0.5],
            color="k", lw=1.6)  # fmt: skip
    places = getattr(world, "places", {}) or {}
    for name, letter in (("start", "S"), ("goal", "G")):
        if name in places:
            r, c = divmod(int(places[name]), w)
            ax.text(c, r, letter, ha="center", va="center", color="w", fontsize=8,
                    fontweight="bold")  # fmt: skip
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(title, fontsize=8)
    return im


def sr_snapshots(activity: pd.DataFrame, trials: pd.DataFrame) -> list[tuple[str, int]]:
    """(label, snapshot trial) for Fig. 7C: the latest snapshots at the end of the exploration
    phase and at the end of training."""
    snaps = np.sort(activity["trial"].unique())
    explore = trials.loc[trials["phase"] != REWARDED, "trial"]
    wanted = []
    if not explore.empty:
        wanted.append(("end of exploration", int(explore.max())))
    wanted.append(("end of training", int(trials["trial"].max())))
    out = []
    for label, t in wanted:
        before = snaps[snaps <= t]
        if before.size:
            out.append((label, int(before.max())))
    return out


def draw_fig7(
    groups: Mapping[str, pd.DataFrame],
    activity: pd.DataFrame | None = None,
    world=None,
    *,
    sr_group: str = "latent",
    layer: str = "sr/output",
):
    """Fig. 7B (+ 7C when ``activity`` of ``sr_group`` and its ``world`` are given).

    Returns ``(figure, table)``; the table is long format with ``panel`` ("7B" or "7C"),
    ``series`` (group, or SR snapshot), ``trial`` (aligned trial for 7B, snapshot trial for
    7C), ``state`` (7C), ``runs``, ``mean``, ``q25``, ``q75``.
    """
    import matplotlib.pyplot as plt

    snaps: list[tuple[str, int]] = []
    if activity is not None and world is not None and sr_group in groups:
        activity = activity[activity["layer"] == layer]
        snaps = sr_snapshots(activity, groups[sr_group])
    n = 1 + len(snaps)
    widths = [1.35] + [1.0] * len(snaps)
    fig, axes = plt.subplots(1, n, figsize=(3.6 + 3.0 * len(snaps), 2.6), squeeze=False,
                             constrained_layout=True, width_ratios=widths)  # fmt: skip
    ax_b = axes[0, 0]
    plot_latency_groups(groups, ax_b)
    ax_b.set_title("B  escape latency (mean, IQR)", fontsize=9, loc="left")
    summary = latency_summary(groups)
    table = [
        summary.rename(columns={"group": "series", "aligned_trial": "trial"}).assign(panel="7B")
    ]
    if snaps:
        assert activity is not None
        start = int(world.starts[0])
        reach = world.reachable()
        runs = activity["run"].nunique()
        for k, (label, trial) in enumerate(snaps, 1):
            sr = start_state_sr(activity, start, trial, world.n_states, layer)
            im = plot_sr_on_maze(sr, world, axes[0, k], mask=~reach,
                                 title=f"{'C  ' if k == 1 else ''}SR of start: {label}\n"
                                       f"(trial {trial}, mean of {runs} runs)")  # fmt: skip
            fig.colorbar(im, ax=axes[0, k], shrink=0.7)
            table.append(pd.DataFrame({"panel": "7C", "series": label, "trial": trial,
                                       "state": np.arange(world.n_states), "runs": runs,
                                       "mean": sr}))  # fmt: skip
    cols = ["panel", "series", "trial", "state", "runs", "mean", "q25", "q75"]
    out = pd.concat(table, ignore_index=True).reindex(columns=cols)
    return fig, out


def _load(run_dir: Path) -> pd.DataFrame:
    from cobelrun.results import load_trials

    return load_trials(run_dir)


def group_of(trials: pd.DataFrame) -> str:
    """``latent`` if the run has unrewarded trials before the rewarded phase, else ``direct``."""
    return "latent" if (trials["phase"] != REWARDED).any() else "direct"


def world_of(run_dir: str | Path):
    """The maze of a run folder, rebuilt from its ``config.yaml``."""
    from omegaconf import OmegaConf

    from cobelrun.config import instantiate

    cfg = OmegaConf.load(RunFolder(run_dir).config)
    return instantiate("env", cfg.env).unwrapped.world


def plot_run(run_dir: str | Path, out: str | Path | None = None, *others: str | Path) -> Path:
    """Fig. 7 for a run folder and optionally the other group's folder(s) into ``out``.

    Each folder's group is recognised from its phases (``latent`` has an exploration phase).
    With an ``activity.parquet`` holding ``sr/output`` in the latent group's folder, the SR of
    the start state is drawn at the end of exploration and at the end of training.
    """
    import matplotlib

    matplotlib.use("Agg")

    dirs = [Path(run_dir), *(Path(o) for o in others if o is not None)]
    groups: dict[str, pd.DataFrame] = {}
    folder: dict[str, Path] = {}
    for d in dirs:
        trials = _load(d)
        name = group_of(trials)
        if name in groups:
            raise CobelError(f"{folder[name]} and {d} are both {name} runs; give one of each")
        groups[name], folder[name] = trials, d
    activity = world = None
    latent_dir = folder.get("latent")
    if latent_dir is not None and RunFolder(latent_dir).table("activity").is_file():
        from cobelrun.results import load_table

        activity = load_table(latent_dir, "activity")
        world = world_of(latent_dir)
    fig, _ = draw_fig7(groups, activity, world)
    fig.suptitle("Latent learning in the Blodgett maze (Fig. 7)", fontsize=10)
    return save_figure(fig, Path(out) if out is not None else dirs[0] / "plot.png")
