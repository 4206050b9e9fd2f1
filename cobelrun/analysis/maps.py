"""Spatial activity maps: the probe grid, and maps as arrays from the ``activity_maps`` table.

An activity map is a unit's activation with the agent placed at each position of a regular grid
over the maze, facing each of a few headings (paper section 2.3.1). :func:`probe_grid` lays the
grid: ``nx x ny`` bins over the maze's bounding box, one probe position at each bin centre, and
the mask of the bins inside the maze (free cells of a gridworld-derived maze; the convex hull of
the nodes of a free-form graph such as the hexagonal maze). Only inside positions are probed.

``activity_maps.parquet`` (written by :class:`cobelrun.monitors.maps.ActivityMapMonitor`) is long
format: ``run, trial, layer, unit, heading, ix, iy, x, y, value`` with ``heading`` in degrees;
``activity_map_grid.parquet`` holds the grid, one row per bin (``ix, iy``, bin edges ``x0, x1,
y0, y1`` and ``explored``, the inside mask). :func:`load_activity_maps` reads both; :func:`maps_array` turns one snapshot into the
``(units, headings, ny, nx)`` array and ``(ny, nx)`` explored mask that
:func:`cobelrun.analysis.place_cells.place_cells` takes. Row ``iy = 0`` is the lowest ``y``
(plot with ``origin="lower"``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cobelrun.errors import CobelError, ConfigError

__all__ = [
    "GRID_TABLE",
    "MAPS_TABLE",
    "ProbeGrid",
    "load_activity_maps",
    "maps_array",
    "probe_grid",
    "spatial_distances",
]

#: Table names (``<name>.parquet`` in a run folder) of the maps and of their probe grid.
MAPS_TABLE = "activity_maps"
GRID_TABLE = "activity_map_grid"


@dataclass(frozen=True)
class ProbeGrid:
    """Probe positions of an activity map.

    Attributes
    ----------
    x_edges : (nx + 1,) float64
        Bin edges along x (world units).
    y_edges : (ny + 1,) float64
        Bin edges along y.
    inside : (ny, nx) bool
        Bins whose centre lies inside the maze (the explored area).
    """

    x_edges: np.ndarray
    y_edges: np.ndarray
    inside: np.ndarray

    @property
    def nx(self) -> int:
        return int(self.x_edges.size - 1)

    @property
    def ny(self) -> int:
        return int(self.y_edges.size - 1)

    @property
    def x_centres(self) -> np.ndarray:
        return (self.x_edges[:-1] + self.x_edges[1:]) / 2

    @property
    def y_centres(self) -> np.ndarray:
        return (self.y_edges[:-1] + self.y_edges[1:]) / 2

    def indices(self) -> tuple[np.ndarray, np.ndarray]:
        """``(ix, iy)`` of the inside bins, row-major (iy, then ix)."""
        iy, ix = np.nonzero(self.inside)
        return ix, iy

    def points(self) -> np.ndarray:
        """(M, 2) ``(x, y)`` of the inside bins' centres, in :meth:`indices` order."""
        ix, iy = self.indices()
        return np.stack([self.x_centres[ix], self.y_centres[iy]], axis=1)


def probe_grid(
    positions: np.ndarray,
    cells: bool = False,
    nx: int = 25,
    ny: int = 25,
    cell_size: float = 1.0,
) -> ProbeGrid:
    """The ``nx x ny`` probe grid over a maze.

    Parameters
    ----------
    positions : (N, 2) array
        Node positions (world units).
    cells : bool
        The nodes are the centres of square gridworld cells of side ``cell_size`` (walls around
        them): the grid spans the cells and a bin is inside if its centre lies in a node's cell.
        Otherwise (an open arena around a free-form graph) the grid spans the nodes' bounding
        box and a bin is inside if its centre lies in the nodes' convex hull.
    nx, ny : int
        Bins along x and y (default 25 x 25, as the paper).
    """
    for name, v in (("nx", nx), ("ny", ny)):
        if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 2:
            raise ConfigError(f"probe grid {name} must be an integer >= 2, got {v!r}")
    pos = np.asarray(positions, np.float64).reshape(-1, 2)
    half = cell_size / 2 if cells else 0.0
    lo, hi = pos.min(axis=0) - half, pos.max(axis=0) + half
    if np.any(hi - lo <= 0):
        raise ConfigError("probe grid: the maze has no extent in x or y")
    xe, ye = np.linspace(lo[0], hi[0], nx + 1), np.linspace(lo[1], hi[1], ny + 1)
    xc, yc = (xe[:-1] + xe[1:]) / 2, (ye[:-1] + ye[1:]) / 2
    gx, gy = np.meshgrid(xc, yc)  # (ny, nx)
    pts = np.stack([gx.ravel(), gy.ravel()], axis=1)
    if cells:
        d = np.abs(pts[:, None, :] - pos[None, :, :]).max(axis=2)
        inside = (d <= half + 1e-9).any(axis=1)
    elif pos.shape[0] >= 3 and np.linalg.matrix_rank(pos - pos.mean(axis=0)) == 2:
        from scipy.spatial import Delaunay

        inside = Delaunay(pos).find_simplex(pts, tol=1e-9) >= 0
    else:
        inside = np.ones(len(pts), bool)
    return ProbeGrid(xe, ye, inside.reshape(ny, nx))


def grid_from_table(df: pd.DataFrame) -> ProbeGrid:
    """The :class:`ProbeGrid` of an ``activity_map_grid`` table (one row per bin)."""
    nx, ny = int(df["ix"].max()) + 1, int(df["iy"].max()) + 1
    if len(df) != nx * ny:
        raise CobelError(f"probe grid table has {len(df)} rows for a {nx} x {ny} grid")
    xs = df.drop_duplicates("ix").sort_values("ix")
    ys = df.drop_duplicates("iy").sort_values("iy")
    inside = np.zeros((ny, nx), bool)
    inside[df["iy"].to_numpy(), df["ix"].to_numpy()] = df["explored"].to_numpy(bool)
    x_edges = np.append(xs["x0"].to_numpy(), xs["x1"].to_numpy()[-1])
    y_edges = np.append(ys["y0"].to_numpy(), ys["y1"].to_numpy()[-1])
    return ProbeGrid(x_edges, y_edges, inside)


def load_activity_maps(run_dir: str | Path) -> tuple[pd.DataFrame, ProbeGrid]:
    """``activity_maps.parquet`` of a run folder and its probe grid."""
    run_dir = Path(run_dir)
    paths = [run_dir / f"{name}.parquet" for name in (MAPS_TABLE, GRID_TABLE)]
    for p in paths:
        if not p.is_file():
            raise CobelError(f"{run_dir} has no {p.name} (no activity-map monitor)")
    try:
        maps, grid = (pd.read_parquet(p) for p in paths)
    except Exception as exc:
        raise CobelError(f"cannot read the activity maps of {run_dir}: {exc}") from None
    return maps, grid_from_table(grid)


def maps_array(
    df: pd.DataFrame, grid: ProbeGrid
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One snapshot's rows -> ``(maps, explored, units, headings_deg)``.

    ``df`` holds the rows of one (run, trial, layer). ``maps`` is ``(units, headings, ny, nx)``
    float64 with NaN outside the probed bins; ``explored`` the grid's inside mask.
    """
    for col in ("run", "trial", "layer"):
        if col in df and df[col].nunique() > 1:
            raise ConfigError(f"maps_array takes one snapshot; the rows have several {col}s")
    units = np.unique(df["unit"].to_numpy())
    heads = np.unique(df["heading"].to_numpy())
    u = np.searchsorted(units, df["unit"].to_numpy())
    h = np.searchsorted(heads, df["heading"].to_numpy())
    maps = np.full((units.size, heads.size, grid.ny, grid.nx), np.nan)
    maps[u, h, df["iy"].to_numpy(), df["ix"].to_numpy()] = df["value"].to_numpy()
    return maps, grid.inside.copy(), units, heads.astype(np.float64)


def spatial_distances(grid: ProbeGrid) -> np.ndarray:
    """(M, M) Euclidean distances between the inside probe positions (world units)."""
    p = grid.points()
    return np.hypot(*(p[:, None, :] - p[None, :, :]).transpose(2, 0, 1))


def classify_snapshots(
    df: pd.DataFrame,
    grid: ProbeGrid,
    layer: str | None = None,
    criterion: Any = None,
    rsa: bool = True,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Classify every snapshot of an ``activity_maps`` table.

    Returns ``(units, snapshots)``: ``units`` has one row per (run, trial, unit) with the
    columns of :func:`cobelrun.analysis.place_cells.place_cells`; ``snapshots`` one row per
    (run, trial) with ``place_cells``, ``units``, ``place_cell_fraction``, the median
    ``spatial_information`` and (``rsa=True``) ``rsa_spatial``: the Spearman correlation of
    the population RDM with the spatial-distance RDM (:func:`cobelrun.analysis.rsa.spatial_rsa`).
    ``layer`` default: the table's only layer.
    """
    from cobelrun.analysis.place_cells import place_cells

    layers = df["layer"].unique()
    if layer is None:
        if len(layers) != 1:
            raise ConfigError(f"the table has layers {sorted(layers)}; pick one with layer=")
        layer = str(layers[0])
    elif layer not in layers:
        raise ConfigError(f"layer {layer!r} is not in the table; it has {sorted(layers)}")
    rows, per_unit = [], []
    points = grid.points()
    for (run, trial), snap in df[df["layer"] == layer].groupby(["run", "trial"], sort=True):
        maps, explored, units, heads = maps_array(snap, grid)
        pc = place_cells(maps, explored, criterion, headings_rad=np.deg2rad(heads))
        pc.insert(0, "trial", int(trial))
        pc.insert(0, "run", int(run))
        pc["unit"] = units
        per_unit.append(pc)
        row = {
            "run": int(run),
            "trial": int(trial),
            "place_cells": int(pc["is_place_cell"].sum()),
            "units": len(units),
            "place_cell_fraction": float(pc["is_place_cell"].mean()),
            "spatial_information_median": float(pc["spatial_information"].median()),
        }
        if rsa:
            from cobelrun.analysis.rsa import spatial_rsa

            row["rsa_spatial"] = spatial_rsa(maps, explored, points)
        rows.append(row)
    return pd.concat(per_unit, ignore_index=True), pd.DataFrame(rows)
