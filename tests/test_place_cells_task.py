"""Fig. 8 pieces: the CNN's input check, dqn_fig8, rendering at arbitrary poses, the activity-map
monitor (online and from the render cache), and NWB export checked by nwbinspector. The CLI
runs in-process (``cli``) except in the slow offline-vs-online test."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from cobelrun.analysis.maps import load_activity_maps, maps_array, probe_grid
from cobelrun.envs import topology as topo
from cobelrun.envs.observations import ImageObservation
from cobelrun.envs.topology_env import TopologyEnv
from cobelrun.errors import CobelError, ConfigError
from tests import inprocess

cli = inprocess.cli  # fixture: cobel in this process

pytest.importorskip("pybullet")


def hex_env(**kw) -> TopologyEnv:
    obs = {"height": 12, "width": 48, "fov": 240, "n_cameras": 4, **kw}
    return TopologyEnv(topology=topo.hexagonal(), actions="face", start_heading="random",
                       observation=ImageObservation(**obs))  # fmt: skip


def test_small_image_is_one_line_config_error(cli):
    out = cli("run", "task=gridworld", "env=hex_3d", "agent=dqn", "task.runs=1")
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1, out.stderr
    assert "12x48x3" in lines[0] and "4x4 kernel" in lines[0] and "2x11" in lines[0]


def test_small_image_error_in_python_and_for_dict_inputs():
    pytest.importorskip("stable_baselines3")
    from cobelrun.agents.dqn import DQNAgent
    from cobelrun.envs.observations import MultiSensoryObservation, PoseObservation

    with pytest.raises(ConfigError, match=r"12x48x3 .* too small .* agent.convs"):
        DQNAgent(hex_env(), seed=0)
    multi = MultiSensoryObservation({"image": ImageObservation(height=12, width=48, fov=240,
                                     n_cameras=4), "pose": PoseObservation()})  # fmt: skip
    env = TopologyEnv(topology=topo.hexagonal(), actions="face", observation=multi)
    with pytest.raises(ConfigError, match=r"NatureCNN for input 'image'"):
        DQNAgent(env, seed=0)


def test_dqn_fig8_network_and_analysis_layer():
    pytest.importorskip("stable_baselines3")
    from cobelrun.agents.dqn import DQNAgent

    env = hex_env()
    agent = DQNAgent(env, policy="CnnPolicy", convs=[[32, 5, 1], [64, 4, 2], [64, 3, 2]],
                     features_dim=50, dropout=0.35, net_arch=[], seed=0)  # fmt: skip
    net = agent.model.q_net
    convs = [m for m in net.modules() if m.__class__.__name__ == "Conv2d"]
    assert [(c.out_channels, c.kernel_size, c.stride) for c in convs] == [
        (32, (5, 5), (1, 1)), (64, (4, 4), (2, 2)), (64, (3, 3), (2, 2))]  # fmt: skip
    assert any(m.__class__.__name__ == "Dropout" and m.p == 0.35 for m in net.modules())
    assert net.q_net[0].out_features == 12
    assert agent.layer_names()[0] == "analysis"
    obs = np.stack([env.observe_pose(n, 0) for n in range(5)])
    net.train(True)  # dropout on: activations must still be deterministic (eval mode inside)
    a1 = agent.activations(obs, ["analysis"])["analysis"]
    a2 = agent.activations(obs, ["analysis"])["analysis"]
    assert a1.shape == (5, 50) and np.array_equal(a1, a2) and (a1 >= 0).all()
    assert net.training  # restored
    assert np.array_equal(agent.predict(obs), agent.predict(obs))


@pytest.mark.parametrize("prioritized", [False, True])
def test_dropout_only_in_the_online_network_while_learning(prioritized):
    """keras-rl trains with dropout in the online network and takes the TD targets from the
    target network's ``predict`` (inference mode, no dropout); so does SB3's DQN (its policy's
    set_training_mode leaves the target network in eval mode). Every forward pass of a
    training call is recorded: the target network's all in eval mode, some of the online
    network's (the gradient steps; acting runs in eval mode) in training mode."""
    pytest.importorskip("stable_baselines3")
    from cobelrun.agents.dqn import DQNAgent

    agent = DQNAgent(hex_env(), policy="CnnPolicy", convs=[[32, 5, 1], [64, 4, 2], [64, 3, 2]],
                     features_dim=50, dropout=0.35, net_arch=[], learning_starts=5,
                     batch_size=8, prioritized=prioritized, seed=0)  # fmt: skip
    modes: dict[str, list[bool]] = {"online": [], "target": []}
    policy = agent.model.policy
    for name, net in (("online", policy.q_net), ("target", policy.q_net_target)):
        drop = next(m for m in net.modules() if m.__class__.__name__ == "Dropout")
        drop.register_forward_hook(lambda m, i, o, name=name: modes[name].append(m.training))
    agent.train(2, 20)
    assert modes["target"] and not any(modes["target"])
    assert any(modes["online"])  # the gradient steps (acting runs in eval mode)


def test_keras_init_and_q_init():
    """init=keras: Glorot-uniform weights within their bound, zero biases; q_init sets the output
    biases, so an untrained network's Q values sit at q_init; the target net is the same."""
    pytest.importorskip("stable_baselines3")
    import torch

    from cobelrun.agents.dqn import DQNAgent

    env = hex_env()
    kw = {"policy": "CnnPolicy", "convs": [[32, 5, 1], [64, 4, 2], [64, 3, 2]],
          "features_dim": 50, "dropout": 0.35, "net_arch": []}  # fmt: skip
    agent = DQNAgent(env, init="keras", q_init=-5.0, seed=0, **kw)
    net, target = agent.model.policy.q_net, agent.model.policy.q_net_target
    layers = [m for m in net.modules() if isinstance(m, torch.nn.Linear | torch.nn.Conv2d)]
    assert len(layers) == 5
    for m in layers[:-1]:
        assert torch.count_nonzero(m.bias) == 0
    for m in layers:
        w = m.weight.detach().numpy()
        fan_in = w[0].size
        fan_out = w.shape[0] * (w[0, 0].size if w.ndim == 4 else 1)
        bound = np.sqrt(6 / (fan_in + fan_out))
        assert np.abs(w).max() <= bound
        assert w.std() == pytest.approx(bound / np.sqrt(3), rel=0.1)  # uniform(-b, b)
    assert np.all(layers[-1].bias.detach().numpy() == -5.0)
    for (k, v), (k2, v2) in zip(net.state_dict().items(), target.state_dict().items(), strict=True):
        assert k == k2 and torch.equal(v, v2)
    obs = np.stack([env.observe_pose(n, 0) for n in range(20)])
    q = agent.predict(obs)
    assert abs(q.mean() + 5.0) < 0.5 and q.std() > 0
    # the default (PyTorch's init) draws non-zero biases; same seed, same weights
    torch_agent = DQNAgent(env, seed=0, **kw)
    assert torch.count_nonzero(torch_agent.model.q_net.q_net[0].bias) > 0
    again = DQNAgent(env, init="keras", q_init=-5.0, seed=0, **kw)
    assert np.array_equal(again.predict(obs), q)
    with pytest.raises(ConfigError, match=r"agent\.init 'glorot' is not known.*allowed"):
        DQNAgent(env, init="glorot", seed=0, **kw)
    with pytest.raises(ConfigError, match=r"agent\.q_init must be a finite number"):
        DQNAgent(env, q_init=float("nan"), seed=0, **kw)


def test_render_at_pose_matches_nodes_and_differs_between_them():
    env = hex_env()
    base = env.unwrapped
    x, y = base.topology.positions[10]
    h = float(base.topology.directions[2])
    assert np.array_equal(base.render_at_pose(x, y, h), base.observe_pose(10, 2))
    between = base.render_at_pose(x + 0.5, y, h)
    assert between.shape == (3, 12, 48) and not np.array_equal(between, base.observe_pose(10, 2))
    assert np.array_equal(between, base.render_at_pose(x + 0.5, y, h + 2 * np.pi))


def test_probe_grid_inside_masks():
    hexa = probe_grid(topo.hexagonal().positions)
    assert hexa.inside.shape == (25, 25) and hexa.inside.all()  # the hexagonal maze is convex
    t = topo.tmaze_paper()
    g = probe_grid(t.positions, cells=True, nx=14, ny=12)
    # 12 cells in a 7x6 bounding box, 2x2 bins per cell
    assert g.inside.sum() == 12 * 4
    pts = g.points()
    d = np.abs(pts[:, None, :] - t.positions[None]).max(axis=2).min(axis=1)
    assert (d <= 0.5).all()


def test_offline_probe_grid_equals_online(tmp_path, monkeypatch):
    monkeypatch.setenv("COBEL_CACHE", str(tmp_path / "cache"))
    from cobelrun.render import cache

    online = hex_env()
    grid = probe_grid(online.topology.positions, nx=5, ny=4)
    heads = np.deg2rad([0.0, 90.0])
    want = online.observe_grid(grid.points(), heads)
    assert want.shape == (20, 2, 3, 12, 48)
    with cache.building_mode():  # the graph's own views are not cached here: bind lazily
        offline = hex_env(render="offline")
    with pytest.raises(CobelError, match="no render cache"):
        offline.observe_grid(grid.points(), heads)
    module = offline.observation_module
    cache.build(module.cache_request(grid.points(), heads), jobs=1)
    assert np.array_equal(offline.observe_grid(grid.points(), heads), want)

    # with the cache there, an online env reads it instead of rendering
    def no_render(*args):
        raise AssertionError("rendered although the cache exists")

    node_view = online.observe_pose(7, 0)
    monkeypatch.setattr(online.observation_module, "render_raw_at", no_render)
    assert np.array_equal(online.observe_grid(grid.points(), heads), want)
    x, y = grid.points()[3]
    assert np.array_equal(offline.render_at_pose(x, y, heads[1]), want[3, 1])
    cache.build(module.cache_request(), jobs=1)  # the graph's views
    with pytest.raises(CobelError, match="not in the loaded render caches"):
        offline.render_at_pose(x + 0.01, y, heads[1])
    node_x, node_y = offline.topology.positions[7]
    assert np.array_equal(offline.render_at_pose(node_x, node_y, 0.0), node_view)


TINY = ["task=place_cells", "task.runs=1", "task.protocol.phases.0.trials=3",
        "task.protocol.max_steps=8", "agent.learning_starts=4", "task.monitors.maps.every=2",
        "task.monitors.maps.grid=[6,5]"]  # fmt: skip


def test_place_cells_task_maps_and_nwb(cli, tmp_path):
    pytest.importorskip("stable_baselines3")
    pytest.importorskip("pynwb")
    nwbinspector = pytest.importorskip("nwbinspector")
    out = cli("run", *TINY)
    assert out.returncode == 0, out.stderr
    run_dir = out.stdout.strip().splitlines()[-1]
    df, grid = load_activity_maps(run_dir)
    assert set(df.columns) == {"run", "trial", "layer", "unit", "heading", "ix", "iy", "x", "y",
                               "value"}  # fmt: skip
    assert sorted(df["trial"].unique()) == [0, 2, 3]  # before training, every 2nd, the last
    assert (df["layer"] == "analysis").all() and df["unit"].nunique() == 50
    assert sorted(df["heading"].unique()) == [0, 60, 120, 180, 240, 300]
    maps, explored, _, _ = maps_array(df[df["trial"] == 3], grid)
    assert maps.shape == (50, 6, 5, 6) and explored.all()

    exported = cli("export", "nwb", run_dir)
    assert exported.returncode == 0, exported.stderr
    path = exported.stdout.strip().splitlines()[-1]
    bad = [m for m in nwbinspector.inspect_nwbfile(path)
           if m.importance.name in ("CRITICAL", "BEST_PRACTICE_VIOLATION", "PYNWB_VALIDATION",
                                    "ERROR")]  # fmt: skip
    assert not bad, [(m.check_function_name, m.message) for m in bad]
    from pynwb import NWBHDF5IO

    with NWBHDF5IO(path, "r") as io:
        f = io.read()
        assert len(f.trials) == 3
        assert f.processing["behavior"]["Position"]["position"].rate == 10.0
        table = f.processing["network"]["activity_maps_analysis"]
        assert table["maps"].data.shape == (3 * 50, 6, 5, 6)
        assert np.allclose(table["maps"].data[2 * 50 + 7], maps[7])
        assert "place cells" in f.keywords[:]
        assert f.subject.subject_id == "DQNAgent-run0"
        # the task's text says "every 800 trials": the overrides it ran with are named too
        assert f.session_description.startswith("Fig. 8: place cells")
        assert "Run with: task.runs=1 task.protocol.phases.0.trials=3" in f.session_description
        assert "task.monitors.maps.every=2" in f.session_description

    # cobel plot (the run summary's first hint) draws the run's place-cell panels
    plotted = cli("plot", run_dir)
    assert plotted.returncode == 0, plotted.stderr
    assert plotted.stdout.strip().splitlines()[-1].endswith("plot.png")
    from cobelrun.figures.place_cells import plot_run

    with pytest.raises(CobelError, match=r"has no activity_maps\.parquet .*--kind occupancy"):
        plot_run(tmp_path)


@pytest.mark.slow
def test_place_cells_task_offline_equals_online(cobel, tmp_path):
    pytest.importorskip("stable_baselines3")
    env = {"COBEL_CACHE": str(tmp_path / "cache")}
    online = cobel("run", *TINY)
    assert online.returncode == 0, online.stderr
    built = cobel("render-cache", *TINY, "--jobs", "1", env=env)
    assert built.returncode == 0, built.stderr
    assert "30 probe positions x 6 headings" in built.stdout
    off = cobel("run", *TINY, "env.observation.render=offline", env=env)
    assert off.returncode == 0, off.stderr
    df_on, _ = load_activity_maps(online.stdout.strip().splitlines()[-1])
    df_off, _ = load_activity_maps(off.stdout.strip().splitlines()[-1])
    pd.testing.assert_frame_equal(df_on, df_off)


def test_nwb_export_of_a_tabular_run(cli, tmp_path):
    pytest.importorskip("pynwb")
    nwbinspector = pytest.importorskip("nwbinspector")
    out = cli("run", "task=tmaze_extinction", "task.runs=2",
                "task.protocol.phases.0.trials=5", "task.protocol.phases.1.trials=5")  # fmt: skip
    assert out.returncode == 0, out.stderr
    run_dir = out.stdout.strip().splitlines()[-1]
    exported = cli("export", "nwb", run_dir, "--out", str(tmp_path / "nwb"))
    assert exported.returncode == 0, exported.stderr
    files = exported.stdout.strip().splitlines()
    assert [f.rsplit("/", 1)[-1] for f in files] == ["run_0000.nwb", "run_0001.nwb"]
    for path in files:
        msgs = list(nwbinspector.inspect_nwbfile(path))
        assert not [m for m in msgs if m.importance.name in ("CRITICAL", "BEST_PRACTICE_VIOLATION",
                                                              "PYNWB_VALIDATION", "ERROR")]  # fmt: skip
    from pynwb import NWBHDF5IO

    with NWBHDF5IO(files[1], "r") as io:
        f = io.read()
        trials = f.trials.to_dataframe()
        assert len(trials) == 10 and set(trials["phase"]) == {"acquisition", "extinction"}
        assert "network" not in f.processing
    missing = cli("export", "nwb", str(tmp_path / "nope"))
    assert missing.returncode == 2 and "does not exist" in missing.stderr


class _Layer:
    """An agent whose one layer gives ``fn(views)`` (units in the last axis)."""

    def __init__(self, fn) -> None:
        self.fn = fn

    def layer_names(self) -> list[str]:
        return ["analysis"]

    def activations(self, views, layers):
        return {"analysis": self.fn(np.asarray(views, np.float32))}


def test_maps_monitor_warns_once_when_a_layer_goes_silent(caplog):
    from cobelrun.monitors.maps import ActivityMapMonitor

    mon = ActivityMapMonitor(grid=[3, 3], headings=2)
    mon.setup(hex_env())
    rows: list[dict] = []
    mon.bind(lambda table, cols: rows.append(cols))
    alive = _Layer(lambda v: np.stack([v.mean(axis=(1, 2, 3)), np.zeros(len(v))], axis=1))
    dead = _Layer(lambda v: np.zeros((len(v), 2), np.float32))
    flat = _Layer(lambda v: np.full((len(v), 2), 0.5, np.float32))  # on, but the same everywhere
    nan = _Layer(lambda v: np.full((len(v), 2), np.nan, np.float32))
    with caplog.at_level("WARNING", logger="cobel"):
        mon.start_run(0, dead)  # before training: an untrained layer is not reported
        mon.snapshot(alive, 800)  # one unit varies over the poses
        assert not caplog.records
        mon.snapshot(dead, 1600)
        mon.snapshot(dead, 2400)  # once per run and layer
        mon.start_run(1, alive)
        mon.snapshot(flat, 800)
        mon.start_run(2, alive)
        mon.snapshot(nan, 800)
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 3, lines
    assert (
        "layer 'analysis' of run 0 at trial 1600 is silent: all 2 units are 0 at all 18" in lines[0]
    )
    assert "dead layer" in lines[0] and "dead layer" not in lines[1]
    assert "run 1 at trial 800 is constant: none of its 2 units changes over the 18" in lines[1]
    assert "run 2 at trial 800 has non-finite values" in lines[2]
    # the grid table, each start_run's trial-0 snapshot and the 5 snapshots taken here
    assert len(rows) == 1 + 3 + 5 and all("value" in r for r in rows[1:])


@pytest.mark.parametrize("grid", [25, "ab", [1, 1], [6]])
def test_maps_monitor_grid_must_be_two_integers(grid):
    from cobelrun.monitors.maps import ActivityMapMonitor

    with pytest.raises(ConfigError, match=r"activity maps 'grid' must be \[nx, ny\] integers >= 2"):
        ActivityMapMonitor(grid=grid)


def test_unknown_layer_fails_before_the_run_folder_is_made(cli, tmp_path):
    out = tmp_path / "run"
    proc = cli("run", *TINY, "task.monitors.maps.layers=[analysys]", f"hydra.run.dir={out}")
    assert proc.returncode == 2
    err = proc.stderr.strip().splitlines()[-1]
    assert (
        "unknown layer 'analysys' (did you mean 'analysis'?); agent DQNAgent has: analysis" in err
    )
    assert not out.exists()
