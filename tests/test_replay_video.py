"""``cobel replay``: the recorded poses of chosen trials as a video, one frame per step,
encoded by imageio-ffmpeg's ffmpeg; bad selections are one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import cobelrun
from cobelrun.errors import CobelError
from cobelrun.figures.replay_video import SIZE, frames, replay_file, select_steps
from cobelrun.figures.runs import load_geometry

pytest.importorskip(
    "imageio_ffmpeg", reason="cobel replay --video needs imageio-ffmpeg (web extra)"
)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("replay") / "run"
    cobelrun.run("tmaze_extinction", ["task.runs=2", "task.protocol.phases.0.trials=4",
                                      "task.protocol.phases.1.trials=2"], out=out)  # fmt: skip
    return out


def test_mp4_has_one_frame_per_recorded_step(run_dir: Path, tmp_path: Path) -> None:
    import imageio_ffmpeg

    steps = cobelrun.load(run_dir).steps
    want = steps[(steps["run"] == 1) & steps["trial"].between(2, 3)]
    path, n = replay_file(run_dir, tmp_path / "v.mp4", run=1, trials="2:3", fps=20)
    assert n == len(want) + 2 > 2  # each step, then each trial's arrival
    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    assert tuple(meta["size"]) == SIZE
    assert sum(1 for _ in reader) == n


def test_frames_move_with_the_agent(run_dir: Path) -> None:
    steps = select_steps(cobelrun.load(run_dir).steps, 0, "1")
    got = list(frames(steps.head(3), load_geometry(run_dir)))
    assert all(f.shape == (SIZE[1], SIZE[0], 3) and f.dtype == np.uint8 for f in got)
    if steps["x"].iloc[0] != steps["x"].iloc[1] or steps["y"].iloc[0] != steps["y"].iloc[1]:
        assert not np.array_equal(got[0], got[1])


def test_gif_default_name_and_one_line_errors(run_dir: Path, tmp_path: Path) -> None:
    path, n = replay_file(run_dir, tmp_path / "a.gif", trials="1")
    assert path.read_bytes()[:6] in (b"GIF89a", b"GIF87a") and n > 0
    with pytest.raises(CobelError, match=r"must end in \.gif or \.mp4"):
        replay_file(run_dir, tmp_path / "a.avi")
    with pytest.raises(CobelError, match="recorded runs: 0, 1"):
        replay_file(run_dir, tmp_path / "b.gif", run=9)
    with pytest.raises(CobelError, match=r"has recorded steps for trials 1\.\.6"):
        replay_file(run_dir, tmp_path / "b.gif", trials="50:60")
    assert not (tmp_path / "b.gif").exists()


def test_greedy_replay_runs_the_saved_agent(run_dir: Path, tmp_path: Path) -> None:
    from cobelrun.commands.replay import greedy_steps

    steps = cobelrun.load(run_dir).steps
    a = greedy_steps(run_dir, 1)
    b = greedy_steps(run_dir, 1)
    assert a.equals(b)  # greedy and seeded: the same path twice
    first = steps[(steps["run"] == 1)].sort_values(["trial", "step"]).iloc[0]
    assert (a["x"].iloc[0], a["y"].iloc[0]) == (first["x"], first["y"])  # the start pose
    moves = np.hypot(np.diff(a["x"]), np.diff(a["y"]))
    assert (moves <= 1.0 + 1e-9).all() and len(a) <= 36  # one cell a step, max_steps 35
    _, n = replay_file(run_dir, tmp_path / "g.gif", run=1, greedy_steps=greedy_steps(run_dir, 1))
    assert n == len(a)
    with pytest.raises(CobelError, match=r"no saved agent for run 9"):
        greedy_steps(run_dir, 9)
