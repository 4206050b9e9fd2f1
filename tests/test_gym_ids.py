"""Every registered env id is reachable from gymnasium with no prior import; task envs get a
TimeLimit from the config."""

from __future__ import annotations

import subprocess
import sys

import pytest
from gymnasium.utils.env_checker import check_env

from cobelrun.envs import ENV_IDS


def test_module_prefixed_ids_need_no_import():
    code = (
        "import gymnasium as gym, sys\n"
        f"ids = {sorted(ENV_IDS)!r}\n"
        "assert 'cobelrun' not in sys.modules\n"
        "for i in ids:\n"
        "    env = gym.make('cobelrun.envs:' + i)\n"
        "    env.reset(seed=0); env.step(env.action_space.sample())\n"
        "    print(i, env.unwrapped.__class__.__name__)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert len(out.stdout.splitlines()) == len(ENV_IDS)


def test_every_id_is_documented():
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "envs.md").read_text()
    assert all(f"`{i}`" in text for i in ENV_IDS)


@pytest.mark.parametrize(("task", "steps"), [("tmaze_extinction", 35), ("latent_learning", None)])
def test_make_env_time_limit_from_config(task, steps):
    from omegaconf import OmegaConf

    import cobelrun.api as api

    env = api.make_env(task)
    expected = steps or OmegaConf.select(api.compose(task), "task.protocol.max_steps")
    assert env.spec is None or env.spec.max_episode_steps in (None, expected)
    assert env._max_episode_steps == expected  # the TimeLimit wrapper
    check_env(env.unwrapped, skip_render_check=True)
    env.reset(seed=0)
    truncated = terminated = False
    n = 0
    while not (truncated or terminated):
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        n += 1
    assert n <= expected


def test_gymnasium_entry_point_registers_every_id():
    """The package's `gymnasium.envs` entry point (read by gymnasium 0.26-0.29 at import; see
    docs/envs.md) is in the installed metadata and, called as those loaders call it (inside
    `namespace(<key>)`), registers every id in a fresh interpreter."""
    code = (
        "import sys\n"
        "from importlib.metadata import entry_points\n"
        "import gymnasium as gym\n"
        "from gymnasium.envs.registration import namespace\n"
        "assert 'cobelrun' not in sys.modules\n"
        "(ep,) = [e for e in entry_points(group='gymnasium.envs') if e.value.startswith('cobelrun')]\n"
        "assert (ep.name, ep.value) == ('cobel', 'cobelrun.envs:register_envs'), ep\n"
        "with namespace(ep.name):\n"
        "    ep.load()()\n"
        "for i in sorted(k for k in gym.registry if k.startswith('cobel/')):\n"
        "    env = gym.make(i)\n"
        "    env.reset(seed=0)\n"
        "    print(i, env.spec.namespace, type(env.unwrapped).__name__)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    lines = [line.split() for line in out.stdout.splitlines()]
    assert [line[0] for line in lines] == sorted(ENV_IDS)
    assert {line[1] for line in lines} == {"cobel"}
    assert [line[2] for line in lines] == [ENV_IDS[i].split(":")[1] for i in sorted(ENV_IDS)]
