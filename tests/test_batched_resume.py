"""Checkpoints inside a batched chunk (issue 35, ``task.batch_runs``): a chunk of runs trained
as one computation writes its checkpoints between pieces of a phase, as a sequential run does,
and ``resume`` goes on from there: the resumed tables equal an uninterrupted batched run's row
for row, and the resumed process trains only the trials after the checkpoint (tiny settings,
in-process; the stop is a KeyboardInterrupt right after a piece, before its checkpoint)."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from omegaconf import OmegaConf

from cobelrun import api, runner
from cobelrun.batched import BatchedRuns
from cobelrun.checkpoint import CheckpointError, read_header
from tests.inprocess import cli  # noqa: F401 (fixture)
from tests.test_resume import FAST, assert_same_tables, mcap_messages, stop_at, tables

#: two runs in one chunk: every checkpoint but the first lies inside the chunk
CHUNK = ["task.runs=2", "task.batch_runs=2"]

CASES = {
    "dqn": ("two_afc", [*CHUNK, "agent=dqn", "task.protocol.phases.0.trials=14",
                        "agent.net_arch=[8]"]),
    "per_dqn": ("two_afc", [*CHUNK, "agent=per_dqn", "task.protocol.phases.0.trials=14",
                            "agent.net_arch=[8]", "agent.learning_starts=2",
                            "agent.batch_size=4"]),
    "dyna_dqn": ("latent_learning", [*CHUNK, "agent=dyna_dqn",
                                     "task.monitors.activity.layers=[q/output]",
                                     "task.monitors.activity.every=3",
                                     "task.protocol.phases.0.trials=2",
                                     "task.protocol.phases.1.trials=10", "agent.hidden=[8]",
                                     "agent.replay_batch=4", "task.protocol.max_steps=6"]),
    "dyna_dsr": ("latent_learning", [*CHUNK, "task.monitors.activity.every=3",
                                     "task.protocol.phases.0.trials=4",
                                     "task.protocol.phases.1.trials=10", "agent.hidden=[8]",
                                     "agent.replay_batch=4", "task.protocol.max_steps=10"]),
    # Fig. 6A's image DQN (36 x 36 camera views, no dropout), tiny
    "dqn_images": ("tmaze_extinction_3d", [
        *CHUNK, "task.protocol.phases.0.trials=12", "task.protocol.phases.1.trials=2",
        "task.protocol.max_steps=15", "agent.learning_starts=10", "agent.batch_size=8"]),
    # Fig. 8's CNN (dropout, the analysis layer's activity maps, saved agents), tiny
    "dqn_fig8": ("place_cells_original", [
        *CHUNK, "task.protocol.phases=[{name: training, trials: 12}]",
        "task.protocol.max_steps=12", "agent.learning_starts=8", "agent.batch_size=8",
        "task.monitors.maps.grid=[3,3]", "task.monitors.maps.headings=2",
        "task.monitors.maps.every=4", "task.save_agents=all"]),
}  # fmt: skip


def stopped_in_chunk(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, task: str,
                     overrides: list[str], piece: int = 3) -> tuple[Path, dict[str, Any]]:  # fmt: skip
    """A batched run stopped right after its ``piece``-th piece; its checkpoint's header."""
    folder = tmp_path / "stopped"
    with monkeypatch.context() as m:
        stop_at(m, piece, BatchedRuns)
        with pytest.raises(KeyboardInterrupt):
            runner.run(api.compose(task, [*overrides, *FAST]), folder)
    return folder, read_header(folder / "checkpoint.npz")


def resumed_counting(folder: Path, monkeypatch: pytest.MonkeyPatch) -> list[tuple[int, int]]:
    """Resume ``folder``; the (first trial, trials) of every piece the resumed process ran."""
    ran: list[tuple[int, int]] = []
    orig = BatchedRuns.piece

    def counting(self: Any, phase: Any, max_steps: int, first: int, k: int, n: int) -> None:
        ran.append((first + k, n))
        orig(self, phase, max_steps, first, k, n)

    with monkeypatch.context() as m:
        m.setattr(BatchedRuns, "piece", counting)
        runner.run(OmegaConf.load(folder / "config.yaml"), folder, resume=True)
    assert (folder / ".done").is_file() and not (folder / "checkpoint.npz").exists()
    return ran


@pytest.mark.parametrize(
    "agent",
    [pytest.param(a, marks=[pytest.mark.slow] if a in ("dqn_fig8", "dqn_images", "dyna_dsr", "per_dqn") else [])
     for a in CASES],
)  # fmt: skip
def test_resumed_chunk_equals_uninterrupted(agent: str, tmp_path: Path,
                                            monkeypatch: pytest.MonkeyPatch) -> None:  # fmt: skip
    task, overrides = CASES[agent]
    ref = runner.run(api.compose(task, [*overrides, *FAST]), tmp_path / "ref")
    folder, header = stopped_in_chunk(tmp_path, monkeypatch, task, overrides)
    pos = header["position"]
    # the checkpoint lies inside the chunk and inside a phase, and holds both runs' state
    assert pos["run"] == 0 and pos["k"] > 0, pos
    assert header["batch"]["runs"] == [0, 1] and header["agent"] is not None
    before = {name: len(t) for name, t in tables(folder).items()}
    assert header["recorder"]["tables"]["trials"] < before["trials"]  # rows to drop
    ran = resumed_counting(folder, monkeypatch)
    # the resumed process went on at the checkpoint's trial: the trials before it were not
    # trained again (a chunk restarted from its start would begin at trial 1)
    at = pos["first"] + pos["k"]
    per_run = api.compose(task, [*overrides, *FAST]).task.protocol
    n_trials = sum(int(p.trials) for p in per_run.phases)
    assert ran[0][0] == at and sum(n for _, n in ran) == n_trials - at + 1
    assert_same_tables(ref, folder)
    if (ref / "run.mcap").is_file():  # poses and trial events as without the stop
        assert mcap_messages(folder / "run.mcap") == mcap_messages(ref / "run.mcap")
    if (ref / "agents.npz").is_file():  # the trained agents, weights and Adam moments
        with np.load(ref / "agents.npz") as a, np.load(folder / "agents.npz") as b:
            assert sorted(a.files) == sorted(b.files)
            for key in a.files:
                np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_chunk_checkpoint_refused_for_another_config_or_sequential_runs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A chunk's checkpoint continues only its own config; read one line, nothing touched."""
    task, overrides = CASES["dqn"]
    folder, header = stopped_in_chunk(tmp_path, monkeypatch, task, overrides)
    assert header["position"]["k"] > 0
    files = sorted(p.name for p in folder.iterdir())
    other = OmegaConf.load(folder / "config.yaml")
    other.agent.epsilon = 0.2
    with pytest.raises(CheckpointError, match="written for another config") as err:
        runner.run(other, folder, resume=True)
    assert "\n" not in str(err.value)
    assert sorted(p.name for p in folder.iterdir()) == files


def test_chunk_checkpoint_is_bounded_by_the_filled_replay(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The replay memories go in as far as they are filled, not at their capacity."""
    import zipfile

    task, overrides = CASES["dqn"]
    folder, _ = stopped_in_chunk(tmp_path, monkeypatch, task, overrides)
    with zipfile.ZipFile(folder / "checkpoint.npz") as zf:
        names = zf.namelist()
    assert "agent/replay.obs.npy" in names and "agent/adam.exp_avg.0.npy" in names
    with np.load(folder / "checkpoint.npz") as z:
        pos, full = z["agent/replay.pos"], z["agent/replay.full"]
        assert not full.any()
        assert z["agent/replay.obs"].shape[1] == pos.max() > 0
        assert z["agent/adam.steps"].min() > 0  # both runs learned before the checkpoint


@pytest.mark.parametrize(
    "sig", [signal.SIGTERM, pytest.param(signal.SIGUSR1, marks=pytest.mark.slow)]
)
def test_signal_stops_a_chunk_at_the_next_piece_with_a_checkpoint(
    sig: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """SIGTERM/SIGUSR1 in the middle of a batched chunk's phase: the chunk writes its
    checkpoint after the piece under way and stops (Stopped: the CLI's exit 75); the resume
    trains only the trials after it and ends with the uninterrupted tables."""
    from cobelrun.checkpoint import REQUEUE_EXIT
    from cobelrun.signals import Stopped

    task, overrides = CASES["dqn"]
    # no checkpoint by trials: only the signal writes one inside the chunk
    slow = [*overrides, "task.record.flush_seconds=0.001", "task.checkpoint.every_minutes=30"]
    ref = runner.run(api.compose(task, slow), tmp_path / "ref")
    folder = tmp_path / "stopped"
    orig, calls = BatchedRuns.piece, {"n": 0}

    def signalled(self: Any, *args: Any) -> None:
        calls["n"] += 1
        if calls["n"] == 2:  # the signal arrives while the second piece runs
            os.kill(os.getpid(), sig)
        orig(self, *args)

    with monkeypatch.context() as m:
        m.setattr(BatchedRuns, "piece", signalled)
        with pytest.raises(Stopped):
            runner.run(api.compose(task, slow), folder)
    assert calls["n"] == 2  # stopped at the boundary after the piece under way
    header = read_header(folder / "checkpoint.npz")
    assert header["position"]["k"] > 0 and header["batch"]["runs"] == [0, 1]
    assert json.loads((folder / "manifest.json").read_text())["status"] == "interrupted"
    assert REQUEUE_EXIT == 75
    ran = resumed_counting(folder, monkeypatch)
    assert ran[0][0] == header["position"]["first"] + header["position"]["k"]
    assert_same_tables(ref, folder)


@pytest.mark.slow
def test_sigterm_to_a_batched_cli_run_exits_75_and_cobel_resume_finishes_it(
    tmp_path: Path,
    cli: Any,  # noqa: F811
) -> None:
    """A real ``cobel run`` of a batched chunk sent SIGTERM mid-phase: checkpoint inside the
    chunk, exit 75; ``cobel resume`` then ends with the tables of the run without the stop."""
    import time

    from cobelrun.checkpoint import REQUEUE_EXIT
    from tests.conftest import start_cobel_run

    args = ["task=two_afc", "agent=dqn", *CHUNK, "task.protocol.phases.0.trials=400",
            "agent.net_arch=[16]", "agent.learning_starts=10",
            "task.record.flush_seconds=0.05", "task.checkpoint.every_minutes=30"]  # fmt: skip
    out = tmp_path / "run"
    proc = start_cobel_run(args, out, tmp_path)
    deadline = time.time() + 300
    # the chunk's first checkpoint (its start) is written once the signal guard is installed
    while time.time() < deadline and proc.poll() is None:
        if (out / "checkpoint.npz").is_file():
            break
        time.sleep(0.02)
    # past the chunk's start (a signal there stops it before its first piece, at k = 0)
    time.sleep(0.5)
    assert proc.poll() is None, proc.communicate()[1]
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == REQUEUE_EXIT, err
    header = read_header(out / "checkpoint.npz")
    assert header["position"]["k"] > 0 and header["batch"]["runs"] == [0, 1]
    result = cli("resume", str(out), "--quiet")
    assert result.returncode == 0, result.stderr
    assert not (out / "checkpoint.npz").exists() and (out / ".done").is_file()
    ref = runner.run(api.compose(None, args), tmp_path / "ref")
    assert_same_tables(ref, out)
