"""Stop real ``cobel run -m`` sweeps at seeded random points: no orphans, true statuses, and a
resume that completes the rest to the same tables as an uninterrupted sweep.

SIGINT (once, or twice with the second during shutdown) goes to the whole process group (as a
terminal's Ctrl-C does), SIGTERM and SIGKILL to the launcher only (as ``kill PID`` or a
scheduler does). No process the sweep started may outlive it: every process of its tree is
found by a token in its environment, so workers started after the signal or re-parented when
the launcher died are found too. The default suite runs the lock test and the status and
worker checks; ``-m slow`` runs the seeded kill points (``SWEEP_KILL_SEEDS`` per signal,
default 4: 16 kill points).
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import signal
import subprocess
import time
from pathlib import Path

import pandas as pd
import psutil
import pytest

from tests.conftest import cobel_exe
from tests.faults import killpoints

ARGS = ["-m", "task=tmaze_extinction", "task.runs=120", "task.record.flush_seconds=0.2",
        "task.save_agents=false", "seed=1,2,3", "hydra.launcher.n_jobs=2"]  # fmt: skip
KEY = ["job", "run", "trial"]


def env_for(root: Path) -> dict[str, str]:
    env = {**os.environ, "COBEL_RESULTS": str(root)}
    env.pop("HYDRA_FULL_ERROR", None)
    return env


def sweep_dir(root: Path) -> Path:
    found = sorted((root / "tmaze_extinction" / "sweeps").glob("*"))
    assert len(found) == 1, found
    return found[0]


def collected(root: Path) -> dict[str, pd.DataFrame]:
    d = sweep_dir(root)
    proc = subprocess.run([*cobel_exe(), "collect", str(d)], env=env_for(root),
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    out = {}
    for t in ("trials", "steps"):
        frame = pd.read_parquet(d / "collected" / f"{t}.parquet")
        keys = [*KEY, "step"] if t == "steps" else KEY
        out[t] = frame.sort_values(keys).reset_index(drop=True)
    return out


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> dict[str, pd.DataFrame]:
    root = tmp_path_factory.mktemp("reference")
    proc = subprocess.run([*cobel_exe(), "run", *ARGS], env=env_for(root), capture_output=True,
                          text=True, timeout=600)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return collected(root)


def stop_sweep(root: Path, seed: int, signals: list[int]) -> tuple[subprocess.Popen, str, str]:
    """Start the sweep, wait until a job has handed rows to disk, sleep a seeded moment, send
    ``signals``; returns the process, its stderr and the token that tags its process tree."""
    rng = random.Random(seed)
    env, token = killpoints.tagged_env(env_for(root))
    proc = subprocess.Popen([*cobel_exe(), "run", *ARGS], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)  # fmt: skip
    deadline = time.time() + 180
    while time.time() < deadline and proc.poll() is None:
        if list(root.glob("tmaze_extinction/sweeps/*/*/.parts/trials")):
            break
        time.sleep(0.05)
    time.sleep(rng.uniform(0.0, 3.0))
    for i, sig in enumerate(signals):
        if proc.poll() is not None:
            break
        if sig == signal.SIGINT:
            os.killpg(proc.pid, sig)  # a terminal's Ctrl-C reaches every process of the group
        else:
            proc.send_signal(sig)
        if i + 1 < len(signals):
            time.sleep(rng.uniform(0.0, 0.5))  # the second Ctrl-C lands during shutdown
    _, err = proc.communicate(timeout=300)
    return proc, err, token


def check_prefix(found: pd.DataFrame, ref: pd.DataFrame, what: str) -> None:
    """``found`` (one job's table) must be the first rows of ``ref`` (the same job's rows of the
    uninterrupted sweep, in run, trial, step order)."""
    keys = ["run", "trial", "step"] if "step" in found else ["run", "trial"]
    assert not found.duplicated(subset=keys).any(), what
    found = found.sort_values(keys).reset_index(drop=True)
    expect = ref.iloc[: len(found)].reset_index(drop=True)
    pd.testing.assert_frame_equal(found[expect.columns], expect, check_dtype=False, obj=what)


def check_statuses(root: Path, reference: dict[str, pd.DataFrame]) -> dict[str, int]:
    """Every job's status is true: completed jobs hold their whole tables, interrupted ones a
    prefix of the reference (no row changed or duplicated), jobs that never ran hold nothing."""
    d = sweep_dir(root)
    status = subprocess.run([*cobel_exe(), "status", str(d)], env=env_for(root),
                            capture_output=True, text=True, timeout=300)  # fmt: skip
    assert "Traceback" not in status.stderr, status.stderr
    counts: dict[str, int] = {}
    for job in range(3):
        jd = d / str(job)
        state = json.loads((jd / "job.json").read_text())["status"]
        counts[state] = counts.get(state, 0) + 1
        ref = {t: f[f["job"] == job].drop(columns=["job", "seed"]).reset_index(drop=True)
               for t, f in reference.items()}  # fmt: skip
        manifest = (
            json.loads((jd / "manifest.json").read_text())
            if (jd / "manifest.json").exists()
            else None
        )
        if state == "completed":
            assert (jd / ".done").exists() and manifest["status"] == "completed"
            trials = pd.read_parquet(jd / "trials.parquet")
            assert len(trials) == len(ref["trials"])
        elif state == "interrupted":
            assert not (jd / ".done").exists()
            if manifest is not None:  # it had started: its files are closed and readable
                assert manifest["status"] == "interrupted", manifest["status"]
                assert not (jd / ".parts").exists()
                for t in ("trials", "steps"):
                    if (jd / f"{t}.parquet").exists():
                        frame = pd.read_parquet(jd / f"{t}.parquet")
                        check_prefix(frame, ref[t], f"job {job} {t}")
            else:  # it never started: `cobel status` says why, whatever stopped the launcher
                error = json.loads((jd / "job.json").read_text()).get("error", "")
                assert "started" in error, (job, error)
        else:  # nothing stays `queued` once the launcher is gone (SIGKILL included)
            raise AssertionError(f"job {job} is {state!r} after the sweep's launcher ended")
    return counts


def resume_matches(root: Path, reference: dict[str, pd.DataFrame]) -> int:
    """Run the same command again: the collected tables must equal the uninterrupted sweep's;
    returns the rows of the reference missing or changed (0)."""
    proc = subprocess.run([*cobel_exe(), "run", *ARGS], env=env_for(root), capture_output=True,
                          text=True, timeout=600)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    got = collected(root)
    lost = 0
    for t, ref in reference.items():
        keys = [*KEY, "step"] if t == "steps" else KEY
        lost += len(ref) - len(ref.merge(got[t][ref.columns].drop_duplicates(), how="inner"))
        pd.testing.assert_frame_equal(got[t][ref.columns], ref, check_dtype=False, obj=t)
        assert not got[t].duplicated(subset=keys).any(), t
    return lost


CASES = {
    "sigint": [signal.SIGINT],
    "double_sigint": [signal.SIGINT, signal.SIGINT],
    "sigterm": [signal.SIGTERM],
    "sigkill": [signal.SIGKILL],
}


def run_case(tmp_path: Path, reference, case: str, seed: int) -> None:
    root = tmp_path / "results"
    proc, err, token = stop_sweep(root, seed, CASES[case])
    if proc.returncode == 0:  # a fast machine, a late kill point
        killpoints.log(kind="sweep", case=case, seed=seed, outcome="finished_before_signal")
        pytest.skip("the sweep finished before the signal")
    lost = 0
    try:
        if case == "sigkill":
            assert proc.returncode == -signal.SIGKILL
        else:
            assert proc.returncode == 130, err
            assert "Traceback" not in err, err
            assert "cobel: interrupted;" in err and "resume with: cobel run -m" in err, err
        killpoints.assert_tree_gone(token)
        counts = check_statuses(root, reference)
        lost = resume_matches(root, reference)
        assert lost == 0, f"{lost} rows lost after the resume"
    except BaseException:
        killpoints.log(kind="sweep", case=case, seed=seed, outcome="failed", rows_lost=lost)
        raise
    killpoints.log(kind="sweep", case=case, seed=seed, outcome="survived", rows_lost=lost,
                   statuses=counts)  # fmt: skip


#: seeded kill points per signal (4 signals x 4 = 16 sweep kill points)
SEEDS = int(os.environ.get("SWEEP_KILL_SEEDS", "4"))


@pytest.mark.slow  # about a minute each on a loaded 2-core machine
@pytest.mark.parametrize("seed", range(SEEDS))
@pytest.mark.parametrize("case", list(CASES))
def test_stopped_sweep(tmp_path, reference, case, seed):
    run_case(tmp_path, reference, case, seed=1000 + seed)


def test_second_sweep_into_the_same_folder_is_refused(tmp_path):
    root = tmp_path / "results"
    first = subprocess.Popen([*cobel_exe(), "run", *ARGS[:-2], "seed=1", "task.runs=2000"],
                             env=env_for(root), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True, start_new_session=True)  # fmt: skip
    try:
        deadline = time.time() + 180
        while time.time() < deadline and not list(
            root.glob("tmaze_extinction/sweeps/*/0/job.json")
        ):
            time.sleep(0.05)
        second = subprocess.run([*cobel_exe(), "run", *ARGS[:-2], "seed=1", "task.runs=2000"],
                                env=env_for(root), capture_output=True, text=True, timeout=300)  # fmt: skip
        assert second.returncode == 2, second.stderr
        lines = second.stderr.strip().splitlines()
        assert len(lines) == 1 and "is in use by another `cobel run -m` (pid " in lines[0]
        assert f"pid {first.pid}" in lines[0], lines[0]
    finally:
        first.send_signal(signal.SIGTERM)
        first.communicate(timeout=300)
    assert first.returncode == 130
    job = json.loads((sweep_dir(root) / "0" / "job.json").read_text())
    assert job["status"] in ("interrupted", "completed")


def _dead_pid() -> int:
    proc = subprocess.Popen(["true"])
    proc.wait()
    return proc.pid


@pytest.mark.parametrize("launcher", ["dead", "alive"])
def test_queued_job_of_a_dead_launcher_is_reported_not_started(tmp_path, launcher):
    """A job still ``queued`` when its launcher was SIGKILLed never starts: ``cobel status``
    says ``interrupted`` (not started) once the launcher is gone, ``queued`` while it lives."""
    from cobelrun.io import sweep_folder as sweep

    d = tmp_path / "sweep"
    sweep.write_sweep(d, command="cobel run -m seed=1,2", swept=["seed"],
                      jobs=[{"job": 0, "overrides": ["seed=1"], "params": {"seed": 1}}])  # fmt: skip
    sweep.write_job_status(d / "0", "queued", job=0, overrides=["seed=1"])
    holder = subprocess.Popen(["sleep", "60"])
    try:
        pid = _dead_pid() if launcher == "dead" else holder.pid
        job = json.loads((d / "0" / "job.json").read_text())
        (d / "0" / "job.json").write_text(json.dumps({**job, "launcher_pid": pid}))
        status = subprocess.run([*cobel_exe(), "status", str(d)], capture_output=True, text=True,
                                timeout=120)  # fmt: skip
        [row] = sweep.job_rows(d, write=False)
        state = json.loads((d / "0" / "job.json").read_text())
    finally:
        holder.kill()
        holder.wait()
    assert status.returncode == 1 and "Traceback" not in status.stderr, status.stderr
    if launcher == "dead":
        assert row["status"] == "interrupted" and state["status"] == "interrupted"
        assert row["error"] == (
            f"not started: the sweep's launcher (pid {pid}) ended before this job started"
        )
        assert "not started" in status.stdout and "interrupted" in status.stdout
    else:
        assert row["status"] == "queued" and state["status"] == "queued"


@pytest.mark.parametrize("finished", [False, True])
def test_job_running_in_a_dead_process_is_interrupted(tmp_path, finished):
    """A job killed before it wrote a manifest (its job.json says ``running``) is not reported
    ``running`` forever; one killed after its last file but before its job.json said so is
    ``completed`` (a SIGKILLed sweep of seed 1000 left one marked interrupted)."""
    from cobelrun.io import sweep_folder as sweep

    d = tmp_path / "sweep"
    sweep.write_sweep(d, command="cobel run -m seed=1,2", swept=["seed"],
                      jobs=[{"job": 0, "overrides": ["seed=1"], "params": {"seed": 1}}])  # fmt: skip
    sweep.write_job_status(d / "0", "queued", job=0, overrides=["seed=1"])
    sweep.write_job_status(d / "0", "running")
    job = json.loads((d / "0" / "job.json").read_text())
    (d / "0" / "job.json").write_text(json.dumps({**job, "pid": _dead_pid()}))
    if finished:
        (d / "0" / "manifest.json").write_text(json.dumps({"status": "completed"}))
        (d / "0" / ".done").write_text("")
    [row] = sweep.job_rows(d, write=False)
    assert row["status"] == ("done" if finished else "interrupted")
    state = json.loads((d / "0" / "job.json").read_text())["status"]
    assert state == ("completed" if finished else "interrupted")


WORKER = """
import os, sys, time
time.sleep(float(sys.argv[1]))  # a worker still importing when its launcher dies
from cobelrun.sweep import worker_init
worker_init()
if float(sys.argv[2]):  # a job finishing its files: signals are ignored meanwhile
    from cobelrun.signals import SignalGuard
    guard = SignalGuard()
    with guard.installed(), guard.closing():
        time.sleep(float(sys.argv[2]))
time.sleep(120)  # then idle, waiting for a next job that never comes
"""
LAUNCHER = """
import os, subprocess, sys, time
env = {**os.environ, "COBEL_SWEEP_LAUNCHER": str(os.getpid())}
child = subprocess.Popen([sys.executable, "-c", sys.argv[1], sys.argv[2], sys.argv[3]], env=env)
print(child.pid, flush=True)
time.sleep(float(sys.argv[4]))  # then the launcher ends (as if SIGKILLed) without a word
os._exit(0)
"""


def _gone(pid: int, within: float) -> bool:
    deadline = time.time() + within
    while time.time() < deadline:
        try:
            if psutil.Process(pid).status() == psutil.STATUS_ZOMBIE:
                return True
        except psutil.NoSuchProcess:
            return True
        time.sleep(0.1)
    return False


@pytest.mark.parametrize(("starting", "closing", "launcher_lives"),
                         [(1.5, 0, 0.0), (0.0, 0, 3.0), (0.0, 6, 3.0)],
                         ids=["launcher_dies_while_worker_starts", "launcher_dies_later",
                              "launcher_dies_while_a_job_closes_its_files"])  # fmt: skip
def test_worker_does_not_outlive_its_launcher(starting, closing, launcher_lives):
    """A sweep worker exits once its launcher is gone: also when the launcher died while the
    worker was still starting (before its initializer could ask the kernel for a signal), and
    when the signal landed while a job finished its files (signals are ignored then, and the
    worker went back to waiting for a job; the SIGKILLed sweep of seed 1000 left one so)."""
    import sys

    proc = subprocess.run([sys.executable, "-c", LAUNCHER, WORKER, str(starting), str(closing),
                           str(launcher_lives)], capture_output=True, text=True, timeout=60)  # fmt: skip
    worker = int(proc.stdout.split()[0])
    try:
        assert _gone(worker, within=30), "the worker outlived its launcher"
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(worker, signal.SIGKILL)
