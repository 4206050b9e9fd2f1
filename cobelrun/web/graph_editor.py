"""``cobel edit``'s topology-graph page (``/graph``): nodes, edges, starts and goals of a
:class:`~cobelrun.envs.topology_env.TopologyEnv`, what each phase of its task's protocol sets,
and a preview of the agent's camera view at a node and heading: the env's render cache where it
has one for the graph, else rendered by the env's own image observation (the run's pybullet
scene).

Saving writes ``env/NAME.yaml`` with a ``cobelrun.envs.topology.manual`` topology; every other
key of the loaded env (actions, headings, step reward, the observation) and its comments are
kept, and an unchanged env is written back byte for byte. With the task, ``task/NAME.yaml``
is the graph's task (the folder's, the built-in one of ``hex_3d``, or a DQN task for the grid
template) with edited phases inline. "Run it" runs that task for a quick look: one run, each
phase cut to a few trials.
"""

from __future__ import annotations

import base64
import io
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cobelrun.errors import CobelError, ConfigError
from cobelrun.web import edit_config as ec
from cobelrun.web.edit_page import EditPage
from cobelrun.web.graph_design import ENV_TARGETS, GRAPH_TOOLS, GraphDesign

#: built-in starting points of the graph page: name -> (label, env config as data or a file)
GRAPH_TEMPLATES: dict[str, str] = {
    "grid": "grid graph, 5 x 5, one 84 x 84 camera",
    "hex_3d": "hexagonal graph (Fig. 8), 240 degree panorama",
}
_GRID_TEMPLATE = """\
# A 5 x 5 grid graph seen through one camera (made with cobel edit).
_target_: cobelrun.envs.TopologyEnv
topology:
  _target_: cobelrun.envs.topology.grid
  width: 5
  height: 5
rewards: {24: 1.0}
terminals: [24]
starts: [0]
actions: turn
start_heading: 90
observation:
  _target_: cobelrun.envs.observations.ImageObservation
  height: 84
  width: 84
  fov: 90
  n_cameras: 1
  render: online
"""
#: the built-in task whose protocol comes with a built-in graph
GRAPH_TASKS = {"hex_3d": "place_cells"}
#: the task that comes with the grid template: DQN on the camera images, one phase
_GRID_TASK = """\
# @package _global_
# DQN finds the goal node of a topology graph from its camera images (made with cobel edit).
defaults:
  - override /env: grid
  - override /agent: dqn
  - override /protocol: single

task:
  name: grid
  description: "DQN on a topology graph's camera images (cobel edit's graph template)."
  runs: 1
  protocol:
    max_steps: 100
    phases:
      - name: training
        trials: 200
  monitors:
    reward: {_target_: cobelrun.monitors.RewardMonitor}
    latency: {_target_: cobelrun.monitors.EscapeLatencyMonitor}
    trajectory: {_target_: cobelrun.monitors.TrajectoryMonitor}
"""
#: "run it": at most this many trials per phase by default (graph tasks train deep agents on
#: rendered images: a quick look, not the experiment)
RUN_IT_TRIALS = 20
NO_TASK = ("no task came with this graph (a template, or the folder's task/NAME.yaml); write "
           "task/NAME.yaml yourself")  # fmt: skip
#: the graph's click handler: a node, or a point of the background in world units
CLICK_JS = """(e) => {
  const n = e.target.closest('[data-node]');
  if (n) { emit({node: +n.dataset.node}); return; }
  const svg = e.target.closest('svg');
  if (!svg) return;
  const b = svg.getBoundingClientRect(), px = +svg.dataset.px;
  emit({x: +svg.dataset.x0 + (e.clientX - b.left) / px,
        y: +svg.dataset.y1 - (e.clientY - b.top) / px});
}"""


@dataclass
class LoadedGraph:
    design: GraphDesign
    doc: Any
    text: str
    source: Path | None
    origin: str
    loaded: GraphDesign
    task_doc: Any = None
    task_source: Path | None = None


def _from_text(text: str, where: str, source: Path | None) -> LoadedGraph:
    y = ec._yaml()
    doc = y.load(text)
    if not isinstance(doc, dict):
        raise ConfigError(f"{where} is not an env config: it holds no mapping of config keys")
    design = GraphDesign.from_env_config(ec.plain(doc), where)
    return LoadedGraph(design, doc, text, source, where, design.copy())


def _with_task(loaded: LoadedGraph, task: Any, folders: list[Path]) -> LoadedGraph:
    """The task's data and its protocol's phases on the design (and on the design as loaded)."""
    loaded.task_doc = task
    proto = ec._task_protocol(task, folders) or {}
    for d in (loaded.design, loaded.loaded):
        d.phases = [dict(p) for p in proto.get("phases") or [] if isinstance(p, dict)]
        d.max_steps = int(proto.get("max_steps", 100))
    return loaded


def load_graph_template(name: str) -> LoadedGraph:
    """A graph template with the protocol of its task (:data:`GRAPH_TASKS`, the grid's DQN
    task)."""
    if name == "grid":
        loaded = _from_text(_GRID_TEMPLATE, "template grid", None)
        return _with_task(loaded, ec._yaml().load(_GRID_TASK), [ec._builtin()])
    path = ec._builtin() / "env" / f"{name}.yaml"
    if not path.is_file():
        raise ConfigError(f"graph template {name!r} is unknown; templates: "
                          f"{', '.join(GRAPH_TEMPLATES)} (or any built-in topology env)")  # fmt: skip
    ec.read_yaml(path)  # size and aliases bounded, a mapping
    loaded = _from_text(path.read_text(encoding="utf-8"), f"template {name}", None)
    if name in GRAPH_TASKS:
        task = ec.read_yaml(ec._builtin() / "task" / f"{GRAPH_TASKS[name]}.yaml")
        _with_task(loaded, task, [ec._builtin()])
    return loaded


def load_graph(folder: Path, name: str) -> LoadedGraph:
    """``env/NAME.yaml`` of ``folder`` (or the built-in env NAME) as a graph design, with the
    protocol of the folder's ``task/NAME.yaml`` where there is one."""
    ec.check_name(name)
    path = folder / "env" / f"{name}.yaml"
    if not path.exists():
        return load_graph_template(name)
    ec.read_yaml(path)
    loaded = _from_text(path.read_text(encoding="utf-8"), str(path), path)
    task_path = folder / "task" / f"{name}.yaml"
    if task_path.is_file():
        _with_task(loaded, ec.read_yaml(task_path), [folder, ec._builtin()])
        loaded.task_source = task_path
    return loaded


def quick_overrides(phases: list[dict[str, Any]], at_most: int) -> list[str]:
    """``task.protocol.phases.K.trials=N`` for each phase longer than ``at_most`` trials
    ("run it" is a quick look)."""
    out = []
    for k, p in enumerate(phases):
        trials = p.get("trials")
        if isinstance(trials, int) and trials > at_most:
            out.append(f"task.protocol.phases.{k}.trials={int(at_most)}")
    return out


def graph_env_names(folder: Path) -> list[str]:
    """The folder's env configs that are topology graphs the page draws."""
    out = []
    for name in ec.env_names(folder):
        try:
            doc = ec.read_yaml(folder / "env" / f"{name}.yaml")
        except CobelError:
            continue
        topo = doc.get("topology")
        if doc.get("_target_") in ENV_TARGETS and isinstance(topo, dict):
            out.append(name)
    return out


def graph_text(loaded: LoadedGraph, design: GraphDesign) -> str:
    """The text ``env/NAME.yaml`` gets: unchanged, or the loaded data with ``topology``,
    ``rewards``, ``terminals`` and ``starts`` replaced (other keys and comments kept)."""
    from ruamel.yaml.comments import CommentedMap

    if _no_phases(design) == _no_phases(loaded.loaded):  # (phases go to the task)
        return loaded.text
    doc = loaded.doc
    node = design.env_node()
    topo = CommentedMap(node["topology"])
    topo["nodes"] = ec._block([ec._flow(p) for p in topo["nodes"]])
    pairs = [ec._flow(e) for e in topo["edges"]]  # one a line where many (as gridworld doors):
    topo["edges"] = ec._flow(pairs) if len(pairs) <= 8 else ec._block(pairs)  # no [\n 6, 11]
    doc["topology"] = topo
    for key in ("rewards", "terminals", "starts"):
        if key in node:
            value = node[key]
            doc[key] = ec._flow(value) if isinstance(value, list) else value
        else:
            doc.pop(key, None)
    if loaded.source is None and ec.MARK not in loaded.text:
        doc.yaml_set_start_comment(f"Topology graph {ec.MARK} from {loaded.origin}.")
    return ec.dump(doc)


def _no_phases(design: GraphDesign) -> GraphDesign:
    d = design.copy()
    d.phases, d.max_steps = [], 0
    return d


def save_graph(folder: Path, name: str, loaded: LoadedGraph, design: GraphDesign, *,
               with_task: bool = False) -> list[Path]:  # fmt: skip
    """Write ``env/NAME.yaml`` (and, ``with_task``, ``task/NAME.yaml``: the graph's task with
    its env and name set to NAME and edited phases inline) after the checks; the files
    written."""
    ec.check_name(name)
    problems = design.problems()
    if problems:
        raise ConfigError(f"not saved: {problems[0]}")
    path = ec._inside(folder, folder / "env" / f"{name}.yaml")
    outputs = [(path, graph_text(loaded, design), loaded.source)]
    if with_task:
        if loaded.task_doc is None:
            raise ConfigError(NO_TASK)
        text = ec.protocol_task_text(loaded.task_doc, name, design, loaded.loaded)
        outputs.append((ec._inside(folder, folder / "task" / f"{name}.yaml"), text,
                        loaded.task_source))  # fmt: skip
    ec.write_configs(folder, [(out, text, (source,)) for out, text, source in outputs], path)
    return [out for out, _, _ in outputs]


def png_url(img: np.ndarray) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    plt.imsave(buf, img, format="png")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


class GraphPage(EditPage):
    """One browser tab's graph editor (the parts shared with the other pages come from
    :class:`EditPage`)."""

    here = "/graph"
    title = "cobel edit: topology graph"
    phase_tools = "The start, goal, terminal and clear tools now change what this phase sets"
    task_label = "also write task/NAME.yaml (the graph's task: protocol, agent, monitors)"
    existing_label = "graph in the folder"

    def __init__(self, editor: Any, env: str = "") -> None:
        self.editor = editor
        self.error = ""
        self.loaded = load_graph_template("grid")
        self.start_name = "my_graph"
        if env:
            try:
                self.loaded, self.start_name = load_graph(editor.folder, env), env
            except CobelError as exc:
                self.error = str(exc)
        self.design = self.loaded.design.copy()
        self.init_state()
        self.tool = "node"
        self.selected: int | None = None

    def build(self) -> None:
        from nicegui import ui

        self.header()
        with ui.row().classes("w-full no-wrap items-start gap-6"):
            with ui.column().classes("w-72 gap-1"):
                self.load_rows(GRAPH_TEMPLATES)
                ui.label("tools").classes("font-bold mt-2")
                self.tool_grid(GRAPH_TOOLS)
                self.value = ui.number("reward", value=1.0, step=0.5).classes("w-24 cobel-value")
                self.heading = ui.select([], label="heading (degrees)").classes(
                    "w-40 cobel-heading"
                )
                self.phase_rows()
                ui.button("undo", on_click=self.undo).props("dense").classes("cobel-undo")
            with ui.column().classes("gap-2"):
                self.graph = ui.html("", sanitize=False).classes("cobel-graph-box")
                self.graph.on("click", self._click, js_handler=CLICK_JS)
                self.problem_list = ui.column().classes("gap-0 cobel-problems")
                self.view_label = ui.label().classes("text-sm cobel-view-label")
                self.view_source = ui.label().classes("text-xs text-gray-600 cobel-view-source")
                self.view = (
                    ui.image().classes("w-96 cobel-view").style("image-rendering: pixelated")
                )
            with ui.column().classes("w-96 gap-1"):
                self.save_panel()
        self.refresh()

    def refresh(self) -> None:
        from nicegui import ui

        d = self.design
        self.refresh_common()
        problems = d.problems()
        self.graph.content = d.svg(selected=self.selected, phase=self.phase, problems=problems)
        self.problem_list.clear()
        with self.problem_list:
            for p in problems:
                ui.label(p).classes("text-sm text-negative cobel-problem")
            if not problems:
                ui.label("no problems: cobel run accepts this graph").classes(
                    "text-sm text-positive cobel-ok"
                )
        degrees = [round(float(a), 1) for a in np.rad2deg(2 * np.pi * np.arange(d.n_directions)
                                                         / d.n_directions)]  # fmt: skip
        if self.heading.options != degrees:
            self.heading.set_options(degrees, value=90.0 if 90.0 in degrees else degrees[0])
        try:
            self.yaml.content = graph_text(self.loaded, d)
        except CobelError as exc:
            self.yaml.content = f"# {exc}"

    def run_options(self) -> None:
        from nicegui import ui

        self.quick = ui.number("run it: at most this many trials per phase",
                               value=RUN_IT_TRIALS, min=1, precision=0)  # fmt: skip
        self.quick.classes("w-72 cobel-run-trials")

    def set_tool(self, name: str) -> None:
        self.tool, self.selected = name, None
        self.refresh()

    def after_undo(self) -> None:
        self.selected = None

    def after_use(self) -> None:
        self.selected = None

    async def _click(self, e: Any) -> None:
        a = e.args if isinstance(e.args, dict) else {}
        d = self.design
        if "node" in a:
            i = int(a["node"])
            if not 0 <= i < len(d.nodes):
                return
            if self.tool == "node":
                self.change(lambda: d.remove_node(i))
            elif self.tool == "edge":
                if self.selected is None:
                    self.selected = i
                    self.refresh()
                else:
                    first, self.selected = self.selected, None
                    self.change(lambda: d.toggle_edge(first, i))
            elif self.tool == "view":
                self.selected = i
                self.refresh()
                await self._preview(i)
            else:
                value = float(self.value.value or 0.0)
                self.change(lambda: d.paint(self.tool, i, value, phase=self.phase))
        elif "x" in a and self.tool == "node":
            x, y = float(a["x"]), float(a["y"])
            self.change(lambda: d.add_node(x, y))

    async def _preview(self, i: int) -> None:
        from nicegui import run

        heading = float(self.heading.value or 0.0)
        self.view_label.text = f"rendering the view at node {i}, heading {heading:g} degrees ..."
        self.view_source.text = ""
        try:
            img, source = await run.io_bound(self.design.preview, i, heading)
        except CobelError as exc:
            self.view_label.text = str(exc)
            return
        self.view.set_source(png_url(img))
        self.view_label.text = (f"agent's view at node {i}, heading {heading:g} degrees "
                                f"({img.shape[0]} x {img.shape[1]} px, the run's camera)")  # fmt: skip
        self.view_source.text = source

    # ------------------------------------------------------------------ EditPage's hooks
    def load_template(self, name: str) -> LoadedGraph:
        return load_graph_template(name)

    def load_existing(self, name: str) -> LoadedGraph:
        return load_graph(self.folder, name)

    def existing_names(self) -> list[str]:
        return graph_env_names(self.folder)

    def write(self, name: str, with_task: bool) -> list[Path]:
        written = save_graph(self.folder, name, self.loaded, self.design, with_task=with_task)
        phases, max_steps = self.design.phases, self.design.max_steps
        self.loaded = load_graph(self.folder, name)
        if not with_task:  # phases stay as edited (they are written with the task)
            self.loaded.design.phases, self.loaded.design.max_steps = phases, max_steps
        self.design = self.loaded.design.copy()
        return written

    def run_target(self, name: str) -> tuple[str, int, list[str]]:
        has_task = (self.folder / "task" / f"{name}.yaml").is_file()
        if not (self.with_task.value or has_task):
            raise CobelError("run it needs a task: tick 'also write task/NAME.yaml' (the graph's "
                             "task), or write task/NAME.yaml")  # fmt: skip
        if self.with_task.value and self.loaded.task_doc is None:
            raise CobelError(NO_TASK)
        return name, 1, quick_overrides(self.design.phases, int(self.quick.value or 1))

    def figure(self, fmt: str) -> bytes:
        from cobelrun.web.grid_design import geometry_figure

        return geometry_figure(self.design.phase_env(self.phase), fmt)  # as the phase leaves it
