"""``cobel edit``: a gridworld editor in the browser, a NiceGUI page over
:mod:`cobelrun.web.grid_design` (the design and its checks) and :mod:`cobelrun.web.edit_config`
(reading and writing configs).

The page draws the grid as an SVG (one ``rect`` per cell); a click paints with the chosen tool.
After every change the design is checked with the code ``cobel run`` uses and each message is
shown next to the cell it names. "Save" writes ``env/NAME.yaml`` (and ``task/NAME.yaml``) into
the config folder; "Run it" saves, then starts ``cobel run -cd DIR task=... env=NAME`` with a
few runs in a child process and, once the run folder exists, a ``cobel serve`` dashboard on
another local port that shows it. Both children end with the editor.

Like ``cobel serve``, the page binds to 127.0.0.1 by default and uses only the JavaScript
inside NiceGUI's wheel.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any
from urllib.parse import quote

from cobelrun.errors import CobelError, ConfigError
from cobelrun.web import edit_config as ec
from cobelrun.web.edit_page import ENV_NONE, EditPage  # noqa: F401 (re-exported)
from cobelrun.web.edit_runs import RUN_IT_RUNS, Child, Editor, RunPanel  # noqa: F401 (re-exported)
from cobelrun.web.grid_design import TOOLS, GridDesign, Problem

#: the cells' click handler: which cell, and where in it (for the side of a door or wall)
CLICK_JS = """(e) => {
  const t = e.target.closest('[data-r]');
  if (!t) return;
  const b = t.getBoundingClientRect();
  emit({r: +t.dataset.r, c: +t.dataset.c,
        fx: (e.clientX - b.left) / b.width, fy: (e.clientY - b.top) / b.height});
}"""


def side_of(fx: float, fy: float) -> str:
    """The side of a cell nearest a click at fraction ``(fx, fy)`` of the cell."""
    d = {"left": fx, "right": 1.0 - fx, "up": fy, "down": 1.0 - fy}
    return min(d, key=d.__getitem__)


def cell_px(design: GridDesign) -> int:
    """Pixels per cell: big cells for small grids, the whole grid within ~640 px."""
    return max(14, min(44, 640 // max(design.width, design.height)))


class Page(EditPage):
    """One browser tab's gridworld editor: its design, undo history, tool and the widgets
    (the parts shared with the other pages come from :class:`EditPage`)."""

    here = "/"
    phase_tools = "Painting starts, goals, rewards and terminals now changes what this phase sets"

    def __init__(self, editor: Editor, env: str = "") -> None:
        self.editor = editor
        self.error = ""
        self.loaded = editor.first()
        name = editor.name
        if env:  # /?env=NAME: that env of the folder (or a built-in one)
            try:
                self.loaded, name = ec.load(editor.folder, env), env
            except CobelError as exc:
                self.error = str(exc)
        self.start_name = name
        self.design = self.loaded.design.copy()
        self.init_state()
        self.tool = "wall"
        self.problems: list[Problem] = []

    # ------------------------------------------------------------------ building
    def build(self) -> None:
        from nicegui import ui

        self.header()
        with ui.row().classes("w-full no-wrap items-start gap-6"):
            with ui.column().classes("w-72 gap-1"):
                self._side_panel()
            with ui.column().classes("gap-2"):
                with ui.element("div").style("position: relative").classes("cobel-canvas"):
                    self.grid = ui.html("", sanitize=False).classes("cobel-grid-box")
                    self.grid.on("click", self._click, js_handler=CLICK_JS)
                    self.overlay = ui.element("div").style(
                        "position: absolute; left: 0; top: 0; pointer-events: none"
                    )
                self.problem_list = ui.column().classes("gap-0 cobel-problems")
                self.info = ui.label().classes("text-sm text-gray-700 cobel-info")
            with ui.column().classes("w-96 gap-1"):
                self.save_panel()
        self.refresh()

    def _side_panel(self) -> None:
        from nicegui import ui

        self.load_rows({k: v[0] for k, v in ec.TEMPLATES.items()})
        ui.label("size").classes("font-bold mt-2")
        with ui.row().classes("items-center no-wrap"):
            # no min/max on the boxes: they would clamp 100 to 32 silently; resize says why
            self.width = ui.number("width", value=self.design.width, precision=0)
            self.width.classes("w-20 cobel-width")
            self.height = ui.number("height", value=self.design.height, precision=0)
            self.height.classes("w-20 cobel-height")
            ui.button("resize", on_click=self._resize).props("dense").classes("cobel-resize")
        ui.label("paint").classes("font-bold mt-2")
        self.tool_grid(TOOLS)
        with ui.row().classes("items-center no-wrap"):
            self.value = ui.number("reward", value=1.0, step=0.5).classes("w-24 cobel-value")
            self.weight = ui.number("start weight", value=1, min=1, max=20, precision=0)
            self.weight.classes("w-28 cobel-weight")
        self.place = ui.input("place name", placeholder="left_arm").classes("w-48 cobel-place")
        self.phase_rows()
        ui.button("undo", on_click=self.undo).props("dense").classes("mt-2 cobel-undo")

    # ------------------------------------------------------------------ drawing
    def refresh(self) -> None:
        from nicegui import ui

        d = self.design
        self.refresh_common()
        self.problems = d.problems()
        px = cell_px(d)
        self.grid.content = d.svg(phase=self.phase, px=px, problems=self.problems)
        self.overlay.clear()
        with self.overlay:
            for p in self.problems:
                if p.cell is None:
                    continue
                r, c = p.cell
                ui.label(p.message).classes(
                    "cobel-problem-at text-xs bg-red-50 text-red-800 border border-red-400 "
                    "rounded px-1").style(f"position: absolute; left: {(c + 1) * px + 6}px; "
                                          f"top: {r * px}px; width: 22rem")  # fmt: skip
        self.problem_list.clear()
        with self.problem_list:
            for p in self.problems:
                ui.label(p.message).classes("text-sm text-negative cobel-problem")
            if not self.problems:
                ui.label("no problems: cobel run accepts this world").classes(
                    "text-sm text-positive cobel-ok"
                )
        probs = d.start_probabilities()
        starts = ", ".join(f"({r},{c}) {p:.2f}" for (r, c), p in sorted(probs.items())[:8])
        more = f" and {len(probs) - 8} more" if len(probs) > 8 else ""
        self.info.text = (f"{d.width} x {d.height} cells; start probabilities: {starts}{more}; "
                          "orange bars: one-way doors (blocked going out of the cell they sit "
                          "in); black bars: walls")  # fmt: skip
        try:
            self.yaml.content = ec.env_text(self.loaded, d)
        except CobelError as exc:
            self.yaml.content = f"# {exc}"

    # ------------------------------------------------------------------ events
    def _click(self, e: Any) -> None:
        a = e.args if isinstance(e.args, dict) else {}
        try:
            cell = (int(a["r"]), int(a["c"]))
            fx, fy = float(a.get("fx", 0.5)), float(a.get("fy", 0.5))
        except (KeyError, TypeError, ValueError):
            return
        value = float(self.value.value or 0.0)
        weight = int(self.weight.value or 1)
        name = str(self.place.value or "")
        self.change(lambda: self.design.paint(self.tool, cell, value=value, weight=weight,
                                              side=side_of(fx, fy), phase=self.phase,
                                              name=name))  # fmt: skip

    def _resize(self) -> None:
        # an empty box is None; check_size names it (at most MAX_SIDE cells a side)
        w, h = (v if v is None else int(v) for v in (self.width.value, self.height.value))
        self.change(lambda: self.design.resize(w, h))

    def after_use(self) -> None:
        self.width.value, self.height.value = self.design.width, self.design.height

    # ------------------------------------------------------------------ EditPage's hooks
    def load_template(self, name: str) -> ec.Loaded:
        return ec.load_template(name)

    def load_existing(self, name: str) -> ec.Loaded:
        return ec.load(self.editor.folder, name)

    def existing_names(self) -> list[str]:
        return ec.env_names(self.editor.folder)

    def open_failed(self, exc: CobelError) -> None:
        if "too large to edit" in str(exc):  # offer its YAML instead (read, size-checked)
            path = self.editor.folder / "env" / f"{self.existing.value}.yaml"
            try:
                ec.read_yaml(path)
                self.yaml.content = path.read_text(encoding="utf-8")
            except (CobelError, OSError):
                pass

    def write(self, name: str, with_task: bool) -> list[Path]:
        written = ec.save(self.editor.folder, name, self.loaded, self.design, with_task=with_task)
        # what is on disk now is what was loaded: later saves compare against it
        self.loaded = ec.load(self.editor.folder, name)
        if not with_task:  # phases stay as edited (they are written with the task)
            self.loaded.design.phases = self.design.phases
            self.loaded.design.max_steps = self.design.max_steps
        self.design = self.loaded.design.copy()
        return written

    def run_target(self, name: str) -> tuple[str, int, list[str]]:
        return (name if self.with_task.value else "gridworld"), RUN_IT_RUNS, []

    def figure(self, fmt: str) -> bytes:
        return self.design.figure(fmt, phase=self.phase)


def build(editor: Editor) -> None:
    """Register the editor's page and the children's clean-up."""
    from nicegui import app, ui

    from cobelrun.web.graph_editor import GraphPage

    @ui.page("/", title="cobel edit")
    def index(env: str = "") -> None:
        page = page_of(editor.folder, env) if env else None  # /?env=NAME as env=NAME does
        if page is None and not env and editor.graph_env:
            env, page = editor.graph_env, editor.graph_page
        if page is not None:
            ui.navigate.to(f"/{page}?env={quote(env)}")
            return
        Page(editor, env).build()

    @ui.page("/graph", title="cobel edit: graph")
    def graph(env: str = "") -> None:
        GraphPage(editor, env).build()

    from cobelrun.web.arena_editor import ArenaPage

    @ui.page("/arena", title="cobel edit: arena")
    def arena(env: str = "") -> None:
        ArenaPage(editor, env).build()

    app.on_shutdown(editor.stop)


def prepare(folder: Path | None, env: str | None, results: Path) -> Editor:
    """Check the command line and load what it names (one-line errors, nothing started)."""
    folder = (folder if folder is not None else Path("conf")).absolute()
    if folder.exists() and not folder.is_dir():
        raise CobelError(f"{folder} is not a folder; pass a config folder with -cd DIR")
    initial = None
    name = "my_maze"
    graph_env, page = None, "graph"
    if env is not None:
        name = ec.check_name(env)
        try:
            initial = ec.load(folder, env) if folder.is_dir() else ec.load_template(env)
        except ConfigError as exc:
            if "is not a gridworld env config" not in str(exc):
                raise
            graph_env, page = _other_page(folder, env, exc)
            name = "my_maze"
    return Editor(folder=folder, results=results, name=name, initial=initial,
                  graph_env=graph_env, graph_page=page)  # fmt: skip


def page_of(folder: Path, env: str) -> str | None:
    """The page (``graph`` or ``arena``) that edits ``env`` where it is a topology graph or an
    arena; ``None`` where the gridworld page takes it or says why it cannot."""
    try:
        ec.check_name(env)
        ec.load(folder, env) if folder.is_dir() else ec.load_template(env)
    except ConfigError as exc:
        if "is not a gridworld env config" in str(exc):
            try:
                return _other_page(folder, env, exc)[1]
            except CobelError:
                return None
    except CobelError:
        return None
    return None


def url_of(host: str, port: int, editor: Editor) -> str:
    """The address ``cobel edit`` prints: the page that opens what the command line named."""
    shown = f"[{host}]" if ":" in host else host
    page = f"{editor.graph_page}?env={quote(editor.graph_env)}" if editor.graph_env else ""
    return f"http://{shown}:{port}/{page}"


def _other_page(folder: Path, env: str, gridworld_error: ConfigError) -> tuple[str, str]:
    """``(env, page)`` where ``env`` is a topology graph (``graph``) or an arena (``arena``),
    checked now; neither: the gridworld's message (it names what the editor edits)."""
    from cobelrun.web.arena_editor import load_arena
    from cobelrun.web.graph_editor import load_graph

    try:
        load_graph(folder, env)
        return env, "graph"
    except ConfigError as exc:
        if "is not a topology env config" not in str(exc):
            raise
    try:
        load_arena(folder, env)
        return env, "arena"
    except ConfigError as exc:
        if "is not an arena env config" not in str(exc):
            raise
    raise gridworld_error from None


def edit(folder: Path | None = None, env: str | None = None, *, host: str = "127.0.0.1",
         port: int = 8081, results: Path = Path("results")) -> None:  # fmt: skip
    """Serve the editor until interrupted.

    Raises
    ------
    CobelError
        A bad env name, a file that is not a gridworld env config or too large to edit, a
        port in use, NiceGUI missing.
    """
    from cobelrun.web.app import port_free

    if not 0 < port < 65536:
        raise CobelError(f"--port {port} is not a port number (1-65535)")
    editor = prepare(folder, env, results)
    if not port_free(host, port):
        raise CobelError(f"port {port} on {host} is in use; pick another with --port")
    try:
        from nicegui import ui
    except ImportError:
        raise CobelError("cobel edit needs NiceGUI: pip install 'cobelrun[web]'") from None
    build(editor)
    print(f"cobel edit: open {url_of(host, port, editor)} (config folder {editor.folder}); "
          "Ctrl-C ends it", flush=True)  # fmt: skip
    try:
        ui.run(host=host, port=port, title="cobel edit", reload=False, show=False,
               show_welcome_message=False, uvicorn_logging_level="warning")  # fmt: skip
    finally:
        editor.stop()
