"""Plots for any run, sweep or set of runs, drawn from the saved tables and geometry.

Learning curves (``plot_curves``: one curve per group, mean and 95% confidence band over
independent runs, the n of each curve in its label), occupancy maps and trajectories on a
run's saved ``world.json`` (never re-composing configs), and the maze/arena/graph itself
(``draw_geometry``, ``ascii_geometry`` for ``cobel show``). Functions take data frames and an
``ax``; the ``plot_*_file`` helpers read folders and write PNGs.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cobelrun.errors import CobelError
from cobelrun.io.run_folder import RunFolder

#: ``cobel plot RUN --kind`` choices
KINDS = ("occupancy", "trajectories", "latency", "response", "reward")

#: kind -> (trials column, y label)
CURVES = {
    "latency": ("steps", "escape latency [steps]"),
    "response": ("cumulative_response", "cumulative responses"),
    "reward": ("reward", "reward"),
}


# -- learning curves -----------------------------------------------------------------------
def curve_stats(trials: pd.DataFrame, column: str, units: Sequence[str] = ("run",)) -> pd.DataFrame:
    """Per trial: mean, n and 95% confidence interval (t distribution) of ``column`` over the
    independent units (``run``; ``job, run`` in a sweep).

    Returns
    -------
    pandas.DataFrame
        Index ``trial``; columns ``mean``, ``n``, ``lo``, ``hi``.
    """
    from cobelrun.figures.bands import mean_ci

    if column not in trials:
        raise CobelError(f"the trials table has no {column!r} column; it has: "
                         f"{', '.join(map(str, trials.columns))}")  # fmt: skip
    per_unit = trials.groupby([*units, "trial"], sort=False)[column].mean().reset_index()
    return mean_ci(per_unit.groupby("trial")[column])


def plot_curves(
    trials: pd.DataFrame,
    column: str,
    ax: Any,
    *,
    hue: str | None = None,
    units: Sequence[str] = ("run",),
    label: str | None = None,
    ylabel: str | None = None,
) -> list[tuple[str, int]]:
    """Mean ``column`` per trial with a 95% confidence band (clipped to the range the measure
    can take: :mod:`cobelrun.figures.bands`), one curve per ``hue`` value.

    Parameters
    ----------
    trials
        A trials table (a run, a sweep from ``cobelrun.load_sweep`` or several runs).
    column
        The column to draw (``reward``, ``steps``, ``cumulative_response``, ...).
    ax
        A matplotlib ``Axes``.
    hue
        A column whose values get their own curve (a swept key such as ``agent.epsilon``).
    units
        The columns that identify one independent sample (``run``; ``job, run`` for sweeps).
    label, ylabel
        Curve label (without hue) and y-axis label.

    Returns
    -------
    list of (label, n)
        Each curve's label and its number of independent units.
    """
    import matplotlib.pyplot as plt

    from cobelrun.figures.bands import BAND, clip_to_measure
    from cobelrun.figures.extinction import _mark_phases

    groups = [(None, trials)] if hue is None else list(trials.groupby(hue, sort=True))
    colors = plt.get_cmap("viridis" if len(groups) > 3 else "tab10")
    drawn = []
    for i, (value, part) in enumerate(groups):
        s = curve_stats(part, column, units)
        n = int(s["n"].max())
        name = label or column if hue is None else f"{hue}={value}"
        color = colors(i / max(1, len(groups) - 1)) if len(groups) > 3 else colors(i)
        ax.plot(s.index, s["mean"], color=color, lw=1.4, label=f"{name} (n={n}, {BAND})")
        # the band drawn stays inside the range the measure can take (at small n the t
        # interval reaches negative latencies or more responses than trials)
        lo, hi = clip_to_measure(column, s.index.to_numpy(), s["lo"], s["hi"], part[column])
        ax.fill_between(s.index, lo, hi, color=color, alpha=0.25, lw=0)
        drawn.append((str(name), n))
    if "phase" in trials:
        _mark_phases(ax, trials)
    ax.set_xlabel("trial")
    ax.set_ylabel(ylabel or column)
    ax.legend(loc="best")
    return drawn


def _curve_column(trials: pd.DataFrame, y: str | None) -> tuple[str, str]:
    if y is not None:
        column, ylabel = CURVES.get(y, (y, y))
        return column, ylabel
    for kind in ("response", "latency", "reward"):
        column, ylabel = CURVES[kind]
        if column in trials:
            return column, ylabel
    raise CobelError("the trials table has none of the columns cumulative_response, steps, reward")


def plot_sweep_file(
    sweep_dir: str | Path,
    hue: str | None = None,
    y: str | None = None,
    out: str | Path | None = None,
) -> Path:
    """``cobel plot SWEEP_DIR --hue KEY``: one curve per value of a swept key, n = jobs x runs."""
    import matplotlib.pyplot as plt

    from cobelrun.figures import save_figure
    from cobelrun.io.sweep_folder import read_sweep
    from cobelrun.results import load_sweep

    sweep_dir = Path(sweep_dir)
    info = read_sweep(sweep_dir)
    swept = info["swept"]
    tasks = [a.split("=", 1)[1] for a in str(info.get("command") or "").split()
             if a.startswith("task=")]  # fmt: skip
    if hue is not None and hue not in swept:
        from cobelrun.errors import allowed_list, suggest

        raise CobelError(f"--hue {hue!r} is not a swept key{suggest(hue, swept)}; "
                         f"swept: {allowed_list(swept) or 'none'}")  # fmt: skip
    trials = load_sweep(sweep_dir)
    column, ylabel = _curve_column(trials, y)
    fig, ax = plt.subplots(figsize=(5.5, 3.5))
    plot_curves(trials, column, ax, hue=hue, units=("job", "run"), ylabel=ylabel)
    ax.set_title(f"{tasks[0] if tasks else sweep_dir.name}: swept {', '.join(swept) or 'nothing'}"
                 + (f", by {hue}" if hue else ""), fontsize=9)  # fmt: skip
    fig.tight_layout()
    default = sweep_dir / ("plot.png" if y is None else f"plot_{y}.png")  # --y names its file
    return save_figure(fig, Path(out) if out else default)


def compare_file(
    run_dirs: Sequence[str | Path], y: str | None = None, out: str | Path | None = None,
    labels: Sequence[str] | None = None,
) -> Path:  # fmt: skip
    """``cobel compare RUN_A RUN_B ...``: the runs' curves overlaid, one colour each."""
    import matplotlib.pyplot as plt

    from cobelrun.figures import save_figure
    from cobelrun.results import load_trials

    if len(run_dirs) < 2:
        raise CobelError("cobel compare takes at least two run folders")
    names = list(labels) if labels else [Path(d).name for d in run_dirs]
    if len(names) != len(run_dirs):
        raise CobelError(f"{len(names)} labels for {len(run_dirs)} run folders")
    frames = [load_trials(d).assign(source=name) for d, name in zip(run_dirs, names, strict=True)]
    trials = pd.concat(frames, ignore_index=True)
    column, ylabel = _curve_column(trials, y)
    fig, ax = plt.subplots(figsize=(5.5, 3.5))
    plot_curves(trials, column, ax, hue="source", units=("source", "run"), ylabel=ylabel)
    fig.tight_layout()
    default = "compare.png" if y is None else f"compare_{y}.png"  # --y names its file
    return save_figure(fig, Path(out) if out else Path(run_dirs[0]) / default)


# -- geometry ----------------------------------------------------------------------------------
def load_geometry(run_dir: str | Path) -> Any:
    """A run's saved geometry (``world.json``) as :class:`cobelrun.envs.base.Geometry`."""
    from cobelrun.io.validate import read_world

    path = RunFolder(run_dir).world
    if not path.is_file():
        raise CobelError(f"{Path(run_dir)} has no {RunFolder.WORLD} (the env has no geometry)")
    return read_world(path)


def draw_geometry(geometry: Any, ax: Any, *, labels: bool = True) -> None:
    """Draw walls, one-way doors, free cells, graph nodes/edges, arena outline and named
    regions on ``ax``. A door is a dashed segment with an arrow across it in the direction it
    can be passed (:func:`draw_doors`)."""
    from matplotlib.collections import LineCollection
    from matplotlib.patches import Polygon, Rectangle

    cs = geometry.cell_size
    for x, y in geometry.cells:
        ax.add_patch(Rectangle((x - cs / 2, y - cs / 2), cs, cs, fc="0.95", ec="0.85", lw=0.5))
    if len(geometry.outline):
        ax.add_patch(Polygon(geometry.outline, closed=True, fill=False, ec="0.2", lw=1.2))
    if len(geometry.walls):
        segs = geometry.walls.reshape(-1, 2, 2)
        ax.add_collection(LineCollection(segs, colors="0.15", linewidths=1.5))
    draw_doors(geometry, ax)
    if geometry.kind == "graph" and len(geometry.nodes):
        if len(geometry.edges):
            segs = geometry.nodes[geometry.edges]
            ax.add_collection(LineCollection(segs, colors="0.6", linewidths=0.8))
        ax.scatter(geometry.nodes[:, 0], geometry.nodes[:, 1], s=8, color="0.3", zorder=3)
    for name, region in geometry.regions.items():
        if region.get("shape") == "polygon":
            ax.add_patch(Polygon(region["points"], closed=True, fc="tab:orange", alpha=0.2))
            x, y = np.mean(np.asarray(region["points"], float), axis=0)
        else:
            x, y = region["x"], region["y"]
            if region.get("shape") == "circle":
                from matplotlib.patches import Circle

                ax.add_patch(Circle((x, y), region["radius"], fc="tab:orange", alpha=0.25))
            else:
                ax.plot(x, y, "*", color="tab:orange", ms=8, zorder=4)
        if labels:
            ax.annotate(name, (x, y), xytext=(3, 3), textcoords="offset points", fontsize=7)
    x0, y0, x1, y1 = geometry.bounds
    pad = 0.05 * max(x1 - x0, y1 - y0, 1e-9)
    ax.set_xlim(x0 - pad, x1 + pad)
    ax.set_ylim(y0 - pad, y1 + pad)
    ax.set_aspect("equal")


#: colour of one-way doors in every picture of a maze
DOOR_COLOR = "tab:purple"


def draw_doors(geometry: Any, ax: Any) -> None:
    """One-way doors (``geometry.doors``) as dashed segments, each with an arrow from one side
    to the other in the direction the door can be passed."""
    from matplotlib.collections import LineCollection

    doors = getattr(geometry, "doors", np.zeros((0, 6)))
    if not len(doors):
        return
    ax.add_collection(LineCollection(doors[:, :4].reshape(-1, 2, 2), colors=DOOR_COLOR,
                                     linewidths=1.5, linestyles=(0, (2, 1.5)), zorder=2.5,
                                     label="one-way door"))  # fmt: skip
    size = 0.3 * geometry.cell_size
    for x0, y0, x1, y1, dx, dy in doors.tolist():
        mx, my = (x0 + x1) / 2, (y0 + y1) / 2
        ax.annotate("", xy=(mx + size * dx, my + size * dy), xytext=(mx - size * dx, my - size * dy),
                    arrowprops={"arrowstyle": "-|>", "color": DOOR_COLOR, "lw": 1.0,
                                "shrinkA": 0, "shrinkB": 0}, zorder=2.6)  # fmt: skip


def occupancy(steps: pd.DataFrame, geometry: Any, bins: int = 30) -> tuple[np.ndarray, ...]:
    """Visits per spatial bin: grid cells for grids, ``bins`` x ``bins`` for arenas/graphs.

    A visit is each step's pose and each trial's arrival (the pose after its last step, where
    the steps table records it: :func:`cobelrun.analysis.paths.visited_poses`), so the goal
    cell of a trial that reached it counts.

    Returns
    -------
    (counts, xedges, yedges)
        ``counts[i, j]`` visits with x in bin i and y in bin j.
    """
    from cobelrun.analysis.paths import visited_poses

    x0, y0, x1, y1 = geometry.bounds
    if geometry.kind == "grid" and len(geometry.cells):
        cs = geometry.cell_size
        cx, cy = np.unique(geometry.cells[:, 0]), np.unique(geometry.cells[:, 1])
        xedges = np.arange(cx.min() - cs / 2, cx.max() + cs, cs)
        yedges = np.arange(cy.min() - cs / 2, cy.max() + cs, cs)
    else:
        xedges, yedges = np.linspace(x0, x1, bins + 1), np.linspace(y0, y1, bins + 1)
    poses = visited_poses(steps)
    counts, xe, ye = np.histogram2d(poses["x"], poses["y"], bins=(xedges, yedges))
    return counts, xe, ye


#: what a figure drawn from a steps table without ``next_*`` columns says about itself
NO_ARRIVALS = (
    "older run folder: poses before each step only (the cells trials ended in are missing)"
)


def _note_no_arrivals(steps: pd.DataFrame, ax: Any) -> None:
    """Say on the figure when the steps table lacks the arrival poses."""
    from cobelrun.analysis.paths import has_arrivals

    if len(steps) and not has_arrivals(steps):
        ax.text(0.0, -0.18, NO_ARRIVALS, transform=ax.transAxes, fontsize=6, color="0.35",
                va="top")  # fmt: skip


def plot_occupancy(steps: pd.DataFrame, geometry: Any, ax: Any) -> None:
    """Share of visited poses (steps and arrivals) in each place, on the maze."""
    counts, xe, ye = occupancy(steps, geometry)
    share = np.ma.masked_equal(counts / max(1.0, counts.sum()), 0.0)
    draw_geometry(geometry, ax, labels=True)
    mesh = ax.pcolormesh(xe, ye, share.T, cmap="magma_r", alpha=0.85, zorder=2)
    unit = "cell" if geometry.kind == "grid" else "bin"
    ax.figure.colorbar(mesh, ax=ax, label=f"share of visits per {unit}")
    ax.set_title("occupancy")
    _axis_units(geometry, ax)
    _note_no_arrivals(steps, ax)


def plot_trajectories(
    steps: pd.DataFrame, geometry: Any, ax: Any, *, run: int = 0, count: int = 8
) -> None:
    """``count`` trials of run ``run``, evenly spread over the run, coloured by trial; each
    path runs from the trial's start to where its last step led (circle: start, square: end)."""
    import matplotlib.pyplot as plt

    from cobelrun.analysis.paths import visited_poses

    part = steps[steps["run"] == run]
    if part.empty:
        raise CobelError(f"no recorded steps for run {run}")
    poses = visited_poses(part)
    trials = np.unique(part["trial"])
    chosen = trials[np.linspace(0, len(trials) - 1, min(count, len(trials))).round().astype(int)]
    draw_geometry(geometry, ax, labels=True)
    cmap = plt.get_cmap("viridis")
    for i, t in enumerate(np.unique(chosen)):
        tr = poses[poses["trial"] == t]
        jitter = (i - len(chosen) / 2) * 0.02 * geometry.cell_size
        color = cmap(i / max(1, len(chosen) - 1))
        x, y = tr["x"].to_numpy() + jitter, tr["y"].to_numpy() + jitter
        ax.plot(x, y, color=color, lw=1.2, alpha=0.9, zorder=3, label=f"trial {t}")
        ax.plot(x[:1], y[:1], "o", color=color, ms=3, zorder=4)
        ax.plot(x[-1:], y[-1:], "s", color=color, ms=3, zorder=4)
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0))
    ax.set_title(f"trajectories, run {run}")
    _axis_units(geometry, ax)
    _note_no_arrivals(part, ax)


def _axis_units(geometry: Any, ax: Any) -> None:
    """x/y labels with the layout's unit: grid cells, or world units (m) of arenas/graphs."""
    unit = "cells" if geometry.kind == "grid" else "m"
    ax.set_xlabel(f"x [{unit}]")
    ax.set_ylabel(f"y [{unit}]")


def plot_kind(run_dir: str | Path, kind: str, out: str | Path | None = None) -> Path:
    """``cobel plot RUN --kind KIND``: occupancy, trajectories or a learning curve."""
    import matplotlib.pyplot as plt

    from cobelrun.errors import allowed_list, suggest
    from cobelrun.figures import save_figure
    from cobelrun.results import load_steps, load_trials

    if kind not in KINDS:
        raise CobelError(f"unknown plot kind {kind!r}{suggest(kind, KINDS)}; allowed: "
                         f"{allowed_list(KINDS)}")  # fmt: skip
    run_dir = Path(run_dir)
    fig, ax = plt.subplots(figsize=(5.5, 4.0))
    try:
        if kind in CURVES:
            column, ylabel = CURVES[kind]
            plot_curves(load_trials(run_dir), column, ax, ylabel=ylabel, label=kind)
        else:
            geometry = load_geometry(run_dir)
            steps = load_steps(run_dir)
            draw = plot_occupancy if kind == "occupancy" else plot_trajectories
            draw(steps, geometry, ax)
        from cobelrun.figures.titles import run_title

        ax.set_title(f"{run_title(run_dir)}: {ax.get_title() or kind}", fontsize=9)
    except BaseException:
        plt.close(fig)
        raise
    fig.tight_layout()
    return save_figure(fig, Path(out) if out else run_dir / f"plot_{kind}.png")


# -- ASCII -------------------------------------------------------------------------------------
def ascii_geometry(geometry: Any, width: int = 60) -> str:
    """A terminal drawing: grids cell by cell (``.`` free, ``#`` blocked, a region's first
    letter at its place); arenas and graphs on a character raster (``o`` node, ``.`` inside)."""
    x0, y0, x1, y1 = geometry.bounds
    marks = {}
    if geometry.kind == "grid" and len(geometry.cells):
        cs = geometry.cell_size
        xs = np.unique(geometry.cells[:, 0])
        ys = np.unique(geometry.cells[:, 1])
        ncol = round((xs.max() - xs.min()) / cs) + 1
        nrow = round((ys.max() - ys.min()) / cs) + 1
        grid = [["#"] * ncol for _ in range(nrow)]

        def at(x: float, y: float) -> tuple[int, int]:
            return round((ys.max() - y) / cs), round((x - xs.min()) / cs)

        for x, y in geometry.cells:
            r, c = at(x, y)
            grid[r][c] = "."
    else:
        ncol = width
        nrow = max(4, round(width * (y1 - y0) / max(x1 - x0, 1e-9) / 2))
        grid = [[" "] * ncol for _ in range(nrow)]

        def at(x: float, y: float) -> tuple[int, int]:
            c = round((x - x0) / max(x1 - x0, 1e-9) * (ncol - 1))
            r = round((y1 - y) / max(y1 - y0, 1e-9) * (nrow - 1))
            return min(max(r, 0), nrow - 1), min(max(c, 0), ncol - 1)

        if len(geometry.outline):
            from matplotlib.path import Path as MplPath

            poly = MplPath(geometry.outline)
            for r in range(nrow):
                for c in range(ncol):
                    x = x0 + c / (ncol - 1) * (x1 - x0)
                    y = y1 - r / max(nrow - 1, 1) * (y1 - y0)
                    if poly.contains_point((x, y)):
                        grid[r][c] = "."
        for x, y in geometry.nodes:
            r, c = at(x, y)
            grid[r][c] = "o"
    for name, region in geometry.regions.items():
        if "x" in region:
            r, c = at(region["x"], region["y"])
        else:
            r, c = at(*np.mean(np.asarray(region["points"], float), axis=0))
        letter = name[0].upper()
        grid[r][c] = letter
        marks.setdefault(letter, []).append(name)
    legend = "  ".join(f"{k}: {', '.join(v)}" for k, v in marks.items())
    return "\n".join("".join(row) for row in grid) + ("\n" + legend if legend else "")
