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


def test_online_views_are_rendered_once_per_pose_and_equal_fresh_renders(monkeypatch):
    env, fresh = image_env(), image_env(reuse_views=False)
    module = env.observation_module
    calls = []
    render_raw = module.render_raw
    monkeypatch.setattr(module, "render_raw", lambda n, h: calls.append((n, h)) or render_raw(n, h))
    poses = [(3, 0), (3, 2), (3, 0), (5, 1), (3, 2)]
    views = [env.observe_pose(n, h) for n, h in poses]
    assert calls == [(3, 0), (3, 2), (5, 1)]  # each pose rendered on its first visit only
    for (n, h), view in zip(poses, views, strict=True):
        assert np.array_equal(view, fresh.observe_pose(n, h))
    assert not np.shares_memory(views[0], views[2])  # new data on every call (gymnasium)
    views[0][...] = 0  # what a caller does with its copy does not reach the kept view
    assert np.array_equal(env.observe_pose(3, 0), fresh.observe_pose(3, 0))
    # the renderer runs on every visit without reuse_views (Fig. 4's online frame times)
    calls_fresh = []
    raw_fresh = fresh.observation_module.render_raw
    monkeypatch.setattr(fresh.observation_module, "render_raw",
                        lambda n, h: calls_fresh.append((n, h)) or raw_fresh(n, h))  # fmt: skip
    for n, h in poses:
        fresh.observe_pose(n, h)
    assert calls_fresh == poses
    env.close()
    fresh.close()


def test_online_views_stop_being_kept_past_the_byte_budget(monkeypatch):
    from cobelrun.envs import observations

    env = image_env()
    module = env.observation_module
    one = env.observe_pose(0, 0).nbytes
    monkeypatch.setattr(observations, "ONLINE_VIEWS_BYTES", 2 * one)
    for node in range(4):
        env.observe_pose(node, 1)
    calls = []
    render_raw = module.render_raw
    monkeypatch.setattr(module, "render_raw", lambda n, h: calls.append((n, h)) or render_raw(n, h))
    for node in range(4):
        env.observe_pose(node, 1)
    env.observe_pose(0, 0)
    assert calls == [(1, 1), (2, 1), (3, 1)]  # (0, 0) and (0, 1) filled the budget
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


# ---------------------------------------------------------------------- wall panels
def test_panels_cut_walls_into_seeded_colours():
    from cobelrun.render.scene import SceneSpec, SceneStyle

    spec = SceneSpec.from_topology(topo.hexagonal(9, 9), {"panel_width": 1.0, "panel_seed": 3})
    walls = spec.walls()
    pieces = spec.style.panels(walls)
    # the arena's 9 x 7.93 outline: 9 + 8 + 9 + 8 panels of about one unit each
    assert len(pieces) == sum(max(1, round(np.hypot(w[2] - w[0], w[3] - w[1]))) for w in walls)
    assert len(pieces) == 34
    t = spec.style.wall_thickness
    lengths = [np.hypot(p[2] - p[0], p[3] - p[1]) for p in pieces]
    total = sum(np.hypot(w[2] - w[0], w[3] - w[1]) + t for w in walls)
    assert sum(lengths) == pytest.approx(total)  # contiguous, half a thickness past each end
    assert len({p[4] for p in pieces}) == 34  # every panel its own colour
    again = SceneStyle.from_config({"panel_width": 1.0, "panel_seed": 3}).panels(walls)
    other = SceneStyle.from_config({"panel_width": 1.0, "panel_seed": 4}).panels(walls)
    assert again == pieces and other != pieces
    # without panels: one piece per wall in its facing's colour
    plain = SceneStyle().panels(walls)
    assert [p[4] for p in plain] == [SceneStyle().wall_colors[w[4]] for w in walls]


def test_panels_keep_earlier_scene_keys_and_change_the_view():
    from cobelrun.render.scene import SceneStyle

    assert "panel_width" not in SceneStyle().to_dict()  # earlier render-cache keys stay valid
    assert SceneStyle.from_config({"panel_width": 1}).to_dict()["panel_width"] == 1.0

    def hex_env(**scene):
        obs = ImageObservation(height=20, width=80, fov=240, n_cameras=4, scene=scene)
        return TopologyEnv(topology=topo.hexagonal(9, 9), observation=obs, max_steps=50)

    plain, a, b = hex_env(), hex_env(panel_width=1.0), hex_env(panel_width=1.0)
    c = hex_env(panel_width=1.0, panel_seed=1)
    # node 0 faces east along the north wall: panels bring colours the plain walls do not have
    assert np.array_equal(a.observe_pose(0, 0), b.observe_pose(0, 0))
    assert not np.array_equal(a.observe_pose(0, 0), c.observe_pose(0, 0))
    colours = lambda env: len(np.unique(env.observe_pose(0, 0).reshape(3, -1), axis=1).T)  # noqa: E731
    assert colours(a) > colours(plain) + 20
    for env in (plain, a, b, c):
        env.close()


@pytest.mark.parametrize(
    ("scene", "msg"),
    [
        ({"panel_width": 0}, "scene.panel_width must be a length > 0 or null, got 0"),
        ({"panel_width": "wide"}, "scene.panel_width must be a length > 0 or null, got 'wide'"),
        ({"panel_seed": -1}, "scene.panel_seed must be an integer >= 0, got -1"),
        ({"panel_seed": 1.5}, "scene.panel_seed must be an integer >= 0, got 1.5"),
    ],
)
def test_bad_panels_are_one_line(scene, msg):
    from cobelrun.errors import ConfigError
    from cobelrun.render.scene import SceneStyle

    with pytest.raises(ConfigError) as err:
        SceneStyle.from_config(scene)
    assert str(err.value) == msg


# ---------------------------------------------------------------------- vertical field of view
@pytest.mark.parametrize("vfov", [None, 90.0, 40.0])
def test_vfov_sets_how_many_rows_a_wall_covers(vfov):
    from cobelrun.render.scene import CameraSpec, Scene, SceneSpec

    spec = SceneSpec.from_topology(topo.hexagonal(9, 9), {"texture": None})
    cam = CameraSpec(height=96, width=96, fov=60.0, vfov=vfov)
    cx, cy = 4.0, 3.0 * np.sqrt(3) / 2 + np.sqrt(3) / 2  # the centre node
    with Scene(spec) as scene:
        img = scene.render(cx, cy, 0.0, cam).astype(int)  # facing the east wall (green)
    column = img[:, 48]
    wall_rows = int(np.sum((column[:, 1] > column[:, 0] + 40) & (column[:, 1] > column[:, 2] + 40)))
    # a pinhole camera: the wall's height h at distance d covers H * (h / d) / (2 tan(vfov / 2)) rows
    d = 8.5 - spec.style.wall_thickness / 2 - cx
    half = np.tan(np.deg2rad(30.0 if vfov is None else vfov / 2))  # square pixels: vfov = fov
    assert wall_rows == pytest.approx(96 * spec.style.wall_height / d / (2 * half), abs=1.5)


def test_vfov_keeps_earlier_camera_keys_and_bad_values_are_one_line():
    from cobelrun.errors import ConfigError
    from cobelrun.render.scene import CameraSpec

    assert "vfov" not in CameraSpec().to_dict()  # earlier render-cache keys stay valid
    assert CameraSpec(vfov=90.0).to_dict()["vfov"] == 90.0
    for bad in (0, 180.0, "wide", True):
        with pytest.raises(ConfigError) as err:
            ImageObservation(height=12, width=48, fov=240, n_cameras=4, vfov=bad)
        assert str(err.value) == f"camera vfov must be in (0, 170) degrees or null, got {bad}"


def test_textures_are_loaded_and_their_files_are_gone(tmp_path, monkeypatch):
    """Wall and floor textures reach the picture (it differs from the untextured scene), and
    their temporary files are removed once pybullet has loaded them: a scene that is never
    closed (a killed process) leaves no folder behind."""
    import tempfile

    from cobelrun.render.scene import CameraSpec, Scene, SceneSpec

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # this test's temporary folder
    graph = topo.hexagonal(5, 5)
    textured = Scene(SceneSpec.from_topology(graph, {}))
    plain = Scene(SceneSpec.from_topology(graph, {"texture": None}))
    try:
        assert not list(tmp_path.iterdir())  # built, not closed: nothing left in /tmp
        a = textured.render(0.0, 0.0, 0.0, CameraSpec()).astype(int)
        b = plain.render(0.0, 0.0, 0.0, CameraSpec()).astype(int)
        assert np.abs(a - b).mean() > 1.0
    finally:
        textured.close()
        plain.close()
