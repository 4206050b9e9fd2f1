"""Preemption and time limits (issue 35): a deep run sent SIGTERM in the middle of a phase
writes a checkpoint at its next trial boundary and exits 75; ``cobel resume`` then finishes it
with the tables of the same run without the stop. Real processes: signals and exit codes are
what is tested."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import pandas as pd
import pytest

from cobelrun import api, runner
from cobelrun.checkpoint import REQUEUE_EXIT, read_header
from tests.conftest import cobel_exe, start_cobel_run
from tests.inprocess import cli  # noqa: F401 (fixture)

#: a sequential DQN run long enough (~2 x 300 learning steps) to be stopped mid-phase
ARGS = ["task=two_afc", "agent=dqn", "task.runs=2", "task.batch_runs=false",
        "task.protocol.phases.0.trials=300", "agent.net_arch=[16]", "agent.learning_starts=10",
        "task.record.flush_seconds=0.05", "task.checkpoint.every_minutes=30"]  # fmt: skip


def tables(folder: Path) -> dict[str, pd.DataFrame]:
    return {p.stem: pd.read_parquet(p) for p in sorted(folder.glob("*.parquet"))}


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGUSR1])
def test_signal_mid_phase_checkpoints_exits_75_and_resumes(tmp_path: Path, cli, sig) -> None:  # noqa: F811
    out = tmp_path / "run"
    proc = start_cobel_run(ARGS, out, tmp_path)
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        if (out / ".parts" / "trials").is_dir():  # the first trials were recorded
            break
        time.sleep(0.02)
    assert proc.poll() is None, proc.communicate()[1]
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == REQUEUE_EXIT, err
    assert "checkpoint written" in err and "cobel resume" in err
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["status"] == "interrupted" and manifest["checkpoints"]["written"] >= 1
    position = read_header(out / "checkpoint.npz")["position"]
    assert position["k"] > 0 or position["run"] == 1  # inside the run, not at its start
    result = cli("resume", str(out), "--quiet")
    assert result.returncode == 0, result.stderr
    assert not (out / "checkpoint.npz").exists() and (out / ".done").is_file()
    ref = runner.run(api.compose(None, ARGS), tmp_path / "ref")
    got, want = tables(out), tables(ref)
    assert got.keys() == want.keys()
    for name in want:
        pd.testing.assert_frame_equal(got[name], want[name], obj=name)


def _preempt_running_job(results: Path, proc: subprocess.Popen) -> int:
    """Wait for the sweep's job 0 to record trials, then send it submitit's preemption signal
    (SIGUSR2), as SLURM does ahead of a time limit; return its pid."""
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        for job in results.glob("two_afc/sweeps/*/0"):
            status = (
                json.loads((job / "job.json").read_text()) if (job / "job.json").is_file() else {}
            )
            if status.get("status") == "running" and (job / ".parts" / "trials").is_dir():
                os.kill(int(status["pid"]), signal.SIGUSR2)
                return int(status["pid"])
        time.sleep(0.05)
    raise AssertionError(f"job 0 did not start: {proc.communicate()[1][-2000:]}")


def _check_requeued_sweep(tmp_path: Path, proc: subprocess.Popen) -> Path:
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err[-3000:]
    (sweep,) = (tmp_path / "results" / "two_afc" / "sweeps").iterdir()
    index = pd.read_csv(sweep / "jobs.csv")
    assert list(index["status"]) == ["done"], index
    job = sweep / "0"
    assert not (job / "checkpoint.npz").exists() and (job / ".done").is_file()
    manifest = json.loads((job / "manifest.json").read_text())
    assert manifest["resumed_from"]["k"] > 0 or manifest["resumed_from"]["run"] == 1
    ref = runner.run(api.compose(None, [*ARGS, "seed=4"]), tmp_path / "ref")
    got, want = tables(job), tables(ref)
    assert got.keys() == want.keys()
    for name in want:
        pd.testing.assert_frame_equal(got[name], want[name], obj=name)
    return sweep


def _sweep_env(tmp_path: Path, extra: dict[str, str] | None = None) -> dict[str, str]:
    env = {**os.environ, "COBEL_RESULTS": str(tmp_path / "results"), **(extra or {})}
    env.pop("HYDRA_FULL_ERROR", None)
    return env


@pytest.mark.slow
def test_submitit_local_requeues_a_preempted_job_which_resumes(tmp_path: Path) -> None:
    """hydra/launcher=submitit_local: SIGUSR2 to the running job -> checkpoint at the next
    trial boundary -> submitit's own handler requeues it (its launcher is Checkpointable) ->
    the restarted job resumes the checkpoint -> the uninterrupted tables."""
    proc = subprocess.Popen(
        [*cobel_exe(), "run", "-m", "hydra/launcher=submitit_local",
         "hydra.launcher.timeout_min=10", *ARGS, "seed=4"],
        env=_sweep_env(tmp_path), cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    _preempt_running_job(tmp_path / "results", proc)
    sweep = _check_requeued_sweep(tmp_path, proc)
    logs = "".join(p.read_text() for p in (sweep / ".submitit").rglob("*_log.*"))
    assert "Caught signal SIGUSR2" in logs and "Requeued job" in logs


@pytest.mark.slow
def test_slurm_requeues_a_preempted_job_which_resumes(tmp_path: Path) -> None:
    """hydra/launcher=slurm against the stand-in sbatch/srun/sacct/scontrol (tests/fake_slurm):
    SIGUSR2 to the running array task -> checkpoint -> submitit calls `scontrol requeue` ->
    the task runs again and resumes -> done, with the uninterrupted tables."""
    fake = Path(__file__).parent / "fake_slurm"
    state = tmp_path / "slurm_state"
    env = _sweep_env(tmp_path, {"PATH": f"{fake}{os.pathsep}{os.environ['PATH']}",
                                "FAKE_SLURM_DIR": str(state)})  # fmt: skip
    proc = subprocess.Popen(
        [*cobel_exe(), "run", "-m", "hydra/launcher=slurm", "hydra.launcher.partition=testpart",
         "hydra.launcher.timeout_min=10", *ARGS, "seed=4"],
        env=env, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    _preempt_running_job(tmp_path / "results", proc)
    _check_requeued_sweep(tmp_path, proc)
    (requeues,) = state.glob("requeues_*")  # submitit called `scontrol requeue` once
    assert requeues.read_text() == "1\n"


@pytest.mark.slow
def test_sigkill_after_a_checkpoint_resumes_from_the_parts(tmp_path: Path, cli) -> None:  # noqa: F811
    """SIGKILL (no chance to write anything): the tables are left in parts, past the last
    checkpoint; ``cobel resume`` takes the parts up to the checkpoint and finishes the run."""
    out = tmp_path / "run"
    args = [*ARGS, "task.checkpoint.every_trials=40"]
    proc = start_cobel_run(args, out, tmp_path)
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        if (out / "checkpoint.npz").is_file():
            break
        time.sleep(0.02)
    time.sleep(0.3)  # more trials recorded after it
    assert proc.poll() is None, proc.communicate()[1]
    proc.kill()
    proc.communicate(timeout=60)
    assert (out / ".parts" / "trials").is_dir() and not (out / "trials.parquet").exists()
    result = cli("resume", str(out), "--quiet")
    assert result.returncode == 0, result.stderr
    ref = runner.run(api.compose(None, args), tmp_path / "ref")
    got, want = tables(out), tables(ref)
    assert got.keys() == want.keys()
    for name in want:
        pd.testing.assert_frame_equal(got[name], want[name], obj=name)
