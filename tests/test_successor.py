"""Successor-representation agents, value iteration and the revaluation tasks (Russek et al. 2017)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from cobelrun.agents import SRMB, SRTD, SRDyna, SuccessorCore, ValueIteration
from cobelrun.agents.base import TrialCallback as TrialCallbackBase
from cobelrun.analysis.revaluation import revaluation_scores
from cobelrun.envs import GridWorldEnv, open_field
from cobelrun.errors import ConfigError
from cobelrun.revaluation import RevaluationJob, revaluation_world, transitions
from tests.test_configs import _compose


def test_core_from_model_is_the_fixed_point_of_its_td_rule():
    rng = np.random.default_rng(0)
    T = transitions()
    terminal = revaluation_world().terminal
    policy = np.array([0, 1, 1, 0, 0, 1, 0])
    core = SuccessorCore(7, 4, 0.9, 1.0, 1.0)
    core.from_model(T, policy, terminal)
    # M(s,a) = 1_{s'} + gamma M(s', pi(s')) for every (s, a) with a deterministic successor s'
    for s in range(7):
        for a in range(4):
            s2 = int(T[s, a].argmax())
            expect = np.eye(7)[s2] + (0 if terminal[s2] else 0.9 * core.M[s2, policy[s2]])
            np.testing.assert_allclose(core.M[s, a], expect, atol=1e-12)
    core.w[:] = rng.random(7)
    np.testing.assert_allclose(core.q(0), core.M[0] @ core.w)


def test_value_iteration_plans_the_optimal_values():
    env = GridWorldEnv(open_field(4, 4, starts=[0], goal=15))
    env.unwrapped.np_random = np.random.default_rng(0)
    agent = ValueIteration(env, seed=0, epsilon=0.3)
    batch = agent.train(60, 50)
    # the goal is 6 steps away and pays 1 on arrival: V(start) = gamma^5
    assert agent.predict(np.array([0]))[0].max() == pytest.approx(0.9**5)
    assert np.median(batch.steps[-10:]) <= 8


@pytest.mark.parametrize("cls", [SRTD, SRDyna, SRMB, ValueIteration])
def test_seeded_runs_repeat_and_save_load_round_trip(cls, tmp_path):
    def trained(seed):
        env = GridWorldEnv(open_field(4, 4, starts=[0], goal=15))
        env.unwrapped.np_random = np.random.default_rng(1)
        agent = cls(env, seed=seed)
        return agent, agent.train(15, 50)

    a, batch_a = trained(3)
    _, batch_b = trained(3)
    np.testing.assert_array_equal(batch_a.steps, batch_b.steps)
    assert batch_a.steps[-5:].mean() < 15  # learns the 6-step path (from up to 50)
    path = a.save(tmp_path / "agent")
    c, _ = trained(4)
    c.load(path)
    for key, arr in a.get_state().items():
        np.testing.assert_array_equal(c.get_state()[key], arr)
    np.testing.assert_allclose(c.predict(np.arange(16)), a.predict(np.arange(16)))


@pytest.mark.parametrize(
    ("cls", "kw", "match"),
    [
        (SRTD, dict(learning_rate=2.0), r"agent.learning_rate must be a number in \[0, 1.0\]"),
        (SRDyna, dict(replay_batch=-1), "agent.replay_batch must be an integer >= 0"),
        (
            SRMB,
            dict(policy="greed"),
            "agent.policy 'greed' is not known; allowed: 'epsilon_greedy'",
        ),
        (ValueIteration, dict(tolerance=0), "agent.tolerance must be a number > 0"),
    ],
)
def test_bad_parameters_one_line_config_error(cls, kw, match):
    with pytest.raises(ConfigError, match=match):
        cls(GridWorldEnv(revaluation_world()), **kw)


def _job(design, runs=6):
    cfg = _compose("task=reward_revaluation")
    agents = {k: v for k, v in cfg.task.job.agents.items()
              if k in ("q_learning", "dyna_q", "sr_td", "sr_mb", "sr_dyna")}  # fmt: skip
    return RevaluationJob(design=design, agents=agents, runs=runs, training_trials=200,
                          revaluation_trials=20, replay_budgets=[10])  # fmt: skip


def test_russek_revaluation_pattern():
    """SR-TD: reward only; SR-MB: reward and transition; SR-Dyna and Dyna-Q with replay: all
    three; Q-learning: none (6 seeded runs per agent, scores in [-1, 1])."""
    tables = [_job(d).table(seed=0) for d in ("reward", "transition", "policy")]
    scores = revaluation_scores(pd.concat(tables)).set_index(["design", "agent"])["score"]
    solves = {
        "q_learning": (False, False, False),
        "sr_td": (True, False, False),
        "sr_mb": (True, True, False),
        "sr_dyna": (True, True, True),
        "dyna_q": (True, True, True),
    }
    for agent, expected in solves.items():
        for design, ok in zip(("reward", "transition", "policy"), expected, strict=True):
            score = scores[(design, agent)]
            assert (score >= 0.8) if ok else (score <= 0.2), (design, agent, score)


def test_revaluation_job_config_errors():
    cfg = _compose("task=reward_revaluation")
    with pytest.raises(ConfigError, match=r"task.job.design 'rewards' is not known"):
        RevaluationJob(design="rewards", agents=cfg.task.job.agents)
    with pytest.raises(ConfigError, match=r"task.job.replay_budgets must be integers >= 0"):
        RevaluationJob(design="reward", agents=cfg.task.job.agents, replay_budgets=[-1])
    with pytest.raises(ConfigError, match=r"task.job.agents is empty"):
        RevaluationJob(design="reward", agents={})


def test_cli_revaluation_writes_scores(cobel, tmp_path):
    out = tmp_path / "run"
    proc = cobel("run", "task=policy_revaluation", "task.job.runs=2", "task.job.training_trials=50",
                 "task.job.revaluation_trials=5", "task.job.replay_budgets=[0]",
                 f"hydra.run.dir={out}")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    scores = pd.read_csv(out / "revaluation_scores.csv")
    assert set(scores["agent"]) == {"q_learning", "dyna_q", "sr_td", "sr_mb", "sr_dyna",
                                    "value_iteration"}  # fmt: skip
    assert scores["score"].between(-1, 1).all() and (scores["runs"] == 2).all()


@pytest.mark.slow
def test_revaluation_pattern_with_20_runs_and_replay_budgets():
    """The acceptance setting (20 runs) and how the pattern changes with the replay budget."""
    cfg = _compose("task=reward_revaluation")
    scores = {}
    for design in ("reward", "transition", "policy"):
        job = RevaluationJob(design=design, agents=cfg.task.job.agents, runs=20,
                             replay_budgets=[1, 10, 50])  # fmt: skip
        table = revaluation_scores(job.table(seed=0))
        for row in table.itertuples():
            scores[(design, row.agent, row.replay_budget)] = row.score
    for design in ("reward", "transition", "policy"):
        assert scores[(design, "q_learning", -1)] == 0.0
        assert scores[(design, "value_iteration", -1)] >= 0.9
        for agent in ("dyna_q", "sr_dyna"):
            assert scores[(design, agent, 50)] >= 0.9, (design, agent)
    # little replay: SR-Dyna still revalues rewards; policy revaluation needs more replay
    assert scores[("reward", "sr_dyna", 1)] >= 0.9
    assert scores[("policy", "sr_dyna", 1)] <= 0.3 and scores[("policy", "dyna_q", 1)] <= 0.3
    assert scores[("reward", "sr_td", -1)] >= 0.9 and scores[("transition", "sr_td", -1)] <= 0.1
    assert scores[("transition", "sr_mb", -1)] >= 0.9 and scores[("policy", "sr_mb", -1)] <= 0.1


# ------------------------------------------------------------------ Russek's grid designs
def _optimal_q(world):
    """Optimal Q of a known world (arrival rewards, no bootstrap from terminals)."""
    V = np.zeros(world.n_states)
    for _ in range(500):
        Q = world.T @ (world.rewards + 0.9 * V)
        V = np.where(world.terminal, 0.0, Q.max(axis=1))
    return Q


@pytest.mark.parametrize("design", ["reward", "transition", "policy"])
def test_grid_designs_need_a_new_path_from_the_start(design):
    """In every grid design the phase-1 optimal path from the start does not reach the new goal
    in the phase-2 world, and the phase-2 optimal path does (within 1.5 x the shortest)."""
    from cobelrun.revaluation import GRID_DESIGNS, greedy_reaches

    grid = GRID_DESIGNS[design]

    class Oracle:  # an agent that knows the optimal values of a world
        def __init__(self, world):
            self.Q = _optimal_q(world)

        def predict(self, states):
            return self.Q[states]

    env = GridWorldEnv(grid.world())
    before = Oracle(env.unwrapped.world)
    grid.apply(env)
    world = env.unwrapped.world
    start, goal = world.state(grid.start), world.state(grid.goal)
    rng = np.random.default_rng(0)
    assert greedy_reaches(before, world, start, goal, rng) == 0.0
    assert greedy_reaches(Oracle(world), world, start, goal, rng) == 1.0
    if design == "policy":  # the states between the start and B pointed to A in phase 1
        q1 = before.Q
        row = [world.state([1, c]) for c in range(5, 9)]
        assert (q1[row].argmax(axis=1) == 0).all()  # left, towards A
    if design == "transition":  # the upper corridor cannot lead back into the start
        door = world.state("door")
        assert world.next_state[door, 3] == door  # down from the door is blocked


def test_grid_design_phase_two_changes():
    from cobelrun.revaluation import GRID_DESIGNS

    env = GridWorldEnv(GRID_DESIGNS["reward"].world())
    w = env.unwrapped.world
    assert not w.terminal.any() and not w.rewards.any()  # latent learning: no reward at first
    assert len(np.unique(w.starts)) == int((~w.blocked).sum())  # exploration from everywhere
    GRID_DESIGNS["reward"].apply(env)
    assert w.rewards[w.state("R")] == 10 and w.terminal[w.state("R")]
    assert sorted(w.starts.tolist()) == sorted([w.state("R_up"), w.state("R_left")])
    env = GridWorldEnv(GRID_DESIGNS["transition"].world())
    w = env.unwrapped.world
    share = np.mean(w.starts == w.state("start"))
    assert 0.45 < share < 0.55  # half of the phase-1 trials start at the start
    b, c = w.state("B"), w.state("C")
    assert w.next_state[b, 2] == c
    GRID_DESIGNS["transition"].apply(env)
    assert env.unwrapped.world.next_state[b, 2] == b  # walled off
    with pytest.raises(ConfigError, match=r"task.job.maze 'maze' is not known"):
        RevaluationJob(design="reward", agents={"q": {"_target_": "cobelrun.agents.DynaQ"}},
                       maze="maze")  # fmt: skip


def _grid_scores(agents, runs, budgets=(0,)):
    cfg = _compose("task=reward_revaluation")
    nodes = {k: v for k, v in cfg.task.job.agents.items() if k in agents}
    scores = {}
    for design in ("reward", "transition", "policy"):
        job = RevaluationJob(design=design, agents=nodes, runs=runs, replay_budgets=list(budgets),
                             maze="grid")  # fmt: skip
        for row in revaluation_scores(job.table(seed=0)).itertuples():
            scores[(design, row.agent, row.replay_budget)] = (row.score, row.after)
    return scores


def test_russek_pattern_in_the_grid_designs():
    """Russek et al.'s gridworlds, 5 seeded runs: SR-TD solves latent learning only, SR-MB
    latent learning and the detour but not policy revaluation, Q-learning none, value
    iteration all three (score: greedy paths from the start reaching the new goal)."""
    scores = _grid_scores(("q_learning", "sr_td", "sr_mb", "value_iteration"), runs=5)
    solves = {
        "q_learning": (False, False, False),
        "sr_td": (True, False, False),
        "sr_mb": (True, True, False),
        "value_iteration": (True, True, True),
    }
    for agent, expected in solves.items():
        for design, ok in zip(("reward", "transition", "policy"), expected, strict=True):
            score, after = scores[(design, agent, -1)]
            assert (score >= 0.8 and after == 1.0) if ok else score <= 0.2, (design, agent, score)


@pytest.mark.slow
def test_grid_designs_need_enough_replay():
    """Dyna-Q and SR-Dyna solve all three grid revaluations with 1000 backups per step, and
    Dyna-Q none with 10 (20 runs, the setting of docs/replay.md)."""
    scores = _grid_scores(("dyna_q", "sr_dyna"), runs=20, budgets=(10, 1000))
    for design in ("reward", "transition", "policy"):
        for agent in ("dyna_q", "sr_dyna"):
            score, after = scores[(design, agent, 1000)]
            assert after >= 0.9 and score >= 0.7, (design, agent, score, after)
        assert scores[(design, "dyna_q", 10)][0] <= 0.1
    assert (
        scores[("reward", "sr_dyna", 10)][0] >= 0.7
    )  # SR-Dyna: latent learning without much replay


# -- the compiled trial loops (sr_kernels, srmb_kernels) ------------------------------------
SR_VARIANTS = [
    (SRTD, {}),
    (SRDyna, {"replay_batch": 3}),
    (SRDyna, {"replay_batch": 2, "replay_reward": True}),
    (SRMB, {}),
]


def _sr_run(cls, kw, engine, callbacks=(), world=None):
    from cobelrun.envs import from_layout

    world = world or from_layout("S....\n.#.#.\n....G", slip=0.2)
    world.starts = np.array([0, 1, 5])  # several starts: the env's generator draws each trial
    env = GridWorldEnv(world)
    env.unwrapped.np_random = np.random.default_rng(7)
    agent = cls(env, seed=11, engine=engine, **kw)
    batches = [agent.train(12, 40, callbacks), agent.test(3, 40, callbacks)]
    return agent, batches


@pytest.mark.parametrize("policy", ["epsilon_greedy", "softmax"])
@pytest.mark.parametrize(("cls", "kw"), SR_VARIANTS)
def test_compiled_and_python_paths_give_identical_tables(cls, kw, policy):
    """Same seeds: the compiled trial kernel and the Python step loop (per-step hooks) make the
    same draws, so the trial and step tables and the learned arrays are identical, on a
    stochastic world with several start states."""
    kw = {**kw, "policy": policy, "beta": 3.0}
    a, fast = _sr_run(cls, kw, "compiled")
    b, slow = _sr_run(cls, kw, "python")
    for x, y in zip(fast, slow, strict=True):
        for field in ("start_state", "end_state", "steps", "terminated", "offsets",
                      "step_state", "step_action", "step_next_state", "step_reward"):  # fmt: skip
            np.testing.assert_array_equal(getattr(x, field), getattr(y, field), err_msg=field)
    assert fast[0].steps.sum() > 30
    for key, arr in a.get_state().items():
        np.testing.assert_array_equal(arr, b.get_state()[key], err_msg=key)


class _Steps(TrialCallbackBase):
    def __init__(self):
        self.n = 0

    def _on_step(self, agent, trial, step, transition):
        self.n += 1


class _Ends(TrialCallbackBase):
    def __init__(self):
        self.ends = []

    def _on_trial_end(self, agent, trial, record):
        self.ends.append((trial, len(record["actions"]), float(agent.core.w.sum())))


@pytest.mark.parametrize(("cls", "kw"), SR_VARIANTS[1:2] + SR_VARIANTS[3:])
def test_trial_end_callbacks_run_between_compiled_trials(cls, kw):
    """Trial-end hooks keep the compiled path (one trial per call) with the same results;
    per-step hooks take the Python loop, also with the same results; engine='compiled'
    refuses per-step hooks in one line."""
    _, plain = _sr_run(cls, kw, "auto")
    ends = _Ends()
    _, hooked = _sr_run(cls, kw, "auto", [ends])
    steps = _Steps()
    _, stepped = _sr_run(cls, kw, "auto", [steps])
    for x, y, z in zip(plain, hooked, stepped, strict=True):
        np.testing.assert_array_equal(x.step_action, y.step_action)
        np.testing.assert_array_equal(x.step_action, z.step_action)
    assert [n for _, n, _ in ends.ends] == plain[0].steps.tolist() + plain[1].steps.tolist()
    assert steps.n == sum(int(b.steps.sum()) for b in plain)
    with pytest.raises(ConfigError, match=r"agent.engine .compiled. cannot run per-step callbacks"):
        _sr_run(cls, kw, "compiled", [_Steps()])


def test_sr_dyna_replay_reward_moves_w_towards_the_replayed_rewards():
    """With replay_reward, replayed experiences also update w: at a slow reward rate (0.1),
    w(goal) after 30 rewarded trials is ~1 - 0.9^30 from experience alone and ~1 with replayed
    rewards as well."""
    ws = {}
    for flag in (False, True):
        env = GridWorldEnv(open_field(4, 4, starts=[0], goal=15))
        env.unwrapped.np_random = np.random.default_rng(1)
        agent = SRDyna(env, seed=3, replay_batch=20, replay_reward=flag, reward_rate=0.1)
        agent.train(30, 50)
        ws[flag] = agent.core.w[15]
    assert ws[False] < 0.97 and ws[True] > 0.999


def test_bad_engine_is_one_line_config_error():
    with pytest.raises(ConfigError, match=r"agent.engine 'fast' is not known; allowed: 'auto'"):
        SRTD(GridWorldEnv(revaluation_world()), engine="fast")
    with pytest.raises(ConfigError, match=r"agent.replay_reward must be true or false"):
        SRDyna(GridWorldEnv(revaluation_world()), replay_reward="yes")


def _v1_sr_dyna():
    """An SR-Dyna agent trained a little, its state as schema 1 wrote it (no model_reward)."""
    env = GridWorldEnv(open_field(4, 4, starts=[0], goal=15))
    agent = SRDyna(env, seed=0, replay_batch=2)
    agent.train(5, 50)
    state = {k: v.copy() for k, v in agent.get_state().items() if k != "model_reward"}
    meta = {**agent.saved_meta(), "schema_version": 1}
    return env, state, meta


def test_sr_dyna_loads_schema_1_files_and_archives(tmp_path):
    """Schema 1 (before model_reward) is migrated on load, from a file and from a run's
    agents.npz: the learned arrays as saved, model_reward = w[model_next] where experienced;
    a newer schema than this cobel knows is refused in one line."""
    import json

    from cobelrun.agents.base import META_KEY, check_load_from
    from cobelrun.io.agents_archive import AgentArchive
    from cobelrun.runner import load_saved_agent

    env, state, meta = _v1_sr_dyna()
    seen = state["model_next"] >= 0
    assert seen.any()
    expected = np.where(seen, state["w"][np.maximum(state["model_next"], 0)], 0.0)
    path = tmp_path / "v1.npz"
    np.savez(path, **{META_KEY: np.array(json.dumps(meta))}, **state)
    run_dir = tmp_path / "run"
    archive = AgentArchive(run_dir / "agents.npz", run_dir / ".parts-agents")
    archive.add(0, state, meta)
    archive.close()
    for load in (lambda a: a.load(path), lambda a: load_saved_agent(a, str(run_dir), 0)):
        fresh = SRDyna(env, seed=1, replay_batch=2)
        load(fresh)
        for key in ("M", "w", "model_next"):
            np.testing.assert_array_equal(fresh.get_state()[key], state[key], err_msg=key)
        np.testing.assert_array_equal(fresh.model_reward, expected)
    check_load_from(SRDyna(env, seed=1), str(path), 1)
    check_load_from(SRDyna(env, seed=1), str(run_dir), 1)
    newer = tmp_path / "v3.npz"
    np.savez(newer, **{META_KEY: np.array(json.dumps({**meta, "schema_version": 3}))}, **state)
    with pytest.raises(ConfigError, match=r"v3.npz: schema version 3, expected 2$"):
        SRDyna(env, seed=1).load(newer)
