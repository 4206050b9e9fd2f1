"""``cobel edit``'s topology-graph page (``/graph``): nodes, edges, starts and goals of a
:class:`~cobelrun.envs.topology_env.TopologyEnv`, and a preview of the agent's camera view at
a node and heading, rendered by the env's own image observation (the run's pybullet scene).

Saving writes ``env/NAME.yaml`` with a ``cobelrun.envs.topology.manual`` topology; every other
key of the loaded env (actions, headings, step reward, the observation) and its comments are
kept, and an unchanged env is written back byte for byte.
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


def _from_text(text: str, where: str, source: Path | None) -> LoadedGraph:
    y = ec._yaml()
    doc = y.load(text)
    if not isinstance(doc, dict):
        raise ConfigError(f"{where} is not an env config: it holds no mapping of config keys")
    design = GraphDesign.from_env_config(ec.plain(doc), where)
    return LoadedGraph(design, doc, text, source, where, design.copy())


def load_graph_template(name: str) -> LoadedGraph:
    if name == "grid":
        return _from_text(_GRID_TEMPLATE, "template grid", None)
    path = ec._builtin() / "env" / f"{name}.yaml"
    if not path.is_file():
        raise ConfigError(f"graph template {name!r} is unknown; templates: "
                          f"{', '.join(GRAPH_TEMPLATES)} (or any built-in topology env)")  # fmt: skip
    ec.read_yaml(path)  # size and aliases bounded, a mapping
    return _from_text(path.read_text(encoding="utf-8"), f"template {name}", None)


def load_graph(folder: Path, name: str) -> LoadedGraph:
    """``env/NAME.yaml`` of ``folder`` (or the built-in env NAME) as a graph design."""
    ec.check_name(name)
    path = folder / "env" / f"{name}.yaml"
    if not path.exists():
        return load_graph_template(name)
    ec.read_yaml(path)
    return _from_text(path.read_text(encoding="utf-8"), str(path), path)


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

    if design == loaded.loaded:
        return loaded.text
    doc = loaded.doc
    node = design.env_node()
    topo = CommentedMap(node["topology"])
    topo["nodes"] = ec._block([ec._flow(p) for p in topo["nodes"]])
    topo["edges"] = ec._flow([ec._flow(e) for e in topo["edges"]])
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


def save_graph(folder: Path, name: str, loaded: LoadedGraph, design: GraphDesign) -> Path:
    """Write ``env/NAME.yaml`` after the graph passes the checks; the file written."""
    from cobelrun.targets import check_config

    ec.check_name(name)
    problems = design.problems()
    if problems:
        raise ConfigError(f"not saved: {problems[0]}")
    path = ec._inside(folder, folder / "env" / f"{name}.yaml")
    text = graph_text(loaded, design)
    ours = loaded.source is not None and path.resolve() == loaded.source.resolve()
    if path.exists() and not ours and path.read_text(encoding="utf-8") != text:
        raise CobelError(f"{path} exists; pick another name (or load it to edit it)")
    check_config(ec.plain(ec._yaml().load(text)), "env")
    ec._write(path, text)
    return path


def png_url(img: np.ndarray) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    plt.imsave(buf, img, format="png")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


class GraphPage:
    """One browser tab's graph editor."""

    def __init__(self, folder: Path, env: str = "") -> None:
        self.folder = folder
        self.error = ""
        self.loaded = load_graph_template("grid")
        self.name0 = "my_graph"
        if env:
            try:
                self.loaded, self.name0 = load_graph(folder, env), env
            except CobelError as exc:
                self.error = str(exc)
        self.design = self.loaded.design.copy()
        self.history: list[GraphDesign] = []
        self.tool = "node"
        self.selected: int | None = None

    def build(self) -> None:
        from nicegui import ui

        with ui.row().classes("items-center w-full"):
            ui.label("cobel edit: topology graph").classes("text-xl font-bold")
            ui.link("gridworlds", "/").classes("text-sm")
            ui.link("2D arenas", "/arena").classes("text-sm")
            self.origin = ui.label().classes("text-sm text-gray-600 cobel-origin")
        with ui.row().classes("w-full no-wrap items-start gap-6"):
            with ui.column().classes("w-72 gap-1"):
                with ui.row().classes("items-center no-wrap"):
                    self.template = ui.select(GRAPH_TEMPLATES, value=None, label="template")
                    self.template.classes("w-48 cobel-template")
                    ui.button("load", on_click=self._load_template).props("dense").classes(
                        "cobel-load-template"
                    )
                names = graph_env_names(self.folder)
                with ui.row().classes("items-center no-wrap"):
                    self.existing = ui.select(names, value=None, label="graph in the folder")
                    self.existing.classes("w-48 cobel-existing")
                    ui.button("open", on_click=self._open).props("dense").classes("cobel-open")
                ui.label("tools").classes("font-bold mt-2")
                self.tool_buttons = {}
                with ui.grid(columns=2).classes("gap-1"):
                    for name, what in GRAPH_TOOLS.items():
                        b = ui.button(name, on_click=lambda _, n=name: self._set_tool(n))
                        b.props("dense no-caps").classes(f"cobel-tool cobel-tool-{name}")
                        b.tooltip(what)
                        self.tool_buttons[name] = b
                self.value = ui.number("reward", value=1.0, step=0.5).classes("w-24 cobel-value")
                self.heading = ui.select([], label="heading (degrees)").classes(
                    "w-40 cobel-heading"
                )
                ui.button("undo", on_click=self._undo).props("dense").classes("cobel-undo")
            with ui.column().classes("gap-2"):
                self.graph = ui.html("", sanitize=False).classes("cobel-graph-box")
                self.graph.on("click", self._click, js_handler=CLICK_JS)
                self.problem_list = ui.column().classes("gap-0 cobel-problems")
                with ui.row().classes("items-center"):
                    self.view_label = ui.label().classes("text-sm cobel-view-label")
                self.view = (
                    ui.image().classes("w-96 cobel-view").style("image-rendering: pixelated")
                )
            with ui.column().classes("w-96 gap-1"):
                self.name = ui.input("env name", value=self.name0).classes("w-64 cobel-name")
                ui.button("save", on_click=self._save).classes("cobel-save")
                with ui.row():
                    ui.button("export PNG", on_click=lambda: self._export("png")).props(
                        "dense outline"
                    ).classes("cobel-export-png")
                    ui.button("export SVG", on_click=lambda: self._export("svg")).props(
                        "dense outline"
                    ).classes("cobel-export-svg")
                self.status = ui.label(self.error).classes("text-sm cobel-status")
                ui.label("env/NAME.yaml as it will be saved").classes("font-bold mt-2")
                self.yaml = ui.code("", language="yaml").classes("w-96 text-xs cobel-yaml")
        self.refresh()

    def refresh(self) -> None:
        from nicegui import ui

        d = self.design
        self.graph.content = d.svg(selected=self.selected)
        problems = d.problems()
        self.problem_list.clear()
        with self.problem_list:
            for p in problems:
                ui.label(p).classes("text-sm text-negative cobel-problem")
            if not problems:
                ui.label("no problems: cobel run accepts this graph").classes(
                    "text-sm text-positive cobel-ok"
                )
        self.origin.text = f"from {self.loaded.origin}"
        degrees = [round(float(a), 1) for a in np.rad2deg(2 * np.pi * np.arange(d.n_directions)
                                                         / d.n_directions)]  # fmt: skip
        if self.heading.options != degrees:
            self.heading.set_options(degrees, value=90.0 if 90.0 in degrees else degrees[0])
        for n, b in self.tool_buttons.items():
            b.props(f"color={'primary' if n == self.tool else 'grey-6'}")
        try:
            self.yaml.content = graph_text(self.loaded, d)
        except CobelError as exc:
            self.yaml.content = f"# {exc}"

    def _set_tool(self, name: str) -> None:
        self.tool, self.selected = name, None
        self.refresh()

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

    async def _click(self, e: Any) -> None:
        a = e.args if isinstance(e.args, dict) else {}
        d = self.design
        if "node" in a:
            i = int(a["node"])
            if not 0 <= i < len(d.nodes):
                return
            if self.tool == "node":
                self._change(lambda: d.remove_node(i))
            elif self.tool == "edge":
                if self.selected is None:
                    self.selected = i
                    self.refresh()
                else:
                    first, self.selected = self.selected, None
                    self._change(lambda: d.toggle_edge(first, i))
            elif self.tool == "view":
                self.selected = i
                self.refresh()
                await self._preview(i)
            else:
                value = float(self.value.value or 0.0)
                self._change(lambda: d.paint(self.tool, i, value))
        elif "x" in a and self.tool == "node":
            x, y = float(a["x"]), float(a["y"])
            self._change(lambda: d.add_node(x, y))

    async def _preview(self, i: int) -> None:
        from nicegui import run

        heading = float(self.heading.value or 0.0)
        self.view_label.text = f"rendering the view at node {i}, heading {heading:g} degrees ..."
        try:
            img = await run.io_bound(self.design.agent_view, i, heading)
        except CobelError as exc:
            self.view_label.text = str(exc)
            return
        if img is None:
            return
        self.view.set_source(png_url(img))
        self.view_label.text = (f"agent's view at node {i}, heading {heading:g} degrees "
                                f"({img.shape[0]} x {img.shape[1]} px, the run's camera)")  # fmt: skip

    def _undo(self) -> None:
        if self.history:
            self.design = self.history.pop()
            self.selected = None
            self.refresh()

    def _use(self, loaded: LoadedGraph, name: str) -> None:
        self.loaded, self.design = loaded, loaded.design.copy()
        self.history.clear()
        self.selected = None
        self.name.value = name
        self.status.text = f"loaded {loaded.origin}"
        self.refresh()

    def _load_template(self) -> None:
        if self.template.value:
            try:
                self._use(load_graph_template(self.template.value), self.template.value)
            except CobelError as exc:
                self.status.text = str(exc)

    def _open(self) -> None:
        if self.existing.value:
            try:
                self._use(load_graph(self.folder, self.existing.value), self.existing.value)
            except CobelError as exc:
                self.status.text = str(exc)

    def _save(self) -> None:
        name = str(self.name.value or "").strip()
        try:
            path = save_graph(self.folder, name, self.loaded, self.design)
            self.loaded = load_graph(self.folder, name)
        except CobelError as exc:
            self.status.text = str(exc)
            return
        self.design = self.loaded.design.copy()
        self.existing.set_options(graph_env_names(self.folder))
        self.status.text = f"saved {path}"
        self.refresh()

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
