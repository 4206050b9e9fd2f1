"""Issue 33, "fix the pictures": arrival poses in the steps table (trajectories and occupancy
reach the goal), one-way doors as their own geometry, NWB positions against the trials table,
bands inside the measure's range, rate maps of arena cells, the camera view in replays."""

from __future__ import annotations

from pathlib import Path

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
