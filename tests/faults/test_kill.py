"""Kill real ``cobel run`` processes at seeded random points; nothing finished may be lost.

Each kill point starts the Fig. 6B task with many runs in a subprocess, sends a signal at a random
moment (seeded), and compares what survived with a complete reference run of the same config
and seed: the trials and steps that survived must be exactly a prefix of the reference (no
row changed, duplicated or skipped), every file must open, and the manifest must say how the
run ended. SIGINT, a second SIGINT during shutdown and SIGTERM lose nothing that was simulated
before the signal; SIGKILL loses at most the rows of the last ``flush_seconds``, and
``cobel status RUN`` repairs the folder (tables merged from their parts, manifest marked).

Kill points: each signal (SIGINT, a second SIGINT during shutdown, SIGTERM, SIGKILL) at
``SEEDS`` seeded moments; the first two seeds of each are in the default run, the rest are
``-m slow``. No process started by the run may outlive it.
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
from tests.faults import killpoints
from tests.test_mcap import read as read_mcap

RUNS = 2000  # ~5 s of loop on an idle 2-core VM: a signal 0-2 s after the first parts lands
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


def start(out: Path) -> tuple[subprocess.Popen, str]:
    env = {**os.environ, "COBEL_RESULTS": str(out.parent)}
    env.pop("HYDRA_FULL_ERROR", None)
    env, token = killpoints.tagged_env(env)
    proc = subprocess.Popen([*cobel_exe(), "run", *ARGS, f"hydra.run.dir={out}"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    return proc, token


def wait_started(out: Path, proc: subprocess.Popen) -> None:
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        if (out / ".parts" / "trials").is_dir():  # the first rows were handed to disk
            return
        time.sleep(0.02)
    if (out / ".done").exists():
        return  # it finished before we saw its parts (the caller skips such a point)
    raise AssertionError(f"the run did not start: {proc.communicate()[1]}")


def check_prefix(found: pd.DataFrame, ref: pd.DataFrame, what: str) -> int:
    """``found`` must equal the first len(found) rows of ``ref`` (in run, trial order)."""
    found = found.reset_index(drop=True)
    assert not found.duplicated(subset=[*KEY, "step"] if "step" in found else KEY).any(), what
    expect = ref.iloc[: len(found)].reset_index(drop=True)
    pd.testing.assert_frame_equal(found[expect.columns], expect, check_dtype=False, obj=what)
    return len(found)


def kill_at(seed: int, out: Path, signals: list[int]) -> tuple[subprocess.Popen, str, str]:
    rng = random.Random(seed)
    proc, token = start(out)
    wait_started(out, proc)
    time.sleep(rng.uniform(0.0, 2.0))
    for i, sig in enumerate(signals):
        if proc.poll() is not None:
            break
        proc.send_signal(sig)
        if i + 1 < len(signals):
            time.sleep(rng.uniform(0.0, 0.05))  # the second Ctrl-C lands during shutdown
    _, err = proc.communicate(timeout=120)
    return proc, err, token


CASES = {
    "sigint": [signal.SIGINT],
    "double_sigint": [signal.SIGINT, signal.SIGINT],
    "sigterm": [signal.SIGTERM],
    "sigkill": [signal.SIGKILL],
}
#: seeded kill points per signal (4 signals x 21 = 84 single-run kill points)
SEEDS = int(os.environ.get("RUN_KILL_SEEDS", "21"))
DEFAULT_SEEDS = 2  # per signal, in the default run
slow = pytest.mark.slow
POINTS = [
    pytest.param(case, seed, id=f"{case}-{seed}", marks=[slow] if seed >= DEFAULT_SEEDS else [])
    for case in CASES
    for seed in range(SEEDS)
]


@pytest.mark.parametrize(("case", "seed"), POINTS)
def test_kill_point_loses_no_finished_trial(tmp_path, reference, case, seed):
    out = tmp_path / "run"
    proc, err, token = kill_at(seed, out, CASES[case])
    if (out / ".done").exists():  # the run was complete before the signal (a fast machine)
        killpoints.log(kind="run", case=case, seed=seed, outcome="finished_before_signal")
        pytest.skip(f"the run finished before the signal (exit {proc.returncode})")
    lost = -1
    try:
        killpoints.assert_tree_gone(token)
        if case == "sigkill":
            kept, lost = check_sigkill(out, proc, reference)
        else:
            kept, lost = check_signal(out, proc, err, reference)
        assert lost == 0, f"{lost} rows of finished trials lost"
    except BaseException:
        killpoints.log(kind="run", case=case, seed=seed, outcome="failed", rows_lost=max(lost, 0))
        raise
    killpoints.log(kind="run", case=case, seed=seed, outcome="survived", rows_kept=kept,
                   rows_lost=lost)  # fmt: skip
    print(f"{case} seed {seed}: {kept} trial rows kept, {lost} lost")


def lost_rows(out: Path, reference: dict[str, pd.DataFrame]) -> tuple[int, int]:
    """(trial rows kept, rows of finished trials missing or changed) after checking that every
    table is exactly a prefix of the uninterrupted run."""
    trials = pd.read_parquet(out / "trials.parquet")
    steps = pd.read_parquet(out / "steps.parquet")
    lost = killpoints.rows_lost(trials, reference["trials"], KEY)
    lost += killpoints.rows_lost(steps, reference["steps"], [*KEY, "step"])
    n = check_prefix(trials, reference["trials"], "trials")
    check_prefix(steps, reference["steps"], "steps")
    return n, lost


def check_signal(out, proc, err, reference) -> tuple[int, int]:
    """SIGINT, a second SIGINT, SIGTERM: nothing simulated is lost."""
    assert proc.returncode == 130, err
    assert "Traceback" not in err and len(err.strip().splitlines()) <= 2, err
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["status"] == "interrupted"
    assert not (out / ".done").exists() and not (out / ".parts").exists()
    n, lost = lost_rows(out, reference)
    steps = pd.read_parquet(out / "steps.parquet")
    # nothing simulated is dropped: the steps of exactly the recorded trials are there
    assert n > 0 and len(steps) == reference["trials"]["steps"].iloc[:n].sum()
    assert any(m[0].endswith("/pose") for m in read_mcap(out / "run.mcap"))  # indexed reader
    return n, lost


def check_sigkill(out, proc, reference) -> tuple[int, int]:
    """SIGKILL: at most the last flush is lost; ``cobel status`` repairs the folder."""
    assert proc.returncode == -signal.SIGKILL
    assert json.loads((out / "manifest.json").read_text())["status"] == "running"
    status = subprocess.run([*cobel_exe(), "status", str(out)], capture_output=True, text=True,
                            timeout=120)  # fmt: skip
    assert status.returncode == 1 and "interrupted" in status.stdout, status.stderr
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["status"] == "interrupted" and manifest["killed"] is True
    assert not (out / ".parts").exists()
    n, lost = lost_rows(out, reference)
    assert any(m[0] == "/maze" for m in read_mcap(out / "run.mcap"))  # repaired: indexed reader
    # a second status does nothing more
    again = subprocess.run([*cobel_exe(), "status", str(out)], capture_output=True, text=True)
    assert "  repaired " not in again.stdout
    return n, lost
