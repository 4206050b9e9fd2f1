"""Observation modules for pose-based environments (paper section 2.2.3).

A module turns the agent's pose (node, heading) into what the agent sees. It is *bound* to a
:class:`~cobelrun.envs.topology.Topology` by the environment, which then calls
:meth:`ObservationModule.observe` with the pose and the environment's random generator (so noise
is seeded like every other draw of the environment).

- :class:`PoseObservation`: ``(x, y, cos heading, sin heading)``.
- :class:`ImageObservation`: camera images of the 3D scene, rendered online with pybullet or read
  from the offline render cache (``render="offline"`` never imports pybullet).
- :class:`NoisyObservation`: Gaussian or salt-and-pepper noise on another module's output.
- :class:`MultiSensoryObservation`: a ``Dict`` of several modules (for SB3's MultiInputPolicy;
  the keys name the network input each observation goes to).
"""

from __future__ import annotations

import abc
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from cobelrun.errors import CobelError, ConfigError, allowed_list, suggest

__all__ = [
    "ImageObservation",
    "MultiSensoryObservation",
    "NoisyObservation",
    "ObservationModule",
    "PoseObservation",
]


class ObservationModule(abc.ABC):
    """Base class: :meth:`bind` to a topology, then :meth:`observe` poses."""

    space: gym.Space
    topology: Any = None

    def bind(self, topology: Any) -> None:
        """Attach to a topology and set :attr:`space`. Called once by the environment."""
        self.topology = topology
        self.space = self._make_space(topology)

    @abc.abstractmethod
    def _make_space(self, topology: Any) -> gym.Space: ...

    @abc.abstractmethod
    def observe(self, node: int, heading: int, rng: np.random.Generator) -> Any:
        """Observation at pose ``(node, heading index)``; ``rng`` draws any noise."""

    def render_at_pose(
        self, x: float, y: float, heading_rad: float, rng: np.random.Generator | None = None
    ) -> Any:
        """Observation at any pose ``(x, y, heading)`` in world units, also between nodes.

        Used for spatial activity maps. ``rng`` draws any noise (default: a generator seeded
        with 0, so the environment's own stream is never touched).
        """
        raise CobelError(f"{type(self).__name__} cannot observe poses between graph nodes")

    def observe_grid(
        self,
        positions: np.ndarray,
        headings_rad: np.ndarray,
        rng: np.random.Generator | None = None,
    ) -> Any:
        """Observations at every ``positions x headings`` pose: ``(M, D, *obs_shape)``.

        ``positions`` is ``(M, 2)`` world ``(x, y)``, ``headings_rad`` ``(D,)``. The default
        calls :meth:`render_at_pose` per pose; image modules read a render cache when offline.
        """
        rng = rng if rng is not None else np.random.default_rng(0)
        pos = np.asarray(positions, np.float64).reshape(-1, 2)
        heads = np.asarray(headings_rad, np.float64).reshape(-1)
        obs = [[self.render_at_pose(x, y, h, rng) for h in heads] for x, y in pos]
        return _stack_grid(obs)

    def image_modules(self) -> list[ImageObservation]:
        """Image modules inside this module (for building render caches)."""
        return []

    def close(self) -> None:  # noqa: B027  (optional hook, nothing to release by default)
        """Release resources (renderers)."""


def _stack_grid(obs: list[list[Any]]) -> Any:
    """Nested lists ``[position][heading]`` of observations -> ``(M, D, ...)`` (dicts per key)."""
    first = obs[0][0]
    if isinstance(first, Mapping):
        return {k: np.stack([np.stack([o[k] for o in row]) for row in obs]) for k in first}
    return np.stack([np.stack(row) for row in obs])


class PoseObservation(ObservationModule):
    """The pose as ``(x, y, cos heading, sin heading)``, float32.

    Parameters
    ----------
    normalize : bool
        Scale ``x`` and ``y`` to [0, 1] over the extent of the graph's nodes (default True).
    """

    def __init__(self, normalize: bool = True) -> None:
        self.normalize = bool(normalize)

    def _make_space(self, topology: Any) -> gym.Space:
        pos = np.asarray(topology.positions, dtype=np.float64)
        self._lo = pos.min(axis=0)
        span = pos.max(axis=0) - self._lo
        self._span = np.where(span > 0, span, 1.0)
        if self.normalize:
            xy = (pos - self._lo) / self._span
        else:
            xy = pos
        self._table = np.empty((topology.n_nodes, topology.n_directions, 4), np.float32)
        self._table[..., :2] = xy[:, None, :]
        self._table[..., 2] = np.cos(topology.directions)[None, :]
        self._table[..., 3] = np.sin(topology.directions)[None, :]
        low = np.array([*xy.min(axis=0), -1.0, -1.0], np.float32)
        high = np.array([*xy.max(axis=0), 1.0, 1.0], np.float32)
        return spaces.Box(low=low, high=high, dtype=np.float32)

    def observe(self, node: int, heading: int, rng: np.random.Generator) -> np.ndarray:
        return self._table[node, heading].copy()

    def render_at_pose(
        self, x: float, y: float, heading_rad: float, rng: np.random.Generator | None = None
    ) -> np.ndarray:
        xy = np.array([x, y], np.float64)
        if self.normalize:
            xy = (xy - self._lo) / self._span
        return np.array([*xy, np.cos(heading_rad), np.sin(heading_rad)], np.float32)


#: Sources of images.
RENDER_MODES: tuple[str, ...] = ("online", "offline")
IMAGE_DTYPES: tuple[str, ...] = ("uint8", "float32")


class ImageObservation(ObservationModule):
    """Camera images of the 3D scene at the agent's pose.

    The scene is built from the bound topology (walls around a gridworld's cells, or an open arena)
    with pybullet (:mod:`cobelrun.render.scene`). Images are rendered at ``height x width``, or at
    ``render_size`` and then resized (area average) to ``height x width``.

    Parameters
    ----------
    height, width : int
        Observation size in pixels (Fig. 6A: 84 x 84; Fig. 8: 12 x 48 panoramas).
    fov : float
        Horizontal field of view in degrees (the whole panorama when ``n_cameras > 1``).
    n_cameras : int
        Cameras stitched side by side (e.g. 4 for a 240 degree panorama, as Fig. 8).
    eye_height, pitch : float
        Camera height (cell units) and downward tilt (degrees).
    vfov : float, optional
        Vertical field of view in degrees (default: square pixels; Fig. 8's original: 90).
    channels_first : bool
        ``(C, H, W)`` layout (default, what SB3's CnnPolicy expects) or ``(H, W, C)``.
    dtype : {"uint8", "float32"}
        ``uint8`` in [0, 255] (default: SB3's CnnPolicy recognises it as an image and divides by
        255 itself, and replay memories stay 4x smaller); ``float32`` normalised to [0, 1]
        (use SB3 with ``policy_kwargs={"normalize_images": False}``).
    grayscale : bool
        One luminance channel instead of RGB.
    render : {"online", "offline"}
        ``online``: render with pybullet. ``offline``: read the render cache built by
        ``cobel render-cache`` (pybullet is not imported).
    renderer : {"tiny", "egl"}
        pybullet renderer for online rendering and cache building.
    scene : mapping, optional
        Scene style (:class:`~cobelrun.render.scene.SceneStyle`: wall colours, texture, cues,
        lighting).
    render_size : [h, w], optional
        Render at this size, then resize to ``height x width``.
    cache_dir : str, optional
        Render-cache folder (default ``$COBEL_CACHE`` or ``~/.cache/cobel/render``).
    reuse_views : bool
        Online: render each graph pose once, on its first visit, and hand out copies of that
        view on later visits (the scene does not change during a run and pybullet renders a
        pose the same every time, so a run's results do not change), up to
        :data:`ONLINE_VIEWS_BYTES` of views. ``false``: render on every step (what Fig. 4's
        online frame times measure).
    """

    def __init__(
        self,
        height: int = 84,
        width: int = 84,
        fov: float = 90.0,
        n_cameras: int = 1,
        eye_height: float = 0.3,
        pitch: float = 0.0,
        channels_first: bool = True,
        dtype: str = "uint8",
        grayscale: bool = False,
        render: str = "online",
        renderer: str = "tiny",
        scene: Mapping[str, Any] | None = None,
        render_size: Sequence[int] | None = None,
        cache_dir: str | None = None,
        reuse_views: bool = True,
        vfov: float | None = None,
    ) -> None:
        from cobelrun.render.scene import RENDERERS, CameraSpec, SceneStyle

        for key, value, allowed in (
            ("render", render, RENDER_MODES),
            ("dtype", dtype, IMAGE_DTYPES),
            ("renderer", renderer, RENDERERS),
        ):
            if value not in allowed:
                raise ConfigError(
                    f"observation {key} {value!r} is unknown{suggest(str(value), allowed)}; allowed: {allowed_list(allowed)}"
                )
        for key, value in (("height", height), ("width", width)):
            if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
                raise ConfigError(f"observation {key} must be a positive integer, got {value!r}")
        self.height, self.width = int(height), int(width)
        if render_size is None:
            rh, rw = self.height, self.width
        else:
            if len(render_size) != 2:
                raise ConfigError(
                    f"observation render_size must be [height, width], got {render_size!r}"
                )
            rh, rw = (int(v) for v in render_size)
            if rh < self.height or rw < self.width:
                raise ConfigError(
                    f"observation render_size {[rh, rw]} must be at least the image size {[self.height, self.width]}"
                )
        from cobelrun.safety import check_allocation

        # before anything is built: one view's render buffers (pybullet's RGBA, depth and
        # segmentation, 12 B per pixel, and the RGB copy), its observation, and the observation
        # space's low and high bounds (gymnasium's Box holds both at full size)
        obs = self.height * self.width * (1 if grayscale else 3) * (4 if dtype == "float32" else 1)
        check_allocation("env.observation.height/width", rh * rw * 15 + 3 * obs,
                         f"one {rh}x{rw} rendered view and its observation space",
                         "lower env.observation.height and width")  # fmt: skip
        self.camera = CameraSpec(height=rh, width=rw, fov=float(fov), n_cameras=int(n_cameras),
                                 eye_height=float(eye_height), pitch=float(pitch),
                                 vfov=vfov)  # fmt: skip
        self.style = SceneStyle.from_config(scene)
        self.channels_first = bool(channels_first)
        self.dtype = dtype
        self.grayscale = bool(grayscale)
        self.render = render
        self.renderer = renderer
        self.cache_dir = None if cache_dir is None else str(cache_dir)
        self._scene: Any = None
        self._images: np.ndarray | None = None  # offline: (N, D, H, W, 3) uint8
        self._obs_table: np.ndarray | None = None  # offline: processed observations
        # offline views at poses off the graph (probe grids), by rounded (x, y, heading)
        self._pose_views: dict[tuple[float, float, float], np.ndarray] = {}
        # online: graph views rendered once and kept (the scene is static), up to a byte budget
        self.reuse_views = bool(reuse_views)
        self._online_views: dict[tuple[int, int], np.ndarray] = {}

    # ------------------------------------------------------------------ binding
    def bind(self, topology: Any) -> None:
        from cobelrun.render.cache import building
        from cobelrun.render.scene import SceneSpec

        if self.render == "offline" or building():  # every view at once: cache (+ table)
            from cobelrun.safety import check_allocation

            views = len(topology.positions) * len(topology.directions)
            per_view = self.camera.height * self.camera.width * 3 + (
                0 if building() else self._obs_bytes()
            )
            check_allocation("env.observation.height/width", views * per_view,
                             f"{views} pre-rendered {self.camera.height}x{self.camera.width} "
                             "views and their observations",
                             "lower env.observation.height and width")  # fmt: skip
        super().bind(topology)
        self.scene_spec = SceneSpec.from_topology(topology, self.style)
        if self.render == "offline":
            from cobelrun.render import cache

            if not cache.building():
                self._load_offline()

    def _obs_bytes(self) -> int:
        """Bytes of one observation (the processed image)."""
        c = 1 if self.grayscale else 3
        return self.height * self.width * c * (4 if self.dtype == "float32" else 1)

    def _load_offline(self) -> None:
        """Load this module's pre-rendered views (every frame block checked against its checksum
        once, here) and process them into the read-only observation table that :meth:`observe`
        hands out views of."""
        from cobelrun.render import cache

        self._images = cache.load(self.cache_request())
        self._obs_table = self.process(self._images)
        self._obs_table.setflags(write=False)

    def cache_request(
        self, positions: np.ndarray | None = None, headings_rad: np.ndarray | None = None
    ) -> Any:
        """The render-cache request (scene, camera, poses, renderer) of this module.

        Default poses: every (node, heading) of the bound topology; give ``positions`` (M, 2)
        and ``headings_rad`` (D,) for another grid of poses (e.g. an activity-map probe grid).
        """
        from cobelrun.render.cache import CacheRequest

        t = self.topology
        if t is None:
            raise CobelError("the image observation is not bound to a topology yet")
        return CacheRequest(
            scene=self.scene_spec,
            camera=self.camera,
            positions=np.asarray(t.positions if positions is None else positions, np.float64),
            directions=np.asarray(t.directions if headings_rad is None else headings_rad),
            renderer=self.renderer,
            cache_dir=None if self.cache_dir is None else Path(self.cache_dir),
        )

    def _make_space(self, topology: Any) -> gym.Space:
        c = 1 if self.grayscale else 3
        shape = (
            (c, self.height, self.width) if self.channels_first else (self.height, self.width, c)
        )
        if self.dtype == "uint8":
            return spaces.Box(low=0, high=255, shape=shape, dtype=np.uint8)
        return spaces.Box(low=0.0, high=1.0, shape=shape, dtype=np.float32)

    # ------------------------------------------------------------------ images
    def process(self, rgb: np.ndarray) -> np.ndarray:
        """Raw renders ``(..., h, w, 3)`` uint8 -> observations (resize, grey, layout, dtype)."""
        img = rgb
        rh, rw = img.shape[-3], img.shape[-2]
        if (rh, rw) != (self.height, self.width):
            img = _resize_area(img, self.height, self.width)
        if self.grayscale:
            lum = img.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
            img = np.clip(np.rint(lum), 0, 255).astype(np.uint8)[..., None]
        if self.channels_first:
            img = np.moveaxis(img, -1, -3)
        if self.dtype == "float32":
            img = img.astype(np.float32) * np.float32(1.0 / 255.0)
        return np.ascontiguousarray(img)

    def render_raw(self, node: int, heading: int) -> np.ndarray:
        """Render pose ``(node, heading)`` online: ``(h, w, 3)`` uint8 at the camera size."""
        x, y = self.topology.positions[node]
        return self.render_raw_at(x, y, float(self.topology.directions[heading]))

    def render_raw_at(self, x: float, y: float, heading_rad: float) -> np.ndarray:
        """Render any pose online with pybullet: ``(h, w, 3)`` uint8 at the camera size."""
        if self._scene is None:
            from cobelrun.render.scene import Scene

            self._scene = Scene(self.scene_spec, renderer=self.renderer)
        return self._scene.render(float(x), float(y), float(heading_rad), self.camera)

    def render_at_pose(
        self, x: float, y: float, heading_rad: float, rng: np.random.Generator | None = None
    ) -> np.ndarray:
        """The observation at any pose: rendered online, or offline from a loaded cache.

        Offline, the pose must be a graph pose (node position and heading) or part of a probe
        grid loaded by :meth:`observe_grid`; anything else is an error naming the command that
        renders it.
        """
        if self.render == "online":
            return self.process(self.render_raw_at(x, y, heading_rad))
        key = _pose_key(x, y, heading_rad)
        if key not in self._pose_views:
            t = self.topology
            if self._obs_table is None:
                self._load_offline()
            assert self._obs_table is not None
            hit_n = np.flatnonzero(np.all(np.isclose(t.positions, [x, y], atol=1e-6), axis=1))
            diff = np.abs(np.angle(np.exp(1j * (np.asarray(t.directions) - heading_rad))))
            hit_h = np.flatnonzero(diff < 1e-6)
            if hit_n.size and hit_h.size:
                return self._obs_table[hit_n[0], hit_h[0]].copy()
            from cobelrun.render.cache import build_hint

            raise CobelError(
                f"pose (x {x:g}, y {y:g}, heading {np.rad2deg(heading_rad):g} deg) is not in the "
                f"loaded render caches (offline rendering); build the probe grid with: {build_hint()}"
            )
        return self._pose_views[key].copy()

    def observe_grid(
        self,
        positions: np.ndarray,
        headings_rad: np.ndarray,
        rng: np.random.Generator | None = None,
    ) -> np.ndarray:
        """Observations at every ``positions x headings`` pose, ``(M, D, *obs_shape)``.

        Offline: read from the render cache of exactly this grid (``cobel render-cache``
        builds it for tasks with an activity-map monitor); the views are also kept for
        :meth:`render_at_pose`. Online: read from that cache too where it exists for the
        installed pybullet (the same pixels, content-addressed), else rendered with pybullet.
        """
        from cobelrun.render import cache

        pos = np.asarray(positions, np.float64).reshape(-1, 2)
        heads = np.asarray(headings_rad, np.float64).reshape(-1)
        request = self.cache_request(pos, heads)
        if self.render == "online":
            try:
                return self.process(cache.load(request))
            except CobelError:  # no cache (or a stale one): render
                raw = np.stack([[self.render_raw_at(x, y, h) for h in heads] for x, y in pos])
                return self.process(raw)
        obs = self.process(cache.load(request))
        for i, (x, y) in enumerate(pos):
            for j, h in enumerate(heads):
                self._pose_views[_pose_key(x, y, h)] = obs[i, j]
        return obs

    def observe(self, node: int, heading: int, rng: np.random.Generator) -> np.ndarray:
        """Online: render and process the view. Offline: a read-only view into the loaded table
        (no copy: a step costs an index, at any image size; writing into it raises)."""
        if self._obs_table is not None:
            return self._obs_table[node, heading]
        if self.render == "offline":  # bound while the cache was being built
            self._load_offline()
            assert self._obs_table is not None
            return self._obs_table[node, heading]
        # online: a graph pose's view is rendered once (the scene does not change during a
        # run, and pybullet renders a pose the same every time) and kept; every visit gets a
        # copy (gymnasium's contract: new observation data on every call; a few kB). Past
        # ONLINE_VIEWS_BYTES further views are rendered on every visit.
        if not self.reuse_views:
            return self.process(self.render_raw(node, heading))
        key = (node, heading)
        view = self._online_views.get(key)
        if view is None:
            view = self.process(self.render_raw(node, heading))
            if (len(self._online_views) + 1) * view.nbytes > ONLINE_VIEWS_BYTES:  # same sizes
                return view
            self._online_views[key] = view
        return view.copy()

    def image_modules(self) -> list[ImageObservation]:
        return [self]

    def close(self) -> None:
        if self._scene is not None:
            self._scene.close()
            self._scene = None

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_scene"] = None  # a pybullet connection does not travel
        state["_online_views"] = {}  # re-rendered where needed
        return state


#: Bytes of processed online views an :class:`ImageObservation` keeps per graph pose (e.g. the
#: 462 poses of Fig. 8's 12 x 48 panoramas take 0.8 MB, 1,000 poses of 75 x 300 images 68 MB).
ONLINE_VIEWS_BYTES = 128 * 2**20


def _pose_key(x: float, y: float, heading_rad: float) -> tuple[float, float, float]:
    return (round(float(x), 6), round(float(y), 6), round(float(heading_rad) % (2 * np.pi), 6))


def _resize_area(img: np.ndarray, h: int, w: int) -> np.ndarray:
    """Area-average resize of ``(..., H, W, C)`` uint8 to ``(..., h, w, C)`` (downscaling)."""
    x = _bin_mean(img.astype(np.float32), h, img.ndim - 3)
    x = _bin_mean(x, w, img.ndim - 2)
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def _bin_mean(x: np.ndarray, n: int, axis: int) -> np.ndarray:
    size = x.shape[axis]
    starts = np.searchsorted((np.arange(size) * n) // size, np.arange(n))
    counts = np.diff(np.append(starts, size)).astype(np.float32)
    shape = [1] * x.ndim
    shape[axis] = n
    return np.add.reduceat(x, starts, axis=axis) / counts.reshape(shape)


NOISE_KINDS: tuple[str, ...] = ("gaussian", "salt_pepper")


class NoisyObservation(ObservationModule):
    """Noise on another module's observations (imprecise biological senses).

    Parameters
    ----------
    base : ObservationModule
        The module whose output is corrupted (a Box space).
    kind : {"gaussian", "salt_pepper"}
        ``gaussian``: add N(0, std^2) in units of the observation's [low, high] range.
        ``salt_pepper``: set a fraction ``amount`` of the entries to low or high.
    std : float
        Gaussian noise standard deviation as a fraction of the value range (default 0.05).
    amount : float
        Fraction of entries hit by salt-and-pepper noise (default 0.02).

    Noise is drawn from the environment's ``np_random``, so it is seeded with the environment.
    Results are clipped to the space and keep its dtype.
    """

    def __init__(
        self,
        base: ObservationModule,
        kind: str = "gaussian",
        std: float = 0.05,
        amount: float = 0.02,
    ) -> None:
        if not isinstance(base, ObservationModule):
            raise ConfigError(
                f"noise base must be an observation module, got {type(base).__name__}"
            )
        if kind not in NOISE_KINDS:
            raise ConfigError(
                f"noise kind {kind!r} is unknown{suggest(str(kind), NOISE_KINDS)}; allowed: {allowed_list(NOISE_KINDS)}"
            )
        if not float(std) >= 0 or not 0 <= float(amount) <= 1:
            raise ConfigError(f"noise needs std >= 0 and amount in [0, 1], got {std}, {amount}")
        self.base, self.kind, self.std, self.amount = base, kind, float(std), float(amount)

    def bind(self, topology: Any) -> None:
        self.base.bind(topology)
        super().bind(topology)

    def _make_space(self, topology: Any) -> gym.Space:
        space = self.base.space
        if not isinstance(space, spaces.Box):
            raise ConfigError(
                f"noise needs a Box observation to corrupt, got {type(space).__name__}"
            )
        self._low = space.low.astype(np.float32)
        self._high = space.high.astype(np.float32)
        return space

    def observe(self, node: int, heading: int, rng: np.random.Generator) -> np.ndarray:
        return self._corrupt(self.base.observe(node, heading, rng), rng)

    def render_at_pose(
        self, x: float, y: float, heading_rad: float, rng: np.random.Generator | None = None
    ) -> np.ndarray:
        rng = rng if rng is not None else np.random.default_rng(0)
        return self._corrupt(self.base.render_at_pose(x, y, heading_rad, rng), rng)

    def observe_grid(
        self,
        positions: np.ndarray,
        headings_rad: np.ndarray,
        rng: np.random.Generator | None = None,
    ) -> np.ndarray:
        rng = rng if rng is not None else np.random.default_rng(0)
        return self._corrupt(self.base.observe_grid(positions, headings_rad, rng), rng)

    def _corrupt(self, clean: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        x = clean.astype(np.float32)
        if self.kind == "gaussian":
            x = x + rng.standard_normal(x.shape, dtype=np.float32) * (
                self.std * (self._high - self._low)
            )
        else:
            hit = rng.random(x.shape) < self.amount
            salt = rng.random(x.shape) < 0.5
            x = np.where(hit, np.where(salt, self._high, self._low), x)
        x = np.clip(x, self._low, self._high)
        if np.issubdtype(self.space.dtype, np.integer):
            x = np.rint(x)
        return x.astype(self.space.dtype)

    def image_modules(self) -> list[ImageObservation]:
        return self.base.image_modules()

    def close(self) -> None:
        self.base.close()


class MultiSensoryObservation(ObservationModule):
    """Several modules at once: a ``Dict`` observation (e.g. ``{image: ..., pose: ...}``).

    Parameters
    ----------
    modules : mapping name -> ObservationModule
        The keys name the inputs (SB3's MultiInputPolicy routes each to its own extractor).
    """

    def __init__(self, modules: Mapping[str, ObservationModule]) -> None:
        if not isinstance(modules, Mapping) or not modules:
            raise ConfigError("multisensory observation needs a non-empty mapping name -> module")
        for name, m in modules.items():
            if not isinstance(m, ObservationModule):
                raise ConfigError(f"multisensory module {name!r} is not an observation module")
        self.modules = {str(k): v for k, v in modules.items()}

    def bind(self, topology: Any) -> None:
        for m in self.modules.values():
            m.bind(topology)
        super().bind(topology)

    def _make_space(self, topology: Any) -> gym.Space:
        return spaces.Dict({k: m.space for k, m in self.modules.items()})

    def observe(self, node: int, heading: int, rng: np.random.Generator) -> dict[str, Any]:
        return {k: m.observe(node, heading, rng) for k, m in self.modules.items()}

    def render_at_pose(
        self, x: float, y: float, heading_rad: float, rng: np.random.Generator | None = None
    ) -> dict[str, Any]:
        rng = rng if rng is not None else np.random.default_rng(0)
        return {k: m.render_at_pose(x, y, heading_rad, rng) for k, m in self.modules.items()}

    def observe_grid(
        self,
        positions: np.ndarray,
        headings_rad: np.ndarray,
        rng: np.random.Generator | None = None,
    ) -> dict[str, Any]:
        rng = rng if rng is not None else np.random.default_rng(0)
        return {k: m.observe_grid(positions, headings_rad, rng) for k, m in self.modules.items()}

    def image_modules(self) -> list[ImageObservation]:
        return [im for m in self.modules.values() for im in m.image_modules()]

    def close(self) -> None:
        for m in self.modules.values():
            m.close()
