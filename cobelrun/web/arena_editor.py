"""``cobel edit``'s 2D-arena page (``/arena``): outline, obstacles, goal regions and start
points of a :class:`~cobelrun.envs.continuous.Continuous2DEnv`, with the env's place-cell
centres and the boundary-vector rays at a clicked pose drawn from the built env.

Saving writes ``env/NAME.yaml`` with the edited ``arena``, ``obstacles``, ``goals`` and
``starts``; every other key and comment of the loaded file is kept, and an unchanged env is
written back byte for byte.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cobelrun.errors import CobelError, ConfigError
from cobelrun.web import edit_config as ec
from cobelrun.web.arena_design import ARENA_TOOLS, ENV_TARGETS, ArenaDesign

#: built-in arenas to start from: name -> label
ARENA_TEMPLATES: dict[str, str] = {
    "arena": "open square (the paper's 2D interface)",
    "water_maze": "Morris water maze (pool, platform, 493 place cells)",
}
#: the built-in task whose protocol comes with a built-in arena
ARENA_TASKS = {"water_maze": "morris_water_maze"}
#: a click in world units (the SVG's data-* give the transform)
CLICK_JS = """(e) => {
  const svg = e.target.closest('svg');
  if (!svg) return;
  const b = svg.getBoundingClientRect(), s = +svg.dataset.scale;
  emit({x: +svg.dataset.x0 + (e.clientX - b.left) / s,
        y: +svg.dataset.y1 - (e.clientY - b.top) / s});
}"""
_KEYS = ("arena", "obstacles", "goals", "starts")


@dataclass
class LoadedArena:
    design: ArenaDesign
    doc: Any
    text: str
    source: Path | None
    origin: str
    loaded: ArenaDesign
    task_doc: Any = None
    task_source: Path | None = None


def _from_text(text: str, where: str, source: Path | None) -> LoadedArena:
    doc = ec._yaml().load(text)
    if not isinstance(doc, dict):
        raise ConfigError(f"{where} is not an env config: it holds no mapping of config keys")
    design = ArenaDesign.from_env_config(ec.plain(doc), where)
    return LoadedArena(design, doc, text, source, where, design.copy())


def load_arena(folder: Path | None, name: str) -> LoadedArena:
    """``env/NAME.yaml`` of ``folder``, else the built-in env NAME, as an arena design."""
    ec.check_name(name)
    path = None if folder is None else folder / "env" / f"{name}.yaml"
    source = path
    if path is None or not path.exists():
        path, source = ec._builtin() / "env" / f"{name}.yaml", None
    ec.read_yaml(path)  # size and aliases bounded, a mapping
    where = str(path) if source is not None else f"template {name}"
    loaded = _from_text(path.read_text(encoding="utf-8"), where, source)
    task = None  # the protocol that comes along: the folder's task/NAME.yaml or a built-in one
    if folder is not None and (folder / "task" / f"{name}.yaml").is_file():
        task, dirs = ec.read_yaml(folder / "task" / f"{name}.yaml"), [folder, ec._builtin()]
    elif source is None and name in ARENA_TASKS:
        task, dirs = (
            ec.read_yaml(ec._builtin() / "task" / f"{ARENA_TASKS[name]}.yaml"),
            [ec._builtin()],
        )
    if task is not None:
        loaded.task_doc = task
        if folder is not None and (folder / "task" / f"{name}.yaml").is_file():
            loaded.task_source = folder / "task" / f"{name}.yaml"
        proto = ec._task_protocol(task, dirs) or {}
        for d in (loaded.design, loaded.loaded):
            d.phases = [dict(p) for p in proto.get("phases") or [] if isinstance(p, dict)]
            d.max_steps = int(proto.get("max_steps", 100))
    return loaded


def arena_env_names(folder: Path) -> list[str]:
    out = []
    for name in ec.env_names(folder):
        try:
            if ec.read_yaml(folder / "env" / f"{name}.yaml").get("_target_") in ENV_TARGETS:
                out.append(name)
        except CobelError:
            continue
    return out


def arena_text(loaded: LoadedArena, design: ArenaDesign) -> str:
    """``env/NAME.yaml``: unchanged, or the loaded data with the arena's keys replaced."""
    from ruamel.yaml.comments import CommentedMap

    if design.node == loaded.loaded.node:  # (phases are shown, not edited here)
        return loaded.text
    doc = loaded.doc
    for key in _KEYS:
        value = design.node.get(key)
        if value is None:
            doc.pop(key, None)
        elif key in ("goals", "starts") and isinstance(value, dict):
            m = CommentedMap()
            for k, v in value.items():
                m[k] = _flow_map(v) if isinstance(v, dict) else ec._flow(list(v))
            doc[key] = m
        elif key == "obstacles":
            doc[key] = ec._block([_flow_map(o) for o in value])
        else:
            doc[key] = _flow_map(value)
    if loaded.source is None and ec.MARK not in loaded.text:
        doc.yaml_set_start_comment(f"Arena {ec.MARK} from {loaded.origin}.")
    return ec.dump(doc)


def _flow_map(d: dict[str, Any]) -> Any:
    from ruamel.yaml.comments import CommentedMap

    m = CommentedMap({k: ec._flow([ec._flow(p) for p in v]) if k == "points" else v
                      for k, v in d.items()})  # fmt: skip
    m.fa.set_flow_style()
    return m


def save_arena(folder: Path, name: str, loaded: LoadedArena, design: ArenaDesign, *,
               with_task: bool = False) -> Path:  # fmt: skip
    """Write ``env/NAME.yaml`` (and, ``with_task``, ``task/NAME.yaml``: the task that came
    with the arena, its env and name set to NAME) after the checks; the env file written."""
    from cobelrun.targets import check_config

    ec.check_name(name)
    problems = design.problems()
    if problems:
        raise ConfigError(f"not saved: {problems[0][0]}")
    path = ec._inside(folder, folder / "env" / f"{name}.yaml")
    outputs = [(path, arena_text(loaded, design), loaded.source)]
    if with_task:
        if loaded.task_doc is None:
            raise ConfigError("no task came with this arena (a template with a protocol, such "
                              "as water_maze, or the folder's task/NAME.yaml); write one yourself")  # fmt: skip
        outputs.append((ec._inside(folder, folder / "task" / f"{name}.yaml"),
                        ec.task_file_text(loaded.task_doc, name), loaded.task_source))  # fmt: skip
    for out, text, source in outputs:
        ours = source is not None and out.resolve() == source.resolve()
        if out.exists() and not ours and out.read_text(encoding="utf-8") != text:
            raise CobelError(f"{out} exists; pick another name (or load it to edit it)")
        check_config(ec.plain(ec._yaml().load(text)), "env" if out == path else "task")
    for out, text, _ in outputs:
        ec._write(out, text)
    return path


class ArenaPage:
    """One browser tab's arena editor."""

    def __init__(self, editor: Any, env: str = "") -> None:
        self.editor = editor
        folder = self.folder = editor.folder
        self.error = ""
        self.loaded = load_arena(None, "arena")
        self.name0 = "my_arena"
        if env:
            try:
                self.loaded, self.name0 = load_arena(folder, env), env
            except CobelError as exc:
                self.error = str(exc)
        self.design = self.loaded.design.copy()
        self.history: list[ArenaDesign] = []
        self.tool = "start"
        self.pose: tuple[float, float] | None = None
        self.phase: int | None = None

    def build(self) -> None:
        from nicegui import ui

        with ui.row().classes("items-center w-full"):
            ui.label("cobel edit: 2D arena").classes("text-xl font-bold")
            ui.link("gridworlds", "/").classes("text-sm")
            ui.link("topology graphs", "/graph").classes("text-sm")
            self.origin = ui.label().classes("text-sm text-gray-600 cobel-origin")
        with ui.row().classes("w-full no-wrap items-start gap-6"):
            with ui.column().classes("w-72 gap-1"):
                with ui.row().classes("items-center no-wrap"):
                    self.template = ui.select(ARENA_TEMPLATES, value=None, label="template")
                    self.template.classes("w-48 cobel-template")
                    ui.button("load", on_click=self._load_template).props("dense").classes(
                        "cobel-load-template"
                    )
                with ui.row().classes("items-center no-wrap"):
                    self.existing = ui.select(arena_env_names(self.folder), value=None,
                                              label="arena in the folder").classes("w-48")  # fmt: skip
                    ui.button("open", on_click=self._open).props("dense")
                ui.label("outline").classes("font-bold mt-2")
                with ui.row().classes("items-center no-wrap"):
                    self.shape = ui.select(["circle", "square"], value="circle").classes("w-24")
                    self.size = ui.number("radius / side", value=1.0, min=0.01).classes("w-28")
                    ui.button("set", on_click=self._outline).props("dense").classes(
                        "cobel-outline-set"
                    )
                ui.label("tools").classes("font-bold mt-2")
                self.tool_buttons = {}
                with ui.grid(columns=2).classes("gap-1"):
                    for name, what in ARENA_TOOLS.items():
                        b = ui.button(name, on_click=lambda _, n=name: self._set_tool(n))
                        b.props("dense no-caps").classes(f"cobel-tool cobel-tool-{name}")
                        b.tooltip(what)
                        self.tool_buttons[name] = b
                ui.button("finish shape", on_click=self._finish).props("dense").classes(
                    "cobel-finish"
                )
                with ui.row().classes("items-center no-wrap"):
                    self.radius = ui.number("goal radius", value=0.1, min=0.001).classes("w-28")
                    self.reward = ui.number("reward", value=1.0).classes("w-24")
                ui.label("phase").classes("font-bold mt-2")
                self.phase_select = ui.select({-1: "env (as built)"}, value=-1,
                                              on_change=self._set_phase).classes(
                    "w-64 cobel-phase")  # fmt: skip
                ui.button("undo", on_click=self._undo).props("dense").classes("cobel-undo")
            with ui.column().classes("gap-2"):
                self.canvas = ui.html("", sanitize=False).classes("cobel-arena-box")
                self.canvas.on("click", self._click, js_handler=CLICK_JS)
                self.problem_list = ui.column().classes("gap-0 cobel-problems")
                self.info = ui.label().classes("text-sm text-gray-700 cobel-info")
            with ui.column().classes("w-96 gap-1"):
                self.name = ui.input("env name", value=self.name0).classes("w-64 cobel-name")
                self.with_task = ui.checkbox("also write task/NAME.yaml (the protocol's task)")
                self.with_task.classes("cobel-with-task")
                with ui.row():
                    ui.button("save", on_click=self._save).classes("cobel-save")
                    ui.button("run it", on_click=self._run_it).classes("cobel-run")
                with ui.row():
                    ui.button("export PNG", on_click=lambda: self._export("png")).props(
                        "dense outline"
                    ).classes("cobel-export-png")
                    ui.button("export SVG", on_click=lambda: self._export("svg")).props(
                        "dense outline"
                    ).classes("cobel-export-svg")
                self.status = ui.label(self.error).classes("text-sm cobel-status")
                from cobelrun.web.edit_runs import RunPanel

                self.runner = RunPanel(self.editor)
                ui.label("env/NAME.yaml as it will be saved").classes("font-bold mt-2")
                self.yaml = ui.code("", language="yaml").classes("w-96 text-xs cobel-yaml")
        self.refresh()

    def refresh(self) -> None:
        from nicegui import ui

        problems = self.design.problems()
        bad = problems[0][1] if problems else None
        self.canvas.content = self.design.svg(pose=self.pose, bad=bad, phase=self.phase)
        opts = {-1: "env (as built)"}
        opts.update({i: f"phase {i + 1}: {n}" for i, n in enumerate(self.design.phase_names())})
        if self.phase_select.options != opts:
            self.phase_select.set_options(opts, value=-1 if self.phase is None else self.phase)
        self.problem_list.clear()
        with self.problem_list:
            for msg, _ in problems:
                ui.label(msg).classes("text-sm text-negative cobel-problem")
            if not problems:
                ui.label("no problems: cobel run accepts this arena").classes(
                    "text-sm text-positive cobel-ok"
                )
        pending = len(self.design.pending)
        self.info.text = ((f"{pending} vertices drawn; 'finish shape' closes the polygon. " if
                           pending else "") + "blue dots: place-cell centres; green lines: "
                          "boundary-vector rays at the pose clicked with 'rays'")  # fmt: skip
        self.origin.text = f"from {self.loaded.origin}"
        for n, b in self.tool_buttons.items():
            b.props(f"color={'primary' if n == self.tool else 'grey-6'}")
        try:
            self.yaml.content = arena_text(self.loaded, self.design)
        except CobelError as exc:
            self.yaml.content = f"# {exc}"

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

    def _set_tool(self, name: str) -> None:
        self.tool = name
        self.refresh()

    def _set_phase(self, e: Any) -> None:
        self.phase = None if e.value in (None, -1) else int(e.value)
        self.refresh()

    def _click(self, e: Any) -> None:
        a = e.args if isinstance(e.args, dict) else {}
        try:
            x, y = float(a["x"]), float(a["y"])
        except (KeyError, TypeError, ValueError):
            return
        d = self.design
        x0, _, x1, _ = d.bounds()
        if self.tool == "start":
            self._change(lambda: d.add_start(x, y))
        elif self.tool == "goal":
            r, v = float(self.radius.value or 0.0), float(self.reward.value or 0.0)
            self._change(lambda: d.add_goal(x, y, r, v))
        elif self.tool in ("obstacle", "outline"):
            self._change(lambda: d.add_vertex(x, y))
        elif self.tool == "erase":
            self._change(lambda: d.erase(x, y, 0.03 * (x1 - x0)))
        elif self.tool == "rays":
            self.pose = (x, y)
            self.refresh()

    def _finish(self) -> None:
        what = "outline" if self.tool == "outline" else "obstacle"
        self._change(lambda: self.design.finish(what))

    def _outline(self) -> None:
        self._change(lambda: self.design.set_outline(str(self.shape.value),
                                                     float(self.size.value or 0.0)))  # fmt: skip

    def _undo(self) -> None:
        if self.history:
            self.design = self.history.pop()
            self.refresh()

    def _use(self, loaded: LoadedArena, name: str) -> None:
        self.loaded, self.design = loaded, loaded.design.copy()
        self.history.clear()
        self.pose, self.phase = None, None
        self.name.value = name
        self.status.text = f"loaded {loaded.origin}"
        self.refresh()

    def _load_template(self) -> None:
        if self.template.value:
            try:
                self._use(load_arena(None, self.template.value), self.template.value)
            except CobelError as exc:
                self.status.text = str(exc)

    def _open(self) -> None:
        if self.existing.value:
            try:
                self._use(load_arena(self.folder, self.existing.value), self.existing.value)
            except CobelError as exc:
                self.status.text = str(exc)

    def _save(self) -> Path | None:
        name = str(self.name.value or "").strip()
        try:
            path = save_arena(self.folder, name, self.loaded, self.design,
                              with_task=bool(self.with_task.value))  # fmt: skip
            self.loaded = load_arena(self.folder, name)
        except CobelError as exc:
            self.status.text = str(exc)
            return None
        self.design = self.loaded.design.copy()
        self.existing.set_options(arena_env_names(self.folder))
        self.status.text = f"saved {path}" + (" and its task" if self.with_task.value else "")
        self.refresh()
        return path

    def _run_it(self) -> None:
        """Save, then ``cobel run -cd DIR task=NAME env=NAME`` (one run: an arena's trials
        are long), for arenas whose task is written or in the folder."""
        name = str(self.name.value or "").strip()
        has_task = (self.folder / "task" / f"{name}.yaml").is_file()
        if not (self.with_task.value or has_task):
            self.status.text = ("run it needs a task: tick 'also write task/NAME.yaml' (an arena "
                                "that came with a protocol), or write task/NAME.yaml")  # fmt: skip
            return
        if self._save() is not None:
            self.runner.start(name, name, runs=1)

    def _export(self, fmt: str) -> None:
        from nicegui import ui

        from cobelrun.web.grid_design import geometry_figure

        try:
            data = geometry_figure(self.design.export_env(), fmt)
        except CobelError as exc:
            self.status.text = str(exc)
            return
        name = str(self.name.value or "").strip() or "maze"
        ui.download.content(data, f"{name}.{fmt}")
