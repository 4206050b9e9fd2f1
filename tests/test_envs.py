"""Registry-driven conformance tests for every ``cobel/`` environment."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import cobelrun.envs
from cobelrun.envs import DiscreteGridWorldEnv, GridWorldEnv, from_layout, tmaze_paper
from cobelrun.errors import ConfigError, LayoutError

COBEL_IDS = sorted(env_id for env_id in gym.registry if env_id.startswith("cobel/"))
NON_SPATIAL = {"cobel/TwoAFC-v0", "cobel/Bandit-v0", "cobel/Sequence-v0"}
#: envs that take no gridworld ``world``: built with their defaults in the seeded-rollout test
NO_WORLD = NON_SPATIAL | {"cobel/Continuous2D-v0"}


def test_registry_has_cobel_envs() -> None:
    assert set(cobelrun.envs.ENV_IDS) <= set(COBEL_IDS)
    cobelrun.envs.register_envs()  # idempotent


@pytest.mark.parametrize("env_id", COBEL_IDS)
def test_check_env(env_id: str) -> None:
    check_env(gym.make(env_id).unwrapped, skip_render_check=True)


def rollout(env: gym.Env, seed: int, n: int = 200) -> list:
    rng = np.random.default_rng(seed)
    out = []
    obs, info = env.reset(seed=seed)
    out.append((np.asarray(obs).tolist(), info["state"]))
    for _ in range(n):
        obs, r, term, trunc, info = env.step(int(rng.integers(env.action_space.n)))
        out.append((np.asarray(obs).tolist(), r, term, trunc, info["state"]))
        if term or trunc:
            obs, info = env.reset()
            out.append((np.asarray(obs).tolist(), info["state"]))
    return out


@pytest.mark.parametrize("env_id", COBEL_IDS)
@pytest.mark.parametrize("slip", [0.0, 0.3])
def test_same_seed_same_rollout(env_id: str, slip: float) -> None:
    world = from_layout("S...\n.#..\nS..G", slip=slip)
    # envs without a gridworld are built with their defaults
    kwargs = {} if env_id in NO_WORLD else {"world": world, "max_steps": 15}
    if env_id == "cobel/Sequence-v0":  # its default is one scripted trial: nothing random
        kwargs = {"cues": ["A", "B"], "length": 4, "trial_types": {
            "A+": {"cues": {"A": [0, 4]}, "outcome": 1.0},
            "B-": {"cues": {"B": [0, 4]}, "outcome": 0.0}}}  # fmt: skip
    a = gym.make(env_id, **kwargs)
    b = gym.make(env_id, **kwargs)
    assert rollout(a, 7) == rollout(b, 7)
    assert rollout(a, 7) != rollout(a, 8)


@pytest.mark.parametrize("cls", [GridWorldEnv, DiscreteGridWorldEnv])
def test_max_steps_truncation(cls: type[GridWorldEnv]) -> None:
    env = cls(tmaze_paper(), max_steps=3)
    env.reset(seed=0)
    flags = [env.step(3)[3] for _ in range(3)]  # "down" at the start: stays, never terminal
    assert flags == [False, False, True]
    env.reset()
    assert env.steps == 0 and env.state == 38
    assert not GridWorldEnv(tmaze_paper()).reset(seed=0)[1] == {}


def test_step_semantics_and_info() -> None:
    env = GridWorldEnv()  # default: paper T-maze
    obs, info = env.reset(seed=1)
    assert obs == 38 and info == {"state": 38, "x": 3.0, "y": 1.0}
    for a in (1, 1, 1, 1, 1, 2, 2):
        obs, r, term, trunc, info = env.step(a)
        assert r == 0.0 and not term and not trunc
    obs, r, term, trunc, info = env.step(np.int64(2))
    assert (obs, r, term, trunc) == (6, 1.0, True, False)
    assert info == {"state": 6, "x": 6.0, "y": 6.0}


def test_apply_changes_and_reset_world() -> None:
    env = GridWorldEnv(tmaze_paper())
    env.apply_changes(rewards={"right_arm": 0.0, "left_arm": 1.0}, starts=["junction"])
    assert env.world.rewards[0] == 1.0 and env.world.rewards[6] == 0.0
    assert env.reset(seed=0)[0] == 3
    assert env.base_world.rewards[6] == 1.0 and env.base_world.starts.tolist() == [38]
    env.apply_changes(terminals={3: False, 4: True}, starts=[38])
    assert env.world.terminal[4]
    env.reset_world()
    assert env.world.rewards[6] == 1.0 and env.world.rewards[0] == 0.0
    assert not env.world.terminal[4] and env.reset()[0] == 38
    with pytest.raises(LayoutError, match="wall cell"):
        env.apply_changes(starts=[7])


def test_env_copies_the_world() -> None:
    world = tmaze_paper()
    env = GridWorldEnv(world)
    world.set_rewards({6: 5.0})
    assert env.world.rewards[6] == 1.0


def test_reset_draws_start_from_np_random() -> None:
    world = from_layout("S.S\n.S.")
    env = GridWorldEnv(world)
    env.reset(seed=3)
    rng = np.random.default_rng(3)
    starts = world.starts
    seen = [env.reset()[0] for _ in range(20)]
    expected = [int(starts[rng.integers(0, len(starts))]) for _ in range(21)][1:]
    assert seen == expected
    assert set(seen) == {0, 2, 4}


def test_stochastic_step_matches_cumsum_draw() -> None:
    world = from_layout("S...\n....\n...G", slip=0.4)
    env = GridWorldEnv(world)
    env.reset(seed=11)
    rng = np.random.default_rng(11)
    rng.integers(0, 1)  # the start draw
    s = 0
    for a in [2, 3, 2, 3, 0, 1] * 5:
        u = rng.random()
        expected = int(np.searchsorted(np.cumsum(world.T[s, a]), u, side="right"))
        s = env.step(a)[0]
        assert s == expected
        if world.terminal[s]:
            break


def test_action_mask() -> None:
    env = GridWorldEnv(tmaze_paper())
    mask = env.action_mask()
    assert mask.shape == (49, 4) and mask.dtype == bool
    assert mask[38].tolist() == [False, True, False, False]
    assert mask[3].tolist() == [True, False, True, True]
    assert not mask[7].any()  # wall cell


@pytest.mark.parametrize("bad", [4, -1, 1.5, "up", True, np.array([1, 2])])
def test_invalid_action(bad) -> None:
    env = GridWorldEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match="invalid action"):
        env.step(bad)


def test_discrete_observations() -> None:
    env = DiscreteGridWorldEnv(tmaze_paper())
    obs, info = env.reset(seed=0)
    assert obs.dtype == np.float32 and obs.shape == (49,)
    assert obs.argmax() == 38 and obs.sum() == 1.0 and info["state"] == 38
    assert env.observation_space == gym.spaces.Box(0.0, 1.0, (49,), np.float32)
    coords = DiscreteGridWorldEnv(tmaze_paper(), observations="coords")
    assert coords.reset(seed=0)[0].tolist() == [3.0, 1.0]
    custom = np.arange(49 * 2, dtype=float).reshape(49, 2)
    env2 = DiscreteGridWorldEnv(tmaze_paper(), observations=custom)
    assert env2.observation_space.shape == (2,) and env2.observation_space.high.max() == 97.0
    check_env(env2, skip_render_check=True)


def test_constructor_errors() -> None:
    with pytest.raises(ConfigError, match=r"did you mean 'onehot'"):
        DiscreteGridWorldEnv(observations="one_hot")
    with pytest.raises(ConfigError, match=r"shape \(S=49, d\)"):
        DiscreteGridWorldEnv(observations=np.zeros((3, 2)))
    with pytest.raises(ConfigError, match="max_steps must be a positive integer"):
        GridWorldEnv(max_steps=0)
    with pytest.raises(ConfigError, match="render_mode 'human' is not supported"):
        GridWorldEnv(render_mode="human")
    with pytest.raises(ConfigError, match="world must be a cobelrun World"):
        GridWorldEnv(world="tmaze")  # type: ignore[arg-type]


def test_render_ansi() -> None:
    env = GridWorldEnv(from_layout("S.G"), render_mode="ansi")
    env.reset(seed=0)
    assert env.render() == "A.G\n"
    assert GridWorldEnv().render() is None


@pytest.mark.parametrize("bad", [2, -1, True, np.array([1, 0]), 0.5])
def test_two_afc_rejects_invalid_actions(bad):
    from cobelrun.envs.choice import TwoAFCEnv

    env = TwoAFCEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"invalid action .*allowed: (integers )?0\.\.1"):
        env.step(bad)
    assert env.step(np.int64(1))[2] is True  # numpy integers are fine
