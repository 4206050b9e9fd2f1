"""Fig. 4: frame time of online vs offline rendering, as a task job.

``task=render_benchmark`` names :class:`FrameTimeBenchmark` as its ``task.job``, so
``cobel run task=render_benchmark`` runs this instead of the standard protocol loop. For each
image size, agent and rendering mode it builds the task's environment at that size, lets a fresh
agent forage through the task's first protocol phase (rewards and terminals of that phase) and
takes the wall time of every step. The clock is read at the start of each step, as in the paper,
so a frame holds the agent's action selection and learning and the environment's step with its
rendering; trial ends (learning at trial end, reset) fall between trials and are not frames.

Modes:

- ``online``: pybullet renders every step (``reuse_views: false``);
- ``offline``: the images come from the render cache (an array lookup);
- ``none``: the no-render baseline: the same views, loaded into memory before timing and handed
  out as read-only array views (:class:`NoRenderObservation`), so a frame holds only the agent's
  and the environment's own cost. Online, offline and no-render runs of a repetition use the
  same seeds and see the same images, so they take the same actions.

Every point is measured ``repeats`` times; the repetitions are interleaved (repetition ``r``
measures every size, agent and mode before repetition ``r + 1`` starts, and the mode order
alternates between repetitions) so that changing machine load hits all modes alike. A
repetition's value is its mean frame time; points are summarised as median and interquartile
range over the repetitions (:func:`summarize`).

Offline mode needs the render cache. The job builds it itself, through the same
:func:`cobelrun.render.cache.build` as ``cobel render-cache``, before any frame is timed, and
records the build time: with ``fresh_cache: true`` (default) every size is rendered into a
temporary folder, so the build is always timed and nothing is reused or left behind; with
``fresh_cache: false`` the shared cache (``$COBEL_CACHE``) is used and only missing sizes are
built (``cache_build_s`` is empty for sizes found there).

Writes into the run folder: ``frame_times.csv`` (one row per repetition x size x agent x mode),
``frame_times_summary.csv`` (median and IQR per point, offline/online and offline/no-render),
``frame_times.json`` (settings, machine, ratios, cache build times) and ``frame_times.png``.
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

from cobelrun.envs.observations import ImageObservation
from cobelrun.errors import CobelError, ConfigError
from cobelrun.io.atomic import atomic_path, atomic_write_text

#: Fig. 4's image sizes (height, width).
SIZES: tuple[tuple[int, int], ...] = ((20, 80), (30, 120), (45, 180), (60, 240), (75, 300))
#: the square sizes of the original's online/offline scripts (16 .. 256 px)
SQUARE_SIZES: tuple[tuple[int, int], ...] = ((16, 16), (32, 32), (64, 64), (128, 128), (256, 256))
MODES: tuple[str, ...] = ("online", "offline", "none")
#: the paper's published frame times (ms; Blender, 16-core Xeon + Quadro RTX 5000), MFEC
PAPER_MS: dict[tuple[int, int], dict[str, float]] = {
    (20, 80): {"online": 16.9, "offline": 1.5},
    (75, 300): {"online": 34.1, "offline": 24.2},
}
#: An agent entry with this value takes uniformly random actions (environment cost only).
RANDOM = "random"
TABLE = "frame_times.csv"
POINTS = "frame_times_summary.csv"
SUMMARY = "frame_times.json"
PLOT = "frame_times.png"


#: frame clocks: wall time (the paper's) or this process's CPU time (robust to machine load;
#: pybullet's DIRECT renderer and torch run in-process, so their work is counted)
CLOCKS: dict[str, Callable[[], float]] = {"wall": time.perf_counter, "cpu": time.process_time}


class FrameClock(gym.Wrapper):
    """Reads the clock at the start of every step; frame = time between consecutive step starts."""

    def __init__(self, env: gym.Env, clock: Callable[[], float] = time.perf_counter) -> None:
        super().__init__(env)
        self.frames: list[float] = []
        self.clock = clock
        self._last: float | None = None

    def reset(self, **kwargs: Any) -> Any:
        self._last = None  # the time from the last step to a reset is not a frame
        return self.env.reset(**kwargs)

    def step(self, action: Any) -> Any:
        now = self.clock()
        if self._last is not None:
            self.frames.append(now - self._last)
        self._last = now
        return self.env.step(action)


class NoRenderObservation(ImageObservation):
    """The no-render baseline's observation module: the render cache's views, loaded into memory
    before any frame is timed, returned as read-only array views (no renderer, no copy). The
    images, and so the agent's trajectory for a seed, are the same as online and offline; what
    a frame holds is the agent's and the environment's own cost. :func:`sized_env_config` puts
    it in place of the image module for mode ``none``."""

    def _load_offline(self) -> None:
        super()._load_offline()
        assert self._obs_table is not None
        self._obs_table.setflags(write=False)

    def observe(self, node: int, heading: int, rng: np.random.Generator) -> np.ndarray:
        if self._obs_table is None:
            self._load_offline()
        return self._obs_table[node, heading]  # type: ignore[index]


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
    if mode == "none":
        obs["_target_"] = f"{__name__}.NoRenderObservation"
    obs.update(height=int(height), width=int(width), render="offline" if mode == "none" else mode)
    if mode == "online":
        obs["reuse_views"] = False  # online frames time the renderer on every step
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
    rep: int = 0,
    clock: str = "wall",
) -> dict[str, Any]:
    """Frame times of one agent foraging ``trials x steps`` in the environment ``env_cfg``.

    ``agent`` is an agent config node (``_target_``; built on the timed environment) or
    ``"random"``. ``phase`` gives the rewards and terminals to apply (a protocol phase).
    Repetition ``rep`` draws its agent and environment seeds from ``seed`` (the same in every
    mode, so online, offline and no-render runs of a repetition see the same views).
    """
    from cobelrun.config import instantiate
    from cobelrun.envs.base import Changeable
    from cobelrun.protocol import Protocol
    from cobelrun.runner import run_seed

    env = instantiate("env", env_cfg)
    try:
        agent_seed, env_seed = run_seed(seed, rep)
        base = env.unwrapped
        if isinstance(base, Changeable):
            base.reset_world()
        if phase is not None:  # after reset_world, which undoes changes (as in the runner)
            protocol = Protocol.from_config({"max_steps": steps, "phases": [dict(phase)]})
            protocol.apply(protocol.phases[0], env)
        base.np_random = np.random.default_rng(env_seed)
        timed = FrameClock(env, CLOCKS[clock])
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


KEY = ["agent", "height", "width"]


def summarize(table: pd.DataFrame) -> pd.DataFrame:
    """Median and interquartile range of the repetitions' mean frame times per agent, size and
    mode (long format: ``agent, height, width, pixels, mode, reps, median_ms, q25_ms, q75_ms``)."""
    g = table.groupby([*KEY, "mode"], sort=False)["frame_ms_mean"]
    out = pd.DataFrame({
        "reps": g.count(),
        "median_ms": g.median(),
        "q25_ms": g.quantile(0.25),
        "q75_ms": g.quantile(0.75),
    }).reset_index()  # fmt: skip
    out.insert(3, "pixels", out["height"] * out["width"])
    return out


def ratios(table: pd.DataFrame) -> pd.DataFrame:
    """Per agent and size: median frame time per mode (``online_ms``, ``offline_ms``,
    ``none_ms``), ``offline_over_online``, ``offline_over_none`` (the render overhead left
    offline) and ``render_ms`` (online - none: the renderer's cost per frame), from the
    repetitions' medians. Missing modes give NaN."""
    points = summarize(table)
    wide = points.pivot_table(index=KEY, columns="mode", values="median_ms", sort=False)
    wide = wide.reindex(columns=list(MODES))
    out = wide.rename(columns={m: f"{m}_ms" for m in MODES}).rename_axis(columns=None)
    out["offline_over_online"] = out["offline_ms"] / out["online_ms"]
    out["offline_over_none"] = out["offline_ms"] / out["none_ms"]
    out["render_ms"] = out["online_ms"] - out["none_ms"]  # the renderer's share of a frame
    return out.reset_index()


_STYLE = {"online": ("o-", "tab:red"), "offline": ("s-", "tab:blue"), "none": ("^:", "0.3")}
_LABEL = {"online": "online", "offline": "offline (render cache)", "none": "no rendering"}


def plot_frame_times(table: pd.DataFrame, axes: Any = None) -> Any:
    """Fig. 4 style, one column per agent: top, frame time (median and IQR over repetitions, log
    scales) over image size (pixels) online, offline and without rendering, with the paper's
    published frame times; bottom, offline/online with the paper's two ratios. ``axes``: a
    2 x n_agents array of axes (default: a new figure). Returns the matplotlib Figure."""
    import matplotlib.pyplot as plt

    agents = list(dict.fromkeys(table["agent"]))
    if axes is None:
        _, axes = plt.subplots(2, len(agents), figsize=(3.6 * len(agents), 5.2), squeeze=False,
                               sharex=True, layout="constrained")  # fmt: skip
    axes = np.asarray(axes).reshape(2, -1)
    points, rat = summarize(table), ratios(table)
    for col, agent in enumerate(agents):
        top, bottom = axes[0, col], axes[1, col]
        for mode in MODES:
            sel = points[(points["agent"] == agent) & (points["mode"] == mode)]
            if sel.empty:
                continue
            sel = sel.sort_values("pixels")
            fmt, color = _STYLE[mode]
            yerr = [sel["median_ms"] - sel["q25_ms"], sel["q75_ms"] - sel["median_ms"]]
            top.errorbar(sel["pixels"], sel["median_ms"], yerr=yerr, fmt=fmt, color=color,
                         ms=4, capsize=2, label=_LABEL[mode])  # fmt: skip
        for (h, w), ms in PAPER_MS.items():
            for mode, marker in (("online", "*"), ("offline", "P")):
                top.plot(h * w, ms[mode], marker, color=_STYLE[mode][1], mfc="none", ms=8,
                         label=f"paper {mode} (Blender)" if (h, w) == (20, 80) else None)  # fmt: skip
        r = rat[rat["agent"] == agent].assign(pixels=lambda d: d["height"] * d["width"])
        r = r.sort_values("pixels")
        bottom.plot(r["pixels"], r["offline_over_online"], "s-", color="tab:blue", ms=4,
                    label="offline / online (here)")  # fmt: skip
        paper = [(h * w, ms["offline"] / ms["online"]) for (h, w), ms in PAPER_MS.items()]
        bottom.plot(*zip(*paper, strict=True), "*", color="k", ms=9,
                    label="paper: 20x80 0.089 (11x), 75x300 0.71 (1.4x)")  # fmt: skip
        for ax in (top, bottom):
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.spines[["top", "right"]].set_visible(False)
        top.set_title(str(agent).upper())
        top.set_ylabel("frame time (ms)")
        bottom.set_ylabel("offline / online")
        bottom.set_xlabel("image size (pixels, h x w)")
        bottom.axhline(1.0, color="0.6", lw=0.8, ls="--")
        top.legend(frameon=False, fontsize=6)
        bottom.legend(frameon=False, fontsize=6)
    return axes[0, 0].figure


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
        Image sizes ``[[height, width], ...]`` (default Fig. 4's 20x80 .. 75x300; the task adds
        the original scripts' squares 16 .. 256 px).
    agents
        Label -> agent config node (the task composes ``agent=mfec`` and ``agent=dqn`` here);
        ``"random"`` takes random actions (environment cost only); ``null`` drops an entry.
    modes
        Rendering modes to time: ``online``, ``offline``, ``none`` (the no-render baseline).
    repeats
        Repetitions of every point, interleaved (see the module docstring); >= 1.
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
    clock
        ``wall`` (default, the paper's: wall time per step) or ``cpu`` (this process's CPU time
        per step: what the step costs, whatever else the machine runs; renderer and torch work
        in-process, so both count).
    """

    def __init__(
        self,
        sizes: Sequence[Sequence[int]] = SIZES,
        agents: Mapping[str, Any] | None = None,
        modes: Sequence[str] = MODES,
        repeats: int = 5,
        trials: int | None = None,
        steps: int | None = None,
        fresh_cache: bool = True,
        cache_jobs: int | None = None,
        plot: bool = True,
        clock: str = "wall",
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
        if not modes or bad or len(set(modes)) != len(modes):
            raise ConfigError(
                f"task.job.modes {bad or modes!r}: allowed 'online', 'offline', 'none', each once"
            )
        self.modes = modes
        if isinstance(repeats, bool) or not isinstance(repeats, int) or repeats < 1:
            raise ConfigError(f"task.job.repeats must be an integer >= 1, got {repeats!r}")
        self.repeats = repeats
        for name, value in (("trials", trials), ("steps", steps), ("cache_jobs", cache_jobs)):
            if value is not None and (
                isinstance(value, bool) or not isinstance(value, int) or value < 1
            ):
                raise ConfigError(f"task.job.{name} must be null or an integer >= 1, got {value!r}")
        if steps is not None and steps < 2:
            raise ConfigError("task.job.steps must be >= 2 (a frame is the time between steps)")
        self.trials, self.steps = trials, steps
        self.fresh_cache, self.cache_jobs, self.plot = bool(fresh_cache), cache_jobs, bool(plot)
        if clock not in CLOCKS:
            raise ConfigError(f"task.job.clock {clock!r} is not known; allowed: 'wall', 'cpu'")
        self.clock = clock

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
        total = self.repeats * len(self.sizes) * len(self.agents) * len(self.modes)
        rows: list[dict[str, Any]] = []
        builds: dict[tuple[int, int], float | None] = {}
        try:
            if {"offline", "none"} & set(self.modes):  # every cache before the first timed frame
                for h, w in self.sizes:
                    env_off = sized_env_config(cfg.env, h, w, "offline", tmp)
                    builds[(h, w)] = build_caches(env_off, jobs=self.cache_jobs)
            for rep in range(self.repeats):
                modes = self.modes if rep % 2 == 0 else self.modes[::-1]
                for h, w in self.sizes:
                    for label, agent in self.agents.items():
                        for mode in modes:
                            env_cfg = sized_env_config(
                                cfg.env, h, w, mode, tmp if mode != "online" else None
                            )
                            r = measure(env_cfg, agent, trials=trials, steps=steps, seed=seed,
                                        phase=phase, label=label, rep=rep, clock=self.clock)  # fmt: skip
                            rows.append({"rep": rep, "agent": label, "height": h, "width": w,
                                         "pixels": h * w, "mode": mode, "clock": self.clock, **r,
                                         "cache_build_s": builds.get((h, w))
                                         if mode == "offline" else None})  # fmt: skip
                            if progress is not None:
                                progress(len(rows), total, run=0, runs=1)
                # every finished repetition is on disk: a stopped job keeps what it measured
                pd.DataFrame(rows).to_csv(run_dir / TABLE, index=False)
        finally:
            if tmp is not None:
                shutil.rmtree(tmp, ignore_errors=True)
        table = pd.DataFrame(rows)
        with atomic_path(run_dir / TABLE) as tmp:
            table.to_csv(tmp, index=False)
        with atomic_path(run_dir / POINTS) as tmp:
            summarize(table).to_csv(tmp, index=False)
        rat = ratios(table)

        def by_point(col: str) -> dict[str, float]:
            return {f"{r.agent}_{r.height}x{r.width}": round(float(getattr(r, col)), 4)
                    for r in rat.itertuples() if np.isfinite(getattr(r, col))}  # fmt: skip

        summary = {
            "benchmark": "frame_times",
            "trials": trials,
            "steps": steps,
            "repeats": self.repeats,
            "clock": self.clock,
            "seed": seed,
            "fresh_cache": self.fresh_cache,
            "machine": machine(),
            "offline_over_online": by_point("offline_over_online"),
            "offline_over_none": by_point("offline_over_none"),
            "cache_build_s": {f"{h}x{w}": b for (h, w), b in builds.items()},
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
