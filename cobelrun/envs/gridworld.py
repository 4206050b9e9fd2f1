"""Gymnasium environments over a tabular :class:`~cobelrun.envs.world.World`, with the
allocentric (left, up, right, down) or the egocentric (turn left, turn right, forward) action
set (:class:`EgocentricWorld`)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from cobelrun.envs.base import (
    ChangeableWorld,
    Geometry,
    check_action,
    episode_options,
    headings_of_moves,
)
from cobelrun.envs.world import World, tmaze_paper
from cobelrun.errors import ConfigError, LayoutError, allowed_list, suggest
from cobelrun.safety import check_allocation

_ARROWS = ("<", "^", ">", "v")
#: heading (radians, CCW from +x) of the moves left, up, right, down
ACTION_HEADING = np.array([np.pi, np.pi / 2, 0.0, -np.pi / 2])
#: heading at trial start: facing up
START_HEADING = np.pi / 2

#: the action sets of :class:`GridWorldEnv` (``actions``)
ACTION_SETS = ("allocentric", "egocentric")
ALLOCENTRIC_ACTIONS = ("left", "up", "right", "down")
#: the egocentric actions (neuro-nav's ``GridOrientation.variable``, same order)
EGOCENTRIC_ACTIONS = ("turn_left", "turn_right", "forward")
#: egocentric headings 0 = up, 1 = right, 2 = down, 3 = left (turning right adds 1): the
#: allocentric move a step forward makes, and the heading in radians (CCW from +x)
HEADING_MOVE = np.array([1, 2, 3, 0])
HEADING_ANGLE = ACTION_HEADING[HEADING_MOVE]
N_HEADINGS = 4


class EgocentricWorld(World):
    """A :class:`World` whose state includes the heading and whose actions turn or go forward.

    Built by :func:`egocentric` from an allocentric world of ``S`` cells: four copies of the
    grid stacked top to bottom, one per heading (0 = facing up, 1 = right, 2 = down,
    3 = left), so ``state = heading * S + cell`` (neuro-nav's numbering) and the grid is
    ``width x 4 height``. Actions: 0 = turn left (counter-clockwise), 1 = turn right
    (clockwise), both in place and certain; 2 = forward, the allocentric world's move in the
    heading's direction (with its walls, doors, warps and slip). Every cell's reward and
    terminal flag hold in all four headings (turning on a rewarded cell, like bumping into a
    wall there, arrives there again); start states face up (the top copy).

    Places keep their names on the top copy. :meth:`set_rewards` and :meth:`set_terminal`
    change a cell in all four headings (a protocol phase's changes keep their meaning);
    :meth:`set_starts` takes the states given (a place or ``[row, col]`` of the top copy
    faces up).
    """

    def __setattr__(self, name: str, value: Any) -> None:
        if name == "T":
            value = np.array(value, dtype=np.float64)
            n = int(self.width) * int(self.height)
            shape = (n, len(EGOCENTRIC_ACTIONS), n)
            if value.shape != shape:
                raise LayoutError(f"T must have shape {shape}, got {value.shape}")
            if np.any(value < 0) or not np.allclose(value.sum(axis=2), 1.0, atol=1e-9):
                raise LayoutError("T must hold probabilities: non-negative, each T[s, a] sums to 1")
            value.setflags(write=False)
            object.__setattr__(self, "_next_state_known", False)
            object.__setattr__(self, "_next_state", None)
        object.__setattr__(self, name, value)

    @property
    def n_actions(self) -> int:
        """Number of actions (3: turn left, turn right, forward)."""
        return len(EGOCENTRIC_ACTIONS)

    @property
    def n_cells(self) -> int:
        """Cells of the allocentric grid (a quarter of the states)."""
        return self.n_states // N_HEADINGS

    def heading_of(self, states: Any) -> np.ndarray:
        """Heading index (0 up, 1 right, 2 down, 3 left) of each state."""
        return np.asarray(states, np.int64) // self.n_cells

    def copy(self) -> EgocentricWorld:
        new = super().copy()
        new.__class__ = EgocentricWorld
        return new  # type: ignore[return-value]

    def _all_headings(self, mapping: Any, what: str) -> list[list[Any]]:
        from cobelrun.envs.world import _pairs

        S = self.n_cells
        return [[h * S + self._index(ref, what) % S, value]
                for ref, value in _pairs(mapping, what) for h in range(N_HEADINGS)]  # fmt: skip

    def set_rewards(self, mapping: Mapping[Any, float]) -> None:
        """As :meth:`World.set_rewards`, for each state's cell in all four headings."""
        super().set_rewards(self._all_headings(mapping, "rewards"))  # type: ignore[arg-type]

    def set_terminal(self, mapping: Mapping[Any, bool]) -> None:
        """As :meth:`World.set_terminal`, for each state's cell in all four headings."""
        super().set_terminal(self._all_headings(mapping, "terminals"))  # type: ignore[arg-type]


def egocentric(world: World) -> EgocentricWorld:
    """The egocentric version of an allocentric ``world`` (see :class:`EgocentricWorld`)."""
    if isinstance(world, EgocentricWorld):
        return world
    S, w, h = world.n_states, world.width, world.height
    n = N_HEADINGS * S
    check_allocation("env.actions", n * len(EGOCENTRIC_ACTIONS) * n * 8 * 2,
                     f"the egocentric transition table ({n:,} x 3 x {n:,} float64)",
                     "use a smaller world")  # fmt: skip
    T = np.zeros((n, len(EGOCENTRIC_ACTIONS), n))
    cells = np.arange(S)
    for hd in range(N_HEADINGS):
        rows = hd * S + cells
        T[rows, 0, ((hd - 1) % N_HEADINGS) * S + cells] = 1.0  # turn left
        T[rows, 1, ((hd + 1) % N_HEADINGS) * S + cells] = 1.0  # turn right
        T[hd * S : (hd + 1) * S, 2, hd * S : (hd + 1) * S] = world.T[:, HEADING_MOVE[hd], :]
    rows, cols = np.divmod(np.arange(n), w)
    return EgocentricWorld(
        width=w, height=N_HEADINGS * h, T=T, rewards=np.tile(world.rewards, N_HEADINGS),
        terminal=np.tile(world.terminal, N_HEADINGS), starts=world.starts.copy(),
        coords=np.stack([cols, N_HEADINGS * h - 1 - rows], axis=1).astype(np.float64),
        blocked=np.tile(world.blocked, N_HEADINGS), places=dict(world.places),
        reward_sd=world.reward_sd,
    )  # fmt: skip


class GridWorldEnv(ChangeableWorld, gym.Env[int, int]):
    """A tabular gridworld; the observation is the state index.

    Description
    -----------
    The agent moves between the cells of a :class:`World` (``docs/paper-settings.md``, "Conventions":
    states numbered row-major from the top-left, ``state = row * width + col``). Moves into a
    wall cell, off the grid or through a wall leave the agent in place. Worlds built with
    ``slip > 0`` are stochastic.

    Action Space
    ------------
    ``Discrete(4)``: 0 = left, 1 = up, 2 = right, 3 = down. With ``actions="egocentric"``
    ``Discrete(3)``: 0 = turn left, 1 = turn right, 2 = forward (the heading is part of the
    state; :class:`EgocentricWorld`).

    Observation Space
    -----------------
    ``Discrete(S)`` with ``S = width * height``: the index of the current state
    (egocentric: ``4 * width * height``, ``heading * width * height + cell``).

    Rewards
    -------
    ``world.rewards[s']`` of the state ``s'`` the agent arrives in; with ``world.reward_sd > 0``
    every non-zero reward gets Gaussian noise drawn from ``np_random`` (positive rewards
    truncated at 0).

    Starting State
    --------------
    One of ``world.starts``, drawn uniformly as ``starts[np_random.integers(0, len(starts))]``
    (drawn even with a single start, so compiled agent kernels can replay the same draws).

    Episode End
    -----------
    Terminated on arriving in a terminal state (``world.terminal``); truncated after
    ``max_steps`` steps (if given).

    Arguments
    ---------
    world : World, optional
        The world (default: the paper's 7 x 7 T-maze, :func:`~cobelrun.envs.world.tmaze_paper`).
        The env works on a copy; ``base_world`` keeps the state at construction.
    max_steps : int, optional
        Steps per episode before truncation (None: no limit).
    render_mode : {"ansi", "rgb_array", None}
        ``"ansi"`` renders the grid as text, ``"rgb_array"`` as a top-down image.
    actions : {"allocentric", "egocentric"}
        The action set: compass moves (default), or turn left / turn right / forward with the
        heading in the state (the world becomes :func:`egocentric` of ``world``: four copies of
        the grid, one per heading, stacked top to bottom, as ``cobel show`` draws it).

    ``info`` (from ``reset`` and ``step``) holds ``state``, ``x`` and ``y`` (egocentric: and
    ``heading``, 0 = up, 1 = right, 2 = down, 3 = left).
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["ansi", "rgb_array"], "render_fps": 4}
    #: pixels per grid cell of ``render_mode="rgb_array"``
    RENDER_CELL_PX = 16

    def __init__(
        self,
        world: World | None = None,
        max_steps: int | None = None,
        render_mode: str | None = None,
        actions: str = "allocentric",
    ) -> None:
        if world is None:
            world = tmaze_paper()
        if not isinstance(world, World):
            raise ConfigError(
                f"world must be a cobelrun World (e.g. _target_: cobelrun.envs.world.tmaze_paper), got {type(world).__name__}"
            )
        if actions not in ACTION_SETS:
            raise ConfigError(
                f"env.actions {actions!r} is not known{suggest(str(actions), ACTION_SETS)}; "
                f"allowed: {allowed_list(ACTION_SETS)}"
            )
        max_steps, render_mode = episode_options(
            max_steps, render_mode, self.metadata["render_modes"]
        )
        if actions == "egocentric":
            world = egocentric(world)
        #: the world's states include the heading (turn / forward actions)
        self.egocentric = isinstance(world, EgocentricWorld)
        self._base_world = world.copy()
        self._world = world.copy()
        self.max_steps = max_steps
        self.render_mode = render_mode
        self.action_space = spaces.Discrete(world.n_actions)
        self.observation_space = self._make_observation_space()
        self._state = int(self._world.starts[0])
        self._heading = START_HEADING
        self._steps = 0

    # ------------------------------------------------------------------ world access
    @property
    def state(self) -> int:
        """The current state index."""
        return self._state

    @property
    def steps(self) -> int:
        """Steps taken in the current episode."""
        return self._steps

    def action_mask(self) -> np.ndarray:
        """(S, A) bool: True where an action has some probability of leaving the state."""
        T = self._world.T
        n = self._world.n_states
        stay = T[np.arange(n), :, np.arange(n)]  # (S, A) probability of staying
        return stay < 1.0

    # ------------------------------------------------------------------ gymnasium API
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Start an episode in a uniformly drawn start state."""
        super().reset(seed=seed)
        starts = self._world.starts
        self._state = int(starts[self.np_random.integers(0, len(starts))])
        self._heading = START_HEADING
        self._steps = 0
        return self._observe(self._state), self._info(self._state)

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        """Take one action; returns ``(obs, reward, terminated, truncated, info)``."""
        a = self._check_action(action)
        world = self._world
        s = self._state
        ns = world.next_state
        if ns is not None:
            s2 = int(ns[s, a])
        else:
            u = self.np_random.random()
            cum = np.cumsum(world.T[s, a])
            s2 = min(int(np.searchsorted(cum, u, side="right")), world.n_states - 1)
        self._state = s2
        self._heading = self._heading_after(s2, a)
        self._steps += 1
        reward = float(world.rewards[s2])
        if world.reward_sd > 0.0 and reward != 0.0:  # Mattar & Daw's noisy reward
            noisy = reward + world.reward_sd * float(self.np_random.standard_normal())
            reward = max(0.0, noisy) if reward > 0.0 else noisy
        terminated = bool(world.terminal[s2])
        truncated = self.max_steps is not None and self._steps >= self.max_steps
        return self._observe(s2), reward, terminated, truncated, self._info(s2)

    def _heading_after(self, s2: int, a: int) -> float:
        if self.egocentric:
            return float(HEADING_ANGLE[s2 // self._world.n_cells])
        return float(ACTION_HEADING[a])

    def render(self) -> str | np.ndarray | None:
        """``render_mode="ansi"``: the grid as text (``A`` agent, or egocentric ``^ > v <``
        by heading, ``#`` wall, ``G`` rewarded terminal, ``E`` other terminal, ``+`` rewarded
        state). ``render_mode="rgb_array"``: a
        top-down image (height x 16, width x 16, 3) uint8 in the same colours as ``cobel show``
        (walls dark, rewarded terminal gold, other terminal pink, rewarded state green, agent
        a blue disc), row 0 at the top as in the text."""
        if self.render_mode == "rgb_array":
            return self._render_rgb()
        if self.render_mode != "ansi":
            return None
        w = self._world
        chars = []
        for s in range(w.n_states):
            if s == self._state:
                ch = "^>v<"[s // w.n_cells] if self.egocentric else "A"
            elif w.blocked[s]:
                ch = "#"
            elif w.terminal[s]:
                ch = "G" if w.rewards[s] != 0 else "E"
            elif w.rewards[s] != 0:
                ch = "+"
            else:
                ch = "."
            chars.append(ch)
        rows = ["".join(chars[r * w.width : (r + 1) * w.width]) for r in range(w.height)]
        return "\n".join(rows) + "\n"

    def _render_rgb(self) -> np.ndarray:
        w = self._world
        px = self.RENDER_CELL_PX
        colour = np.full((w.n_states, 3), 242, np.uint8)
        colour[(w.rewards != 0) & ~w.terminal] = (200, 235, 200)
        colour[w.terminal & (w.rewards != 0)] = (250, 200, 60)
        colour[w.terminal & (w.rewards == 0)] = (240, 190, 190)
        colour[w.blocked] = (40, 40, 40)
        img = np.repeat(np.repeat(colour.reshape(w.height, w.width, 3), px, 0), px, 1)
        img[::px, :] = img[:, ::px] = 200  # cell borders
        img[w.blocked.reshape(w.height, w.width).repeat(px, 0).repeat(px, 1)] = 40
        r, c = divmod(int(self._state), w.width)
        yy, xx = np.mgrid[0:px, 0:px]
        disc = (yy - (px - 1) / 2) ** 2 + (xx - (px - 1) / 2) ** 2 <= (0.35 * px) ** 2
        img[r * px : (r + 1) * px, c * px : (c + 1) * px][disc] = (30, 90, 200)
        return img

    # ------------------------------------------------------------------ contracts
    def agent_pose(self) -> np.ndarray:
        """``(x, y, heading)``: the cell's coordinates and the direction of the last move
        (facing up, pi/2, at trial start)."""
        x, y = self._world.coords[self._state]
        return np.array([x, y, self._heading])

    def poses_of(self, states: np.ndarray, actions: np.ndarray | None = None) -> np.ndarray:
        """(k, 3) poses of ``states``; the heading is the compass direction of the action that
        led there (``-1`` or no actions: facing up)."""
        states = np.asarray(states, np.int64)
        out = np.empty((states.shape[0], 3))
        out[:, :2] = self._world.coords[states]
        if self.egocentric:  # the heading is the state's
            out[:, 2] = HEADING_ANGLE[states // self._world.n_cells]
            return out
        acts = np.full(states.shape, -1) if actions is None else actions
        out[:, 2] = headings_of_moves(acts, ACTION_HEADING, START_HEADING)
        return out

    def geometry(self) -> Geometry:
        """The grid as data: free cells, a wall segment wherever a move is blocked (outer
        walls, wall cells, two-way walls), one-way doors on their own (``doors``: the segment
        and the direction it can be passed), places and starts."""
        w = self._world
        free = np.flatnonzero(~w.blocked)
        xy = w.coords[free]
        intended = np.argmax(w.T[free], axis=2)  # (k, A): the move's main outcome
        stays = intended == free[:, None]
        if self.egocentric:  # each heading's copy: the walls a forward move meets in any copy
            S = w.n_cells
            cell, heading = free % S, free // S
            blocked_dir = np.zeros((S, len(ALLOCENTRIC_ACTIONS)), bool)
            blocked_dir[cell, HEADING_MOVE[heading]] = stays[:, 2]
            stays = blocked_dir[cell]
        # wall side of each action (left, up, right, down) relative to the cell centre
        side = np.array([[-0.5, -0.5, -0.5, 0.5], [-0.5, 0.5, 0.5, 0.5],
                         [0.5, -0.5, 0.5, 0.5], [-0.5, -0.5, 0.5, -0.5]])  # fmt: skip
        k, a = np.nonzero(stays)
        segs = np.round(np.tile(xy[k], 2) + side[a], 9)
        # a blocked move whose reverse passes is a one-way door: passable towards this cell
        move = np.array([[-1.0, 0.0], [0.0, 1.0], [1.0, 0.0], [0.0, -1.0]])  # world x, y
        index = {(float(x), float(y)): i for i, (x, y) in enumerate(xy.tolist())}
        door = np.zeros(len(k), bool)
        if self.egocentric:  # where a forward move facing each way leads, per cell
            S = w.n_cells
            forward = np.argmax(w.T[:, 2], axis=1) % S
            allo = np.empty((S, len(ALLOCENTRIC_ACTIONS)), np.int64)
            for h, d in enumerate(HEADING_MOVE):
                allo[:, d] = forward[h * S : (h + 1) * S]
        for j, (kk, aa) in enumerate(zip(k.tolist(), a.tolist(), strict=True)):
            nb = index.get(tuple((xy[kk] + move[aa]).tolist()))
            if nb is None:
                continue
            if self.egocentric:
                door[j] = allo[free[nb] % S, (aa + 2) % 4] == free[kk] % S
            else:
                door[j] = intended[nb, (aa + 2) % 4] == free[kk]
        doors = np.hstack([segs[door], 0.0 - move[a[door]]]) if door.any() else np.zeros((0, 6))
        segs = segs[~door]
        segs = np.unique(segs, axis=0) if segs.size else segs
        lo, hi = xy.min(axis=0) - 0.5, xy.max(axis=0) + 0.5
        return Geometry(kind="grid", bounds=(lo[0], lo[1], hi[0], hi[1]), walls=segs, cells=xy,
                        nodes=xy, regions=self._place_regions(), doors=doors)  # fmt: skip

    # ------------------------------------------------------------------ hooks for subclasses
    def _make_observation_space(self) -> spaces.Space:
        return spaces.Discrete(self._world.n_states)

    def _observe(self, s: int) -> Any:
        return int(s)

    def _info(self, s: int) -> dict[str, Any]:
        x, y = self._world.coords[s]
        if self.egocentric:
            return {"state": int(s), "x": float(x), "y": float(y),
                    "heading": int(s // self._world.n_cells)}  # fmt: skip
        return {"state": int(s), "x": float(x), "y": float(y)}

    def _check_action(self, action: Any) -> int:
        names = EGOCENTRIC_ACTIONS if self.egocentric else ALLOCENTRIC_ACTIONS
        return check_action(action, self._world.n_actions, names)


class DiscreteGridWorldEnv(GridWorldEnv):
    """A tabular gridworld with a feature vector per state (one-hot by default).

    Description
    -----------
    Same dynamics as :class:`GridWorldEnv`; the agent observes ``observations[s]`` instead of
    the state index (e.g. for deep agents such as Dyna-DSR on one-hot inputs, docs/paper-settings.md Fig. 7).

    Action Space
    ------------
    ``Discrete(4)``: 0 = left, 1 = up, 2 = right, 3 = down.

    Observation Space
    -----------------
    ``Box(low=min, high=max, shape=(d,), float32)`` over the rows of ``observations``.

    Rewards
    -------
    ``world.rewards[s']`` of the state ``s'`` the agent arrives in.

    Starting State
    --------------
    As :class:`GridWorldEnv`: ``starts[np_random.integers(0, len(starts))]``.

    Episode End
    -----------
    Terminal state reached, or ``max_steps`` steps (truncation).

    Arguments
    ---------
    world : World, optional
        The world (default: the paper's 7 x 7 T-maze).
    max_steps : int, optional
        Steps per episode before truncation.
    render_mode : {"ansi", "rgb_array", None}
        Text rendering.
    observations : (S, d) array, "onehot" or "coords", optional
        Observation of each state. Default ``"onehot"`` (identity, ``d = S``); ``"coords"`` gives
        the ``(x, y)`` cell coordinates.

    ``info`` holds ``state`` (the state index), ``x`` and ``y``.
    """

    OBSERVATION_KINDS: ClassVar[tuple[str, ...]] = ("onehot", "coords")

    def __init__(
        self,
        world: World | None = None,
        max_steps: int | None = None,
        render_mode: str | None = None,
        observations: np.ndarray | str | None = None,
    ) -> None:
        if world is None:
            world = tmaze_paper()
        self.observations = self._build_observations(world, observations)
        super().__init__(world=world, max_steps=max_steps, render_mode=render_mode)

    @classmethod
    def _build_observations(cls, world: Any, observations: Any) -> np.ndarray:
        n = world.n_states if isinstance(world, World) else 0
        if observations is None:
            observations = "onehot"
        if isinstance(observations, str):
            if observations == "onehot":
                obs = np.eye(n, dtype=np.float32)
            elif observations == "coords":
                obs = world.coords.astype(np.float32)
            else:
                raise ConfigError(
                    f"observations {observations!r} is unknown{suggest(observations, cls.OBSERVATION_KINDS)}; "
                    f"allowed: {allowed_list(cls.OBSERVATION_KINDS)} or an (S, d) array"
                )
        else:
            try:
                obs = np.array(observations, dtype=np.float32)
            except (TypeError, ValueError):
                raise ConfigError(
                    "observations must be an (S, d) array of numbers, 'onehot' or 'coords'"
                ) from None
            if obs.ndim != 2 or obs.shape[0] != n or obs.shape[1] < 1:
                raise ConfigError(
                    f"observations must have shape (S={n}, d), got {obs.shape}; one row per state"
                )
            if not np.all(np.isfinite(obs)):
                raise ConfigError("observations must be finite numbers")
        obs.setflags(write=False)
        return obs

    def _make_observation_space(self) -> spaces.Space:
        obs = self.observations
        return spaces.Box(
            low=float(obs.min()), high=float(obs.max()), shape=(obs.shape[1],), dtype=np.float32
        )

    def _observe(self, s: int) -> np.ndarray:
        return self.observations[s].copy()
