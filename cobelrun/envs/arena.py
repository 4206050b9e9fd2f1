"""Continuous 2D arenas: outline, obstacles, goal regions and start points as data.

An :class:`Arena` is built once from plain config (shapely checks the geometry: a platform
outside the pool, a goal inside a wall, a start inside an obstacle are one-line
:class:`~cobelrun.errors.ConfigError`\\ s) and then reduced to numpy arrays (wall segments,
circle and polygon regions) that the environment's compiled step kernel uses. Shapely is never
called in the step loop.

Shapes are given as mappings:

``{shape: circle, x, y, radius}``
    A disc (arena outlines are approximated by a regular polygon of ``resolution`` sides for
    collisions; containment tests are exact).
``{shape: rectangle, x0, y0, x1, y1}`` (or ``{shape: square, x0, y0, size}``)
    An axis-aligned rectangle.
``{shape: polygon, points: [[x, y], ...]}``
    Any simple polygon (closed implicitly).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cobelrun.errors import ConfigError, allowed_list, suggest

SHAPES = ("circle", "rectangle", "square", "polygon")
_SHAPE_KEYS = {
    "circle": ("x", "y", "radius"),
    "rectangle": ("x0", "y0", "x1", "y1"),
    "square": ("x0", "y0", "size"),
    "polygon": ("points",),
}
#: keys a goal region accepts besides its shape keys
GOAL_KEYS = ("reward", "terminal")
#: default number of polygon sides of a circular outline or obstacle (collision walls)
CIRCLE_RESOLUTION = 128


def _shapely() -> Any:
    try:
        import shapely
    except ImportError:  # pragma: no cover - shapely is a core dependency
        raise ConfigError("continuous arenas need shapely: pip install shapely") from None
    return shapely


def _number(where: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.number):
        raise ConfigError(f"{where} must be a number, got {value!r}")
    if not np.isfinite(value):
        raise ConfigError(f"{where} must be finite, got {value!r}")
    return float(value)


@dataclass(frozen=True)
class Shape:
    """A validated shape: its kind and parameters (``x, y, radius`` or ``points``)."""

    kind: str  # "circle" or "polygon"
    x: float = 0.0
    y: float = 0.0
    radius: float = 0.0
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    @classmethod
    def parse(cls, where: str, spec: Any, extra: Sequence[str] = ()) -> Shape:
        """Build from a config mapping; ``extra`` are further keys the caller handles."""
        if not isinstance(spec, Mapping):
            raise ConfigError(f"{where} must be a mapping with a 'shape' ({allowed_list(SHAPES)})")
        kind = spec.get("shape")
        if kind not in SHAPES:
            raise ConfigError(
                f"{where}.shape {kind!r} is unknown{suggest(str(kind), SHAPES)}; "
                f"allowed: {allowed_list(SHAPES)}"
            )
        allowed = ("shape", *_SHAPE_KEYS[kind], *extra)
        for key in spec:
            if key not in allowed:
                raise ConfigError(
                    f"unknown key '{where}.{key}'{suggest(str(key), allowed)}; "
                    f"allowed: {allowed_list(allowed)}"
                )
        missing = [k for k in _SHAPE_KEYS[kind] if k not in spec]
        if missing:
            raise ConfigError(f"{where} ({kind}) needs {allowed_list(missing)}")
        if kind == "circle":
            radius = _number(f"{where}.radius", spec["radius"])
            if radius <= 0:
                raise ConfigError(f"{where}.radius must be > 0, got {radius}")
            return cls("circle", _number(f"{where}.x", spec["x"]),
                       _number(f"{where}.y", spec["y"]), radius)  # fmt: skip
        if kind in ("rectangle", "square"):
            x0, y0 = _number(f"{where}.x0", spec["x0"]), _number(f"{where}.y0", spec["y0"])
            if kind == "square":
                size = _number(f"{where}.size", spec["size"])
                if size <= 0:
                    raise ConfigError(f"{where}.size must be > 0, got {size}")
                x1, y1 = x0 + size, y0 + size
            else:
                x1, y1 = _number(f"{where}.x1", spec["x1"]), _number(f"{where}.y1", spec["y1"])
                if x1 <= x0 or y1 <= y0:
                    raise ConfigError(f"{where} needs x1 > x0 and y1 > y0, got {dict(spec)}")
            pts = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], np.float64)
            return cls("polygon", points=pts)
        try:
            pts = np.array(spec["points"], np.float64)
        except (TypeError, ValueError):
            raise ConfigError(f"{where}.points must be a list of [x, y] pairs") from None
        if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 3 or not np.isfinite(pts).all():
            raise ConfigError(f"{where}.points must be >= 3 finite [x, y] pairs")
        if not _shapely().Polygon(pts).is_valid:
            raise ConfigError(f"{where}.points do not form a simple polygon (edges cross)")
        return cls("polygon", points=pts)

    def polygon(self, resolution: int = CIRCLE_RESOLUTION) -> np.ndarray:
        """(P, 2) vertices; a circle becomes the regular ``resolution``-gon through its edge."""
        if self.kind == "polygon":
            return self.points
        a = np.linspace(0.0, 2 * np.pi, resolution, endpoint=False)
        return np.stack([self.x + self.radius * np.cos(a), self.y + self.radius * np.sin(a)], 1)

    def geom(self) -> Any:
        """The exact shapely geometry (a buffered point for circles)."""
        shapely = _shapely()
        if self.kind == "circle":
            return shapely.Point(self.x, self.y).buffer(self.radius, quad_segs=64)
        return shapely.Polygon(self.points)

    def region(self) -> dict[str, Any]:
        """A :class:`~cobelrun.envs.base.Geometry` region dict."""
        if self.kind == "circle":
            return {"shape": "circle", "x": self.x, "y": self.y, "radius": self.radius}
        return {"shape": "polygon", "points": self.points.tolist()}

    def contains(self, xy: np.ndarray) -> np.ndarray:
        """(k,) bool: which of the (k, 2) points lie inside (boundary included)."""
        xy = np.atleast_2d(np.asarray(xy, np.float64))
        if self.kind == "circle":
            d2 = (xy[:, 0] - self.x) ** 2 + (xy[:, 1] - self.y) ** 2
            return d2 <= self.radius**2
        return points_in_polygon(xy, self.points)

    @property
    def centre(self) -> np.ndarray:
        if self.kind == "circle":
            return np.array([self.x, self.y])
        c = self.geom().centroid
        return np.array([c.x, c.y])


def points_in_polygon(xy: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """(k,) bool: even-odd rule for (k, 2) points in a (P, 2) polygon (vectorised)."""
    x, y = xy[:, 0:1], xy[:, 1:2]
    x0, y0 = poly[:, 0], poly[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    crosses = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xi = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    return (np.sum(crosses & (x < xi), axis=1) % 2) == 1


@dataclass
class Goal:
    """A goal region: shape, reward on each step that ends inside, whether it ends the trial."""

    name: str
    shape: Shape
    reward: float = 1.0
    terminal: bool = True


class Arena:
    """Outline + obstacles + goals + named starts, validated with shapely.

    Parameters
    ----------
    outline : mapping, optional
        The arena's shape (default the unit square ``{shape: square, x0: 0, y0: 0, size: 1}``,
        the paper's 2D interface).
    obstacles : list of mappings, optional
        Internal walls/obstacles (shapes); the agent cannot enter them.
    goals : mapping name -> shape mapping with ``reward`` and ``terminal``, optional
        Goal regions (reward default 1.0, terminal default true).
    starts : mapping name -> [x, y], list of [x, y], or "random", optional
        Start points (default: the centre of the outline's free space).
    resolution : int
        Sides of the polygon that stands in for a circular outline or obstacle in collisions.
    """

    def __init__(
        self,
        outline: Mapping[str, Any] | None = None,
        obstacles: Sequence[Mapping[str, Any]] | None = None,
        goals: Mapping[str, Mapping[str, Any]] | None = None,
        starts: Mapping[str, Sequence[float]] | Sequence[Sequence[float]] | str | None = None,
        resolution: int = CIRCLE_RESOLUTION,
    ) -> None:
        if isinstance(resolution, bool) or not isinstance(resolution, int) or resolution < 8:
            raise ConfigError(f"arena resolution must be an integer >= 8, got {resolution!r}")
        self.resolution = resolution
        if outline is None:
            outline = {"shape": "square", "x0": 0.0, "y0": 0.0, "size": 1.0}
        self.outline = Shape.parse("arena", outline)
        self.obstacles = [Shape.parse(f"obstacles[{i}]", o) for i, o in enumerate(obstacles or [])]
        outline_geom = self.outline.geom()
        free = outline_geom
        for i, ob in enumerate(self.obstacles):
            g = ob.geom()
            if not outline_geom.intersects(g):
                raise ConfigError(f"obstacles[{i}] lies outside the arena")
            free = free.difference(g)
        if free.is_empty:
            raise ConfigError("the obstacles cover the whole arena")
        self.free = free
        self.goals: dict[str, Goal] = {}
        for name, spec in (goals or {}).items():
            where = f"goals.{name}"
            shape = Shape.parse(where, spec, extra=GOAL_KEYS)
            reward = _number(f"{where}.reward", spec.get("reward", 1.0))
            terminal = spec.get("terminal", True)
            if not isinstance(terminal, bool):
                raise ConfigError(f"{where}.terminal must be true or false, got {terminal!r}")
            g = shape.geom()
            if not outline_geom.contains(g.representative_point()) or not outline_geom.covers(
                g.buffer(-1e-9) if shape.kind == "polygon" else g
            ):
                raise ConfigError(f"goal '{name}' lies (partly) outside the arena")
            for i, ob in enumerate(self.obstacles):
                if ob.geom().contains(g.representative_point()):
                    raise ConfigError(f"goal '{name}' lies inside a wall (obstacles[{i}])")
            if free.intersection(g).area <= 0:
                raise ConfigError(f"goal '{name}' cannot be reached: it lies inside the walls")
            self.goals[str(name)] = Goal(str(name), shape, reward, terminal)
        self.random_starts = starts == "random"
        self.starts = self._parse_starts(starts)

    def _parse_starts(self, starts: Any) -> dict[str, np.ndarray]:
        if starts is None or starts == "random":
            c = self.free.representative_point() if not self._centre_free() else None
            centre = self.outline.centre if c is None else np.array([c.x, c.y])
            return {"centre": centre}
        if isinstance(starts, str):
            raise ConfigError(
                f"starts must be 'random', a list or mapping of [x, y], got {starts!r}"
            )
        if isinstance(starts, Mapping):
            items = list(starts.items())
        else:
            items = [(f"start_{i}", p) for i, p in enumerate(starts)]
        if not items:
            raise ConfigError("starts must name at least one start point")
        out = {}
        for name, p in items:
            try:
                xy = np.array(p, np.float64).reshape(2)
            except (TypeError, ValueError):
                raise ConfigError(f"starts.{name} must be an [x, y] pair, got {p!r}") from None
            self.check_free(f"start '{name}'", xy)
            out[str(name)] = xy
        return out

    def _centre_free(self) -> bool:
        return bool(self.is_free(self.outline.centre[None])[0])

    def check_free(self, what: str, xy: np.ndarray) -> None:
        """Raise a ConfigError if the point lies outside the arena or inside an obstacle."""
        xy = np.asarray(xy, np.float64).reshape(1, 2)
        if not np.isfinite(xy).all():
            raise ConfigError(f"{what} must be finite, got {xy[0].tolist()}")
        if (
            not self.outline.contains(xy)[0]
            or not points_in_polygon(xy, self.outline.polygon(self.resolution))[0]
        ):
            raise ConfigError(f"{what} at {xy[0].tolist()} lies outside the arena")
        for i, ob in enumerate(self.obstacles):
            if ob.contains(xy)[0]:
                raise ConfigError(
                    f"{what} at {xy[0].tolist()} lies inside an obstacle (obstacles[{i}])"
                )

    def is_free(self, xy: np.ndarray) -> np.ndarray:
        """(k,) bool: inside the outline's collision polygon and outside every obstacle."""
        xy = np.atleast_2d(np.asarray(xy, np.float64))
        ok = points_in_polygon(xy, self.outline.polygon(self.resolution))
        for ob in self.obstacles:
            ok &= ~ob.contains(xy)
        return ok

    # ---------------------------------------------------------------- arrays for kernels
    def wall_segments(self) -> np.ndarray:
        """(m, 4) float64 segments ``x0, y0, x1, y1``: outline edges, then obstacle edges,
        oriented so that the free space lies left of each (outline counter-clockwise,
        obstacles clockwise)."""
        segs = []
        for k, shape in enumerate((self.outline, *self.obstacles)):
            p = shape.polygon(self.resolution)
            x, y = p[:, 0], p[:, 1]
            ccw = np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) > 0
            if ccw != (k == 0):
                p = p[::-1]
            segs.append(np.concatenate([p, np.roll(p, -1, axis=0)], axis=1))
        return np.ascontiguousarray(np.concatenate(segs), np.float64)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        b = self.outline.geom().bounds
        return (float(b[0]), float(b[1]), float(b[2]), float(b[3]))

    def sample_free(self, rng: np.random.Generator, n: int = 1) -> np.ndarray:
        """(n, 2) points drawn uniformly from the free space (rejection sampling)."""
        x0, y0, x1, y1 = self.bounds
        out = np.empty((0, 2))
        while len(out) < n:
            cand = rng.uniform((x0, y0), (x1, y1), size=(max(2 * n, 16), 2))
            out = np.concatenate([out, cand[self.is_free(cand)]])
        return out[:n]
