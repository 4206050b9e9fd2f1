"""A pybullet scene built from a maze spec, and a camera at an agent pose.

The scene is what the paper's Blender / Unity / Godot simulators provided (section 2.2.4): a floor,
walls around the maze (coloured by the direction they face, optionally textured), distal cues
outside the maze, and lighting. The same topology that the agent moves on defines the geometry:
graphs built from a gridworld get walls around exactly their cells; free-form graphs (hexagonal,
Delaunay, manual) get an open arena with four walls around the nodes.

Rendering runs headless (``pybullet.DIRECT``) with the CPU TinyRenderer by default, which is
deterministic: the same pose gives the same image, bit for bit. ``renderer="egl"`` loads
pybullet's EGL plugin (hardware OpenGL where a GPU driver exists) and falls back to TinyRenderer
with a message when the plugin cannot load.

Only this module imports pybullet, and only when a :class:`Scene` is created: the data classes
(:class:`SceneStyle`, :class:`SceneSpec`, :class:`CameraSpec`) are plain Python, so offline
rendering from the cache never needs pybullet.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import struct
import sys
import tempfile
import zlib
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from cobelrun.errors import CobelError, ConfigError, allowed_list, suggest

#: Renderers: TinyRenderer (CPU, deterministic, default) or pybullet's EGL plugin.
RENDERERS: tuple[str, ...] = ("tiny", "egl")

#: Default wall colours by the direction the wall *faces* (its normal): east, north, west, south.
#: Distinct colours act as a compass, so views that are mirror images in geometry differ.
DEFAULT_WALL_COLORS: tuple[tuple[float, float, float], ...] = (
    (0.80, 0.25, 0.20),  # faces east (seen when looking west)
    (0.25, 0.55, 0.80),  # faces north (seen when looking south)
    (0.25, 0.70, 0.30),  # faces west (seen when looking east)
    (0.85, 0.75, 0.25),  # faces south (seen when looking north)
)

#: Default distal cues: (shape, [x, y, z] relative to the maze centre and size, rgb).
DEFAULT_CUES: tuple[dict[str, Any], ...] = (
    {"shape": "sphere", "direction": 0.0, "size": 0.9, "color": (0.9, 0.1, 0.1)},
    {"shape": "box", "direction": 90.0, "size": 0.9, "color": (0.1, 0.2, 0.9)},
    {"shape": "cylinder", "direction": 180.0, "size": 0.9, "color": (0.1, 0.8, 0.2)},
)

_SHAPES = ("sphere", "box", "cylinder")


@dataclass(frozen=True)
class SceneStyle:
    """Looks of a scene (everything except its geometry).

    Attributes
    ----------
    wall_height : float
        Wall height in cell units (default 0.6; the camera sits at ``CameraSpec.eye_height``).
    wall_thickness : float
        Wall thickness in cell units.
    wall_colors : list of 4 [r, g, b]
        Colours of walls facing east, north, west, south (0..1).
    floor_color, sky_color : [r, g, b]
        Floor colour; ``sky_color`` is a backdrop box around the whole scene.
    texture : {"stripes", "checker", None}
        Procedural texture multiplied onto the walls (and a checker onto the floor).
    cues : list of mappings
        Distal cues outside the maze: ``shape`` (sphere/box/cylinder), ``direction`` (degrees
        from the maze centre, counter-clockwise from +x), ``distance`` (beyond the maze border,
        default 2), ``height`` (centre height, default 1.0), ``size``, ``color``.
    light_direction : [x, y, z]
        Direction *towards* the light.
    ambient, diffuse, specular : float
        Light coefficients of TinyRenderer's Phong shading.
    shadow : bool
        Cast shadows (slower).
    panel_width : float or None
        Split every wall into panels about this long (cell units), each with its own colour drawn
        from ``panel_seed`` (replacing ``wall_colors``): walls with non-repeating detail along
        them, like the photographed office walls of the paper's Fig. 8 scene, so the view's
        layout changes with the position, not only with the heading. None (default): one colour
        per wall.
    panel_seed : int
        Seed of the panel colours (the same seed gives the same walls).
    """

    wall_height: float = 0.6
    wall_thickness: float = 0.06
    wall_colors: tuple[tuple[float, float, float], ...] = DEFAULT_WALL_COLORS
    floor_color: tuple[float, float, float] = (0.55, 0.55, 0.55)
    sky_color: tuple[float, float, float] = (0.75, 0.85, 0.95)
    texture: str | None = "stripes"
    cues: tuple[Mapping[str, Any], ...] = DEFAULT_CUES
    light_direction: tuple[float, float, float] = (0.4, 0.3, 1.0)
    ambient: float = 0.6
    diffuse: float = 0.5
    specular: float = 0.05
    shadow: bool = False
    panel_width: float | None = None
    panel_seed: int = 0

    def __post_init__(self) -> None:
        cues = tuple(_check_cue(i, c) for i, c in enumerate(self.cues or ()))
        object.__setattr__(self, "cues", cues)

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any] | SceneStyle | None) -> SceneStyle:
        """Build from a plain mapping; unknown keys and bad values fail with one line."""
        if cfg is None:
            return cls()
        if isinstance(cfg, SceneStyle):
            return cfg
        if not isinstance(cfg, Mapping):
            raise ConfigError(f"scene must be a mapping of style options, got {cfg!r}")
        allowed = [f.name for f in fields(cls)]
        for key in cfg:
            if key not in allowed:
                raise ConfigError(
                    f"unknown key 'scene.{key}'{suggest(str(key), allowed)}; allowed: {allowed_list(allowed)}"
                )
        kw = dict(cfg)
        if "wall_colors" in kw:
            kw["wall_colors"] = tuple(_rgb(c, "scene.wall_colors") for c in kw["wall_colors"])
            if len(kw["wall_colors"]) != 4:
                raise ConfigError(
                    "scene.wall_colors needs 4 colours (facing east, north, west, south)"
                )
        for key in ("floor_color", "sky_color"):
            if key in kw:
                kw[key] = _rgb(kw[key], f"scene.{key}")
        if "light_direction" in kw:
            kw["light_direction"] = tuple(float(v) for v in kw["light_direction"])
        if kw.get("texture") not in (None, "stripes", "checker"):
            raise ConfigError(
                f"scene.texture {kw['texture']!r} is unknown; allowed: 'stripes', 'checker', null"
            )
        if "cues" in kw:
            kw["cues"] = tuple(kw["cues"] or ())
        for key in ("wall_height", "wall_thickness", "ambient", "diffuse", "specular"):
            if key in kw:
                kw[key] = float(kw[key])
                if kw[key] < 0:
                    raise ConfigError(f"scene.{key} must be >= 0, got {kw[key]}")
        if kw.get("panel_width") is not None:
            try:
                kw["panel_width"] = float(kw["panel_width"])
            except (TypeError, ValueError):
                kw["panel_width"] = -1.0
            if not kw["panel_width"] > 0:
                raise ConfigError(
                    f"scene.panel_width must be a length > 0 or null, got {cfg['panel_width']!r}"
                )
        if "panel_seed" in kw:
            v = kw["panel_seed"]
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 0:
                raise ConfigError(f"scene.panel_seed must be an integer >= 0, got {v!r}")
            kw["panel_seed"] = int(v)
        return cls(**kw)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["cues"] = [dict(c) for c in self.cues]
        if self.panel_width is None:  # absent without panels: earlier cache keys stay valid
            del d["panel_width"], d["panel_seed"]
        return json.loads(json.dumps(d))

    def panels(
        self, walls: Sequence[tuple[float, float, float, float, int]]
    ) -> list[tuple[float, float, float, float, tuple[float, float, float]]]:
        """The coloured pieces ``(x0, y0, x1, y1, rgb)`` that make up ``walls``.

        Without ``panel_width`` one piece per wall in its facing's colour; with it, each wall is
        cut into ``max(1, round(length / panel_width))`` equal panels whose colours are drawn in
        order from ``numpy.random.default_rng(panel_seed)`` (each channel uniform in 0.1..0.95);
        the first and last panel reach ``wall_thickness / 2`` past the wall's ends, as a whole
        wall's box does, so corners stay closed.
        """
        if self.panel_width is None:
            return [(x0, y0, x1, y1, self.wall_colors[f]) for x0, y0, x1, y1, f in walls]
        rng = np.random.default_rng(self.panel_seed)
        out = []
        for x0, y0, x1, y1, _ in walls:
            n = max(1, round(float(np.hypot(x1 - x0, y1 - y0)) / self.panel_width))
            cols = rng.uniform(0.1, 0.95, size=(n, 3))
            ext = self.wall_thickness / 2 / max(float(np.hypot(x1 - x0, y1 - y0)), 1e-12)
            for k in range(n):
                a = k / n if k else -ext
                b = (k + 1) / n if k < n - 1 else 1.0 + ext
                rgb = tuple(round(float(v), 6) for v in cols[k])
                out.append((x0 + a * (x1 - x0), y0 + a * (y1 - y0),
                            x0 + b * (x1 - x0), y0 + b * (y1 - y0), rgb))  # fmt: skip
        return out


def _rgb(value: Any, where: str) -> tuple[float, float, float]:
    try:
        rgb = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: colours are [r, g, b] in 0..1, got {value!r}") from None
    if len(rgb) != 3 or not all(0.0 <= v <= 1.0 for v in rgb):
        raise ConfigError(f"{where}: colours are [r, g, b] in 0..1, got {value!r}")
    return rgb  # type: ignore[return-value]


def _check_cue(i: int, cue: Any) -> dict[str, Any]:
    where = f"scene.cues[{i}]"
    allowed = ("shape", "direction", "distance", "height", "size", "color")
    if not isinstance(cue, Mapping):
        raise ConfigError(f"{where} must be a mapping with keys {allowed_list(allowed)}")
    for key in cue:
        if key not in allowed:
            raise ConfigError(
                f"unknown key '{where}.{key}'{suggest(str(key), allowed)}; allowed: {allowed_list(allowed)}"
            )
    shape = cue.get("shape", "sphere")
    if shape not in _SHAPES:
        raise ConfigError(f"{where}.shape {shape!r} is unknown; allowed: {allowed_list(_SHAPES)}")
    return {
        "shape": shape,
        "direction": float(cue.get("direction", 0.0)),
        "distance": float(cue.get("distance", 2.0)),
        "height": float(cue.get("height", 1.0)),
        "size": float(cue.get("size", 0.9)),
        "color": _rgb(cue.get("color", (1.0, 1.0, 1.0)), f"{where}.color"),
    }


@dataclass(frozen=True)
class SceneSpec:
    """Geometry + style of a scene: the part of a render-cache key that describes the world.

    Attributes
    ----------
    cells : tuple of (x, y) cell centres, or None
        Free cells of a gridworld maze (unit cells); walls go around them. None: open arena.
    bounds : (xmin, ymin, xmax, ymax)
        Extent of the nodes (the arena walls sit ``margin`` outside it).
    margin : float
        Arena walls' distance from the outermost nodes (open arenas only).
    style : SceneStyle
    segments : tuple of (x0, y0, x1, y1), or None
        Walls of any orientation (a continuous arena's outline and obstacles, from its
        :class:`~cobelrun.envs.base.Geometry`); given, they replace the walls around ``cells``
        or ``bounds``, and the floor covers ``bounds``.
    """

    cells: tuple[tuple[float, float], ...] | None
    bounds: tuple[float, float, float, float]
    margin: float = 0.5
    style: SceneStyle = field(default_factory=SceneStyle)
    segments: tuple[tuple[float, float, float, float], ...] | None = None

    @classmethod
    def from_topology(cls, topology: Any, style: SceneStyle | Mapping[str, Any] | None = None,
                      margin: float = 0.5) -> SceneSpec:  # fmt: skip
        """The scene of a :class:`~cobelrun.envs.topology.Topology` (cells if it has them)."""
        pos = np.asarray(topology.positions, dtype=np.float64)
        cells = None
        if getattr(topology, "cells", None) is not None:
            cells = tuple((round(float(x), 6), round(float(y), 6)) for x, y in pos)
        lo, hi = pos.min(axis=0), pos.max(axis=0)
        bounds = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
        return cls(
            cells=cells, bounds=bounds, margin=float(margin), style=SceneStyle.from_config(style)
        )

    @classmethod
    def from_geometry(
        cls, geometry: Any, style: SceneStyle | Mapping[str, Any] | None = None
    ) -> SceneSpec:
        """The scene of a continuous arena: its wall segments on a floor over its bounds."""
        segs = tuple(tuple(round(float(v), 9) for v in w) for w in np.asarray(geometry.walls))
        return cls(cells=None, bounds=tuple(float(b) for b in geometry.bounds), margin=0.0,  # type: ignore[arg-type]
                   style=SceneStyle.from_config(style), segments=segs)  # fmt: skip

    def to_dict(self) -> dict[str, Any]:
        out = {
            "cells": None if self.cells is None else [list(c) for c in self.cells],
            "bounds": list(self.bounds),
            "margin": self.margin,
            "style": self.style.to_dict(),
        }
        if self.segments is not None:  # absent otherwise: earlier cache keys stay valid
            out["segments"] = [list(w) for w in self.segments]
        return out

    def walls(self) -> list[tuple[float, float, float, float, int]]:
        """Wall segments ``(x0, y0, x1, y1, facing)``; ``facing`` 0..3 = east, north, west, south.

        Collinear neighbouring segments with the same facing are merged (fewer bodies, faster
        rendering). Free-form ``segments`` face the side left of their direction (inwards for an
        outline listed counter-clockwise), coloured by the nearest compass facing.
        """
        if self.segments is not None:
            out = []
            for x0, y0, x1, y1 in self.segments:
                normal = np.arctan2(x1 - x0, -(y1 - y0))  # angle of (-dy, dx), the left normal
                facing = round(normal / (np.pi / 2)) % 4  # 0 east, 1 north, 2 west, 3 south
                out.append((x0, y0, x1, y1, int(facing)))
            return out
        if self.cells is None:
            x0, y0, x1, y1 = self.bounds
            m = self.margin
            x0, y0, x1, y1 = x0 - m, y0 - m, x1 + m, y1 + m
            return [
                (x0, y0, x0, y1, 0),
                (x0, y0, x1, y0, 1),
                (x1, y0, x1, y1, 2),
                (x0, y1, x1, y1, 3),
            ]
        free = {(round(x), round(y)) for x, y in self.cells}
        segs: dict[tuple[int, float], list[tuple[float, float]]] = {}
        for cx, cy in sorted(free):
            # side: (neighbour offset, facing of the wall face seen from inside the cell)
            for (dx, dy), facing in (((1, 0), 2), ((0, 1), 3), ((-1, 0), 0), ((0, -1), 1)):
                if (cx + dx, cy + dy) in free:
                    continue
                if dx:  # vertical wall at x = cx + dx / 2
                    segs.setdefault((facing, cx + dx / 2), []).append((cy - 0.5, cy + 0.5))
                else:
                    segs.setdefault((facing, cy + dy / 2), []).append((cx - 0.5, cx + 0.5))
        out = []
        for (facing, line), spans in sorted(segs.items()):
            spans.sort()
            merged = [list(spans[0])]
            for a, b in spans[1:]:
                if np.isclose(a, merged[-1][1]):
                    merged[-1][1] = b
                else:
                    merged.append([a, b])
            for a, b in merged:
                if facing in (0, 2):
                    out.append((line, a, line, b, facing))
                else:
                    out.append((a, line, b, line, facing))
        return out


@dataclass(frozen=True)
class CameraSpec:
    """The agent's camera.

    Attributes
    ----------
    height, width : int
        Image size in pixels (the whole panorama for several cameras).
    fov : float
        Horizontal field of view in degrees: of the single camera, or of the whole panorama when
        ``n_cameras > 1`` (e.g. 240 stitched from 4 cameras of 60 degrees, as Fig. 8).
    n_cameras : int
        Cameras side by side (same eye, headings spread over ``fov``); their images are
        concatenated left to right. Each covers ``fov / n_cameras`` degrees.
    eye_height : float
        Camera height above the floor (cell units).
    pitch : float
        Downward tilt in degrees (0 = level).
    near, far : float
        Clipping planes (cell units).
    vfov : float or None
        Vertical field of view in degrees. None (default): square pixels, i.e. the vertical field
        follows from the horizontal one and the image's aspect. Fig. 8's original stitched 90 x 90
        degree cameras and squeezed the panorama to 12 rows, so its 12 rows span 90 degrees.
    """

    height: int = 84
    width: int = 84
    fov: float = 90.0
    n_cameras: int = 1
    eye_height: float = 0.3
    pitch: float = 0.0
    near: float = 0.05
    far: float = 50.0
    vfov: float | None = None

    def __post_init__(self) -> None:
        for key in ("height", "width", "n_cameras"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 1:
                raise ConfigError(f"camera {key} must be a positive integer, got {v!r}")
        if self.n_cameras > self.width:
            raise ConfigError(
                f"camera n_cameras ({self.n_cameras}) cannot exceed width ({self.width})"
            )
        per = self.fov / self.n_cameras
        if not 0 < per < 170:
            raise ConfigError(
                f"camera fov per camera must be in (0, 170) degrees, got {self.fov} / {self.n_cameras} = {per:g}; "
                "use more cameras for a wide panorama"
            )
        if not 0 < self.near < self.far:
            raise ConfigError(f"camera needs 0 < near < far, got near={self.near}, far={self.far}")
        v = self.vfov
        if v is not None and (
            isinstance(v, bool) or not isinstance(v, int | float) or not 0 < v < 170
        ):
            raise ConfigError(f"camera vfov must be in (0, 170) degrees or null, got {self.vfov}")

    def to_dict(self) -> dict[str, Any]:
        d = {k: (int(v) if isinstance(v, np.integer) else v) for k, v in asdict(self).items()}
        if self.vfov is None:  # absent with square pixels: earlier cache keys stay valid
            del d["vfov"]
        return d

    def splits(self) -> list[tuple[int, float, float]]:
        """Per camera: (pixel columns, yaw offset from the heading in degrees, horizontal fov)."""
        cols = [len(c) for c in np.array_split(np.arange(self.width), self.n_cameras)]
        out, left = [], self.fov / 2.0
        for c in cols:
            span = self.fov * c / self.width
            out.append((c, left - span / 2.0, span))
            left -= span
        return out


def spec_hash(payload: Mapping[str, Any]) -> str:
    """sha256 of a JSON-able mapping (sorted keys); the first 20 hex digits."""
    blob = json.dumps(payload, sort_keys=True, separators=(",", ":")).encode()
    return hashlib.sha256(blob).hexdigest()[:20]


# ---------------------------------------------------------------------- pybullet side
@contextlib.contextmanager
def _quiet_stdout() -> Iterator[None]:
    """Silence C-level prints on fd 1 (pybullet announces its build time on import)."""
    try:
        sys.stdout.flush()
        saved = os.dup(1)
    except (OSError, ValueError, AttributeError):
        yield
        return
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
            yield
            _flush_c_stdout()
    finally:
        os.dup2(saved, 1)
        os.close(saved)


def _flush_c_stdout() -> None:
    with contextlib.suppress(Exception):
        import ctypes

        ctypes.CDLL(None).fflush(None)


def import_pybullet() -> Any:
    """Import pybullet, or fail with the extra to install."""
    if "pybullet" in sys.modules and sys.modules["pybullet"] is not None:
        return sys.modules["pybullet"]
    try:
        with _quiet_stdout():
            import pybullet
    except ImportError:
        raise CobelError(
            "online rendering needs pybullet: pip install 'cobelrun[render]' "
            "(or render offline from a cache: env.observation.render=offline)"
        ) from None
    return pybullet


def pybullet_version() -> str | None:
    """Installed pybullet version from package metadata (does not import pybullet)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("pybullet")
    except PackageNotFoundError:
        return None


def _write_png(path: Path, img: np.ndarray) -> None:
    h, w, _ = img.shape
    raw = b"".join(b"\x00" + img[r].tobytes() for r in range(h))

    def chunk(tag: bytes, data: bytes) -> bytes:
        crc = zlib.crc32(tag + data) & 0xFFFFFFFF
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", crc)

    header = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(raw))
        + chunk(b"IEND", b"")
    )


def _texture(kind: str) -> np.ndarray:
    """A 64 x 64 grey-scale procedural texture (multiplied onto the object's colour)."""
    i, j = np.indices((64, 64))
    if kind == "checker":
        v = np.where(((i // 16) + (j // 16)) % 2 == 0, 255, 170)
    else:  # vertical stripes + a darker base band
        v = np.where((j // 8) % 2 == 0, 255, 200)
        v = np.where(i > 52, 140, v)
    return np.repeat(v[..., None], 3, axis=2).astype(np.uint8)


class Scene:
    """A pybullet world (DIRECT mode) holding one :class:`SceneSpec`; renders camera images.

    Parameters
    ----------
    spec : SceneSpec
    renderer : {"tiny", "egl"}
        ``"tiny"``: CPU TinyRenderer (default, deterministic). ``"egl"``: load pybullet's EGL
        plugin before building the scene; if it does not load, fall back to TinyRenderer and say
        so on stderr. :attr:`renderer` is the renderer actually used.
    """

    def __init__(self, spec: SceneSpec, renderer: str = "tiny") -> None:
        if renderer not in RENDERERS:
            raise ConfigError(
                f"renderer {renderer!r} is unknown{suggest(str(renderer), RENDERERS)}; allowed: {allowed_list(RENDERERS)}"
            )
        self.spec = spec
        self.p = p = import_pybullet()
        self.client = p.connect(p.DIRECT)
        self._plugin = -1
        self.renderer = "tiny"
        if renderer == "egl":
            self._plugin = self._load_egl()
            self.renderer = "egl" if self._plugin >= 0 else "tiny"
        self._flag = p.ER_BULLET_HARDWARE_OPENGL if self.renderer == "egl" else p.ER_TINY_RENDERER
        self._build()

    def _load_egl(self) -> int:
        p = self.p
        plugin = -1
        try:
            import pkgutil

            egl = pkgutil.get_loader("eglRenderer")
            if egl is not None:
                with _quiet_stdout():
                    plugin = p.loadPlugin(
                        egl.get_filename(), "_eglRendererPlugin", physicsClientId=self.client
                    )
            if plugin < 0:
                with _quiet_stdout():
                    plugin = p.loadPlugin("eglRendererPlugin", physicsClientId=self.client)
        except Exception:
            plugin = -1
        if plugin < 0:
            print(
                "cobel: EGL renderer plugin could not be loaded; falling back to TinyRenderer (CPU)",
                file=sys.stderr,
            )
        return plugin

    # ------------------------------------------------------------------ building
    def _box(self, half: Sequence[float], pos: Sequence[float], rgb: Sequence[float],
             texture: int | None = None, yaw: float = 0.0) -> int:  # fmt: skip
        p, c = self.p, self.client
        vs = p.createVisualShape(
            p.GEOM_BOX, halfExtents=list(half), rgbaColor=[*rgb, 1.0], physicsClientId=c
        )
        orn = p.getQuaternionFromEuler([0.0, 0.0, float(yaw)])
        body = p.createMultiBody(0, -1, vs, basePosition=list(pos), baseOrientation=orn,
                                 physicsClientId=c)  # fmt: skip
        if texture is not None:
            p.changeVisualShape(
                body, -1, textureUniqueId=texture, rgbaColor=[*rgb, 1.0], physicsClientId=c
            )
        return body

    def _load_texture(self, kind: str) -> int:
        # pybullet reads the image when it loads it: the file is removed at once, so a
        # process that is killed later leaves no folder behind
        with tempfile.TemporaryDirectory(prefix="cobel-scene-") as tmp:
            path = Path(tmp) / f"{kind}.png"
            _write_png(path, _texture(kind))
            return int(self.p.loadTexture(str(path), physicsClientId=self.client))

    def _build(self) -> None:
        p, c = self.p, self.client
        s = self.spec
        st = s.style
        p.resetSimulation(physicsClientId=c)
        wall_tex = self._load_texture(st.texture) if st.texture else None
        floor_tex = self._load_texture("checker") if st.texture else None
        x0, y0, x1, y1 = s.bounds
        pad = (
            0.5 if s.cells is not None else (s.margin if s.segments is None else st.wall_thickness)
        )
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        hx, hy = (x1 - x0) / 2 + pad, (y1 - y0) / 2 + pad
        # floor: one slab under the maze (or one tile per cell for gridworld mazes)
        if s.cells is None:
            self._box([hx, hy, 0.01], [cx, cy, -0.01], st.floor_color, floor_tex)
        else:
            for x, y in s.cells:
                self._box([0.5, 0.5, 0.01], [x, y, -0.01], st.floor_color, floor_tex)
        # walls (cut into coloured panels when style.panel_width is set)
        h, t = st.wall_height, st.wall_thickness
        panels = st.panels(s.walls())
        whole = st.panel_width is None  # one box per wall, half a thickness past each end
        for wx0, wy0, wx1, wy1, rgb in panels:
            length = float(np.hypot(wx1 - wx0, wy1 - wy0)) + (t if whole else 0.0)
            mid = [(wx0 + wx1) / 2, (wy0 + wy1) / 2, h / 2]
            if s.segments is not None:
                # a free-form wall: a box along the segment, rotated to its direction
                yaw = float(np.arctan2(wy1 - wy0, wx1 - wx0))
                self._box([length / 2, t / 2, h / 2], mid, rgb, wall_tex, yaw=yaw)
            elif np.isclose(wx0, wx1):
                self._box([t / 2, length / 2, h / 2], mid, rgb, wall_tex)
            else:
                self._box([length / 2, t / 2, h / 2], mid, rgb, wall_tex)
        # distal cues outside the maze
        radius = max(hx, hy)
        for cue in st.cues:
            a = np.deg2rad(cue["direction"])
            d = radius + cue["distance"]
            pos = [cx + d * np.cos(a), cy + d * np.sin(a), cue["height"]]
            r = cue["size"] / 2
            rgba = [*cue["color"], 1.0]
            if cue["shape"] == "sphere":
                vs = p.createVisualShape(p.GEOM_SPHERE, radius=r, rgbaColor=rgba, physicsClientId=c)
            elif cue["shape"] == "cylinder":
                vs = p.createVisualShape(
                    p.GEOM_CYLINDER, radius=r, length=2 * r, rgbaColor=rgba, physicsClientId=c
                )
            else:
                vs = p.createVisualShape(
                    p.GEOM_BOX, halfExtents=[r, r, r], rgbaColor=rgba, physicsClientId=c
                )
            p.createMultiBody(0, -1, vs, basePosition=pos, physicsClientId=c)
        # backdrop: a large box seen from inside (sky / room walls), far enough to hold the cues
        far = radius + max([cue["distance"] for cue in st.cues], default=0.0) + 3.0
        for k in range(4):
            a = k * np.pi / 2
            pos = [cx + far * np.cos(a), cy + far * np.sin(a), far / 2 - 0.5]
            half = [0.05, far, far / 2] if k % 2 == 0 else [far, 0.05, far / 2]
            self._box(half, pos, st.sky_color)

    # ------------------------------------------------------------------ rendering
    def render(self, x: float, y: float, heading: float, camera: CameraSpec) -> np.ndarray:
        """RGB image ``(camera.height, camera.width, 3)`` uint8 seen from pose ``(x, y, heading)``.

        ``heading`` is in radians, counter-clockwise from +x; the image centre looks along it.
        """
        p, c = self.p, self.client
        st = self.spec.style
        eye = [float(x), float(y), camera.eye_height]
        tilt = np.deg2rad(camera.pitch)
        parts = []
        for cols, yaw_deg, hfov in camera.splits():
            yaw = heading + np.deg2rad(yaw_deg)
            fwd = [np.cos(yaw) * np.cos(tilt), np.sin(yaw) * np.cos(tilt), -np.sin(tilt)]
            target = [eye[0] + fwd[0], eye[1] + fwd[1], eye[2] + fwd[2]]
            view = p.computeViewMatrix(eye, target, [0, 0, 1], physicsClientId=c)
            aspect = cols / camera.height
            if camera.vfov is None:  # square pixels
                vfov = np.rad2deg(2 * np.arctan(np.tan(np.deg2rad(hfov) / 2) / aspect))
            else:  # pybullet's aspect is the ratio of the frustum's tangents, not of the pixels
                vfov = camera.vfov
                aspect = np.tan(np.deg2rad(hfov) / 2) / np.tan(np.deg2rad(vfov) / 2)
            proj = p.computeProjectionMatrixFOV(
                vfov, aspect, camera.near, camera.far, physicsClientId=c
            )
            out = p.getCameraImage(
                cols, camera.height, view, proj,
                lightDirection=list(st.light_direction), lightAmbientCoeff=st.ambient,
                lightDiffuseCoeff=st.diffuse, lightSpecularCoeff=st.specular,
                shadow=int(st.shadow), renderer=self._flag,
                flags=p.ER_NO_SEGMENTATION_MASK, physicsClientId=c,
            )  # fmt: skip
            rgba = np.asarray(out[2], dtype=np.uint8).reshape(camera.height, cols, 4)
            parts.append(rgba[..., :3])
        return np.ascontiguousarray(np.concatenate(parts, axis=1) if len(parts) > 1 else parts[0])

    def close(self) -> None:
        """Disconnect from pybullet (idempotent)."""
        if self.client is not None and self.client >= 0:
            with contextlib.suppress(Exception):
                if self._plugin >= 0:
                    self.p.unloadPlugin(self._plugin, physicsClientId=self.client)
                self.p.disconnect(physicsClientId=self.client)
            self.client = -1

    def __enter__(self) -> Scene:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self.close()
