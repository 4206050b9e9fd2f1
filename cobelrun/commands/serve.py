"""``cobel serve [RESULTS_DIR] [--port P]``: the results dashboard in the browser."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

HELP = """Serve a local dashboard of a results folder: runs and sweeps, figures, live curves.

\b
Examples:
  cobel serve                      # results/ on http://127.0.0.1:8080
  cobel serve results/dyna_maze --port 8090
\b
Runs in progress update from the parts they write. The page only reads the folders (through
the same validated readers as `cobel plot`); it binds to 127.0.0.1 unless --host says otherwise.
Needs the web extra: pip install 'cobelrun[web]'.
"""


def register(app: typer.Typer) -> None:
    """Add ``cobel serve`` to ``app``."""

    @app.command("serve", help=HELP)
    def serve_cmd(
        results_dir: Annotated[
            Path, typer.Argument(help="A results folder (or one run or sweep folder).")
        ] = Path("results"),
        port: Annotated[int, typer.Option("--port", "-p", help="TCP port.")] = 8080,
        host: Annotated[
            str,
            typer.Option("--host", help="Address to bind (other than 127.0.0.1 exposes it)."),
        ] = "127.0.0.1",
    ) -> None:
        from cobelrun.commands.common import fail
        from cobelrun.errors import CobelError
        from cobelrun.web.app import serve

        try:
            serve(results_dir, host=host, port=port)
        except CobelError as exc:
            fail(str(exc))
