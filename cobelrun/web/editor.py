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
from cobelrun.web.edit_runs import RUN_IT_RUNS, Child, Editor, RunPanel  # noqa: F401 (re-exported)
from cobelrun.web.grid_design import MAX_SIDE, TOOLS, GridDesign, Problem

#: the cells' click handler: which cell, and where in it (for the side of a door or wall)
CLICK_JS = """(e) => {
  const t = e.target.closest('[data-r]');
  if (!t) return;
  const b = t.getBoundingClientRect();
  emit({r: +t.dataset.r, c: +t.dataset.c,
        fx: (e.clientX - b.left) / b.width, fy: (e.clientY - b.top) / b.height});
}"""
#: runs that "Run it" starts (a quick look, not an experiment)
ENV_NONE = -1  # the phase selector's "env as built"


def side_of(fx: float, fy: float) -> str:
    """The side of a cell nearest a click at fraction ``(fx, fy)`` of the cell."""
    d = {"left": fx, "right": 1.0 - fx, "up": fy, "down": 1.0 - fy}
    return min(d, key=d.__getitem__)


def cell_px(design: GridDesign) -> int:
    """Pixels per cell: big cells for small grids, the whole grid within ~640 px."""
    return max(14, min(44, 640 // max(design.width, design.height)))


class Page:
    """One browser tab's editor: its design, undo history, tool and the widgets."""

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
        self.history: list[GridDesign] = []
        self.tool = "wall"
        self.phase: int | None = None
        self.problems: list[Problem] = []

    # ------------------------------------------------------------------ building
    def build(self) -> None:
        from nicegui import ui

        ed = self.editor
        with ui.row().classes("items-center w-full"):
            ui.label("cobel edit").classes("text-xl font-bold")
            ui.label(f"config folder {ed.folder}").classes("text-sm cobel-folder")
            ui.link("topology graphs", "/graph").classes("text-sm cobel-graph-link")
            ui.link("2D arenas", "/arena").classes("text-sm cobel-arena-link")
            self.origin = ui.label().classes("text-sm text-gray-600 cobel-origin")
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
                self._save_panel()
        self.refresh()

    def _side_panel(self) -> None:
        from nicegui import ui

        ui.label("start from").classes("font-bold")
        labels = {k: v[0] for k, v in ec.TEMPLATES.items()}
        with ui.row().classes("items-center no-wrap"):
            self.template = ui.select(labels, value=None, label="template").classes(
                "w-48 cobel-template"
            )
            ui.button("load", on_click=self._load_template).props("dense").classes(
                "cobel-load-template"
            )
        names = ec.env_names(self.editor.folder)
        with ui.row().classes("items-center no-wrap"):
            self.existing = ui.select(names, value=None, label="env in the folder").classes(
                "w-48 cobel-existing"
            )
            ui.button("open", on_click=self._open_existing).props("dense").classes("cobel-open")
        ui.label("size").classes("font-bold mt-2")
        with ui.row().classes("items-center no-wrap"):
            self.width = ui.number("width", value=self.design.width, min=1, max=MAX_SIDE,
                                   precision=0).classes("w-20 cobel-width")  # fmt: skip
            self.height = ui.number("height", value=self.design.height, min=1, max=MAX_SIDE,
                                    precision=0).classes("w-20 cobel-height")  # fmt: skip
            ui.button("resize", on_click=self._resize).props("dense").classes("cobel-resize")
        ui.label("paint").classes("font-bold mt-2")
        self.tool_buttons = {}
        with ui.grid(columns=2).classes("gap-1"):
            for name, what in TOOLS.items():
                b = ui.button(name, on_click=lambda _, n=name: self._set_tool(n))
                b.props("dense no-caps").classes(f"cobel-tool cobel-tool-{name}").tooltip(what)
                self.tool_buttons[name] = b
        with ui.row().classes("items-center no-wrap"):
            self.value = ui.number("reward", value=1.0, step=0.5).classes("w-24 cobel-value")
            self.weight = ui.number("start weight", value=1, min=1, max=20, precision=0)
            self.weight.classes("w-28 cobel-weight")
        self.place = ui.input("place name", placeholder="left_arm").classes("w-48 cobel-place")
        ui.label("phase").classes("font-bold mt-2")
        self.phase_select = ui.select({ENV_NONE: "env (as built)"}, value=ENV_NONE,
                                      on_change=self._set_phase).classes("w-64 cobel-phase")  # fmt: skip
        self.phase_hint = ui.label().classes("text-xs text-gray-600 cobel-phase-hint")
        self.trials = ui.number("trials in this phase", min=1, precision=0).classes(
            "w-40 cobel-trials"
        )
        self.trials.on("change", self._set_trials)
        self.trials.set_visibility(False)
        ui.button("undo", on_click=self._undo).props("dense").classes("mt-2 cobel-undo")

    def _save_panel(self) -> None:
        from nicegui import ui

        ui.label("save").classes("font-bold")
        self.name = ui.input("env name", value=self.start_name).classes("w-64 cobel-name")
        self.with_task = ui.checkbox("also write task/NAME.yaml (protocol, agent, monitors)")
        self.with_task.classes("cobel-with-task")
        with ui.row():
            ui.button("save", on_click=self._save).classes("cobel-save")
            ui.button("run it", on_click=self._run_it).classes("cobel-run")
        self.status = ui.label(self.error).classes("text-sm cobel-status")
        self.runner = RunPanel(self.editor)
        with ui.row():
            ui.button("export PNG", on_click=lambda: self._export("png")).props("dense outline")
            ui.button("export SVG", on_click=lambda: self._export("svg")).props("dense outline")
        ui.label("env/NAME.yaml as it will be saved").classes("font-bold mt-2")
        self.yaml = ui.code("", language="yaml").classes("w-96 text-xs cobel-yaml")

    # ------------------------------------------------------------------ drawing
    def refresh(self) -> None:
        from nicegui import ui

        d = self.design
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
        self.origin.text = f"from {self.loaded.origin}"
        for name, b in self.tool_buttons.items():
            b.props(f"color={'primary' if name == self.tool else 'grey-6'}")
        opts = {ENV_NONE: "env (as built)"}
        opts.update({i: f"phase {i + 1}: {n}" for i, n in enumerate(d.phase_names())})
        if self.phase_select.options != opts:
            self.phase_select.set_options(
                opts, value=ENV_NONE if self.phase is None else self.phase
            )
        self.phase_hint.text = self._phase_text()
        try:
            self.yaml.content = ec.env_text(self.loaded, d)
        except CobelError as exc:
            self.yaml.content = f"# {exc}"

    def _phase_text(self) -> str:
        d = self.design
        if self.phase is None or not 0 <= self.phase < len(d.phases):
            return (f"{len(d.phases)} protocol phase(s); pick one to see and edit the goals and "
                    "starts it sets")  # fmt: skip
        p = d.phases[self.phase]
        sets = []
        for key in ("rewards", "terminals"):
            if p.get(key):
                sets.append(f"{key} " + ", ".join(f"{k}: {v}" for k, v in p[key].items()))
        if p.get("starts") is not None:
            sets.append("starts " + ", ".join(str(s) for s in p["starts"]))
        if p.get("cycle"):
            sets.append(f"a per-trial cycle of {len(p['cycle'])} changes")
        what = "; ".join(sets) or "nothing (the world as the phase before left it)"
        return (f"{p.get('name')} ({p.get('trials')} trials) sets {what}. Painting starts, goals, "
                "rewards and terminals now changes what this phase sets.")  # fmt: skip

    # ------------------------------------------------------------------ events
    def _change(self, fn: Any) -> None:
        before = self.design.copy()
        try:
            fn()
        except CobelError as exc:
            self.design = before
            self.status.text = str(exc)
            return
        self.history.append(before)
        del self.history[:-100]
        self.refresh()

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
        self._change(lambda: self.design.paint(self.tool, cell, value=value, weight=weight,
                                               side=side_of(fx, fy), phase=self.phase,
                                               name=name))  # fmt: skip

    def _set_tool(self, name: str) -> None:
        self.tool = name
        for n, b in self.tool_buttons.items():
            b.props(f"color={'primary' if n == name else 'grey-6'}")

    def _set_phase(self, e: Any) -> None:
        v = e.value
        self.phase = None if v in (None, ENV_NONE) else int(v)
        if self.phase is not None:
            self.trials.value = self.design.phases[self.phase].get("trials")
        self.trials.set_visibility(self.phase is not None)
        self.refresh()

    def _set_trials(self) -> None:
        if self.phase is None or self.trials.value is None:
            return
        i, n = self.phase, int(self.trials.value)
        if self.design.phases[i].get("trials") != n:
            self._change(lambda: self.design.phases[i].__setitem__("trials", n))

    def _resize(self) -> None:
        w, h = int(self.width.value or 0), int(self.height.value or 0)
        self._change(lambda: self.design.resize(w, h))

    def _undo(self) -> None:
        if self.history:
            self.design = self.history.pop()
            self.refresh()

    def _use(self, loaded: ec.Loaded, name: str) -> None:
        self.loaded = loaded
        self.design = loaded.design.copy()
        self.history.clear()
        self.phase = None
        self.trials.set_visibility(False)
        self.width.value, self.height.value = self.design.width, self.design.height
        self.name.value = name
        self.status.text = f"loaded {loaded.origin}"
        self.refresh()

    def _load_template(self) -> None:
        if not self.template.value:
            self.status.text = "pick a template first"
            return
        try:
            self._use(ec.load_template(self.template.value), self.template.value)
        except CobelError as exc:
            self.status.text = str(exc)

    def _open_existing(self) -> None:
        if not self.existing.value:
            self.status.text = "pick an env of the folder first"
            return
        try:
            self._use(ec.load(self.editor.folder, self.existing.value), self.existing.value)
        except CobelError as exc:
            self.status.text = str(exc)
            if "too large to edit" in str(exc):  # offer its YAML instead (read, size-checked)
                path = self.editor.folder / "env" / f"{self.existing.value}.yaml"
                try:
                    ec.read_yaml(path)
                    self.yaml.content = path.read_text(encoding="utf-8")
                except (CobelError, OSError):
                    pass

    def _save(self) -> list[Path] | None:
        name = str(self.name.value or "").strip()
        try:
            written = ec.save(self.editor.folder, name, self.loaded, self.design,
                              with_task=bool(self.with_task.value))  # fmt: skip
        except CobelError as exc:
            self.status.text = str(exc)
            return None
        # what is on disk now is what was loaded: later saves compare against it
        self.loaded = ec.load(self.editor.folder, name)
        if not self.with_task.value:  # phases stay as edited (they are written with the task)
            self.loaded.design.phases = self.design.phases
            self.loaded.design.max_steps = self.design.max_steps
        self.design = self.loaded.design.copy()
        self.existing.set_options(ec.env_names(self.editor.folder))
        self.status.text = "saved " + ", ".join(str(p) for p in written)
        self.refresh()
        return written

    def _run_it(self) -> None:
        if self._save() is None:
            return
        name = str(self.name.value).strip()
        self.runner.start(name, name if self.with_task.value else "gridworld")

    def _export(self, fmt: str) -> None:
        from nicegui import ui

        try:
            data = self.design.figure(fmt, phase=self.phase)
        except CobelError as exc:
            self.status.text = str(exc)
            return
        name = str(self.name.value or "maze").strip() or "maze"
        ui.download.content(data, f"{name}.{fmt}")


def build(editor: Editor) -> None:
    """Register the editor's page and the children's clean-up."""
    from nicegui import app, ui

    from cobelrun.web.graph_editor import GraphPage

    @ui.page("/", title="cobel edit")
    def index(env: str = "") -> None:
        if not env and editor.graph_env:
            ui.navigate.to(f"/{editor.graph_page}?env={quote(editor.graph_env)}")
            return
        Page(editor, env).build()

    @ui.page("/graph", title="cobel edit: graph")
    def graph(env: str = "") -> None:
        GraphPage(editor.folder, env).build()

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
    try:
        ui.run(host=host, port=port, title="cobel edit", reload=False, show=False,
               show_welcome_message=False, uvicorn_logging_level="warning")  # fmt: skip
    finally:
        editor.stop()
