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
from tests.conftest import cobel_exe
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
    env = {**os.environ, "COBEL_RESULTS": str(tmp_path)}
    env.pop("HYDRA_FULL_ERROR", None)
    proc = subprocess.Popen([*cobel_exe(), "run", *ARGS, f"hydra.run.dir={out}", "--quiet"],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
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
