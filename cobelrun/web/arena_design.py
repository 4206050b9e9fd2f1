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

from cobelrun.errors import CobelError, ConfigError, LayoutError

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


#: place cells the arena page draws (and rebuilds on every click); the water maze has 493
MAX_PLACE_CELLS = 5000


def check_place_cells(observation: Any, where: str) -> None:
    """Refuse an arena whose place cells are too many to draw and rebuild on every click (one
    line, saying what to do); what the run itself accepts is the run's check."""
    parts = observation if isinstance(observation, list) else [observation]
    for part in parts:
        if not isinstance(part, dict) or part.get("kind") != "place_cells":
            continue
        centres, n = part.get("centres"), part.get("n", 100)
        count = len(centres) if isinstance(centres, list) else n
        if isinstance(count, int) and not isinstance(count, bool) and count > MAX_PLACE_CELLS:
            raise LayoutError(
                f"{where}: {count} place cells are too many to draw here (at most "
                f"{MAX_PLACE_CELLS}); edit its YAML instead"
            )


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
        reversal): checked, shown, and edited with :meth:`paint_phase` (the goals a phase
        switches on and off, its start points).
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
        check_place_cells(node.get("observation"), where)
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

    # ------------------------------------------------------------------ start heading
    def start_heading(self) -> float | str:
        """The env's ``start_heading``: degrees, ``"random"`` or ``"centre"`` (its default)."""
        h = self.node.get("start_heading", "centre")
        return h if isinstance(h, str) else float(h)

    def set_start_heading(self, value: Any) -> None:
        """``start_heading`` as the env takes it: an angle in degrees (counter-clockwise from
        +x), ``"random"`` or ``"centre"`` (facing the arena's centre)."""
        if isinstance(value, str) and value.strip() in ("random", "centre"):
            self.node["start_heading"] = value.strip()
            return
        try:
            deg = float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"start heading must be an angle in degrees, 'random' or 'centre', "
                              f"got {value!r}") from None  # fmt: skip
        if not np.isfinite(deg):
            raise ConfigError(f"start heading must be a finite angle in degrees, got {value!r}")
        deg = round(deg % 360.0, 4)
        self.node["start_heading"] = int(deg) if deg == int(deg) else deg

    # ------------------------------------------------------------------ phases
    def phase_starts(self, k: int) -> list[Any] | None:
        """The start list in force during phase ``k`` (names or [x, y] points; the last phase
        up to ``k`` that sets ``starts``), or None: the env's own starts."""
        for p in reversed(self.phases[: k + 1]):
            if p.get("starts") is not None:
                return list(p["starts"])
        return None

    def goal_at(self, x: float, y: float) -> str | None:
        """The goal region that holds ``(x, y)`` (the last drawn on top), or None."""
        from cobelrun.envs.arena import Shape

        hit = None
        for name, spec in (self.node.get("goals") or {}).items():
            try:
                if Shape.parse("goal", spec, extra=("reward", "terminal")).contains(
                    np.array([[x, y]])
                )[0]:
                    hit = name
            except CobelError:
                continue
        return hit

    def paint_phase(self, tool: str, x: float, y: float, k: int, *, radius: float = 0.1,
                    reward: float = 1.0, tol: float = 0.03) -> str:  # fmt: skip
        """What phase ``k`` of the protocol sets, edited by a click at ``(x, y)``:

        - ``goal`` on a goal region: switch it on (``reward``, terminal) or, when it pays
          during the phase, off (reward 0, not terminal); on open water: a new circular goal
          region (``radius``), off in the env as built and switched on by this phase. Moving
          the water maze's platform in a reversal is: switch the old one off, click the new
          place.
        - ``start`` near a start point of the env: add it to (or remove it from) the phase's
          starts; elsewhere: add the point ``[x, y]``.
        - ``erase``: a goal region switched off, a start of the phase removed.

        Returns what it changed (for the status line)."""
        if not 0 <= k < len(self.phases):
            raise ConfigError(f"phase {k} does not exist; phases: {', '.join(self.phase_names())}")
        phase = self.phases[k]
        if tool in ("goal", "erase"):
            name = self.goal_at(x, y)
            on = False
            if name is None and tool == "goal":
                name = self.add_goal(x, y, radius, 0.0)  # off as built: the phase switches it on
                self.node["goals"][name]["terminal"] = False
                on = True
            elif name is not None:
                goal = self.phase_env(k).unwrapped.arena.goals[name]
                on = tool == "goal" and not (goal.reward or goal.terminal)
            if name is not None:
                rewards = dict(phase.get("rewards") or {})
                terminals = dict(phase.get("terminals") or {})
                rewards[name], terminals[name] = (float(reward) if on else 0.0), on
                phase["rewards"], phase["terminals"] = rewards, terminals
                return f"phase {phase.get('name')}: goal {name} {'on' if on else 'off'}"
        if tool in ("start", "erase"):
            starts = self.phase_starts(k)
            env_starts = self.node.get("starts")
            if starts is None:
                starts = list(env_starts) if isinstance(env_starts, dict) else []
            near = self._start_near(starts, x, y, tol)
            if near is not None:
                del starts[near]
                phase["starts"] = starts
                return f"phase {phase.get('name')}: start removed"
            if tool == "start":
                named = self._start_near(list(env_starts or {}) if isinstance(env_starts, dict)
                                         else [], x, y, tol)  # fmt: skip
                starts.append(list(env_starts)[named] if named is not None
                              else [round(x, 4), round(y, 4)])  # fmt: skip
                phase["starts"] = starts
                return f"phase {phase.get('name')}: start added"
            return "nothing to erase there"
        raise ConfigError(f"the {tool} tool edits the env, not a phase; pick 'env (as built)' "
                          "to use it")  # fmt: skip

    def _start_near(self, refs: list[Any], x: float, y: float, tol: float) -> int | None:
        """Index of the start in ``refs`` (names or points) within ``tol`` of ``(x, y)``."""
        named = self.node.get("starts") if isinstance(self.node.get("starts"), dict) else {}
        for i, ref in enumerate(refs):
            xy = named.get(ref) if isinstance(ref, str) else ref
            if xy is not None and np.hypot(float(xy[0]) - x, float(xy[1]) - y) <= tol:
                return i
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
               f'font-family="sans-serif"><defs><marker id="cobel-arrow" markerWidth="6" '
               'markerHeight="6" refX="3" refY="3" orient="auto"><path d="M0,0 L6,3 L0,6 z" '
               f'fill="#0b3d91"/></marker></defs><rect x="0" y="0" width="{w:.0f}" '
               f'height="{h:.0f}" fill="#e8e8e8"/>']  # fmt: skip

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
        named = starts if isinstance(starts, dict) else {}
        in_phase = None if phase is None or not self.phases else self.phase_starts(phase)
        points: list[tuple[str, list[float], bool]] = [
            (str(n), list(map(float, xy)), in_phase is None or n in in_phase)
            for n, xy in named.items()
        ]
        for ref in in_phase or []:
            if not isinstance(ref, str):  # a point the phase starts from
                points.append((f"({ref[0]:g}, {ref[1]:g})", [float(ref[0]), float(ref[1])], True))
        heading = self.start_heading()
        arrow = 0.06 * (x1 - x0)
        for name, (sx, sy), active in points:
            px, py = P(sx, sy).split(",")
            stroke = "#d00000" if bad == name else "#0b3d91"
            op = "1" if active else "0.3"
            cls = "cobel-start" + ("" if active else " cobel-start-off")
            if heading == "random":
                out.append(f'<circle class="cobel-heading-random" cx="{px}" cy="{py}" r="11" '
                           f'fill="none" stroke="#0b3d91" stroke-dasharray="3 3" '
                           f'opacity="{op}"/>')  # fmt: skip
            else:
                if heading == "centre":
                    c = env.arena.outline.centre if env is not None else np.zeros(2)
                    a = float(np.arctan2(c[1] - sy, c[0] - sx))
                else:
                    a = float(np.deg2rad(heading))
                ex, ey = sx + arrow * np.cos(a), sy + arrow * np.sin(a)
                out.append(f'<polyline class="cobel-heading" data-deg="{np.rad2deg(a) % 360:.1f}" '
                           f'points="{P(sx, sy)} {P(ex, ey)}" stroke="#0b3d91" stroke-width="3" '
                           f'marker-end="url(#cobel-arrow)" opacity="{op}"/>')  # fmt: skip
            out.append(f'<circle class="{cls}" data-name="{html.escape(name)}" '
                       f'cx="{px}" cy="{py}" r="6" fill="#cfe0ff" stroke="{stroke}" '
                       f'stroke-width="2" opacity="{op}"/>')  # fmt: skip
        if self.pending:
            pts = " ".join(P(*p) for p in self.pending)
            out.append(f'<polyline class="cobel-pending" points="{pts}" fill="none" '
                       'stroke="#d62728" stroke-width="2" stroke-dasharray="4 3"/>')  # fmt: skip
        out.append("</svg>")
        return "".join(out)
