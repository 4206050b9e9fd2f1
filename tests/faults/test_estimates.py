"""Estimate before allocating, and bad saved agents refused before any folder exists (issue 31,
item 4 and the bad ``+agent.load_from`` files of item 7): an agent archive whose member would
decompress to gigabytes, a sweep of ten million jobs and a 20,000 x 20,000 camera image are
each refused in one line within seconds, with nothing allocated and no folder made."""

from __future__ import annotations

import io
import shutil
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from tests.faults.folders import TINY, copy_folder

#: bytes the bomb's Q member claims (and would decompress to)
BOMB_BYTES = 2_000_000_000


def _npy(arr: np.ndarray) -> bytes:
    b = io.BytesIO()
    np.lib.format.write_array(b, arr, allow_pickle=False)
    return b.getvalue()


def bomb_archive(src: Path, dst: Path, *, data_bytes: int = 8 << 20) -> None:
    """A copy of ``src`` (a real agents.npz) whose ``Q`` member's header and shape table claim
    2 GB of float64 (a 1000:1 deflate bomb, as the issue's 1.9 MB file). Only ``data_bytes``
    of zeros are stored: a reader that checks the header first never gets to them, one that
    loads first would allocate the 2 GB (or fail reading them)."""
    n = BOMB_BYTES // 8
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED) as zout:
        for name in zin.namelist():
            if name == "Q.shape.npy":
                zout.writestr(name, _npy(np.array([[n]], np.int64)))
            elif name == "Q.npy":
                with zout.open(name, "w", force_zip64=True) as out:
                    header = {"descr": "<f8", "fortran_order": False, "shape": (n,)}
                    np.lib.format.write_array_header_2_0(out, header)
                    out.write(bytes(data_bytes))
            else:
                zout.writestr(name, zin.read(name))


def _no_run_folder(results: Path) -> None:
    made = [p for p in results.rglob("*")] if results.exists() else []
    assert not made, f"a run folder was made: {made[:5]}"


def _one_line(proc) -> str:
    assert proc.returncode != 0, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("cobel: error:")]
    assert len(errors) == 1, proc.stderr
    return errors[0]


BAD_AGENTS = {
    "truncated": lambda f: f.write_bytes(f.read_bytes()[: f.stat().st_size // 2]),
    "not-an-npz": lambda f: f.write_text("hello"),
    "empty": lambda f: f.write_bytes(b""),
}


@pytest.mark.parametrize("case", sorted(BAD_AGENTS))
def test_bad_load_from_archive_is_refused_before_any_folder(cobel, real_run, tmp_path, case):
    src = copy_folder(real_run, tmp_path / "saved")
    BAD_AGENTS[case](src / "agents.npz")
    proc = cobel("run", "--quiet", *TINY, f"+agent.load_from={src}")
    line = _one_line(proc)
    assert "cannot load agent from" in line and "agents.npz" in line
    _no_run_folder(tmp_path / "results")


def test_load_from_agent_of_another_shape_is_refused_before_any_folder(cobel, real_run, tmp_path):
    """A saved agent of a 7x7 T-maze loaded into a gridworld of another size."""
    proc = cobel("run", "--quiet", "task=gridworld", "task.runs=1", f"+agent.load_from={real_run}")
    line = _one_line(proc)
    assert "cannot load agent from" in line and "key 'Q' of run 0: expected shape" in line
    _no_run_folder(tmp_path / "results")


def test_load_from_single_file_with_nan_is_refused_before_any_folder(cobel, real_run, tmp_path):
    """A single agent file (older layout) whose Q table holds NaN."""
    from cobelrun.io.agents_archive import read_agent

    arrays, meta = read_agent(real_run / "agents.npz", 0)
    arrays["Q"] = arrays["Q"].copy()
    arrays["Q"][0, 0] = np.nan
    import json

    path = tmp_path / "agent.npz"
    np.savez(path, __meta__=np.array(json.dumps(meta)), **arrays)
    proc = cobel("run", "--quiet", *TINY, f"+agent.load_from={path}")
    line = _one_line(proc)
    assert "expected finite values" in line
    _no_run_folder(tmp_path / "results")


def test_agents_npz_bomb_is_refused_from_its_header(real_run, tmp_path):
    """The 2 GB member is refused in one line, in well under a second, and nothing near its
    size is allocated (tracemalloc's peak stays below 64 MB)."""
    import tracemalloc

    from cobelrun.agents.base import check_load_from
    from cobelrun.errors import ConfigError
    from cobelrun.hydra_app import composer
    from cobelrun.runner import build_task

    saved = tmp_path / "saved"
    saved.mkdir()
    bomb_archive(real_run / "agents.npz", saved / "agents.npz")
    assert (saved / "agents.npz").stat().st_size < 1 << 20  # small on disk
    with composer() as compose:
        cfg = compose(list(TINY))
    agent = build_task(cfg).make_agent(seed=0)
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        with pytest.raises(
            ConfigError, match=r"key 'Q' of run 0: expected shape \(49, 4\), got \(250000000,\)"
        ):
            check_load_from(agent, str(saved), 1)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert time.perf_counter() - t0 < 30  # bounds a hang; the memory peak is the test
    assert peak < 64 << 20, f"peak {peak / 2**20:.0f} MiB"


def test_single_agent_file_bomb_is_refused_from_its_header(real_run, tmp_path):
    """An agent file (not an archive) whose member claims 2 GB: refused from its header."""
    import tracemalloc

    from cobelrun.errors import ConfigError
    from cobelrun.hydra_app import composer
    from cobelrun.runner import build_task

    path = tmp_path / "agent.npz"
    n = BOMB_BYTES // 8
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("__meta__.npy", _npy(np.array("{}")))
        with zf.open("Q.npy", "w", force_zip64=True) as out:
            np.lib.format.write_array_header_2_0(
                out, {"descr": "<f8", "fortran_order": False, "shape": (n,)}
            )
            out.write(bytes(1 << 20))
    with composer() as compose:
        cfg = compose(list(TINY))
    agent = build_task(cfg).make_agent(seed=0)
    tracemalloc.start()
    try:
        with pytest.raises(ConfigError, match=r"key 'Q': expected shape \(49, 4\)"):
            agent.load(path)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 64 << 20


def test_huge_sweep_is_refused_before_expansion(cobel, tmp_path):
    t0 = time.perf_counter()
    proc = cobel("run", "-m", "task=tmaze_extinction", "seed=range(0,10000000)", timeout=60)
    line = _one_line(proc)
    assert "10,000,000 jobs" in line and "seed" in line and "COBEL_MAX_JOBS=10000000" in line
    assert time.perf_counter() - t0 < 30
    _no_run_folder(tmp_path / "results")


def test_sweep_limit_counts_every_swept_key(monkeypatch):
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from cobelrun.errors import CobelError
    from cobelrun.sweep_plan import check_job_count

    parsed = OverridesParser.create().parse_overrides(
        ["seed=range(0,100)", "agent.gamma=0.9,0.95", "agent.epsilon=choice(0.1,0.2,0.3)"]
    )
    assert check_job_count(parsed) == 600
    monkeypatch.setenv("COBEL_MAX_JOBS", "599")
    with pytest.raises(
        CobelError, match=r"600 jobs .* sweep fewer values of seed .*COBEL_MAX_JOBS=600"
    ):
        check_job_count(parsed)
    monkeypatch.setenv("COBEL_MAX_JOBS", "lots")
    with pytest.raises(CobelError, match="COBEL_MAX_JOBS must be a positive whole number"):
        check_job_count(parsed)


def test_render_cache_of_huge_images_is_refused_before_rendering(cobel, tmp_path):
    pytest.importorskip("pybullet")
    t0 = time.perf_counter()
    proc = cobel("render-cache", "task=tmaze_extinction_3d", "env.observation.height=20000",
                 "env.observation.width=20000", env={"COBEL_CACHE": str(tmp_path / "cache")},
                 timeout=120)  # fmt: skip
    line = _one_line(proc)
    assert "env.observation.height/width would allocate about" in line
    assert "lower env.observation.height and width" in line
    assert time.perf_counter() - t0 < 30
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").rglob("*.npy"))


def test_offline_image_observation_estimates_its_views(monkeypatch):
    """A run with offline images: every pre-rendered view is counted before any is loaded."""
    from cobelrun.errors import ConfigError
    from cobelrun.hydra_app import composer
    from cobelrun.runner import build_task

    monkeypatch.setenv("COBEL_MEMORY_LIMIT", "2G")
    with composer() as compose:
        cfg = compose(["task=tmaze_extinction_3d", "env.observation.render=offline",
                       "env.observation.height=4000",
                       "env.observation.width=4000"])  # fmt: skip
    with pytest.raises(
        ConfigError, match=r"env.observation.height/width would allocate about .* pre-rendered"
    ):
        build_task(cfg)


def test_copy_helper_keeps_links(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "x").symlink_to("/")
    copy_folder(tmp_path / "a", tmp_path / "b")
    assert (tmp_path / "b" / "x").is_symlink()
    shutil.rmtree(tmp_path / "b")


def test_load_from_checks_every_run_in_one_pass(real_run, tmp_path):
    """A saved job's archive is checked for every run the new job needs: the intact one
    passes, a run it lacks is one line naming the run, and a {run} file pattern is checked
    file by file."""
    from cobelrun.agents.base import check_load_from
    from cobelrun.errors import ConfigError
    from cobelrun.hydra_app import composer
    from cobelrun.runner import build_task

    with composer() as compose:
        cfg = compose(list(TINY))
    agent = build_task(cfg).make_agent(seed=0)
    check_load_from(agent, str(real_run), 1)
    with pytest.raises(ConfigError, match=r"has no saved agent for run 1"):
        check_load_from(agent, str(real_run), 2)
    (tmp_path / "r0").mkdir()
    shutil.copy(real_run / "agents.npz", tmp_path / "r0" / "agents.npz")
    check_load_from(agent, str(tmp_path / "r{run}"), 1)
    with pytest.raises(ConfigError, match=r"r1 does not exist"):
        check_load_from(agent, str(tmp_path / "r{run}"), 2)
