"""Fig. 4 frame-time benchmark: the task job, `cobel run task=render_benchmark`, `cobel figure fig4`."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from cobelrun.agents.blas import blas_threads, set_blas_threads
from cobelrun.errors import ConfigError

pytest.importorskip("pybullet")

TINY = ["task.job.sizes=[[20,80]]", "task.job.trials=1", "task.job.steps=6", "task.job.repeats=2"]


def compose(overrides: list[str]):
    from cobelrun.figures.registry import _composer

    with _composer() as c:
        return c(["task=render_benchmark", *overrides])


def test_blas_threads_set_and_read_back():
    before = blas_threads()
    if not before:
        pytest.skip("no OpenBLAS found in this process")
    try:
        assert set_blas_threads(1) == len(before)
        assert blas_threads() == [1] * len(before)
        np.testing.assert_allclose(np.ones((4, 3)) @ np.arange(3.0), [3.0] * 4)
    finally:
        for n in set(before):
            set_blas_threads(n)


def test_frame_time_job_in_process(tmp_path, monkeypatch):
    """The job measures repetition x size x agent x mode, interleaved with the mode order
    alternating, builds the offline cache itself, and the runner writes the manifest and done
    marker around it."""
    from cobelrun.io.run_folder import DONE_MARKER
    from cobelrun.runner import run

    monkeypatch.setenv("COBEL_CACHE", str(tmp_path / "shared-cache"))
    cfg = compose([*TINY, "task.job.agents.dqn=null", "+task.job.agents.random=random"])
    out = run(cfg, tmp_path / "run")
    table = pd.read_csv(out / "frame_times.csv")
    modes = ["online", "offline", "none"]
    order = [(0, a, m) for a in ("mfec", "random") for m in modes]
    order += [(1, a, m) for a in ("mfec", "random") for m in modes[::-1]]
    assert list(zip(table["rep"], table["agent"], table["mode"], strict=True)) == order
    assert (table["frames"] == 5).all() and (table["frame_ms_mean"] > 0).all()
    # the same seeds and images in every mode of a repetition: the same foraging path
    assert table.groupby(["rep", "agent"])["steps"].nunique().eq(1).all()
    assert table.loc[table["mode"] == "offline", "cache_build_s"].gt(0).all()
    assert table.loc[table["mode"] != "offline", "cache_build_s"].isna().all()
    points = pd.read_csv(out / "frame_times_summary.csv")
    assert len(points) == 2 * 3 and points["reps"].eq(2).all()
    assert (points["q25_ms"] <= points["median_ms"]).all()
    assert (points["median_ms"] <= points["q75_ms"]).all()
    summary = json.loads((out / "frame_times.json").read_text())
    assert set(summary["offline_over_online"]) == {"mfec_20x80", "random_20x80"}
    assert set(summary["offline_over_none"]) == {"mfec_20x80", "random_20x80"}
    assert summary["steps"] == 6 and summary["trials"] == 1 and summary["repeats"] == 2
    assert summary["clock"] == "wall" and table["clock"].eq("wall").all()
    assert (out / "frame_times.png").stat().st_size > 0
    assert (out / DONE_MARKER).is_file()
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["status"] == "completed"
    assert not (tmp_path / "shared-cache").exists()  # fresh_cache: a temporary folder


def test_summary_medians_iqr_and_ratios():
    from cobelrun.render.benchmark import ratios, summarize

    rows = [{"agent": "a", "height": 2, "width": 3, "mode": mode, "rep": rep,
             "frame_ms_mean": base * (1 + rep)}
            for mode, base in (("online", 10.0), ("offline", 1.0), ("none", 0.8))
            for rep in range(5)]  # fmt: skip
    points = summarize(pd.DataFrame(rows)).set_index("mode")
    assert points.loc["online", "median_ms"] == 30.0 and points.loc["online", "reps"] == 5
    assert (points.loc["online", "q25_ms"], points.loc["online", "q75_ms"]) == (20.0, 40.0)
    r = ratios(pd.DataFrame(rows)).iloc[0]
    assert r["offline_over_online"] == pytest.approx(0.1)
    assert r["offline_over_none"] == pytest.approx(1.25)
    assert r["render_ms"] == pytest.approx(30.0 - 2.4)  # online - none medians
    missing = ratios(pd.DataFrame([x for x in rows if x["mode"] != "none"])).iloc[0]
    assert np.isnan(missing["offline_over_none"]) and missing["offline_over_online"] == 0.1


def test_no_render_mode_hands_out_the_offline_views_read_only(tmp_path):
    from cobelrun.config import instantiate
    from cobelrun.render.benchmark import build_caches
    from cobelrun.render.benchmark import sized_env_config as sized

    cfg = compose([])
    build_caches(sized(cfg.env, 16, 16, "offline", str(tmp_path)), jobs=1)
    off = instantiate("env", sized(cfg.env, 16, 16, "offline", str(tmp_path)))
    none = instantiate("env", sized(cfg.env, 16, 16, "none", str(tmp_path)))
    a, b = (e.unwrapped.observation_module for e in (off, none))
    assert type(b).__name__ == "NoRenderObservation"
    rng = np.random.default_rng(0)
    for node, heading in ((0, 0), (5, 3), (11, 1)):
        np.testing.assert_array_equal(a.observe(node, heading, rng), b.observe(node, heading, rng))
    for module in (a, b):  # neither the baseline nor the offline path copies a frame
        view = module.observe(3, 2, rng)
        assert not view.flags.writeable and np.shares_memory(view, module.observe(3, 2, rng))
        with pytest.raises(ValueError):
            view[0, 0, 0] = 1  # read-only: a consumer cannot change the cached frames
    assert not np.shares_memory(a.observe(3, 2, rng), b.observe(3, 2, rng))  # separate tables
    off.close()
    none.close()


def test_online_mode_renders_every_frame():
    from cobelrun.config import instantiate
    from cobelrun.render.benchmark import sized_env_config as sized

    env = instantiate("env", sized(compose([]).env, 16, 16, "online", None))
    module = env.unwrapped.observation_module
    assert module.reuse_views is False  # Fig. 4's online frames time the renderer every step
    rng = np.random.default_rng(0)
    a, b = module.observe(3, 2, rng), module.observe(3, 2, rng)
    assert np.array_equal(a, b) and not np.shares_memory(a, b)
    env.close()


def test_frame_time_job_shared_cache_and_validation(tmp_path, monkeypatch):
    from cobelrun.runner import build_task, run

    monkeypatch.setenv("COBEL_CACHE", str(tmp_path / "shared-cache"))
    over = [*TINY, "task.job.agents.dqn=null", "task.job.fresh_cache=false", "task.job.plot=false"]
    out = run(compose(over), tmp_path / "a")
    assert any((tmp_path / "shared-cache").iterdir())  # built into the shared cache
    assert pd.read_csv(out / "frame_times.csv")["cache_build_s"].notna().any()
    again = pd.read_csv(run(compose(over), tmp_path / "b") / "frame_times.csv")
    assert again["cache_build_s"].isna().all()  # found there: nothing built, nothing timed
    assert not (tmp_path / "b" / "frame_times.png").exists()
    for bad, match in (
        (["task.job.sizes=[[20]]"], r"task\.job\.sizes"),
        (["task.job.modes=[online,blender]"], r"task\.job\.modes"),
        (["task.job.modes=[online,online]"], r"task\.job\.modes"),
        (["task.job.repeats=0"], r"task\.job\.repeats"),
        (["task.job.clock=gpu"], r"task\.job\.clock"),
        (["+task.job.agents.mfec.kk=3"], r"unknown key 'task\.job\.agents\.mfec\.kk'"),
        (["task.job.steps=1"], r"task\.job\.steps"),
        (["+task.job.colour=red"], r"unknown key 'task\.job\.colour'"),
    ):
        with pytest.raises(ConfigError, match=match):
            build_task(compose(bad))


def test_cobel_run_render_benchmark_writes_table_and_plot(cobel, tmp_path):
    proc = cobel("run", "task=render_benchmark", *TINY, "hydra.run.dir=out",
                 env={"COBEL_CACHE": str(tmp_path / "cache")})  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    out = tmp_path / "out"
    table = pd.read_csv(out / "frame_times.csv")
    assert sorted(set(table["agent"])) == ["dqn", "mfec"]
    assert sorted(set(table["mode"])) == ["none", "offline", "online"]
    assert sorted(set(table["rep"])) == [0, 1]
    assert (out / "frame_times.png").is_file() and (out / ".done").is_file()


def test_figure_fig4_quick(cobel, tmp_path):
    proc = cobel("figure", "fig4", "--quick", env={"COBEL_CACHE": str(tmp_path / "cache")})
    assert proc.returncode == 0, proc.stderr
    out = tmp_path / "results" / "figures"
    for suffix in ("png", "pdf", "csv"):
        assert (out / f"fig4_quick.{suffix}").stat().st_size > 0
    table = pd.read_csv(out / "fig4_quick.csv")
    assert len(table) == 2 * 2  # sizes x agents, one column per mode and statistic
    assert table["reps"].eq(2).all()
    for col in ("online_median_ms", "offline_q25_ms", "none_q75_ms", "offline_over_online",
                "offline_over_none"):  # fmt: skip
        assert table[col].notna().all(), col


def test_measure_applies_the_phase_so_arm_ends_do_not_end_trials(tmp_path):
    """Foraging: every trial runs its full budget (the phase's terminals are applied after the
    world reset); without the phase a random walk soon ends a trial in an arm."""
    from cobelrun.render.benchmark import FrameTimeBenchmark, build_caches, measure
    from cobelrun.render.benchmark import sized_env_config as sized

    cfg = compose([])
    trials, steps, phase = FrameTimeBenchmark(agents={"r": "random"}).budget(cfg)
    assert (trials, steps) == (5, 400) and phase["terminals"] == {
        "left_arm": False,
        "right_arm": False,
    }
    env_cfg = sized(cfg.env, 20, 80, "offline", str(tmp_path))
    assert build_caches(env_cfg, jobs=1) > 0 and build_caches(env_cfg, jobs=1) is None
    r = measure(env_cfg, "random", trials=2, steps=300, seed=0, phase=phase)
    assert r["steps"] == 600 and r["frames"] == 598
    assert measure(env_cfg, "random", trials=2, steps=300, seed=0)["steps"] < 600


def test_frame_clock_times_between_step_starts_with_the_given_clock():
    from cobelrun.envs import TwoAFCEnv
    from cobelrun.render.benchmark import CLOCKS, FrameClock

    ticks = iter([10.0, 11.0, 13.0, 16.0, 20.0])
    env = FrameClock(TwoAFCEnv(), clock=lambda: next(ticks))
    env.reset(seed=0)
    for _ in range(3):
        env.step(0)
    env.reset()  # the gap across a reset is not a frame
    env.step(1)
    assert env.frames == [1.0, 2.0]
    assert set(CLOCKS) == {"wall", "cpu"}
