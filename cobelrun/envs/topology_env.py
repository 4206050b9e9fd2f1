"""Gymnasium environment on a topology graph: poses (node, heading), actions, observation module."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from cobelrun.envs import topology as topo
from cobelrun.envs.base import ChangeableWorld, Geometry, check_action, episode_options
from cobelrun.envs.observations import ObservationModule, PoseObservation
from cobelrun.envs.world import World, _finite, _pairs
from cobelrun.errors import ConfigError, LayoutError


@dataclass(eq=False)
class GraphWorld:
    """Rewards, terminals and starts on a topology's nodes: the ``world`` of a :class:`TopologyEnv`.

    Offers what monitors, the recorder and protocols read from a gridworld's
    :class:`~cobelrun.envs.world.World`: :meth:`state` (resolve a node by index or place name),
    :attr:`coords`, :attr:`places`, :attr:`n_states`, and in-place ``set_*`` changes.
    "State" means node here.
    """

    topology: topo.Topology
    rewards: np.ndarray
    terminal: np.ndarray
    starts: np.ndarray
    places: dict[str, int] = field(init=False)

    def __post_init__(self) -> None:
        n = self.topology.n_nodes
        self.rewards = np.asarray(self.rewards, np.float64).reshape(-1).copy()
        self.terminal = np.asarray(self.terminal, bool).reshape(-1).copy()
        if self.rewards.shape != (n,) or self.terminal.shape != (n,):
            raise LayoutError(f"rewards and terminal need one entry per node ({n})")
        self.places = dict(self.topology.places)
        self.set_starts(np.asarray(self.starts).reshape(-1).tolist())

    @property
    def n_states(self) -> int:
        return self.topology.n_nodes

    @property
    def coords(self) -> np.ndarray:
        """(N, 2) node coordinates."""
        return self.topology.positions

    def state(self, ref: Any) -> int:
        """Resolve a node reference (index or place name)."""
        return self.topology.node(ref)

    def describe(self, s: int) -> str:
        x, y = self.coords[s]
        return f"node {int(s)} (x {x:g}, y {y:g})"

    def copy(self) -> GraphWorld:
        return GraphWorld(
            self.topology, self.rewards.copy(), self.terminal.copy(), self.starts.copy()
        )

    def set_rewards(self, mapping: Mapping[Any, float]) -> None:
        """Set arrival rewards of some nodes: ``{node or place: reward}``."""
        new = self.rewards.copy()
        for ref, value in _pairs(mapping, "rewards"):
            new[self.topology._index(ref, "rewards")] = _finite(value, f"rewards[{ref!r}]")
        self.rewards = new

    def set_terminal(self, mapping: Mapping[Any, bool]) -> None:
        """Mark nodes terminal or not: ``{node or place: bool}``."""
        new = self.terminal.copy()
        starts = set(self.starts.tolist())
        for ref, flag in _pairs(mapping, "terminals"):
            s = self.topology._index(ref, "terminals")
            if not isinstance(flag, bool | np.bool_):
                raise ConfigError(f"terminals[{ref!r}] must be true or false, got {flag!r}")
            if flag and s in starts:
                raise LayoutError(
                    f"terminals: {self.describe(s)} is a start node; it cannot be terminal"
                )
            new[s] = bool(flag)
        self.terminal = new

    def set_starts(self, refs: Iterable[Any] | Any) -> None:
        """Replace the start nodes (``"all"``: every non-terminal node)."""
        if isinstance(refs, str) and refs == "all":
            refs = np.flatnonzero(~self.terminal).tolist()
        elif isinstance(refs, int | np.integer | str):
            refs = [refs]
        starts = [self.topology._index(r, "starts") for r in refs]
        if not starts:
            raise LayoutError("starts: at least one start node is needed")
        for s in starts:
            if self.terminal[s]:
                raise LayoutError(
                    f"starts: {self.describe(s)} is terminal; starts must be non-terminal"
                )
        self.starts = np.asarray(starts, np.int64)


class TopologyEnv(ChangeableWorld, gym.Env):
    """Navigation on a topology graph with poses (node, heading) and an observation module.

    Description
    -----------
    The agent stands on a node of a :class:`~cobelrun.envs.topology.Topology` facing one of its
    ``D`` directions (paper section 2.2.2). Actions move it to neighbouring nodes and, in the
    rotation modes, turn it (:class:`~cobelrun.envs.topology.ActionMap`). The observation module
    (section 2.2.3) turns the pose into what the agent sees: pose vector, rendered images, noisy
    or multisensory combinations.

    Action Space
    ------------
    ``Discrete(A)``: ``"none"`` mode: ``D`` moves by absolute direction; ``"turn"``: ``D`` moves
    relative to the heading + turn left / right (6 on a grid, Fig. 6A); ``"face"``: ``D`` moves +
    ``D`` face-direction turns (12 on a hexagonal graph, Fig. 8). :attr:`action_names` lists them.

    Observation Space
    -----------------
    The module's space (default :class:`~cobelrun.envs.observations.PoseObservation`:
    ``Box(4,)`` float32 ``(x, y, cos, sin)``).

    Rewards
    -------
    ``rewards[n']`` of the node arrived at (turning re-arrives at the same node), plus
    ``step_reward`` on every step that does not end in a terminal node (Fig. 8: +1 at the goal,
    -1 per step: ``rewards={goal: 1}, step_reward=-1``).

    Starting State
    --------------
    A node drawn uniformly from the starts; heading ``start_heading`` (index or degrees, see
    below) or drawn uniformly when ``start_heading="random"``.

    Episode End
    -----------
    Terminated on arriving at a terminal node; truncated after ``max_steps`` steps (if given).

    Arguments
    ---------
    topology : Topology, optional
        The graph. Default: derived from ``world`` (or the paper's T-maze if neither is given).
    world : World, optional
        A gridworld: gives the topology (:func:`~cobelrun.envs.topology.from_world`) *and* its
        rewards, terminal states, start states and place names, carried over to the nodes.
    rewards : mapping node -> float, optional
        Arrival rewards (after the world's).
    terminals : list of nodes, optional
        Terminal nodes (added to the world's).
    starts : list of nodes or "all", optional
        Start nodes (default: the world's, else every non-terminal node).
    start_heading : int, float or "random"
        Heading at reset: ``"random"``, or an angle in degrees (nearest direction). Default 90
        (north, up the stem of the T-maze).
    step_reward : float
        Added on each step that does not end in a terminal node (default 0).
    actions : {"none", "turn", "face"}
        Action mode (default ``"turn"``).
    observation : ObservationModule, optional
        Default :class:`PoseObservation`.
    max_steps : int, optional
        Truncation limit.

    ``info`` holds ``state`` and ``node`` (the node index), ``heading`` (index), ``angle``
    (degrees), ``x`` and ``y``.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(
        self,
        topology: topo.Topology | None = None,
        world: World | None = None,
        rewards: Mapping[Any, float] | None = None,
        terminals: Iterable[Any] | None = None,
        starts: Iterable[Any] | str | None = None,
        start_heading: int | float | str = 90.0,
        step_reward: float = 0.0,
        actions: str = "turn",
        observation: ObservationModule | None = None,
        max_steps: int | None = None,
        render_mode: str | None = None,
    ) -> None:
        if world is not None and not isinstance(world, World):
            raise ConfigError(f"world must be a cobelrun World, got {type(world).__name__}")
        if topology is None:
            if world is None:
                from cobelrun.envs.world import tmaze_paper

                world = tmaze_paper()
            topology = topo.from_world(world)
        elif not isinstance(topology, topo.Topology):
            raise ConfigError(
                f"topology must be a cobelrun Topology, got {type(topology).__name__}"
            )
        n = topology.n_nodes
        node_rewards = np.zeros(n)
        node_terminal = np.zeros(n, bool)
        node_starts: list[int] | str = "all"
        if world is not None:
            if topology.states is None:
                raise ConfigError(
                    "world was given with a topology not built from a world; give one of them"
                )
            node_rewards = world.rewards[topology.states].copy()
            node_terminal = world.terminal[topology.states].copy()
            inv = {int(s): i for i, s in enumerate(topology.states)}
            node_starts = [inv[int(s)] for s in world.starts if int(s) in inv]
        gw = GraphWorld(topology, node_rewards, node_terminal, [0] if not node_terminal[0] else
                        [int(np.flatnonzero(~node_terminal)[0])])  # fmt: skip
        gw.set_rewards(rewards or {})
        if terminals is not None:
            if isinstance(terminals, int | str):
                terminals = [terminals]
            gw.terminal[[gw.state(t) for t in terminals]] = True
        gw.set_starts(starts if starts is not None else node_starts)
        self.topology = topology
        self.action_map = topo.ActionMap.build(topology, actions)
        self.step_reward = _finite(step_reward, "step_reward")
        self._start_heading = self._parse_heading(start_heading)
        self.max_steps, self.render_mode = episode_options(
            max_steps, render_mode, self.metadata["render_modes"]
        )
        self.observation_module = observation if observation is not None else PoseObservation()
        if not isinstance(self.observation_module, ObservationModule):
            raise ConfigError(
                f"observation must be an observation module, got {type(observation).__name__}"
            )
        self.observation_module.bind(topology)
        self.observation_space = self.observation_module.space
        self.action_space = gym.spaces.Discrete(self.action_map.n_actions)
        self._base_world = gw.copy()
        self._world = gw
        self._node = int(gw.starts[0])
        self._heading = 0 if self._start_heading is None else self._start_heading
        self._steps = 0

    def _parse_heading(self, value: Any) -> int | None:
        if isinstance(value, str):
            if value == "random":
                return None
            raise ConfigError(
                f"start_heading must be an angle in degrees or 'random', got {value!r}"
            )
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(
                f"start_heading must be an angle in degrees or 'random', got {value!r}"
            )
        return self.topology.heading_index(float(value))

    # ------------------------------------------------------------------ world access
    @property
    def action_names(self) -> tuple[str, ...]:
        return self.action_map.names

    @property
    def pose(self) -> tuple[int, int]:
        """Current ``(node, heading index)``."""
        return self._node, self._heading

    @property
    def state(self) -> int:
        """Current node."""
        return self._node

    def agent_pose(self) -> np.ndarray:
        """``(x, y, heading)`` of the current node and heading (radians)."""
        x, y = self.topology.positions[self._node]
        return np.array([x, y, self.topology.directions[self._heading]])

    def poses_of(self, states: np.ndarray, actions: np.ndarray | None = None) -> np.ndarray:
        """(k, 3) poses of nodes ``states``. A node does not carry a heading (turns change it
        in place), so the heading is the start heading (or pi/2 where that is random); runs
        through the step loop record the true heading from :meth:`agent_pose`."""
        states = np.asarray(states, np.int64)
        out = np.empty((states.shape[0], 3))
        out[:, :2] = self.topology.positions[states]
        h = self._start_heading
        out[:, 2] = np.pi / 2 if h is None else self.topology.directions[h]
        return out

    def geometry(self) -> Geometry:
        """The graph as data: node positions, undirected edges, places and starts, and each
        one-way edge as a door (:func:`~cobelrun.envs.topology.one_way_doors`), drawn as a grid's one-way doors are."""
        top = self.topology
        directed = top.edges
        edges = np.unique(np.sort(directed, axis=1), axis=0) if len(directed) else directed
        lo, hi = top.positions.min(axis=0) - 0.5, top.positions.max(axis=0) + 0.5
        return Geometry(kind="graph", bounds=(lo[0], lo[1], hi[0], hi[1]),
                        nodes=top.positions, edges=edges, regions=self._place_regions(),
                        doors=topo.one_way_doors(top.positions, directed))  # fmt: skip

    def observe_pose(self, node: int, heading: int) -> Any:
        """The observation at any graph pose, noise drawn from ``np_random``."""
        return self.observation_module.observe(int(node), int(heading), self.np_random)

    def render_at_pose(
        self, x: float, y: float, heading_rad: float, rng: np.random.Generator | None = None
    ) -> Any:
        """The observation at an arbitrary pose in world units (also between nodes).

        ``x``, ``y`` as :attr:`Topology.positions`, ``heading_rad`` counter-clockwise from +x.
        Noise (if any) is drawn from ``rng`` (default: a generator seeded with 0), never from
        the environment's ``np_random``, so probing does not change the run.
        """
        return self.observation_module.render_at_pose(float(x), float(y), float(heading_rad), rng)

    def observe_grid(
        self,
        positions: np.ndarray,
        headings_rad: np.ndarray,
        rng: np.random.Generator | None = None,
    ) -> Any:
        """Observations at every ``positions (M, 2) x headings_rad (D,)`` pose: ``(M, D, ...)``.

        Image observations read the render cache of the grid when ``render=offline``.
        """
        return self.observation_module.observe_grid(positions, headings_rad, rng)

    # ------------------------------------------------------------------ gymnasium API
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        super().reset(seed=seed)
        starts = self._world.starts
        self._node = int(starts[self.np_random.integers(0, len(starts))])
        if self._start_heading is None:
            self._heading = int(self.np_random.integers(0, self.topology.n_directions))
        else:
            self._heading = self._start_heading
        self._steps = 0
        return self.observe_pose(self._node, self._heading), self._info()

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        a = self._check_action(action)
        n, h = self._node, self._heading
        self._node = n2 = int(self.action_map.next_node[n, h, a])
        self._heading = int(self.action_map.next_heading[n, h, a])
        self._steps += 1
        terminated = bool(self._world.terminal[n2])
        reward = float(self._world.rewards[n2]) + (0.0 if terminated else self.step_reward)
        truncated = self.max_steps is not None and self._steps >= self.max_steps
        return self.observe_pose(n2, self._heading), reward, terminated, truncated, self._info()

    def render(self) -> np.ndarray | None:
        """``rgb_array``: the first image module's current view (H, W, 3) uint8."""
        if self.render_mode != "rgb_array":
            return None
        mods = self.observation_module.image_modules()
        if not mods:
            return None
        m = mods[0]
        if m._images is not None:
            return np.asarray(m._images[self._node, self._heading]).copy()
        return m.render_raw(self._node, self._heading)

    def close(self) -> None:
        self.observation_module.close()
        super().close()

    def _info(self) -> dict[str, Any]:
        x, y = self.topology.positions[self._node]
        angle = float(np.rad2deg(self.topology.directions[self._heading]))
        return {"state": self._node, "node": self._node, "heading": self._heading,
                "angle": angle, "x": float(x), "y": float(y)}  # fmt: skip

    def _check_action(self, action: Any) -> int:
        return check_action(action, self.action_map.n_actions, self.action_names)
