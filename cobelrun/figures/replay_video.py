"""Watch a run: the recorded poses of chosen trials drawn on the maze, frame by frame, as a
GIF or MP4 (``cobel replay RUN``).

With ``--greedy`` the saved agent is run instead, greedily, in the env its config builds
(:func:`greedy_steps`). Frames are drawn with matplotlib (the run's saved ``world.json``, the agent as a dot with a
heading tick and a fading trail) and encoded by the ffmpeg that ships inside the
``imageio-ffmpeg`` wheel (``pip install 'cobelrun[web]'``): H.264 for ``.mp4``, a palette GIF
for ``.gif``. Without ``--greedy`` only the recorded tables are read; no config is composed
and no agent is run.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cobelrun.errors import CobelError

#: output formats by suffix
FORMATS = (".gif", ".mp4")
#: frame size in pixels (both divisible by 16, as H.264 wants)
SIZE = (640, 480)
#: a GIF gets one palette of the frames' own colours (small files, no dithering noise)
GIF_PALETTE = (
    "split[a][b];[a]palettegen=max_colors=64:stats_mode=diff[p];[b][p]paletteuse=dither=none"
)
#: the most frames one video gets (a longer selection is refused, naming --trials)
MAX_FRAMES = 20_000


def select_steps(steps: pd.DataFrame, run: int, trials: str | None) -> pd.DataFrame:
    """The recorded steps of run ``run`` in the trial range ``trials`` (``A:B``), in order."""
    from cobelrun.figures.learned import parse_trials

    runs = sorted(int(r) for r in steps["run"].unique())
    if run not in runs:
        raise CobelError(f"run {run} has no recorded steps; recorded runs: "
                         f"{', '.join(map(str, runs[:20]))}")  # fmt: skip
    part = steps[steps["run"] == run]
    first, last = parse_trials(trials)
    have = sorted(int(t) for t in part["trial"].unique())
    if first is None and last is None:
        first = last = have[0]  # one trial unless asked for more
    if first is not None:
        part = part[part["trial"] >= first]
    if last is not None:
        part = part[part["trial"] <= last]
    if part.empty:
        raise CobelError(f"--trials {trials}: run {run} has recorded steps for trials "
                         f"{have[0]}..{have[-1]}")  # fmt: skip
    if len(part) > MAX_FRAMES:
        raise CobelError(f"{len(part):,} steps selected (at most {MAX_FRAMES:,} frames); "
                         "choose fewer with --trials A:B")  # fmt: skip
    return part.sort_values(["trial", "step"])


#: a camera: the (h, w, 3) uint8 view at a pose (x, y, heading in radians)
Camera = Callable[[float, float, float], np.ndarray]


def frames(
    steps: pd.DataFrame,
    geometry: Any,
    *,
    title: str = "",
    trail: int = 30,
    camera: Camera | None = None,
) -> Iterator[np.ndarray]:
    """RGB frames (H, W, 3) uint8, one per row of ``steps`` (a pose); with ``camera``, the
    view at each pose is drawn beside the maze."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from cobelrun.figures.runs import draw_geometry

    w, h = SIZE
    if camera is None:
        fig, ax = plt.subplots(figsize=(w / 100, h / 100), dpi=100)
        view_ax = None
    else:
        fig, (ax, view_ax) = plt.subplots(1, 2, figsize=(w / 100, h / 100), dpi=100,
                                          gridspec_kw={"width_ratios": [1.4, 1.0]})  # fmt: skip
    try:
        draw_geometry(geometry, ax, labels=len(geometry.regions) <= 12)
        (path_line,) = ax.plot([], [], color="tab:blue", lw=1.5, alpha=0.6, zorder=4)
        (dot,) = ax.plot([], [], "o", color="tab:red", ms=9, zorder=5)
        (tick,) = ax.plot([], [], color="tab:red", lw=2, zorder=5)
        label = fig.suptitle(" ", fontsize=9) if view_ax is not None else ax.set_title(" ")
        moving: tuple[Any, ...] = (path_line, dot, tick, label)
        if view_ax is not None and camera is not None and len(steps):
            first = steps.iloc[0]
            image = view_ax.imshow(camera(float(first["x"]), float(first["y"]),
                                          float(first.get("heading", 0.0))))  # fmt: skip
            view_ax.set_title("the agent's view", fontsize=8)
            view_ax.set_axis_off()
            moving = (*moving, image)
        fig.tight_layout()
        for artist in moving:
            artist.set_animated(True)  # drawn per frame over the maze drawn once (blitting)
        fig.canvas.draw()
        background = fig.canvas.copy_from_bbox(fig.bbox)
        size = (
            geometry.cell_size
            if geometry.kind == "grid"
            else 0.05
            * max(geometry.bounds[2] - geometry.bounds[0], geometry.bounds[3] - geometry.bounds[1])
        )
        x = steps["x"].to_numpy(float)
        y = steps["y"].to_numpy(float)
        heading = steps["heading"].to_numpy(float) if "heading" in steps else np.zeros(len(x))
        trial = steps["trial"].to_numpy()
        step = steps["step"].to_numpy()
        start = 0
        for i in range(len(x)):
            if i and trial[i] != trial[i - 1]:
                start = i
            lo = max(start, i - trail)
            path_line.set_data(x[lo : i + 1], y[lo : i + 1])
            dot.set_data([x[i]], [y[i]])
            hx, hy = np.cos(heading[i]) * 0.45 * size, np.sin(heading[i]) * 0.45 * size
            tick.set_data([x[i], x[i] + hx], [y[i], y[i] + hy])
            label.set_text(f"{title}trial {trial[i]}, step {step[i]}")
            if camera is not None:
                image.set_data(camera(float(x[i]), float(y[i]), float(heading[i])))
            fig.canvas.restore_region(background)
            for artist in moving:
                fig.draw_artist(artist)
            rgba = np.asarray(fig.canvas.buffer_rgba())
            yield np.ascontiguousarray(rgba[:h, :w, :3])
    finally:
        plt.close(fig)


def write_video(frames_iter: Iterator[np.ndarray], out: Path, fps: float) -> int:
    """Encode frames into ``out`` (``.mp4``: H.264; ``.gif``) with imageio-ffmpeg's ffmpeg;
    returns the number of frames written."""
    if out.suffix.lower() not in FORMATS:
        raise CobelError(f"--video {out}: the file must end in {' or '.join(FORMATS)}")
    try:
        import imageio_ffmpeg
    except ImportError:
        raise CobelError("cobel replay --video needs imageio-ffmpeg: pip install "
                         "'cobelrun[web]'") from None  # fmt: skip
    from cobelrun.io.atomic import atomic_path, disk_error

    gif = out.suffix.lower() == ".gif"
    n = 0
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(out) as tmp:
            writer = imageio_ffmpeg.write_frames(
                str(tmp), SIZE, fps=fps, codec="gif" if gif else "libx264",
                pix_fmt_out="pal8" if gif else "yuv420p", macro_block_size=1 if gif else 16,
                ffmpeg_log_level="error",
                output_params=(["-vf", GIF_PALETTE, "-f", "gif"] if gif else ["-f", "mp4"]),
            )  # fmt: skip
            writer.send(None)
            try:
                for frame in frames_iter:
                    writer.send(frame)
                    n += 1
            finally:
                writer.close()
    except OSError as exc:
        raise CobelError(disk_error(exc, out)) from None
    return n


def replay_file(
    run_dir: str | Path,
    out: str | Path | None = None,
    *,
    run: int = 0,
    trials: str | None = None,
    fps: float = 10.0,
    greedy_steps: pd.DataFrame | None = None,
    camera: Camera | None = None,
) -> tuple[Path, int]:
    """``cobel replay RUN``: write the video; returns (file, frames). ``greedy_steps``: poses
    of the saved agent run greedily (``cobel replay --greedy`` makes them,
    :func:`cobelrun.commands.replay.greedy_steps`) drawn instead of the recorded steps.
    ``camera``: the view at a pose, drawn beside the maze (``cobel replay`` makes it for 3D
    envs, :func:`cobelrun.commands.replay.camera_view`)."""
    from cobelrun.analysis.paths import visited_poses
    from cobelrun.figures.runs import load_geometry
    from cobelrun.figures.titles import run_title as _title
    from cobelrun.results import load_steps

    run_dir = Path(run_dir)
    if not fps > 0:
        raise CobelError(f"--fps {fps} must be > 0")
    target = Path(out) if out else run_dir / f"replay_run{run}.gif"
    if target.suffix.lower() not in FORMATS:
        raise CobelError(f"--video {target}: the file must end in {' or '.join(FORMATS)}")
    geometry = load_geometry(run_dir)
    if greedy_steps is not None:
        part = greedy_steps
        title = f"{_title(run_dir)}, run {run}, greedy: "
    else:
        # one frame per step, then each trial's arrival (the goal it reached)
        part = visited_poses(select_steps(load_steps(run_dir), run, trials))
        title = f"{_title(run_dir)}, run {run}: "
    n = write_video(frames(part, geometry, title=title, camera=camera), target, fps)
    return target, n
