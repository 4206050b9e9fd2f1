"""Offline render cache: every (node, heading) view rendered once, stored content-addressed.

The paper's offline mode (section 3.3): when the agent can only be at a few poses, render each
view once and read images from memory instead of querying the renderer at every step. The cache
is keyed by everything that determines the pixels:

- the scene spec (cells / arena bounds, wall colours, texture, cues, lighting),
- the camera (image size, field of view, number of stitched cameras, eye height, pitch, clipping),
- the poses (node positions and heading angles),
- the renderer (``tiny`` / ``egl``),
- the pybullet version.

Layout: ``<root>/<key>/pybullet-<version>.npy`` (``(N, D, H, W, 3)`` uint8) with a
``meta.json`` next to it, where ``key`` hashes everything but the pybullet version. Reading
(:func:`load`) takes the pybullet version from package metadata, so it never imports pybullet;
on a machine without pybullet the newest file of the key is used. ``root`` is the request's
``cache_dir``, else ``$COBEL_CACHE``, else ``~/.cache/cobel/render``.

Build caches with ``cobel render-cache <the run's overrides>`` (or :func:`build`).
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import time
import zlib
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cobelrun.errors import CobelError
from cobelrun.io.atomic import atomic_write_text
from cobelrun.render.scene import CameraSpec, SceneSpec, pybullet_version, spec_hash

#: Bump when the cache layout or the scene-building code changes what pixels a key means.
CACHE_FORMAT = 1

_BUILDING = False


@contextlib.contextmanager
def building_mode() -> Iterator[None]:
    """While active, offline image modules do not load their cache when bound (used to build it)."""
    global _BUILDING
    old, _BUILDING = _BUILDING, True
    try:
        yield
    finally:
        _BUILDING = old


def building() -> bool:
    """True inside :func:`building_mode`."""
    return _BUILDING


def cache_root(cache_dir: str | os.PathLike[str] | None = None) -> Path:
    """The cache folder: ``cache_dir``, else ``$COBEL_CACHE``, else ``~/.cache/cobel/render``."""
    if cache_dir is not None:
        return Path(cache_dir).expanduser()
    env = os.environ.get("COBEL_CACHE")
    if env:
        return Path(env).expanduser()
    return Path.home() / ".cache" / "cobel" / "render"


@dataclass(eq=False)
class CacheRequest:
    """Everything that determines the cached pixels (see the module docstring)."""

    scene: SceneSpec
    camera: CameraSpec
    positions: np.ndarray
    directions: np.ndarray
    renderer: str = "tiny"
    cache_dir: Path | None = None

    @property
    def n_nodes(self) -> int:
        return int(np.asarray(self.positions).shape[0])

    @property
    def n_directions(self) -> int:
        return int(np.asarray(self.directions).shape[0])

    def payload(self) -> dict[str, Any]:
        """JSON-able description hashed into the key (pybullet version excluded)."""
        return {
            "format": CACHE_FORMAT,
            "scene": self.scene.to_dict(),
            "camera": self.camera.to_dict(),
            "positions": np.round(np.asarray(self.positions, np.float64), 6).tolist(),
            "directions": np.round(np.asarray(self.directions, np.float64), 9).tolist(),
            "renderer": self.renderer,
        }

    def key(self) -> str:
        return spec_hash(self.payload())

    def folder(self) -> Path:
        return cache_root(self.cache_dir) / self.key()

    def poses(self) -> np.ndarray:
        """(N * D, 3) float64 rows ``(x, y, heading radians)`` in (node, heading) order."""
        pos = np.asarray(self.positions, np.float64)
        d = np.asarray(self.directions, np.float64)
        n, k = pos.shape[0], d.shape[0]
        out = np.empty((n * k, 3))
        out[:, :2] = np.repeat(pos, k, axis=0)
        out[:, 2] = np.tile(d, n)
        return out


def _file(folder: Path, version: str) -> Path:
    return folder / f"pybullet-{version}.npy"


def _sums_file(path: Path) -> Path:
    """The checksums of a cache file: ``pybullet-<version>.npy.crc32.json``."""
    return path.with_name(path.name + ".crc32.json")


def block_checksums(images: np.ndarray) -> list[int]:
    """CRC-32 of each node's frame block (``images[i]``: every heading of node ``i``)."""
    flat = np.ascontiguousarray(images).reshape(images.shape[0], -1)
    return [zlib.crc32(flat[i].data) for i in range(flat.shape[0])]


def check_blocks(path: Path, images: np.ndarray) -> None:
    """Compare every frame block of a loaded cache with the checksums written with it; a
    one-line CobelError naming the first corrupted node and the rebuild command."""
    rebuild = f"rebuild it with: {build_hint()} --force"
    from cobelrun.io.validate import read_json_object

    try:
        sums = read_json_object(_sums_file(path))["crc32"]
        if not isinstance(sums, list) or not all(type(v) is int for v in sums):
            raise TypeError
    except (CobelError, KeyError, TypeError):
        raise CobelError(
            f"render cache {path} has no readable checksums ({_sums_file(path).name}), so it "
            f"cannot be trusted; {rebuild}"
        ) from None
    found = block_checksums(images)
    if len(sums) != len(found):
        raise CobelError(f"render cache {path} has {len(found)} frame blocks but checksums for "
                         f"{len(sums)}; {rebuild}")  # fmt: skip
    for node, (want, got) in enumerate(zip(sums, found, strict=True)):
        if int(want) != got:
            raise CobelError(
                f"render cache {path} is corrupted: the frames of node {node} do not match their "
                f"checksum; {rebuild}"
            )


def build_hint() -> str:
    """The command that builds the cache for the current run (from ``sys.argv`` when possible)."""
    argv = [a for a in sys.argv[1:]]
    if argv and argv[0] in ("run", "render-cache"):
        keep = [a for a in argv[1:] if not a.startswith("-") and not a.startswith("hydra.")]
        return "cobel render-cache " + " ".join(keep) if keep else "cobel render-cache"
    return "cobel render-cache <the overrides of your run>"


def locate(request: CacheRequest) -> Path:
    """The cache file for ``request``; a one-line CobelError if it is missing or stale."""
    folder = request.folder()
    version = pybullet_version()
    existing = (
        sorted(folder.glob("pybullet-*.npy"), key=lambda p: p.stat().st_mtime)
        if folder.is_dir()
        else []
    )
    if version is not None:
        path = _file(folder, version)
        if path.is_file():
            return path
        if existing:
            old = ", ".join(p.stem.removeprefix("pybullet-") for p in existing)
            raise CobelError(
                f"render cache {request.key()} in {folder.parent} is stale (rendered with pybullet {old}, "
                f"installed {version}); rebuild it with: {build_hint()}"
            )
    elif existing:
        return existing[-1]
    raise CobelError(
        f"no render cache for this scene and camera (key {request.key()}) in {folder.parent}; "
        f"build it with: {build_hint()}"
    )


#: bytes pybullet's ``getCameraImage`` hands back per pixel (RGBA 4, depth 4, segmentation 4)
#: plus the RGB copy kept
RENDER_BYTES_PER_PIXEL = 15


def check_cache_memory(request: CacheRequest, jobs: int | None = None) -> None:
    """Refuse a render cache whose images would not fit in memory, before anything is rendered:
    ``N nodes x D headings x H x W x 3`` bytes held together, plus one frame's render buffers
    per worker (:func:`cobelrun.safety.check_allocation`)."""
    from cobelrun.safety import check_allocation

    cam = request.camera
    pixels = int(cam.height) * int(cam.width)
    workers = max(1, min(int(jobs or os.cpu_count() or 1), request.n_nodes * request.n_directions))
    need = (
        request.n_nodes * request.n_directions * pixels * 3
        + workers * pixels * RENDER_BYTES_PER_PIXEL
    )
    check_allocation(
        "env.observation.height/width",
        need,
        f"the render cache ({request.n_nodes} nodes x {request.n_directions} headings x "
        f"{cam.height}x{cam.width} pixels x 3 bytes)",
        "lower env.observation.height and width (or render_size)",
    )


def load(request: CacheRequest) -> np.ndarray:
    """The cached images ``(N, D, H, W, 3)`` uint8 of ``request`` (never imports pybullet).

    The file's ``.npy`` header is checked against the request before its data is read."""
    from cobelrun.io.validate import read_npy_header

    path = locate(request)
    cam = request.camera
    want = (request.n_nodes, request.n_directions, cam.height, cam.width, 3)
    try:
        with open(path, "rb") as fh:
            shape, dtype = read_npy_header(fh)
    except (OSError, ValueError) as exc:
        raise CobelError(
            f"render cache {path} cannot be read ({exc}); rebuild it with: {build_hint()}"
        ) from None
    if shape != want or dtype != np.uint8:
        raise CobelError(
            f"render cache {path} holds {shape} {dtype}, expected {want} uint8; "
            f"rebuild it with: {build_hint()}"
        )
    try:
        images = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise CobelError(
            f"render cache {path} cannot be read ({exc}); rebuild it with: {build_hint()}"
        ) from None
    if images.shape != want or images.dtype != np.uint8:
        raise CobelError(
            f"render cache {path} holds {images.shape} {images.dtype}, expected {want} uint8; "
            f"rebuild it with: {build_hint()}"
        )
    check_blocks(path, images)
    images.setflags(write=False)
    return images


# ---------------------------------------------------------------------- building
_WORKER_SCENE: Any = None


def _init_worker(scene: SceneSpec, renderer: str, quiet: bool = False) -> None:
    global _WORKER_SCENE
    from cobelrun.render.scene import Scene

    if quiet:  # worker processes: pybullet's C-level banner must not reach the terminal
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), 1)

    _WORKER_SCENE = Scene(scene, renderer=renderer)


def _render_chunk(
    idx: np.ndarray, poses: np.ndarray, camera: CameraSpec
) -> tuple[np.ndarray, np.ndarray, str]:
    scene = _WORKER_SCENE
    out = np.empty((len(idx), camera.height, camera.width, 3), np.uint8)
    for i, (x, y, h) in enumerate(poses):
        out[i] = scene.render(x, y, h, camera)
    return idx, out, scene.renderer


def render_all(
    request: CacheRequest,
    *,
    jobs: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[np.ndarray, str]:
    """Render every (node, heading) view; returns ``((N, D, H, W, 3) uint8, renderer used)``.

    ``jobs`` worker processes (default: CPU count) each build the scene once and render a share
    of the poses; ``jobs=1`` renders in this process.
    """
    poses = request.poses()
    total = len(poses)
    cam = request.camera
    flat = np.empty((total, cam.height, cam.width, 3), np.uint8)
    jobs = max(1, min(int(jobs or os.cpu_count() or 1), total))
    used = request.renderer
    if jobs == 1:
        _init_worker(request.scene, request.renderer)
        try:
            step = max(1, total // 50)
            for start in range(0, total, step):
                idx = np.arange(start, min(start + step, total))
                _, imgs, used = _render_chunk(idx, poses[idx], cam)
                flat[idx] = imgs
                if progress:
                    progress(int(idx[-1]) + 1, total)
        finally:
            _WORKER_SCENE.close()
    else:
        import multiprocessing as mp

        method = "fork" if "fork" in mp.get_all_start_methods() else "spawn"
        chunks = np.array_split(np.arange(total), min(total, jobs * 4))
        done = 0
        with ProcessPoolExecutor(
            max_workers=jobs,
            mp_context=mp.get_context(method),
            initializer=_init_worker,
            initargs=(request.scene, request.renderer, True),
        ) as pool:
            futures = [pool.submit(_render_chunk, c, poses[c], cam) for c in chunks if len(c)]
            for fut in as_completed(futures):
                idx, imgs, used = fut.result()
                flat[idx] = imgs
                done += len(idx)
                if progress:
                    progress(done, total)
    return flat.reshape(request.n_nodes, request.n_directions, cam.height, cam.width, 3), used


def build(
    request: CacheRequest,
    *,
    jobs: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    force: bool = False,
) -> tuple[Path, bool]:
    """Render and store the cache of ``request``; returns ``(file, built)``.

    An existing cache for the installed pybullet is kept unless ``force`` (``built`` is False).
    The file is written to a temporary name and renamed, so readers never see half a cache.
    """
    version = pybullet_version()
    if version is None:
        raise CobelError("building a render cache needs pybullet: pip install 'cobelrun[render]'")
    folder = request.folder()
    path = _file(folder, version)
    if path.is_file() and not force:
        return path, False
    check_cache_memory(request, jobs)
    t0 = time.perf_counter()
    images, used = render_all(request, jobs=jobs, progress=progress)
    if used != request.renderer:
        raise CobelError(
            f"renderer {request.renderer!r} is not available here (fell back to {used!r}); "
            f"build the cache with renderer={used} or on a machine where {request.renderer} works"
        )
    folder.mkdir(parents=True, exist_ok=True)
    tmp = folder / f".{path.name}.{os.getpid()}.tmp"
    try:
        with open(tmp, "wb") as fh:
            np.save(fh, images, allow_pickle=False)
        # checksums first: a crash between the two renames leaves a cache that fails its
        # check (rebuild), never one that is served unchecked
        atomic_write_text(
            _sums_file(path), json.dumps({"block": "node", "crc32": block_checksums(images)})
        )
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    meta = {
        "key": request.key(),
        "pybullet": version,
        "shape": list(images.shape),
        "render_seconds": round(time.perf_counter() - t0, 3),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
        **request.payload(),
    }
    atomic_write_text(folder / "meta.json", json.dumps(meta, indent=1))
    return path, True


def verify(request: CacheRequest, *, sample: int = 8, seed: int = 0) -> tuple[int, int]:
    """Re-render ``sample`` random cached views; returns ``(views checked, max abs pixel diff)``."""
    from cobelrun.render.scene import Scene

    images = load(request)
    rng = np.random.default_rng(seed)
    poses = request.poses()
    pick = rng.choice(len(poses), size=min(sample, len(poses)), replace=False)
    worst = 0
    with Scene(request.scene, renderer=request.renderer) as scene:
        for i in pick:
            node, head = divmod(int(i), request.n_directions)
            x, y, h = poses[i]
            img = scene.render(x, y, h, request.camera)
            diff = np.abs(img.astype(np.int16) - images[node, head].astype(np.int16))
            worst = max(worst, int(diff.max()))
    return len(pick), worst
