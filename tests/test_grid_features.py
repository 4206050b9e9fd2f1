"""Grid features: warps (teleport cells) in layouts, drawn as places; agents use them."""

from __future__ import annotations

import numpy as np
import pytest

from cobelrun.agents import SRTD, Sarsa
from cobelrun.envs import GridWorldEnv, from_layout
from cobelrun.errors import LayoutError

ROOMS = """
#########
#S..#...#
#...#...#
#...#..G#
#########
"""


def test_a_move_onto_a_warp_entry_lands_on_its_exit():
    w = from_layout(ROOMS, warps=[[[3, 3], [1, 5]]])
    entry, exit_ = w.state([3, 3]), w.state([1, 5])
    assert w.places["warp_0"] == entry and w.places["warp_0_exit"] == exit_
    assert w.next_state[w.state([3, 2]), 2] == exit_  # right, onto the entry
    assert w.next_state[w.state([2, 3]), 3] == exit_  # down, onto the entry
    others = np.arange(w.n_states) != entry
    assert not (w.next_state[others] == entry).any()  # no move leads onto the entry
    assert w.reachable()[w.state("goal")]  # only through the warp
    slip = from_layout(ROOMS, warps={"warp": [1, 5]}, places={"warp": [3, 3]}, slip=0.3)
    assert slip.T[w.state([3, 2]), 2, exit_] == pytest.approx(0.7)
    assert slip.T[others][:, :, entry].sum() == 0.0


@pytest.mark.parametrize(
    ("warps", "match"),
    [
        ([[[3, 3], [3, 3]]], r"warp state 30 \(row 3, col 3\) leads to itself"),
        ([[[0, 0], [1, 5]]], r"warp entry .* is a wall cell; warps join free cells"),
        ([[[1, 1], [1, 5]]], r"warp entry .* is a start; an entry is never occupied"),
        ([[[3, 7], [1, 5]]], r"warp entry .* is a goal or terminal"),
        ([[[3, 3], [1, 5]], [[1, 5], [2, 6]]], r"warp exit .* is another warp's entry"),
    ],
)
def test_bad_warps_are_one_line_layout_errors(warps, match):
    with pytest.raises(LayoutError, match=match):
        from_layout(ROOMS, warps=warps)


def test_without_the_warp_the_goal_is_unreachable():
    with pytest.raises(LayoutError, match=r"goal .* is unreachable from every start"):
        from_layout(ROOMS)


@pytest.mark.parametrize("cls", [Sarsa, SRTD])
def test_tabular_agents_learn_the_path_through_the_warp(cls):
    """Start to the entry is 4 moves, exit to goal 4 more: 8 steps through the warp."""
    env = GridWorldEnv(from_layout(ROOMS, warps=[[[3, 3], [1, 5]]]))
    env.unwrapped.np_random = np.random.default_rng(0)
    agent = cls(env, seed=0, policy="softmax", beta=50.0)
    batch = agent.train(150, 200)
    assert batch.terminated[-20:].all()
    assert np.median(batch.steps[-20:]) == 8


KEY_DOOR = """
#########
#S..#..G#
#...D...#
#K..#...#
#########
"""


def test_a_key_opens_the_doors():
    """Top copy: no key, the door is a wall, no reachable goal there; the key's cell warps to
    the bottom copy, where the door is open and the goal is 8 steps on (2 to the key)."""
    from cobelrun.envs.world import keys_and_doors

    w = keys_and_doors(KEY_DOOR)
    assert (w.width, w.height) == (9, 11)  # two copies of 5 rows and a wall row
    door_top, door_held = w.state([2, 4]), w.state([8, 4])
    assert w.blocked[door_top] and not w.blocked[door_held]
    assert w.next_state[w.state([2, 1]), 3] == w.places["key_0_held"]  # down onto the key
    assert w.places["key_0_held"] == w.state([9, 1])
    assert np.flatnonzero(w.terminal).tolist() == [w.places["goal_with_key"]]
    assert "goal" not in w.places  # the goal behind the door cannot be reached without the key
    assert w.distances([w.state("start")])[w.state("goal_with_key")] == 10
    with pytest.raises(LayoutError, match=r"layout has doors \('D'\) but no key"):
        keys_and_doors(KEY_DOOR.replace("K", "."))
    with pytest.raises(LayoutError, match=r"unknown layout symbol 'X'"):
        keys_and_doors(KEY_DOOR.replace("K", "X"))


@pytest.mark.parametrize("cls", [Sarsa, SRTD])
def test_tabular_agents_learn_to_fetch_the_key_first(cls):
    """Near-greedy agents: every final trial takes the key, then the door, to the goal, within
    20 % of the shortest path (SARSA settles on a 12-step path, SR-TD on the 10-step one)."""
    from cobelrun.envs.world import keys_and_doors

    env = GridWorldEnv(keys_and_doors(KEY_DOOR))
    env.unwrapped.np_random = np.random.default_rng(0)
    agent = cls(env, seed=0, policy="softmax", beta=50.0)
    batch = agent.train(200, 300)
    assert batch.terminated[-20:].all()  # the goal exists only with the key: fetched first
    assert np.median(batch.steps[-20:]) <= 1.2 * 10  # shortest: 10 steps
