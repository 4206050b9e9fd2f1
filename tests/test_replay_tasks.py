"""Issue 14, second round: noisy rewards, per-trial protocol cycles, the linear track, replays
in ``run.mcap``."""

from __future__ import annotations

import numpy as np
import pytest

from cobelrun.agents import PMA, DynaQ
from cobelrun.config import instantiate
from cobelrun.envs import GridWorldEnv, from_layout
from cobelrun.envs.world import World
from cobelrun.errors import ConfigError, LayoutError
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
