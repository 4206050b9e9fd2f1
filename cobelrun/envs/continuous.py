"""A continuous 2D arena (the paper's 2D interface) and the Morris water maze built on it."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from cobelrun.envs.arena import Arena, Shape, points_in_polygon
from cobelrun.envs.base import Geometry, check_action, episode_options
from cobelrun.envs.cells import CameraView, SpatialCode, build_observation
from cobelrun.envs.raycast import move_kernel
from cobelrun.errors import ConfigError, allowed_list, suggest
from cobelrun.safety import check_allocation

MOVEMENTS = ("directions", "differential", "continuous")
START_ORDERS = ("random", "shuffled")
#: distance (world units) kept from a wall when a move is stopped by it
WALL_MARGIN = 1e-6


def arc_step(heading: float, v: float, omega: float, dt: float) -> tuple[float, float, float]:
    """Exact displacement ``(dx, dy)`` and new heading of a unicycle / differential-drive
    robot moving at speed ``v`` and turn rate ``omega`` for ``dt`` (a circular arc)."""
    if abs(omega) < 1e-12:
        return v * dt * np.cos(heading), v * dt * np.sin(heading), heading
    h2 = heading + omega * dt
    r = v / omega
    return r * (np.sin(h2) - np.sin(heading)), -r * (np.cos(h2) - np.cos(heading)), h2


def wrap_angle(a: float) -> float:
    """Angle in [-pi, pi)."""
    return (a + np.pi) % (2 * np.pi) - np.pi


class Continuous2DEnv(gym.Env[np.ndarray, Any]):
    """An agent moving in a continuous 2D arena with walls, goals and a spatial-cell code.

    Description
    -----------
    The paper's 2D interface (docs/paper-settings.md): the agent has a continuous position and a heading in
    an arena whose outline is any polygon or circle, with internal walls/obstacles as polygons
    or circles (:class:`~cobelrun.envs.arena.Arena`). Moves that would cross a wall stop just
    before it (and can cost ``wall_penalty``). Goals are circular or polygonal regions.
    Geometry is checked with shapely once; the step itself is a compiled segment-intersection
    kernel over precomputed wall segments.

    Action Space
    ------------
    ``movement="directions"``: ``Discrete(n_directions)``, move ``speed * dt`` in the
    allocentric direction ``2 pi k / n`` (counter-clockwise from +x: 4 gives east, north,
    west, south, the paper's cardinal moves; 8 adds the diagonals, Foster et al. 2000); the
    heading becomes the direction moved. ``movement="differential"``: ``Discrete(len(wheels))``
    (default 3: forward, turn left, turn right), each action a pair of wheel speeds
    ``(v_left, v_right)`` in units of ``wheel_speed``; the robot moves with ``v = (v_l + v_r) / 2``
    and ``omega = (v_r - v_l) / axle_length`` along the exact arc. ``movement="continuous"``:
    ``Box(-1, 1, (2,), float32)``: forward speed ``a[0] * max_speed`` and turn rate
    ``a[1] * max_turn`` for ``dt`` (the same arc kinematics).

    Observation Space
    -----------------
    ``Box(float32)``: the concatenation of the configured observation parts
    (:mod:`cobelrun.envs.cells`): ``pose`` ``(x, y, cos h, sin h)``, place cells, grid cells,
    boundary-vector cells, head-direction cells.

    Rewards
    -------
    ``goal.reward`` for each step that ends inside a goal region (rewards and terminal flags
    change with protocol phases through :meth:`apply_changes`), plus ``wall_penalty`` (usually
    negative) on a step stopped by a wall, plus ``step_reward`` on every step.

    Starting State
    --------------
    A start point: ``start_order="random"`` draws one uniformly each episode;
    ``"shuffled"`` goes through the start points in a random order, reshuffled after each
    block (Morris water maze days: each cardinal point once per day). ``starts="random"``
    draws a point uniformly in the free space. Heading: ``start_heading`` degrees, ``"random"``,
    or ``"centre"`` (facing the arena's centre).

    Episode End
    -----------
    Terminated when a step ends inside a terminal goal region; truncated after ``max_steps``
    steps (if given).

    Arguments
    ---------
    arena : mapping, optional
        Outline shape (default the unit square; e.g. ``{shape: circle, x: 0, y: 0, radius: 1}``).
    obstacles : list of mappings, optional
        Internal walls and obstacles (polygons, rectangles, circles).
    goals : mapping name -> region, optional
        Goal regions ``{shape, ..., reward: 1.0, terminal: true}``.
    starts : mapping name -> [x, y], list of [x, y] or "random", optional
        Start points (default the arena's centre).
    start_order : {"random", "shuffled"}
    start_heading : float, "random" or "centre"
    movement : {"directions", "differential", "continuous"}
    n_directions : int
        Allocentric directions (``movement="directions"``), default 4.
    speed : float
        Swim/run speed in world units per second (directions mode), default 0.15.
    dt : float
        Seconds per step, default 0.1 (so a step is 0.015, the paper's 2D interface).
    wheel_speed, axle_length : float
        Differential drive: wheel speed unit (units/s) and wheel separation (units).
    wheels : list of [v_left, v_right], optional
        Differential-drive actions (default ``[[1, 1], [-1, 1], [1, -1]]``).
    max_speed, max_turn : float
        Continuous mode: speed (units/s) and turn rate (rad/s) at action +-1.
    wall_penalty, step_reward : float
        Added on a wall hit / on every step.
    observation : list of mappings, optional
        Observation parts (default ``[{kind: pose}]``); see :func:`~cobelrun.envs.cells.build_observation`.
    max_steps : int, optional
        Truncation limit.
    resolution : int
        Sides of the polygon standing in for a circle in collisions (default 128).
    render_mode : {"rgb_array", None}
        ``"rgb_array"``: :meth:`render` returns the agent's first-person view of the 3D
        pybullet scene of the arena.
    camera, scene : mapping, optional
        :class:`~cobelrun.render.scene.CameraSpec` (height, width, fov, eye_height, ...) and
        :class:`~cobelrun.render.scene.SceneStyle` (wall colours, cues, lighting) of that view.

    ``info`` holds ``state`` (the index of the goal region the agent is in, -1 outside all),
    ``x``, ``y``, ``heading`` and ``collision``.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        arena: Mapping[str, Any] | None = None,
        obstacles: Sequence[Mapping[str, Any]] | None = None,
        goals: Mapping[str, Mapping[str, Any]] | None = None,
        starts: Any = None,
        start_order: str = "random",
        start_heading: float | str = "centre",
        movement: str = "directions",
        n_directions: int = 4,
        speed: float = 0.15,
        dt: float = 0.1,
        wheel_speed: float = 0.15,
        axle_length: float = 0.1,
        wheels: Sequence[Sequence[float]] | None = None,
        max_speed: float = 0.3,
        max_turn: float = np.pi,
        wall_penalty: float = 0.0,
        step_reward: float = 0.0,
        observation: Sequence[Mapping[str, Any]] | None = None,
        max_steps: int | None = None,
        resolution: int = 128,
        render_mode: str | None = None,
        camera: Mapping[str, Any] | None = None,
        scene: Mapping[str, Any] | None = None,
    ) -> None:
        self.arena = Arena(arena, obstacles, goals, starts, resolution)
        self._base_goals = {k: (g.shape, g.reward, g.terminal) for k, g in self.arena.goals.items()}
        if movement not in MOVEMENTS:
            raise ConfigError(
                f"movement {movement!r} is unknown{suggest(str(movement), MOVEMENTS)}; "
                f"allowed: {allowed_list(MOVEMENTS)}"
            )
        if start_order not in START_ORDERS:
            raise ConfigError(
                f"start_order {start_order!r} is unknown{suggest(str(start_order), START_ORDERS)}; "
                f"allowed: {allowed_list(START_ORDERS)}"
            )
        self.movement = movement
        self.start_order = start_order
        self.dt = _positive("dt", dt)
        self.speed = _positive("speed", speed)
        self.wheel_speed = _positive("wheel_speed", wheel_speed)
        self.axle_length = _positive("axle_length", axle_length)
        self.max_speed = _positive("max_speed", max_speed)
        self.max_turn = _positive("max_turn", max_turn)
        self.wall_penalty = _finite("wall_penalty", wall_penalty)
        self.step_reward = _finite("step_reward", step_reward)
        if isinstance(start_heading, str):
            if start_heading not in ("random", "centre"):
                raise ConfigError(
                    f"start_heading must be an angle in degrees, 'random' or 'centre', got {start_heading!r}"
                )
            self._start_heading: float | str = start_heading
        else:
            self._start_heading = np.deg2rad(_finite("start_heading", start_heading))
        self.max_steps, self.render_mode = episode_options(
            max_steps, render_mode, self.metadata["render_modes"]
        )
        from cobelrun.render.scene import CameraSpec, SceneStyle  # plain data, no pybullet

        try:
            self.camera = CameraSpec(**dict(camera or {}))
        except TypeError as exc:
            raise ConfigError(f"camera: {exc}".replace("__init__() ", "")) from None
        self.scene_style = SceneStyle.from_config(scene)
        self._scene: Any = None

        if movement == "directions":
            if (
                isinstance(n_directions, bool)
                or not isinstance(n_directions, int)
                or n_directions < 2
            ):
                raise ConfigError(f"n_directions must be an integer >= 2, got {n_directions!r}")
            check_allocation("env.n_directions", n_directions * 128,
                             f"{n_directions:,} movement directions (their angles, names and "
                             "an agent's values for each)", "lower env.n_directions")  # fmt: skip
            self.directions = 2 * np.pi * np.arange(n_directions) / n_directions
            self.action_space: spaces.Space = spaces.Discrete(n_directions)
            self.action_names = tuple(_compass(a) for a in self.directions)
        elif movement == "differential":
            w = np.array([[1, 1], [-1, 1], [1, -1]] if wheels is None else wheels, np.float64)
            if w.ndim != 2 or w.shape[1] != 2 or len(w) < 1 or not np.isfinite(w).all():
                raise ConfigError("wheels must be a list of [v_left, v_right] pairs")
            self.wheels = w * self.wheel_speed
            self.action_space = spaces.Discrete(len(w))
            default = ("forward", "left", "right")
            self.action_names = default if wheels is None else tuple(f"wheels{list(p)}" for p in w)
        else:
            self.action_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
            self.action_names = ("speed", "turn")

        self._n_actions = int(getattr(self.action_space, "n", 0))
        self.walls = self.arena.wall_segments()
        self.observation_parts: list[SpatialCode] = build_observation(observation, self.arena)
        for part in self.observation_parts:
            if isinstance(part, CameraView):  # the 3D view through the scene renderer
                part.attach(self.view_at_pose, self.camera.height, self.camera.width)
        dim = sum(p.n for p in self.observation_parts)
        lows = np.concatenate([p.low for p in self.observation_parts])
        highs = np.concatenate([p.high for p in self.observation_parts])
        self.observation_space = spaces.Box(lows.astype(np.float32), highs.astype(np.float32),
                                            shape=(dim,), dtype=np.float32)  # fmt: skip
        self._obs = np.zeros(dim, np.float32)
        self._start_names = list(self.arena.starts)
        self._start_xy = np.stack([self.arena.starts[k] for k in self._start_names])
        self._base_starts = self._start_xy.copy(), list(self._start_names)
        self._queue: list[int] = []
        self._refresh_goals()
        self._x, self._y = (float(v) for v in self._start_xy[0])
        self._heading = 0.0
        self._steps = 0

    # ------------------------------------------------------------------ goals as arrays
    def _refresh_goals(self) -> None:
        goals = list(self.arena.goals.values())
        self.goal_names = [g.name for g in goals]
        self._goal_reward = np.array([g.reward for g in goals], np.float64)
        self._goal_terminal = np.array([g.terminal for g in goals], bool)
        self._goal_circle = [(g.shape.x, g.shape.y, g.shape.radius ** 2)
                             if g.shape.kind == "circle" else None for g in goals]  # fmt: skip
        self._goal_poly = [g.shape.points for g in goals]

    def goal_at(self, x: float, y: float) -> int:
        """Index of the first goal region containing ``(x, y)``, -1 for none."""
        for i, c in enumerate(self._goal_circle):
            if c is not None:
                if (x - c[0]) ** 2 + (y - c[1]) ** 2 <= c[2]:
                    return i
            elif points_in_polygon(np.array([[x, y]]), self._goal_poly[i])[0]:
                return i
        return -1

    # ------------------------------------------------------------------ Changeable
    def apply_changes(
        self,
        rewards: Mapping[Any, float] | None = None,
        terminals: Mapping[Any, bool] | None = None,
        starts: Iterable[Any] | None = None,
    ) -> None:
        """Change goal rewards and terminal flags (by goal name) or the start points.

        Parameters
        ----------
        rewards : mapping goal name -> float, optional
        terminals : mapping goal name -> bool, optional
            ``{platform: false}`` with ``rewards {platform: 0}`` removes a hidden platform
            (a probe trial); a second goal region switched on moves it (reversal).
        starts : list of start names or [x, y] points, optional
        """
        for mapping, what in ((rewards, "rewards"), (terminals, "terminals")):
            for name, value in (mapping or {}).items():
                goal = self._goal(name, what)
                if what == "rewards":
                    goal.reward = _finite(f"rewards.{name}", value)
                else:
                    if not isinstance(value, bool):
                        raise ConfigError(f"terminals.{name} must be true or false, got {value!r}")
                    goal.terminal = value
        if starts is not None:
            names, points = [], []
            for ref in starts:
                if isinstance(ref, str):
                    if ref not in self.arena.starts:
                        known = list(self.arena.starts)
                        raise ConfigError(
                            f"unknown start {ref!r}{suggest(ref, known)}; known: {allowed_list(known)}"
                        )
                    names.append(ref)
                    points.append(self.arena.starts[ref])
                else:
                    xy = np.array(ref, np.float64).reshape(2)
                    self.arena.check_free(f"start {xy.tolist()}", xy)
                    names.append(f"({xy[0]:g}, {xy[1]:g})")
                    points.append(xy)
            if not names:
                raise ConfigError("starts must name at least one start point")
            self._start_names, self._start_xy = names, np.stack(points)
            self._queue = []
        self._refresh_goals()

    def _goal(self, name: Any, what: str) -> Any:
        if name not in self.arena.goals:
            known = list(self.arena.goals)
            raise ConfigError(
                f"{what}: unknown goal {name!r}{suggest(str(name), known)}; known: {allowed_list(known)}"
            )
        return self.arena.goals[name]

    def reset_world(self) -> None:
        """Restore goals and starts as built (undo every :meth:`apply_changes`)."""
        for name, (shape, reward, terminal) in self._base_goals.items():
            g = self.arena.goals[name]
            g.shape, g.reward, g.terminal = shape, reward, terminal
        self._start_xy, self._start_names = self._base_starts[0].copy(), list(self._base_starts[1])
        self._queue = []
        self._refresh_goals()

    # ------------------------------------------------------------------ Posed / geometry
    def agent_pose(self) -> np.ndarray:
        """``(x, y, heading)`` in world units and radians (CCW from +x)."""
        return np.array([self._x, self._y, self._heading])

    def geometry(self) -> Geometry:
        """The arena as data: outline polygon, wall segments, goal regions and start points."""
        regions: dict[str, dict[str, Any]] = {}
        for name, g in self.arena.goals.items():
            regions[name] = {**g.shape.region(), "reward": g.reward, "terminal": g.terminal}
        for name, xy in zip(self._start_names, self._start_xy, strict=True):
            regions.setdefault(
                f"start_{name}", {"shape": "point", "x": float(xy[0]), "y": float(xy[1])}
            )
        return Geometry(kind="arena", bounds=self.arena.bounds, walls=self.walls,
                        outline=self.arena.outline.polygon(self.arena.resolution),
                        regions=regions)  # fmt: skip

    def render_at_pose(self, x: float, y: float, heading: float) -> np.ndarray:
        """The observation the agent would get at pose ``(x, y, heading)``."""
        return self._observe(float(x), float(y), float(heading)).copy()

    def view_at_pose(self, x: float, y: float, heading: float) -> np.ndarray:
        """The first-person RGB view ``(h, w, 3)`` uint8 at a pose: the 3D pybullet scene of
        the arena (walls coloured by the direction they face, distal cues, no visible goals),
        rendered with the camera given as ``camera`` (imports pybullet on first use)."""
        if self._scene is None:
            from cobelrun.render.scene import Scene, SceneSpec

            self._scene = Scene(SceneSpec.from_geometry(self.geometry(), self.scene_style))
        return self._scene.render(float(x), float(y), float(heading), self.camera)

    def render(self) -> np.ndarray | None:
        """The agent's first-person view (``render_mode="rgb_array"``, :meth:`view_at_pose`)."""
        if self.render_mode != "rgb_array":
            return None
        return self.view_at_pose(self._x, self._y, self._heading)

    def close(self) -> None:
        if self._scene is not None:
            self._scene.close()
            self._scene = None
        super().close()

    @property
    def steps(self) -> int:
        return self._steps

    # ------------------------------------------------------------------ gymnasium API
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode at a start point (see Starting State)."""
        super().reset(seed=seed)
        if seed is not None:
            self._queue = []
        if self.arena.random_starts:
            x, y = self.arena.sample_free(self.np_random)[0]
        else:
            if self.start_order == "random":
                k = int(self.np_random.integers(0, len(self._start_names)))
            else:
                if not self._queue:
                    self._queue = [
                        int(i) for i in self.np_random.permutation(len(self._start_names))
                    ]
                k = self._queue.pop(0)
            x, y = self._start_xy[k]
        self._x, self._y = float(x), float(y)
        if self._start_heading == "random":
            self._heading = float(self.np_random.uniform(-np.pi, np.pi))
        elif self._start_heading == "centre":
            c = self.arena.outline.centre
            dx, dy = c[0] - self._x, c[1] - self._y
            self._heading = float(np.arctan2(dy, dx)) if dx * dx + dy * dy > 1e-18 else 0.0
        else:
            self._heading = float(self._start_heading)
        self._steps = 0
        obs = self._observe(self._x, self._y, self._heading).copy()
        return obs, self._info(self.goal_at(self._x, self._y), False)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Move by one action; returns ``(obs, reward, terminated, truncated, info)``."""
        h = self._heading
        if self.movement == "directions":
            a = self._action_index(action)
            h = float(self.directions[a])
            d = self.speed * self.dt
            dx, dy = d * np.cos(h), d * np.sin(h)
        elif self.movement == "differential":
            a = self._action_index(action)
            vl, vr = self.wheels[a]
            dx, dy, h = arc_step(h, 0.5 * (vl + vr), (vr - vl) / self.axle_length, self.dt)
        else:
            act = np.asarray(action, np.float64).reshape(-1)
            if act.shape != (2,) or not np.isfinite(act).all():
                raise ValueError(
                    f"invalid action {action!r}; allowed: 2 numbers in [-1, 1] (speed, turn)"
                )
            act = np.clip(act, -1.0, 1.0)
            dx, dy, h = arc_step(h, act[0] * self.max_speed, act[1] * self.max_turn, self.dt)
        x, y, hit = move_kernel(self._x, self._y, dx, dy, self.walls, WALL_MARGIN)
        self._x, self._y, self._heading = x, y, wrap_angle(h)
        self._steps += 1
        g = self.goal_at(x, y)
        reward = self.step_reward + (self.wall_penalty if hit else 0.0)
        terminated = False
        if g >= 0:
            reward += float(self._goal_reward[g])
            terminated = bool(self._goal_terminal[g])
        truncated = self.max_steps is not None and self._steps >= self.max_steps
        obs = self._observe(x, y, self._heading).copy()
        return obs, float(reward), terminated, bool(truncated), self._info(g, hit)

    def _action_index(self, action: Any) -> int:
        n = self._n_actions
        if type(action) is int and 0 <= action < n:  # the common case, checked cheaply
            return action
        return check_action(action, n, self.action_names)

    def _observe(self, x: float, y: float, heading: float) -> np.ndarray:
        i = 0
        for part in self.observation_parts:
            part.write(x, y, heading, self._obs[i : i + part.n])
            i += part.n
        return self._obs

    def _info(self, goal: int, hit: bool) -> dict[str, Any]:
        return {"state": goal, "x": self._x, "y": self._y, "heading": self._heading,
                "collision": bool(hit)}  # fmt: skip


def _positive(name: str, value: Any) -> float:
    v = _finite(name, value)
    if v <= 0:
        raise ConfigError(f"{name} must be > 0, got {value!r}")
    return v


def _finite(name: str, value: Any) -> float:
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float | np.number)
        or not np.isfinite(value)
    ):
        raise ConfigError(f"{name} must be a finite number, got {value!r}")
    return float(value)


def _compass(angle: float) -> str:
    names = {0: "E", 45: "NE", 90: "N", 135: "NW", 180: "W", 225: "SW", 270: "S", 315: "SE"}
    deg = round(float(np.rad2deg(angle)), 6)
    return names.get(int(deg), f"{deg:g}deg") if float(deg).is_integer() else f"{deg:g}deg"


__all__ = ["Continuous2DEnv", "Shape", "arc_step", "move_kernel"]
