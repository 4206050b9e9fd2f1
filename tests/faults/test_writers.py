"""One writer per run folder (issue 31, item 3): results root and run folders resolved (a
symlink to ``/`` is refused), an ``fcntl`` lock while a folder is written (a second writer is
refused naming the holder's pid), and a folder that holds a run is never replaced.

The concurrency cases use real processes: a holder started with ``subprocess`` and the
second writer through the real CLI.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from cobelrun.errors import CobelError
from cobelrun.io.lock import LOCK_FILE, RunLock, holder, holds_run
from cobelrun.safety import check_folder, results_root
from tests.conftest import ROOT, cobel_exe

TINY = ["task=tmaze_extinction", "task.runs=1", "task.protocol.phases.0.trials=3",
        "task.protocol.phases.1.trials=3"]  # fmt: skip

HOLD = """
import sys, time
from cobelrun.io.lock import RunLock
with RunLock(sys.argv[1]):
    print("held", flush=True)
    time.sleep(float(sys.argv[2]))
"""


def one_line_error(proc) -> str:
    lines = [line for line in proc.stderr.strip().splitlines() if line]
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert len(lines) == 1 and lines[0].startswith("cobel: error:"), proc.stderr
    return lines[0]


def hold(folder: Path, seconds: float = 60) -> subprocess.Popen:
    """Another process that holds ``folder``'s lock until killed."""
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(folder), str(seconds)],
                            stdout=subprocess.PIPE, text=True, cwd=ROOT,
                            env={**os.environ, "PYTHONPATH": str(ROOT)})  # fmt: skip
    assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
    return proc


def snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in sorted(folder.rglob("*")) if p.is_file()}  # fmt: skip


# -- roots and folders resolved -----------------------------------------------------------------
def test_a_results_root_that_resolves_to_slash_is_refused(tmp_path):
    link = tmp_path / "link"
    link.symlink_to("/")
    with pytest.raises(CobelError, match=r"COBEL_RESULTS=.*link\) resolves to /, the file"):
        results_root({"COBEL_RESULTS": str(link)})
    with pytest.raises(CobelError, match="resolves to /"):
        results_root({"COBEL_RESULTS": "/"})
    with pytest.raises(CobelError, match="resolves to /"):
        check_folder(link / "x" / "..")


def test_cli_symlink_to_slash_as_results_root_writes_nothing(cobel, tmp_path):
    (tmp_path / "link").symlink_to("/")
    before = set(os.listdir("/"))
    proc = cobel("run", *TINY, env={"COBEL_RESULTS": "link"})
    assert "resolves to /, the file system's root" in one_line_error(proc)
    assert set(os.listdir("/")) == before and not Path("/tmaze_extinction").exists()


def test_cli_run_dir_through_a_symlink_to_slash_is_refused(cobel, tmp_path):
    (tmp_path / "link").symlink_to("/")
    proc = cobel("run", *TINY, f"hydra.run.dir={tmp_path / 'link'}")
    assert "resolves to /, the file system's root" in one_line_error(proc)


# -- the lock -------------------------------------------------------------------------------
def test_lock_is_exclusive_across_processes_and_names_the_holder(tmp_path):
    folder = tmp_path / "run"
    other = hold(folder)
    try:
        assert holder(folder) == other.pid
        with pytest.raises(CobelError, match=f"is being written by process {other.pid}"):
            with RunLock(folder):
                pass
    finally:
        other.kill()
        other.wait()
    with RunLock(folder):  # the kernel dropped the killed holder's lock
        assert holder(folder) == os.getpid()
    assert not (folder / LOCK_FILE).exists()  # released: the lock file is gone


def test_lock_is_reentrant_within_a_process(tmp_path):
    with RunLock(tmp_path / "r"), RunLock(tmp_path / "r"):
        assert holder(tmp_path / "r") == os.getpid()
    assert not (tmp_path / "r" / LOCK_FILE).exists()


def test_holds_run(tmp_path):
    assert holds_run(tmp_path) is None
    (tmp_path / ".hydra").mkdir()
    assert holds_run(tmp_path) == ".hydra" and holds_run(tmp_path, hydra=False) is None
    (tmp_path / "manifest.json").write_text("{}")
    assert holds_run(tmp_path, hydra=False) == "manifest.json"


# -- a second writer, through the CLI -----------------------------------------------------------
def test_two_writers_one_folder(cobel, tmp_path):
    """The issue's case: two `cobel run ... hydra.run.dir=SAME` a moment apart. The second is
    refused naming the first's pid; the first ends as if alone."""
    out = tmp_path / "same"
    env = {**os.environ, "COBEL_RESULTS": str(tmp_path / "results")}
    env.pop("HYDRA_FULL_ERROR", None)
    first = subprocess.Popen(
        [*cobel_exe(), "run", "task=tmaze_extinction", "task.runs=40", "seed=1",
         f"hydra.run.dir={out}", "--quiet"],
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while not (out / "manifest.json").exists():  # the first is writing
            assert first.poll() is None, first.communicate()
            assert time.monotonic() < deadline
            time.sleep(0.05)
        # freeze the first mid-run (SIGSTOP) so the second surely comes while it writes
        os.kill(first.pid, signal.SIGSTOP)
        try:
            second = cobel("run", "task=tmaze_extinction", "task.runs=1", "seed=2",
                           f"hydra.run.dir={out}", "--quiet")  # fmt: skip
        finally:
            os.kill(first.pid, signal.SIGCONT)
        line = one_line_error(second)
        assert f"{out} is being written by process {first.pid}" in line, line
    finally:
        _, stderr = first.communicate(timeout=300)
    assert first.returncode == 0, stderr
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["status"] == "completed" and manifest["seed"] == 1
    assert "seed: 1" in (out / "config.yaml").read_text()
    trials = pd.read_parquet(out / "trials.parquet")
    assert trials["run"].nunique() == 40
    pd.read_parquet(out / "steps.parquet")  # readable, not corrupt
    assert (out / ".done").read_text() == "completed\n"
    assert not (out / LOCK_FILE).exists()


def test_run_dir_that_holds_a_run_is_never_replaced(cobel, tmp_path):
    out = tmp_path / "done"
    assert cobel("run", *TINY, f"hydra.run.dir={out}", "--quiet").returncode == 0
    before = snapshot(out)
    rows = len(pd.read_parquet(out / "trials.parquet"))
    proc = cobel("run", *TINY, "task.protocol.phases.0.trials=1", "seed=5",
                 f"hydra.run.dir={out}")  # fmt: skip
    line = one_line_error(proc)
    assert f"hydra.run.dir {out} already holds a run (manifest.json)" in line, line
    assert snapshot(out) == before and len(pd.read_parquet(out / "trials.parquet")) == rows


def test_api_and_rerun_out_refuse_a_folder_being_written(tmp_path):
    from cobelrun.api import run

    out = tmp_path / "busy"
    other = hold(out)
    try:
        with pytest.raises(CobelError, match=f"being written by process {other.pid}"):
            run("tmaze_extinction", TINY[1:], out)
        assert os.listdir(out) == [LOCK_FILE]  # nothing of the holder's changed
    finally:
        other.kill()
        other.wait()


def test_a_sweep_job_whose_folder_is_held_fails_alone(cobel, tmp_path):
    """Each sweep job locks its folder: a job whose folder another process writes fails with
    the holder's pid; the other jobs run."""
    sweep = tmp_path / "sweep"
    other = hold(sweep / "0")
    try:
        proc = cobel("run", "-m", *TINY, "seed=1,2", f"hydra.sweep.dir={sweep}",
                     "hydra/launcher=basic", "--quiet")  # fmt: skip
    finally:
        other.kill()
        other.wait()
    assert proc.returncode == 1, proc.stderr
    job0 = json.loads((sweep / "0" / "job.json").read_text())
    assert job0["status"] == "failed" and f"process {other.pid}" in job0["error"]
    assert json.loads((sweep / "1" / "job.json").read_text())["status"] == "completed"
    assert not (sweep / "0" / "manifest.json").exists()


# -- getting-started's rerun through Hydra ------------------------------------------------------
def test_run_from_a_saved_runs_hydra_folder(cobel, tmp_path):
    first = tmp_path / "first"
    assert cobel("run", *TINY, f"hydra.run.dir={first}", "--quiet").returncode == 0
    proc = cobel("run", "-cd", str(first / ".hydra"), "-cn", "config", "seed=2", "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""  # cobel's logging: nothing on the terminal but warnings
    out = Path(proc.stdout.strip().splitlines()[-1])
    assert out.is_relative_to(tmp_path / "results" / "tmaze_extinction")
    assert json.loads((out / "manifest.json").read_text())["seed"] == 2
    assert (out / "cobel.log").is_file()
