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
        [*cobel_exe(), "run", "--allow-target", "linear_track.*", "--allow-target",
         "path_length.PathLengthMonitor", "task=gridworld", "env=linear_track", "task.runs=2",
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


def test_linear_track_bad_input_is_a_config_error(tmp_path):
    """The example env raises cobel's ConfigError, and a bad phase fails before any output."""
    import sys

    import pytest

    from cobelrun.errors import ConfigError

    sys.path.insert(0, str(EXAMPLES))
    try:
        from linear_track import LinearTrackEnv
    finally:
        sys.path.remove(str(EXAMPLES))
    env = LinearTrackEnv()
    with pytest.raises(ConfigError, match="terminals are its two ends"):
        env.apply_changes(terminals={"left_end": False})
    with pytest.raises(ConfigError, match="unknown place 'middle'; allowed: left_end"):
        env.apply_changes(rewards={"middle": 1.0})
    with pytest.raises(ConfigError, match="integer >= 3"):
        LinearTrackEnv(length=2)

    work = tmp_path / "work"
    shutil.copytree(EXAMPLES, work)
    env_vars = {**os.environ, "PYTHONPATH": str(work), "COBEL_ALLOW_TARGETS": "linear_track.*"}
    env_vars.pop("HYDRA_FULL_ERROR", None)
    for bad, message in [
        ("+task.protocol.phases.0.terminals={left_end:false}", "terminals are its two ends"),
        ("+task.protocol.phases.0.rewards={middle:1.0}", "unknown place 'middle'"),
    ]:
        out = tmp_path / "run"
        proc = subprocess.run(
            [*cobel_exe(), "run", "task=gridworld", "env=linear_track", "task.runs=1", bad,
             f"hydra.run.dir={out}"],
            cwd=work, env=env_vars, capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert proc.returncode == 2, proc.stderr
        # the example's conf/env/linear_track.yaml replaces the built-in env of that name,
        # which cobel announces in one line; then the error, in one line
        note, error = proc.stderr.strip().splitlines()
        assert note.startswith("cobel: note: ") and "replaces the built-in env=linear_track" in note
        assert error.startswith("cobel: error: ") and message in error
        assert not out.exists()


def test_bad_phase_of_a_builtin_env_fails_before_output(tmp_path):
    """A phase naming a state the maze lacks is refused while validating: no run folder."""
    out = tmp_path / "run"
    proc = subprocess.run(
        [*cobel_exe(), "run", "task=gridworld", "task.runs=1",
         "+task.protocol.phases.0.terminals={100:true}", f"hydra.run.dir={out}"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and "100" in proc.stderr, proc.stderr
    assert not out.exists()
