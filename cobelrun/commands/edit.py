"""``cobel edit [env=NAME] [-cd DIR] [--port P]``: design a maze or arena in the browser."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

HELP = """Edit a gridworld, topology graph or 2D arena in the browser; save it as env/NAME.yaml.

\b
Examples:
  cobel edit                          # start from the open field; saves into ./conf
  cobel edit env=tmaze_paper          # a built-in env (or ./conf/env/NAME.yaml) to start from
  cobel edit env=water_maze           # an arena (hex_3d: a topology graph)
  cobel edit -cd myconf env=my_maze --port 8090
\b
Paint walls, one-way doors, starts (with weights), goals with rewards and terminal cells; see
the protocol's phases (the T-maze's acquisition and extinction goals); every change is checked
as `cobel run` checks it. "Run it" starts `cobel run -cd DIR task=... env=NAME` with a few runs
and links to the dashboard. Topology graphs (/graph: nodes, edges, the agent's camera view)
and 2D arenas (/arena: outline, obstacles, goals, starts, place cells, boundary-vector rays)
have their own pages, with phases and "run it" too; the graph's view preview reads the env's
render cache where it has one. Binds to 127.0.0.1 unless --host says otherwise.
Needs NiceGUI and ruamel.yaml (the web extra).
"""


def register(app: typer.Typer) -> None:
    """Add ``cobel edit`` to ``app``."""

    @app.command(
        "edit",
        help=HELP,
        context_settings={"allow_extra_args": True, "ignore_unknown_options": True},
    )
    def edit_cmd(
        ctx: typer.Context,
        port: Annotated[int, typer.Option("--port", "-p", help="TCP port.")] = 8081,
        host: Annotated[
            str,
            typer.Option("--host", help="Address to bind (other than 127.0.0.1 exposes it)."),
        ] = "127.0.0.1",
        results: Annotated[
            Path, typer.Option("--results", help="Where 'run it' writes its runs.")
        ] = Path("results"),
    ) -> None:
        from cobelrun.commands.common import fail
        from cobelrun.errors import CobelError
        from cobelrun.web.editor import edit

        try:
            folder, env = None, None
            args = list(ctx.args)
            while args:
                arg = args.pop(0)
                flag, eq, value = arg.partition("=")
                if flag in ("-cd", "--config-dir"):  # as cobel run's; created on the first save
                    if not eq and not args:
                        raise CobelError(f"{flag} needs a folder")
                    folder = Path(value if eq else args.pop(0)).expanduser()
                elif flag == "env" and eq:
                    env = value
                else:
                    raise CobelError(
                        f"cobel edit takes env=NAME, -cd DIR, --port P, --host H and --results "
                        f"DIR; got {arg!r}"
                    )
            edit(folder, env, host=host, port=port, results=results)
        except CobelError as exc:
            fail(str(exc))
