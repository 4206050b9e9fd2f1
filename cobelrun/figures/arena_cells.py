"""Rate maps of an arena's spatial cells (``cobel plot RUN --kind rate`` for 2D arena runs).

A continuous arena (``cobel/Continuous2D-v0``) observes the world through populations of
spatial cells (:mod:`cobelrun.envs.cells`: place cells, grid cells, boundary vector cells).
Their layout is fixed when the env is built (the same in every run of a folder), so their
rate maps come from the env the run's ``config.yaml`` builds: its ``env`` node only, validated
and instantiated through the instantiation gate (:func:`cobelrun.config.instantiate`, as
``cobel show`` builds an env); no agent is built and nothing runs. Each cell's rate is evaluated (:meth:`~cobelrun.envs.cells.SpatialCode.rates`)
on a regular grid of poses over the arena, facing east; bins outside the free space are blank.

Head-direction cells (no spatial field), the pose code and the camera view have no rate map.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from cobelrun.errors import CobelError
from cobelrun.io.run_folder import RunFolder

__all__ = ["SPATIAL_KINDS", "cell_rate_maps", "has_spatial_cells", "plot_cell_rate_maps"]

#: observation parts with a spatial field (``observation[i].kind``)
SPATIAL_KINDS = ("place_cells", "grid_cells", "boundary_vector_cells")
#: bins per side of a rate map
BINS = 50


def _observation_kinds(run_dir: Path) -> list[str]:
    """The ``kind`` of each part of the env's observation in ``config.yaml`` (read as data)."""
    from omegaconf import OmegaConf

    path = RunFolder(run_dir).config
    if not path.is_file():
        return []
    try:
        env = OmegaConf.to_container(OmegaConf.load(path).get("env") or {}, resolve=False)
    except Exception:  # a damaged config: this kind is simply not offered
        return []
    if not isinstance(env, dict) or "Continuous2D" not in str(env.get("_target_", "")):
        return []
    parts = env.get("observation")
    if not isinstance(parts, list):
        return []
    return [str(p.get("kind")) for p in parts if isinstance(p, dict)]


def has_spatial_cells(run_dir: str | Path) -> bool:
    """Whether the run's env is an arena observed through place, grid or boundary cells."""
    return any(k in SPATIAL_KINDS for k in _observation_kinds(Path(run_dir)))


def cell_rate_maps(env: Any, per_population: int = 8, bins: int = BINS) -> list[dict[str, Any]]:
    """Rate maps of up to ``per_population`` cells of each spatial population of ``env``.

    Returns
    -------
    list of dict
        One per cell: ``population`` (the part's kind), ``cell`` (index within it),
        ``rate`` ((bins, bins) array, row 0 the lowest y; NaN outside the free space),
        ``extent`` (x0, x1, y0, y1).
    """
    base = env.unwrapped
    x0, y0, x1, y1 = base.arena.bounds
    xs = np.linspace(x0, x1, bins + 1)
    ys = np.linspace(y0, y1, bins + 1)
    cx, cy = np.meshgrid((xs[:-1] + xs[1:]) / 2, (ys[:-1] + ys[1:]) / 2)
    xy = np.column_stack([cx.ravel(), cy.ravel()])
    free = np.asarray(base.arena.is_free(xy), bool)
    poses = np.column_stack([xy, np.zeros(len(xy))])
    out = []
    for part in base.observation_parts:
        if getattr(part, "kind", None) not in SPATIAL_KINDS:
            continue
        rates = np.asarray(part.rates(poses), np.float64)  # (bins * bins, n)
        for c in np.unique(np.linspace(0, part.n - 1, min(per_population, part.n)).round()):
            r = rates[:, int(c)].copy()
            r[~free] = np.nan
            out.append({"population": part.kind, "cell": int(c), "rate": r.reshape(bins, bins),
                        "extent": (x0, x1, y0, y1)})  # fmt: skip
    return out


def plot_cell_rate_maps(run_dir: str | Path, per_population: int = 8) -> Any:
    """The figure of :func:`cell_rate_maps` for a run folder's arena (one panel per cell)."""
    import matplotlib.pyplot as plt
    from omegaconf import OmegaConf

    from cobelrun.config import instantiate

    run_dir = Path(run_dir)
    if not has_spatial_cells(run_dir):
        raise CobelError(f"{run_dir}: its env is not an arena observed through "
                         f"{', '.join(SPATIAL_KINDS)}")  # fmt: skip
    env = instantiate("env", OmegaConf.load(RunFolder(run_dir).config).env)
    try:
        maps = cell_rate_maps(env, per_population)
        outline = env.unwrapped.geometry().outline
    finally:
        env.close()
    cols = min(4, len(maps))
    rows = int(np.ceil(len(maps) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(2.4 * cols, 2.2 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.set_axis_off()
    for ax, m in zip(axes.ravel(), maps, strict=False):
        ax.set_axis_on()
        im = ax.imshow(m["rate"], origin="lower", extent=m["extent"], cmap="jet")
        if len(outline):
            ring = np.vstack([outline, outline[:1]])
            ax.plot(ring[:, 0], ring[:, 1], color="0.2", lw=0.8)
        bar = fig.colorbar(im, ax=ax, fraction=0.046)
        bar.ax.tick_params(labelsize=6)
        bar.set_label("rate", fontsize=7)
        ax.set_title(f"{m['population'].replace('_', ' ')} {m['cell']}", fontsize=8)
        ax.set_xlabel("x [m]", fontsize=7)
        ax.set_ylabel("y [m]", fontsize=7)
        ax.tick_params(labelsize=6)
    fig.suptitle(f"rate maps of the arena's cells (the env's observation; facing east), "
                 f"{len(maps)} cells", fontsize=9)  # fmt: skip
    return fig
