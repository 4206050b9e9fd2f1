"""Resume with ``task.record.mcap_timeline=per_run`` (issue 33): every run's clock starts at
the file's start, so the stopped process's MCAP is cut run by run at each run's clock at the
checkpoint (its watermark) before the resumed process's is joined to it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from cobelrun import api, runner
from cobelrun.io.mcap import STEP_NS, McapRecorder, per_run_cut
from cobelrun.io.mcap_repair import join_mcap
from tests.test_resume import FAST, mcap_messages, stopped_and_resumed

START = 10**18


def _write(path: Path, runs: dict[int, range]) -> None:
    """A file as a per_run recorder writes it: the scene at START, then per run its poses,
    trial events and tables at START + k steps for k in ``runs[run]``."""
    from cobelrun.envs.gridworld import GridWorldEnv

    geometry = GridWorldEnv().geometry()
    with McapRecorder(path, geometry=geometry, start_ns=START) as rec:
        for run, ks in runs.items():
            t = START + np.array(list(ks), np.int64) * STEP_NS
            rec.write_poses(run, t, np.zeros((len(t), 3)))
            n = len(t)
            rec.write_trial_events(run, np.arange(1, n + 1), "p", t, t, np.zeros(n, int),
                                   np.zeros(n, int), np.ones(n, int), np.zeros(n))  # fmt: skip
            for k, ti in enumerate(t.tolist()):
                rec.write_trial_table(run, "p", k + 1, ti, np.ones(1, int), np.zeros(1),
                                      np.zeros(1, int), np.zeros(1, int), np.ones(1, bool))  # fmt: skip


def _read(path: Path) -> list[tuple[str, int, int]]:
    """(topic, run, step) of every message; run -1 for the scene."""
    from cobelrun.io.mcap import _trial_table_type

    out = []
    with open(path, "rb") as f:
        for _, ch, m in make_reader(f, validate_crcs=True).iter_messages():
            step = (m.log_time - START) // STEP_NS
            if ch.topic == "/maze":
                run = -1
            elif ch.topic == "/trial":
                run = json.loads(m.data)["run"]
            elif ch.topic == "/trials":
                run = _trial_table_type()[0].FromString(m.data).run
            else:
                run = int(ch.topic.split("/")[1][4:])
            out.append((ch.topic, run, step))
    return sorted(out)


def test_per_run_join_cuts_each_run_at_its_own_clock(tmp_path: Path) -> None:
    """Run 0 was at step 3 and run 1 at step 2 when the checkpoint was taken; the stopped
    process went on to step 5 in both (dropped), the resumed one wrote from the checkpoint
    on: the join holds each step of each run once, and one scene."""
    stopped, resumed, ref = tmp_path / "a.mcap", tmp_path / "b.mcap", tmp_path / "ref.mcap"
    _write(stopped, {0: range(0, 6), 1: range(0, 6), 2: range(0, 1)})
    _write(resumed, {0: range(3, 8), 1: range(2, 8), 2: range(0, 8)})
    _write(ref, {0: range(0, 8), 1: range(0, 8), 2: range(0, 8)})
    join_mcap(stopped, resumed, resumed, per_run_cut(START, {0: 3 * STEP_NS, 1: 2 * STEP_NS}))
    got = _read(resumed)
    assert got == _read(ref)
    assert [x for x in got if x[0] == "/maze"] == [("/maze", -1, 0)]
    cut = per_run_cut(START, {"0": 5})  # the checkpoint's JSON keys are strings
    assert cut("/run_0000/pose", b"") == START + 5 and cut("/run_0003/camera", b"") == START
    assert cut("/other", b"") is None


@pytest.mark.slow  # ~4 s: two tiny runs, stopped and resumed (the join is checked above)
def test_resumed_per_run_mcap_equals_uninterrupted(tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:  # fmt: skip
    task = "tmaze_extinction"
    overrides = ["task.runs=2", "task.batch_runs=false", "task.protocol.phases.0.trials=12",
                 "task.protocol.phases.1.trials=12", "task.record.mcap_timeline=per_run"]  # fmt: skip
    ref = runner.run(api.compose(task, [*overrides, *FAST]), tmp_path / "ref")
    folder = stopped_and_resumed(tmp_path, monkeypatch, task, overrides)
    assert mcap_messages(folder / "run.mcap") == mcap_messages(ref / "run.mcap")
