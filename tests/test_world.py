"""Tabular worlds: paper mazes, layout parsing, validation, persistence."""

from __future__ import annotations

import zipfile
from collections import deque
from itertools import pairwise

import numpy as np
import pytest

from cobelrun.envs.world import (
    BLODGETT_DOORS,
    BLODGETT_PATH,
    World,
    _blodgett_walls,
    blodgett,
    from_layout,
    open_field,
    t_maze,
    tmaze_paper,
)
from cobelrun.errors import ConfigError, LayoutError


def count_shortest_paths(world: World, a: int, b: int) -> tuple[int, int]:
    """(length, number of distinct shortest paths) from a to b over T > 0."""
    adj = (world.T > 0).any(axis=1)
    np.fill_diagonal(adj, False)
    dist = {a: 0}
    ways = {a: 1}
    queue = deque([a])
    while queue:
        s = queue.popleft()
        for n in np.flatnonzero(adj[s]).tolist():
            if n not in dist:
                dist[n] = dist[s] + 1
                ways[n] = ways[s]
                queue.append(n)
            elif dist[n] == dist[s] + 1:
                ways[n] += ways[s]
    return dist[b], ways[b]


def walk(world: World, s: int, actions: list[int]) -> list[int]:
    out = [s]
    for a in actions:
        s = int(world.next_state[s, a])
        out.append(s)
    return out


# ---------------------------------------------------------------------- paper mazes
def test_tmaze_paper_facts() -> None:
    w = tmaze_paper()
    assert (w.width, w.height, w.n_states, w.n_actions) == (7, 7, 49, 4)
    assert w.T.shape == (49, 4, 49)
    reach = w.reachable()
    assert reach.sum() == 12
    assert set(np.flatnonzero(reach)) == {0, 1, 2, 3, 4, 5, 6, 10, 17, 24, 31, 38}
    assert w.starts.tolist() == [38]
    assert w.places == {"start": 38, "junction": 3, "left_arm": 0, "right_arm": 6}
    assert np.flatnonzero(w.terminal).tolist() == [0, 6]
    assert np.flatnonzero(w.rewards).tolist() == [6] and w.rewards[6] == 1.0
    d = w.distances()
    assert d[0] == d[6] == 8
    assert count_shortest_paths(w, 38, 6) == (8, 1)
    # conventions: 0=left 1=up 2=right 3=down, walls leave the agent in place
    assert walk(w, 38, [1, 1, 1, 1, 1, 2, 2, 2]) == [38, 31, 24, 17, 10, 3, 4, 5, 6]
    assert w.next_state[38].tolist() == [38, 31, 38, 38]
    assert w.coords[38].tolist() == [3.0, 1.0]  # x = col, y = height - 1 - row
    assert w.coords[3].tolist() == [3.0, 6.0]
    assert w.blocked.sum() == 49 - 12


def test_blodgett_facts() -> None:
    w = blodgett()
    assert (w.width, w.height, w.n_states) == (8, 5, 40)
    assert w.starts.tolist() == [24]
    assert w.terminal[15] and w.terminal.sum() == 1
    assert w.rewards.sum() == 0.0
    assert len(_blodgett_walls()) == 34
    assert w.reachable().sum() == 20
    assert count_shortest_paths(w, 24, 15) == (13, 1)
    # the exact shortest path, step by step along the distance gradient
    d = w.distances()
    assert [int(d[s]) for s in BLODGETT_PATH] == list(range(14))
    for a, b in pairwise(BLODGETT_PATH):
        assert w.T[a, :, b].max() == 1.0, (a, b)


@pytest.mark.parametrize(("a", "b"), BLODGETT_DOORS)
def test_blodgett_one_way_doors_block_one_direction(a: int, b: int) -> None:
    w = blodgett()
    assert w.T[a, :, b].max() == 0.0  # a -> b blocked
    assert w.T[b, :, a].max() == 1.0  # b -> a open


def test_blodgett_goal_reward() -> None:
    assert blodgett(goal_reward=10.0).rewards[15] == 10.0


def test_t_maze_builder() -> None:
    w = t_maze(5, 3)
    assert (w.width, w.height) == (7, 6)
    assert w.places == {"start": 38, "junction": 3, "left_arm": 0, "right_arm": 6}
    assert w.reachable().sum() == 12
    assert w.rewards[6] == 1.0 and w.rewards[0] == 0.0
    assert w.terminal[[0, 6]].all()
    left = t_maze(2, 1, goal="left", goal_reward=5.0)
    assert left.rewards[left.places["left_arm"]] == 5.0
    assert t_maze(2, 1, goal=None).rewards.sum() == 0.0
    with pytest.raises(ConfigError, match="did you mean 'right'"):
        t_maze(2, 1, goal="rigth")


def test_open_field() -> None:
    w = open_field(4, 3, goal=[2, 3])
    assert w.places["goal"] == 11 and w.terminal[11] and w.rewards[11] == 1.0
    assert 11 not in w.starts and len(w.starts) == 11
    assert w.reachable().all()
    w2 = open_field(3, 3, starts=[0])
    assert w2.starts.tolist() == [0] and not w2.terminal.any()


# ---------------------------------------------------------------------- layout parsing
def test_layout_parsing_and_options() -> None:
    w = from_layout(
        """
            S..
            .#E
            ..G
        """,
        goal_reward=2.0,
        rewards={"corner": 0.0, 1: 0.5},
        places={"corner": [0, 2]},
    )
    assert (w.width, w.height) == (3, 3)
    assert w.places == {"corner": 2}
    assert w.starts.tolist() == [0]
    assert w.blocked.tolist() == [False] * 4 + [True] + [False] * 4
    assert w.terminal.tolist() == [False] * 5 + [True, False, False, True]
    assert w.rewards[8] == 2.0 and w.rewards[5] == 0.0 and w.rewards[1] == 0.5
    assert w.next_state[1, 3] == 1  # down into the wall cell: stay
    assert w.next_state[0, 0] == 0  # off the grid: stay
    assert w.next_state[0, 2] == 1
    auto = from_layout("S.G")
    assert auto.places == {"start": 0, "goal": 2}


def test_layout_walls_one_way_starts_terminals() -> None:
    w = from_layout(
        "....\n....",
        walls=[[0, 1]],
        one_way=[[[1, 2], [1, 3]]],
        starts=[0, 4],
        terminals=[3],
    )
    assert w.next_state[0, 2] == 0 and w.next_state[1, 0] == 1  # two-way wall
    assert w.next_state[6, 2] == 6  # 6 -> 7 blocked
    assert w.next_state[7, 0] == 6  # 7 -> 6 allowed
    assert w.starts.tolist() == [0, 4]
    assert w.terminal[3] and w.terminal.sum() == 1


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"layout": "S.x\n..."}, r"unknown layout symbol 'x' at row 0, col 2; allowed symbols"),
        ({"layout": "S..\n.."}, r"row 1 has 2 cells but row 0 has 3"),
        ({"layout": "...\n..."}, r"no start"),
        ({"layout": "S.#\n...", "starts": [2]}, r"start state 2 .* is a wall cell"),
        ({"layout": "S.#\n..G", "starts": [[0, 2]]}, r"wall cell"),
        ({"layout": "S#G\n.#."}, r"goal state 2 .* unreachable from every start"),
        ({"layout": "S#E\n.#."}, r"terminal state 2 .* unreachable"),
        ({"layout": "S#.\n.#.", "rewards": {2: 1.0}}, r"rewarded state 2 .* unreachable"),
        ({"layout": "S..\n...", "terminals": [9]}, r"state 9 is out of range; allowed 0\.\.5"),
        ({"layout": "S..\n...", "rewards": {7: 1.0}}, r"out of range"),
        ({"layout": "S..\n...", "walls": [[0, 2]]}, r"walls: states 0 and 2 are not adjacent"),
        ({"layout": "S..\n...", "walls": [[2, 3]]}, r"not adjacent"),  # wraps around a row
        ({"layout": "S..\n...", "one_way": [[0, 9]]}, r"one_way: state 9 is out of range"),
        ({"layout": "S..\n...", "walls": [[0, [5, 0]]]}, r"outside the 2 x 3 grid"),
        ({"layout": "S..\n...", "places": {"x": 6}}, r"place 'x': state 6 is out of range"),
        ({"layout": "S..\n...", "slip": 1.0}, r"slip must be in \[0, 1\)"),
        ({"layout": "", "starts": [0]}, r"layout is empty"),
        ({"layout": "G..\n...", "starts": [0]}, r"start state 0 .* is terminal"),
    ],
)
def test_layout_errors(kwargs: dict, match: str) -> None:
    layout = kwargs.pop("layout")
    with pytest.raises(LayoutError, match=match):
        from_layout(layout, **kwargs)


def test_layout_error_messages_are_one_line() -> None:
    for bad in ("S.x", "S..\n..", "...", "S#G\n.#."):
        with pytest.raises(LayoutError) as err:
            from_layout(bad)
        assert "\n" not in str(err.value)


# ---------------------------------------------------------------------- slip
def test_slip_is_stochastic_and_normalised() -> None:
    w = from_layout("S...\n....\n...G", slip=0.2)
    assert w.next_state is None
    np.testing.assert_allclose(w.T.sum(axis=2), 1.0)
    # state 5 (row 1, col 1) has four distinct neighbours: 0.8 intended, 0.2/3 each other
    assert w.T[5, 2, 6] == pytest.approx(0.8)
    assert w.T[5, 2, 4] == pytest.approx(0.2 / 3)
    assert w.T[5, 2, 1] == pytest.approx(0.2 / 3)
    # corner: "left" and "up" both stay, so staying collects their probability
    assert w.T[0, 2, 0] == pytest.approx(2 * 0.2 / 3)


# ---------------------------------------------------------------------- state refs, setters
def test_state_resolution() -> None:
    w = tmaze_paper()
    assert w.state(38) == 38
    assert w.state(np.int64(6)) == 6
    assert w.state("right_arm") == 6
    assert w.state("38") == 38
    assert w.state([5, 3]) == 38
    assert w.state((0, 6)) == 6
    with pytest.raises(
        LayoutError, match=r"unknown place 'rigth_arm' \(did you mean 'right_arm'\?\)"
    ):
        w.state("rigth_arm")
    with pytest.raises(LayoutError, match=r"out of range; allowed 0\.\.48"):
        w.state(49)
    with pytest.raises(LayoutError, match="outside the 7 x 7 grid"):
        w.state([7, 0])
    with pytest.raises(ConfigError, match="not a state reference"):
        w.state(1.5)
    with pytest.raises(ConfigError, match="not a state"):
        w.state(True)


def test_setters_validate_and_apply() -> None:
    w = tmaze_paper()
    w.set_rewards({"right_arm": 0.0, "left_arm": 1.0})
    assert w.rewards[0] == 1.0 and w.rewards[6] == 0.0
    w.set_rewards([[[0, 3], 0.5]])  # list of pairs: [row, col] refs are fine
    assert w.rewards[3] == 0.5
    w.set_starts(["junction", 10])
    assert w.starts.tolist() == [3, 10]
    w.set_terminal({4: True, 0: False})
    assert w.terminal[4] and not w.terminal[0]
    with pytest.raises(LayoutError, match="wall cell"):
        w.set_starts([7])
    with pytest.raises(LayoutError, match="wall cell"):
        w.set_rewards({7: 1.0})
    with pytest.raises(ConfigError, match="finite"):
        w.set_rewards({6: float("nan")})
    with pytest.raises(ConfigError, match="true or false"):
        w.set_terminal({6: "yes"})
    with pytest.raises(LayoutError, match="is a start state"):
        w.set_terminal({10: True})


def test_set_starts_rejects_terminal_and_empty() -> None:
    w = tmaze_paper()
    with pytest.raises(LayoutError, match="is terminal"):
        w.set_starts([6])
    with pytest.raises(LayoutError, match="at least one start"):
        w.set_starts([])


def test_next_state_cache_and_read_only_T() -> None:
    w = tmaze_paper()
    ns = w.next_state
    assert ns is w.next_state and ns.dtype == np.int64 and ns.shape == (49, 4)
    with pytest.raises(ValueError, match="read-only"):
        w.T[38, 1, 31] = 0.0
    T = w.T.copy()
    T[38, 1] = 0.0
    T[38, 1, 38] = 1.0
    w.T = T
    assert w.next_state[38, 1] == 38
    T[38, 1] = 0.5 * np.eye(49)[38] + 0.5 * np.eye(49)[31]
    w.T = T
    assert w.next_state is None
    with pytest.raises(LayoutError, match="sums to 1"):
        w.T = T * 2


def test_copy_is_independent() -> None:
    w = tmaze_paper()
    c = w.copy()
    c.set_rewards({6: 0.0})
    c.places["x"] = 1
    assert w.rewards[6] == 1.0 and "x" not in w.places


# ---------------------------------------------------------------------- persistence
@pytest.mark.parametrize("make", [tmaze_paper, blodgett, lambda: from_layout("S..\n..G", slip=0.1)])
def test_save_load_round_trip(tmp_path, make) -> None:
    w = make()
    w.set_rewards({int(w.starts[0]): 3.25})
    path = w.save(tmp_path / "world")
    assert path.suffix == ".npz"
    with zipfile.ZipFile(path) as z:  # plain arrays only: loadable without pickle
        names = set(z.namelist())
    assert "places.npy" in names
    with np.load(path, allow_pickle=False) as z:
        assert z["places"].dtype.kind == "U"
    back = World.load(path)
    assert (back.width, back.height, back.places) == (w.width, w.height, w.places)
    for name in ("T", "rewards", "terminal", "starts", "coords", "blocked"):
        a, b = getattr(w, name), getattr(back, name)
        assert a.dtype == b.dtype and np.array_equal(a, b), name
    assert (back.next_state is None) == (w.next_state is None)
