"""``cobel serve``: the results dashboard, a NiceGUI app over :mod:`cobelrun.web.data`.

Pages: ``/`` (every run and sweep folder: status, task, seed, overrides, duration; refreshed
while runs go), ``/run?p=REL`` (a run: its task figure, trajectories and occupancy drawn by
:mod:`cobelrun.figures`, and a learning curve that grows while the run writes its parts),
``/sweep?p=REL`` (a sweep's curves by any swept key, ``--hue`` chosen in the page).

NiceGUI ships its JavaScript (Vue, Quasar, ECharts) inside its wheel; nothing is fetched from
elsewhere. The page never composes or instantiates a folder's config: it only reads tables,
manifests and ``world.json`` through the validated readers.
"""

from __future__ import annotations

import base64
import os
import tempfile
import threading
from pathlib import Path
from typing import Any
from urllib.parse import quote

from cobelrun.errors import CobelError
from cobelrun.web import data

#: seconds between refreshes of the folder list and of a running run's curve
REFRESH_S = 1.0
#: columns of the folder table
COLUMNS = ("path", "kind", "status", "task", "seed", "overrides", "duration_s", "started")

_draw_lock = threading.Lock()  # matplotlib's pyplot state is not thread-safe


class Scanner:
    """The folder rows, re-read only for folders whose manifest/job/sweep file changed."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self._rows: dict[str, tuple[tuple[float, ...], data.Folder]] = {}

    @staticmethod
    def _stamp(path: Path, kind: str) -> tuple[float, ...]:
        names = ("sweep.json",) if kind == "sweep" else ("manifest.json", "job.json", ".done")
        out = []
        for n in names:
            try:
                out.append((path / n).stat().st_mtime)
            except OSError:
                out.append(-1.0)
        return tuple(out)

    def rows(self) -> list[data.Folder]:
        seen = {}
        for path, kind in data._walk(self.root):
            rel = path.relative_to(self.root).as_posix() or "."
            stamp = self._stamp(path, kind)
            cached = self._rows.get(rel)
            if cached is None or cached[0] != stamp:
                row = data._sweep_row(path, rel) if kind == "sweep" else data._run_row(path, rel)
                cached = (stamp, row)
            seen[rel] = cached
        self._rows = seen
        return [row for _, row in seen.values()]


def _png_url(draw: Any) -> str:
    """Run ``draw(out_path)`` (a figure function writing a PNG) and return a data URL."""
    with _draw_lock, tempfile.TemporaryDirectory(prefix="cobel-serve-") as tmp:
        out = Path(draw(Path(tmp) / "fig.png"))
        return "data:image/png;base64," + base64.b64encode(out.read_bytes()).decode()


def _figure(draw: Any) -> tuple[str | None, str]:
    """``(data URL, "")`` or ``(None, one-line error)``."""
    try:
        return _png_url(draw), ""
    except CobelError as exc:
        return None, str(exc)
    except Exception as exc:  # a figure module that cannot draw this run: shown, not fatal
        return None, f"{type(exc).__name__}: {str(exc).strip().splitlines()[0] if str(exc) else ''}"


def build(root: Path) -> None:
    """Register the pages for results folder ``root``."""
    from nicegui import run, ui

    scanner = Scanner(root)

    def header(title: str) -> None:
        with ui.row().classes("items-center w-full"):
            ui.link("cobel", "/").classes("text-xl font-bold no-underline")
            ui.label(title).classes("text-lg cobel-title")

    @ui.page("/", title="cobel results")
    def index() -> None:
        header(str(root))
        columns = [{"name": c, "label": c, "field": c, "align": "left", "sortable": True}
                   for c in COLUMNS]  # fmt: skip
        table = ui.table(columns=columns, rows=[], row_key="path", pagination=50)
        table.classes("w-full cobel-folders")
        table.add_slot(
            "body-cell-path",
            r"""<q-td :props="props"><a class="cobel-folder-link"
                :href="'/' + props.row.kind + '?p=' + encodeURIComponent(props.row.path)"
                >{{ props.row.path }}</a></q-td>""",
        )
        count = ui.label().classes("cobel-count")

        def refresh() -> None:
            rows = [f.row() for f in scanner.rows()]
            if rows != table.rows:
                table.rows = rows
                table.update()
            count.text = f"{len(rows)} folders"

        refresh()
        ui.timer(REFRESH_S * 2, refresh)

    @ui.page("/run", title="cobel run")
    async def run_page(p: str = "") -> None:
        try:
            path = data.resolve(root, p)
        except CobelError as exc:
            header("not found")
            ui.label(str(exc)).classes("text-negative cobel-error")
            return
        header(p)
        info = data._run_row(path, p)
        with ui.row().classes("gap-6"):
            for k, v in info.row().items():
                if v not in ("", None) and k != "path":
                    ui.label(f"{k}: {v}").classes(f"cobel-info cobel-info-{k}")
        live = data.LiveCurve(path)
        trials = live.trials()
        column = data.curve_column(trials) or "reward"
        measures = [c for c in data.CURVE_COLUMNS if c in trials] or [column]
        with ui.row().classes("items-center"):
            ui.label("live curve:")
            pick = ui.select(measures, value=column).classes("cobel-measure")
            count = ui.label().classes("cobel-live-count")
        chart = ui.echart({
            "animation": False,
            "xAxis": {"type": "value", "name": "trial"},
            "yAxis": {"type": "value", "name": data.CURVE_COLUMNS.get(column, column)},
            "tooltip": {"trigger": "axis"},
            "series": [{"type": "line", "showSymbol": False, "data": []}],
        }).classes("w-full h-64 cobel-live-chart")  # fmt: skip

        def update() -> None:
            t = live.trials()
            pts = data.curve_points(t, pick.value)
            runs = int(t["run"].nunique()) if "run" in t else 0
            count.text = f"{len(pts)} trials ({runs} runs)"
            if pts != chart.options["series"][0]["data"]:
                chart.options["series"][0]["data"] = pts
                chart.options["yAxis"]["name"] = data.CURVE_COLUMNS.get(pick.value, pick.value)
                chart.update()

        pick.on_value_change(lambda _: update())
        update()
        ui.timer(REFRESH_S, update)

        from cobelrun.figures import plot_run
        from cobelrun.figures.kinds import plot_kind

        folder = path
        has_world = (folder / "world.json").is_file()
        has_steps = (folder / "steps.parquet").is_file()
        figures: list[tuple[str, Any]] = [("task figure", lambda out: plot_run(folder, out))]
        if has_world and has_steps:
            figures += [
                ("trajectories", lambda out: plot_kind(folder, "trajectories", out)),
                ("occupancy", lambda out: plot_kind(folder, "occupancy", out)),
            ]
        from cobelrun.figures import learned

        try:  # what the agent learned, where the run saved it
            figures += [
                (k, lambda out, k=k: learned.plot_learned(folder, k, out))
                for k in learned.available(folder)
                if k in ("value", "policy", "rate")
            ]
        except CobelError:
            pass
        await ui.context.client.connected(timeout=60)  # page sent first; figures follow
        with ui.row().classes("w-full"):
            for name, draw in figures:
                with ui.card().classes(f"cobel-figure cobel-figure-{name.replace(' ', '-')}"):
                    ui.label(name).classes("font-bold")
                    got = await run.io_bound(_figure, draw)
                    url, err = got if got is not None else (None, "")
                    if url:
                        ui.image(url).classes("w-96").props("no-transition no-spinner")
                    else:
                        ui.label(err).classes("text-negative cobel-error")

    @ui.page("/sweep", title="cobel sweep")
    async def sweep_page(p: str = "") -> None:
        try:
            path = data.resolve(root, p)
            info = data._sweep_row(path, p)
        except CobelError as exc:
            header("not found")
            ui.label(str(exc)).classes("text-negative cobel-error")
            return
        header(p)
        ui.label(f"{info.jobs} jobs; swept: {', '.join(info.swept) or 'nothing'}")
        from cobelrun.figures.runs import plot_sweep_file

        with ui.row().classes("items-center"):
            hue = ui.select(["(none)", *info.swept], value=info.swept[0] if info.swept else
                            "(none)", label="--hue").classes("w-64 cobel-hue")  # fmt: skip
            y = ui.select(["latency", "reward", "response"], value="reward", label="--y")
            y.classes("w-48 cobel-y")
        img = ui.image().classes("w-[40rem] cobel-sweep-figure").props("no-transition")
        err = ui.label().classes("text-negative cobel-error")

        async def redraw() -> None:
            h = None if hue.value == "(none)" else hue.value

            def draw(out: Path) -> Path:
                return plot_sweep_file(path, h, y.value, out)

            got = await run.io_bound(_figure, draw)
            url, msg = got if got is not None else (None, "")  # None: the page was closed
            img.set_source(url or "")
            err.text = msg

        hue.on_value_change(redraw)
        y.on_value_change(redraw)
        await ui.context.client.connected(timeout=60)  # page sent first; figures follow
        await redraw()


def port_free(host: str, port: int) -> bool:
    """Whether ``host:port`` can be bound now."""
    import socket

    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


def serve(root: str | os.PathLike[str], *, host: str = "127.0.0.1", port: int = 8080) -> None:
    """Serve the dashboard of results folder ``root`` until interrupted.

    Raises
    ------
    CobelError
        ``root`` is not a results folder, the port is in use, or NiceGUI is not installed.
    """
    root = data.check_results_dir(root).resolve()
    if not 0 < port < 65536:
        raise CobelError(f"--port {port} is not a port number (1-65535)")
    if not port_free(host, port):
        raise CobelError(f"port {port} on {host} is in use; pick another with --port")
    try:
        from nicegui import ui
    except ImportError:
        raise CobelError("cobel serve needs NiceGUI: pip install 'cobelrun[web]'") from None
    build(root)
    ui.run(host=host, port=port, title="cobel", reload=False, show=False,
           show_welcome_message=False, uvicorn_logging_level="warning")  # fmt: skip


def url_of(rel: str, kind: str = "run") -> str:
    """The page of folder ``rel`` (relative to the results folder)."""
    return f"/{kind}?p={quote(rel)}"
