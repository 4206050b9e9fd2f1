"""docs/extending.md's worked examples run as written: a new env module + YAML, a new monitor."""

from __future__ import annotations

import json
import os
import shutil
import subprocess

import numpy as np
import pandas as pd

from tests.conftest import ROOT, cobel_exe

EXAMPLES = ROOT / "docs" / "examples"


def test_linear_track_and_path_length_monitor(tmp_path):
    work = tmp_path / "work"
    shutil.copytree(EXAMPLES, work)
    out = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": str(work)}
    env.pop("HYDRA_FULL_ERROR", None)
    proc = subprocess.run(
        [*cobel_exe(), "run", "task=gridworld", "env=linear_track", "task.runs=2",
         "task.protocol.phases.0.trials=30", "+task.monitors.path._target_=path_length.PathLengthMonitor",
         f"hydra.run.dir={out}"],
        cwd=work, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    steps = pd.read_parquet(out / "steps.parquet")
    trials = pd.read_parquet(out / "trials.parquet")
    # positions in metres from the env's pose contract
    np.testing.assert_allclose(steps["x"], steps["state"] * 0.1)
    h = steps["heading"].to_numpy()
    assert (np.isclose(h, 0.0) | np.isclose(h, np.pi, atol=1e-6)).all()
    # the monitor's column: every step moves 0.1 m along the track
    np.testing.assert_allclose(trials["path_length"], trials["steps"] * 0.1)
    geometry = json.loads((out / "world.json").read_text())
    assert geometry["kind"] == "graph" and len(geometry["nodes"]) == 9
    assert set(geometry["regions"]) == {"left_end", "right_end"}
    # Dyna-Q learns to walk straight to the rewarded right end (4 steps from the middle)
    last = trials[trials["trial"] > 20]
    assert last["steps"].mean() < 6 and (last["end_state"] == 8).mean() > 0.8


def test_env_missing_a_contract_is_a_one_line_error(tmp_path):
    proc = subprocess.run(
        [*cobel_exe(), "run", "task=two_afc", "task.runs=1",
         "+task.monitors.response._target_=cobelrun.monitors.ResponseMonitor",
         "+task.monitors.response.states=[0]", f"hydra.run.dir={tmp_path / 'run'}"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 2
    assert "needs an environment with 'discrete_states'" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "run").exists()
