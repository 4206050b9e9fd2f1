"""The Morris water maze task with Foster et al.'s actor-critic: acceptance, agent, CLI."""

from __future__ import annotations

import time

import numpy as np
import pandas as pd
import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from cobelrun.agents.actor_critic import ActorCritic
from cobelrun.analysis.watermaze import QUADRANTS, add_days
from cobelrun.config import builtin_conf_dir, instantiate, register_resolvers
from cobelrun.errors import ConfigError
from cobelrun.runner import run
from tests import inprocess

cli = inprocess.cli  # fixture: cobel in this process


def _compose(*overrides: str):
    register_resolvers()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(builtin_conf_dir()), version_base="1.3"):
        return compose("config", overrides=list(overrides))


@pytest.fixture(scope="module")
def default_task(tmp_path_factory):
    """The default task (8 runs, seed 0) run once for the module: (trials table, seconds)."""
    out = tmp_path_factory.mktemp("wm")
    t0 = time.perf_counter()
    run(_compose("task=morris_water_maze"), out / "run", background_writes=False)
    return add_days(pd.read_parquet(out / "run" / "trials.parquet")), time.perf_counter() - t0


def test_acquisition_probe_and_reversal(default_task):
    """FACTS.md "Water maze": the actor-critic learns the reference-memory task within tens of
    trials, searches the trained quadrant in the probe, and is inflexible when the platform
    moves. Issue 13's acceptance: last-day latency <= 50% of day 1; probe target quadrant
    >= 0.40 on average and above each other quadrant; first reversal day slower than the last
    acquisition day."""
    trials, _ = default_task
    assert trials["run"].nunique() == 8
    acq = trials[trials.phase == "acquisition"].groupby("day")["escape_latency_s"].mean()
    assert len(acq) == 8 and acq.iloc[-1] <= 0.5 * acq.iloc[0]
    assert acq.iloc[0] > 60  # day 1: mostly searching (trials time out at 120 s)
    probe = trials[trials.phase == "probe"]
    assert len(probe) == 8 and (probe["escape_latency_s"] == 60.0).all()  # no platform: 60 s
    frac = {q: probe[f"{q}_quadrant_fraction"].mean() for q in QUADRANTS}
    assert frac["target"] >= 0.40
    assert all(frac["target"] > frac[q] for q in QUADRANTS[1:])
    assert (probe["platform"] == "platform").all()
    rev = trials[trials.phase == "reversal"]
    assert (rev["platform"] == "platform_reversal").all()
    assert rev[rev.day == 1]["escape_latency_s"].mean() > acq.iloc[-1]
    # latency in seconds is the step count times dt = 0.1 s
    np.testing.assert_allclose(trials["escape_latency_s"], trials["steps"] * 0.1)


def test_same_seed_same_trials(default_task, tmp_path):
    trials, _ = default_task
    cfg = _compose("task=morris_water_maze", "task.runs=2", "task.protocol.phases.2.trials=4")
    run(cfg, tmp_path / "a", background_writes=False)
    again = pd.read_parquet(tmp_path / "a" / "trials.parquet")
    first = trials[(trials.run < 2) & (trials.trial <= 32 + 1 + 4)]
    cols = ["run", "steps", "escape_latency_s", "path_length", "target_quadrant_fraction"]
    pd.testing.assert_frame_equal(
        first[cols].reset_index(drop=True), again[cols].reset_index(drop=True)
    )


# ---------------------------------------------------------------------------- the agent
@pytest.fixture
def pool_env():
    return instantiate("env", _compose("env=water_maze").env)


def test_actor_critic_seeded_and_saved(pool_env, tmp_path):
    env = pool_env
    env.apply_changes(starts=[[0.42, 0.3]])  # near the platform: some trials reach it
    env.np_random = np.random.default_rng(1)
    a = ActorCritic(env, critic_lr=0.1, actor_lr=0.1, seed=3)
    ba = a.train(4, 300)
    assert ba.terminated.any()
    env.apply_changes(starts=[[0.42, 0.3]])
    env.np_random = np.random.default_rng(1)
    b = ActorCritic(env, critic_lr=0.1, actor_lr=0.1, seed=3)
    bb = b.train(4, 300)
    np.testing.assert_array_equal(ba.step_pose, bb.step_pose)
    assert ba.step_pose.shape == (ba.n_steps, 3) and ba.start_pose.shape == (4, 3)
    assert np.abs(a.w).sum() > 0 and np.abs(a.z).sum() > 0  # rewarded trials moved the weights
    path = a.save(tmp_path / "ac")
    c = ActorCritic(env, seed=0)
    c.load(path)
    np.testing.assert_array_equal(c.z, a.z)
    np.testing.assert_array_equal(c.predict(np.eye(env.observation_space.shape[0])[:3]),
                                  a.predict(np.eye(env.observation_space.shape[0])[:3]))  # fmt: skip
    # bad files (shapes, NaN, other agents, ...) are the agent conformance suite's
    # (tests/test_agent_conformance.py runs every conf/agent YAML, this one included)


def test_actor_critic_rejects_bad_parameters(pool_env):
    with pytest.raises(ConfigError, match=r"agent.gamma must be a number in \[0.0, 1.0\]"):
        ActorCritic(pool_env, gamma=1.5)
    with pytest.raises(ConfigError, match=r"agent\.beta must be"):
        ActorCritic(pool_env, beta=-1)


def test_figure_morris_quick_and_bad_input_through_the_cli(cli, tmp_path):
    """``cobel figure morris --quick`` runs the task through the CLI (2 runs, 2 days, probe,
    1 reversal day) and draws every panel; a platform outside the pool is one line."""
    proc = cli("figure", "morris", "--quick")
    assert proc.returncode == 0, proc.stderr
    out = tmp_path / "results" / "figures"
    assert (out / "morris_quick.png").stat().st_size > 10_000
    table = pd.read_csv(out / "morris_quick.csv")
    daily = table[table["table"] == "daily"]
    assert list(daily["phase"]) == ["acquisition", "acquisition", "reversal"]
    assert (daily["runs"] == 2).all() and daily["escape_latency_s_mean"].between(0, 120).all()
    probe = table[table["table"] == "probe"]
    assert list(probe["quadrant"]) == list(QUADRANTS)
    assert probe["fraction_mean"].sum() == pytest.approx(1.0, abs=1e-6)
    bad = cli("run", "task=morris_water_maze", "env.goals.platform.x=1.2")
    assert bad.returncode != 0
    assert "goal 'platform' lies (partly) outside the arena" in bad.stderr
    assert len(bad.stderr.strip().splitlines()) == 1
