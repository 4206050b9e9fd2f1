"""What ``cobel edit`` edits, as plain data: a gridworld design and its protocol phases.

A :class:`GridDesign` holds what a user paints (wall cells, two-way walls and one-way doors
between cells, start cells with whole-number weights, rewarded and terminal cells, named
places) and turns it into the keyword arguments of :func:`cobelrun.envs.world.from_layout`,
the builder ``cobel run`` calls for ``env.world``. Validation (:meth:`GridDesign.problems`)
builds the world with that same function and applies the protocol's phases with the same
:class:`cobelrun.protocol.Protocol` code a run uses, so the editor shows exactly the one-line
messages ``cobel run`` would print, placed at the cell they name.

Start weights: the env draws a start uniformly from ``world.starts`` (compiled agent kernels
replay that draw), so a cell of weight ``k`` is listed ``k`` times in ``starts``; its
probability is ``k / sum(weights)``.

Cells are ``(row, col)`` with row 0 at the top, ``state = row * width + col``, as in
:mod:`cobelrun.envs.world`.
"""

from __future__ import annotations

import copy
import html
import re
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cobelrun.envs.world import ACTIONS, World, from_layout
from cobelrun.errors import CobelError, ConfigError, LayoutError

__all__ = [
    "MAX_SIDE",
    "TOOLS",
    "GridDesign",
    "Problem",
    "same_world",
]

Cell = tuple[int, int]

#: the largest grid side the editor draws (a bigger layout is edited as YAML): each check
#: builds the dense (S, 4, S) transition table, 34 MB at 32 x 32
MAX_SIDE = 32
#: the most whole-number weight a start cell may have
MAX_WEIGHT = 20
#: painting tools: name -> what a click does
TOOLS: dict[str, str] = {
    "wall": "toggle a wall cell",
    "start": "add a start cell (click again: weight + 1; the weight box sets it)",
    "goal": "terminal cell paying the reward in the box",
    "reward": "non-terminal cell paying the reward in the box",
    "terminal": "terminal cell without reward",
    "door": "one-way door: click near a cell's side; the move out through it is blocked",
    "edge": "two-way wall on the side of a cell nearest the click",
    "erase": "clear the cell (free, no start, reward or terminal)",
    "place": "name the cell with the text in the 'place name' box (empty: drop its names)",
}
#: the edge of a cell nearest a click: (d_row, d_col)
_SIDES = {"left": (0, -1), "up": (-1, 0), "right": (0, 1), "down": (1, 0)}
#: world-builder keys the design owns; any other key of ``env.world`` passes through
OWNED_KEYS = ("layout", "walls", "one_way", "rewards", "terminals", "starts", "places",
              "goal_reward")  # fmt: skip
#: keys of ``env.world`` kept from a from_layout config and passed to the builder unchanged
PASS_KEYS = ("slip", "reward_sd", "warps")

_CELL_RE = re.compile(r"row (\d+), col (\d+)")
_PLACE_RE = re.compile(r"[A-Za-z][A-Za-z0-9_]{0,63}")
_STATE_RE = re.compile(r"\bstates? (\d+)\b")


@dataclass
class Problem:
    """One validation message, at a cell where it names one.

    Attributes
    ----------
    message : str
        The one-line message ``cobel run`` gives.
    cell : (row, col) or None
        The cell it is about (None: the whole design).
    phase : str or None
        The protocol phase it comes from (None: the env itself).
    """

    message: str
    cell: Cell | None = None
    phase: str | None = None


@dataclass
class GridDesign:
    """A gridworld as the editor holds it.

    Attributes
    ----------
    width, height : int
        Grid size in cells.
    walls : set of (row, col)
        Wall cells.
    edges : set of ((row, col), (row, col))
        Two-way walls between adjacent cells (each pair sorted).
    doors : set of ((row, col), (row, col))
        One-way doors: the move from the first cell to the second is blocked.
    starts : list of (row, col)
        Start cells in the order the env draws from; a cell listed k times has weight k.
    rewards : dict (row, col) -> float
        Arrival rewards (non-zero).
    terminals : set of (row, col)
        Terminal cells.
    places : dict name -> (row, col)
        Named cells (``right_arm``); protocols and monitors refer to them.
    goal_reward : float
        The reward a ``G`` cell of the layout pays (cells paying it are written as ``G``).
    extra : dict
        Other builder keys kept from the loaded config (``slip``, ``reward_sd``, ``warps``).
    phases : list of dict
        The protocol's phases (plain data, unknown keys kept); their ``rewards``,
        ``terminals`` and ``starts`` use place names or state indices.
    max_steps : int
        The protocol's per-trial step limit.
    env_target, env_extra : str, dict
        The env's ``_target_`` and its other keys (``observations``, ``max_steps``, ...): the
        check builds the env with them, as a run does.
    """

    width: int
    height: int
    walls: set[Cell] = field(default_factory=set)
    edges: set[tuple[Cell, Cell]] = field(default_factory=set)
    doors: set[tuple[Cell, Cell]] = field(default_factory=set)
    starts: list[Cell] = field(default_factory=list)
    rewards: dict[Cell, float] = field(default_factory=dict)
    terminals: set[Cell] = field(default_factory=set)
    places: dict[str, Cell] = field(default_factory=dict)
    goal_reward: float = 1.0
    extra: dict[str, Any] = field(default_factory=dict)
    phases: list[dict[str, Any]] = field(default_factory=list)
    max_steps: int = 100
    env_target: str = "cobelrun.envs.GridWorldEnv"
    env_extra: dict[str, Any] = field(default_factory=dict)

    # ------------------------------------------------------------------ construction
    @classmethod
    def blank(cls, width: int, height: int) -> GridDesign:
        """An open field of ``width x height`` cells with the top-left cell as start."""
        check_size(width, height)
        return cls(width=int(width), height=int(height), starts=[(0, 0)])

    @classmethod
    def from_world(cls, world: World, extra: dict[str, Any] | None = None) -> GridDesign:
        """The design of a built world: wall cells, and a two-way wall or one-way door
        wherever the intended move between two free neighbours stays in place (warps, kept
        in ``extra``, are moves that land elsewhere, not blocks)."""
        w, h = world.width, world.height
        check_size(w, h)
        cell = lambda s: (int(s) // w, int(s) % w)  # noqa: E731
        blocked = world.blocked
        intended = np.argmax(world.T, axis=2)  # (S, A): each move's main outcome
        edges: set[tuple[Cell, Cell]] = set()
        doors: set[tuple[Cell, Cell]] = set()
        for s in range(world.n_states):
            if blocked[s]:
                continue
            r, c = divmod(s, w)
            for a, (_, dr, dc) in enumerate(ACTIONS):
                rr, cc = r + dr, c + dc
                if not (0 <= rr < h and 0 <= cc < w) or blocked[rr * w + cc]:
                    continue
                nxt = rr * w + cc
                if intended[s, a] != s:
                    continue
                back = intended[nxt, (a + 2) % 4] == nxt  # ACTIONS: left, up, right, down
                if back:
                    edges.add(tuple(sorted(((r, c), (rr, cc)))))  # type: ignore[arg-type]
                else:
                    doors.add(((r, c), (rr, cc)))
        return cls(
            width=w,
            height=h,
            walls={cell(s) for s in np.flatnonzero(blocked)},
            edges=edges,
            doors=doors,
            starts=[cell(s) for s in world.starts],
            rewards={cell(s): float(world.rewards[s]) for s in np.flatnonzero(world.rewards)},
            terminals={cell(s) for s in np.flatnonzero(world.terminal)},
            places={k: cell(v) for k, v in world.places.items()},
            extra=dict(extra or {}),
        )

    def copy(self) -> GridDesign:
        """A deep copy (the editor keeps one per undo step and one as loaded)."""
        return copy.deepcopy(self)

    # ------------------------------------------------------------------ references
    def state(self, cell: Cell) -> int:
        """The state index of ``cell``."""
        return cell[0] * self.width + cell[1]

    def ref(self, cell: Cell) -> str | int:
        """How configs refer to ``cell``: its place name where it has one, else its index."""
        for name, at in self.places.items():
            if at == cell:
                return name
        return self.state(cell)

    def cell_of(self, ref: Any) -> Cell:
        """The cell of a state reference (index, place name or ``[row, col]``)."""
        s = self._probe_world().state(ref)
        return divmod(s, self.width)

    def _probe_world(self) -> World:
        """A world with this design's size and places only, to resolve references."""
        n = self.width * self.height
        T = np.zeros((n, 4, n))
        T[np.arange(n), :, np.arange(n)] = 1.0
        return World(width=self.width, height=self.height, T=T, rewards=np.zeros(n),
                     terminal=np.zeros(n, bool), starts=[0], coords=np.zeros((n, 2)),
                     blocked=np.zeros(n, bool),
                     places={k: self.state(v) for k, v in self.places.items()})  # fmt: skip

    # ------------------------------------------------------------------ to the builder
    def world_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of :func:`cobelrun.envs.world.from_layout` for this design (plain
        data, as they are written into ``env.world``)."""
        g = float(self.goal_reward)
        unique_starts = sorted(set(self.starts))
        # row-major, each once, on plain cells: 'S' cells say it all (else a starts list, so a
        # start on a wall or terminal cell reaches the builder and its message)
        s_chars = self.starts == unique_starts and not (
            set(self.starts) & (self.walls | self.terminals)
        )
        rows = []
        for r in range(self.height):
            row = []
            for c in range(self.width):
                cell = (r, c)
                rew = self.rewards.get(cell, 0.0)
                if cell in self.walls:
                    ch = "#"
                elif cell in self.terminals:
                    ch = "G" if rew == g and rew != 0 else "E"
                elif s_chars and cell in self.starts:
                    ch = "S"
                else:
                    ch = "."
                row.append(ch)
            rows.append("".join(row))
        out: dict[str, Any] = {"layout": "\n".join(rows) + "\n"}
        if self.edges:
            out["walls"] = [[self.state(a), self.state(b)] for a, b in sorted(self.edges)]
        if self.doors:
            out["one_way"] = [[self.state(a), self.state(b)] for a, b in sorted(self.doors)]
        rewards = {self.state(cell): float(v) for cell, v in sorted(self.rewards.items())
                   if v != 0 and not (cell in self.terminals and v == g)}  # fmt: skip
        if rewards:
            out["rewards"] = rewards
        if not s_chars:
            out["starts"] = [list(s) for s in self.starts]
        if self.places:
            out["places"] = {k: list(v) for k, v in self.places.items()}
        out["goal_reward"] = g
        for k, v in self.extra.items():
            out[k] = v
        return out

    def world(self) -> World:
        """Build the world with the builder ``cobel run`` uses (raises its one-line errors)."""
        return from_layout(**self.world_kwargs())

    # ------------------------------------------------------------------ phases
    def phase_names(self) -> list[str]:
        return [str(p.get("name", f"phase {i}")) for i, p in enumerate(self.phases)]

    def protocol_config(self) -> dict[str, Any]:
        """``task.protocol`` as plain data."""
        return {"max_steps": int(self.max_steps), "phases": [dict(p) for p in self.phases]}

    def phase_world(self, phase: int | None) -> World:
        """The world during ``phase`` (None: as built): the phases up to it applied in order,
        as a run applies them (changes persist into later phases)."""
        from cobelrun.envs.gridworld import GridWorldEnv
        from cobelrun.protocol import Protocol

        world = self.world()
        if phase is None or not self.phases:
            return world
        env = GridWorldEnv(world)
        protocol = Protocol.from_config(self.protocol_config())
        for p in protocol.phases[: phase + 1]:
            protocol.apply(p, env)
        return env.world

    # ------------------------------------------------------------------ validation
    def problems(self) -> list[Problem]:
        """Every message ``cobel run`` would give for this design: the world's builder, then
        the protocol's check (each phase's changes applied in order). Empty: it runs."""
        from cobelrun.envs.gridworld import GridWorldEnv
        from cobelrun.protocol import Protocol

        try:
            world = self.world()
            self._build_env(world)
        except CobelError as exc:
            return [Problem(str(exc), self._locate(str(exc)))]
        out: list[Problem] = []
        if not self.phases:
            return out
        try:
            protocol = Protocol.from_config(self.protocol_config())
        except CobelError as exc:
            return [Problem(str(exc))]
        env = GridWorldEnv(world)
        for phase in protocol.phases:  # as Protocol.check, one phase at a time to name it
            try:
                protocol.apply(phase, env)
                for k in range(len(phase.cycle or ())):
                    protocol.apply_trial(phase, k, env)
            except CobelError as exc:
                msg = f"task.protocol phase {phase.name!r}: {exc}"
                out.append(Problem(msg, self._locate(str(exc)), phase.name))
                break
            except (ValueError, KeyError, TypeError) as exc:
                out.append(Problem(f"task.protocol phase {phase.name!r}: {exc}", None, phase.name))
                break
        return out

    def _build_env(self, world: World) -> Any:
        """The env around ``world`` with the config's other keys, as a run builds it."""
        return build_with("env", {"_target_": self.env_target, **self.env_extra}, world=world)

    def _locate(self, message: str) -> Cell | None:
        """The cell a builder message names ("state 5 (row 1, col 2)", "states 3 and 4")."""
        m = _CELL_RE.search(message)
        if m:
            cell = (int(m.group(1)), int(m.group(2)))
        else:
            m = _STATE_RE.search(message)
            if not m:
                return None
            cell = divmod(int(m.group(1)), self.width)
        if 0 <= cell[0] < self.height and 0 <= cell[1] < self.width:
            return cell
        return None

    # ------------------------------------------------------------------ editing
    def resize(self, width: int, height: int) -> None:
        """Change the size; what falls outside is dropped, new cells are free."""
        check_size(width, height)
        inside = lambda c: 0 <= c[0] < height and 0 <= c[1] < width  # noqa: E731
        self.width, self.height = int(width), int(height)
        self.walls = {c for c in self.walls if inside(c)}
        self.edges = {e for e in self.edges if inside(e[0]) and inside(e[1])}
        self.doors = {e for e in self.doors if inside(e[0]) and inside(e[1])}
        self.starts = [c for c in self.starts if inside(c)]
        self.rewards = {c: v for c, v in self.rewards.items() if inside(c)}
        self.terminals = {c for c in self.terminals if inside(c)}
        self.places = {k: c for k, c in self.places.items() if inside(c)}

    def weight(self, cell: Cell) -> int:
        """The start weight of ``cell`` (0: not a start)."""
        return self.starts.count(cell)

    def start_probabilities(self) -> dict[Cell, float]:
        """Each start cell's probability of being drawn at reset."""
        counts = Counter(self.starts)
        n = len(self.starts)
        return {c: k / n for c, k in counts.items()} if n else {}

    def paint(self, tool: str, cell: Cell, *, value: float = 1.0, weight: int = 1,
              side: str | None = None, phase: int | None = None, name: str = "") -> None:  # fmt: skip
        """Apply ``tool`` (one of :data:`TOOLS`) at ``cell``.

        ``value`` is the reward of ``goal``/``reward``, ``weight`` the start weight, ``side``
        (left/up/right/down) the side of ``door``/``edge``, ``name`` the place name of
        ``place`` (protocols and monitors refer to cells by it). With ``phase`` set, ``start``,
        ``goal``, ``reward``, ``terminal`` and ``erase`` change that phase's entries instead of
        the env (what the protocol changes when the phase starts).
        """
        if tool not in TOOLS:
            raise ConfigError(f"unknown tool {tool!r}; tools: {', '.join(TOOLS)}")
        r, c = cell
        if not (0 <= r < self.height and 0 <= c < self.width):
            raise ConfigError(f"cell (row {r}, col {c}) is outside the {self.height} x "
                              f"{self.width} grid")  # fmt: skip
        if phase is not None and tool in ("start", "goal", "reward", "terminal", "erase"):
            self._paint_phase(tool, cell, value, weight, phase)
            return
        if tool == "place":
            self._name(cell, name.strip())
        elif tool == "wall":
            if cell in self.walls:
                self.walls.discard(cell)
            else:
                self._clear(cell)
                self.walls.add(cell)
        elif tool == "erase":
            self._clear(cell)
        elif tool == "start":
            weight = _check_weight(weight)
            self.walls.discard(cell)
            self.terminals.discard(cell)
            have = self.weight(cell)
            if have == weight:  # the same weight again: remove the start
                self.starts = [s for s in self.starts if s != cell]
            elif have < weight:
                self.starts += [cell] * (weight - have)
            else:
                for _ in range(have - weight):
                    i = len(self.starts) - 1 - self.starts[::-1].index(cell)
                    del self.starts[i]
        elif tool in ("goal", "reward", "terminal"):
            self.walls.discard(cell)
            self.starts = [s for s in self.starts if s != cell]
            v = 0.0 if tool == "terminal" else float(value)
            if not np.isfinite(v):
                raise ConfigError(f"reward must be a finite number, got {value!r}")
            if v:
                self.rewards[cell] = v
            else:
                self.rewards.pop(cell, None)
            if tool == "reward":
                self.terminals.discard(cell)
            else:
                self.terminals.add(cell)
        elif tool in ("door", "edge"):
            if side not in _SIDES:
                raise ConfigError(f"{tool}: side must be one of {', '.join(_SIDES)}, got {side!r}")
            dr, dc = _SIDES[side]
            other = (r + dr, c + dc)
            if not (0 <= other[0] < self.height and 0 <= other[1] < self.width):
                return  # the grid's border is a wall already
            pair = tuple(sorted((cell, other)))
            if tool == "edge":
                self.doors.discard((cell, other))
                self.doors.discard((other, cell))
                if pair in self.edges:
                    self.edges.discard(pair)  # type: ignore[arg-type]
                else:
                    self.edges.add(pair)  # type: ignore[arg-type]
            else:
                self.edges.discard(pair)  # type: ignore[arg-type]
                if (cell, other) in self.doors:
                    self.doors.discard((cell, other))
                else:
                    self.doors.discard((other, cell))
                    self.doors.add((cell, other))

    def _name(self, cell: Cell, name: str) -> None:
        if not name:
            self.places = {k: v for k, v in self.places.items() if v != cell}
            return
        if not _PLACE_RE.fullmatch(name):
            raise ConfigError(f"place name {name!r} is not valid; use a letter then letters, "
                              "digits or '_' (like left_arm)")  # fmt: skip
        self.places[name] = cell  # a name names one cell: given again, it moves

    def _clear(self, cell: Cell) -> None:
        self.walls.discard(cell)
        self.starts = [s for s in self.starts if s != cell]
        self.rewards.pop(cell, None)
        self.terminals.discard(cell)

    def _paint_phase(self, tool: str, cell: Cell, value: float, weight: int, i: int) -> None:
        if not 0 <= i < len(self.phases):
            raise ConfigError(f"phase {i} does not exist; phases: {', '.join(self.phase_names())}")
        phase = self.phases[i]
        ref = self.ref(cell)
        rewards = dict(phase.get("rewards") or {})
        terminals = dict(phase.get("terminals") or {})
        for d in (rewards, terminals):  # one entry per cell, under its current reference
            for k in [k for k in d if k != ref and self._same_cell(k, cell)]:
                d[ref] = d.pop(k)
        if tool == "start":
            _check_weight(weight)
            now = self.phase_world(i)
            starts = [divmod(int(s), self.width) for s in now.starts]
            if cell in starts:
                starts = [s for s in starts if s != cell]
            else:
                starts += [cell] * int(weight)
            phase["starts"] = [self.ref(s) for s in starts]
        elif tool in ("goal", "reward"):
            rewards[ref] = float(value)
            terminals[ref] = tool == "goal"
        elif tool == "terminal":
            rewards[ref] = 0.0
            terminals[ref] = True
        elif tool == "erase":
            rewards[ref] = 0.0
            terminals[ref] = False
        phase["rewards"], phase["terminals"] = rewards, terminals
        for key in ("rewards", "terminals"):
            if not phase[key]:
                del phase[key]

    def _same_cell(self, ref: Any, cell: Cell) -> bool:
        try:
            return self.cell_of(ref) == cell
        except CobelError:
            return False

    # ------------------------------------------------------------------ drawing
    def svg(self, *, phase: int | None = None, px: int = 32,
            problems: list[Problem] | None = None) -> str:  # fmt: skip
        """The design as an SVG (one ``rect.cobel-cell`` per cell with ``data-r``/``data-c``;
        doors as orange bars on the blocked side, two-way walls as black bars), drawn as the
        world is during ``phase``. Used by the page and by "export SVG"."""
        try:
            world = self.phase_world(phase)
            rewards = {divmod(int(s), self.width): float(world.rewards[s])
                       for s in np.flatnonzero(world.rewards)}  # fmt: skip
            terminals = {divmod(int(s), self.width) for s in np.flatnonzero(world.terminal)}
            starts = Counter(divmod(int(s), self.width) for s in world.starts)
        except CobelError:  # an invalid design: draw what is painted
            rewards, terminals, starts = self.rewards, self.terminals, Counter(self.starts)
        n_starts = sum(starts.values()) or 1
        bad = {p.cell for p in problems or () if p.cell is not None}
        w, h = self.width * px, self.height * px
        out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{w + 2}" height="{h + 2}" '
               f'viewBox="-1 -1 {w + 2} {h + 2}" class="cobel-grid" font-family="sans-serif">']  # fmt: skip
        font = max(8, px // 3)
        for r in range(self.height):
            for c in range(self.width):
                cell = (r, c)
                x, y = c * px, r * px
                rew = rewards.get(cell, 0.0)
                if cell in self.walls:
                    fill = "#282828"
                elif cell in terminals:
                    fill = "#fac83c" if rew else "#f0bebe"
                elif rew:
                    fill = "#c8ebc8"
                elif cell in starts:
                    fill = "#cfe0ff"
                else:
                    fill = "#f2f2f2"
                stroke = (
                    ' stroke="#d00000" stroke-width="3"' if cell in bad else ' stroke="#c8c8c8"'
                )
                kind = "wall" if cell in self.walls else "free"
                out.append(f'<rect class="cobel-cell cobel-{kind}" data-r="{r}" data-c="{c}" '
                           f'x="{x}" y="{y}" width="{px}" height="{px}" fill="{fill}"{stroke}/>')  # fmt: skip
                label = ""
                if cell in starts:
                    k = starts[cell]
                    label = "S" if len(starts) == 1 else f"S{k / n_starts:.2f}".replace("0.", ".")
                if rew:
                    label = (label + " " if label else "") + f"{rew:g}"
                elif cell in terminals and not label:
                    label = "E"
                if label:
                    out.append(f'<text x="{x + px / 2}" y="{y + px / 2 + font / 3}" font-size="{font}" '
                               f'text-anchor="middle" pointer-events="none">{html.escape(label)}</text>')  # fmt: skip
        for a, b in sorted(self.edges):
            out.append(_bar(a, b, px, "#000000", 0.5))
        for a, b in sorted(self.doors):  # drawn on the blocked cell's side of the edge
            out.append(_bar(a, b, px, "#ff7f0e", 0.35, cls="cobel-door"))
        for name, (r, c) in self.places.items():
            out.append(f'<text x="{c * px + 2}" y="{r * px + font}" font-size="{max(7, font - 3)}" '
                       f'fill="#555" pointer-events="none">{html.escape(name)}</text>')  # fmt: skip
        out.append("</svg>")
        return "".join(out)

    def figure(self, fmt: str, *, phase: int | None = None) -> bytes:
        """The world drawn as ``cobel show`` draws it (matplotlib), as PNG or SVG bytes."""
        from cobelrun.envs.gridworld import GridWorldEnv

        return geometry_figure(GridWorldEnv(self.phase_world(phase)), fmt)


def geometry_figure(env: Any, fmt: str) -> bytes:
    """An env's geometry drawn as ``cobel show`` draws it (walls, doors, nodes, regions; axes
    in the env's units), as PNG or SVG bytes: the editors' "export"."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cobelrun.figures.runs import draw_geometry

    if fmt not in ("png", "svg"):
        raise ConfigError(f"export format {fmt!r} is unknown; allowed: png, svg")
    geometry = env.unwrapped.geometry()
    x0, y0, x1, y1 = geometry.bounds
    aspect = (y1 - y0) / max(x1 - x0, 1e-9)
    side = 6.0
    fig, ax = plt.subplots(figsize=(side, side * aspect + 0.4))
    try:
        draw_geometry(geometry, ax, labels=len(geometry.regions) <= 20)
        _draw_payoffs(env, ax)
        unit = "cells" if geometry.kind == "grid" else "m" if geometry.kind != "graph" else "units"
        ax.set_xlabel(f"x [{unit}]")
        ax.set_ylabel(f"y [{unit}]")
        buf = io.BytesIO()
        fig.savefig(buf, format=fmt, bbox_inches="tight", dpi=150)
    finally:
        plt.close(fig)
    return buf.getvalue()


def _draw_payoffs(env: Any, ax: Any) -> None:
    """Mark what the world pays, ends and starts at (a gridworld's cells, a graph's nodes) as
    the env is now, so an export of a phase shows that phase's goals: goals gold (their reward
    beside them), other rewards green, terminals without a reward pink, starts blue; a legend
    names them. An arena's goal regions that pay now get a gold rim and their reward."""
    arena = getattr(env.unwrapped, "arena", None)
    if arena is not None and hasattr(arena, "goals"):
        from matplotlib.patches import Circle, Polygon

        paying = [g for g in arena.goals.values() if g.reward > 0]
        for k, g in enumerate(paying):
            sh = g.shape
            patch = (Circle((sh.x, sh.y), sh.radius) if sh.kind == "circle"
                     else Polygon(sh.points, closed=True))  # fmt: skip
            patch.set(fill=False, ec="#d4a000", lw=2.5, zorder=3.5,
                      label="goal (pays now)" if k == 0 else None)  # fmt: skip
            ax.add_patch(patch)
            centre = (sh.x, sh.y) if sh.kind == "circle" else np.mean(sh.points, axis=0)
            ax.annotate(f"{g.reward:g}", centre, xytext=(0, -14), textcoords="offset points",
                        ha="center", va="top", fontsize=7)  # fmt: skip
        if paying:
            ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, frameon=False)
        return
    world = getattr(env.unwrapped, "world", None)
    if world is None or getattr(world, "coords", None) is None:
        return
    xy = np.asarray(world.coords, float)
    rewards = np.asarray(world.rewards, float)
    terminal = np.asarray(world.terminal, bool)
    starts = np.unique(np.asarray(world.starts, int))
    kinds = [("goal", (rewards > 0), "#fac83c"), ("reward", (rewards < 0), "#9ad29a"),
             ("terminal", terminal & (rewards == 0), "#f0bebe")]  # fmt: skip
    for label, mask, colour in kinds:
        at = np.unique(xy[mask], axis=0, return_index=True)[1] if mask.any() else []
        states = np.flatnonzero(mask)[np.sort(np.asarray(at, int))] if len(at) else []
        if not len(states):
            continue
        ax.scatter(xy[states, 0], xy[states, 1], s=140, color=colour, edgecolors="0.3",
                   zorder=3.5, label=label)  # fmt: skip
        if label != "terminal":
            for s in states:
                ax.annotate(f"{rewards[s]:g}", xy[s], ha="center", va="center", fontsize=7,
                            zorder=3.6)  # fmt: skip
    if len(starts):
        at = np.unique(xy[starts], axis=0)
        ax.scatter(at[:, 0], at[:, 1], s=30, marker="^", color="tab:blue", zorder=3.7,
                   label="start")  # fmt: skip
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, frameon=False)


def build_with(where: str, node: dict[str, Any], **objects: Any) -> Any:
    """Build a ``_target_`` node whose values are plain data, with ``objects`` (built parts,
    such as ``world``) passed as keyword arguments: the target through cobel's gate and checked
    against its signature (:func:`cobelrun.config.validate_node`), then called. Hydra's
    ``instantiate`` would turn the objects into configs, and takes ~1 s over a graph's lists.
    A node with nested ``_target_`` values is left to the run (None is returned)."""
    from hydra.utils import get_object

    from cobelrun.config import validate_node

    validate_node(where, node, provided=list(objects))  # the gate, the keys and their types
    values = {k: v for k, v in node.items() if k != "_target_"}
    if any(isinstance(v, dict) and "_target_" in v for v in values.values()):
        return None
    try:
        return get_object(str(node["_target_"]))(**copy.deepcopy(values), **objects)
    except CobelError:
        raise
    except Exception as exc:  # as instantiate reports a constructor's error
        lines = str(exc).strip().splitlines()
        raise ConfigError(f"cannot build {where}: {lines[-1] if lines else exc}") from None


def _bar(a: Cell, b: Cell, px: int, colour: str, frac: float, cls: str = "cobel-edge") -> str:
    """A bar on the edge between adjacent cells ``a`` and ``b``, shifted into ``a`` by
    ``(0.5 - frac) * 0.2 px`` for doors so the blocked side shows."""
    (ra, ca), (rb, cb) = a, b
    width = max(3, px // 8)
    if ra == rb:  # a vertical edge
        x = max(ca, cb) * px
        shift = (-1 if cb > ca else 1) * (width if cls == "cobel-door" else 0)
        return (f'<line class="{cls}" x1="{x + shift}" y1="{ra * px + 2}" x2="{x + shift}" '
                f'y2="{(ra + 1) * px - 2}" stroke="{colour}" stroke-width="{width}"/>')  # fmt: skip
    y = max(ra, rb) * px
    shift = (-1 if rb > ra else 1) * (width if cls == "cobel-door" else 0)
    return (f'<line class="{cls}" x1="{ca * px + 2}" y1="{y + shift}" x2="{(ca + 1) * px - 2}" '
            f'y2="{y + shift}" stroke="{colour}" stroke-width="{width}"/>')  # fmt: skip


def _check_weight(weight: Any) -> int:
    if (
        isinstance(weight, bool)
        or not isinstance(weight, int | np.integer)
        or not (1 <= int(weight) <= MAX_WEIGHT)
    ):
        raise ConfigError(f"start weight must be a whole number 1..{MAX_WEIGHT}, got {weight!r}")
    return int(weight)


def check_size(width: Any, height: Any) -> None:
    """Refuse a grid the editor cannot draw comfortably (one line, saying what to do)."""
    for what, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, int | np.integer) or int(v) < 1:
            raise ConfigError(f"grid {what} must be a whole number >= 1, got {v!r}")
    if int(width) * int(height) < 2:
        raise LayoutError("a gridworld needs at least 2 cells")
    if int(width) > MAX_SIDE or int(height) > MAX_SIDE:
        raise LayoutError(
            f"a {width} x {height} grid is too large to edit comfortably here (at most "
            f"{MAX_SIDE} x {MAX_SIDE}); edit its YAML layout instead"
        )


def same_world(a: World, b: World) -> bool:
    """Whether two worlds are the same: size, transitions, rewards, terminals, starts (in
    order), wall cells, places and reward noise."""
    return (
        (a.width, a.height) == (b.width, b.height)
        and np.array_equal(a.T, b.T)
        and np.array_equal(a.rewards, b.rewards)
        and np.array_equal(a.terminal, b.terminal)
        and np.array_equal(a.starts, b.starts)
        and np.array_equal(a.blocked, b.blocked)
        and a.places == b.places
        and a.reward_sd == b.reward_sd
    )
