"""``cobel render-cache``: pre-render every view of a task's image observations (offline mode).

Composes the config exactly as ``cobel run`` would (same overrides), builds the environment
without loading any cache, and renders each image module's (node, heading) views once, in
parallel worker processes, into the content-addressed cache (:mod:`cobelrun.render.cache`).
Monitors that look at poses off the graph (the activity-map monitor's probe grid) name their
poses through ``cache_requests(env)``; those grids are rendered too.
A run with ``env.observation.render=offline`` then reads the images and never imports pybullet.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import sys
import time
from collections.abc import Callable, Iterator
from typing import Annotated, Any

import typer

HELP = """Pre-render all views of a task's image observations into the offline render cache.

\b
Give the same overrides as for `cobel run`:
  cobel render-cache task=tmaze_extinction_3d
  cobel render-cache task=tmaze_extinction_3d env.observation.height=75 env.observation.width=300
  cobel render-cache task=tmaze_extinction_3d --verify      # re-render a sample and compare
\b
Then run offline (no pybullet needed): cobel run task=... env.observation.render=offline
The cache lives in $COBEL_CACHE (default ~/.cache/cobel/render) or env.observation.cache_dir.
"""


def compose(overrides: list[str]) -> Any:
    """Compose the run config for ``overrides`` exactly as ``cobel run`` does (no sweeps)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import OverrideParseException

    from cobelrun.errors import ConfigError
    from cobelrun.hydra_app import composer

    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
    except OverrideParseException as exc:
        raise ConfigError(f"cannot parse override: {str(exc).splitlines()[0]}") from None
    if any(o.is_sweep_override() for o in parsed):
        raise ConfigError("render-cache takes one configuration; remove the sweep (a,b) overrides")
    with composer() as compose_config:
        return compose_config(overrides)


@contextlib.contextmanager
def _progress(label: str) -> Iterator[Callable[[int, int], None] | None]:
    if not sys.stderr.isatty():
        yield None
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TextColumn("views"), TimeElapsedColumn(), transient=True) as bar:  # fmt: skip
        task = bar.add_task(label, total=None)
        yield lambda done, total: bar.update(task, completed=done, total=total)


def _silence_exit_banner() -> None:
    """pybullet prints its build time to stdout at interpreter exit; keep the output clean."""

    def hush() -> None:
        with contextlib.suppress(Exception):
            sys.stdout.flush()
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, 1)

    atexit.register(hush)


def render_cache_cmd(
    ctx: typer.Context,
    verify: Annotated[
        bool, typer.Option("--verify", help="Re-render a sample of cached views and compare.")
    ] = False,
    sample: Annotated[int, typer.Option("--sample", help="Views re-rendered by --verify.")] = 16,
    jobs: Annotated[
        int | None, typer.Option("--jobs", "-j", help="Worker processes (default: CPU count).")
    ] = None,
    force: Annotated[
        bool, typer.Option("--force", help="Rebuild even if the cache exists.")
    ] = False,
) -> None:
    from cobelrun.commands.common import fail
    from cobelrun.config import instantiate
    from cobelrun.errors import CobelError
    from cobelrun.render import cache

    overrides = list(ctx.args)
    try:
        cfg = compose(overrides)
        with cache.building_mode():
            env = instantiate("env", cfg.env)
        module = getattr(env.unwrapped, "observation_module", None)
        images = module.image_modules() if module is not None else []
        if not images:
            fail(f"env {type(env.unwrapped).__name__} has no image observation; nothing to render "
                 "(pick a task with images, e.g. task=tmaze_extinction_3d)")  # fmt: skip
        _silence_exit_banner()
        requests = [("nodes", im.cache_request()) for im in images]
        requests += [("probe positions", req) for req in _monitor_requests(cfg, env)]
        for what_poses, req in requests:
            cam = req.camera
            label = (
                f"{req.n_nodes} {what_poses} x {req.n_directions} headings, "
                f"{cam.height}x{cam.width}"
            )
            t0 = time.perf_counter()
            with _progress(f"render {label}") as progress:
                path, built = cache.build(req, jobs=jobs, progress=progress, force=force)
            dt = time.perf_counter() - t0
            what = (
                f"rendered {req.n_nodes * req.n_directions} views in {dt:.2f} s"
                if built
                else "up to date"
            )
            typer.echo(f"{what}: {label} ({req.renderer}) -> {path}")
            if verify:
                n, worst = cache.verify(req, sample=sample)
                if worst:
                    fail(f"verify: {n} re-rendered views differ from the cache by up to {worst} "
                         f"levels; rebuild with --force")  # fmt: skip
                typer.echo(f"verified: {n} re-rendered views identical to the cache")
        env.close()
    except CobelError as exc:
        fail(str(exc))


def _monitor_requests(cfg: Any, env: Any) -> list[Any]:
    """Cache requests of the task's monitors that render views off the graph (activity maps)."""
    from omegaconf import OmegaConf

    from cobelrun.config import instantiate

    out = []
    monitors = cfg.task.get("monitors") if "task" in cfg else None
    for name, node in (monitors or {}).items():
        if node is None:
            continue
        monitor = instantiate(f"task.monitors.{name}", OmegaConf.to_container(node, resolve=True))
        if hasattr(monitor, "cache_requests"):
            out += monitor.cache_requests(env)
    return out


def register(app: typer.Typer) -> None:
    """Add ``render-cache`` to the ``cobel`` app."""
    app.command(
        "render-cache",
        help=HELP,
        context_settings={"allow_extra_args": True, "ignore_unknown_options": True},
    )(render_cache_cmd)
