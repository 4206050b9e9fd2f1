"""Continuous 2D arenas: env checker, kinematics, collisions, goals and phases, bad input,
spatial cells against RatInABox, water-maze analyses and the actor-critic agent."""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from cobelrun.analysis import watermaze as wm
from cobelrun.envs import Continuous2DEnv
from cobelrun.envs.base import capabilities
from cobelrun.envs.cells import (
    BoundaryVectorCells,
    GridCells,
    HeadDirectionCells,
    PlaceCells,
    halton,
)
from cobelrun.errors import ConfigError

POOL = {"shape": "circle", "x": 0.0, "y": 0.0, "radius": 1.0}
PLATFORM = {"shape": "circle", "x": 0.42, "y": 0.42, "radius": 0.05}
CARDINAL = {"north": [0.0, 0.95], "east": [0.95, 0.0], "south": [0.0, -0.95], "west": [-0.95, 0.0]}


def pool(**kw):
    args = dict(arena=POOL, goals={"platform": PLATFORM}, starts=CARDINAL, n_directions=8,
                speed=0.3, dt=0.1, observation=[{"kind": "place_cells", "n": 50, "sigma": 0.16}])  # fmt: skip
    args.update(kw)
    return Continuous2DEnv(**args)


# ---------------------------------------------------------------------------- conformance
@pytest.mark.parametrize("movement", ["directions", "differential", "continuous"])
def test_check_env_every_movement(movement):
    obs = [{"kind": "pose"}, {"kind": "place_cells", "n": 20}, {"kind": "grid_cells", "n": 6},
           {"kind": "boundary_vector_cells", "n": 5}, {"kind": "head_direction", "n": 4}]  # fmt: skip
    env = Continuous2DEnv(movement=movement, observation=obs,
                          obstacles=[{"shape": "rectangle", "x0": 0.4, "y0": 0.4, "x1": 0.6, "y1": 0.6}],
                          goals={"goal": {"shape": "circle", "x": 0.9, "y": 0.9, "radius": 0.08}},
                          starts={"a": [0.1, 0.1]})  # fmt: skip
    check_env(env, skip_render_check=True)
    assert env.observation_space.shape == (4 + 20 + 6 + 5 + 4,)
    assert {"changeable", "pose", "geometry", "render_at_pose"} <= set(capabilities(env))


def test_registered_and_seeded_rollouts_identical():
    def roll(seed):
        env = gym.make("cobel/Continuous2D-v0", arena=POOL, goals={"p": PLATFORM}, starts=CARDINAL,
                       start_order="shuffled", start_heading="random", n_directions=8)  # fmt: skip
        rng = np.random.default_rng(seed)
        obs, _ = env.reset(seed=seed)
        out = [obs.tolist()]
        for _ in range(300):
            obs, r, term, trunc, info = env.step(int(rng.integers(8)))
            out.append((obs.tolist(), r, term, info["x"], info["y"]))
            if term or trunc:
                out.append(env.reset()[0].tolist())
        return out

    assert roll(3) == roll(3)
    assert roll(3) != roll(4)


# ---------------------------------------------------------------------------- kinematics
def test_allocentric_moves_step_and_heading():
    env = Continuous2DEnv(starts={"c": [0.5, 0.5]})  # unit square, 4 moves of 0.015
    env.reset(seed=0)
    for a, (dx, dy) in enumerate([(1, 0), (0, 1), (-1, 0), (0, -1)]):
        before = env.agent_pose()
        env.step(a)
        after = env.agent_pose()
        np.testing.assert_allclose(after[:2] - before[:2], 0.015 * np.array([dx, dy]), atol=1e-12)
        assert np.isclose(np.cos(after[2]), dx) and np.isclose(np.sin(after[2]), dy)
    assert pool().action_names == ("E", "NE", "N", "NW", "W", "SW", "S", "SE")


def _integrate(x, y, h, v, w, dt, n=100_000):
    """Unicycle kinematics by many small Euler steps."""
    ddt = dt / n
    for _ in range(n // 1000):  # vectorised chunks keep this fast
        hs = h + w * ddt * np.arange(1000)
        x += np.sum(v * np.cos(hs)) * ddt
        y += np.sum(v * np.sin(hs)) * ddt
        h += w * ddt * 1000
    return x, y, h


def test_differential_drive_wheel_kinematics():
    wheels = [[1, 1], [-1, 1], [1, -1], [0.5, 1.0]]
    env = Continuous2DEnv(movement="differential", wheels=wheels, wheel_speed=0.2,
                          axle_length=0.1, dt=0.1, starts={"c": [0.5, 0.5]}, start_heading=30.0)  # fmt: skip
    env.reset(seed=0)
    x0, y0, h0 = env.agent_pose()
    env.step(0)  # forward: 0.2 m/s for 0.1 s along the heading
    x1, y1, h1 = env.agent_pose()
    np.testing.assert_allclose(
        [x1 - x0, y1 - y0], 0.02 * np.array([np.cos(h0), np.sin(h0)]), atol=1e-12
    )
    assert h1 == pytest.approx(h0)
    env.step(1)  # turn left in place: omega = (0.2 + 0.2) / 0.1 = 4 rad/s for 0.1 s
    x2, y2, h2 = env.agent_pose()
    assert (x2, y2) == pytest.approx((x1, y1)) and h2 == pytest.approx(h1 + 0.4)
    env.step(2)
    assert env.agent_pose()[2] == pytest.approx(h1)
    # an arc: v = 0.15, omega = 1 rad/s; the exact arc matches fine-grained integration
    x3, y3, h3 = env.agent_pose()
    env.step(3)
    ref = _integrate(x3, y3, h3, 0.15, 1.0, 0.1)
    np.testing.assert_allclose(env.agent_pose(), ref, atol=1e-7)


def test_continuous_action_is_clipped_and_checked():
    env = Continuous2DEnv(movement="continuous", max_speed=0.3, max_turn=np.pi,
                          starts={"c": [0.5, 0.5]}, start_heading=0.0)  # fmt: skip
    env.reset(seed=0)
    env.step(np.array([2.0, 0.0], np.float32))  # clipped to full speed
    assert env.agent_pose()[0] == pytest.approx(0.53)
    with pytest.raises(ValueError, match="speed, turn"):
        env.step(np.array([np.nan, 0.0]))


# ---------------------------------------------------------------------------- collisions
def test_walls_stop_the_agent_and_cost_a_penalty():
    env = Continuous2DEnv(starts={"c": [0.99, 0.5]}, wall_penalty=-0.5, step_reward=-0.01)
    env.reset(seed=0)
    _, r, _, _, info = env.step(0)  # east into the wall at x = 1
    assert info["collision"] and r == pytest.approx(-0.51)
    assert 0.99 < env.agent_pose()[0] < 1.0
    for _ in range(5):
        env.step(0)
    assert env.agent_pose()[0] < 1.0
    _, r, _, _, info = env.step(2)  # away from the wall: free
    assert not info["collision"] and r == pytest.approx(-0.01)


def test_obstacles_block_and_the_pool_wall_holds():
    env = Continuous2DEnv(starts={"c": [0.2, 0.5]}, speed=1.0, dt=0.1,
                          obstacles=[{"shape": "polygon", "points": [[0.4, 0.2], [0.5, 0.2], [0.5, 0.8], [0.4, 0.8]]}])  # fmt: skip
    env.reset(seed=0)
    for _ in range(10):
        env.step(0)
    assert env.agent_pose()[0] < 0.4
    env = pool(speed=3.0)  # 0.3 per step in a 1 m pool: never leaves it
    env.reset(seed=1)
    rng = np.random.default_rng(0)
    for _ in range(2000):
        env.step(int(rng.integers(8)))
        assert np.hypot(*env.agent_pose()[:2]) < 1.0


# ---------------------------------------------------------------------------- goals and phases
def test_goal_ends_trial_and_phases_move_or_remove_it():
    goals = {
        "platform": PLATFORM,
        "other": {**PLATFORM, "x": -0.42, "y": -0.42, "reward": 0.0, "terminal": False},
    }
    env = pool(goals=goals, starts={"near": [0.42, 0.30]}, n_directions=4, speed=0.3)
    env.reset(seed=0)
    _, r, term, _, info = env.step(1)  # north by 0.03 ... not yet
    assert not term
    for _ in range(5):
        _, r, term, _, info = env.step(1)
        if term:
            break
    assert term and r == 1.0 and info["state"] == env.goal_names.index("platform")
    env.apply_changes(rewards={"platform": 0.0}, terminals={"platform": False})  # probe
    env.reset()
    rs = [env.step(1)[1:3] for _ in range(8)]
    assert all(r == 0.0 and not t for r, t in rs)
    env.apply_changes(rewards={"other": 1.0}, terminals={"other": True}, starts=[[-0.42, -0.30]])
    env.reset()
    _, r, term, _, _ = env.step(3)
    assert not term
    while not term:
        _, r, term, _, _ = env.step(3)
    assert r == 1.0 and env.agent_pose()[1] < -0.37
    env.reset_world()
    assert env.arena.goals["platform"].terminal and not env.arena.goals["other"].terminal
    with pytest.raises(ConfigError, match=r"unknown goal 'platfrom'.*did you mean 'platform'"):
        env.apply_changes(rewards={"platfrom": 1.0})


def test_shuffled_starts_cover_each_point_once_per_block():
    env = pool(start_order="shuffled")
    env.reset(seed=5)
    seen = [tuple(env.agent_pose()[:2])]
    for _ in range(7):
        env.reset()
        seen.append(tuple(env.agent_pose()[:2]))
    assert len(set(seen[:4])) == 4 and len(set(seen[4:])) == 4
    assert seen[:4] != seen[4:]  # reshuffled (for this seed)


# ---------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (
            {"goals": {"platform": {**PLATFORM, "x": 1.5}}},
            "goal 'platform' lies .*outside the arena",
        ),
        (
            {"goals": {"platform": {**PLATFORM, "radius": -0.05}}},
            r"goals.platform.radius must be > 0",
        ),
        ({"arena": {**POOL, "radius": -1}}, r"arena.radius must be > 0"),
        (
            {"obstacles": [{"shape": "circle", "x": 0.42, "y": 0.42, "radius": 0.2}]},
            "goal 'platform' lies inside a wall",
        ),
        (
            {"obstacles": [{"shape": "circle", "x": 0.0, "y": 0.9, "radius": 0.2}]},
            "start 'north' .* inside an obstacle",
        ),
        ({"starts": {"out": [2.0, 0.0]}}, "start 'out' .* outside the arena"),
        ({"arena": {"shape": "hexagon"}}, "arena.shape 'hexagon' is unknown"),
        (
            {"arena": {**POOL, "radius": 1.0, "radus": 2}},
            "unknown key 'arena.radus'.*did you mean 'radius'",
        ),
        ({"movement": "diferential"}, "did you mean 'differential'"),
        ({"observation": [{"kind": "place_cell"}]}, "did you mean 'place_cells'"),
        ({"observation": [{"kind": "place_cells", "sigma": -1}]}, "sigma must be > 0"),
    ],
)
def test_bad_input_is_one_line_config_error(kwargs, match):
    with pytest.raises(ConfigError, match=match) as err:
        pool(**kwargs)
    assert "\n" not in str(err.value)


# ---------------------------------------------------------------------------- cells vs RatInABox
@pytest.fixture(scope="module")
def rib():
    pytest.importorskip("ratinabox", reason="RatInABox is the reference (dev extra)")
    import ratinabox
    from ratinabox.Agent import Agent
    from ratinabox.Environment import Environment

    ratinabox.verbose = False
    # RatInABox draws its cell parameters from numpy's global generator: seed it for this
    # module only, and put the previous state back afterwards
    saved = np.random.get_state()  # noqa: NPY002
    np.random.seed(0)  # noqa: NPY002
    yield Agent(Environment())  # unit square, solid walls
    np.random.set_state(saved)  # noqa: NPY002


@pytest.fixture(scope="module")
def square_env():
    return Continuous2DEnv()


def _positions(n=300, seed=0):
    return np.random.default_rng(seed).uniform(0.02, 0.98, (n, 2))


def test_place_cells_match_ratinabox(rib, square_env):
    from ratinabox.Neurons import PlaceCells as RPlace

    ref = RPlace(
        rib, {"n": 40, "widths": 0.12, "description": "gaussian", "wall_geometry": "euclidean"}
    )
    ours = PlaceCells(centres=ref.place_cell_centres, sigma=0.12)
    ours.bind(square_env.arena)
    pos = _positions()
    expected = ref.get_state(evaluate_at=None, pos=pos).T
    np.testing.assert_allclose(ours.rates(np.c_[pos, np.zeros(len(pos))]), expected, atol=1e-12)
    out = np.empty(40)
    ours.write(pos[0, 0], pos[0, 1], 0.0, out)  # the compiled per-step path
    np.testing.assert_allclose(out, expected[0], atol=1e-12)


@pytest.mark.parametrize("description", ["rectified_cosines", "shifted_cosines"])
def test_grid_cells_match_ratinabox(rib, description):
    from ratinabox.Neurons import GridCells as RGrid

    ref = RGrid(rib, {"n": 12, "description": description})
    ours = GridCells(n=12, gridscale=ref.gridscales.tolist(), orientation=ref.orientations.tolist(),
                     phase_offsets=ref.phase_offsets.tolist(), description=description)  # fmt: skip
    pos = _positions()
    expected = ref.get_state(evaluate_at=None, pos=pos).T
    np.testing.assert_allclose(ours.rates(np.c_[pos, np.zeros(len(pos))]), expected, atol=1e-10)


def test_head_direction_cells_match_ratinabox(rib):
    from ratinabox.Neurons import HeadDirectionCells as RHD

    ref = RHD(rib, {"n": 8, "angular_spread_degrees": 30})
    ours = HeadDirectionCells(n=8, spread_deg=30)
    for h in np.linspace(-np.pi, np.pi, 37):
        expected = ref.get_state(evaluate_at=None, head_direction=np.array([np.cos(h), np.sin(h)]))[
            :, 0
        ]
        # RatInABox's get_angle adds 1e-6 to the x component: angles differ by up to ~1e-6
        np.testing.assert_allclose(ours.rates(np.array([[0.5, 0.5, h]]))[0], expected, atol=1e-5)


def test_boundary_vector_cells_match_ratinabox(rib, square_env):
    from ratinabox.Neurons import BoundaryVectorCells as RBVC

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = RBVC(rib, {"n": 10})
    ours = BoundaryVectorCells(
        n=10, tuning_distance=ref.tuning_distances.tolist(),
        tuning_angle_deg=np.rad2deg(ref.tuning_angles).tolist(),
        sigma_angle_deg=np.rad2deg(ref.sigma_angles).tolist(),
        sigma_distance=ref.sigma_distances.tolist(),
    )  # fmt: skip
    ours.bind(square_env.arena)
    pos = _positions(150)
    expected = ref.get_state(evaluate_at=None, pos=pos).T
    got = ours.rates(np.c_[pos, np.zeros(len(pos))])
    # RatInABox integrates over 2-degree test directions too (with 0 deg counted twice and
    # 358 deg left out): the two sums agree to a small fraction of the peak rate
    assert np.max(np.abs(got - expected)) < 0.03
    for i in range(10):
        assert np.corrcoef(got[:, i], expected[:, i])[0, 1] > 0.995


def test_place_cell_layouts_fill_the_free_space():
    env = pool(observation=[{"kind": "place_cells", "n": 493, "sigma": 0.16}])
    c = env.observation_parts[0].centres
    assert c.shape == (493, 2) and np.all(np.hypot(c[:, 0], c[:, 1]) < 1.0)
    # even coverage: every quadrant holds about a quarter
    counts = np.histogram2d(c[:, 0], c[:, 1], bins=[[-1, 0, 1], [-1, 0, 1]])[0]
    assert counts.min() > 0.2 * 493
    assert halton(4, 2).tolist() == [0.5, 0.25, 0.75, 0.125]


# ---------------------------------------------------------------------------- analyses
def test_water_maze_measures_on_synthetic_paths():
    # a straight swim from the west edge to the platform at (0.42, 0.42)
    path = np.linspace([-0.9, 0.0], [0.42, 0.42], 101)
    assert wm.path_length(path) == pytest.approx(np.hypot(1.32, 0.42))
    assert wm.escape_latency_s(100, 0.1) == pytest.approx(10.0)
    assert wm.mean_distance_to_platform(path, (0.42, 0.42)) == pytest.approx(
        np.hypot(1.32, 0.42) / 2, rel=1e-3
    )
    # a circle of radius 0.5 spends a quarter of the time in each quadrant
    a = np.linspace(0, 2 * np.pi, 4000, endpoint=False)
    circle = np.c_[0.5 * np.cos(a), 0.5 * np.sin(a)]
    occ = wm.quadrant_occupancy(circle, (0.42, 0.42))
    assert all(v == pytest.approx(0.25, abs=1e-3) for v in occ.values())
    # a swim around the platform site: target quadrant only, 3 crossings of the platform
    loops = np.concatenate([np.c_[0.42 + 0.1 * np.cos(a[:200]), 0.42 + 0.1 * np.sin(a[:200])],
                            np.tile([[0.42, 0.42], [0.6, 0.6]], (3, 1))])  # fmt: skip
    assert wm.target_quadrant_fraction(loops, (0.42, 0.42)) == 1.0
    assert wm.platform_crossings(loops, (0.42, 0.42), 0.05) == 3
    ann = wm.annulus_crossings(loops, (0.42, 0.42), 0.05)
    assert ann["target"] == 3 and ann["opposite"] == 0 and ann["index"] == 3
    # the opposite quadrant is labelled as such
    occ = wm.quadrant_occupancy(np.array([[-0.5, -0.5], [0.5, -0.5], [-0.5, 0.5]]), (0.42, 0.42))
    assert occ["opposite"] == pytest.approx(1 / 3) and occ["adjacent_cw"] == pytest.approx(1 / 3)
    df = wm.trial_measures([path, loops], (0.42, 0.42), 0.05, 0.1)
    assert list(df.columns) == list(wm.MEASURE_COLUMNS) and len(df) == 2
    with pytest.raises(ValueError, match="positions must be"):
        wm.path_length(np.zeros((3, 4)))


def test_first_person_view_of_the_arena():
    pytest.importorskip("pybullet")
    env = Continuous2DEnv(arena=POOL, render_mode="rgb_array", camera={"height": 24, "width": 48},
                          obstacles=[{"shape": "rectangle", "x0": 0.3, "y0": -0.1, "x1": 0.5, "y1": 0.1}],
                          starts={"c": [0.0, 0.0]}, start_heading=0.0)  # fmt: skip
    env.reset(seed=0)
    east = env.render()
    assert east.shape == (24, 48, 3) and east.dtype == np.uint8
    # looking east at the obstacle's west face (colour of walls facing west) vs west at the pool
    west = env.view_at_pose(0.0, 0.0, np.pi)
    assert np.abs(east.astype(int) - west).mean() > 10
    np.testing.assert_array_equal(env.view_at_pose(0.0, 0.0, 0.0), east)  # deterministic
    centre = east[12, 24].astype(int)
    assert centre[1] > centre[0] and centre[1] > centre[2]  # green: a wall facing west
    env.close()


@pytest.mark.parametrize("movement", ["directions", "continuous"])
def test_sb3_check_env(movement):
    """SB3's own checker accepts the discrete (DQN) and the continuous (SAC, PPO) action spaces."""
    sb3_checker = pytest.importorskip("stable_baselines3.common.env_checker")
    env = Continuous2DEnv(movement=movement, observation=[{"kind": "place_cells", "n": 30}],
                          goals={"goal": {"shape": "circle", "x": 0.85, "y": 0.85, "radius": 0.1}},
                          starts={"s": [0.15, 0.15]}, max_steps=50)  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # SB3 warns about spaces it would mishandle
        sb3_checker.check_env(env, warn=True)
