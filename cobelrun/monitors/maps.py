"""Spatial activity maps of deep agents: unit activations over a grid of poses in the maze.

:class:`ActivityMapMonitor` places the agent (in thought: the environment is not stepped) at
every position of a probe grid (:func:`cobelrun.analysis.maps.probe_grid`, default 25 x 25 over
the maze, only positions inside it) facing each of ``headings`` directions, feeds the views
through the agent's network and records the chosen layers' units. Snapshots are taken before
training (trial 0), after every ``every``-th trial (default 800, Fig. 8) and after the last
trial.

The views do not change during a run (the scene is fixed), so they are produced once per process:
rendered online with pybullet at poses between the graph nodes (``render_at_pose``), or read from
the render cache when the environment renders offline (``cobel render-cache`` builds the probe
grid's cache for tasks with this monitor). A snapshot is then only forward passes.

Rows go to ``activity_maps.parquet``: ``run, trial, layer, unit, heading`` (degrees), ``ix, iy``
(grid bin), ``x, y`` (world units), ``value``; the grid with its inside mask goes to
``activity_map_grid.parquet`` (one row per bin: ``ix, iy, x0, x1, y0, y1, explored``), read
back by :func:`cobelrun.analysis.maps.load_activity_maps`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
import pyarrow as pa

from cobelrun.analysis.maps import GRID_TABLE, MAPS_TABLE, ProbeGrid, probe_grid
from cobelrun.envs.base import ObservesGrid, supports
from cobelrun.errors import ConfigError
from cobelrun.monitors.activity import ActivityMonitor, HasActivations
from cobelrun.monitors.base import SceneGrid, Table
from cobelrun.safety import check_allocation

#: the run's log (``cobel.log``; warnings also on stderr)
LOG = logging.getLogger("cobel")


class ActivityMapMonitor(ActivityMonitor):
    """Record layer activations over a grid of positions x headings every ``every`` trials.

    Parameters
    ----------
    layers
        Layer names (the agent's ``layer_names()``); default ``["analysis"]`` where the agent has
        it (the dense layer of a CNN DQN, Fig. 8), else a ConfigError listing the layers.
    every
        Snapshot after every N-th trial (default 800, Fig. 8), plus trial 0 and the last trial.
    grid
        ``[nx, ny]`` probe bins over the maze's bounding box (default ``[25, 25]``).
    headings
        Number of evenly spaced headings from 0 degrees (default 6: 0, 60, ..., 300), or a list
        of angles in degrees.
    batch_size
        Views per forward pass.
    """

    #: a run's snapshot bookkeeping and whether the grid rows are written, kept by checkpoints
    checkpoint_fields: ClassVar[tuple[str, ...]] = ("_run", "_last", "layers", "_grid_written")

    requires = ("observe_grid",)

    def __init__(
        self,
        layers: Sequence[str] | None = None,
        every: int = 800,
        grid: Sequence[int] = (25, 25),
        headings: int | Sequence[float] = 6,
        batch_size: int = 1024,
    ) -> None:
        super().__init__(layers=layers, every=every, probes=None)
        if (
            isinstance(grid, str)
            or not hasattr(grid, "__len__")
            or len(grid) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 2 for v in grid)
        ):
            raise ConfigError(f"activity maps 'grid' must be [nx, ny] integers >= 2, got {grid!r}")
        self.nx, self.ny = int(grid[0]), int(grid[1])
        check_allocation("task.monitors (activity maps grid)", self.nx * self.ny * 64 * 8,
                         f"activity maps on a {self.nx:,} x {self.ny:,} grid",
                         "use a coarser grid")  # fmt: skip
        if isinstance(headings, int) and not isinstance(headings, bool):
            if headings < 1:
                raise ConfigError(f"activity maps 'headings' must be >= 1, got {headings}")
            self.headings_deg = np.arange(headings) * (360.0 / headings)
        else:
            try:
                self.headings_deg = np.asarray([float(h) for h in headings])  # type: ignore[union-attr]
            except (TypeError, ValueError):
                raise ConfigError(
                    f"activity maps 'headings' must be a count or a list of degrees, got {headings!r}"
                ) from None
            if self.headings_deg.size == 0:
                raise ConfigError("activity maps 'headings' must not be empty")
        if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
            raise ConfigError(f"activity maps 'batch_size' must be >= 1, got {batch_size!r}")
        self.batch_size = batch_size
        self.grid: ProbeGrid | None = None
        self.env: Any = None
        self._views: Any = None
        #: seconds spent producing the probe views (rendering or reading the cache)
        self.view_seconds: float | None = None
        #: seconds of each snapshot's forward passes and row building
        self.snapshot_seconds: list[float] = []
        self._grid_written = False
        #: (run, layer) pairs already reported as silent (one warning each)
        self._silent_reported: set[tuple[int, str]] = set()
        #: snapshots awaiting run.mcap / the live view (:meth:`scene_grids`; the newest kept)
        self._grids: list[SceneGrid] = []

    # -- wiring ------------------------------------------------------------------------------
    def setup(self, env: Any) -> None:
        base = env.unwrapped
        if not supports(base, ObservesGrid) or base.topology is None:
            raise ConfigError(
                f"activity maps need an environment that renders at any pose (a topology env); "
                f"{type(base).__name__} does not"
            )
        self.env = base
        topology = base.topology
        self.grid = probe_grid(
            topology.positions, cells=topology.cells is not None, nx=self.nx, ny=self.ny
        )

    @property
    def headings_rad(self) -> np.ndarray:
        return np.deg2rad(self.headings_deg)

    def cache_requests(self, env: Any) -> list[Any]:
        """Render-cache requests of the probe grid (for ``cobel render-cache``)."""
        self.setup(env)
        assert self.grid is not None
        module = env.unwrapped.observation_module
        return [
            im.cache_request(self.grid.points(), self.headings_rad) for im in module.image_modules()
        ]

    def fields(self) -> list[pa.Field]:
        """Columns of ``activity_maps``."""
        return [
            pa.field("run", pa.int32()),
            pa.field("trial", pa.int32()),
            pa.field("layer", pa.string()),
            pa.field("unit", pa.int32()),
            pa.field("heading", pa.float32()),
            pa.field("ix", pa.int16()),
            pa.field("iy", pa.int16()),
            pa.field("x", pa.float32()),
            pa.field("y", pa.float32()),
            pa.field("value", pa.float32()),
        ]

    def tables(self) -> list[Table]:
        grid = (
            pa.field("ix", pa.int16()), pa.field("iy", pa.int16()),
            pa.field("x0", pa.float64()), pa.field("x1", pa.float64()),
            pa.field("y0", pa.float64()), pa.field("y1", pa.float64()),
            pa.field("explored", pa.bool_()),
        )  # fmt: skip
        return [Table(MAPS_TABLE, tuple(self.fields()), per="event"),
                Table(GRID_TABLE, grid, per="event")]  # fmt: skip

    def _emit_grid(self) -> None:
        g = self.grid
        assert g is not None
        iy, ix = np.indices((g.ny, g.nx))
        ix, iy = ix.ravel(), iy.ravel()
        self.emit(GRID_TABLE, {
            "ix": ix.astype(np.int16), "iy": iy.astype(np.int16),
            "x0": g.x_edges[ix], "x1": g.x_edges[ix + 1],
            "y0": g.y_edges[iy], "y1": g.y_edges[iy + 1],
            "explored": g.inside.ravel(),
        })  # fmt: skip

    # -- snapshots ---------------------------------------------------------------------------
    def start_run(self, run: int, agent: Any = None) -> None:
        if not self._grid_written:
            self._emit_grid()
            self._grid_written = True
        if self.layers is None and isinstance(agent, HasActivations):
            names = list(agent.layer_names())
            if "analysis" not in names:
                raise ConfigError(
                    f"activity maps: agent {type(agent).__name__} has no 'analysis' layer; "
                    f"pick task.monitors.maps.layers from: {', '.join(names)}"
                )
            self.layers = ["analysis"]
        super().start_run(run, agent)

    def views(self) -> Any:
        """The observations at every probe pose, ``(M * D, ...)`` (produced once, then kept)."""
        if self._views is None:
            assert self.grid is not None, "setup() first"
            t0 = time.perf_counter()
            obs = self.env.observe_grid(self.grid.points(), self.headings_rad)
            m, d = self.grid.points().shape[0], self.headings_deg.size
            if isinstance(obs, dict):
                self._views = {k: v.reshape(m * d, *v.shape[2:]) for k, v in obs.items()}
            else:
                self._views = obs.reshape(m * d, *obs.shape[2:])
            self.view_seconds = time.perf_counter() - t0
        return self._views

    def snapshot(self, agent: Any, trial: int) -> None:
        assert self.layers is not None and self.grid is not None
        views = self.views()
        t0 = time.perf_counter()
        n = len(next(iter(views.values()))) if isinstance(views, dict) else len(views)
        parts: dict[str, list[np.ndarray]] = {name: [] for name in self.layers}
        for start in range(0, n, self.batch_size):
            sl = slice(start, start + self.batch_size)
            batch = {k: v[sl] for k, v in views.items()} if isinstance(views, dict) else views[sl]
            k = min(self.batch_size, n - start)
            for name, arr in agent.activations(batch, self.layers).items():
                parts[name].append(np.asarray(arr, np.float32).reshape(k, -1))
        ix, iy = self.grid.indices()
        pts = self.grid.points().astype(np.float32)
        m, d = pts.shape[0], self.headings_deg.size
        cols: dict[str, list[np.ndarray]] = {f.name: [] for f in self.fields()}
        for name, chunks in parts.items():
            acts = np.concatenate(chunks).reshape(m, d, -1)  # (positions, headings, units)
            units = acts.shape[2]
            self._check_silent(name, acts, trial)
            values = acts.transpose(2, 1, 0)  # (units, headings, positions)
            size = values.size
            cols["run"].append(np.full(size, self._run, np.int32))
            cols["trial"].append(np.full(size, trial, np.int32))
            cols["layer"].append(np.full(size, name, dtype=object))
            cols["unit"].append(np.repeat(np.arange(units, dtype=np.int32), d * m))
            cols["heading"].append(
                np.tile(np.repeat(self.headings_deg.astype(np.float32), m), units)
            )
            cols["ix"].append(np.tile(ix.astype(np.int16), units * d))
            cols["iy"].append(np.tile(iy.astype(np.int16), units * d))
            cols["x"].append(np.tile(pts[:, 0], units * d))
            cols["y"].append(np.tile(pts[:, 1], units * d))
            cols["value"].append(values.ravel())
            self._keep_grid(name, trial, acts, ix, iy)
        self._last = trial
        self.snapshot_seconds.append(time.perf_counter() - t0)
        if cols["run"]:
            self.emit(MAPS_TABLE, {k: np.concatenate(v) for k, v in cols.items()})

    #: units of a layer shown as maps in run.mcap and the live view (fields unit_00, ...)
    SCENE_UNITS = 16
    #: snapshots kept for scene_grids() between two calls (a run without run.mcap never asks)
    SCENE_PENDING = 64

    def _keep_grid(
        self, layer: str, trial: int, acts: np.ndarray, ix: np.ndarray, iy: np.ndarray
    ) -> None:
        """The snapshot of a layer as a :class:`SceneGrid` on ``/run_NNNN/activity_<layer>``:
        the first :data:`SCENE_UNITS` units' activity averaged over headings, NaN outside."""
        g = self.grid
        assert g is not None
        mean = acts.mean(axis=1)  # (positions, units)
        fields = {}
        for u in range(min(self.SCENE_UNITS, mean.shape[1])):
            plane = np.full((g.ny, g.nx), np.nan, np.float32)
            plane[iy, ix] = mean[:, u]
            fields[f"unit_{u:02d}"] = plane
        if not fields:
            return
        self._grids.append(SceneGrid(
            name=f"activity_{layer}", trial=int(trial),
            origin=(float(g.x_edges[0]), float(g.y_edges[0])),
            cell_size=(float(g.x_edges[1] - g.x_edges[0]), float(g.y_edges[1] - g.y_edges[0])),
            fields=fields, metadata={"layer": layer, "units": str(mean.shape[1]),
                                     "headings": "mean"},
        ))  # fmt: skip
        del self._grids[: -self.SCENE_PENDING]

    def scene_grids(self) -> list[SceneGrid]:
        grids, self._grids = self._grids, []
        return grids

    def _check_silent(self, layer: str, acts: np.ndarray, trial: int) -> None:
        """Warn once per run and layer when, after training started, the layer's values are not
        finite, all 0 (a dead layer: every ReLU unit off at every pose, so it has no maps to
        classify and passes no gradient to the layers below it; it seldom recovers), or
        constant over the poses (no spatial information). A layer that recovers and dies again
        is not reported a second time."""
        key = (self._run, layer)
        if trial == 0 or key in self._silent_reported or acts.size == 0:
            return
        flat = acts.reshape(-1, acts.shape[2])
        where = f"activity maps: layer {layer!r} of run {self._run} at trial {trial}"
        units, poses = flat.shape[1], flat.shape[0]
        if not np.isfinite(flat).all():
            message = f"{where} has non-finite values (NaN or inf): the network diverged"
        elif not flat.any():
            message = (
                f"{where} is silent: all {units} units are 0 at all {poses} probe poses (a dead "
                "layer: no maps to classify; for a ReLU layer no gradient reaches the layers "
                "below it, so it seldom recovers; docs/place_cells.md, 'Why the analysis layer "
                "collapsed')"
            )
        elif not np.any(flat.max(axis=0) > flat.min(axis=0)):
            message = (
                f"{where} is constant: none of its {units} units changes over the {poses} "
                "probe poses (no spatial information to classify)"
            )
        else:
            return
        self._silent_reported.add(key)
        LOG.warning(message)
