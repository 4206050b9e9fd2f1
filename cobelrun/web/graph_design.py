"""What ``cobel edit`` edits for topology graphs (the 3D mazes): nodes, edges, starts, goals.

A :class:`GraphDesign` holds node positions, undirected edges, the number of heading
directions, named places, node rewards, terminal nodes and start nodes, plus the env's other
keys (``actions``, ``start_heading``, ``step_reward``, ``observation``, ...) unchanged. It
becomes a :class:`~cobelrun.envs.topology_env.TopologyEnv` config whose ``topology`` is
:func:`cobelrun.envs.topology.manual`; it is checked by building that env with the code
``cobel run`` uses, and the agent's view at a node and heading is rendered by the env's own
:class:`~cobelrun.envs.observations.ImageObservation` (the run's pybullet scene, image size and
field of view), built through cobel's instantiation gate.

Graphs built from a gridworld (``world:`` configs such as ``tmaze_3d``) are edited as that
gridworld; this module takes graphs given by a ``topology:`` node.
"""

from __future__ import annotations

import copy
import html
import re
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cobelrun.errors import CobelError, ConfigError, LayoutError

__all__ = ["GRAPH_TOOLS", "MAX_NODES", "GraphDesign"]

#: the most nodes the editor draws
MAX_NODES = 400
#: tools of the graph page: name -> what a click does
GRAPH_TOOLS: dict[str, str] = {
    "node": "click empty space: add a node there (snapped to the spacing); click a node: remove it",
    "edge": "click two nodes: add or remove the edge between them",
    "start": "toggle a start node",
    "goal": "terminal node paying the reward in the box",
    "terminal": "terminal node without reward",
    "clear": "no reward, not terminal, not a start",
    "view": "preview the agent's camera view at the node (heading from the menu)",
}
#: topology builders whose graphs the editor loads
TOPOLOGY_BUILDERS = tuple(
    f"cobelrun.envs.topology.{name}" for name in ("grid", "hexagonal", "delaunay", "manual")
)
ENV_TARGETS = ("cobelrun.envs.TopologyEnv", "cobelrun.envs.topology_env.TopologyEnv")


@dataclass
class GraphDesign:
    """A topology graph as the editor holds it.

    Attributes
    ----------
    nodes : list of (x, y)
        Node positions (cell units of the 3D scene).
    edges : set of (a, b)
        Undirected edges between node indices, ``a < b``.
    n_directions : int
        Heading directions (4: grid, 6: hexagonal).
    places : dict name -> node
    rewards : dict node -> float
    terminals : set of node
    starts : list of node, or "all"
    extra : dict
        The env's other keys, kept as loaded (plain data).
    spacing : float
        Grid step new nodes snap to.
    phases, max_steps : list of dict, int
        The protocol of the task that uses the graph (plain data, unknown keys kept); the
        ``rewards``, ``terminals`` and ``starts`` a phase sets are painted with ``phase=``.
    """

    nodes: list[tuple[float, float]]
    edges: set[tuple[int, int]] = field(default_factory=set)
    n_directions: int = 4
    places: dict[str, int] = field(default_factory=dict)
    rewards: dict[int, float] = field(default_factory=dict)
    terminals: set[int] = field(default_factory=set)
    starts: list[int] | str = "all"
    extra: dict[str, Any] = field(default_factory=dict)
    spacing: float = 1.0
    phases: list[dict[str, Any]] = field(default_factory=list)
    max_steps: int = 100
    #: the loaded topology node and the graph it built (the run builds that node while the
    #: graph is unchanged: its exact positions, so its render-cache key)
    source: tuple[dict[str, Any], Any] | None = field(default=None, compare=False, repr=False)

    @classmethod
    def from_env_config(cls, node: dict[str, Any], where: str) -> GraphDesign:
        """The design of a TopologyEnv config (plain data); its topology is built through the
        gate (:func:`cobelrun.config.instantiate`) after its size is checked."""
        from cobelrun.config import instantiate

        if node.get("_target_") not in ENV_TARGETS:
            raise ConfigError(f"{where} is not a topology env config (its _target_ is "
                              f"{node.get('_target_')!r})")  # fmt: skip
        topo_node = node.get("topology")
        if not isinstance(topo_node, dict) or topo_node.get("_target_") not in TOPOLOGY_BUILDERS:
            raise ConfigError(
                f"{where}: cobel edit draws graphs given by a topology node built by grid, "
                "hexagonal, delaunay or manual; a graph built from a gridworld (world: ...) is "
                "edited as that gridworld"
            )
        w, h = topo_node.get("width", 9), topo_node.get("height", 9)
        if isinstance(w, int) and isinstance(h, int) and w * h > MAX_NODES:
            raise LayoutError(f"{where}: a {w} x {h} graph is too large to edit here (at most "
                              f"{MAX_NODES} nodes); edit its YAML instead")  # fmt: skip
        topology = instantiate("env.topology", topo_node)
        if topology.n_nodes > MAX_NODES:
            raise LayoutError(f"{where}: {topology.n_nodes} nodes are too many to edit here (at "
                              f"most {MAX_NODES}); edit its YAML instead")  # fmt: skip
        edges = {(int(min(a, b)), int(max(a, b))) for a, b in topology.edges.tolist()}
        d = cls(
            nodes=[(float(x), float(y)) for x, y in topology.positions.tolist()],
            edges=edges,
            n_directions=topology.n_directions,
            places=dict(topology.places),
            spacing=float(topo_node.get("spacing", 1.0)),
            extra={k: v for k, v in node.items()
                   if k not in ("_target_", "topology", "rewards", "terminals", "starts")},
        )  # fmt: skip
        d.source = (copy.deepcopy(topo_node), d._graph())
        d.rewards = {d.node(k): float(v) for k, v in (node.get("rewards") or {}).items()}
        terms = node.get("terminals") or []
        d.terminals = {d.node(t) for t in ([terms] if isinstance(terms, int | str) else terms)}
        starts = node.get("starts", "all")
        d.starts = "all" if starts in (None, "all") else [d.node(s) for s in starts]
        return d

    def copy(self) -> GraphDesign:
        return copy.deepcopy(self)

    def node(self, ref: Any) -> int:
        """A node index from an index or a place name."""
        if isinstance(ref, str) and ref in self.places:
            return self.places[ref]
        try:
            i = int(ref)
        except (TypeError, ValueError):
            raise ConfigError(f"{ref!r} is not a node; use an index or a place name") from None
        if not 0 <= i < len(self.nodes):
            raise LayoutError(f"node {i} is out of range; allowed 0..{len(self.nodes) - 1}")
        return i

    def ref(self, i: int) -> str | int:
        for name, at in self.places.items():
            if at == i:
                return name
        return int(i)

    # ------------------------------------------------------------------ to the env
    def topology_node(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "_target_": "cobelrun.envs.topology.manual",
            "nodes": [[round(x, 6), round(y, 6)] for x, y in self.nodes],
            "edges": [list(e) for e in sorted(self.edges)],
            "n_directions": int(self.n_directions),
        }
        if self.places:
            out["places"] = dict(self.places)
        return out

    def _graph(self) -> tuple[Any, ...]:
        return (list(self.nodes), set(self.edges), self.n_directions, dict(self.places))

    def run_topology_node(self) -> dict[str, Any]:
        """The topology node a run of the saved env builds: the loaded one while nodes, edges,
        headings and places are as loaded (the file keeps it), else :meth:`topology_node`."""
        if self.source is not None and self.source[1] == self._graph():
            return copy.deepcopy(self.source[0])
        return self.topology_node()

    def env_node(self) -> dict[str, Any]:
        """The env config (plain data): TopologyEnv, the manual topology, rewards, terminals,
        starts, and the kept keys."""
        out: dict[str, Any] = {"_target_": "cobelrun.envs.TopologyEnv",
                               "topology": self.topology_node()}  # fmt: skip
        if self.rewards:
            out["rewards"] = {self.ref(k): float(v) for k, v in sorted(self.rewards.items())}
        if self.terminals:
            out["terminals"] = [self.ref(t) for t in sorted(self.terminals)]
        out["starts"] = "all" if self.starts == "all" else [self.ref(s) for s in self.starts]
        out.update(self.extra)
        return out

    def export_env(self) -> Any:
        """The env built as a run builds it, without its observation (a check or a picture
        needs no camera): the topology, then the env around it, both through the gate."""
        from cobelrun.web.grid_design import build_with

        node = self.env_node()
        node.pop("observation", None)
        topology = build_with("env.topology", node.pop("topology"))
        return build_with("env", node, topology=topology)

    def problems(self) -> list[str]:
        """``cobel run``'s messages for this graph: the topology and the env built as a run
        builds them (the observation left out: it only renders)."""
        try:
            env = self.export_env()
        except CobelError as exc:
            return [str(exc)]
        out = []
        reach = _reachable(self, [int(s) for s in env.unwrapped.world.starts])
        for g in sorted(set(self.rewards) | self.terminals):
            if not reach[g]:
                out.append(f"goal node {g} is unreachable from every start; add an edge to it")
        if out or not self.phases:
            return out
        from cobelrun.protocol import Protocol

        try:  # each phase's changes, in order, as a run applies them
            protocol = Protocol.from_config(self.protocol_config())
        except CobelError as exc:
            return [f"task.protocol: {exc}"]
        for p in protocol.phases:
            try:
                protocol.apply(p, env)
                for k in range(len(p.cycle or ())):
                    protocol.apply_trial(p, k, env)
            except CobelError as exc:
                return [f"task.protocol phase {p.name!r}: {exc}"]
            world = env.unwrapped.world
            reach = _reachable(self, [int(s) for s in world.starts])
            paying = np.flatnonzero((world.rewards > 0) & ~reach)
            if paying.size:
                return [f"task.protocol phase {p.name!r}: goal node {int(paying[0])} is "
                        "unreachable from every start; add an edge to it"]  # fmt: skip
        return []

    # ------------------------------------------------------------------ phases
    def phase_names(self) -> list[str]:
        return [str(p.get("name", f"phase {i}")) for i, p in enumerate(self.phases)]

    def protocol_config(self) -> dict[str, Any]:
        return {"max_steps": int(self.max_steps), "phases": [dict(p) for p in self.phases]}

    def phase_env(self, phase: int | None) -> Any:
        """The env (without its camera) as it is during ``phase`` (None: as built): the phases
        up to it applied in order with the run's protocol code (changes carry forward)."""
        from cobelrun.protocol import Protocol

        env = self.export_env()
        if phase is None or not self.phases:
            return env
        protocol = Protocol.from_config(self.protocol_config())
        for p in protocol.phases[: phase + 1]:
            protocol.apply(p, env)
            for k in range(len(p.cycle or ())):
                protocol.apply_trial(p, k, env)
        return env

    def phase_state(self, phase: int | None) -> tuple[dict[int, float], set[int], set[int]]:
        """``(rewards, terminals, starts)`` by node during ``phase`` (None: as designed)."""
        if phase is None or not self.phases:
            starts = set(range(len(self.nodes))) if self.starts == "all" else set(self.starts)
            return dict(self.rewards), set(self.terminals), starts
        w = self.phase_env(phase).unwrapped.world
        rewards = {int(i): float(w.rewards[i]) for i in np.flatnonzero(w.rewards)}
        return rewards, {int(i) for i in np.flatnonzero(w.terminal)}, {int(s) for s in w.starts}

    def _paint_phase(self, tool: str, i: int, value: float, k: int) -> None:
        """What phase ``k`` sets at node ``i`` (by place name where it has one)."""
        if not 0 <= k < len(self.phases):
            raise ConfigError(f"phase {k} does not exist; phases: {', '.join(self.phase_names())}")
        phase = self.phases[k]
        ref = self.ref(i)
        rewards = {kk: v for kk, v in (phase.get("rewards") or {}).items()
                   if self._node_or_none(kk) != i}  # fmt: skip
        terminals = {kk: v for kk, v in (phase.get("terminals") or {}).items()
                     if self._node_or_none(kk) != i}  # fmt: skip
        rewards_now, terminals_now, starts_now = self.phase_state(k)
        starts = sorted(starts_now)
        if tool == "start":
            if i in starts:
                starts = [s for s in starts if s != i]
            else:  # a start is neither terminal nor paying
                starts = sorted([*starts, i])
                if rewards_now.get(i):
                    rewards[ref] = 0.0
                if i in terminals_now:
                    terminals[ref] = False
            phase["starts"] = [self.ref(s) for s in starts]
        elif tool in ("goal", "terminal"):
            rewards[ref] = float(value) if tool == "goal" else 0.0
            terminals[ref] = True
            if i in starts:
                phase["starts"] = [self.ref(s) for s in starts if s != i]
        elif tool == "clear":
            rewards[ref], terminals[ref] = 0.0, False
        else:
            raise ConfigError(f"unknown node tool {tool!r}")
        phase["rewards"], phase["terminals"] = rewards, terminals
        for key in ("rewards", "terminals"):
            if not phase[key]:
                del phase[key]

    def _node_or_none(self, ref: Any) -> int | None:
        try:
            return self.node(ref)
        except CobelError:
            return None

    # ------------------------------------------------------------------ editing
    def add_node(self, x: float, y: float) -> int:
        if len(self.nodes) >= MAX_NODES:
            raise LayoutError(f"at most {MAX_NODES} nodes here; edit the YAML for more")
        s = self.spacing or 1.0
        x, y = round(x / s) * s, round(y / s) * s
        for i, (a, b) in enumerate(self.nodes):
            if np.hypot(a - x, b - y) < 0.25 * s:
                return i  # a node there already
        self.nodes.append((float(x), float(y)))
        return len(self.nodes) - 1

    def remove_node(self, i: int) -> None:
        """Remove node ``i``; later nodes move down one index (edges, places, goals follow)."""
        if len(self.nodes) <= 2:
            raise LayoutError("a graph needs at least 2 nodes")
        shift = lambda k: k - 1 if k > i else k  # noqa: E731
        del self.nodes[i]
        self.edges = {(shift(a), shift(b)) for a, b in self.edges if i not in (a, b)}
        self.places = {k: shift(v) for k, v in self.places.items() if v != i}
        self.rewards = {shift(k): v for k, v in self.rewards.items() if k != i}
        self.terminals = {shift(k) for k in self.terminals if k != i}
        if self.starts != "all":
            self.starts = [shift(s) for s in self.starts if s != i]

    def toggle_edge(self, a: int, b: int) -> None:
        if a == b:
            return
        e = (min(a, b), max(a, b))
        if e in self.edges:
            self.edges.discard(e)
        else:
            self.edges.add(e)

    def paint(self, tool: str, i: int, value: float = 1.0, phase: int | None = None) -> None:
        """``start``, ``goal``, ``terminal`` or ``clear`` at node ``i``; with ``phase``, what
        that phase of the protocol sets (not the env)."""
        if phase is not None:
            self._paint_phase(tool, i, value, phase)
            return
        if tool == "start":
            starts = list(range(len(self.nodes))) if self.starts == "all" else list(self.starts)
            starts = [s for s in starts if s != i] if i in starts else [*starts, i]
            self.starts = starts
            self.terminals.discard(i)
            self.rewards.pop(i, None)
        elif tool in ("goal", "terminal"):
            self.terminals.add(i)
            if tool == "goal" and value:
                self.rewards[i] = float(value)
            else:
                self.rewards.pop(i, None)
            if self.starts != "all":
                self.starts = [s for s in self.starts if s != i]
        elif tool == "clear":
            self.terminals.discard(i)
            self.rewards.pop(i, None)
            if self.starts != "all":
                self.starts = [s for s in self.starts if s != i]
        else:
            raise ConfigError(f"unknown node tool {tool!r}")

    # ------------------------------------------------------------------ drawing and views
    def view(self) -> tuple[float, float, float, float]:
        """``(x0, y0, x1, y1)`` of the drawing: the nodes' box plus 1.5 spacings."""
        pts = np.asarray(self.nodes)
        lo, hi = pts.min(axis=0) - 1.5, pts.max(axis=0) + 1.5  # room to add nodes around
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])

    def svg(self, px: float = 48.0, selected: int | None = None,
            phase: int | None = None, problems: list[str] | None = None) -> str:  # fmt: skip
        """Nodes (``circle.cobel-node``, ``data-node``), edges, and a background
        (``rect.cobel-bg``) whose clicks give world coordinates through ``data-*``; goals,
        terminals and starts as they are during ``phase`` (None: as designed). A node that
        one of ``problems`` names (``goal node N``) gets a red ring and the message beside it
        (``text.cobel-problem-at``)."""
        bad = {int(m.group(1)): msg for msg in problems or ()
               for m in [re.search(r"\bgoal node (\d+) ", msg)] if m}  # fmt: skip
        try:
            rewards, terminals, starts = self.phase_state(phase)
        except CobelError:  # a phase the run would refuse: drawn as designed (the message says why)
            rewards, terminals, starts = self.phase_state(None)
        x0, y0, x1, y1 = self.view()
        w, h = (x1 - x0) * px, (y1 - y0) * px
        to = lambda x, y: ((x - x0) * px, (y1 - y) * px)  # noqa: E731  (y up)
        out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{w:.0f}" height="{h:.0f}" '
               f'class="cobel-graph" font-family="sans-serif" data-x0="{x0}" data-y1="{y1}" '
               f'data-px="{px}">',
               f'<rect class="cobel-bg" x="0" y="0" width="{w:.0f}" height="{h:.0f}" '
               'fill="#fafafa" stroke="#ddd"/>']  # fmt: skip
        for a, b in sorted(self.edges):
            (xa, ya), (xb, yb) = to(*self.nodes[a]), to(*self.nodes[b])
            out.append(f'<line class="cobel-graph-edge" x1="{xa:.1f}" y1="{ya:.1f}" x2="{xb:.1f}" '
                       f'y2="{yb:.1f}" stroke="#888" stroke-width="3"/>')  # fmt: skip
        names = {v: k for k, v in self.places.items()}
        r = px * 0.22
        for i, (x, y) in enumerate(self.nodes):
            cx, cy = to(x, y)
            if i in terminals:
                fill = "#fac83c" if rewards.get(i) else "#f0bebe"
            elif rewards.get(i):
                fill = "#c8ebc8"
            elif i in starts:
                fill = "#cfe0ff"
            else:
                fill = "#ffffff"
            stroke = "#d00000" if i == selected or i in bad else "#333"
            out.append(f'<circle class="cobel-node" data-node="{i}" cx="{cx:.1f}" cy="{cy:.1f}" '
                       f'r="{r:.1f}" fill="{fill}" stroke="{stroke}" '
                       f'stroke-width="{4 if i in bad else 2}"/>')  # fmt: skip
            if i in bad:  # the message up to its advice, on the side with more room
                left = cx > w / 2
                tx, anchor = (cx - r - 3, "end") if left else (cx + r + 3, "start")
                out.append(f'<text class="cobel-problem-at" x="{tx:.1f}" y="{cy - r:.1f}" '
                           f'text-anchor="{anchor}" font-size="11" fill="#b00000" '
                           f'pointer-events="none">{html.escape(bad[i].split(";")[0])}</text>')  # fmt: skip
            label = str(i) if not rewards.get(i) else f"{i}:{rewards[i]:g}"
            out.append(f'<text x="{cx:.1f}" y="{cy + 4:.1f}" font-size="{max(8, px / 5):.0f}" '
                       f'text-anchor="middle" pointer-events="none">{label}</text>')  # fmt: skip
            if i in names:
                out.append(f'<text x="{cx:.1f}" y="{cy - r - 3:.1f}" font-size="10" fill="#555" '
                           f'text-anchor="middle" pointer-events="none">'
                           f"{html.escape(names[i])}</text>")  # fmt: skip
        out.append("</svg>")
        return "".join(out)

    def camera(self) -> Any:
        """The env's image observation (through the gate, rendered online), or an 84 x 84,
        90 degree camera where the env observes poses only."""
        from cobelrun.config import instantiate
        from cobelrun.envs.observations import ImageObservation

        node = self.extra.get("observation")
        if isinstance(node, dict) and node.get("_target_", "").endswith("ImageObservation"):
            node = {**node, "render": "online"}  # (its cache_dir kept: preview reads it)
            obs = instantiate("env.observation", node)
        else:
            obs = ImageObservation(height=84, width=84, fov=90.0, render="online")
        return obs

    def preview(self, i: int, heading_deg: float) -> tuple[np.ndarray, str]:
        """The agent's camera image at node ``i`` facing ``heading_deg`` and where it came
        from: the env's render cache (``cobel render-cache``: the same scene, camera and poses,
        so the same key) when it has one for this graph, else rendered with pybullet."""
        from cobelrun.render import cache

        request = self.cache_request()
        try:
            path = cache.locate(request)
            images = cache.load(request)
        except CobelError as exc:
            why = str(exc).split(";")[0]
        else:
            h = int(np.argmin(np.abs(np.angle(np.exp(1j * (np.asarray(request.directions)
                                                           - np.deg2rad(heading_deg)))))))  # fmt: skip
            return np.array(images[i, h]), f"read from the render cache {path}"
        return self.agent_view(i, heading_deg), f"rendered with pybullet ({why})"

    def cache_request(self) -> Any:
        """The render-cache request of the saved env's camera (scene, camera, every node and
        heading, renderer, cache folder): what ``cobel render-cache`` builds for it."""
        from cobelrun.web.grid_design import build_with

        obs = self.camera()
        obs.bind(build_with("env.topology", self.run_topology_node()))
        return obs.cache_request()

    def agent_view(self, i: int, heading_deg: float) -> np.ndarray:
        """The agent's camera image at node ``i`` facing ``heading_deg`` (HxWx3 uint8),
        rendered by the run's pybullet scene for this graph."""
        from cobelrun.web.grid_design import build_with

        topology = build_with("env.topology", self.run_topology_node())
        obs = self.camera()
        obs.bind(topology)
        try:
            x, y = self.nodes[i]
            img = np.asarray(obs.render_raw_at(x, y, np.deg2rad(heading_deg)))
        finally:
            obs.close()
        if img.ndim == 3 and img.shape[0] in (1, 3) and img.shape[-1] not in (1, 3):
            img = np.moveaxis(img, 0, -1)
        if img.dtype != np.uint8:
            img = np.clip(img * (255.0 if img.max() <= 1.0 else 1.0), 0, 255).astype(np.uint8)
        return img


def _reachable(d: GraphDesign, starts: list[int]) -> np.ndarray:
    adj: dict[int, list[int]] = {i: [] for i in range(len(d.nodes))}
    for a, b in d.edges:
        adj[a].append(b)
        adj[b].append(a)
    seen = np.zeros(len(d.nodes), bool)
    stack = list(starts)
    seen[stack] = True
    while stack:
        for n in adj[stack.pop()]:
            if not seen[n]:
                seen[n] = True
                stack.append(n)
    return seen
