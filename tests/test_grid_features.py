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
