"""``cobel show env=NAME`` / ``task=NAME``: draw a world before anything runs."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cobelrun.commands.common import AllowTarget, allow_targets

HELP = """Draw an env's maze, arena or graph (PNG) and print it in the terminal; nothing runs.

\b
Examples:
  cobel show env=tmaze_paper
  cobel show task=latent_learning --out blodgett.png
  cobel show env=gridworld_layout env.layout=...      # any `cobel run` overrides
  cobel show -cd myconf env=mymaze                     # a config folder, as cobel run -cd
"""


def register(app: typer.Typer) -> None:
    """Add ``cobel show`` to ``app``."""

    @app.command(
        "show",
        help=HELP,
        context_settings={"allow_extra_args": True, "ignore_unknown_options": True},
    )
    def show_cmd(
        ctx: typer.Context,
        out: Annotated[
            Path | None,
            typer.Option("--out", "-o", help="Output PNG (default ./show_<env>.png)."),
        ] = None,
        no_png: Annotated[
            bool, typer.Option("--no-png", help="Only the terminal drawing.")
        ] = False,
        labels: Annotated[
            bool | None,
            typer.Option(
                "--labels/--no-labels",
                help=f"Name the places in the PNG (default: when at most {MAX_LABELS}).",
                show_default=False,
            ),
        ] = None,
        allow_target: AllowTarget = None,
    ) -> None:
        allow_targets(allow_target)
        from cobelrun.commands.common import fail
        from cobelrun.errors import CobelError

        try:
            path, text = show(list(ctx.args), None if no_png else (out or True), labels=labels)
        except CobelError as exc:
            fail(str(exc))
        typer.echo(text)
        if path is not None:
            typer.echo(str(path))


#: places named in the PNG by default (more overlap: ``env=hex_3d`` has 77)
MAX_LABELS = 20


def show(
    overrides: list[str], out: Path | bool | None, *, labels: bool | None = None
) -> tuple[Path | None, str]:
    """Compose ``overrides`` as ``cobel run`` does, build the env only, draw its geometry.

    ``out``: a PNG path, ``True`` for ``./show_<env>.png`` or ``None`` for no PNG. ``labels``:
    name the places (``None``: when there are at most :data:`MAX_LABELS`; asked for with more,
    the figure grows with their number). Returns the PNG written (or ``None``) and the ASCII
    drawing.
    """
    import matplotlib.pyplot as plt

    from cobelrun.compose import composer, config_args
    from cobelrun.config import instantiate, register_resolvers
    from cobelrun.envs.base import HasGeometry
    from cobelrun.errors import CobelError
    from cobelrun.figures import save_figure
    from cobelrun.figures.runs import ascii_geometry, draw_geometry

    register_resolvers()
    config_dir, config_name, overrides = config_args(overrides)  # -cd/-cp/-cn as cobel run
    with composer(config_dir, config_name) as compose:
        cfg = compose(overrides)
    env = instantiate("env", cfg.env)
    base = env.unwrapped
    choice = next((o.split("=", 1)[1] for o in overrides if o.split("=", 1)[0] == "env"), None)
    name = choice or str(cfg.task.name)
    if not isinstance(base, HasGeometry):
        raise CobelError(f"env {name!r} ({type(base).__name__}) has no geometry to draw")
    geometry = base.geometry()
    text = f"{name}: {geometry.kind}, bounds {tuple(round(b, 3) for b in geometry.bounds)}\n"
    text += ascii_geometry(geometry)
    if out is None:
        return None, text
    path = Path(f"show_{name}.png") if out is True else Path(out)
    n = len(geometry.regions)
    named = n <= MAX_LABELS if labels is None else labels
    side = 4.5 if not named or n <= MAX_LABELS else min(16.0, 4.5 * (n / MAX_LABELS) ** 0.5)
    fig, ax = plt.subplots(figsize=(side, side))
    draw_geometry(geometry, ax, labels=named)
    unit = "cells" if geometry.kind == "grid" else "m"
    ax.set_xlabel(f"x [{unit}]")
    ax.set_ylabel(f"y [{unit}]")
    ax.set_title(name + ("" if named or not n else f" ({n} places; --labels names them)"))
    return save_figure(fig, path), text
