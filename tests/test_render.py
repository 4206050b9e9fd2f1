"""3D scene rendering, image observations and the offline render cache."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from cobelrun.envs import topology as topo
from cobelrun.envs.observations import (
    ImageObservation,
    MultiSensoryObservation,
    NoisyObservation,
    PoseObservation,
)
from cobelrun.envs.topology_env import TopologyEnv
from cobelrun.errors import CobelError
from cobelrun.render import cache

pytest.importorskip("pybullet")


@pytest.fixture
def cache_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("COBEL_CACHE", str(tmp_path / "cache"))
    return tmp_path / "cache"


def image_env(**kw):
    obs = dict(height=20, width=80, fov=240, n_cameras=4)
    obs.update(kw)
    return TopologyEnv(observation=ImageObservation(**obs), max_steps=50)


@pytest.mark.parametrize(
    ("kw", "shape", "dtype", "high"),
    [
        ({}, (3, 20, 80), np.uint8, 255),
        ({"channels_first": False}, (20, 80, 3), np.uint8, 255),
        ({"dtype": "float32"}, (3, 20, 80), np.float32, 1.0),
        ({"grayscale": True, "render_size": [40, 160]}, (1, 20, 80), np.uint8, 255),
    ],
    ids=["uint8_chw", "uint8_hwc", "float01", "grey_resized"],
)
def test_image_shape_dtype_range(kw, shape, dtype, high):
    env = image_env(**kw)
    obs, _ = env.reset(seed=0)
    assert obs.shape == shape and obs.dtype == dtype
    assert env.observation_space.contains(obs)
    assert obs.min() >= 0 and obs.max() <= high
    assert obs.std() > 0  # not a blank frame
    env.close()


def test_same_pose_same_image_and_views_differ():
    env = image_env()
    a = env.observe_pose(3, 0)
    for _ in range(3):
        env.step(0)
    b = env.observe_pose(3, 0)
    assert np.array_equal(a, b)
    # looking down the right arm differs from looking down the left arm (wall colours / cues)
    assert not np.array_equal(env.observe_pose(3, 0), env.observe_pose(3, 2))
    env.close()


@pytest.mark.parametrize("mode", ["image", "noisy_image", "multisensory"])
def test_check_env_with_image_modules(mode):
    img = ImageObservation(height=12, width=48, fov=240, n_cameras=4)
    obs = {
        "image": img,
        "noisy_image": NoisyObservation(img, kind="gaussian", std=0.05),
        "multisensory": MultiSensoryObservation({"image": img, "pose": PoseObservation()}),
    }[mode]
    env = TopologyEnv(topology=topo.hexagonal(), rewards={"centre": 1.0}, terminals=["centre"],
                      starts="all", start_heading="random", actions="face", observation=obs)  # fmt: skip
    check_env(env, skip_render_check=True)
    env.close()


def test_cache_matches_online_and_offline_mode(cache_dir):
    online = image_env()
    req = online.observation_module.cache_request()
    with pytest.raises(CobelError, match=r"no render cache .* build it with: cobel render-cache"):
        image_env(render="offline")
    path, built = cache.build(req, jobs=2)
    assert built and path.parent.parent == cache_dir
    assert cache.build(req, jobs=1) == (path, False)
    offline = image_env(render="offline")
    for node in range(online.topology.n_nodes):
        for h in range(online.topology.n_directions):
            assert np.array_equal(online.observe_pose(node, h), offline.observe_pose(node, h))
    assert cache.verify(req, sample=4) == (4, 0)
    # a different camera is a different key: missing again
    with pytest.raises(CobelError, match="no render cache"):
        image_env(render="offline", fov=200)
    online.close()


def test_offline_mode_without_pybullet(cache_dir):
    cache.build(image_env().observation_module.cache_request(), jobs=1)
    code = textwrap.dedent(
        """
        import sys
        sys.modules["pybullet"] = None  # any import of pybullet now fails
        from cobelrun.envs.observations import ImageObservation
        from cobelrun.envs.topology_env import TopologyEnv
        env = TopologyEnv(observation=ImageObservation(height=20, width=80, fov=240, n_cameras=4,
                                                       render="offline"))
        obs, _ = env.reset(seed=0)
        for a in [0, 0, 4, 0, 5]:
            obs, *_ = env.step(a)
        assert obs.shape == (3, 20, 80)
        try:
            import pybullet  # noqa
        except ImportError:
            print("OK no pybullet")
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env={**__import__("os").environ, "COBEL_CACHE": str(cache_dir)})  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "OK no pybullet" in out.stdout


def test_online_without_pybullet_names_the_extra():
    code = textwrap.dedent(
        """
        import sys
        sys.modules["pybullet"] = None
        from cobelrun.envs.observations import ImageObservation
        from cobelrun.envs.topology_env import TopologyEnv
        from cobelrun.errors import CobelError
        env = TopologyEnv(observation=ImageObservation(height=20, width=80))
        try:
            env.reset(seed=0)
        except CobelError as exc:
            print(exc)
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert "cobelrun[render]" in out.stdout, out.stderr


def test_stale_cache_names_the_command(cache_dir, monkeypatch):
    req = image_env().observation_module.cache_request()
    path, _ = cache.build(req, jobs=1)
    path.rename(path.with_name("pybullet-0.0.1.npy"))
    with pytest.raises(CobelError, match=r"stale .*pybullet 0\.0\.1.*rebuild it with"):
        image_env(render="offline")


def test_render_cache_cli_builds_verifies_and_offline_run_reads(cobel, tmp_path):
    env = {"COBEL_CACHE": str(tmp_path / "c")}
    small = ["env=tmaze_3d", "env.observation.height=20", "env.observation.width=80"]
    out = cobel("render-cache", *small, "--verify", "--jobs", "2", env=env)
    assert out.returncode == 0, out.stderr
    assert "rendered 48 views" in out.stdout and "identical" in out.stdout
    again = cobel("render-cache", *small, env=env)
    assert "up to date" in again.stdout
    bad = cobel("render-cache", "env=tmaze_paper", env=env)
    assert bad.returncode == 2 and "no image observation" in bad.stderr


@pytest.mark.slow
def test_tmaze_3d_task_end_to_end_offline(cobel, tmp_path):
    pytest.importorskip("stable_baselines3")
    import pandas as pd

    env = {"COBEL_CACHE": str(tmp_path / "c")}
    tiny = ["task=tmaze_extinction_3d", "task.runs=1", "task.protocol.phases.0.trials=2",
            "task.protocol.phases.1.trials=2", "task.protocol.max_steps=10",
            "agent.learning_starts=5", "env.observation.render=offline"]  # fmt: skip
    missing = cobel("run", *tiny, env=env)
    assert missing.returncode == 2
    line = missing.stderr.strip().splitlines()[-1]
    assert "no render cache" in line and "cobel render-cache task=tmaze_extinction_3d" in line
    assert cobel("render-cache", *tiny, env=env).returncode == 0
    out = cobel("run", *tiny, env=env)
    assert out.returncode == 0, out.stderr
    run_dir = out.stdout.strip().splitlines()[-1]
    trials = pd.read_parquet(f"{run_dir}/trials.parquet")
    assert len(trials) == 4 and {"response", "steps", "reward"} <= set(trials.columns)
