"""Topology graphs: nodes in the plane, directed edges binned by direction, and pose actions.

The spatial representation module of the paper (section 2.2.2): the agent lives on the nodes of a
graph and faces one of ``D`` headings. A :class:`Topology` stores node positions, the neighbour
of every node in each of the ``D`` direction bins, and named places; :class:`ActionMap` turns
an action into the next pose (node, heading) for the action modes

``"none"``
    No rotation: ``D`` actions "move to the neighbour in direction d"; the heading becomes d.
``"turn"``
    Rotation, Fig. 6A: ``D`` moves relative to the heading (forward, left, back, right for a
    grid) that keep the heading, plus 2 turns by one direction step (left / right, 90 degrees
    on a grid). A grid gives the paper's 6 actions.
``"face"``
    Rotation, Fig. 8: ``D`` moves to the neighbour in direction d (heading kept) plus ``D``
    turns "face direction d". A hexagonal graph gives the paper's 12 actions.

A move without a neighbour in that direction leaves the pose unchanged.

Headings are indices into :attr:`Topology.directions` (radians, counter-clockwise from +x);
``x`` grows to the right and ``y`` upwards, as :attr:`cobelrun.envs.world.World.coords`.

Builders (:func:`grid`, :func:`hexagonal`, :func:`delaunay`, :func:`manual`, :func:`from_world`,
:func:`from_layout`) take plain keyword arguments so Hydra configs can point ``_target_`` at them.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cobelrun.envs import world as _world
from cobelrun.errors import ConfigError, LayoutError, allowed_list, suggest

#: Action modes (see the module docstring).
ACTION_MODES: tuple[str, ...] = ("none", "turn", "face")


@dataclass(eq=False)
class Topology:
    """A graph of places with direction-binned neighbours.

    Attributes
    ----------
    positions : (N, 2) float64
        Node coordinates ``(x, y)`` (units: cells / metres of the scene).
    directions : (D,) float64
        Heading angles in radians, counter-clockwise from +x, evenly spaced from 0.
    neighbours : (N, D) int64
        ``neighbours[n, d]`` is the node reached from ``n`` in direction ``d``, or -1.
    places : dict[str, int]
        Named nodes (``start``, ``left_arm``, ...).
    cells : (N, 2) int64 or None
        For graphs built from a gridworld: the ``(row, col)`` cell of each node, which lets the
        3D scene build walls around exactly these cells. None for free-form graphs (the scene
        is then an open arena around the nodes).
    states : (N,) int64 or None
        For graphs built from a :class:`~cobelrun.envs.world.World`: the world state of each node.
    name : str
        Builder name (e.g. "hex", "delaunay"): a label for the graph, kept with it.
    """

    positions: np.ndarray
    directions: np.ndarray
    neighbours: np.ndarray
    places: dict[str, int] = field(default_factory=dict)
    cells: np.ndarray | None = None
    states: np.ndarray | None = None
    name: str = "graph"

    def __post_init__(self) -> None:
        self.positions = np.array(self.positions, dtype=np.float64).reshape(-1, 2)
        self.directions = np.array(self.directions, dtype=np.float64).reshape(-1)
        self.neighbours = np.array(self.neighbours, dtype=np.int64)
        n, d = self.n_nodes, self.n_directions
        if n < 1:
            raise LayoutError("a topology needs at least one node")
        if d < 2:
            raise LayoutError(f"a topology needs at least 2 directions, got {d}")
        if self.neighbours.shape != (n, d):
            raise LayoutError(f"neighbours must have shape ({n}, {d}), got {self.neighbours.shape}")
        if np.any((self.neighbours < -1) | (self.neighbours >= n)):
            raise LayoutError(f"neighbours must be node indices 0..{n - 1} or -1")
        for arr in (self.positions, self.directions, self.neighbours):
            arr.setflags(write=False)
        self.places = {str(k): self._index(v, f"place '{k}'") for k, v in dict(self.places).items()}

    # ------------------------------------------------------------------ properties
    @property
    def n_nodes(self) -> int:
        """Number of nodes ``N``."""
        return int(self.positions.shape[0])

    @property
    def n_directions(self) -> int:
        """Number of heading directions ``D`` (4 for grids, 6 for hexagonal graphs)."""
        return int(self.directions.shape[0])

    @property
    def coords(self) -> np.ndarray:
        """(N, 2) node coordinates (alias of :attr:`positions`, as ``World.coords``)."""
        return self.positions

    @property
    def edges(self) -> np.ndarray:
        """(E, 2) int64 directed edges ``(from, to)``, sorted."""
        src, d = np.nonzero(self.neighbours >= 0)
        e = np.stack([src, self.neighbours[src, d]], axis=1)
        return np.unique(e, axis=0) if e.size else e.reshape(0, 2)

    @property
    def degree(self) -> np.ndarray:
        """(N,) number of outgoing edges per node."""
        return (self.neighbours >= 0).sum(axis=1)

    # ------------------------------------------------------------------ references
    def node(self, ref: Any) -> int:
        """Resolve a node reference: index, place name, or (for grid-derived graphs) [row, col]."""
        return self._index(ref, "node")

    def _index(self, ref: Any, what: str) -> int:
        if isinstance(ref, bool | np.bool_):
            raise ConfigError(f"{what}: {ref!r} is not a node; use an index or a place name")
        if isinstance(ref, int | np.integer):
            i = int(ref)
            if not 0 <= i < self.n_nodes:
                raise LayoutError(
                    f"{what}: node {i} is out of range; allowed 0..{self.n_nodes - 1}"
                )
            return i
        if isinstance(ref, str):
            places = getattr(self, "places", {}) or {}
            if ref in places:
                return int(places[ref])
            if ref.strip().isdigit():
                return self._index(int(ref), what)
            allowed = allowed_list(sorted(places)) if places else "none defined"
            raise LayoutError(
                f"{what}: unknown place '{ref}'{suggest(ref, places)}; places: {allowed}"
            )
        if isinstance(ref, Sequence | np.ndarray) and self.cells is not None:
            items = list(ref)
            if len(items) == 2 and all(isinstance(v, int | np.integer) for v in items):
                hit = np.flatnonzero(
                    (self.cells[:, 0] == items[0]) & (self.cells[:, 1] == items[1])
                )
                if hit.size:
                    return int(hit[0])
                raise LayoutError(f"{what}: cell {items} is not a node of this graph")
        raise ConfigError(f"{what}: {ref!r} is not a node reference; use an index or a place name")

    def heading_index(self, angle_deg: float) -> int:
        """Index of the direction closest to ``angle_deg`` (degrees, counter-clockwise from +x)."""
        diff = np.angle(np.exp(1j * (self.directions - np.deg2rad(angle_deg))))
        return int(np.argmin(np.abs(diff)))


# ---------------------------------------------------------------------- actions
@dataclass(frozen=True)
class ActionMap:
    """Pose transitions of an action mode on a topology.

    ``next_node[n, h, a]`` and ``next_heading[n, h, a]`` give the pose after action ``a`` in pose
    ``(n, h)``; computed once so a step is two array lookups.
    """

    mode: str
    names: tuple[str, ...]
    next_node: np.ndarray
    next_heading: np.ndarray

    @property
    def n_actions(self) -> int:
        return len(self.names)

    @classmethod
    def build(cls, topology: Topology, mode: str) -> ActionMap:
        """Tabulate the transitions of ``mode`` (one of :data:`ACTION_MODES`)."""
        if mode not in ACTION_MODES:
            raise ConfigError(
                f"action mode {mode!r} is unknown{suggest(str(mode), ACTION_MODES)}; "
                f"allowed: {allowed_list(ACTION_MODES)}"
            )
        n, d = topology.n_nodes, topology.n_directions
        nb = topology.neighbours
        nodes = np.arange(n)[:, None]
        heads = np.arange(d)[None, :]
        moves_n, moves_h, names = [], [], []
        deg = [round(np.rad2deg(a)) for a in topology.directions]

        def move(direction: np.ndarray, keep_heading: bool) -> None:
            target = nb[np.broadcast_to(nodes, (n, d)), direction % d]
            ok = target >= 0
            moves_n.append(np.where(ok, target, np.broadcast_to(nodes, (n, d))))
            if keep_heading:
                moves_h.append(np.broadcast_to(heads, (n, d)).copy())
            else:
                moves_h.append(np.where(ok, direction % d, np.broadcast_to(heads, (n, d))))

        def turn(new_heading: np.ndarray) -> None:
            moves_n.append(np.broadcast_to(nodes, (n, d)).copy())
            moves_h.append(np.broadcast_to(new_heading % d, (n, d)).copy())

        if mode == "none":
            for k in range(d):
                move(np.full((n, d), k), keep_heading=False)
                names.append(f"move_{deg[k]}")
        elif mode == "turn":
            for k in range(d):
                move(heads + k + np.zeros((n, 1), np.int64), keep_heading=True)
                names.append("forward" if k == 0 else f"move_rel_{deg[k]}")
            if d == 4:
                names[1:4] = ["left", "back", "right"]
            turn(heads + 1 + np.zeros((n, 1), np.int64))
            names.append("turn_left")
            turn(heads - 1 + np.zeros((n, 1), np.int64))
            names.append("turn_right")
        else:  # face
            for k in range(d):
                move(np.full((n, d), k), keep_heading=True)
                names.append(f"move_{deg[k]}")
            for k in range(d):
                turn(np.full((n, d), k))
                names.append(f"face_{deg[k]}")
        next_node = np.stack(moves_n, axis=2).astype(np.int64)
        next_heading = np.stack(moves_h, axis=2).astype(np.int64)
        next_node.setflags(write=False)
        next_heading.setflags(write=False)
        return cls(mode=mode, names=tuple(names), next_node=next_node, next_heading=next_heading)


# ---------------------------------------------------------------------- builders
def _directions(n: int) -> np.ndarray:
    return np.arange(n) * (2 * np.pi / n)


def _bin_edges(
    positions: np.ndarray, edges: Iterable[Sequence[int]], n_directions: int, directed: bool
) -> np.ndarray:
    """Neighbour table from an edge list: each edge goes to its nearest direction bin.

    Two edges of one node in the same bin: the one closer in angle wins (the other is unusable
    by direction-based actions); an error is raised if they are equally close.
    """
    n = positions.shape[0]
    dirs = _directions(n_directions)
    nb = np.full((n, n_directions), -1, np.int64)
    err = np.full((n, n_directions), np.inf)
    pairs: list[tuple[int, int]] = []
    for e in edges:
        if isinstance(e, str) or len(e) != 2:
            raise ConfigError(f"edges: each edge must be a pair [a, b] of nodes, got {e!r}")
        a, b = int(e[0]), int(e[1])
        for v in (a, b):
            if not 0 <= v < n:
                raise LayoutError(f"edges: node {v} is out of range; allowed 0..{n - 1}")
        if a == b:
            raise LayoutError(f"edges: self-loop at node {a}")
        pairs.append((a, b))
        if not directed:
            pairs.append((b, a))
    for a, b in pairs:
        dx, dy = positions[b] - positions[a]
        if dx == 0 and dy == 0:
            raise LayoutError(f"edges: nodes {a} and {b} are at the same position")
        ang = np.arctan2(dy, dx)
        diff = np.abs(np.angle(np.exp(1j * (dirs - ang))))
        k = int(np.argmin(diff))
        if nb[a, k] == b:
            continue
        if np.isclose(diff[k], err[a, k]):
            raise LayoutError(
                f"edges: nodes {nb[a, k]} and {b} are both in direction {np.rad2deg(dirs[k]):.0f} deg "
                f"of node {a}; use more directions (n_directions) or fewer edges"
            )
        if diff[k] < err[a, k]:
            nb[a, k], err[a, k] = b, diff[k]
    return nb


def grid(
    width: int,
    height: int,
    *,
    spacing: float = 1.0,
    places: Mapping[str, Any] | None = None,
) -> Topology:
    """A rectangular grid graph (4 directions: 0 = east, 1 = north, 2 = west, 3 = south).

    Nodes are numbered row-major from the top-left like gridworld states
    (``node = row * width + col``; ``x = col * spacing``, ``y = (height - 1 - row) * spacing``).
    """
    width, height = int(width), int(height)
    if width < 1 or height < 1 or width * height < 2:
        raise LayoutError(f"grid needs at least 2 nodes, got {width} x {height}")
    rows, cols = np.divmod(np.arange(width * height), width)
    pos = np.stack([cols, height - 1 - rows], axis=1) * float(spacing)
    nb = np.full((width * height, 4), -1, np.int64)
    for k, (dr, dc) in enumerate(((0, 1), (-1, 0), (0, -1), (1, 0))):
        rr, cc = rows + dr, cols + dc
        ok = (rr >= 0) & (rr < height) & (cc >= 0) & (cc < width)
        nb[ok, k] = (rr * width + cc)[ok]
    return Topology(
        positions=pos,
        directions=_directions(4),
        neighbours=nb,
        places=dict(places or {}),
        cells=np.stack([rows, cols], axis=1),
        name="grid",
    )


def hexagonal(
    width: int = 9,
    height: int = 9,
    *,
    spacing: float = 1.0,
    places: Mapping[str, Any] | None = None,
) -> Topology:
    """A hexagonal graph on a ``width x height`` lattice (6 directions, 60 degrees apart).

    Rows alternate between ``width`` and ``width - 1`` nodes; the shorter rows are shifted by half
    a spacing, so every inner node has 6 neighbours at distance ``spacing``. The paper's 9 x 9
    lattice gives 5 x 9 + 4 x 8 = 77 nodes with node 38 in the centre (Fig. 8, docs/paper-settings.md). Nodes are
    numbered row by row from the top; the place ``centre`` names the middle node.
    """
    width, height = int(width), int(height)
    if width < 2 or height < 1:
        raise LayoutError(f"hexagonal needs width >= 2 and height >= 1, got {width} x {height}")
    dy = np.sqrt(3.0) / 2.0
    pos = []
    for r in range(height):
        k = width if r % 2 == 0 else width - 1
        off = 0.0 if r % 2 == 0 else 0.5
        pos.extend((c + off, (height - 1 - r) * dy) for c in range(k))
    positions = np.asarray(pos) * float(spacing)
    # neighbours: every pair at distance `spacing` (rounded), binned by direction
    diff = positions[:, None, :] - positions[None, :, :]
    dist = np.hypot(diff[..., 0], diff[..., 1])
    a, b = np.nonzero(
        np.isclose(dist, spacing) & (np.arange(len(pos))[:, None] < np.arange(len(pos)))
    )
    nb = _bin_edges(positions, zip(a.tolist(), b.tolist(), strict=True), 6, directed=False)
    centre = int(np.argmin(np.hypot(*(positions - positions.mean(axis=0)).T)))
    return Topology(
        positions=positions,
        directions=_directions(6),
        neighbours=nb,
        places={"centre": centre, **dict(places or {})},
        name="hexagonal",
    )


def delaunay(
    points: Sequence[Sequence[float]],
    *,
    n_directions: int = 8,
    max_edge_length: float | None = None,
    places: Mapping[str, Any] | None = None,
) -> Topology:
    """Delaunay triangulation of ``points`` (``scipy.spatial.Delaunay``) as a graph.

    Parameters
    ----------
    points : (N, 2) list of [x, y]
        Node positions.
    n_directions : int
        Heading / move directions (default 8, 45 degrees apart). Each edge goes to its nearest
        direction; of two edges in one direction the closer in angle is kept.
    max_edge_length : float, optional
        Drop triangulation edges longer than this (e.g. across a concave border).
    places : mapping name -> node, optional
    """
    from scipy.spatial import Delaunay, QhullError

    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] < 3:
        raise LayoutError(f"delaunay needs at least 3 points [x, y], got shape {pts.shape}")
    try:
        tri = Delaunay(pts)
    except QhullError as exc:
        raise LayoutError(
            f"delaunay: cannot triangulate the points ({str(exc).splitlines()[0]})"
        ) from None
    edges = set()
    for simplex in tri.simplices:
        for i in range(3):
            a, b = sorted((int(simplex[i]), int(simplex[(i + 1) % 3])))
            edges.add((a, b))
    if max_edge_length is not None:
        edges = {e for e in edges if np.hypot(*(pts[e[0]] - pts[e[1]])) <= max_edge_length}
    nb = _bin_edges(pts, sorted(edges), int(n_directions), directed=False)
    return Topology(
        positions=pts,
        directions=_directions(int(n_directions)),
        neighbours=nb,
        places=dict(places or {}),
        name="delaunay",
    )


#: a one-way edge's door spans this fraction of the edge's length, across its middle
DOOR_SPAN = 0.5


def one_way_doors(positions: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """The one-way edges of a graph as doors, in :attr:`Geometry.doors`' format
    (``x0, y0, x1, y1, dx, dy``), so that every picture draws them as a grid's one-way doors.

    Parameters
    ----------
    positions : (N, 2) float
        Node positions.
    edges : (E, 2) int
        Directed edges ``(from, to)`` (:attr:`Topology.edges`).

    Returns
    -------
    (d, 6) float64
        One door per edge ``a -> b`` whose reverse ``b -> a`` is not an edge: a segment across
        the edge's middle, :data:`DOOR_SPAN` of its length, and the unit direction ``a -> b``
        in which it can be passed.
    """
    e = np.asarray(edges, np.int64).reshape(-1, 2)
    if not len(e):
        return np.zeros((0, 6))
    pairs = set(map(tuple, e.tolist()))
    one_way = np.array([(b, a) not in pairs for a, b in e.tolist()])
    e = e[one_way & (e[:, 0] != e[:, 1])]
    if not len(e):
        return np.zeros((0, 6))
    pos = np.asarray(positions, np.float64)
    a, b = pos[e[:, 0]], pos[e[:, 1]]
    length = np.linalg.norm(b - a, axis=1, keepdims=True)
    u = (b - a) / np.where(length > 0, length, 1.0)
    across = np.stack([-u[:, 1], u[:, 0]], axis=1) * (DOOR_SPAN * length / 2)
    mid = (a + b) / 2
    return np.hstack([mid - across, mid + across, u])


def manual(
    nodes: Sequence[Sequence[float]],
    edges: Sequence[Sequence[int]],
    *,
    n_directions: int = 4,
    directed: bool = False,
    places: Mapping[str, Any] | None = None,
) -> Topology:
    """A graph given node by node and edge by edge (e.g. written in YAML).

    Parameters
    ----------
    nodes : list of [x, y]
        Node positions; node ``i`` is ``nodes[i]``.
    edges : list of [a, b]
        Edges between node indices; two-way unless ``directed``.
    n_directions : int
        Direction bins for headings and moves (default 4).
    directed : bool
        Treat ``[a, b]`` as the one-way move ``a -> b``.
    places : mapping name -> node index, optional
    """
    pos = np.asarray(nodes, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1] != 2 or pos.shape[0] < 1:
        raise LayoutError(f"manual: nodes must be a list of [x, y] pairs, got shape {pos.shape}")
    nb = _bin_edges(pos, edges, int(n_directions), directed=bool(directed))
    return Topology(
        positions=pos,
        directions=_directions(int(n_directions)),
        neighbours=nb,
        places=dict(places or {}),
        name="manual",
    )


#: gridworld action index for each grid direction (east, north, west, south)
_GRID_TO_WORLD_ACTION = (2, 1, 0, 3)


def from_world(world: _world.World, *, only_reachable: bool = True) -> Topology:
    """The topology of a gridworld: one node per free (reachable) cell, 4 directions.

    Edges follow the world's deterministic moves (walls and one-way doors included). Nodes are
    numbered in increasing world-state order (row-major from the top-left), so the paper's 7 x 7
    T-maze gives 12 nodes: 0..6 along the top row (0 = left arm end, 3 = junction,
    6 = right arm end) and 7..11 down the stem (11 = start). The original's Blender T-maze
    numbered its nodes differently (start 3, right arm 11); configs use place names
    (``start``, ``left_arm``, ``right_arm``), which carry over.
    """
    if not isinstance(world, _world.World):
        raise ConfigError(f"from_world needs a cobelrun World, got {type(world).__name__}")
    free = ~world.blocked
    if only_reachable:
        free &= world.reachable()
    states = np.flatnonzero(free)
    index = np.full(world.n_states, -1, np.int64)
    index[states] = np.arange(states.size)
    T = world.T
    nb = np.full((states.size, 4), -1, np.int64)
    for k, a in enumerate(_GRID_TO_WORLD_ACTION):
        # most likely successor of each move (the intended one when slip < 0.5)
        succ = T[states, a, :].argmax(axis=1)
        ok = (succ != states) & (index[succ] >= 0)
        nb[ok, k] = index[succ[ok]]
    rows, cols = np.divmod(states, world.width)
    places = {k: int(index[v]) for k, v in world.places.items() if index[v] >= 0}
    return Topology(
        positions=world.coords[states],
        directions=_directions(4),
        neighbours=nb,
        places=places,
        cells=np.stack([rows, cols], axis=1),
        states=states,
        name="world",
    )


def from_layout(layout: str, **kwargs: Any) -> Topology:
    """Topology of an ASCII maze (same symbols as :func:`cobelrun.envs.world.from_layout`)."""
    return from_world(_world.from_layout(layout, **kwargs))


def tmaze_paper() -> Topology:
    """The 12-node topology of the paper's T-maze (Fig. 6A), from :func:`world.tmaze_paper`."""
    return from_world(_world.tmaze_paper())
