"""``cobel replay RUN [--run R] [--trials A:B] [--video out.mp4|.gif]``: watch a run."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

HELP = """Watch a run: the agent moving through the maze or arena, from its recorded steps.

\b
Examples:
  cobel replay RUN_DIR                          # run 0, first trial -> RUN_DIR/replay_run0.gif
  cobel replay RUN_DIR --run 3 --trials 95:100 --video out.mp4
  cobel replay RUN_DIR --greedy --trials 1:3       # the saved agent, 3 greedy episodes
\b
Needs the run's steps (task.record.steps=true) and world.json; videos are encoded by the
ffmpeg inside the imageio-ffmpeg wheel (pip install 'cobelrun[web]'). Runs of 3D envs (camera
images) show the agent's view beside the maze (--no-camera: the maze only).
"""


def register(app: typer.Typer) -> None:
    """Add ``cobel replay`` to ``app``."""

    @app.command("replay", help=HELP)
    def replay_cmd(
        run_dir: Annotated[Path, typer.Argument(help="A run folder.", show_default=False)],
        run: Annotated[int, typer.Option("--run", help="Which run.")] = 0,
        trials: Annotated[
            str | None, typer.Option("--trials", help="Trials A:B (default: the first recorded).")
        ] = None,
        video: Annotated[
            Path | None,
            typer.Option("--video", help="Output .gif or .mp4 (default RUN_DIR/replay_runR.gif)."),
        ] = None,
        fps: Annotated[float, typer.Option("--fps", help="Frames (steps) per second.")] = 10.0,
        camera: Annotated[
            bool | None,
            typer.Option(
                "--camera/--no-camera",
                help="The agent's camera view beside the maze (default: on for envs that "
                "observe camera images; builds the env from the folder's config.yaml).",
                show_default=False,
            ),
        ] = None,
        greedy: Annotated[
            bool,
            typer.Option(
                "--greedy",
                help="Run the saved agent greedily instead (builds the "
                "env and agent from the folder's config, as cobel rerun does).",
            ),
        ] = False,
    ) -> None:
        from cobelrun.commands.common import fail
        from cobelrun.errors import CobelError
        from cobelrun.figures.learned import parse_trials
        from cobelrun.figures.replay_video import replay_file

        env = None
        try:
            steps = None
            if greedy:
                first, last = parse_trials(trials)
                episodes = 1 if first is None or last is None else max(1, last - first + 1)
                steps = greedy_steps(run_dir, run, episodes)
            view = None
            if camera or (camera is None and observes_images(run_dir)):
                env, view = camera_view(run_dir)
            path, n = replay_file(
                run_dir, video, run=run, trials=trials, fps=fps, greedy_steps=steps, camera=view
            )
        except CobelError as exc:
            fail(str(exc))
        finally:
            if env is not None:
                env.close()
        typer.echo(f"{path} ({n} frames)")


def greedy_steps(run_dir: str | Path, run: int, episodes: int = 1) -> Any:
    """Poses of ``episodes`` greedy episodes of run ``run``'s saved agent (argmax of its
    action values, no learning), in the env as the run's config builds it (its first phase), as
    a table of poses (run, trial, step, x, y, heading).

    This builds the env and the agent from the folder's
    ``config.yaml`` (:func:`cobelrun.api.rerun_config`: the same validation and instantiation
    gate as ``cobel rerun``), then loads the saved agent (checked against its schema).
    """
    import numpy as np
    import pandas as pd

    from cobelrun.api import rerun_config
    from cobelrun.envs.base import Posed
    from cobelrun.errors import CobelError
    from cobelrun.runner import build_task, load_saved_agent

    run_dir = Path(run_dir)
    cfg = rerun_config(run_dir)
    task = build_task(cfg)
    if task.job is not None or task.make_agent is None:
        raise CobelError(f"{run_dir}: a custom job ({cfg.task.name}) has no agent to replay")
    env = task.env
    try:
        if not isinstance(env.unwrapped, Posed):
            raise CobelError(f"env {type(env.unwrapped).__name__} has no pose to draw")
        agent = task.make_agent(seed=int(cfg.seed) + run)
        load_saved_agent(agent, str(run_dir), run)
        max_steps = int(cfg.task.protocol.get("max_steps") or 1000)
        rows = []
        for ep in range(episodes):
            obs, _ = env.reset(seed=int(cfg.seed) * 1000 + run * 100 + ep)
            for step in range(max_steps + 1):
                x, y, heading = (float(v) for v in env.unwrapped.agent_pose())
                rows.append((run, ep + 1, step, x, y, heading))
                if step == max_steps:
                    break
                q = np.asarray(agent.predict(np.asarray(obs)[None]))[0]
                obs, _, terminated, truncated, _ = env.step(int(np.argmax(q)))
                if terminated or truncated:
                    x, y, heading = (float(v) for v in env.unwrapped.agent_pose())
                    rows.append((run, ep + 1, step + 1, x, y, heading))  # the arrival
                    break
    finally:
        env.close()
    return pd.DataFrame(rows, columns=["run", "trial", "step", "x", "y", "heading"])


def observes_images(run_dir: str | Path) -> bool:
    """Whether the run's env observes camera images (an ``ImageObservation`` module, or an
    arena's ``view`` part), read from its ``config.yaml`` as data."""
    from omegaconf import OmegaConf

    from cobelrun.io.run_folder import RunFolder

    path = RunFolder(run_dir).config
    if not path.is_file():
        return False
    try:
        env = OmegaConf.to_container(OmegaConf.load(path).get("env") or {}, resolve=False)
    except Exception:  # a damaged config: no camera (the replay itself reads the tables)
        return False

    def walk(node: Any) -> bool:
        if isinstance(node, dict):
            if str(node.get("_target_", "")).endswith("ImageObservation"):
                return True
            if node.get("kind") == "view":
                return True
            return any(walk(v) for v in node.values())
        if isinstance(node, list):
            return any(walk(v) for v in node)
        return False

    return walk(env)


def camera_view(run_dir: str | Path) -> tuple[Any, Any]:
    """The env the run's ``config.yaml`` builds (its first phase's world; validated and
    instantiated as ``cobel rerun`` does, env only) and a camera for
    :func:`cobelrun.figures.replay_video.frames`: the RGB image the agent observes at a pose
    (x, y, heading), from the env's render cache (``render: offline``) or its pybullet scene.
    The caller closes the env."""
    import numpy as np

    from cobelrun.api import rerun_config
    from cobelrun.config import instantiate
    from cobelrun.errors import CobelError

    cfg = rerun_config(run_dir)
    env = instantiate("env", cfg.env)
    base = env.unwrapped
    modules = getattr(getattr(base, "observation_module", None), "image_modules", lambda: [])()
    if modules:
        render = modules[0].render_at_pose
    elif hasattr(base, "view_at_pose") and any(
        getattr(p, "kind", None) == "view" for p in getattr(base, "observation_parts", [])
    ):
        render = base.view_at_pose
    else:
        env.close()
        raise CobelError(f"env {type(base).__name__} of {run_dir} observes no camera images; "
                         "replay without --camera")  # fmt: skip

    def view(x: float, y: float, heading: float) -> np.ndarray:
        img = np.asarray(render(x, y, heading))
        if img.ndim == 3 and img.shape[0] in (1, 3) and img.shape[-1] not in (1, 3):
            img = np.moveaxis(img, 0, -1)  # channels first -> (h, w, c)
        if img.dtype != np.uint8:
            img = np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)
        if img.shape[-1] == 1:
            img = np.repeat(img, 3, axis=-1)
        return img

    return env, view
