"""Environment contracts and the pieces cobel's environments share.

Consumers (runner, recorder, monitors, agents, exports) never probe an environment with
``hasattr`` or check its class: they ask one of the runtime-checkable protocols below, each a
capability an environment declares by implementing its methods on ``env.unwrapped``:

:class:`Changeable`
    A protocol phase may change rewards, terminal states/regions and starts
    (``apply_changes``) and a new run restores the world as built (``reset_world``).
:class:`Posed`
    The agent's pose ``(x, y, heading)`` in world units (heading in radians, counter-clockwise
    from +x), for grids, graphs and continuous arenas alike.
:class:`DiscreteStates`
    Integer states with named places (``state_index("right_arm")``) and the pose of any state,
    vectorised (``poses_of(states, actions)``), so compiled agents need not track poses.
:class:`TabularModel`
    A known transition table (``world.T``, ``world.rewards``, ...) that tabular and Dyna agents
    plan with, and the ``action_mask`` of actions that leave a state.
:class:`StateObservations`
    The observation of every state (one-hot codes, choice displays).
:class:`HasGeometry`
    The maze, graph or arena as data (:class:`Geometry`), for plots, MCAP scenes and exports.
:class:`RendersAtPose`
    The observation at an arbitrary pose, e.g. for activity maps between graph nodes.
:class:`ObservesGrid`
    A graph's layout and the observations at every pose of a grid over it (activity maps).

:func:`capabilities` lists what an environment offers; :func:`require` turns a missing
capability into a one-line :class:`~cobelrun.errors.ConfigError`.
"""

from __future__ import annotations

import json
import operator
import weakref
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from cobelrun.errors import ConfigError, allowed_list, suggest

__all__ = [
    "CONTRACTS",
    "Changeable",
    "ChangeableWorld",
    "DiscreteStates",
    "Geometry",
    "HasGeometry",
    "ObservesGrid",
    "Posed",
    "RendersAtPose",
    "StateObservations",
    "TabularModel",
    "TrialScript",
    "capabilities",
    "check_action",
    "require",
    "supports",
]


# ---------------------------------------------------------------------------- contracts
@runtime_checkable
class Changeable(Protocol):
    """Rewards, terminals and starts changed by protocol phases."""

    def apply_changes(
        self,
        rewards: Mapping[Any, float] | None = None,
        terminals: Mapping[Any, bool] | None = None,
        starts: Iterable[Any] | None = None,
    ) -> None: ...

    def reset_world(self) -> None: ...


@runtime_checkable
class Posed(Protocol):
    """The agent's current pose in world units."""

    def agent_pose(self) -> np.ndarray:
        """``(x, y, heading)``: position and heading in radians (CCW from +x), float64 (3,)."""
        ...


@runtime_checkable
class DiscreteStates(Protocol):
    """Integer states: count, named references and their poses."""

    @property
    def n_states(self) -> int: ...

    def state_index(self, ref: Any) -> int:
        """The state of a reference: an index, a place name or a ``[row, col]`` cell."""
        ...

    def poses_of(self, states: np.ndarray, actions: np.ndarray | None = None) -> np.ndarray:
        """(k, 3) poses of ``states``; ``actions`` (the action that led to each, -1 for none)
        give headings where the action defines one."""
        ...


@runtime_checkable
class TabularModel(Protocol):
    """A known tabular world (``T[s, a, s']``, rewards, terminal, starts) and its action mask."""

    @property
    def world(self) -> Any: ...

    def action_mask(self) -> np.ndarray: ...


@runtime_checkable
class StateObservations(Protocol):
    """The observation of every discrete state, e.g. one-hot codes or the displays of a
    choice task (probes of activity monitors, state-based deep agents)."""

    @property
    def observations(self) -> np.ndarray:
        """(n_states, ...) observation of each state."""
        ...


@runtime_checkable
class HasGeometry(Protocol):
    """The environment's layout as data."""

    def geometry(self) -> Geometry: ...


@runtime_checkable
class RendersAtPose(Protocol):
    """Observations at arbitrary poses (between graph nodes, anywhere in an arena)."""

    def render_at_pose(self, x: float, y: float, heading: float) -> Any: ...


@runtime_checkable
class ObservesGrid(RendersAtPose, Protocol):
    """A graph's layout (``topology``: node positions, cells) and the observations at every pose
    of a grid over it at once, e.g. for activity maps (:class:`~cobelrun.envs.TopologyEnv`)."""

    topology: Any

    def observe_grid(
        self,
        positions: np.ndarray,
        headings_rad: np.ndarray,
        rng: np.random.Generator | None = None,
    ) -> Any:
        """Observations at every ``positions (M, 2) x headings_rad (D,)`` pose: ``(M, D, ...)``."""
        ...


@runtime_checkable
class TrialScript(Protocol):
    """Scripted conditioning trials (:class:`cobelrun.envs.sequence.SequenceEnv`): the cue names
    (CSs first, then contexts), how many are CSs, whether the observation carries a complete
    serial compound, and the cues and info of the current trial."""

    cue_names: list[str]
    n_cs: int
    csc: bool

    def trial_cues(self, trial_type: int | None = None) -> np.ndarray: ...

    def trial_info(self) -> dict[str, Any]: ...


#: Every contract by the name agents and monitors use in ``requires``.
CONTRACTS: dict[str, type] = {
    "changeable": Changeable,
    "pose": Posed,
    "discrete_states": DiscreteStates,
    "tabular_model": TabularModel,
    "state_observations": StateObservations,
    "geometry": HasGeometry,
    "render_at_pose": RendersAtPose,
    "observe_grid": ObservesGrid,
    "trial_script": TrialScript,
}


_SUPPORTS: weakref.WeakKeyDictionary[Any, dict[type, bool]] = weakref.WeakKeyDictionary()


def supports(env: Any, contract: type) -> bool:
    """``isinstance(env.unwrapped, contract)``, remembered per env (a runtime protocol check
    costs ~70 us; hot paths ask once per batch of trials)."""
    base = getattr(env, "unwrapped", env)
    try:
        known = _SUPPORTS.setdefault(base, {})
    except TypeError:  # not weak-referenceable
        return isinstance(base, contract)
    if contract not in known:
        known[contract] = isinstance(base, contract)
    return known[contract]


def capabilities(env: Any) -> list[str]:
    """Names of the contracts ``env`` (or its unwrapped env) implements."""
    base = getattr(env, "unwrapped", env)
    return [name for name, proto in CONTRACTS.items() if isinstance(base, proto)]


def require(env: Any, needs: Iterable[str], who: str) -> None:
    """Raise a one-line ConfigError if ``env`` lacks one of the contracts ``needs``."""
    base = getattr(env, "unwrapped", env)
    for name in needs:
        if name not in CONTRACTS:
            raise ValueError(f"unknown contract {name!r}; known: {', '.join(CONTRACTS)}")
        if not isinstance(base, CONTRACTS[name]):
            have = ", ".join(capabilities(base)) or "none"
            raise ConfigError(
                f"{who} needs an environment with '{name}', which {type(base).__name__} "
                f"does not offer (it offers: {have})"
            )


# ---------------------------------------------------------------------------- geometry
@dataclass
class Geometry:
    """A layout as plain data (world units), saved with every run as ``world.json``.

    Attributes
    ----------
    kind : {"grid", "graph", "arena", "none"}
        What the layout is.
    bounds : (xmin, ymin, xmax, ymax)
        Bounding box of everything the agent can reach.
    walls : (m, 4) float64
        Wall segments ``x0, y0, x1, y1`` (grid walls, arena outline edges, obstacle edges).
    cells : (k, 2) float64
        Centres of free grid cells (size ``cell_size``); empty for graphs and arenas.
    cell_size : float
        Side of a grid cell.
    nodes : (N, 2) float64
        Graph node positions (graphs; grids give their free cells as nodes too).
    edges : (E, 2) int64
        Undirected graph edges between node indices.
    outline : (P, 2) float64
        Arena outline polygon (closed implicitly); empty for grids and graphs.
    regions : dict
        Named regions, each ``{"shape": "point"|"circle"|"polygon", ...}``: ``x, y`` (point,
        circle), ``radius`` (circle), ``points`` (polygon). Goals, starts and places.
    doors : (d, 6) float64
        One-way doors ``x0, y0, x1, y1, dx, dy``: the door's segment (not in ``walls``) and
        the unit direction in which it can be passed (the other way it is a wall). Run folders
        written before doors were saved have none (their doors are in ``walls``).
    """

    kind: str
    bounds: tuple[float, float, float, float]
    walls: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    cells: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    cell_size: float = 1.0
    nodes: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    edges: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    outline: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    regions: dict[str, dict[str, Any]] = field(default_factory=dict)
    doors: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))

    KINDS = ("grid", "graph", "arena", "none")

    def __post_init__(self) -> None:
        if self.kind not in self.KINDS:
            raise ValueError(f"geometry kind {self.kind!r}; allowed: {', '.join(self.KINDS)}")
        self.bounds = tuple(float(b) for b in self.bounds)  # type: ignore[assignment]
        self.walls = np.asarray(self.walls, np.float64).reshape(-1, 4)
        self.cells = np.asarray(self.cells, np.float64).reshape(-1, 2)
        self.nodes = np.asarray(self.nodes, np.float64).reshape(-1, 2)
        self.edges = np.asarray(self.edges, np.int64).reshape(-1, 2)
        self.outline = np.asarray(self.outline, np.float64).reshape(-1, 2)
        self.doors = np.asarray(self.doors, np.float64).reshape(-1, 6)
        self.cell_size = float(self.cell_size)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (lists of floats)."""
        return {
            "kind": self.kind,
            "bounds": list(self.bounds),
            "walls": self.walls.tolist(),
            "cells": self.cells.tolist(),
            "cell_size": self.cell_size,
            "nodes": self.nodes.tolist(),
            "edges": self.edges.tolist(),
            "outline": self.outline.tolist(),
            "regions": self.regions,
            "doors": self.doors.tolist(),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Geometry:
        known = {"kind", "bounds", "walls", "cells", "cell_size", "nodes", "edges", "outline",
                 "regions", "doors"}  # fmt: skip
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown geometry keys {unknown}; allowed: {sorted(known)}")
        return cls(**dict(data))

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), separators=(",", ":"))


def point_region(x: float, y: float) -> dict[str, Any]:
    return {"shape": "point", "x": float(x), "y": float(y)}


def headings_of_moves(actions: np.ndarray, table: np.ndarray, default: float) -> np.ndarray:
    """Heading (radians) of each move in ``actions`` from a per-action ``table``; ``default``
    where an action is -1 (trial start)."""
    actions = np.asarray(actions, np.int64)
    out = np.full(actions.shape, float(default))
    ok = actions >= 0
    out[ok] = table[actions[ok]]
    return out


# ---------------------------------------------------------------------------- shared parts
class ChangeableWorld:
    """Mixin for environments whose ``world`` a protocol changes between phases.

    The environment keeps ``_world`` (live) and ``_base_world`` (as built); the world object
    offers ``set_rewards``, ``set_terminal``, ``set_starts`` and ``copy``.
    """

    _world: Any
    _base_world: Any

    @property
    def world(self) -> Any:
        """The live world (changed by :meth:`apply_changes`)."""
        return self._world

    @property
    def base_world(self) -> Any:
        """The world as it was at construction (a copy; do not modify)."""
        return self._base_world

    def reset_world(self) -> None:
        """Restore the world to :attr:`base_world` (undo every :meth:`apply_changes`)."""
        self._world = self._base_world.copy()

    @property
    def n_states(self) -> int:
        """Number of states of the world."""
        return int(self._world.n_states)

    def state_index(self, ref: Any) -> int:
        """The state of ``ref``: an index, a place name (``"right_arm"``) or ``[row, col]``."""
        return int(self._world.state(ref))

    def _place_regions(self) -> dict[str, dict[str, Any]]:
        """Named places and start states as point regions (for :class:`Geometry`)."""
        w = self._world
        regions = {name: point_region(*w.coords[s]) for name, s in w.places.items()}
        for s in np.unique(w.starts):
            regions.setdefault(f"start_{int(s)}", point_region(*w.coords[s]))
        return regions

    def apply_changes(
        self,
        rewards: Mapping[Any, float] | None = None,
        terminals: Mapping[Any, bool] | None = None,
        starts: Iterable[Any] | None = None,
    ) -> None:
        """Change rewards, terminal flags or start states in place (a protocol phase starts).

        Parameters
        ----------
        rewards : mapping state -> float, optional
            New arrival rewards.
        terminals : mapping state -> bool, optional
            Terminal flags to set.
        starts : list of states, optional
            New start states.
        """
        if rewards is not None:
            self._world.set_rewards(rewards)
        if terminals is not None:
            self._world.set_terminal(terminals)
        if starts is not None:
            self._world.set_starts(starts)


def episode_options(
    max_steps: Any, render_mode: Any, modes: Sequence[str]
) -> tuple[int | None, str | None]:
    """An env's checked ``max_steps`` (a positive integer or None) and ``render_mode`` (one of
    ``modes`` or None); a one-line ConfigError otherwise."""
    if max_steps is not None:
        if (
            isinstance(max_steps, bool)
            or not isinstance(max_steps, int | np.integer)
            or max_steps < 1
        ):
            raise ConfigError(f"max_steps must be a positive integer or null, got {max_steps!r}")
        max_steps = int(max_steps)
    if render_mode is not None and render_mode not in modes:
        raise ConfigError(
            f"render_mode {render_mode!r} is not supported{suggest(str(render_mode), list(modes))}; "
            f"allowed: {allowed_list(list(modes))}, None"
        )
    return max_steps, render_mode


def check_action(action: Any, n_actions: int, names: Sequence[str]) -> int:
    """Return ``action`` as an int in ``[0, n_actions)`` or raise a ValueError naming the actions."""
    listed = ", ".join(f"{i}={name}" for i, name in enumerate(names))
    try:
        if hasattr(action, "reshape") and hasattr(
            action, "size"
        ):  # numpy scalar or 1-element array
            if action.size != 1:
                raise TypeError
            action = action.reshape(()).item()
        if isinstance(action, bool) or type(action).__name__ == "bool_":
            raise TypeError
        a = operator.index(action)
    except TypeError:
        raise ValueError(
            f"invalid action {action!r}; allowed: integers 0..{n_actions - 1} ({listed})"
        ) from None
    if not 0 <= a < n_actions:
        raise ValueError(f"invalid action {a}; allowed: 0..{n_actions - 1} ({listed})")
    return a
