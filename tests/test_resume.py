"""Resume (issue 35): a run stopped after a checkpoint and resumed from it writes the same
tables, row for row, as the same run without the stop, for every kind of agent (tiny
settings, in-process: the stop is a KeyboardInterrupt raised in the middle of a later piece,
so the stopped run's tables hold rows past the checkpoint that the resume must drop)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd
import pytest
from omegaconf import OmegaConf

from cobelrun import api, runner
from cobelrun.checkpoint import CheckpointError, read_header
from cobelrun.errors import CobelError
from tests.inprocess import cli  # noqa: F401 (fixture)

#: fast pieces: the pacer's first piece of a phase is 8 trials, then ~flush_seconds worth
FAST = ["task.record.flush_seconds=0.001", "task.checkpoint.every_trials=4"]

CASES = {
    "dyna_q": ("tmaze_extinction", ["task.runs=2", "task.protocol.phases.0.trials=20",
                                    "task.protocol.phases.1.trials=20"]),
    "dqn": ("two_afc", ["agent=dqn", "task.runs=2", "task.batch_runs=false",
                        "task.protocol.phases.0.trials=20", "agent.net_arch=[8]"]),
    "per_dqn": ("two_afc", ["agent=per_dqn", "task.runs=2", "task.batch_runs=false",
                            "task.protocol.phases.0.trials=20", "agent.net_arch=[8]",
                            "agent.learning_starts=2", "agent.batch_size=4"]),
    "dyna_dqn": ("latent_learning", ["agent=dyna_dqn", "task.runs=1", "task.batch_runs=false",
                                     "task.monitors.activity.layers=[q/output]",
                                     "task.monitors.activity.every=3",
                                     "task.protocol.phases.0.trials=6",
                                     "task.protocol.phases.1.trials=10", "agent.hidden=[8]",
                                     "agent.replay_batch=4", "task.protocol.max_steps=30"]),
    "dyna_dsr": ("latent_learning", ["task.runs=1", "task.batch_runs=false",
                                     "task.monitors.activity.every=3",
                                     "task.protocol.phases.0.trials=6",
                                     "task.protocol.phases.1.trials=10", "agent.hidden=[8]",
                                     "agent.replay_batch=4", "task.protocol.max_steps=30"]),
    "mfec": ("gridworld", ["agent=mfec", "task.runs=2", "task.protocol.phases.0.trials=20",
                           "agent.projection_dim=8"]),
    "pma": ("dyna_maze", ["task.runs=1", "task.protocol.phases.0.trials=12",
                          "task.protocol.max_steps=200"]),
    "actor_critic": ("morris_water_maze", ["task.runs=1", "task.protocol.phases.0.trials=10",
                                           "task.protocol.max_steps=100",
                                           "task.protocol.phases.1.max_steps=50"]),
}  # fmt: skip


def stop_at(monkeypatch: pytest.MonkeyPatch, piece: int, cls: Any = runner.OneRun) -> None:
    """KeyboardInterrupt (as Ctrl-C) right after the ``piece``-th piece of the run was
    recorded, before the loop could checkpoint it: the stopped run's tables then hold rows
    past its checkpoint."""
    orig, calls = cls.piece, {"n": 0}

    def patched(self: Any, *args: Any, **kwargs: Any) -> None:
        orig(self, *args, **kwargs)
        calls["n"] += 1
        if calls["n"] == piece:
            raise KeyboardInterrupt

    monkeypatch.setattr(cls, "piece", patched)


def tables(folder: Path) -> dict[str, pd.DataFrame]:
    return {p.stem: pd.read_parquet(p) for p in sorted(folder.glob("*.parquet"))}


def assert_same_tables(a: Path, b: Path) -> None:
    ta, tb = tables(a), tables(b)
    assert ta.keys() == tb.keys()
    for name in ta:
        pd.testing.assert_frame_equal(ta[name], tb[name], obj=name)


def stopped_and_resumed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, task: str,
                        overrides: list[str], piece: int = 3, cls: Any = runner.OneRun) -> Path:  # fmt: skip
    cfg = api.compose(task, [*overrides, *FAST])
    folder = tmp_path / "stopped"
    with monkeypatch.context() as m:
        stop_at(m, piece, cls)
        with pytest.raises(KeyboardInterrupt):
            runner.run(cfg, folder)
    assert (folder / "checkpoint.npz").is_file()
    before = {name: len(t) for name, t in tables(folder).items()}
    header = read_header(folder / "checkpoint.npz")
    marks = header["recorder"]["tables"]
    assert marks["trials"] < before["trials"]  # rows past the checkpoint, dropped on resume
    runner.run(OmegaConf.load(folder / "config.yaml"), folder, resume=True)
    assert not (folder / "checkpoint.npz").exists()  # removed once the run completed
    assert (folder / ".done").is_file()
    return folder


def mcap_messages(path: Path) -> list[tuple[str, int]]:
    """(topic, log time from the first message) of every message of an MCAP, in log order;
    ``/trials`` left out (one message per piece of a phase: pieces follow the clock)."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        found = [
            (ch.topic, m.log_time) for _, ch, m in make_reader(f).iter_messages(log_time_order=True)
        ]
    t0 = min(t for _, t in found)
    return sorted((topic, t - t0) for topic, t in found if topic != "/trials")


#: in the default run (the rest are ``-m slow``: each costs seconds)
DEFAULT = {"dyna_q", "per_dqn", "pma"}


@pytest.mark.parametrize(
    "agent",
    [pytest.param(a, marks=[] if a in DEFAULT else [pytest.mark.slow]) for a in sorted(CASES)],
)
def test_resumed_tables_equal_uninterrupted(agent: str, tmp_path: Path,
                                            monkeypatch: pytest.MonkeyPatch) -> None:  # fmt: skip
    task, overrides = CASES[agent]
    ref = runner.run(api.compose(task, [*overrides, *FAST]), tmp_path / "ref")
    folder = stopped_and_resumed(tmp_path, monkeypatch, task, overrides)
    assert_same_tables(ref, folder)
    if (ref / "run.mcap").is_file():  # the stream before the resume joined with the rest
        assert mcap_messages(folder / "run.mcap") == mcap_messages(ref / "run.mcap")


def test_resume_across_an_empty_phase(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A checkpoint at the end of a phase points at the next phase with trials (an empty
    phase in between is skipped) and the resumed run rebuilds the world up to it."""
    overrides = ["task.runs=2", "task.protocol.phases.0.trials=8",
                 "task.protocol.phases.1.trials=0", "task.protocol.phases.2.trials=12"]  # fmt: skip
    ref = runner.run(api.compose("renewal", [*overrides, *FAST]), tmp_path / "ref")
    folder = stopped_and_resumed(tmp_path, monkeypatch, "renewal", overrides, piece=2)
    assert_same_tables(ref, folder)


def test_resume_refuses_other_config_and_missing_checkpoint(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    task, overrides = CASES["dyna_q"]
    cfg = api.compose(task, [*overrides, *FAST])
    folder = tmp_path / "stopped"
    with monkeypatch.context() as m:
        stop_at(m, 2)
        with pytest.raises(KeyboardInterrupt):
            runner.run(cfg, folder)
    other = OmegaConf.load(folder / "config.yaml")
    other.agent.epsilon = 0.2
    before = sorted(p.name for p in folder.iterdir())
    with pytest.raises(CheckpointError, match="written for another config"):
        runner.run(other, folder, resume=True)
    assert sorted(p.name for p in folder.iterdir()) == before  # nothing touched
    done = runner.run(api.compose(task, [*overrides, *FAST]), tmp_path / "done")
    with pytest.raises(CobelError, match="the run completed already"):
        runner.run(OmegaConf.load(done / "config.yaml"), done, resume=True)
    plain = tmp_path / "plain"  # a tabular run: no checkpoints unless asked for
    with monkeypatch.context() as m:
        stop_at(m, 1)
        with pytest.raises(KeyboardInterrupt):
            runner.run(api.compose(task, overrides), plain)
    with pytest.raises(CheckpointError, match=r"has no checkpoint \(checkpoint.npz\)"):
        runner.run(OmegaConf.load(plain / "config.yaml"), plain, resume=True)


@pytest.mark.slow
def test_sweep_command_again_resumes_a_stopped_job(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    cli: Any,  # noqa: F811
) -> None:
    """``cobel run -m`` again after a job was stopped: the job goes on from its checkpoint
    (not from trial 1) and ends with the tables of an uninterrupted single run."""
    args = ["task=tmaze_extinction", "task.runs=2", *FAST, "hydra/launcher=basic"]
    with monkeypatch.context() as m:
        stop_at(m, 3)
        first = cli("run", "-m", *args, "seed=4,5")
    assert first.returncode != 0
    sweep = next((tmp_path / "results" / "tmaze_extinction" / "sweeps").iterdir())
    job = sweep / "0"
    assert (job / "checkpoint.npz").is_file()
    saved = read_header(job / "checkpoint.npz")["position"]
    resumed_from: list[Any] = []
    orig = runner.RunCheckpoints.open_resume

    def spy(self: Any) -> Any:
        header = orig(self)
        resumed_from.append(header["position"])
        return header

    monkeypatch.setattr(runner.RunCheckpoints, "open_resume", spy)
    again = cli("run", "-m", *args, "seed=4,5")
    assert again.returncode == 0, again.stderr
    assert resumed_from == [saved]  # job 0 went on from its checkpoint
    assert not (job / "checkpoint.npz").exists()
    single = runner.run(api.compose("tmaze_extinction", ["task.runs=2", *FAST, "seed=4"]),
                        tmp_path / "single")  # fmt: skip
    assert_same_tables(single, job)


@pytest.mark.slow
@pytest.mark.parametrize("agent", ["dqn", "dyna_dqn"])
def test_batched_runs_resume_at_their_chunk(
    agent: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Batched runs (task.batch_runs=2 of 4 runs): a chunk is checkpointed at its start and
    between pieces; a stop inside the second chunk resumes from the checkpoint written inside
    it, with the tables of the uninterrupted run (more: tests/test_batched_resume.py)."""
    from cobelrun.batched import BatchedRuns

    task, overrides = CASES[agent]
    overrides = [o for o in overrides if not o.startswith(("task.runs", "task.batch_runs"))]
    overrides += ["task.runs=4", "task.batch_runs=2"]
    ref = runner.run(api.compose(task, [*overrides, *FAST]), tmp_path / "ref")
    pieces = len(api.compose(task, [*overrides, *FAST]).task.protocol.phases)
    folder = stopped_and_resumed(tmp_path, monkeypatch, task, overrides, piece=pieces + 2,
                                 cls=BatchedRuns)  # fmt: skip
    assert_same_tables(ref, folder)


def _stopped_cli_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, cli: Any) -> Path:  # noqa: F811
    """A ``cobel run`` of two 12-trial phases stopped after its 3rd piece, with a checkpoint:
    its folder."""
    with monkeypatch.context() as m:
        stop_at(m, 3)
        first = cli("run", "task=tmaze_extinction", "task.runs=1", *FAST,
                    "task.protocol.phases.0.trials=12", "task.protocol.phases.1.trials=12")  # fmt: skip
    assert first.returncode != 0
    (folder,) = [p.parent for p in (tmp_path / "results").rglob("checkpoint.npz")]
    return folder


def test_cobel_resume_logs_its_launch_in_the_run_log(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    cli: Any,  # noqa: F811
) -> None:
    """``cobel resume`` appends its launch and how it ended to RUN_DIR/cobel.log, as a sweep's
    resumed job does, so the run's launches are counted from its log (the run-import
    sidecars' ``launches``); a refused resume writes nothing to it."""
    from cobelrun.figures.run_import import launches

    folder = _stopped_cli_run(tmp_path, monkeypatch, cli)
    assert len(launches(folder)) == 1
    resumed = cli("resume", str(folder), "--quiet")
    assert resumed.returncode == 0, resumed.stderr
    log = (folder / "cobel.log").read_text()
    assert len(launches(folder)) == 2 and "resumed from its checkpoint" in log
    assert "status completed" in log.split("resumed from its checkpoint")[1]
    again = cli("resume", str(folder))
    assert again.returncode == 2 and (folder / "cobel.log").read_text() == log


def test_resume_of_a_sweep_folder_names_its_jobs(tmp_path: Path) -> None:
    """``cobel resume SWEEP_DIR`` (a plausible slip: the sweep, not its job) says what to give."""
    (tmp_path / "sweep.json").write_text("{}")
    with pytest.raises(CobelError, match=r"not a run folder .*it is a sweep folder \(sweep.json\)"
                       r": give one of its job folders"):  # fmt: skip
        api.resume(tmp_path)
    plain = tmp_path / "plain"
    plain.mkdir()
    with pytest.raises(CobelError, match=r"not a run folder \(no config.yaml\)$"):
        api.resume(plain)


def test_status_of_a_stopped_run_says_how_far_it_got(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    cli: Any,  # noqa: F811
) -> None:
    """``cobel status RUN_DIR`` of an interrupted run: trials recorded of those planned and
    where its checkpoint is (what ``cobel resume`` goes on from); none once it completed."""
    from cobelrun.checkpoint import read_header

    folder = _stopped_cli_run(tmp_path, monkeypatch, cli)
    rows = len(pd.read_parquet(folder / "trials.parquet"))
    pos = read_header(folder / "checkpoint.npz")["position"]
    status = cli("status", str(folder))
    assert status.returncode == 1
    line = next(x for x in status.stdout.splitlines() if "progress:" in x)
    assert f"{rows} of 24 trials recorded ({100 * rows / 24:.1f} %)" in line
    name = ("acquisition", "extinction")[pos["phase"]]
    assert (f"checkpoint: run 0, phase {name!r} ({pos['phase'] + 1} of 2) after {pos['k']} of "
            "12 trials, 0 min ago") in line  # fmt: skip
    assert cli("resume", str(folder), "--quiet").returncode == 0
    assert "progress:" not in cli("status", str(folder)).stdout


def test_progress_counts_a_running_runs_parts(tmp_path: Path) -> None:
    """While a run runs its rows are in parts (a resumed run's first part holds the rows up to
    its checkpoint): they are counted, not the stale table of an earlier launch."""
    import pyarrow as pa

    from cobelrun.commands.summary import run_progress
    from cobelrun.io.run_folder import RunFolder

    folder = RunFolder(tmp_path)
    pd.DataFrame({"trial": range(1, 4)}).to_parquet(folder.table("trials"))  # earlier launch
    folder.parts("trials").mkdir(parents=True)
    for k, rows in enumerate((range(1, 6), range(6, 8))):
        batch = pa.record_batch({"trial": pa.array(list(rows))})
        with pa.OSFile(str(folder.parts("trials") / f"part-{k:06d}.arrow"), "wb") as sink:
            with pa.ipc.new_file(sink, batch.schema) as writer:
                writer.write_batch(batch)
    assert run_progress(folder, {"runs": 2, "trials": 10}) == "7 of 20 trials recorded (35.0 %)"
    assert run_progress(folder, {}) == ""  # nothing planned to compare with


def test_progress_of_a_batched_chunk_names_its_runs(tmp_path: Path) -> None:
    """A batched chunk writes its rows at its end: its checkpoint says which runs it holds,
    the phase by name and the trials done in it."""
    from cobelrun.checkpoint import write_checkpoint
    from cobelrun.commands.summary import run_progress
    from cobelrun.io.run_folder import RunFolder

    folder = RunFolder(tmp_path)
    folder.config.write_text("task:\n  protocol:\n    phases:\n    - {name: learn, trials: 40}\n"
                             "    - {name: test, trials: 10}\n")  # fmt: skip
    header = {"config_hash": "x", "agent": None, "written_unix": 1000.0,
              "position": {"run": 4, "phase": 1, "k": 3, "first": 41},
              "batch": {"runs": [4, 5, 6, 7]}}  # fmt: skip
    write_checkpoint(folder.checkpoint, header, {})
    assert run_progress(folder, {"runs": 8, "trials": 50}, now=1000.0 + 7 * 60) == (
        "checkpoint: runs 4-7 (a batched chunk), phase 'test' (2 of 2) after 3 of 10 trials, "
        "7 min ago"
    )
