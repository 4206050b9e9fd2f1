"""A long phase runs (and is recorded) in pieces (``cobelrun.runner.PhasePacer``).

The pieces change when rows reach the disk, never what they hold: the same seed gives the
same tables however a phase is split, and a run stopped inside a long phase keeps the trials
it finished (before, a stopped DQN run kept none of that phase's trials).
"""

from __future__ import annotations

import pandas as pd
import pytest

from cobelrun.api import compose
from cobelrun.runner import PhasePacer, build_task, execute
from tests.conftest import stop_on_call


def run_task(folder, overrides: list[str]) -> dict[str, pd.DataFrame]:
    task = build_task(compose(None, overrides))
    folder.mkdir()
    execute(task, folder, background_writes=False)
    return {t: pd.read_parquet(folder / f"{t}.parquet") for t in ("trials", "steps")}


def test_pacer_first_piece_then_what_fits():
    pacer = PhasePacer(2.0)
    assert pacer.next("train", 6000) == PhasePacer.FIRST
    assert pacer.next("train", 3) == 3
    pacer.observe("train", 8, 8.0)  # 1 s per trial: 2 fit in 2 s
    assert pacer.next("train", 5992) == 2
    pacer.observe("train", 2, 0.02)  # faster now: 200 would fit, but at most 4x the last piece
    assert pacer.next("train", 5990) == 8
    pacer.observe("train", 8, 0.001)  # the rest fits: one piece
    assert pacer.next("train", 5982) == 5982
    pacer.observe("train", 1, 60.0)  # very slow: one trial at a time, never zero
    assert pacer.next("train", 100) == 1
    assert pacer.next("test", 50) == PhasePacer.FIRST  # each phase (name) is timed apart
    pacer.observe("test", 8, 0.0)  # too fast to time
    assert pacer.next("test", 42) == 42


def test_fast_phases_stay_one_call(tmp_path, monkeypatch):
    """Dyna-Q's phases of 100 trials are one kernel call each after the first piece."""
    from cobelrun.agents.dyna_q import DynaQ

    calls = []
    train = DynaQ.train

    def counting(self, n, *a, **k):
        calls.append(n)
        return train(self, n, *a, **k)

    monkeypatch.setattr(DynaQ, "train", counting)
    run_task(tmp_path / "run", ["task=tmaze_extinction", "task.runs=3"])
    # run 0 starts with pieces (the first includes loading the compiled kernel, so how many
    # depends on the machine); once timed, runs 1 and 2 run each phase of 100 trials at once
    assert calls[0] == PhasePacer.FIRST and sum(calls) == 600, calls
    assert calls[-4:] == [100] * 4, calls


DQN = [
    "task=gridworld", "agent=dqn", "env.world.width=4", "env.world.height=4",
    "env.world.goal=15", "agent.learning_starts=20", "agent.net_arch=[16]",
    "task.protocol.max_steps=30", "task.save_agents=none", "task.batch_runs=false",
    "task.runs=2", "task.record.mcap=false",
    "task.protocol.phases=[{name: train, trials: 20}, {name: probe, trials: 4, learning: false}]",
]  # fmt: skip


@pytest.mark.parametrize("args", [["task=tmaze_extinction", "task.runs=3"], DQN],
                         ids=["dyna_q", "dqn"])  # fmt: skip
def test_same_tables_in_pieces_of_one_trial(tmp_path, args):
    """flush_seconds ~0: every piece after the first is one trial; the tables are identical
    to those of the default pieces."""
    if args is DQN:
        pytest.importorskip("stable_baselines3")
    whole = run_task(tmp_path / "whole", args)
    pieces = run_task(tmp_path / "pieces", [*args, "task.record.flush_seconds=1e-9"])
    for name, table in whole.items():
        pd.testing.assert_frame_equal(pieces[name], table, check_dtype=True)


@pytest.mark.parametrize("exc", [KeyboardInterrupt, RuntimeError])
def test_stop_inside_a_long_phase_keeps_the_finished_trials(tmp_path, monkeypatch, exc):
    """Ctrl-C (or an error) on the 4th piece of run 0's training phase: the trials of the
    first three pieces are in the tables, as the full run recorded them."""
    pytest.importorskip("stable_baselines3")
    from cobelrun.agents.dqn import DQNAgent

    args = [*DQN, "task.record.flush_seconds=1e-9"]
    full = run_task(tmp_path / "full", args)
    stop_on_call(monkeypatch, DQNAgent, "train", 4, exc)
    with pytest.raises(exc):
        run_task(tmp_path / "stopped", args)
    kept = pd.read_parquet(tmp_path / "stopped" / "trials.parquet")
    assert len(kept) == PhasePacer.FIRST + 2  # pieces of 8, 1 and 1 trials
    want = full["trials"].iloc[: len(kept)].reset_index(drop=True)
    pd.testing.assert_frame_equal(kept, want)
    steps = pd.read_parquet(tmp_path / "stopped" / "steps.parquet")
    s = full["steps"]
    want = s[(s.run == 0) & (s.trial <= len(kept))].reset_index(drop=True)
    pd.testing.assert_frame_equal(steps, want)
