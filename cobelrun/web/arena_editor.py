"""``cobel edit``'s 2D-arena page (``/arena``): outline, obstacles, goal regions and start
points of a :class:`~cobelrun.envs.continuous.Continuous2DEnv`, with the env's place-cell
centres and the boundary-vector rays at a clicked pose drawn from the built env.

The start heading (``start_heading``: degrees, ``random`` or ``centre``, the env's one form)
is set and drawn as an arrow at each start. The phases of the protocol that comes with the
arena are edited on the page (a goal switched on or off, a new goal, the starts), with the run's
protocol code checking them, and written into ``task/NAME.yaml`` as ``task.protocol``.

Saving writes ``env/NAME.yaml`` with the edited ``arena``, ``obstacles``, ``goals``,
``starts`` and ``start_heading``; every other key and comment of the loaded file is kept, and
an unchanged env is written back byte for byte.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cobelrun.errors import CobelError, ConfigError
from cobelrun.web import edit_config as ec
from cobelrun.web.arena_design import ARENA_TOOLS, ENV_TARGETS, ArenaDesign
from cobelrun.web.edit_page import EditPage

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
_KEYS = ("arena", "obstacles", "goals", "starts", "start_heading")
#: outlines the "set" button makes (a polygon is drawn with the outline tool)
OUTLINES = ("circle", "square")
#: the start heading menu: the env's start_heading forms
HEADINGS = {"centre": "face the centre", "random": "random", "angle": "angle (degrees)"}


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

    if design.node == loaded.loaded.node:  # (phases go to the task)
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
        elif not isinstance(value, dict):  # start_heading: degrees, random or centre
            doc[key] = value
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
        text = ec.protocol_task_text(loaded.task_doc, name, design, loaded.loaded)
        outputs.append((ec._inside(folder, folder / "task" / f"{name}.yaml"), text,
                        loaded.task_source))  # fmt: skip
    ec.write_configs(folder, [(out, text, (source,)) for out, text, source in outputs], path)
    return path


class ArenaPage(EditPage):
    """One browser tab's arena editor (the parts shared with the other pages come from
    :class:`EditPage`)."""

    here = "/arena"
    title = "cobel edit: 2D arena"
    phase_tools = ("The goal tool (on a goal: switch it on or off; elsewhere: a new goal this "
                   "phase switches on) and the start and erase tools now change what this "
                   "phase sets")  # fmt: skip
    task_label = "also write task/NAME.yaml (the protocol's task)"
    existing_label = "arena in the folder"

    def __init__(self, editor: Any, env: str = "") -> None:
        self.editor = editor
        self.error = ""
        self.loaded = load_arena(None, "arena")
        self.start_name = "my_arena"
        if env:
            try:
                self.loaded, self.start_name = load_arena(editor.folder, env), env
            except CobelError as exc:
                self.error = str(exc)
        self.design = self.loaded.design.copy()
        self.init_state()
        self.tool = "start"
        self.pose: tuple[float, float] | None = None

    def build(self) -> None:
        from nicegui import ui

        self.header()
        with ui.row().classes("w-full no-wrap items-start gap-6"):
            with ui.column().classes("w-72 gap-1"):
                self.load_rows(ARENA_TEMPLATES)
                ui.label("outline").classes("font-bold mt-2")
                with ui.row().classes("items-center no-wrap"):
                    self.shape = ui.select(list(OUTLINES), value="circle").classes(
                        "w-28 cobel-outline-shape"
                    )
                    self.size = ui.number("radius / side", value=1.0, min=0.01).classes(
                        "w-28 cobel-outline-size"
                    )
                    ui.button("set", on_click=self._outline).props("dense").classes(
                        "cobel-outline-set"
                    )
                ui.label("tools").classes("font-bold mt-2")
                self.tool_grid(ARENA_TOOLS)
                ui.button("finish shape", on_click=self._finish).props("dense").classes(
                    "cobel-finish"
                )
                with ui.row().classes("items-center no-wrap"):
                    self.radius = ui.number("goal radius", value=0.1, min=0.001).classes(
                        "w-28 cobel-radius"
                    )
                    self.reward = ui.number("reward", value=1.0).classes("w-24 cobel-value")
                ui.label("start heading").classes("font-bold mt-2")
                with ui.row().classes("items-center no-wrap"):
                    self.heading_kind = ui.select(HEADINGS, value="centre").classes(
                        "w-36 cobel-heading-kind"
                    )
                    self.heading_deg = ui.number("degrees", value=90.0).classes(
                        "w-20 cobel-heading-deg"
                    )
                    ui.button("set", on_click=self._heading).props("dense").classes(
                        "cobel-heading-set"
                    )
                self.phase_rows()
                ui.button("undo", on_click=self.undo).props("dense").classes("cobel-undo")
            with ui.column().classes("gap-2"):
                self.canvas = ui.html("", sanitize=False).classes("cobel-arena-box")
                self.canvas.on("click", self._click, js_handler=CLICK_JS)
                self.problem_list = ui.column().classes("gap-0 cobel-problems")
                self.info = ui.label().classes("text-sm text-gray-700 cobel-info")
            with ui.column().classes("w-96 gap-1"):
                self.save_panel()
        self.after_use()
        self.refresh()

    def refresh(self) -> None:
        from nicegui import ui

        self.refresh_common()
        problems = self.design.problems()
        bad = problems[0][1] if problems else None
        self.canvas.content = self.design.svg(pose=self.pose, bad=bad, phase=self.phase)
        self.problem_list.clear()
        with self.problem_list:
            for msg, _ in problems:
                ui.label(msg).classes("text-sm text-negative cobel-problem")
            if not problems:
                ui.label("no problems: cobel run accepts this arena").classes(
                    "text-sm text-positive cobel-ok"
                )
        pending = len(self.design.pending)
        h = self.design.start_heading()
        heading = (f"{h:g} degrees" if not isinstance(h, str) else
                   "facing the centre" if h == "centre" else "random")  # fmt: skip
        self.info.text = ((f"{pending} vertices drawn; 'finish shape' closes the polygon. " if
                           pending else "") + f"start heading: {heading} (arrows; dashed ring: "
                          "random); blue dots: place-cell centres; green lines: boundary-vector "
                          "rays at the pose clicked with 'rays'")  # fmt: skip
        try:
            self.yaml.content = arena_text(self.loaded, self.design)
        except CobelError as exc:
            self.yaml.content = f"# {exc}"

    def set_tool(self, name: str) -> None:
        self.tool = name
        self.refresh()

    def _click(self, e: Any) -> None:
        a = e.args if isinstance(e.args, dict) else {}
        try:
            x, y = float(a["x"]), float(a["y"])
        except (KeyError, TypeError, ValueError):
            return
        d = self.design
        x0, _, x1, _ = d.bounds()
        r, v = float(self.radius.value or 0.0), float(self.reward.value or 0.0)
        if self.tool == "rays":
            self.pose = (x, y)
            self.refresh()
        elif self.phase is not None:
            k, said = self.phase, []
            if self.change(lambda: said.append(d.paint_phase(self.tool, x, y, k, radius=r,
                                                             reward=v, tol=0.03 * (x1 - x0)))):  # fmt: skip
                self.status.text = said[0]
        elif self.tool == "start":
            self.change(lambda: d.add_start(x, y))
        elif self.tool == "goal":
            self.change(lambda: d.add_goal(x, y, r, v))
        elif self.tool in ("obstacle", "outline"):
            self.change(lambda: d.add_vertex(x, y))
        elif self.tool == "erase":
            self.change(lambda: d.erase(x, y, 0.03 * (x1 - x0)))

    def _finish(self) -> None:
        what = "outline" if self.tool == "outline" else "obstacle"
        if self.change(lambda: self.design.finish(what)) and what == "outline":
            self.after_use()  # the outline menu reads polygon now, not the shape it had

    def _outline(self) -> None:
        self.change(lambda: self.design.set_outline(str(self.shape.value),
                                                    float(self.size.value or 0.0)))  # fmt: skip

    def _heading(self) -> None:
        kind = str(self.heading_kind.value)
        value = self.heading_deg.value if kind == "angle" else kind
        self.change(lambda: self.design.set_start_heading(value))

    def after_undo(self) -> None:
        self.after_use()

    def after_use(self) -> None:
        """The outline and heading widgets show the loaded arena (not their defaults)."""
        self.pose = None
        arena = self.design.node.get("arena") or {"shape": "square", "size": 1.0}
        kind = str(arena.get("shape", "square"))
        options = list(OUTLINES) if kind in OUTLINES else [*OUTLINES, kind]
        self.shape.set_options(options, value=kind)
        size = arena.get("radius") if kind == "circle" else arena.get("size")
        if isinstance(size, int | float):
            self.size.value = float(size)
        h = self.design.start_heading()
        self.heading_kind.value = h if isinstance(h, str) else "angle"
        if not isinstance(h, str):
            self.heading_deg.value = float(h)

    # ------------------------------------------------------------------ EditPage's hooks
    def load_template(self, name: str) -> LoadedArena:
        return load_arena(None, name)

    def load_existing(self, name: str) -> LoadedArena:
        return load_arena(self.folder, name)

    def existing_names(self) -> list[str]:
        return arena_env_names(self.folder)

    def write(self, name: str, with_task: bool) -> list[Path]:
        path = save_arena(self.folder, name, self.loaded, self.design, with_task=with_task)
        phases, max_steps = self.design.phases, self.design.max_steps
        self.loaded = load_arena(self.folder, name)
        if not with_task:  # phases stay as edited (they are written with the task)
            self.loaded.design.phases, self.loaded.design.max_steps = phases, max_steps
        self.design = self.loaded.design.copy()
        return [path, *([self.folder / "task" / f"{name}.yaml"] if with_task else [])]

    def run_target(self, name: str) -> tuple[str, int, list[str]]:
        """``task=NAME`` (one run: an arena's trials are long), for arenas whose task is
        written or in the folder."""
        has_task = (self.folder / "task" / f"{name}.yaml").is_file()
        if not (self.with_task.value or has_task):
            raise CobelError("run it needs a task: tick 'also write task/NAME.yaml' (an arena "
                             "that came with a protocol), or write task/NAME.yaml")  # fmt: skip
        return name, 1, []

    def figure(self, fmt: str) -> bytes:
        from cobelrun.web.grid_design import geometry_figure

        return geometry_figure(self.design.phase_env(self.phase), fmt)  # as the phase leaves it
