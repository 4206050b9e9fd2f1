"""Issue 33, "fix the pictures": arrival poses in the steps table (trajectories and occupancy
reach the goal), one-way doors as their own geometry, NWB positions against the trials table,
bands inside the measure's range, rate maps of arena cells, the camera view in replays."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
import pandas as pd
import pytest

import cobelrun
from cobelrun.analysis.paths import visited_poses
from cobelrun.figures.runs import NO_ARRIVALS, load_geometry, occupancy, plot_trajectories

matplotlib.use("Agg")

TINY = ["env=tmaze_paper", "task.runs=2", "task.protocol.phases.0.trials=5",
        "task.record.mcap=false", "task.save_agents=none"]  # fmt: skip


@pytest.fixture(scope="module")
def grid_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A gridworld T-maze run (2 runs x 5 trials, seeded) whose trials reach the arms."""
    out = tmp_path_factory.mktemp("pictures") / "run"
    cobelrun.run("gridworld", [*TINY, "seed=3"], out=out)
    return out


def _cell(xe: np.ndarray, ye: np.ndarray, x: float, y: float) -> tuple[int, int]:
    return np.searchsorted(xe, x) - 1, np.searchsorted(ye, y) - 1


def test_steps_record_the_pose_after_each_step(grid_run: Path) -> None:
    steps = cobelrun.load(grid_run).steps
    assert {"next_x", "next_y", "next_heading"} <= set(steps.columns)
    s = steps.sort_values(["run", "trial", "step"])
    same = (s["run"].to_numpy()[1:] == s["run"].to_numpy()[:-1]) & (
        s["trial"].to_numpy()[1:] == s["trial"].to_numpy()[:-1]
    )
    # within a trial, where a step led is where the next one starts
    np.testing.assert_array_equal(s["next_x"].to_numpy()[:-1][same], s["x"].to_numpy()[1:][same])
    np.testing.assert_array_equal(s["next_y"].to_numpy()[:-1][same], s["y"].to_numpy()[1:][same])
    from cobelrun.envs.world import tmaze_paper

    coords = tmaze_paper().coords  # and it is the place of the state the step led to
    np.testing.assert_array_equal(s[["next_x", "next_y"]].to_numpy(), coords[s["next_state"]])
    heads = {0: np.pi, 1: np.pi / 2, 2: 0.0, 3: -np.pi / 2}  # facing the way the step went
    np.testing.assert_allclose(s["next_heading"], s["action"].map(heads), atol=1e-6)


def test_goal_cells_are_occupied_and_trajectories_end_on_them(grid_run: Path) -> None:
    import matplotlib.pyplot as plt

    run = cobelrun.load(grid_run)
    steps, trials = run.steps, run.trials
    geometry = load_geometry(grid_run)
    arms = {name: (r["x"], r["y"]) for name, r in geometry.regions.items() if "arm" in name}
    ended = trials[trials["terminated"]]
    assert len(ended) >= 3  # the seeded run reaches an arm in most trials
    counts, xe, ye = occupancy(steps, geometry)
    assert counts.sum() == len(steps) + len(trials)  # every step and every trial's arrival
    before, _, _ = np.histogram2d(steps["x"], steps["y"], bins=(xe, ye))
    reached = set()
    for _, t in ended.iterrows():
        last = steps[(steps["run"] == t["run"]) & (steps["trial"] == t["trial"])].iloc[-1]
        end = (last["next_x"], last["next_y"])
        assert end in arms.values()  # a terminated trial arrives on an arm
        reached.add(end)
    for x, y in reached:
        i, j = _cell(xe, ye, x, y)
        assert before[i, j] == 0  # the steps' own poses never stand on a terminal cell
        assert counts[i, j] > 0  # the arrivals do
    fig, ax = plt.subplots()
    r0 = ended[ended["run"] == 0]
    plot_trajectories(steps[steps["trial"].isin(r0["trial"])], geometry, ax, run=0)
    paths = [line for line in ax.lines if str(line.get_label()).startswith("trial ")]
    assert len(paths) == len(r0)
    ends = [tuple(line.get_xydata()[-1]) for line in paths]
    plt.close(fig)
    # each drawn path ends on an arm (up to the small per-trial offset that keeps paths apart)
    for ex, ey in ends:
        assert min(np.hypot(ex - ax_, ey - ay) for ax_, ay in arms.values()) < 0.2


def test_older_steps_tables_fall_back_and_say_so(grid_run: Path) -> None:
    import matplotlib.pyplot as plt

    steps = cobelrun.load(grid_run).steps
    old = steps.drop(columns=["next_x", "next_y", "next_heading"])
    poses = visited_poses(old)
    assert not poses.attrs["arrivals"] and len(poses) == len(old)
    assert visited_poses(steps).attrs["arrivals"]
    geometry = load_geometry(grid_run)
    fig, ax = plt.subplots()
    plot_trajectories(old, geometry, ax, run=0)
    assert any(NO_ARRIVALS in t.get_text() for t in ax.texts)
    plt.close(fig)
    counts, _, _ = occupancy(old, geometry)
    assert counts.sum() == len(old)


def test_visited_poses_of_a_table() -> None:
    steps = pd.DataFrame({
        "run": [0, 0, 0], "trial": [1, 1, 2], "step": [1, 2, 1], "x": [0.0, 1.0, 5.0],
        "y": [0.0, 0.0, 5.0], "heading": [0.0, 0.0, 1.0], "next_x": [1.0, 2.0, 5.0],
        "next_y": [0.0, 0.0, 6.0], "next_heading": [0.0, 0.0, 1.5],
    })  # fmt: skip
    got = visited_poses(steps)
    assert got[["trial", "step", "x", "y"]].values.tolist() == [
        [1, 1, 0.0, 0.0], [1, 2, 1.0, 0.0], [1, 3, 2.0, 0.0], [2, 1, 5.0, 5.0], [2, 2, 5.0, 6.0],
    ]  # fmt: skip
    assert got["heading"].iloc[-1] == 1.5


# -- one-way doors ------------------------------------------------------------------------------
def _blodgett_geometry() -> Any:
    from cobelrun.envs.gridworld import GridWorldEnv
    from cobelrun.envs.world import blodgett

    return GridWorldEnv(world=blodgett()).geometry()


def test_blodgett_doors_are_doors_not_walls() -> None:
    from cobelrun.envs.world import BLODGETT_DOORS, blodgett

    g = _blodgett_geometry()
    world = blodgett()
    assert len(g.doors) == len(BLODGETT_DOORS) == 6
    walls = {tuple(w) for w in np.round(g.walls, 6).tolist()}
    for a, b in BLODGETT_DOORS:  # the move a -> b is blocked, b -> a passes
        (xa, ya), (xb, yb) = world.coords[a], world.coords[b]
        mid = ((xa + xb) / 2, (ya + yb) / 2)
        row = [d for d in g.doors if np.allclose(((d[0] + d[2]) / 2, (d[1] + d[3]) / 2), mid)]
        assert len(row) == 1
        assert np.allclose(row[0][4:], (xa - xb, ya - yb))  # passable from b towards a
        assert tuple(np.round(row[0][:4], 6).tolist()) not in walls
    # the start cell (24) is not sealed: its door to 25 is open on the way out
    start = world.coords[24]
    sides = [w for w in g.walls if np.isclose(max(w[0], w[2]), start[0] + 0.5)
             and min(w[1], w[3]) <= start[1] <= max(w[1], w[3]) and w[0] == w[2]]  # fmt: skip
    assert not sides


def test_random_walk_crosses_doors_one_way_and_never_walls() -> None:
    from cobelrun.envs.gridworld import GridWorldEnv
    from cobelrun.envs.world import blodgett

    env = GridWorldEnv(world=blodgett())
    g = env.geometry()
    walls = {tuple(w) for w in np.round(g.walls, 6).tolist()}
    doors = {tuple(np.round(d[:4], 6).tolist()): d[4:] for d in g.doors}
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    through = 0
    for _ in range(3000):
        x0, y0, _h = env.agent_pose()
        _, _, term, _, _ = env.step(int(rng.integers(4)))
        x1, y1, _h = env.agent_pose()
        if (x0, y0) != (x1, y1):
            mx, my = (x0 + x1) / 2, (y0 + y1) / 2
            vertical = x0 != x1
            seg = (mx, my - 0.5, mx, my + 0.5) if vertical else (mx - 0.5, my, mx + 0.5, my)
            seg = tuple(np.round(seg, 6).tolist())
            assert seg not in walls  # a path never crosses a drawn wall
            if seg in doors:
                assert np.allclose(doors[seg], (x1 - x0, y1 - y0))  # only the open way
                through += 1
        if term:
            env.reset()
    assert through > 0


def test_doors_in_world_json_scene_and_pictures(tmp_path: Path) -> None:
    import json

    import matplotlib.pyplot as plt

    from cobelrun.envs.base import Geometry
    from cobelrun.figures.runs import draw_geometry
    from cobelrun.io.validate import FolderFileError, read_world
    from cobelrun.render.foxglove_scene import scene_entities

    g = _blodgett_geometry()
    path = tmp_path / "world.json"
    path.write_text(g.to_json())
    back = read_world(path)
    np.testing.assert_array_equal(back.doors, g.doors)
    old = {k: v for k, v in json.loads(g.to_json()).items() if k != "doors"}
    path.write_text(json.dumps(old))
    assert read_world(path).doors.shape == (0, 6)  # folders from before doors: none
    path.write_text(json.dumps({**old, "doors": [[0, 0, 1, 0, 2, 0]]}))
    with pytest.raises(FolderFileError, match="unit direction"):
        read_world(path)
    assert Geometry.from_dict(json.loads(g.to_json())).doors.shape == (6, 6)

    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    from cobelrun.io.mcap import McapRecorder

    McapRecorder(tmp_path / "run.mcap", geometry=g, start_ns=10**18).close()
    with open(tmp_path / "run.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        (scene,) = [m for _, c, _, m in reader.iter_decoded_messages() if c.topic == "/maze"]
    by_id = {e.id: e for e in scene.entities}
    assert len(by_id["doors"].arrows) == 6 and len(by_id["doors"].cubes) == 6
    assert len(by_id["walls"].cubes) == len(g.walls)
    for arrow, d in zip(by_id["doors"].arrows, g.doors, strict=True):  # arrows point the open way
        q = arrow.pose.orientation
        assert np.allclose((np.cos(2 * np.arctan2(q.z, q.w)), np.sin(2 * np.arctan2(q.z, q.w))),
                           d[4:], atol=1e-9)  # fmt: skip
    assert len(scene_entities(g)) == len(by_id)

    fig, ax = plt.subplots()
    draw_geometry(g, ax)
    doors = [c for c in ax.collections if c.get_label() == "one-way door"]
    assert len(doors) == 1 and len(doors[0].get_segments()) == 6
    plt.close(fig)


# -- NWB: positions on the trials table's clock --------------------------------------------------
def test_nwb_positions_line_up_with_the_trials(grid_run: Path, tmp_path: Path) -> None:
    pynwb = pytest.importorskip("pynwb")
    from cobelrun.io.nwb import STEP_SECONDS, export_run_folder

    (path, *_) = export_run_folder(grid_run, tmp_path)
    steps = cobelrun.load(grid_run).steps
    s0 = steps[steps["run"] == 0].sort_values(["trial", "step"])
    with pynwb.NWBHDF5IO(str(path), "r") as io:
        nwb = io.read()
        trials = nwb.trials.to_dataframe()
        pos = nwb.processing["behavior"]["Position"]
        series = pos["position"]
        xy = series.data[:]
        t = series.get_timestamps()
        ends = pos["end_position"]
        end_xy, end_t = ends.data[:], ends.timestamps[:]
        reward_t = nwb.processing["behavior"]["reward"].get_timestamps()
    assert len(xy) == len(s0) == int(trials["steps"].sum())
    for i, row in enumerate(trials.itertuples()):
        first = s0[s0["trial"] == row.trial].iloc[0]
        k = int(np.searchsorted(t, row.start_time - 1e-9))
        assert t[k] == pytest.approx(row.start_time)  # a sample at each trial's start
        assert tuple(xy[k]) == (first["x"], first["y"])  # ... and it is the start pose
        assert end_t[i] == pytest.approx(row.stop_time)
        last = s0[s0["trial"] == row.trial].iloc[-1]
        assert tuple(end_xy[i]) == (last["next_x"], last["next_y"])
    np.testing.assert_allclose(reward_t, t + STEP_SECONDS)  # a reward comes with the arrival
    assert (trials["stop_time"] - trials["start_time"]).round(9).tolist() == (
        trials["steps"] * STEP_SECONDS
    ).round(9).tolist()


# -- bands: 95% CI everywhere, inside the measure's range ---------------------------------------
def _band_extent(ax) -> tuple[float, float, np.ndarray]:
    from matplotlib.collections import PolyCollection

    (band,) = [c for c in ax.collections if isinstance(c, PolyCollection)]
    v = band.get_paths()[0].vertices
    return float(v[:, 1].min()), float(v[:, 1].max()), v


def test_bands_stay_in_the_measure_range_and_say_what_they_are() -> None:
    import matplotlib.pyplot as plt

    from cobelrun.figures.bands import measure_limits
    from cobelrun.figures.extinction import plot_cumulative_response, plot_escape_latency
    from cobelrun.figures.runs import curve_stats, plot_curves

    # two runs, very different: the t interval (t(0.975, 1) = 12.7) goes far out of range
    trials = pd.DataFrame({
        "run": [0, 0, 0, 1, 1, 1], "trial": [1, 2, 3, 1, 2, 3], "phase": ["a"] * 6,
        "steps": [1, 2, 100, 99, 3, 1], "cumulative_response": [0, 1, 2, 1, 2, 3],
    })  # fmt: skip
    s = curve_stats(trials, "steps")
    assert (s["lo"] < 0).any()  # the numbers keep the true interval
    for column, draw in (("steps", plot_escape_latency), ("cumulative_response",
                                                           plot_cumulative_response)):  # fmt: skip
        for how in ("curves", "task"):
            fig, ax = plt.subplots()
            if how == "curves":
                plot_curves(trials, column, ax)
                assert "95% CI" in ax.get_legend().get_texts()[0].get_text()
            else:
                draw(trials, ax)
                assert "95% CI" in ax.get_ylabel()
            lo, hi, v = _band_extent(ax)
            plt.close(fig)
            assert lo >= 0.0
            if column == "cumulative_response":  # never more responses than trials so far
                for x, y in v:
                    assert y <= x + 1e-9
    lo, hi = measure_limits("cumulative_response", np.array([1, 2, 3]))
    assert lo.tolist() == [0, 0, 0] and hi.tolist() == [1, 2, 3]


def test_titles_name_the_task_and_overrides_and_y_names_its_file(
    grid_run: Path, tmp_path: Path
) -> None:
    import json
    import shutil

    from PIL import Image

    from cobelrun.figures.runs import compare_file, plot_kind
    from cobelrun.figures.titles import run_title as _title
    from cobelrun.io.run_folder import RunFolder

    assert _title(grid_run).startswith("gridworld")  # the task, not the folder name
    job = tmp_path / "3"
    shutil.copytree(grid_run, job)
    RunFolder(job).job.write_text(json.dumps({"overrides": ["agent.epsilon=0.5", "seed=2"]}))
    assert _title(job) == "gridworld (agent.epsilon=0.5, seed=2)"  # a sweep job's own keys
    got = compare_file([grid_run, job], y="latency")
    assert got.name == "compare_latency.png" and not (grid_run / "compare.png").exists()
    path = plot_kind(job, "occupancy", tmp_path / "o.png")
    assert Image.open(path).size[0] > 300


# -- rate maps of an arena's cells ---------------------------------------------------------------
ARENA_CONFIG = """\
env:
  _target_: cobelrun.envs.Continuous2DEnv
  arena: {shape: square, x0: 0.0, y0: 0.0, size: 1.0}
  goals:
    goal: {shape: circle, x: 0.85, y: 0.85, radius: 0.1, reward: 1.0, terminal: true}
  starts: {start: [0.15, 0.15]}
  observation:
    - {kind: pose}
    - {kind: place_cells, n: 2, sigma: 0.1, centres: [[0.3, 0.7], [0.8, 0.2]]}
    - {kind: grid_cells, n: 3}
    - {kind: head_direction, n: 4}
"""


def test_rate_maps_of_an_arena_s_cells(tmp_path: Path) -> None:
    from PIL import Image

    from cobelrun.figures.arena_cells import cell_rate_maps
    from cobelrun.figures.kinds import available_kinds, plot_kind
    from cobelrun.figures.learned import available

    run = tmp_path / "arena_run"
    run.mkdir()
    (run / "config.yaml").write_text(ARENA_CONFIG)
    assert "rate" in available(run) and "rate" in available_kinds(run)
    from omegaconf import OmegaConf

    from cobelrun.config import instantiate

    env = instantiate("env", OmegaConf.create(ARENA_CONFIG).env)
    maps = cell_rate_maps(env, bins=40)
    env.close()
    assert [(m["population"], m["cell"]) for m in maps] == [
        ("place_cells", 0), ("place_cells", 1), ("grid_cells", 0), ("grid_cells", 1),
        ("grid_cells", 2),
    ]  # fmt: skip
    for m, centre in zip(maps[:2], [(0.3, 0.7), (0.8, 0.2)], strict=True):
        iy, ix = np.unravel_index(np.nanargmax(m["rate"]), m["rate"].shape)
        assert (
            abs((ix + 0.5) / 40 - centre[0]) <= 1 / 40
            and abs((iy + 0.5) / 40 - centre[1]) <= 1 / 40
        )
    path = plot_kind(run, "rate", tmp_path / "rate.png")
    assert Image.open(path).size[0] > 400


def test_grid_runs_have_no_cell_rate_maps(grid_run: Path) -> None:
    from cobelrun.figures.arena_cells import has_spatial_cells

    assert not has_spatial_cells(grid_run)


# -- the camera view in replays of 3D envs ------------------------------------------------------
def test_which_runs_get_a_camera_view(grid_run: Path, tmp_path: Path) -> None:
    from cobelrun.commands.replay import observes_images

    assert not observes_images(grid_run)
    run = tmp_path / "r"
    run.mkdir()
    (run / "config.yaml").write_text(
        "env:\n  _target_: cobelrun.envs.TopologyEnv\n  observation:\n"
        "    _target_: cobelrun.envs.observations.ImageObservation\n    height: 12\n"
    )
    assert observes_images(run)
    (run / "config.yaml").write_text(ARENA_CONFIG.replace("{kind: pose}", "{kind: view}"))
    assert observes_images(run)


@pytest.mark.slow
def test_replay_of_a_3d_run_shows_the_agent_s_view(tmp_path: Path) -> None:
    pytest.importorskip("imageio_ffmpeg")
    pytest.importorskip("pybullet")
    from cobelrun.commands.replay import camera_view
    from cobelrun.figures.replay_video import SIZE, frames, replay_file

    run_dir = tmp_path / "run3d"
    cobelrun.run("gridworld", ["env=tmaze_3d", "agent=mfec", "task.runs=1",
                               "task.protocol.phases.0.trials=1", "task.protocol.max_steps=12",
                               "task.record.mcap=false", "task.save_agents=none",
                               "env.observation.height=24", "env.observation.width=24"],
                 out=run_dir)  # fmt: skip
    steps = cobelrun.load(run_dir).steps
    env, view = camera_view(run_dir)
    try:
        img = view(*steps[["x", "y", "heading"]].iloc[0].to_numpy(float))
        assert img.shape == (24, 24, 3) and img.dtype == np.uint8 and img.std() > 0
        _, n = replay_file(run_dir, tmp_path / "v.gif", camera=view)
        assert n == len(steps) + 1  # each step and the arrival
        poses = visited_poses(steps)
        got = list(frames(poses.head(len(poses)), load_geometry(run_dir), camera=view))
    finally:
        env.close()
    right = [f[:, SIZE[0] // 2 :] for f in got]
    turned = [i for i in range(1, len(poses)) if poses["heading"].iloc[i] != poses["heading"].iloc[i - 1]
              and (poses["x"].iloc[i], poses["y"].iloc[i]) == (poses["x"].iloc[i - 1], poses["y"].iloc[i - 1])]  # fmt: skip
    assert turned  # the agent turned on the spot at least once in 12 steps
    for i in turned:  # the maze panel barely changes, the view does
        assert not np.array_equal(right[i], right[i - 1])


def test_learned_maps_place_the_goal_states(grid_run: Path) -> None:
    from cobelrun.figures.learned import state_positions

    steps = cobelrun.load(grid_run).steps
    pos = state_positions(steps)
    ends = set(steps["next_state"]) - set(steps["state"])  # terminal states: arrived, never left
    assert ends and ends <= set(pos)
    old = state_positions(steps.drop(columns=["next_x", "next_y", "next_heading"]))
    assert not ends & set(old)


# -- arrival poses in run.mcap and the live view ---------------------------------------------------
def test_mcap_pose_stream_ends_each_trial_on_its_arrival(tmp_path: Path) -> None:
    """Each trial's last pose on /run_NNNN/pose is where it arrived: the steps table's
    next_x, next_y, next_heading of its last step (and the trial's end event is at its time)."""
    import json

    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    out = tmp_path / "run"
    cobelrun.run("gridworld", ["env=blodgett", "+env.world.goal_reward=1.0", "task.runs=1",
                               "task.protocol.phases.0.trials=4", "task.protocol.max_steps=40",
                               "task.save_agents=none", "seed=2"], out=out)  # fmt: skip
    steps = pd.read_parquet(out / "steps.parquet")
    poses, times, ends = [], [], []
    with open(out / "run.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, _, message, pose in reader.iter_decoded_messages(topics=["/run_0000/pose"]):
            q, p = pose.pose.orientation, pose.pose.position
            poses.append((p.x, p.y, 2 * np.arctan2(q.z, q.w)))
            times.append(message.log_time)
        for _, _, message in reader.iter_messages(topics=["/trial"]):
            if json.loads(message.data)["event"] == "end":
                ends.append(message.log_time)
    got = np.array(poses)
    per_trial = steps.groupby("trial").size().to_numpy()
    assert len(got) == len(steps) + len(per_trial)  # each trial's start pose, then every step's
    last = np.cumsum(per_trial + 1) - 1
    arrived = steps.groupby("trial").tail(1)[["next_x", "next_y", "next_heading"]].to_numpy()
    np.testing.assert_allclose(got[last, :2], arrived[:, :2])
    dh = np.angle(np.exp(1j * (got[last, 2] - arrived[:, 2])))
    np.testing.assert_allclose(dh, 0.0, atol=1e-6)
    assert [times[i] for i in last] == ends  # the end event is logged at the arrival pose


def test_live_view_keeps_each_recent_trial_s_arrival() -> None:
    from cobelrun.io.mcap import LIVE_POSES, LIVE_TRIALS, live_pose_indices

    assert live_pose_indices(LIVE_POSES) is None  # a small batch goes whole
    k = 10_000
    arrivals = np.cumsum(np.full(200, 50)) - 1  # 200 trials of 49 steps
    keep = live_pose_indices(k, arrivals)
    assert keep is not None and np.all(np.diff(keep) > 0)
    assert set(arrivals[-LIVE_TRIALS:].tolist()) <= set(keep.tolist())
    assert keep[0] == 0 and keep[-1] == k - 1
    assert len(keep) <= LIVE_POSES + LIVE_TRIALS
    assert len(set(keep.tolist()) & set(arrivals[:-LIVE_TRIALS].tolist())) < 200 - LIVE_TRIALS
    with pytest.raises(ValueError, match="arrivals must index"):
        live_pose_indices(k, np.array([k]))


# -- one-way edges of topology graphs are doors ------------------------------------------------------
def test_one_way_edges_of_a_graph_are_doors(tmp_path: Path) -> None:
    """The Blodgett maze as a topology graph: its six one-way edges are doors at the same
    places and facing the same way as the gridworld's doors, in world.json, the MCAP scene
    and the pictures (``cobel show``'s drawing); two-way edges are none."""
    import json

    import matplotlib.pyplot as plt

    from cobelrun.envs.base import Geometry
    from cobelrun.envs.topology import manual, one_way_doors
    from cobelrun.envs.topology_env import TopologyEnv
    from cobelrun.envs.world import blodgett
    from cobelrun.figures.runs import draw_geometry
    from cobelrun.render.foxglove_scene import scene_entities

    g = TopologyEnv(world=blodgett()).geometry()
    grid = _blodgett_geometry()
    assert g.kind == "graph" and g.doors.shape == (6, 6)

    def key(doors: np.ndarray) -> list[tuple[float, ...]]:
        mid = (doors[:, :2] + doors[:, 2:4]) / 2
        return sorted(map(tuple, np.round(np.hstack([mid, doors[:, 4:]]), 6).tolist()))

    assert key(g.doors) == key(grid.doors)
    for x0, y0, x1, y1, dx, dy in g.doors.tolist():  # across the edge, half its length
        assert np.isclose((x1 - x0) * dx + (y1 - y0) * dy, 0.0)
        assert np.isclose(np.hypot(x1 - x0, y1 - y0), 0.5)
    # a one-way edge stays an edge (its line is drawn), with its door across it
    pairs = {tuple(e) for e in g.edges.tolist()}
    index = {tuple(np.round(p, 6).tolist()): i for i, p in enumerate(g.nodes)}
    for x0, y0, x1, y1, dx, dy in g.doors.tolist():
        mx, my = (x0 + x1) / 2, (y0 + y1) / 2
        ia = index[(round(mx - dx / 2, 6), round(my - dy / 2, 6))]
        ib = index[(round(mx + dx / 2, 6), round(my + dy / 2, 6))]
        assert (min(ia, ib), max(ia, ib)) in pairs

    path = tmp_path / "world.json"  # world.json keeps them
    path.write_text(g.to_json())
    np.testing.assert_array_equal(Geometry.from_dict(json.loads(path.read_text())).doors, g.doors)
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    from cobelrun.io.mcap import McapRecorder

    McapRecorder(tmp_path / "run.mcap", geometry=g, start_ns=10**18).close()  # the MCAP scene
    with open(tmp_path / "run.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        ((_, _, _, scene),) = list(reader.iter_decoded_messages(topics=["/maze"]))
    by_id = {e.id: e for e in scene.entities}
    assert len(by_id) == len(scene_entities(g))
    assert len(by_id["doors"].arrows) == 6 and len(by_id["doors"].cubes) == 6
    fig, ax = plt.subplots()  # as cobel show draws a world
    draw_geometry(g, ax)
    doors = [c for c in ax.collections if c.get_label() == "one-way door"]
    assert len(doors) == 1 and len(doors[0].get_segments()) == 6
    plt.close(fig)

    two_way = manual([[0, 0], [1, 0], [1, 1]], [[0, 1], [1, 2]])
    assert one_way_doors(two_way.positions, two_way.edges).shape == (0, 6)
    one_way = manual([[0, 0], [2, 0]], [[1, 0]], directed=True)
    np.testing.assert_allclose(one_way_doors(one_way.positions, one_way.edges),
                               [[1.0, 0.5, 1.0, -0.5, -1.0, 0.0]])  # fmt: skip
