"""Kill real ``cobel run`` processes at seeded random points; nothing finished may be lost.

Each test starts the Fig. 6B task with many runs in a subprocess, sends a signal at a random
moment (seeded), and compares what survived with a complete reference run of the same config
and seed: the trials and steps that survived must be exactly a prefix of the reference (no
row changed, duplicated or skipped), every file must open, and the manifest must say how the
run ended. SIGINT, a second SIGINT during shutdown and SIGTERM lose nothing that was simulated
before the signal; SIGKILL loses at most the rows of the last ``flush_seconds``, and
``cobel status RUN`` repairs the folder (tables merged from their parts, manifest marked).
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import time
from pathlib import Path

import pandas as pd
import pytest

from tests.conftest import cobel_exe
from tests.test_mcap import read as read_mcap

RUNS = 1000
ARGS = ["task=tmaze_extinction", f"task.runs={RUNS}", "task.record.flush_seconds=0.25",
        "task.save_agents=false"]  # fmt: skip
KEY = ["run", "trial"]


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> dict[str, pd.DataFrame]:
    out = tmp_path_factory.mktemp("reference") / "run"
    proc = subprocess.run([*cobel_exe(), "run", *ARGS, f"hydra.run.dir={out}"],
                          capture_output=True, text=True, timeout=600)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return {t: pd.read_parquet(out / f"{t}.parquet") for t in ("trials", "steps")}


def start(out: Path) -> subprocess.Popen:
    env = {**os.environ, "COBEL_RESULTS": str(out.parent)}
    env.pop("HYDRA_FULL_ERROR", None)
    return subprocess.Popen([*cobel_exe(), "run", *ARGS, f"hydra.run.dir={out}"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip


def wait_started(out: Path, proc: subprocess.Popen) -> None:
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        if (out / ".parts" / "trials").is_dir():  # the first rows were handed to disk
            return
        time.sleep(0.02)
    raise AssertionError(f"the run did not start: {proc.communicate()[1]}")


def check_prefix(found: pd.DataFrame, ref: pd.DataFrame, what: str) -> int:
    """``found`` must equal the first len(found) rows of ``ref`` (in run, trial order)."""
    found = found.reset_index(drop=True)
    assert not found.duplicated(subset=[*KEY, "step"] if "step" in found else KEY).any(), what
    expect = ref.iloc[: len(found)].reset_index(drop=True)
    pd.testing.assert_frame_equal(found[expect.columns], expect, check_dtype=False, obj=what)
    return len(found)


def kill_at(seed: int, out: Path, signals: list[int]) -> tuple[subprocess.Popen, str]:
    rng = random.Random(seed)
    proc = start(out)
    wait_started(out, proc)
    time.sleep(rng.uniform(0.0, 2.0))
    for i, sig in enumerate(signals):
        if proc.poll() is not None:
            break
        proc.send_signal(sig)
        if i + 1 < len(signals):
            time.sleep(rng.uniform(0.0, 0.05))  # the second Ctrl-C lands during shutdown
    _, err = proc.communicate(timeout=120)
    return proc, err


CASES = {
    "sigint": [signal.SIGINT],
    "double_sigint": [signal.SIGINT, signal.SIGINT],
    "sigterm": [signal.SIGTERM],
}


@pytest.mark.parametrize("seed", [1, 2])
@pytest.mark.parametrize("case", list(CASES))
def test_signal_loses_no_finished_trial(tmp_path, reference, case, seed):
    out = tmp_path / "run"
    proc, err = kill_at(seed, out, CASES[case])
    if (out / ".done").exists():  # the run was complete before the signal (a fast machine)
        pytest.skip(f"the run finished before the signal (exit {proc.returncode})")
    assert proc.returncode == 130, err
    assert "Traceback" not in err and len(err.strip().splitlines()) <= 2, err
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["status"] == "interrupted"
    assert not (out / ".done").exists() and not (out / ".parts").exists()
    trials = pd.read_parquet(out / "trials.parquet")
    steps = pd.read_parquet(out / "steps.parquet")
    n = check_prefix(trials, reference["trials"], "trials")
    check_prefix(steps, reference["steps"], "steps")
    # nothing simulated is dropped: the steps of exactly the recorded trials are there
    assert n > 0 and len(steps) == reference["trials"]["steps"].iloc[:n].sum()
    assert any(m[0].endswith("/pose") for m in read_mcap(out / "run.mcap"))  # indexed reader
    print(f"{case} seed {seed}: {n} trial rows kept, all of them the reference's")


@pytest.mark.parametrize("seed", [1, 2])
def test_sigkill_loses_at_most_the_last_flush(tmp_path, reference, seed):
    out = tmp_path / "run"
    proc, _ = kill_at(seed, out, [signal.SIGKILL])
    if (out / ".done").exists():
        pytest.skip("the run finished before the signal")
    assert proc.returncode == -signal.SIGKILL
    assert json.loads((out / "manifest.json").read_text())["status"] == "running"
    status = subprocess.run([*cobel_exe(), "status", str(out)], capture_output=True, text=True,
                            timeout=120)  # fmt: skip
    assert status.returncode == 1 and "interrupted" in status.stdout, status.stderr
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["status"] == "interrupted" and manifest["killed"] is True
    assert not (out / ".parts").exists()
    trials = pd.read_parquet(out / "trials.parquet")
    steps = pd.read_parquet(out / "steps.parquet")
    n = check_prefix(trials, reference["trials"], "trials")
    check_prefix(steps, reference["steps"], "steps")
    assert any(m[0] == "/maze" for m in read_mcap(out / "run.mcap"))  # repaired: indexed reader
    print(f"SIGKILL seed {seed}: {n} trial rows and {len(steps)} step rows kept")
    # a second status does nothing more
    again = subprocess.run([*cobel_exe(), "status", str(out)], capture_output=True, text=True)
    assert "  repaired " not in again.stdout
