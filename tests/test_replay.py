"""Replay agents: PMA (Mattar & Daw 2018) in the Dyna maze, the replays table and its events."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from cobelrun.agents import PMA, DynaQ
from cobelrun.analysis.replay import direction_counts, replay_events, state_distances
from cobelrun.config import instantiate
from cobelrun.envs import GridWorldEnv, open_field
from cobelrun.errors import ConfigError
from cobelrun.runner import run_seed
from tests.test_configs import _compose

SHORTEST = 14
RUNS, TRIALS, MAX_STEPS = 20, 25, 10_000
# the task's shared setting: greedy behaviour, gain under softmax(5), alpha 1, gamma 0.9
SETTING = dict(policy="epsilon_greedy", epsilon=0.0, beta=5.0, learning_rate=1.0, gamma=0.9)


def dyna_maze_env() -> GridWorldEnv:
    return instantiate("env", _compose("task=dyna_maze").env)


def run_agents(cls, runs=RUNS, trials=TRIALS, **kw):
    """``runs`` seeded agents (seeds derived as the runner does); (steps, replays) tables."""
    env = dyna_maze_env()
    steps, replays = [], []
    for run in range(runs):
        agent_seed, env_seed = run_seed(0, run)
        env.unwrapped.np_random = np.random.default_rng(env_seed)
        agent = cls(env, seed=agent_seed, **SETTING, **kw)
        batch = agent.train(trials, MAX_STEPS)
        steps.append(batch.steps)
        rep = getattr(agent, "last_replays", None)
        if rep is not None and rep["trial"].size:
            df = pd.DataFrame(rep)
            df["run"] = run
            df["trial"] += 1
            df["when"] = np.where(df["when"] == 0, "start", "end")
            replays.append(df)
    table = pd.concat(replays, ignore_index=True) if replays else pd.DataFrame()
    return np.array(steps), table


def trials_to_criterion(steps: np.ndarray, tolerance: float = 0.2) -> np.ndarray:
    """1-based first trial of each run within ``tolerance`` of the shortest path."""
    ok = steps <= (1 + tolerance) * SHORTEST
    return np.where(ok.any(axis=1), ok.argmax(axis=1) + 1, steps.shape[1] + 1)


@pytest.fixture(scope="module")
def pma_runs():
    return run_agents(PMA)


def test_dyna_maze_is_suttons_maze():
    world = dyna_maze_env().unwrapped.world
    assert int((~world.blocked).sum()) == 47
    assert world.distances()[world.places["goal"]] == SHORTEST
    assert world.describe(world.places["start"]) == "state 18 (row 2, col 0)"
    assert world.describe(world.places["goal"]) == "state 8 (row 0, col 8)"


def test_gain_is_the_policy_improvement_of_one_backup():
    from cobelrun.agents.replay_kernels import backup_gain

    Q = np.zeros((1, 4))
    gain = backup_gain(Q, 0, 0, 1.0, 1.0, 5.0, np.empty(4))
    p_new = np.exp(5.0) / (np.exp(5.0) + 3)
    assert gain == pytest.approx(p_new * 1.0 - 0.25 * 1.0)
    # a backup that does not change the policy's choice gains nothing
    Q = np.array([[1.0, 0.0, 0.0, 0.0]])
    assert backup_gain(Q, 0, 0, 1.0, 1.0, 5.0, np.empty(4)) == pytest.approx(0.0)


def test_pma_learns_the_shortest_path_in_fewer_trials_than_q_learning(pma_runs):
    pma_steps, _ = pma_runs
    q_steps, _ = run_agents(DynaQ, replay="off")
    pma, q = trials_to_criterion(pma_steps), trials_to_criterion(q_steps)
    assert np.median(pma) <= 3, pma
    assert np.median(q) >= 3 * np.median(pma), (pma, q)
    assert (pma < q).mean() >= 0.9
    # and stays there: PMA's last 10 trials are shortest paths in almost every run
    assert np.median(pma_steps[:, -10:]) == SHORTEST


def test_direction_of_replay_events_at_trial_start_and_end(pma_runs):
    _, replays = pma_runs
    counts = direction_counts(replay_events(replays), min_length=5)
    assert counts.loc["start", "forward"] > 3 * counts.loc["start", "reverse"], counts
    assert counts.loc["end", "reverse"] > 3 * counts.loc["end", "forward"], counts
    assert counts.loc["end", "reverse"] >= 10


def test_replay_happens_only_after_the_first_reward_and_at_start_or_goal(pma_runs):
    _, replays = pma_runs
    assert set(replays["when"]) == {"start", "end"}
    assert (replays["index"] < 20).all() and (replays["gain"] >= 1e-10).all()
    # trial 1 (no reward yet) has no start replay; its end (first reward) replays
    first = replays[replays["trial"] == 1]
    assert set(first["when"]) == {"end"}
    # n-step sequences occur (the extension) and the need is a positive SR entry
    assert (replays["length"] > 1).any() and (replays["need"] > 0).all()


def test_same_seed_same_replays_and_extension_switch():
    a, ra = run_agents(PMA, runs=2, trials=5)
    b, rb = run_agents(PMA, runs=2, trials=5)
    np.testing.assert_array_equal(a, b)
    pd.testing.assert_frame_equal(ra, rb)
    _, one_step = run_agents(PMA, runs=2, trials=5, extend=False)
    assert (one_step["length"] == 1).all()


def test_replay_events_direction_and_breaks():
    # forward 0->1->2->3, a break, then reverse 7->8, 6->7, 5->6, then a jump
    s = [0, 1, 2, 20, 7, 6, 5, 40]
    s2 = [1, 2, 3, 21, 8, 7, 6, 41]
    df = pd.DataFrame({"run": 0, "trial": 1, "when": "start", "index": range(8),
                       "agent_state": 0, "state": s, "next_state": s2})  # fmt: skip
    ev = replay_events(df)
    assert ev["direction"].tolist() == ["forward", "none", "reverse", "none"]
    assert ev["length"].tolist() == [3, 1, 3, 1]
    assert ev[["start_state", "end_state"]].values.tolist() == [[0, 3], [20, 21], [7, 6], [40, 41]]
    mixed = pd.DataFrame({"run": 0, "trial": 1, "when": "end", "index": range(3),
                          "agent_state": 0, "state": [0, 1, 0], "next_state": [1, 2, 1]})  # fmt: skip
    assert replay_events(mixed)["direction"].tolist() == ["mixed"]
    world = open_field(3, 3)
    dist = state_distances(world.next_state)
    assert dist[0, 8] == 4 and dist[4, 4] == 0
    grid = pd.DataFrame({"run": 0, "trial": 1, "when": "start", "index": range(2),
                         "agent_state": 8, "state": [0, 1], "next_state": [1, 2]})  # fmt: skip
    assert replay_events(grid, distances=dist)["distance"].tolist() == [2]  # 8 -> 5 -> 2
    assert replay_events(df.iloc[:0]).empty


def test_save_load_round_trip(tmp_path):
    env = dyna_maze_env()
    agent = PMA(env, seed=1, **SETTING)
    agent.train(3, MAX_STEPS)
    path = agent.save(tmp_path / "pma")
    other = PMA(env, seed=2, **SETTING)
    other.load(path)
    for key, arr in agent.get_state().items():
        np.testing.assert_array_equal(other.get_state()[key], arr)
    small = PMA(GridWorldEnv(open_field(3, 3)), seed=0)
    with pytest.raises(ConfigError, match="expected shape"):
        small.load(path)


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        (dict(replay="sometimes"), "agent.replay 'sometimes' is not known"),
        (dict(need="srr"), "did you mean 'sr'"),
        (dict(n_backups=-1), "agent.n_backups must be an integer >= 0"),
        (dict(gamma=1.5), r"agent.gamma must be a number in \[0.0"),
        (dict(policy="greedy"), "agent.policy 'greedy' is not known"),
    ],
)
def test_bad_parameters_one_line_config_error(kw, match):
    with pytest.raises(ConfigError, match=match):
        PMA(dyna_maze_env(), **kw)


def test_pma_needs_a_tabular_world():
    from cobelrun.envs.choice import TwoAFCEnv

    with pytest.raises(
        ConfigError,
        match=r"does not support observation space|needs an environment with .tabular_model.",
    ):
        PMA(TwoAFCEnv(), seed=0)


def test_cli_writes_the_replays_table(cobel, tmp_path):
    out = tmp_path / "run"
    proc = cobel("run", "task=dyna_maze", "task.runs=2", "task.protocol.phases.0.trials=4",
                 f"hydra.run.dir={out}")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    rep = pd.read_parquet(out / "replays.parquet")
    assert list(rep.columns) == ["run", "trial", "when", "index", "agent_state", "state",
                                 "action", "next_state", "reward", "gain", "need", "length"]  # fmt: skip
    assert set(rep["run"]) == {0, 1} and rep["trial"].between(1, 4).all()
    trials = pd.read_parquet(out / "trials.parquet")
    assert len(trials) == 8
    # Q-learning in the same task writes an empty replays table
    out_q = tmp_path / "run_q"
    proc = cobel("run", "task=dyna_maze", "agent=q_learning", "task.runs=1",
                 "task.protocol.phases.0.trials=2", f"hydra.run.dir={out_q}")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert pd.read_parquet(out_q / "replays.parquet").empty


def test_sfma_replays_form_sequences_whose_direction_depends_on_the_mode():
    from cobelrun.agents import SFMA

    share = {}
    for mode in ("default", "reverse"):
        _, replays = run_agents(SFMA, runs=5, trials=15, mode=mode)
        assert replays["when"].eq("end").all() and replays["need"].isna().all()
        events = replay_events(replays)
        counts = direction_counts(events, min_length=3).loc["end"]
        assert counts.sum() >= 50  # replays form sequences of >= 3 experiences
        share[mode] = counts["reverse"] / counts.sum()
    assert share["reverse"] >= 0.9, share
    assert share["reverse"] > share["default"] + 0.2, share


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        (dict(mode="backward"), "agent.mode 'backward' is not known"),
        (dict(similarity="dr2"), "did you mean 'dr'"),
        (dict(decay_inhibition=1.5), r"agent.decay_inhibition must be a number in \[0, 1.0\]"),
    ],
)
def test_sfma_bad_parameters(kw, match):
    from cobelrun.agents import SFMA

    with pytest.raises(ConfigError, match=match):
        SFMA(dyna_maze_env(), **kw)


def test_sfma_similarities():
    from cobelrun.agents.sfma import default_representation, euclidean_similarity

    world = dyna_maze_env().unwrapped.world
    dr = default_representation(world.T, 0.9)
    start, goal = world.places["start"], world.places["goal"]
    # the DR respects walls: the cell right of the start (behind no wall) is closer than the
    # cell two columns right (behind the wall at column 3)
    assert dr[start, start + 1] > dr[start, start + 3]
    eu = euclidean_similarity(world.coords)
    assert eu[start, start] == 1.0 and eu[start, goal] == pytest.approx(np.exp(-np.hypot(8, 2)))


def test_need_is_the_sr_row_or_the_stationary_distribution():
    from cobelrun.agents.pma import successor_representation
    from cobelrun.agents.replay_kernels import sr_row

    agent = PMA(dyna_maze_env(), seed=0, **SETTING)
    start = int(agent.env.unwrapped.world.starts[0])
    full = successor_representation(agent.T, 0.9)
    np.testing.assert_allclose(sr_row(agent.T, 0.9, start), full[start], atol=1e-12)
    np.testing.assert_allclose(agent.need_vector(start), full[start], atol=1e-12)
    stationary = PMA(dyna_maze_env(), seed=0, need="stationary", **SETTING)
    d = stationary.need_vector(start)
    np.testing.assert_allclose(d @ stationary.T, d, atol=1e-9)  # a left eigenvector, eigenvalue 1
    assert np.linalg.norm(d) == pytest.approx(1.0) and (d >= 0).all()
