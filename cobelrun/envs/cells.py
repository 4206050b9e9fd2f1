"""Observation parts for continuous arenas: the pose and population codes of spatial cells.

Each part maps a pose ``(x, y, heading)`` to ``n`` numbers. The environment writes the parts it
was configured with one after the other into its observation vector (:meth:`SpatialCode.write`,
called once per step; place cells go through a compiled kernel), and :meth:`SpatialCode.rates`
evaluates a part at many poses at once (rate maps, analyses, tests).

Tuning curves follow RatInABox (George et al. 2024, ``ratinabox.Neurons``) so that models
move between the two; ``tests/test_arena.py`` checks them against RatInABox's own classes:

- :class:`PlaceCells`: Gaussian fields ``exp(-|p - c|^2 / (2 sigma^2))`` (Foster et al. 2000;
  RatInABox ``description="gaussian"`` with Euclidean distances);
- :class:`GridCells`: three plane waves at 60 degrees, rectified at the field-width level
  (RatInABox ``"rectified_cosines"``) or shifted (Solstad et al. 2006, ``"shifted_cosines"``);
- :class:`BoundaryVectorCells`: for each of ``360 / dtheta`` directions the distance to the
  first wall, weighted by a Gaussian in distance (width ``xi + d / beta``, Hartley et al. 2000)
  times a von Mises in angle, summed and normalised (Barry & Burgess 2007, de Cothi 2020);
- :class:`HeadDirectionCells`: von Mises tuning ``exp(kappa (cos(h - mu) - 1))`` with
  ``kappa = 1 / spread^2`` and evenly spaced preferred directions.

Cell layouts are fixed when the environment is built (a cell population is part of the modelled
animal, the same in every run); random layouts draw from their own ``seed`` key.

Config: the environment's ``observation`` is a list of parts, e.g.::

    observation:
      - {kind: place_cells, n: 493, sigma: 0.16}
      - {kind: head_direction, n: 8, spread_deg: 45}
"""

from __future__ import annotations

import abc
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import numba
import numpy as np

from cobelrun.envs.raycast import ray_distances
from cobelrun.errors import ConfigError, allowed_list, suggest
from cobelrun.safety import check_allocation

__all__ = [
    "KINDS",
    "BoundaryVectorCells",
    "GridCells",
    "HeadDirectionCells",
    "PlaceCells",
    "PoseCode",
    "SpatialCode",
    "build_observation",
    "halton",
]


class SpatialCode(abc.ABC):
    """One part of an arena observation: ``n`` values that depend on the pose."""

    n: int
    kind: ClassVar[str]

    def bind(self, arena: Any) -> None:  # noqa: B027 (optional hook)
        """Resolve what depends on the arena (layouts, walls)."""

    @property
    def low(self) -> np.ndarray:
        return np.zeros(self.n)

    @property
    def high(self) -> np.ndarray:
        return np.ones(self.n)

    @abc.abstractmethod
    def rates(self, poses: np.ndarray) -> np.ndarray:
        """(k, n) values at the (k, 3) poses ``x, y, heading``."""

    def write(self, x: float, y: float, heading: float, out: np.ndarray) -> None:
        """Write the values at one pose into ``out`` (n,) (the per-step path)."""
        out[:] = self.rates(np.array([[x, y, heading]]))[0]


# ---------------------------------------------------------------------------- pose
class PoseCode(SpatialCode):
    """``(x, y, cos heading, sin heading)``."""

    kind = "pose"
    n = 4

    def __init__(self) -> None:
        self._lo = np.array([-np.inf, -np.inf, -1.0, -1.0])
        self._hi = np.array([np.inf, np.inf, 1.0, 1.0])

    def bind(self, arena: Any) -> None:
        x0, y0, x1, y1 = arena.bounds
        self._lo[:2] = x0, y0
        self._hi[:2] = x1, y1

    @property
    def low(self) -> np.ndarray:
        return self._lo

    @property
    def high(self) -> np.ndarray:
        return self._hi

    def rates(self, poses: np.ndarray) -> np.ndarray:
        p = np.atleast_2d(poses)
        return np.stack([p[:, 0], p[:, 1], np.cos(p[:, 2]), np.sin(p[:, 2])], axis=1)

    def write(self, x: float, y: float, heading: float, out: np.ndarray) -> None:
        out[0], out[1], out[2], out[3] = x, y, np.cos(heading), np.sin(heading)


# ---------------------------------------------------------------------------- place cells
@numba.njit(cache=True)
def _place_kernel(x: float, y: float, cx: np.ndarray, cy: np.ndarray, inv2s2: np.ndarray,
                  out: np.ndarray) -> None:  # fmt: skip
    for i in range(cx.shape[0]):
        dx = x - cx[i]
        dy = y - cy[i]
        out[i] = np.exp(-(dx * dx + dy * dy) * inv2s2[i])


def halton(n: int, base: int) -> np.ndarray:
    """The first ``n`` points (from index 1) of the van der Corput sequence in ``base``."""
    out = np.zeros(n)
    for i in range(n):
        f, k, v = 1.0, i + 1, 0.0
        while k > 0:
            f /= base
            v += f * (k % base)
            k //= base
        out[i] = v
    return out


class PlaceCells(SpatialCode):
    """Gaussian place cells.

    Parameters
    ----------
    n : int
        Number of cells (Foster et al. 2000: 493).
    sigma : float or list
        Field width (standard deviation, world units; Foster et al.: 0.16 m).
    layout : {"halton", "random", "grid"}
        Centres: a Halton sequence (even, deterministic coverage) or uniform random draws, both
        restricted to the arena's free space; ``"grid"`` a square lattice of about ``n`` points
        over the free space (``n`` becomes the number inside).
    centres : (n, 2) list, optional
        Explicit centres (overrides ``n`` and ``layout``).
    seed : int
        Seed of the ``"random"`` layout.
    """

    kind = "place_cells"

    def __init__(self, n: int = 100, sigma: float | Sequence[float] = 0.16,
                 layout: str = "halton", centres: Any = None, seed: int = 0) -> None:  # fmt: skip
        self.n = _count("place_cells.n", n)
        sig = np.atleast_1d(np.asarray(sigma, np.float64))
        if not np.isfinite(sig).all() or (sig <= 0).any():
            raise ConfigError(f"place_cells.sigma must be > 0, got {sigma!r}")
        if layout not in ("halton", "random", "grid"):
            raise ConfigError(
                f"place_cells.layout {layout!r} is unknown{suggest(str(layout), ('halton', 'random', 'grid'))}; "
                "allowed: 'halton', 'random', 'grid'"
            )
        self.sigma_in, self.layout, self.seed = sig, layout, int(seed)
        self.centres = None if centres is None else _points("place_cells.centres", centres)
        if self.centres is not None:
            self.n = len(self.centres)
            self._finish()

    def bind(self, arena: Any) -> None:
        if self.centres is None:
            x0, y0, x1, y1 = arena.bounds
            if self.layout == "grid":
                free_area = arena.free.area
                step = np.sqrt(free_area / self.n)
                gx, gy = np.meshgrid(np.arange(x0 + step / 2, x1, step),
                                     np.arange(y0 + step / 2, y1, step))  # fmt: skip
                cand = np.stack([gx.ravel(), gy.ravel()], 1)
                self.centres = cand[arena.is_free(cand)]
                self.n = len(self.centres)
            else:
                found: list[np.ndarray] = []
                rng = np.random.default_rng(self.seed)
                k, have = 0, 0
                while have < self.n:
                    m = 4 * (self.n - have) + 16
                    if self.layout == "halton":
                        u = np.stack([halton(k + m, 2)[k:], halton(k + m, 3)[k:]], 1)
                        k += m
                    else:
                        u = rng.random((m, 2))
                    cand = np.array([x0, y0]) + u * np.array([x1 - x0, y1 - y0])
                    ok = cand[arena.is_free(cand)]
                    found.append(ok)
                    have += len(ok)
                self.centres = np.concatenate(found)[: self.n]
        elif not arena.is_free(self.centres).all():
            raise ConfigError(
                "place_cells.centres: some centres lie outside the arena's free space"
            )
        self._finish()

    def _finish(self) -> None:
        assert self.centres is not None
        sig = self.sigma_in
        if sig.size not in (1, self.n):
            raise ConfigError(f"place_cells.sigma: give one width or {self.n}, got {sig.size}")
        self.sigma = np.broadcast_to(sig, (self.n,)).astype(np.float64).copy()
        self._cx = np.ascontiguousarray(self.centres[:, 0])
        self._cy = np.ascontiguousarray(self.centres[:, 1])
        self._inv = 1.0 / (2.0 * self.sigma**2)

    def rates(self, poses: np.ndarray) -> np.ndarray:
        p = np.atleast_2d(poses)
        d2 = (p[:, 0:1] - self._cx) ** 2 + (p[:, 1:2] - self._cy) ** 2
        return np.exp(-d2 * self._inv)

    def write(self, x: float, y: float, heading: float, out: np.ndarray) -> None:
        _place_kernel(x, y, self._cx, self._cy, self._inv, out)


# ---------------------------------------------------------------------------- grid cells
class GridCells(SpatialCode):
    """Grid cells: three plane waves at 60 degrees (RatInABox's ``GridCells``).

    Parameters
    ----------
    n : int
        Number of cells.
    gridscale : float or list
        Grid spacing (world units); a list of ``n`` values, or of module spacings that cells
        are assigned to in turn (default modules 0.3, 0.5, 0.8 as RatInABox).
    orientation : float or list
        Grid orientation (radians) per module (or per cell), default (0, 0.1, 0.2).
    phase_offsets : (n, 2) list, optional
        Spatial phases in ``[0, 2 pi)^2`` (default: uniform random from ``seed``).
    description : {"rectified_cosines", "shifted_cosines"}
    width_ratio : float
        Field width / spacing of the rectified form (default 4 / (3 sqrt 3)).
    seed : int
    """

    kind = "grid_cells"
    DESCRIPTIONS = ("rectified_cosines", "shifted_cosines")

    def __init__(self, n: int = 30, gridscale: Any = (0.3, 0.5, 0.8),
                 orientation: Any = (0.0, 0.1, 0.2), phase_offsets: Any = None,
                 description: str = "rectified_cosines",
                 width_ratio: float = 4 / (3 * np.sqrt(3)), seed: int = 0) -> None:  # fmt: skip
        self.n = _count("grid_cells.n", n)
        if description not in self.DESCRIPTIONS:
            raise ConfigError(
                f"grid_cells.description {description!r} is unknown; allowed: {allowed_list(self.DESCRIPTIONS)}"
            )
        if not 0 < width_ratio <= 1:
            raise ConfigError(f"grid_cells.width_ratio must be in (0, 1], got {width_ratio!r}")
        self.description, self.width_ratio = description, float(width_ratio)
        self.gridscales = _per_cell("grid_cells.gridscale", gridscale, self.n, positive=True)
        self.orientations = _per_cell("grid_cells.orientation", orientation, self.n)
        rng = np.random.default_rng(seed)
        if phase_offsets is None:
            self.phase_offsets = rng.uniform(0, 2 * np.pi, (self.n, 2))
        else:
            self.phase_offsets = _points("grid_cells.phase_offsets", phase_offsets)
            if len(self.phase_offsets) != self.n:
                raise ConfigError(f"grid_cells.phase_offsets needs {self.n} rows")
        a = self.orientations[:, None] + np.array([0, np.pi / 3, 2 * np.pi / 3])
        self.w = np.stack([np.cos(a), np.sin(a)], axis=-1)  # (n, 3, 2)
        self.origin = self.gridscales[:, None] * self.phase_offsets / (2 * np.pi)
        self.k = 2 * np.pi / self.gridscales
        self._full = (2 * np.cos(np.sqrt(3) * np.pi * self.width_ratio / 2) + 1) / 3

    def rates(self, poses: np.ndarray) -> np.ndarray:
        p = np.atleast_2d(poses)[:, :2]
        vec = p[:, None, :] - self.origin[None]  # (k, n, 2)
        phase = np.einsum("knd,nwd->knw", vec, self.w) * self.k[None, :, None]
        s = np.cos(phase).sum(axis=-1) / 3
        if self.description == "rectified_cosines":
            return np.maximum((s - self._full) / (1 - self._full), 0.0)
        return (2 / 3) * (s + 0.5)


# ---------------------------------------------------------------------------- BVCs
class BoundaryVectorCells(SpatialCode):
    """Allocentric boundary-vector cells (Hartley et al. 2000; RatInABox's BVCs).

    A cell with preferred distance ``d`` and direction ``phi`` fires
    ``sum_theta G(r(theta); d, xi + d / beta) V(theta; phi, sigma_angle) / norm`` where
    ``r(theta)`` is the distance to the first wall in direction ``theta`` (``360 / dtheta``
    directions), ``G`` a Gaussian and ``V`` a von Mises, both with peak 1, and ``norm`` the sum
    of ``V`` (so a cell peaks at about 1 facing a long straight wall).

    Parameters
    ----------
    n : int
    tuning_distance : (low, high) or list
        Preferred distances (uniform in the range, or one per cell); default (0.05, 0.3).
    tuning_angle_deg : (low, high) or list
        Preferred allocentric directions in degrees; default (0, 360).
    sigma_angle_deg : (low, high) or list
        Angular tuning widths in degrees; default (10, 30).
    xi, beta : float
        Distance tuning width ``xi + d / beta`` (default 0.08 and 12); or ``sigma_distance``
        (list, one per cell) to give the widths directly.
    dtheta_deg : float
        Angular integration step (degrees).
    seed : int
    """

    kind = "boundary_vector_cells"

    def __init__(self, n: int = 10, tuning_distance: Any = (0.05, 0.3),
                 tuning_angle_deg: Any = (0.0, 360.0), sigma_angle_deg: Any = (10.0, 30.0),
                 xi: float = 0.08, beta: float = 12.0, sigma_distance: Any = None,
                 dtheta_deg: float = 2.0, seed: int = 0) -> None:  # fmt: skip
        self.n = _count("boundary_vector_cells.n", n)
        rng = np.random.default_rng(seed)
        w = "boundary_vector_cells"
        self.tuning_distances = _sample(f"{w}.tuning_distance", tuning_distance, self.n, rng)
        self.tuning_angles = np.deg2rad(
            _sample(f"{w}.tuning_angle_deg", tuning_angle_deg, self.n, rng)
        )
        self.sigma_angles = np.deg2rad(
            _sample(f"{w}.sigma_angle_deg", sigma_angle_deg, self.n, rng)
        )
        if sigma_distance is None:
            self.sigma_distances = float(xi) + self.tuning_distances / float(beta)
        else:
            self.sigma_distances = _per_cell(
                f"{w}.sigma_distance", sigma_distance, self.n, positive=True
            )
        if (self.sigma_distances <= 0).any() or (self.sigma_angles <= 0).any():
            raise ConfigError(f"{w}: tuning widths must be > 0")
        if not 0 < dtheta_deg <= 45:
            raise ConfigError(f"{w}.dtheta_deg must be in (0, 45], got {dtheta_deg!r}")
        m = round(360 / dtheta_deg)
        self.test_angles = 2 * np.pi * np.arange(m) / m
        self._cos, self._sin = np.cos(self.test_angles), np.sin(self.test_angles)
        kappa = 1.0 / self.sigma_angles**2
        diff = self.test_angles[None, :] - self.tuning_angles[:, None]
        self._vm = np.exp(kappa[:, None] * (np.cos(diff) - 1.0))  # (n, m)
        self._vm /= self._vm.sum(axis=1, keepdims=True)
        self._walls = np.zeros((0, 4))
        self._r = np.empty(m)

    def bind(self, arena: Any) -> None:
        self._walls = arena.wall_segments()

    def _from_distances(self, r: np.ndarray) -> np.ndarray:
        """(k, n) rates from (k, m) wall distances."""
        d = self.tuning_distances[None, :, None]
        s = self.sigma_distances[None, :, None]
        g = np.exp(-((r[:, None, :] - d) ** 2) / (2 * s**2))  # (k, n, m)
        return np.einsum("knm,nm->kn", g, self._vm)

    def wall_distances(self, poses: np.ndarray) -> np.ndarray:
        p = np.atleast_2d(poses)
        out = np.empty((len(p), len(self.test_angles)))
        for i in range(len(p)):
            ray_distances(p[i, 0], p[i, 1], self._cos, self._sin, self._walls, out[i])
        return out

    def rates(self, poses: np.ndarray) -> np.ndarray:
        return self._from_distances(self.wall_distances(poses))

    def write(self, x: float, y: float, heading: float, out: np.ndarray) -> None:
        ray_distances(x, y, self._cos, self._sin, self._walls, self._r)
        out[:] = self._from_distances(self._r[None])[0]


# ---------------------------------------------------------------------------- HD cells
class HeadDirectionCells(SpatialCode):
    """Head-direction cells: von Mises tuning around ``n`` evenly spaced preferred directions.

    Parameters
    ----------
    n : int
    spread_deg : float
        Tuning width in degrees (``kappa = 1 / spread^2``; RatInABox's default 45).
    """

    kind = "head_direction"

    def __init__(self, n: int = 8, spread_deg: float = 45.0) -> None:
        self.n = _count("head_direction.n", n)
        if not spread_deg > 0:
            raise ConfigError(f"head_direction.spread_deg must be > 0, got {spread_deg!r}")
        self.preferred = 2 * np.pi * np.arange(self.n) / self.n
        self.kappa = 1.0 / np.deg2rad(spread_deg) ** 2

    def rates(self, poses: np.ndarray) -> np.ndarray:
        h = np.atleast_2d(poses)[:, 2:3]
        return np.exp(self.kappa * (np.cos(h - self.preferred) - 1.0))


# ---------------------------------------------------------------------------- config
class CameraView(SpatialCode):
    """The agent's first-person RGB view of the arena's 3D scene, flattened to
    ``height * width * 3`` values in [0, 1].

    Rendered by pybullet through the existing scene path (``render.scene``: walls coloured by
    the direction they face, distal cues, no visible goal) with the env's ``camera``; the env
    attaches its renderer when it builds the observation. Combine it with other parts (e.g.
    ``[{kind: view}, {kind: head_direction}]``); each step renders one image (~0.5 ms at
    12 x 48 with pybullet's TinyRenderer).
    """

    kind = "view"

    def __init__(self) -> None:
        self.n = 0
        self._render: Any = None

    def attach(self, render: Any, height: int, width: int) -> None:
        """The env's ``view_at_pose`` and its camera's image size."""
        self._render, self.n = render, int(height) * int(width) * 3

    def rates(self, poses: np.ndarray) -> np.ndarray:
        if self._render is None:
            raise ConfigError("observation part 'view' needs an env that renders its arena")
        poses = np.asarray(poses, np.float64).reshape(-1, 3)
        return np.stack([self._render(*p).reshape(-1) / 255.0 for p in poses])


KINDS: dict[str, type[SpatialCode]] = {
    c.kind: c
    for c in (PoseCode, PlaceCells, GridCells, BoundaryVectorCells, HeadDirectionCells, CameraView)
}


def build_observation(spec: Sequence[Mapping[str, Any]] | None, arena: Any) -> list[SpatialCode]:
    """Observation parts from config (default ``[{kind: pose}]``), bound to ``arena``."""
    import inspect

    if spec is None:
        spec = [{"kind": "pose"}]
    if (
        isinstance(spec, Mapping)
        or isinstance(spec, str)
        or not isinstance(spec, Sequence)
        or not spec
    ):
        raise ConfigError("observation must be a non-empty list of parts, e.g. [{kind: pose}]")
    parts: list[SpatialCode] = []
    for i, item in enumerate(spec):
        where = f"observation[{i}]"
        if isinstance(item, SpatialCode):
            part = item
        else:
            if not isinstance(item, Mapping) or "kind" not in item:
                raise ConfigError(
                    f"{where} must be a mapping with a 'kind' ({allowed_list(KINDS)})"
                )
            kind = item["kind"]
            if kind not in KINDS:
                raise ConfigError(
                    f"{where}.kind {kind!r} is unknown{suggest(str(kind), KINDS)}; allowed: {allowed_list(KINDS)}"
                )
            cls = KINDS[kind]
            args = {k: v for k, v in item.items() if k != "kind"}
            allowed = [p for p in inspect.signature(cls.__init__).parameters if p != "self"]
            for key in args:
                if key not in allowed:
                    raise ConfigError(
                        f"unknown key '{where}.{key}'{suggest(key, allowed)}; allowed: {allowed_list(allowed)}"
                    )
            part = cls(**args)
        part.bind(arena)
        parts.append(part)
    return parts


# ---------------------------------------------------------------------------- helpers
#: bytes per cell of a population: its centre or parameters, and its activity in the steps
#: a trial batch holds (float64)
BYTES_PER_CELL = 256


def _count(where: str, n: Any) -> int:
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 1:
        raise ConfigError(f"{where} must be an integer >= 1, got {n!r}")
    check_allocation(f"env.observation ({where})", int(n) * BYTES_PER_CELL,
                     f"a population of {int(n):,} cells", f"lower {where}")  # fmt: skip
    return int(n)


def _points(where: str, value: Any) -> np.ndarray:
    try:
        p = np.array(value, np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"{where} must be a list of [x, y] pairs") from None
    if p.ndim != 2 or p.shape[1] != 2 or not np.isfinite(p).all() or len(p) < 1:
        raise ConfigError(f"{where} must be a list of finite [x, y] pairs")
    return p


def _per_cell(where: str, value: Any, n: int, positive: bool = False) -> np.ndarray:
    """One value per cell from a scalar, a list of ``n`` or a shorter list of module values."""
    v = np.atleast_1d(np.asarray(value, np.float64))
    if v.ndim != 1 or not np.isfinite(v).all() or (positive and (v <= 0).any()):
        raise ConfigError(
            f"{where} must be {'positive ' if positive else ''}finite number(s), got {value!r}"
        )
    if v.size == n:
        return v.copy()
    return v[np.arange(n) % v.size]


def _sample(where: str, value: Any, n: int, rng: np.random.Generator) -> np.ndarray:
    """Uniform draws from a ``(low, high)`` pair (tuple) or one value per cell (list of n)."""
    v = np.atleast_1d(np.asarray(value, np.float64))
    if not np.isfinite(v).all():
        raise ConfigError(f"{where} must be finite, got {value!r}")
    if v.size == n and n != 2:  # with n = 2 a pair is a range
        return v.copy()
    if v.size == 2:
        return rng.uniform(v[0], v[1], n)
    if v.size == 1:
        return np.full(n, v[0])
    raise ConfigError(f"{where} must be a (low, high) pair or {n} values, got {value!r}")
