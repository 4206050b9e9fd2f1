"""What ``cobel edit`` edits for continuous 2D arenas: outline, obstacles, goal regions and
start points of a :class:`~cobelrun.envs.continuous.Continuous2DEnv` config.

An :class:`ArenaDesign` is the env's config as plain data (the arena's own form: shapes as
mappings); edits change ``arena``, ``obstacles``, ``goals`` and ``starts`` and leave every other
key as it is. It is checked by building the env with the code ``cobel run`` uses (through the
instantiation gate), so the messages are the run's ("goal 'platform' lies (partly) outside the
arena"); the shape a message names is marked. Previews come from the built env itself: the
place-cell centres of its observation, and the rays its boundary-vector cells cast at a pose
(:meth:`BoundaryVectorCells.wall_distances`, the arena's wall segments).
"""

from __future__ import annotations

import copy
import html
import re
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cobelrun.errors import CobelError, ConfigError

__all__ = ["ARENA_TOOLS", "ArenaDesign"]

ENV_TARGETS = ("cobelrun.envs.Continuous2DEnv", "cobelrun.envs.continuous.Continuous2DEnv")
#: tools of the arena page: name -> what a click does
ARENA_TOOLS: dict[str, str] = {
    "start": "add a start point (named start_N)",
    "goal": "add a circular goal region (radius and reward from the boxes)",
    "obstacle": "add a vertex of a new obstacle polygon; 'finish shape' closes it",
    "outline": "add a vertex of a new polygonal outline; 'finish shape' makes it the arena",
    "erase": "remove the start, goal or obstacle under the click",
    "rays": "preview the boundary-vector rays (and nearby place cells) at the click",
}
_NAMED = re.compile(r"(?:goal|start) '([^']+)'|starts\.(\w+)|obstacles\[(\d+)\]")


@dataclass
class ArenaDesign:
    """A Continuous2DEnv config as plain data, edited in place.

    Attributes
    ----------
    node : dict
        The env config (``_target_``, ``arena``, ``obstacles``, ``goals``, ``starts``, ...).
    pending : list of [x, y]
        Vertices of a polygon being drawn (obstacle or outline).
    phases, max_steps : list of dict, int
        The protocol of the task that uses the env (the water maze's acquisition, probe and
        reversal): checked and shown, not edited here.
    """

    node: dict[str, Any]
    pending: list[list[float]] = field(default_factory=list)
    phases: list[dict[str, Any]] = field(default_factory=list)
    max_steps: int = 100

    @classmethod
    def from_env_config(cls, node: dict[str, Any], where: str) -> ArenaDesign:
        if node.get("_target_") not in ENV_TARGETS:
            raise ConfigError(f"{where} is not an arena env config (its _target_ is "
                              f"{node.get('_target_')!r})")  # fmt: skip
        d = cls(copy.deepcopy(node))
        starts = d.node.get("starts")
        if isinstance(starts, list):  # named, so each can be picked and removed
            d.node["starts"] = {f"start_{i}": p for i, p in enumerate(starts)}
        return d

    def copy(self) -> ArenaDesign:
        return copy.deepcopy(self)

    # ------------------------------------------------------------------ building
    def env(self) -> Any:
        """The env, built as ``cobel run`` builds a flat node (:func:`cobelrun.config.factory`:
        the gate, the keys checked against the constructor, then the constructor)."""
        from cobelrun.config import factory

        return factory("env", self.node)()

    def export_env(self) -> Any:
        """The env built for drawing."""
        return self.env()

    def phase_env(self, phase: int | None) -> Any:
        """The env as it is during ``phase`` (None: as built): the protocol's phases up to it
        applied in order with the code a run uses (:class:`cobelrun.protocol.Protocol`)."""
        from cobelrun.protocol import Protocol

        env = self.env()
        if phase is None or not self.phases:
            return env
        protocol = Protocol.from_config({"max_steps": self.max_steps, "phases": self.phases})
        for p in protocol.phases[: phase + 1]:
            protocol.apply(p, env)
            for k in range(len(p.cycle or ())):
                protocol.apply_trial(p, k, env)
        return env

    def problems(self) -> list[tuple[str, str | None]]:
        """``cobel run``'s message and the goal/start/obstacle it names (if any): the env,
        then each phase of the protocol applied in order."""
        from cobelrun.protocol import Protocol

        try:
            env = self.env()
            if self.phases:
                protocol = Protocol.from_config(
                    {"max_steps": self.max_steps, "phases": self.phases}
                )
                for p in protocol.phases:
                    try:
                        protocol.apply(p, env)
                        for k in range(len(p.cycle or ())):
                            protocol.apply_trial(p, k, env)
                    except CobelError as exc:
                        raise ConfigError(f"task.protocol phase {p.name!r}: {exc}") from None
        except CobelError as exc:
            msg = str(exc)
            m = _NAMED.search(msg) or re.search(r"unknown (?:goal|start) '([^']+)'", msg)
            name = None if m is None else (m.group(1) or m.group(2) or f"obstacles[{m.group(3)}]")
            return [(msg, name)]
        return []

    def phase_names(self) -> list[str]:
        return [str(p.get("name", f"phase {i}")) for i, p in enumerate(self.phases)]

    # ------------------------------------------------------------------ editing
    def _fresh(self, prefix: str, taken: Any) -> str:
        i = 0
        while f"{prefix}_{i}" in taken:
            i += 1
        return f"{prefix}_{i}"

    def add_start(self, x: float, y: float) -> str:
        starts = self.node.get("starts")
        if not isinstance(starts, dict):
            starts = {}
        name = self._fresh("start", starts)
        starts[name] = [round(x, 4), round(y, 4)]
        self.node["starts"] = starts
        return name

    def add_goal(self, x: float, y: float, radius: float, reward: float) -> str:
        if not radius > 0:
            raise ConfigError(f"goal radius must be > 0, got {radius}")
        goals = dict(self.node.get("goals") or {})
        name = self._fresh("goal", goals)
        goals[name] = {"shape": "circle", "x": round(x, 4), "y": round(y, 4),
                       "radius": float(radius), "reward": float(reward), "terminal": True}  # fmt: skip
        self.node["goals"] = goals
        return name

    def add_vertex(self, x: float, y: float) -> None:
        self.pending.append([round(x, 4), round(y, 4)])

    def finish(self, what: str) -> None:
        """Close the pending polygon as an obstacle or as the arena's outline."""
        if len(self.pending) < 3:
            raise ConfigError(f"a polygon needs at least 3 vertices; {len(self.pending)} so far")
        shape = {"shape": "polygon", "points": self.pending}
        if what == "outline":
            self.node["arena"] = shape
        else:
            self.node["obstacles"] = [*(self.node.get("obstacles") or []), shape]
        self.pending = []

    def set_outline(self, kind: str, size: float) -> None:
        """A circle of radius ``size`` around the origin or a square of side ``size`` from it."""
        if not size > 0:
            raise ConfigError(f"the outline's size must be > 0, got {size}")
        if kind == "circle":
            self.node["arena"] = {"shape": "circle", "x": 0.0, "y": 0.0, "radius": float(size)}
        elif kind == "square":
            self.node["arena"] = {"shape": "square", "x0": 0.0, "y0": 0.0, "size": float(size)}
        else:
            raise ConfigError(f"outline {kind!r} is unknown; allowed: circle, square (or draw a "
                              "polygon with the outline tool)")  # fmt: skip

    def erase(self, x: float, y: float, tol: float) -> str | None:
        """Remove the start, goal or obstacle at ``(x, y)``; its name, or None."""
        from cobelrun.envs.arena import Shape

        p = np.array([[x, y]])
        starts = self.node.get("starts")
        if isinstance(starts, dict):
            for name, xy in list(starts.items()):
                if np.hypot(*(np.asarray(xy, float) - p[0])) <= tol:
                    del starts[name]
                    return name
        for name, spec in list((self.node.get("goals") or {}).items()):
            try:
                inside = Shape.parse("goal", spec, extra=("reward", "terminal")).contains(p)[0]
            except CobelError:
                continue
            if inside:
                del self.node["goals"][name]
                return name
        for i, spec in enumerate(list(self.node.get("obstacles") or [])):
            try:
                inside = Shape.parse("obstacle", spec).contains(p)[0]
            except CobelError:
                continue
            if inside:
                del self.node["obstacles"][i]
                return f"obstacles[{i}]"
        return None

    # ------------------------------------------------------------------ drawing
    def bounds(self) -> tuple[float, float, float, float]:
        from cobelrun.envs.arena import Shape

        try:
            pts = Shape.parse("arena", self.node.get("arena") or {"shape": "square", "x0": 0,
                                                                   "y0": 0, "size": 1}).polygon()  # fmt: skip
        except CobelError:
            pts = np.array([[0.0, 0.0], [1.0, 1.0]])
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        pad = 0.08 * float(max(hi - lo))
        return float(lo[0] - pad), float(lo[1] - pad), float(hi[0] + pad), float(hi[1] + pad)

    def svg(self, size: int = 520, pose: tuple[float, float] | None = None,
            bad: str | None = None, phase: int | None = None) -> str:  # fmt: skip
        """The arena (outline, obstacles, goals, starts, place-cell centres, the pending
        polygon and, at ``pose``, the boundary-vector rays) as an SVG; ``data-*`` on the root
        let a click be read back in world units."""
        from cobelrun.envs.arena import Shape

        x0, y0, x1, y1 = self.bounds()
        scale = size / max(x1 - x0, y1 - y0)
        w, h = (x1 - x0) * scale, (y1 - y0) * scale
        P = lambda x, y: f"{(x - x0) * scale:.1f},{(y1 - y) * scale:.1f}"  # noqa: E731
        out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{w:.0f}" height="{h:.0f}" '
               f'class="cobel-arena" data-x0="{x0}" data-y1="{y1}" data-scale="{scale}" '
               f'font-family="sans-serif"><rect x="0" y="0" width="{w:.0f}" height="{h:.0f}" '
               'fill="#e8e8e8"/>']  # fmt: skip

        def poly(spec: Any, cls: str, fill: str, stroke: str, extra: tuple[str, ...] = ()) -> None:
            try:
                pts = Shape.parse("shape", spec, extra=extra).polygon()
            except CobelError:
                return
            out.append(f'<polygon class="{cls}" points="{" ".join(P(*p) for p in pts)}" '
                       f'fill="{fill}" stroke="{stroke}" stroke-width="2"/>')  # fmt: skip

        poly(self.node.get("arena") or {"shape": "square", "x0": 0, "y0": 0, "size": 1},
             "cobel-outline", "#ffffff", "#333")  # fmt: skip
        for i, ob in enumerate(self.node.get("obstacles") or []):
            stroke = "#d00000" if bad == f"obstacles[{i}]" else "#333"
            poly(ob, "cobel-obstacle", "#555", stroke)
        try:
            env = self.phase_env(phase).unwrapped
        except CobelError:
            env = None
        for name, g in (self.node.get("goals") or {}).items():
            reward, terminal = float(g.get("reward", 1.0) or 0), g.get("terminal", True)
            if env is not None and name in env.arena.goals:  # as the phase leaves it
                reward, terminal = env.arena.goals[name].reward, env.arena.goals[name].terminal
            fill = "#fac83c" if reward else "#f0bebe" if terminal else "#ffffff"
            poly(g, f"cobel-goal cobel-goal-{html.escape(str(name))}", fill,
                 "#d00000" if bad == name else "#a07000", ("reward", "terminal"))  # fmt: skip
        if env is not None:
            from cobelrun.envs.cells import BoundaryVectorCells, PlaceCells

            for part in env.observation_parts:
                if isinstance(part, PlaceCells) and part.centres is not None:
                    for cx, cy in part.centres:
                        px, py = P(cx, cy).split(",")
                        out.append(f'<circle class="cobel-place-cell" cx="{px}" cy="{py}" r="2" '
                                   'fill="#1f77b4" fill-opacity="0.6"/>')  # fmt: skip
            if pose is not None:
                bvc = next((p for p in env.observation_parts
                            if isinstance(p, BoundaryVectorCells)), None)  # fmt: skip
                if bvc is None:  # the env has none: the default cells' rays
                    bvc = BoundaryVectorCells(n=1, dtheta_deg=10.0)
                    bvc.bind(env.arena)
                r = bvc.wall_distances(np.array([[pose[0], pose[1], 0.0]]))[0]
                step = max(1, len(r) // 36)
                for a, d in list(zip(bvc.test_angles, r, strict=True))[::step]:
                    if np.isfinite(d):
                        ex, ey = pose[0] + d * np.cos(a), pose[1] + d * np.sin(a)
                        out.append(f'<polyline class="cobel-ray" points="{P(*pose)} {P(ex, ey)}" '
                                   'stroke="#2ca02c" stroke-width="1"/>')  # fmt: skip
        starts = self.node.get("starts")
        if isinstance(starts, dict):
            for name, xy in starts.items():
                px, py = P(*map(float, xy)).split(",")
                stroke = "#d00000" if bad == name else "#0b3d91"
                out.append(f'<circle class="cobel-start" data-name="{html.escape(str(name))}" '
                           f'cx="{px}" cy="{py}" r="6" fill="#cfe0ff" stroke="{stroke}" '
                           'stroke-width="2"/>')  # fmt: skip
        if self.pending:
            pts = " ".join(P(*p) for p in self.pending)
            out.append(f'<polyline class="cobel-pending" points="{pts}" fill="none" '
                       'stroke="#d62728" stroke-width="2" stroke-dasharray="4 3"/>')  # fmt: skip
        out.append("</svg>")
        return "".join(out)
