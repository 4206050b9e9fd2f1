"""Batched runs (``task.batch_runs``): the batched DQN learns as the sequential SB3 DQN does.

A batched run draws from the same random streams as the sequential run of the same seed and
applies the same update rule; only floating-point sums are ordered differently. So most runs
are identical trial for trial to their sequential twins (a run diverges once a rounding
difference flips a greedy choice), learning curves agree statistically, every run is
deterministic and a run does not depend on which other runs share its batch.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("stable_baselines3")

from cobelrun.api import compose
from cobelrun.errors import ConfigError
from cobelrun.runner import build_task, execute, run_seed
from tests.conftest import stop_on_call


def run_task(tmp_path, name: str, overrides: list[str]) -> pd.DataFrame:
    cfg = compose(None, overrides)
    task = build_task(cfg)
    folder = tmp_path / name
    folder.mkdir()
    execute(task, folder, background_writes=False)
    return pd.read_parquet(folder / "trials.parquet"), task, folder


def identical_runs(a: pd.DataFrame, b: pd.DataFrame) -> int:
    return sum(
        a[a.run == r].reset_index(drop=True).equals(b[b.run == r].reset_index(drop=True))
        for r in a["run"].unique()
    )


FIG9 = ["task=two_afc", "task.save_agents=none"]
#: DQN in an open field (variable trial lengths), then test trials without learning;
#: gradient clipping on (SB3's default max_grad_norm 10 is rarely reached: 0.5 is)
GRID = [
    "task=gridworld", "agent=dqn", "env.world.width=4", "env.world.height=4", "env.world.goal=15",
    "agent.learning_starts=20", "agent.max_grad_norm=0.5",
    "agent.net_arch=[32,32]", "task.protocol.max_steps=30", "task.save_agents=none",
    "task.record.steps=false", "task.record.mcap=false",
    "task.protocol.phases=[{name: train, trials: 6}, {name: probe, trials: 2, learning: false}]",
]  # fmt: skip


def test_initial_weights_and_update_rule_match_sb3():
    """Run r's initial network is exactly the sequential agent's; then three gradient steps
    on the same replay contents (same sampled indices) give the same parameters."""
    import torch
    from stable_baselines3.common.logger import configure

    cfg = compose(None, [*GRID, "task.runs=2", "task.batch_runs=false"])
    task = build_task(cfg)
    seeds = [run_seed(0, r)[0] for r in range(2)]
    agents = [task.make_agent(seed=s) for s in seeds]
    learner = agents[0].batch_learner(seeds, 100)
    rng = np.random.default_rng(5)
    n_obs = learner.obs_dim
    for r, agent in enumerate(agents):
        init, want = learner.view(r).get_state(), agent.get_state()
        for key in (k for k in want if k.startswith("policy.")):  # bit for bit
            np.testing.assert_array_equal(init[key], want[key], err_msg=key)
        np.testing.assert_allclose(learner.view(r).predict(np.arange(n_obs)),
                                   agent.predict(np.arange(n_obs)), rtol=1e-6, atol=1e-7)  # fmt: skip
        buf = agent.model.replay_buffer
        for _ in range(40):
            s, s2, a = rng.integers(n_obs), rng.integers(n_obs), rng.integers(4)
            rew, done = float(rng.random() < 0.2), bool(rng.random() < 0.1)
            buf.add(np.array([s]), np.array([s2]), np.array([[a]]), np.array([rew]),
                    np.array([done]), [{}])  # fmt: skip
            learner._store(np.array([r]), np.eye(n_obs, dtype=np.float32)[[s]],
                           np.eye(n_obs, dtype=np.float32)[[s2]], np.array([a]),
                           np.array([rew]), np.array([done]))  # fmt: skip
        agent.model.set_logger(configure(None, []))  # train() logs; no output
        with agent._rng_scope():
            agent.model.train(gradient_steps=3, batch_size=agent.model.batch_size)
    for _ in range(3):
        learner._gradient_step(np.ones(2, bool))
    for r, agent in enumerate(agents):
        got = learner.view(r).predict(np.arange(n_obs))
        np.testing.assert_allclose(got, agent.predict(np.arange(n_obs)), rtol=1e-5, atol=1e-6)
        state = learner.view(r).get_state()
        want = agent.get_state()
        assert set(state) == set(want)
        for key in want:
            np.testing.assert_allclose(state[key], want[key], rtol=1e-4, atol=1e-6, err_msg=key)
    assert torch.get_num_threads() == 1


def _fill(agents, learner, n_transitions: int, seed: int) -> None:
    """The same random transitions into each sequential agent's buffer and its batched run."""
    rng = np.random.default_rng(seed)
    n_obs = learner.obs_dim
    eye = np.eye(n_obs, dtype=np.float32)
    for r, agent in enumerate(agents):
        buf = agent.model.replay_buffer
        for _ in range(n_transitions):
            s, s2, a = rng.integers(n_obs), rng.integers(n_obs), rng.integers(4)
            rew, done = float(rng.random() < 0.2), bool(rng.random() < 0.1)
            buf.add(np.array([s]), np.array([s2]), np.array([[a]]), np.array([rew]),
                    np.array([done]), [{}])  # fmt: skip
            learner._store(np.array([r]), eye[[s]], eye[[s2]], np.array([a]), np.array([rew]),
                           np.array([done]))  # fmt: skip


@pytest.mark.parametrize("capacity", [1, 2, 7, 64, 100])
def test_batched_sum_tree_equals_sequential_trees(capacity):
    """BatchedSumTree row r holds bit for bit what a SumTree given run r's updates holds:
    random updates (duplicate leaves in one update: the last write wins, several runs per
    update, single leaves), totals, minima, leaf values and prefix-sum searches."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    from cobelrun.agents.per import BatchedSumTree, SumTree

    R = 4
    step = st.tuples(
        st.lists(st.integers(0, R - 1), min_size=1, max_size=6, unique=True),
        st.integers(1, 12),
        st.integers(0, 2**32 - 1),
    )

    @settings(max_examples=40, deadline=None, derandomize=True)
    @given(st.lists(step, min_size=1, max_size=8))
    def check(steps):
        trees, batched = [SumTree(capacity) for _ in range(R)], BatchedSumTree(R, capacity)
        for runs, k, seed in steps:
            rng = np.random.default_rng(seed)
            leaf = rng.integers(0, capacity, size=(len(runs), k))  # duplicates are likely
            vals = rng.random((len(runs), k)) * 10.0 ** rng.integers(-6, 3, size=(len(runs), k))
            for j, r in enumerate(runs):
                trees[r].update(leaf[j], vals[j])
            batched.update(np.array(runs)[:, None], leaf, vals)
            for r in range(R):
                np.testing.assert_array_equal(batched.sums[r], trees[r].sums)
                np.testing.assert_array_equal(batched.mins[r], trees[r].mins)
            assert batched.total().tolist() == [t.total for t in trees]
            assert batched.min().tolist() == [t.min for t in trees]
            u = rng.random((R, 9)) * batched.total()[:, None]
            u[:, 0] = 0.0
            u[:, 1] = np.nextafter(batched.total(), 0.0)
            want = np.array([trees[r].find(u[r]) for r in range(R)])
            np.testing.assert_array_equal(batched.find(u), want)
            some = np.array(runs)
            np.testing.assert_array_equal(batched.find(u[some], some), want[some])
            np.testing.assert_array_equal(
                batched.get(some[:, None], leaf), [trees[r][leaf[j]] for j, r in enumerate(runs)]
            )

    check()
    tree = BatchedSumTree(2, 8)
    tree.update(np.array([0, 0, 1, 0]), np.array([3, 5, 3, 3]), np.array([1.0, 2.0, 4.0, 0.5]))
    assert tree.total().tolist() == [2.5, 4.0] and tree.min().tolist() == [0.5, 4.0]
    with pytest.raises(ValueError, match="2 indices but 3 values"):
        tree.update(0, np.array([1, 2]), np.array([1.0, 2.0, 3.0]))


def _leaves(tree, run: int | None, n: int) -> np.ndarray:
    """The first ``n`` leaves, the total and the minimum of a (batched) sum tree's row."""
    if run is None:
        return np.r_[tree.sums[tree.size : tree.size + n], tree.total, tree.min]
    return np.r_[tree.sums[run, tree.size : tree.size + n], tree.total()[run], tree.min()[run]]


#: Fig. 9's task with prioritized replay (dqn_paper's dynamics, PER's defaults)
FIG9_PER = [*FIG9, "agent.prioritized=true"]


def test_prioritized_update_rule_matches_the_sequential_buffer():
    """Batched PER: on the same replay contents each run samples exactly the indices its
    sequential PrioritizedReplayBuffer samples (own generator, stratified, own beta), with
    the same importance weights, and ends with the same parameters, priorities (within float32
    rounding of the TD errors) and beta schedule after a few gradient steps."""
    import torch
    from stable_baselines3.common.logger import configure

    cfg = compose(None, [*GRID, "agent.prioritized=true", "+agent.per_beta_steps=4",
                         "task.runs=3", "task.batch_runs=false"])  # fmt: skip
    task = build_task(cfg)
    seeds = [run_seed(0, r)[0] for r in range(3)]
    agents = [task.make_agent(seed=s) for s in seeds]
    learner = agents[0].batch_learner(seeds, 100)
    assert learner.prioritized and learner.tree.size == 128
    _fill(agents, learner, 40, seed=5)
    for r, agent in enumerate(agents):  # new transitions at priority 1 in both
        np.testing.assert_array_equal(_leaves(learner.tree, r, 40),
                                      _leaves(agent.model.replay_buffer.tree, None, 40))  # fmt: skip
    # what each sequential buffer samples, recorded (the buffer's own generator)
    drawn: list[list[tuple[np.ndarray, np.ndarray]]] = [[] for _ in agents]
    for r, agent in enumerate(agents):
        buf = agent.model.replay_buffer
        sample = buf.sample

        def record(batch_size, env=None, sample=sample, r=r):
            data = sample(batch_size, env=env)
            drawn[r].append((data.indices.copy(), data.weights.numpy().reshape(-1).copy()))
            return data

        buf.sample = record
        agent.model.set_logger(configure(None, []))
        steps = 5 if r != 1 else 3
        with agent._rng_scope():
            agent.model.train(gradient_steps=steps, batch_size=agent.model.batch_size)
    got: list[list[tuple[np.ndarray, np.ndarray]]] = [[] for _ in agents]
    sample_prioritized = learner._sample_prioritized

    def record_batched(runs):
        idx, w = sample_prioritized(runs)
        for j, r in enumerate(runs):
            got[r].append((idx[j].copy(), w[j].copy()))
        return idx, w

    learner._sample_prioritized = record_batched
    for k in range(5):
        learner._gradient_step(np.array([True, k < 3, True]))  # run 1 waits after 3 steps
    for r, agent in enumerate(agents):
        buf = agent.model.replay_buffer
        assert len(got[r]) == len(drawn[r]) == (3 if r == 1 else 5)
        for k, ((gi, gw), (wi, ww)) in enumerate(zip(got[r], drawn[r], strict=True)):
            np.testing.assert_array_equal(gi, wi)
            if k == 0:  # every priority 1
                np.testing.assert_array_equal(gw, ww)
            else:  # priorities from float32 TD errors, rounded differently (the smallest
                # priority, from the smallest |TD error|, sets every weight)
                np.testing.assert_allclose(gw, ww, rtol=1e-4)
        assert learner.n_sampled[r] == buf.n_sampled
        # p^alpha of float32 TD errors: a small |TD error| carries a large relative rounding
        np.testing.assert_allclose(_leaves(learner.tree, r, 40), _leaves(buf.tree, None, 40),
                                   rtol=1e-4, atol=1e-5)  # fmt: skip
        assert learner.max_priority[r] == pytest.approx(buf.max_priority, rel=1e-5)
        state, want = learner.view(r).get_state(), agent.get_state()
        for key in want:
            np.testing.assert_allclose(state[key], want[key], rtol=1e-4, atol=1e-6, err_msg=key)
    # the sampling arithmetic alone, bit for bit: the sequential trees' leaves, generator
    # states and beta schedules copied into the batched run, then one more sample each
    learner._sample_prioritized = sample_prioritized
    for r, agent in enumerate(agents):
        buf = agent.model.replay_buffer
        learner.tree.update(r, np.arange(40), buf.tree[np.arange(40)])
        learner.per_rngs[r].bit_generator.state = buf.rng.bit_generator.state
    idx, w = learner._sample_prioritized(np.arange(3))
    for r, agent in enumerate(agents):
        data = agent.model.replay_buffer.sample(agent.model.batch_size)
        np.testing.assert_array_equal(idx[r], data.indices)
        np.testing.assert_array_equal(w[r], data.weights.numpy().reshape(-1))
    assert learner.n_sampled.tolist() == [6, 4, 6]
    assert torch.get_num_threads() == 1


def test_fig9_batched_matches_sequential(tmp_path):
    """Fig. 9 (two_afc, dqn_paper): same tables; most runs identical trial for trial."""
    seq, _, _ = run_task(tmp_path, "seq", [*FIG9, "task.runs=8", "task.batch_runs=false"])
    bat, task, _ = run_task(tmp_path, "bat", [*FIG9, "task.runs=8", "task.batch_runs=true"])
    assert task.batch == 8
    assert list(seq.columns) == list(bat.columns) and seq.dtypes.equals(bat.dtypes)
    assert len(seq) == len(bat) == 8 * 50
    assert identical_runs(seq, bat) >= 6


def test_batched_runs_are_deterministic_and_independent_of_the_batch(tmp_path):
    """Repeats give identical tables; runs trained 2 at a time equal runs trained 5 at once;
    variable trial lengths, masked waiting runs, clipping and test phases included."""
    a, task, _ = run_task(tmp_path, "a", [*GRID, "task.runs=5", "task.batch_runs=true"])
    b, _, _ = run_task(tmp_path, "b", [*GRID, "task.runs=5", "task.batch_runs=true"])
    c, task2, _ = run_task(tmp_path, "c", [*GRID, "task.runs=5", "task.batch_runs=2"])
    assert task.batch == 5 and task2.batch == 2
    pd.testing.assert_frame_equal(a, b)
    pd.testing.assert_frame_equal(a, c)
    train = a[a.phase == "train"]
    assert train["steps"].nunique() > 3  # trials of different lengths ran in lock-step
    assert (a[a.phase == "probe"]["trial_in_phase"].max()) == 2
    seq, _, _ = run_task(tmp_path, "seq", [*GRID, "task.runs=5", "task.batch_runs=false"])
    assert list(seq.columns) == list(a.columns)
    assert identical_runs(seq, a) >= 3


def test_batched_runs_apply_a_phase_cycle_trial_by_trial(tmp_path):
    """A phase with a per-trial cycle (the linear track's laps): batched runs go through the
    same run loop as sequential ones, one trial per piece with the cycle's change applied to
    every run's env, so trial k starts where cycle[k % 2] says, as in the sequential twin."""
    phases = ("task.protocol.phases=[{name: laps, trials: 5, "
              "cycle: [{starts: [0]}, {starts: [3]}]}]")  # fmt: skip
    args = [*GRID[:-1], phases, "task.runs=3"]
    bat, task, _ = run_task(tmp_path, "bat", [*args, "task.batch_runs=true"])
    seq, _, _ = run_task(tmp_path, "seq", [*args, "task.batch_runs=false"])
    assert task.batch == 3
    assert bat.start_state.tolist() == [0, 3, 0, 3, 0] * 3
    keys = ["run", "trial", "trial_in_phase", "start_state"]
    pd.testing.assert_frame_equal(bat[keys], seq[keys])


def test_fig9_prioritized_batched_matches_sequential(tmp_path):
    """Fig. 9 with prioritized replay: each batched run draws its replay batches from its own
    generator in the sequential buffer's order, so runs are identical trial for trial to the
    sequential PrioritizedDQN runs (measured: 8 of 8, and 20 of 20 with 20 runs) until a
    rounding difference flips a choice."""
    seq, _, _ = run_task(tmp_path, "seq", [*FIG9_PER, "task.runs=8", "task.batch_runs=false"])
    bat, task, _ = run_task(tmp_path, "bat", [*FIG9_PER, "task.runs=8", "task.batch_runs=auto"])
    assert task.batch == 8 and task.batch_note is None
    assert list(seq.columns) == list(bat.columns) and seq.dtypes.equals(bat.dtypes)
    assert len(seq) == len(bat) == 8 * 50
    assert identical_runs(seq, bat) >= 7


def test_prioritized_batched_runs_are_deterministic_and_independent_of_the_batch(tmp_path):
    """PER: repeats give identical tables and runs trained 2 at a time equal runs trained 4 at
    once (trials of different lengths: waiting runs neither sample nor change priorities nor
    move their target networks); the buffer wraps (buffer_size 40 < the steps a run takes).
    Against the sequential runs: every run's first two trials are identical and at least 2 of
    4 runs all the way (measured: 2 of 4; PER turns float32 rounding of TD errors into
    different priorities, and a stratified draw that crosses a moved boundary picks another
    transition, so long PER runs part from their twins sooner than uniform ones)."""
    per = [*GRID, "agent.prioritized=true", "agent.buffer_size=40", "task.runs=4"]
    a, task, _ = run_task(tmp_path, "a", [*per, "task.batch_runs=true"])
    b, _, _ = run_task(tmp_path, "b", [*per, "task.batch_runs=true"])
    c, task2, _ = run_task(tmp_path, "c", [*per, "task.batch_runs=2"])
    assert task.batch == 4 and task2.batch == 2
    pd.testing.assert_frame_equal(a, b)
    pd.testing.assert_frame_equal(a, c)
    train = a[a.phase == "train"]
    assert train["steps"].nunique() > 3 and train.groupby("run")["steps"].sum().min() > 40
    seq, _, _ = run_task(tmp_path, "seq", [*per, "task.batch_runs=false"])
    pd.testing.assert_frame_equal(seq[seq.trial <= 2], a[a.trial <= 2])
    assert identical_runs(seq, a) >= 2


def test_batched_agents_load_into_the_sequential_agent(tmp_path):
    """Saved batched runs are DQNAgent files: they load, and predict what the run learnt."""
    from cobelrun.io.agents_archive import read_agent

    _, task, folder = run_task(tmp_path, "a", [*GRID, "task.runs=3", "task.batch_runs=true",
                                                "task.save_agents=all"])  # fmt: skip
    _, _task_seq, folder_seq = run_task(tmp_path, "s", [*GRID, "task.runs=3",
                                                       "task.batch_runs=false",
                                                       "task.save_agents=all"])  # fmt: skip
    for run in range(3):
        arrays, meta = read_agent(folder / "agents.npz", run)
        agent = task.make_agent(seed=run_seed(0, run)[0])
        agent.load_state(arrays, meta, source="batched")
        arrays_seq, _ = read_agent(folder_seq / "agents.npz", run)
        assert set(arrays) == set(arrays_seq)
        assert int(arrays["num_timesteps"]) > 20


@pytest.mark.slow
@pytest.mark.parametrize("overrides", [FIG9, FIG9_PER], ids=["uniform", "prioritized"])
def test_fig9_learning_curves_agree_statistically(tmp_path, overrides):
    """40 runs of Fig. 9 (uniform and prioritized replay): mean reward per trial within 0.05 of
    the sequential curve over blocks of 10 trials, a two-sample t-test on per-run mean rewards
    does not reject, and at least 30 of 40 runs are identical."""
    from scipy import stats

    seq, _, _ = run_task(tmp_path, "seq", [*overrides, "task.runs=40", "task.batch_runs=false"])
    bat, _, _ = run_task(tmp_path, "bat", [*overrides, "task.runs=40", "task.batch_runs=true"])
    for df in (seq, bat):
        df["block"] = (df["trial"] - 1) // 10
    blocks = seq.groupby("block")["reward"].mean() - bat.groupby("block")["reward"].mean()
    assert blocks.abs().max() <= 0.05
    p = stats.ttest_ind(
        seq.groupby("run")["reward"].mean(), bat.groupby("run")["reward"].mean()
    ).pvalue
    assert p > 0.05
    assert identical_runs(seq, bat) >= 30


def test_bad_batch_settings_are_one_line_errors():
    with pytest.raises(ConfigError, match=r"batch_runs=true: agent DynaQ.* no batched"):
        build_task(compose(None, ["task=gridworld", "task.batch_runs=true"]))
    with pytest.raises(ConfigError, match="batch_runs"):
        build_task(compose(None, ["task=two_afc", "task.batch_runs=0"]))
    with pytest.raises(ConfigError, match=r"cannot batch this task: agent\.train_freq"):
        build_task(compose(None, ["task=two_afc", "agent.train_freq=2", "task.batch_runs=true"]))
    task = build_task(compose(None, ["task=two_afc", "agent.train_freq=2"]))
    assert task.batch == 0 and "train_freq" in task.batch_note
    task = build_task(compose(None, ["task=two_afc", "agent.prioritized=true"]))  # PER batches
    assert task.batch == 100 and task.batch_note is None


#: Fig. 7's task, shortened: exploration then reward, SR snapshots every 2 trials, steps of run 0
FIG7 = [
    "task=latent_learning", "task.protocol.phases.0.trials=3", "task.protocol.phases.1.trials=3",
    "task.protocol.max_steps=40", "task.monitors.activity.every=2", "task.save_agents=all",
]  # fmt: skip


@pytest.mark.parametrize("agent", ["dyna_dsr", pytest.param("dyna_dqn", marks=pytest.mark.slow)])
def test_dyna_batched_runs_match_sequential(tmp_path, agent):
    """Batched Dyna agents draw what their sequential twins draw: same trials, activity
    within rounding, steps of run 0, saved agents loadable; chunks of 2 give the same."""
    from cobelrun.io.agents_archive import read_agent

    extra = [f"agent={agent}", "task.runs=3"]
    if agent == "dyna_dqn":
        extra.append("task.monitors.activity.layers=[q/output]")
    seq, _, f_seq = run_task(tmp_path, "seq", [*FIG7, *extra, "task.batch_runs=false"])
    bat, task, f_bat = run_task(tmp_path, "bat", [*FIG7, *extra, "task.batch_runs=true"])
    two, task2, _ = run_task(tmp_path, "two", [*FIG7, *extra, "task.batch_runs=2"])
    assert task.batch == 3 and task2.batch == 2
    pd.testing.assert_frame_equal(bat, two)
    assert identical_runs(seq, bat) >= 2
    act_s, act_b = (pd.read_parquet(f / "activity.parquet") for f in (f_seq, f_bat))
    keys = ["run", "trial", "layer", "unit", "probe"]
    pd.testing.assert_frame_equal(act_s[keys], act_b[keys])
    same = [r for r in range(3) if seq[seq.run == r].reset_index(drop=True)
            .equals(bat[bat.run == r].reset_index(drop=True))]  # fmt: skip
    close = act_s.run.isin(same)
    np.testing.assert_allclose(act_b.value[close], act_s.value[close], rtol=1e-3, atol=1e-4)
    steps_s, steps_b = (pd.read_parquet(f / "steps.parquet") for f in (f_seq, f_bat))
    assert list(steps_s.columns) == list(steps_b.columns)
    if 0 in same:
        pd.testing.assert_frame_equal(steps_s, steps_b)
    agent_obj = task.make_agent(seed=run_seed(0, 1)[0])
    arrays, meta = read_agent(f_bat / "agents.npz", 1)
    agent_obj.load_state(arrays, meta, source="batched")
    assert int(agent_obj.memory.n_visited[0]) > 0


def test_row_adam_is_one_adam_per_run():
    """RowAdam steps each run as its own torch.optim.Adam would (own step count); a run left
    out of a step keeps its parameters, moments and step count exactly."""
    import torch

    from cobelrun.agents.batched_ops import RowAdam

    gen = torch.Generator().manual_seed(3)
    stacked = [torch.randn(3, 4, 5, generator=gen), torch.randn(3, 1, 5, generator=gen)]
    refs = [[t[r].clone().requires_grad_() for t in stacked] for r in range(3)]
    opts = [torch.optim.Adam(p, lr=0.01, betas=(0.9, 0.99), eps=1e-7) for p in refs]
    adam = RowAdam(stacked, lr=0.01, betas=(0.9, 0.99), eps=1e-7)
    for runs in ([0, 1, 2], [0, 2], [1], [0, 1, 2]):
        runs = np.array(runs)
        grads = [torch.randn(len(runs), *t.shape[1:], generator=gen) for t in stacked]
        before = [t[1].clone() for t in stacked]
        adam.step(grads, runs)
        for i, r in enumerate(runs):
            for p, g in zip(refs[r], grads, strict=True):
                p.grad = g[i].clone()
            opts[r].step()
        if 1 not in runs:
            for t, old in zip(stacked, before, strict=True):
                assert torch.equal(t[1], old)
    assert adam.steps.tolist() == [3, 3, 3]
    for r in range(3):
        for t, ref, (m, v) in zip(stacked, refs[r], adam.moments(r), strict=True):
            torch.testing.assert_close(t[r], ref.detach(), rtol=1e-5, atol=1e-6)
            state = opts[r].state[ref]
            torch.testing.assert_close(m, state["exp_avg"], rtol=1e-5, atol=1e-7)
            torch.testing.assert_close(v, state["exp_avg_sq"], rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize("agent", ["dyna_dsr", "dyna_dqn"])
def test_dyna_state_table_update_equals_the_per_sample_update(agent):
    """With one-hot observations the batched Dyna update runs the networks on every state once
    and sums the loss per (head, state) row; it trains the networks as the per-sample update
    does (runs left out of a step included)."""
    import torch

    from cobelrun.agents.batched_dyna import BatchedDyna

    layers = "q/output" if agent == "dyna_dqn" else "sr/output"  # Dyna-DQN has no SR network
    task = build_task(compose(None, [*FIG7, f"agent={agent}", "task.runs=3",
                                     f"task.monitors.activity.layers=[{layers}]",
                                     "task.batch_runs=false"]))  # fmt: skip

    def learner() -> BatchedDyna:
        agents = [task.make_agent(seed=run_seed(0, r)[0]) for r in range(3)]
        for ag in agents:
            ag._loop_mask = ag._mask()
        return BatchedDyna(agents, successor=agent == "dyna_dsr")

    table, per_sample = learner(), learner()
    per_sample.onehot = False
    assert table.onehot
    rng = np.random.default_rng(1)
    n_states, n = table.agents[0].n_states, 101
    for step in range(4):
        S, S2 = rng.integers(n_states, size=(2, 3, n))
        A = rng.integers(4, size=(3, n))
        rew = rng.random((3, n)) * (rng.random((3, n)) < 0.2)
        term = (rng.random((3, n)) < 0.1).astype(float)
        train = np.array([True, step != 1, True])
        for lrn in (table, per_sample):
            lrn.update(S, A, rew, S2, term, train)
    nets = [(table.net, per_sample.net)]
    if table.reward is not None:
        nets.append((table.reward, per_sample.reward))
    for a, b in nets:
        assert a.optimizer.steps.tolist() == [4, 3, 4]
        for x, y in zip([*a.leaves, *a.target], [*b.leaves, *b.target], strict=True):
            torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-6)
    moved = [(x - y).abs().max() for x, y in zip(table.net.leaves, learner().net.leaves,
                                                  strict=True)]  # fmt: skip
    assert max(moved) > 1e-3  # the updates did change the networks


@pytest.mark.parametrize("exc", [KeyboardInterrupt, RuntimeError])
def test_interrupted_chunk_keeps_its_finished_phases(tmp_path, monkeypatch, exc):
    """Ctrl-C (or an error) in a chunk's second phase: the first phase of every run of the
    chunk is in the tables, exactly as the uninterrupted job recorded it, and the files are
    complete (a sequential run keeps its finished phases too)."""
    from cobelrun.agents.batched_dqn import BatchedDQN

    args = [*GRID, "task.runs=3", "task.batch_runs=true"]
    full, _, _ = run_task(tmp_path, "full", args)
    stop_on_call(monkeypatch, BatchedDQN, "run_phase", 2, exc)  # in the second phase
    with pytest.raises(exc):
        run_task(tmp_path, "stopped", args)
    kept = pd.read_parquet(tmp_path / "stopped" / "trials.parquet")
    want = full[full.phase == "train"].reset_index(drop=True)
    assert len(want) == 3 * 6 and sorted(kept.run.unique()) == [0, 1, 2]
    pd.testing.assert_frame_equal(kept, want)


def _early_late(trials: pd.DataFrame) -> tuple[float, float]:
    return (trials[trials.trial.between(6, 10)].reward.mean(),
            trials[trials.trial.between(41, 50)].reward.mean())  # fmt: skip


def test_two_afc_fast_learns_within_a_couple_of_trials(tmp_path):
    """task=two_afc_fast (Q from 0.5, 4 gradient steps per step), 100 agents, seed 0: mean
    training reward >= 0.75 over trials 6-10 and within 0.05 of the epsilon ceiling 0.85 over
    trials 41-50 (issue 17); the original's dynamics (task=two_afc) stay below 0.75 early."""
    fast, task, _ = run_task(tmp_path, "fast", ["task=two_afc_fast", "task.save_agents=none"])
    assert task.batch == 100 and fast.run.nunique() == 100
    early, late = _early_late(fast)
    assert early >= 0.75 and late >= 0.80, (early, late)
    paper, _, _ = run_task(tmp_path, "paper", FIG9)
    assert _early_late(paper)[0] < 0.72


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_two_afc_fast_other_seeds(tmp_path, seed):
    """The same acceptance for seeds 1-4 (measured: 0.764-0.800 over trials 6-10, 0.845-0.872
    over 41-50)."""
    fast, _, _ = run_task(tmp_path, "fast", ["task=two_afc_fast", "task.save_agents=none",
                                             f"seed={seed}"])  # fmt: skip
    early, late = _early_late(fast)
    assert early >= 0.75 and late >= 0.80, (early, late)
