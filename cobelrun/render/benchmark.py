"""Fig. 4: mean frame time of online vs offline rendering, as a task job.

``task=render_benchmark`` names :class:`FrameTimeBenchmark` as its ``task.job``, so
``cobel run task=render_benchmark`` runs this instead of the standard protocol loop. For each
image size, agent and rendering mode (``online``: pybullet renders every step; ``offline``: the
images come from the render cache) it builds the task's environment at that size, lets a fresh
agent forage through the task's first protocol phase (rewards and terminals of that phase; the
paper: 5 trials x 400 steps) and takes the wall time of every step. The clock is read at the
start of each step, as in the paper, so a frame holds the agent's action selection and learning
and the environment's step with its rendering; trial ends (learning at trial end, reset) fall
between trials and are not frames.

Offline mode needs the render cache. The job builds it itself, through the same
:func:`cobelrun.render.cache.build` as ``cobel render-cache``, before any frame is timed, and
records the build time: with ``fresh_cache: true`` (default) every size is rendered into a
temporary folder, so the build is always timed and nothing is reused or left behind; with
``fresh_cache: false`` the shared cache (``$COBEL_CACHE``) is used and only missing sizes are
built (``cache_build_s`` is empty for sizes found there).

Writes into the run folder: ``frame_times.csv`` (one row per size x agent x mode),
``frame_times.json`` (settings, machine, offline/online ratios, cache build times) and
``frame_times.png`` (Fig. 4 style: frame time over image size, online vs offline, per agent).
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pandas as pd
from omegaconf import DictConfig, OmegaConf

from cobelrun.errors import CobelError, ConfigError
from cobelrun.io.atomic import atomic_path, atomic_write_text

#: Fig. 4's image sizes (height, width).
SIZES: tuple[tuple[int, int], ...] = ((20, 80), (30, 120), (45, 180), (60, 240), (75, 300))
MODES: tuple[str, ...] = ("online", "offline")
#: An agent entry with this value takes uniformly random actions (environment cost only).
RANDOM = "random"
TABLE = "frame_times.csv"
SUMMARY = "frame_times.json"
PLOT = "frame_times.png"


class FrameClock(gym.Wrapper):
    """Reads the clock at the start of every step; frame = time between consecutive step starts."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.frames: list[float] = []
        self._last: float | None = None

    def reset(self, **kwargs: Any) -> Any:
        self._last = None  # the time from the last step to a reset is not a frame
        return self.env.reset(**kwargs)

    def step(self, action: Any) -> Any:
        now = time.perf_counter()
        if self._last is not None:
            self.frames.append(now - self._last)
        self._last = now
        return self.env.step(action)


def _plain(node: Any) -> Any:
    if isinstance(node, DictConfig | Mapping) or OmegaConf.is_list(node):
        return OmegaConf.to_container(OmegaConf.create(node), resolve=True)
    return node


def sized_env_config(env_cfg: Any, height: int, width: int, mode: str, cache_dir: str | None):
    """The environment config at one image size and rendering mode (a plain dict)."""
    env = _plain(env_cfg)
    obs = env.get("observation") if isinstance(env, dict) else None
    if not isinstance(obs, dict) or not {"height", "width", "render"} <= set(obs):
        raise ConfigError(
            "task.job (frame-time benchmark) needs an image observation "
            "env.observation with height, width and render (e.g. env=tmaze_3d)"
        )
    obs.update(height=int(height), width=int(width), render=mode)
    if cache_dir is not None:
        obs["cache_dir"] = cache_dir
    return env


def build_caches(env_cfg: Mapping[str, Any], *, jobs: int | None = None) -> float | None:
    """Build the render cache of every image module of ``env_cfg`` (what ``cobel render-cache``
    does); returns the seconds spent rendering, ``None`` when everything was cached already."""
    from cobelrun.config import instantiate
    from cobelrun.render import cache

    with cache.building_mode():
        env = instantiate("env", env_cfg)
    try:
        module = getattr(env.unwrapped, "observation_module", None)
        seconds, built_any = 0.0, False
        for im in module.image_modules() if module is not None else []:
            t0 = time.perf_counter()
            _, built = cache.build(im.cache_request(), jobs=jobs)
            seconds += time.perf_counter() - t0
            built_any |= built
    finally:
        env.close()
    return seconds if built_any else None


def measure(
    env_cfg: Mapping[str, Any],
    agent: Any,
    *,
    trials: int,
    steps: int,
    seed: int,
    phase: Mapping[str, Any] | None = None,
    label: str = "agent",
) -> dict[str, Any]:
    """Frame times of one agent foraging ``trials x steps`` in the environment ``env_cfg``.

    ``agent`` is an agent config node (``_target_``; built on the timed environment) or
    ``"random"``. ``phase`` gives the rewards and terminals to apply (a protocol phase).
    """
    from cobelrun.config import instantiate
    from cobelrun.envs.base import Changeable
    from cobelrun.protocol import Protocol
    from cobelrun.runner import run_seed

    env = instantiate("env", env_cfg)
    try:
        agent_seed, env_seed = run_seed(seed, 0)
        base = env.unwrapped
        if isinstance(base, Changeable):
            base.reset_world()
        if phase is not None:  # after reset_world, which undoes changes (as in the runner)
            protocol = Protocol.from_config({"max_steps": steps, "phases": [dict(phase)]})
            protocol.apply(protocol.phases[0], env)
        base.np_random = np.random.default_rng(env_seed)
        timed = FrameClock(env)
        if agent == RANDOM:
            rng = np.random.default_rng(agent_seed)
            t0 = time.perf_counter()
            n_steps = 0
            for _ in range(trials):
                timed.reset()
                for _ in range(steps):
                    _, _, terminated, truncated, _ = timed.step(
                        int(rng.integers(timed.action_space.n))
                    )
                    n_steps += 1
                    if terminated or truncated:
                        break
        else:
            node = {k: v for k, v in _plain(agent).items() if k != "load_from"}
            make = instantiate(f"task.job.agents.{label}", node, env=timed, _partial_=True)
            ag = make(seed=agent_seed)
            t0 = time.perf_counter()
            n_steps = int(ag.train(trials, steps).n_steps)
        wall = time.perf_counter() - t0
        frames = np.asarray(timed.frames) * 1e3
    finally:
        env.close()
    if frames.size == 0:
        raise ConfigError("the frame-time benchmark needs at least 2 steps per trial")
    return {
        "steps": n_steps,
        "frames": int(frames.size),
        "frame_ms_mean": float(frames.mean()),
        "frame_ms_median": float(np.median(frames)),
        "frame_ms_std": float(frames.std()),
        "frame_ms_p90": float(np.percentile(frames, 90)),
        "wall_s": round(wall, 3),
    }


def ratios(table: pd.DataFrame) -> pd.DataFrame:
    """Offline over online mean frame time per agent and size (rows with both modes)."""
    key = ["agent", "height", "width"]
    wide = table.pivot_table(index=key, columns="mode", values="frame_ms_mean", sort=False)
    if not set(MODES) <= set(wide.columns):
        return pd.DataFrame(columns=[*key, "online_ms", "offline_ms", "offline_over_online"])
    out = wide[list(MODES)].rename(columns={"online": "online_ms", "offline": "offline_ms"})
    out["offline_over_online"] = out["offline_ms"] / out["online_ms"]
    return out.reset_index().rename_axis(columns=None)


def plot_frame_times(table: pd.DataFrame, axes: Sequence[Any] | None = None) -> Any:
    """Fig. 4 style: mean frame time (ms, log scale; bars: std) over image size, one panel per
    agent, online vs offline. Returns the matplotlib Figure."""
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FormatStrFormatter, NullFormatter

    agents = list(dict.fromkeys(table["agent"]))
    if axes is None:
        fig, grid = plt.subplots(
            1, len(agents), figsize=(3.4 * len(agents), 2.9), squeeze=False, layout="constrained"
        )
        axes = list(grid[0])
    fig = axes[0].figure
    sizes = (
        table[["height", "width"]]
        .drop_duplicates()
        .sort_values(["height", "width"])
        .itertuples(index=False)
    )
    labels = [f"{h}x{w}" for h, w in sizes]
    for ax, agent in zip(axes, agents, strict=False):
        for mode, style in (("online", "o-"), ("offline", "s--")):
            sel = table[(table["agent"] == agent) & (table["mode"] == mode)]
            if sel.empty:
                continue
            sel = sel.assign(
                label=[f"{h}x{w}" for h, w in zip(sel["height"], sel["width"], strict=True)]
            )
            sel = sel.set_index("label").reindex(labels).dropna(subset=["frame_ms_mean"])
            ax.errorbar(
                [labels.index(lb) for lb in sel.index],
                sel["frame_ms_mean"],
                yerr=[
                    np.minimum(sel["frame_ms_std"], sel["frame_ms_mean"] * 0.9),
                    sel["frame_ms_std"],
                ],
                fmt=style,
                capsize=2,
                label=mode,
            )
        ax.set_xticks(range(len(labels)), labels, rotation=30)
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
        ax.yaxis.set_minor_formatter(NullFormatter())
        ax.set_title(str(agent).upper())
        ax.set_xlabel("image size (pixels)")
        ax.set_ylabel("mean frame time (ms)")
        ax.legend(frameon=False)
    return fig


def machine() -> dict[str, Any]:
    from cobelrun.render.scene import pybullet_version

    pyb = pybullet_version()
    return {"cpus": os.cpu_count(), "python": platform.python_version(),
            "platform": platform.platform(), "pybullet": pyb}  # fmt: skip


class FrameTimeBenchmark:
    """Fig. 4 as a task job: frame times over image sizes x agents x {online, offline}.

    Parameters
    ----------
    sizes
        Image sizes ``[[height, width], ...]`` (default Fig. 4's 20x80 .. 75x300).
    agents
        Label -> agent config node (the task composes ``agent=mfec`` and ``agent=dqn`` here);
        ``"random"`` takes random actions (environment cost only); ``null`` drops an entry.
    modes
        Rendering modes to time (``online``, ``offline``).
    trials, steps
        Budget per measurement; ``null`` takes the first protocol phase's trials and the
        protocol's ``max_steps`` (the paper's 5 x 400).
    fresh_cache
        Build every offline cache into a temporary folder (always timed, nothing reused or left
        behind); ``false``: use the shared render cache, building only what is missing.
    cache_jobs
        Worker processes that build a cache (``null``: CPU count, as ``cobel render-cache``).
    plot
        Write ``frame_times.png``.
    """

    def __init__(
        self,
        sizes: Sequence[Sequence[int]] = SIZES,
        agents: Mapping[str, Any] | None = None,
        modes: Sequence[str] = MODES,
        trials: int | None = None,
        steps: int | None = None,
        fresh_cache: bool = True,
        cache_jobs: int | None = None,
        plot: bool = True,
    ) -> None:
        sizes = _plain(sizes)
        if isinstance(sizes, tuple):
            sizes = list(sizes)
        if not isinstance(sizes, list) or not sizes:
            raise ConfigError(f"task.job.sizes must be a list of [height, width], got {sizes!r}")
        for s in sizes:
            if (
                not isinstance(s, list | tuple)
                or len(s) != 2
                or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in s)
            ):
                raise ConfigError(f"task.job.sizes: {s!r} is not [height, width] in pixels")
        self.sizes = [(int(h), int(w)) for h, w in sizes]
        agents = {str(k): v for k, v in (_plain(agents) or {}).items() if v is not None}
        if not agents:
            raise ConfigError("task.job.agents is empty; give at least one agent config")
        from cobelrun.config import validate_node

        for label, node in agents.items():
            if node == RANDOM:
                continue
            if not (isinstance(node, dict) and "_target_" in node):
                raise ConfigError(
                    f"task.job.agents.{label} must be an agent config (with _target_) or "
                    f"'{RANDOM}', got {node!r}"
                )
            node = {k: v for k, v in node.items() if k != "load_from"}
            validate_node(f"task.job.agents.{label}", node, provided=["env", "seed"])
        self.agents = agents
        modes = list(_plain(modes))
        bad = [m for m in modes if m not in MODES]
        if not modes or bad:
            raise ConfigError(f"task.job.modes {bad or modes!r}: allowed 'online', 'offline'")
        self.modes = modes
        for name, value in (("trials", trials), ("steps", steps), ("cache_jobs", cache_jobs)):
            if value is not None and (
                isinstance(value, bool) or not isinstance(value, int) or value < 1
            ):
                raise ConfigError(f"task.job.{name} must be null or an integer >= 1, got {value!r}")
        if steps is not None and steps < 2:
            raise ConfigError("task.job.steps must be >= 2 (a frame is the time between steps)")
        self.trials, self.steps = trials, steps
        self.fresh_cache, self.cache_jobs, self.plot = bool(fresh_cache), cache_jobs, bool(plot)

    def budget(self, cfg: Any) -> tuple[int, int, dict[str, Any] | None]:
        """(trials, steps, first protocol phase) of a composed config."""
        protocol = _plain(cfg.task.get("protocol")) if "task" in cfg else None
        phase = dict(protocol["phases"][0]) if protocol and protocol.get("phases") else None
        trials = self.trials or (phase or {}).get("trials") or 1
        steps = self.steps or (phase or {}).get("max_steps") or (protocol or {}).get("max_steps")
        if not steps:
            raise ConfigError("task.job.steps is not set and the task has no protocol.max_steps")
        if phase is not None:
            phase = {k: v for k, v in phase.items() if k not in ("trials", "max_steps")}
            phase["trials"] = trials
        return int(trials), int(steps), phase

    def __call__(
        self, cfg: Any, run_dir: Path, progress: Callable[..., None] | None = None
    ) -> dict[str, Any]:
        run_dir = Path(run_dir)
        trials, steps, phase = self.budget(cfg)
        seed = int(cfg.seed)
        tmp = tempfile.mkdtemp(prefix="cobel-frame-cache-") if self.fresh_cache else None
        total = len(self.sizes) * len(self.agents) * len(self.modes)
        rows: list[dict[str, Any]] = []
        builds: list[dict[str, Any]] = []
        try:
            for h, w in self.sizes:
                build_s = None
                if "offline" in self.modes:
                    env_off = sized_env_config(cfg.env, h, w, "offline", tmp)
                    build_s = build_caches(env_off, jobs=self.cache_jobs)
                    builds.append({"height": h, "width": w, "seconds": build_s})
                for label, agent in self.agents.items():
                    for mode in self.modes:
                        env_cfg = sized_env_config(
                            cfg.env, h, w, mode, tmp if mode == "offline" else None
                        )
                        r = measure(env_cfg, agent, trials=trials, steps=steps, seed=seed,
                                    phase=phase, label=label)  # fmt: skip
                        rows.append({"agent": label, "height": h, "width": w, "pixels": h * w,
                                     "mode": mode, **r,
                                     "cache_build_s": build_s if mode == "offline" else None})  # fmt: skip
                        if progress is not None:
                            progress(len(rows), total, run=0, runs=1)
        finally:
            if tmp is not None:
                shutil.rmtree(tmp, ignore_errors=True)
        table = pd.DataFrame(rows)
        with atomic_path(run_dir / TABLE) as tmp:
            table.to_csv(tmp, index=False)
        rat = ratios(table)
        summary = {
            "benchmark": "frame_times",
            "trials": trials,
            "steps": steps,
            "seed": seed,
            "fresh_cache": self.fresh_cache,
            "machine": machine(),
            "offline_over_online": {
                f"{r.agent}_{r.height}x{r.width}": round(float(r.offline_over_online), 4)
                for r in rat.itertuples()
            },
            "cache_build_s": {f"{b['height']}x{b['width']}": b["seconds"] for b in builds},
        }
        atomic_write_text(run_dir / SUMMARY, json.dumps(summary, indent=1))
        if self.plot:
            import matplotlib

            matplotlib.use("Agg")
            from cobelrun.figures import save_figure

            save_figure(plot_frame_times(table), run_dir / PLOT)
        return summary


def load_table(run_dir: str | os.PathLike[str]) -> pd.DataFrame:
    """The frame-time table of a ``task=render_benchmark`` run folder."""
    path = Path(run_dir) / TABLE
    if not path.is_file():
        raise CobelError(f"{run_dir} has no {TABLE}; is it a task=render_benchmark run?")
    return pd.read_csv(path)
