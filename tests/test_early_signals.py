"""A scheduler's signal that arrives before the run has installed its handlers (issue 35):
while Python imports and the config is composed, ``cobel run``/``cobel resume`` hold SIGTERM,
SIGUSR1 and SIGUSR2 (:func:`cobelrun.signals.hold_early`); the run then stops at its first
trial boundary with a checkpoint and exits 75, as for a signal in the middle of a run, instead
of dying with 143 and no requeue."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cobelrun import signals
from cobelrun.checkpoint import REQUEUE_EXIT, read_header
from tests.conftest import cobel_exe, start_cobel_run

#: a small sequential DQN run with checkpoints on
ARGS = ["task=two_afc", "agent=dqn", "task.runs=1", "task.batch_runs=false",
        "task.protocol.phases.0.trials=30", "agent.net_arch=[8]", "agent.learning_starts=5",
        "task.checkpoint.every_minutes=30"]  # fmt: skip


def _catches(pid: int, sig: int) -> bool:
    """Whether process ``pid`` has a handler for ``sig`` (``SigCgt`` in /proc)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    mask = next(int(line.split()[1], 16) for line in status.splitlines()
                if line.startswith("SigCgt:"))  # fmt: skip
    return bool(mask >> (sig - 1) & 1)


@pytest.fixture
def isolated_signals():
    """Restore the handlers and the held signals after a test that holds them."""
    saved = {s: signal.getsignal(s) for s in signals.EARLY_SIGNALS}
    yield
    signals._EARLY.clear()
    signals._ORIGINAL.clear()
    for s, h in saved.items():
        signal.signal(s, h)


def test_a_held_signal_asks_a_checkpointing_run_to_stop(isolated_signals) -> None:
    signals.hold_early()
    os.kill(os.getpid(), signal.SIGUSR1)
    assert signals.early_signal() == signal.SIGUSR1
    guard = signals.SignalGuard(defer=True)
    with guard.installed():
        assert guard.stop_requested == signal.SIGUSR1
    assert signals.early_signal() is None  # taken once


def test_a_held_signal_stops_a_run_without_checkpoints_where_it_can(isolated_signals) -> None:
    """No checkpoints: the held SIGTERM is raised at the end of the first critical section
    (where the recorder's rows are consistent), not while the guard is being installed."""
    signals.hold_early()
    os.kill(os.getpid(), signal.SIGTERM)
    guard = signals.SignalGuard()
    with guard.installed():
        with pytest.raises(signals.Interrupted) as info:
            with guard.critical():
                pass
    assert info.value.signum == signal.SIGTERM


def test_once_a_guard_took_over_the_hold_is_gone(isolated_signals) -> None:
    """A run without checkpoints does not handle SIGUSR1/SIGUSR2: they get their original
    handlers back when its guard is installed (not swallowed for the whole run), and the
    signals a guard handles go back to the originals, not to the hold, when it ends."""
    before = {s: signal.getsignal(s) for s in signals.EARLY_SIGNALS}
    signals.hold_early()
    guard = signals.SignalGuard()
    with guard.installed():
        assert signal.getsignal(signal.SIGUSR1) == before[signal.SIGUSR1]
        assert signal.getsignal(signal.SIGTERM) == guard._handler
    assert {s: signal.getsignal(s) for s in signals.EARLY_SIGNALS} == before


def test_only_a_second_ctrl_c_stops_a_checkpointing_run_at_once(isolated_signals) -> None:
    """Repeated SIGTERM/SIGUSR1 (a sweep's launcher forwards SIGTERM each second; a job in a
    terminal also gets the Ctrl-C) are the same request: the run still stops at its boundary
    with a checkpoint. A second SIGINT (a person's Ctrl-C) stops it at once."""
    guard = signals.SignalGuard(defer=True)
    with guard.installed():
        os.kill(os.getpid(), signal.SIGINT)
        for sig in (signal.SIGTERM, signal.SIGTERM, signal.SIGUSR1):
            os.kill(os.getpid(), sig)
        assert guard.stop_requested == signal.SIGINT
        with pytest.raises(signals.Interrupted):
            os.kill(os.getpid(), signal.SIGINT)


def test_a_second_early_signal_ends_the_process_at_once() -> None:
    code = ("import os, signal, time; from cobelrun import signals; signals.hold_early(); "
            "os.kill(os.getpid(), signal.SIGTERM); os.kill(os.getpid(), signal.SIGTERM); "
            "time.sleep(5); print('survived')")  # fmt: skip
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == -signal.SIGTERM and "survived" not in proc.stdout


def _signal_when_caught(proc: subprocess.Popen, sig: int) -> None:
    """Send ``sig`` as soon as the process has a handler for it (cobel's first one)."""
    deadline = time.time() + 60
    while time.time() < deadline and proc.poll() is None and not _catches(proc.pid, sig):
        time.sleep(0.001)
    assert proc.poll() is None, proc.communicate()[1][-2000:]
    proc.send_signal(sig)


def test_sigterm_before_the_run_starts_checkpoints_and_exits_75(tmp_path: Path) -> None:
    """``cobel run`` and then ``cobel resume``, each sent SIGTERM as soon as it can catch one
    (before the run exists, before the resume has taken the folder): each stops at its first
    trial boundary with a checkpoint and exits 75; a last ``cobel resume`` completes the run."""
    out = tmp_path / "run"
    proc = start_cobel_run(ARGS, out, tmp_path)
    _signal_when_caught(proc, signal.SIGTERM)
    assert not (out / "manifest.json").exists()  # it landed before the run started
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == REQUEUE_EXIT, err
    assert "checkpoint written" in err and "cobel resume" in err
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["status"] == "interrupted" and manifest["checkpoints"]["written"] == 1
    k = read_header(out / "checkpoint.npz")["position"]["k"]
    assert 0 < k < 30  # its first boundary

    env = {**os.environ, "COBEL_RESULTS": str(tmp_path)}
    resume = [*cobel_exe(), "resume", str(out), "--quiet"]
    proc = subprocess.Popen(resume, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)  # fmt: skip
    _signal_when_caught(proc, signal.SIGUSR1)
    assert json.loads((out / "manifest.json").read_text())["status"] == "interrupted"
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == REQUEUE_EXIT, err
    assert k < read_header(out / "checkpoint.npz")["position"]["k"] < 30  # one piece further

    again = subprocess.run(resume, env=env, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert (out / ".done").is_file() and not (out / "checkpoint.npz").exists()
