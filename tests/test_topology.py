"""Topology graphs, pose actions, TopologyEnv and observation modules (no rendering)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import cobelrun.envs  # noqa: F401  (registers cobel/ ids)
from cobelrun.envs import topology as topo
from cobelrun.envs.observations import MultiSensoryObservation, NoisyObservation, PoseObservation
from cobelrun.envs.topology_env import TopologyEnv
from cobelrun.envs.world import blodgett
from cobelrun.errors import CobelError, ConfigError


# ---------------------------------------------------------------------- builders
def test_hexagonal_9x9_has_77_nodes_centre_38():
    h = topo.hexagonal(9, 9)
    assert h.n_nodes == 77
    assert h.places["centre"] == 38
    assert h.n_directions == 6
    assert h.degree[38] == 6
    # every edge has unit length and is two-way
    e = h.edges
    length = np.hypot(*(h.positions[e[:, 0]] - h.positions[e[:, 1]]).T)
    assert np.allclose(length, 1.0)
    assert {tuple(x) for x in e} == {(b, a) for a, b in e}


def test_tmaze_topology_has_12_nodes_and_places():
    t = topo.tmaze_paper()
    assert t.n_nodes == 12
    assert t.places == {"start": 11, "junction": 3, "left_arm": 0, "right_arm": 6}
    assert t.degree[3] == 3  # junction: left, right, down the stem
    assert t.states.tolist() == [0, 1, 2, 3, 4, 5, 6, 10, 17, 24, 31, 38]


def test_from_world_keeps_one_way_doors():
    w = blodgett()
    t = topo.from_world(w)
    assert t.n_nodes == 20
    a, b = (int(np.flatnonzero(t.states == s)[0]) for s in (25, 24))
    assert b not in t.neighbours[a]  # 25 -> 24 blocked
    assert a in t.neighbours[b]  # 24 -> 25 open


def test_grid_and_delaunay_and_manual():
    g = topo.grid(3, 2)
    assert g.n_nodes == 6 and g.neighbours[0].tolist() == [1, -1, -1, 3]
    pts = [[0, 0], [1, 0], [0, 1], [1, 1], [0.5, 0.5]]
    d = topo.delaunay(pts, n_directions=8)
    assert d.n_nodes == 5
    assert set(d.neighbours[4][d.neighbours[4] >= 0].tolist()) == {0, 1, 2, 3}
    m = topo.manual([[0, 0], [1, 0], [1, 1]], [[0, 1], [1, 2]], places={"goal": 2})
    assert m.neighbours[1].tolist() == [-1, 2, 0, -1]
    assert m.node("goal") == 2
    with pytest.raises(CobelError, match="out of range"):
        topo.manual([[0, 0], [1, 0]], [[0, 5]])
    with pytest.raises(CobelError, match=r"unknown place 'gaol'.*did you mean 'goal'"):
        m.node("gaol")


# ---------------------------------------------------------------------- actions
def test_turn_mode_semantics_on_a_small_grid():
    g = topo.grid(3, 3)  # centre node 4; east 5, north 1, west 3, south 7
    am = topo.ActionMap.build(g, "turn")
    assert am.names == ("forward", "left", "back", "right", "turn_left", "turn_right")
    north = 1
    assert am.next_node[4, north, 0] == 1  # forward = north
    assert am.next_node[4, north, 1] == 3  # left = west
    assert am.next_node[4, north, 2] == 7  # back = south
    assert am.next_node[4, north, 3] == 5  # right = east
    assert (am.next_heading[4, north, :4] == north).all()  # moves keep the heading
    assert am.next_heading[4, north, 4] == 2 and am.next_node[4, north, 4] == 4  # turn left -> west
    assert am.next_heading[4, north, 5] == 0  # turn right -> east
    assert am.next_node[1, north, 0] == 1  # wall ahead: stay


def test_face_and_none_modes():
    h = topo.hexagonal(9, 9)
    face = topo.ActionMap.build(h, "face")
    assert face.n_actions == 12
    assert (face.next_heading[38, 0, 6:] == np.arange(6)).all()
    assert (face.next_node[38, 0, 6:] == 38).all()
    assert face.next_node[38, 0, 0] == 39 and face.next_heading[38, 0, 0] == 0
    none = topo.ActionMap.build(topo.grid(3, 3), "none")
    assert none.n_actions == 4
    assert none.next_node[4, 0, 1] == 1 and none.next_heading[4, 0, 1] == 1  # heading follows
    with pytest.raises(ConfigError, match=r"action mode 'tunr'.*did you mean 'turn'"):
        topo.ActionMap.build(h, "tunr")


# ---------------------------------------------------------------------- env
def test_topology_env_tmaze_rewards_protocol_changes():
    env = TopologyEnv()
    assert env.action_space.n == 6
    assert env.world.state("right_arm") == 6
    _obs, info = env.reset(seed=0)
    assert info["node"] == 11 and info["angle"] == 90.0
    # walk up the stem (forward x 5), turn right, forward x 3 -> right arm end
    for a in [0] * 5:
        _, r, term, _, info = env.step(a)
        assert not term
    assert info["node"] == 3
    env.step(5)
    for _ in range(2):
        _, r, term, _, _ = env.step(0)
    _, r, term, _, info = env.step(0)
    assert info["node"] == 6 and term and r == 1.0
    env.apply_changes(rewards={"right_arm": 0.0, "left_arm": 1.0})
    assert env.world.rewards[0] == 1.0 and env.world.rewards[6] == 0.0
    env.reset_world()
    assert env.world.rewards[6] == 1.0


def test_hex_env_step_reward_random_heading():
    h = topo.hexagonal()
    env = TopologyEnv(topology=h, rewards={"centre": 1.0}, terminals=["centre"], starts="all",
                      start_heading="random", step_reward=-1.0, actions="face")  # fmt: skip
    heads = {env.reset(seed=s)[1]["heading"] for s in range(30)}
    assert len(heads) > 3
    env.reset(seed=0)
    env._node, env._heading = 37, 0
    _, r, term, _, info = env.step(0)
    assert info["node"] == 38 and term and r == 1.0
    env._node = 0
    _, r, term, _, _ = env.step(6)
    assert r == -1.0 and not term


@pytest.mark.parametrize(
    "make_obs",
    [
        lambda: PoseObservation(),
        lambda: NoisyObservation(PoseObservation(), kind="gaussian", std=0.1),
        lambda: NoisyObservation(PoseObservation(), kind="salt_pepper", amount=0.3),
        lambda: MultiSensoryObservation(
            {"pose": PoseObservation(), "raw": PoseObservation(normalize=False)}
        ),
    ],
    ids=["pose", "gaussian", "salt_pepper", "multisensory"],
)
def test_check_env_pose_modules(make_obs):
    check_env(TopologyEnv(observation=make_obs(), max_steps=20), skip_render_check=True)


def test_noise_is_seeded_from_env():
    def roll(seed):
        env = TopologyEnv(observation=NoisyObservation(PoseObservation(), std=0.2))
        obs = [env.reset(seed=seed)[0]]
        obs += [env.step(a)[0] for a in [0, 4, 0, 5, 0]]
        return np.stack(obs)

    assert np.array_equal(roll(3), roll(3))
    assert not np.array_equal(roll(3), roll(4))


def test_registered_id_and_bad_config():
    env = gym.make("cobel/Topology-v0", actions="none")
    assert env.action_space.n == 4
    with pytest.raises(ConfigError, match="start_heading"):
        TopologyEnv(start_heading="north")
    with pytest.raises(CobelError, match="unknown place"):
        TopologyEnv(rewards={"rigth_arm": 1.0})
