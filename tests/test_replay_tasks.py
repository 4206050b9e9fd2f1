"""Issue 14, second round: noisy rewards, per-trial protocol cycles, the linear track, replays
in ``run.mcap``."""

from __future__ import annotations

import numpy as np
import pytest

from cobelrun.agents import PMA, DynaQ
from cobelrun.agents.replay_log import ReplayLog
from cobelrun.config import instantiate
from cobelrun.envs import GridWorldEnv, from_layout
from cobelrun.envs.world import World
from cobelrun.errors import ConfigError, LayoutError
from cobelrun.recorder import STEP_NS
from tests.test_configs import _compose


# ------------------------------------------------------------------ reward noise
def _goal_rewards(env: GridWorldEnv, seed: int, n: int = 400) -> np.ndarray:
    """Rewards of ``n`` arrivals at the goal of a 1 x 2 corridor."""
    env.reset(seed=seed)
    out = []
    for _ in range(n):
        env.reset()
        out.append(env.step(2)[1])
    return np.array(out)


def test_noisy_reward_has_the_sd_and_is_seeded():
    world = from_layout("SG", reward_sd=0.1)
    env = GridWorldEnv(world)
    r = _goal_rewards(env, seed=3)
    assert abs(r.mean() - 1.0) < 0.02 and abs(r.std() - 0.1) < 0.015
    assert np.array_equal(r, _goal_rewards(GridWorldEnv(world), seed=3))
    assert not np.array_equal(r, _goal_rewards(GridWorldEnv(world), seed=4))
    exact = _goal_rewards(GridWorldEnv(from_layout("SG")), seed=3)
    assert np.all(exact == 1.0)


def test_noisy_positive_reward_is_truncated_at_zero():
    env = GridWorldEnv(from_layout("SG", goal_reward=0.05, reward_sd=0.1))
    r = _goal_rewards(env, seed=0)
    assert r.min() == 0.0 and (r == 0.0).mean() > 0.2  # ~31 % of draws fall below 0


def test_reward_sd_round_trips_and_is_checked(tmp_path):
    world = from_layout("S.G", reward_sd=0.25)
    assert World.load(world.save(tmp_path / "w")).reward_sd == 0.25
    assert world.copy().reward_sd == 0.25
    with pytest.raises(LayoutError, match="reward_sd must be a number >= 0"):
        from_layout("SG", reward_sd=-1)


def test_dyna_maze_reward_noise_option_reaches_the_agents():
    cfg = _compose("task=dyna_maze", "env.world.reward_sd=0.1")
    env = instantiate("env", cfg.env)
    rewards = []
    for cls in (PMA, DynaQ):
        env.unwrapped.np_random = np.random.default_rng(1)
        agent = cls(env, seed=1, policy="epsilon_greedy", epsilon=0.0, learning_rate=1.0)
        batch = agent.train(5, 10_000)
        r = batch.reward[batch.terminated]
        assert r.size == 5 and np.all(r != 1.0) and np.all(np.abs(r - 1.0) < 0.5)
        rewards.append(r)
    with pytest.raises(ConfigError, match="needs exact rewards"):
        DynaQ(env, seed=0, engine="compiled").train(1, 10)


# ------------------------------------------------------------------ per-trial cycles
def test_a_phase_cycle_changes_the_world_trial_by_trial_for_compiled_agents(tmp_path):
    """Rewards and starts alternate per trial; compiled Dyna-Q (run one trial per call) sees
    every change: it is rewarded at the end the cycle pays."""
    import cobelrun

    proto = ("+task.protocol={max_steps: 50, phases: [{name: a, trials: 3}, {name: laps, "
             "trials: 6, cycle: [{starts: [3], rewards: {0: 1, 6: 0}}, "
             "{starts: [2], rewards: {0: 0, 6: 2}}]}]}")  # fmt: skip
    run = cobelrun.run(
        "gridworld",
        ["env=gridworld_layout", "env.world.layout='E..S..E'", "~task.protocol", proto, "agent=dyna_q",
         "agent.engine=compiled", "task.runs=2", "task.record.mcap=false"],
        out=tmp_path / "run",
    )  # fmt: skip
    t = run.trials.sort_values(["run", "trial"])
    laps = t[t["phase"] == "laps"]
    k = (laps["trial"] - 4).to_numpy()
    assert np.array_equal(laps["start_state"].to_numpy(), np.where(k % 2 == 0, 3, 2))
    paid = laps["reward"].to_numpy()
    ends = laps["end_state"].to_numpy()
    west, east = np.where(k % 2 == 0, 1, 0), np.where(k % 2 == 0, 0, 2)
    assert np.all(paid == np.where(ends == 0, west, np.where(ends == 6, east, 0)))
    assert (paid == 2).any() and (paid == 1).any()
    assert set(t[t["phase"] == "a"]["start_state"]) == {3}  # before the cycle: the layout's start
    assert laps.groupby("run")["trial_in_phase"].apply(list).map(list(range(1, 7)).__eq__).all()


def test_bad_cycle_is_one_line_config_error():
    from cobelrun.protocol import Protocol

    with pytest.raises(ConfigError, match=r"phases\[0\].cycle must be a non-empty list"):
        Protocol.from_config({"max_steps": 5, "phases": [{"name": "a", "trials": 2, "cycle": []}]})
    with pytest.raises(ConfigError, match=r"cycle\[0\].start' \(did you mean 'starts'"):
        Protocol.from_config(
            {"max_steps": 5, "phases": [{"name": "a", "trials": 2, "cycle": [{"start": [0]}]}]}
        )


# ------------------------------------------------------------------ linear track
@pytest.fixture(scope="module")
def linear_track(tmp_path_factory):
    import cobelrun

    out = tmp_path_factory.mktemp("lt") / "run"
    return cobelrun.run(
        "linear_track", ["task.runs=6", "task.protocol.phases.0.trials=30"], out=out
    )


def test_linear_track_laps_alternate_and_pma_runs_the_shortest_lap(linear_track):
    t = linear_track.trials.sort_values(["run", "trial"])
    world = instantiate("env", _compose("task=linear_track").env).unwrapped.world
    west_e, east_e = world.state("west_eastward"), world.state("east_eastward")
    east_w, west_w = world.state("east_westward"), world.state("west_westward")
    odd = (t["trial"] % 2 == 1).to_numpy()
    assert np.array_equal(t["start_state"].to_numpy(), np.where(odd, west_e, east_w))
    assert np.array_equal(t["end_state"].to_numpy(), np.where(odd, east_e, west_w))
    # every lap ends where the next one starts (the same end of the track)
    xy = world.coords
    nxt = t.groupby("run")["start_state"].shift(-1).dropna().astype(int).to_numpy()
    ended = t.groupby("run")["end_state"].apply(lambda s: s.iloc[:-1]).to_numpy()
    assert np.array_equal(xy[ended, 0], xy[nxt, 0])
    late = t[t["trial"] > 10]
    assert (late["steps"] == 9).mean() > 0.95
    r = t["reward"].to_numpy()  # noisy reward, sd 0.1
    assert 0.05 < r.std() < 0.15 and abs(r.mean() - 1) < 0.05


def test_linear_track_pma_replays_forward_at_the_start_and_reverse_at_the_end(linear_track):
    from cobelrun.analysis.replay import direction_counts, replay_events

    counts = direction_counts(replay_events(linear_track.table("replays")), 5)
    assert counts.loc["start", "forward"] > 10 * max(1, counts.loc["start", "reverse"])
    assert counts.loc["end", "reverse"] > 10 * max(1, counts.loc["end", "forward"])
    assert counts.loc["end", "reverse"] > 50


# ------------------------------------------------------------------ replays in run.mcap
def test_replays_are_drawn_in_the_mcap_as_a_second_path(tmp_path):
    """Read ``run.mcap`` back: one SceneUpdate per replay bout on ``/run_NNNN/replay`` at the
    trial's start or end event, its line strips through the replayed states' cells."""
    import cobelrun
    from cobelrun.analysis.replay import replay_events
    from tests.test_mcap import read

    run = cobelrun.run("dyna_maze", ["task.runs=3", "task.protocol.phases.0.trials=6",
                                     "task.record.mcap_runs=2"], out=tmp_path / "run")  # fmt: skip
    msgs = read(run.path / "run.mcap")
    replays = run.table("replays")
    world = instantiate("env", _compose("task=dyna_maze").env).unwrapped.world
    trial_t = {(m[3]["run"], m[3]["trial"], m[3]["event"]): m[2] for m in msgs if m[0] == "/trial"}
    assert not any(m[0] == "/run_0002/replay" for m in msgs)  # only the kept runs
    for r in (0, 1):
        drawn = [m for m in msgs if m[0] == f"/run_{r:04d}/replay"]
        assert {m[1] for m in drawn} == {"foxglove.SceneUpdate"}
        bouts = replays[replays["run"] == r].groupby(["trial", "when"], sort=False)
        assert len(drawn) == bouts.ngroups > 0
        events = replay_events(replays[replays["run"] == r])
        for (_, t_ns, msg), ((trial, when), bout) in zip(
            [(m[0], m[2], m[3]) for m in sorted(drawn, key=lambda m: m[2])],
            sorted(bouts, key=lambda kv: (kv[0][0], kv[0][1] == "end")), strict=True,
        ):  # fmt: skip
            assert t_ns == trial_t[(r, trial, "start" if when == "start" else "end")]
            (entity,) = msg.entities
            meta = {kv.key: kv.value for kv in entity.metadata}
            assert meta["trial"] == str(trial) and meta["when"] == when
            assert (
                meta["backups"] == str(len(bout))
                and entity.lifetime.ToNanoseconds() == 10 * STEP_NS
            )
            ev = events[(events["trial"] == trial) & (events["when"] == when)]
            n_lines = sum(1 if d in ("forward", "reverse") else n
                          for d, n in zip(ev["direction"], ev["length"], strict=True))  # fmt: skip
            assert len(entity.lines) == n_lines == len(entity.spheres)
            # every drawn point is a replayed state's cell, and together they cover them all
            xy = {(p.x, p.y) for line in entity.lines for p in line.points}
            states = np.unique(np.concatenate([bout["state"], bout["next_state"]]))
            assert xy == {tuple(c) for c in world.coords[states].tolist()}
            forward = ev[ev["direction"] == "forward"]
            if len(forward):  # a forward event's strip runs s_1, s'_1, s'_2, ... in replay order
                first = bout.iloc[int(forward["first"].iloc[0]) :][: int(forward["length"].iloc[0])]
                want = world.coords[np.r_[first["state"].iloc[0], first["next_state"]]].tolist()
                assert any([[p.x, p.y] for p in line.points] == want for line in entity.lines)


# ------------------------------------------------------------------ SFMA definitions
@pytest.mark.parametrize("mode", ["default", "reverse"])
def test_sfma_first_reactivation_probabilities_are_cobel_v3s(mode):
    """P(e) of the first reactivation, from CoBeL-RL v3's SFMAMemory.replay written out:
    R = C * D[s_c, x(e)] * (1 - I), R /= max R, R < 1e-6 -> 0, P ~ exp(20 R) - 1."""
    from cobelrun.agents import SFMA

    env = GridWorldEnv(from_layout("S....G"))
    agent = SFMA(env, seed=0, mode=mode, n_backups=1)
    rng = np.random.default_rng(5)
    S, A = agent.Q.shape
    nxt = env.unwrapped.world.next_state
    agent.model_next[:] = nxt
    agent.model_next[5] = -1  # the goal: never left
    agent.strength[:] = np.where(agent.model_next >= 0, rng.integers(1, 5, (S, A)), 0)
    x = np.where(mode == "reverse", nxt, np.arange(S)[:, None])
    R = agent.strength * agent.similarity[2, x]
    R /= R.max()
    R[R < 1e-6] = 0.0
    P = np.exp(20 * R) - 1
    P /= P.sum()
    agent._log = ReplayLog()  # the log a train call would open
    picks = np.zeros((S, A))
    for _ in range(4000):
        agent._bout(2, 0, 1)
    rep = agent._log.collect()
    np.add.at(picks, (rep["state"], rep["action"]), 1)
    np.testing.assert_allclose(rep["gain"], P[rep["state"], rep["action"]], rtol=1e-9)
    np.testing.assert_allclose(picks / picks.sum(), P, atol=0.025)


def test_sfma_reward_memory_is_a_running_average():
    from cobelrun.agents import SFMA

    env = GridWorldEnv(from_layout("SG", reward_sd=0.1))
    agent = SFMA(env, seed=0, learning_rate=0.9, replay="off")
    env.unwrapped.np_random = np.random.default_rng(0)
    batch = agent.train(3, 10)
    est = 0.0
    for r in batch.reward:
        est += 0.9 * (r - est)
    assert agent.model_reward[0, 2] == pytest.approx(est)


def test_sfma_on_the_linear_track_reverse_share_depends_on_the_mode(tmp_path):
    """Diekmann & Cheng's headline on the linear track: the default mode replays forward and
    reverse sequences alike, the reverse mode almost only reverse ones."""
    import cobelrun
    from cobelrun.analysis.replay import direction_counts, replay_events

    share = {}
    for mode in ("default", "reverse"):
        run = cobelrun.run("linear_track", ["agent=sfma", f"agent.mode={mode}", "task.runs=5",
                                            "task.protocol.phases.0.trials=30",
                                            "task.record.mcap=false", "task.save_agents=false"],
                           out=tmp_path / mode)  # fmt: skip
        counts = direction_counts(replay_events(run.table("replays")), 5).loc["end"]
        assert counts["forward"] + counts["reverse"] >= 40, counts
        share[mode] = counts["reverse"] / (counts["forward"] + counts["reverse"])
    assert 0.25 < share["default"] < 0.8 and share["reverse"] > 0.9, share
