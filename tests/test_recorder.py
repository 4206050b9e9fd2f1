"""The recorder: declared tables, time-bounded parts, camera frames, metadata."""

from __future__ import annotations

import json
import time

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from cobelrun.envs import GridWorldEnv, tmaze_paper
from cobelrun.errors import ConfigError
from cobelrun.io.agents_archive import runs_in
from cobelrun.io.run_folder import RunFolder
from cobelrun.monitors import Monitor, RewardMonitor, Table, TrialKeysMonitor
from cobelrun.recorder import RecordConfig, RunRecorder
from cobelrun.records import TrialBatch
from tests.test_mcap import read as read_mcap


def batch(n: int = 4, steps: int = 3) -> TrialBatch:
    trials = [{"states": [38] + [31] * steps, "actions": [1] * steps, "rewards": [0.0] * steps,
               "terminated": False} for _ in range(n)]  # fmt: skip
    return TrialBatch.from_trials(trials)


class Snapshots(Monitor):
    """An event table: one row per run start."""

    def tables(self):
        return [Table("snapshots", (pa.field("run", pa.int32()),), per="event")]

    def start_run(self, run, agent=None):
        self.emit("snapshots", {"run": np.array([run], np.int32)})


def test_tables_are_declared_joined_and_carry_metadata(tmp_path):
    env = GridWorldEnv(tmaze_paper())
    monitors = [TrialKeysMonitor(), RewardMonitor(), Snapshots()]
    rec = RunRecorder(RunFolder(tmp_path), env, monitors, RecordConfig(mcap=False),
                      metadata={"cobel.seed": "3"}, background=False)  # fmt: skip
    for run in range(2):
        rec.start_run(run, None)
        rec.record(run, "a", 1, batch())
    rec.close()
    trials = pq.read_table(tmp_path / "trials.parquet")
    assert trials.column_names == ["run", "trial", "phase", "trial_in_phase", "start_state",
                                   "end_state", "terminated", "reward"]  # fmt: skip
    assert trials.num_rows == 8
    meta = trials.schema.metadata
    assert meta[b"cobel.seed"] == b"3" and meta[b"cobel.table"] == b"trials"
    assert meta[b"cobel.schema_version"] == b"2"
    assert pq.read_table(tmp_path / "snapshots.parquet")["run"].to_pylist() == [0, 1]
    assert not (tmp_path / ".parts").exists()


def test_duplicate_columns_and_undeclared_tables_are_errors(tmp_path):
    env = GridWorldEnv(tmaze_paper())
    with pytest.raises(ConfigError, match="same column"):
        RunRecorder(RunFolder(tmp_path), env, [TrialKeysMonitor(), RewardMonitor(),
                    RewardMonitor()], RecordConfig(mcap=False))  # fmt: skip

    class Stray(Monitor):
        def tables(self):
            return []

        def on_batch(self, b, info):
            return {"elsewhere": {"x": np.zeros(b.n_trials)}}

    rec = RunRecorder(RunFolder(tmp_path / "b"), env, [TrialKeysMonitor(), Stray()],
                      RecordConfig(mcap=False), background=False)  # fmt: skip
    with pytest.raises(ConfigError, match="'elsewhere'"):
        rec.record(0, "a", 1, batch())
    rec.close()


def test_rows_reach_disk_within_flush_seconds(tmp_path):
    env = GridWorldEnv(tmaze_paper())
    rec = RunRecorder(RunFolder(tmp_path), env, [TrialKeysMonitor()],
                      RecordConfig(mcap=False, flush_seconds=0.05), background=False)  # fmt: skip
    rec.record(0, "a", 1, batch())
    assert not (tmp_path / ".parts").exists()  # 4 rows: buffered
    time.sleep(0.06)
    rec.record(0, "a", 5, batch())
    parts = list((tmp_path / ".parts" / "trials").iterdir())
    assert len(parts) == 1  # both batches, handed over as one complete part
    with pa.OSFile(str(parts[0]), "rb") as f:
        assert pa.ipc.open_file(f).read_all().num_rows == 8
    rec.close()
    assert pq.read_table(tmp_path / "trials.parquet").num_rows == 8


@pytest.mark.parametrize(
    "bad, match",
    [({"flush_seconds": 0}, "flush_seconds"), ({"mcap_runs": -1}, "mcap_runs"),
     ({"images": "yes"}, "images"), ({"trial_every": 0}, "trial_every")],
)  # fmt: skip
def test_record_config_errors(bad, match):
    with pytest.raises(ConfigError, match=match):
        RecordConfig.from_config(bad)


def test_camera_frames_of_a_3d_maze_go_to_the_mcap(cobel, tmp_path):
    out = tmp_path / "run"
    proc = cobel("run", "task=tmaze_extinction_3d", "task.runs=1", "task.protocol.phases.0.trials=2",
                 "task.protocol.phases.1.trials=1", "+env.render_mode=rgb_array",
                 "task.record.images=true", f"hydra.run.dir={out}")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    messages = read_mcap(out / "run.mcap")
    frames = [m for m in messages if m[0] == "/run_0000/camera"]
    poses = [m for m in messages if m[0] == "/run_0000/pose"]
    assert len(frames) == len(poses) > 0
    assert [m[2] for m in frames] == [m[2] for m in poses]  # one frame per pose, same times
    assert frames[0][1] == "foxglove.RawImage" and frames[0][3].encoding == "rgb8"
    bad = cobel("run", "task=tmaze_extinction", "task.record.images=true",
                f"hydra.run.dir={tmp_path / 'bad'}")  # fmt: skip
    assert bad.returncode == 2 and "render_mode rgb_array" in bad.stderr
    assert not (tmp_path / "bad").exists()


def test_agents_of_a_job_go_into_one_archive(cobel, tmp_path):
    out = tmp_path / "run"
    proc = cobel("run", "task=tmaze_extinction", "task.runs=12", "task.save_agents=[0,5,11]",
                 f"hydra.run.dir={out}")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    folder = RunFolder(out)
    assert runs_in(folder.agents_archive) == [0, 5, 11]
    kept = json.loads(folder.manifest.read_text())["kept"]
    assert kept == {"trials": "all", "steps": {"runs": 12, "trial_every": 1},
                    "mcap": {"runs": 10, "trial_tables": 12, "images": False},
                    "agents": [0, 5, 11]}  # fmt: skip
    assert not folder.agents.exists() and not folder.agent_parts.exists()
    # +agent.load_from picks run r's member and checks it against the agent's schema
    cont = cobel("run", "task=tmaze_extinction", "task.runs=1", f"+agent.load_from={out}",
                 f"hydra.run.dir={tmp_path / 'continued'}")  # fmt: skip
    assert cont.returncode == 0, cont.stderr
    missing = cobel("run", "task=tmaze_extinction", "task.runs=2", f"+agent.load_from={out}",
                    f"hydra.run.dir={tmp_path / 'missing'}")  # fmt: skip
    assert missing.returncode != 0 and "no saved agent for run 1" in missing.stderr
    bad = cobel("run", "task=tmaze_extinction", "task.save_agents=sometimes")
    assert bad.returncode == 2 and "all, last, none or a list" in bad.stderr


def test_archive_round_trip_and_corrupt_state_is_a_clear_error(tmp_path):
    from cobelrun.agents import MFEC, DynaQ
    from cobelrun.io.agents_archive import AgentArchive, read_agent
    from cobelrun.runner import load_saved_agent

    env = GridWorldEnv(tmaze_paper())
    folder = RunFolder(tmp_path)
    archive = AgentArchive(folder.agents_archive, folder.agent_parts, flush_seconds=1e9,
                           max_bytes=1)  # one part per agent  # fmt: skip
    agents = [DynaQ(env, seed=s) for s in range(3)]
    for run, agent in enumerate(agents):
        agent.train(5, 35)
        assert archive.add(run, agent.get_state(), agent.saved_meta())
        archive.write_batch(archive.take())
    archive.close()
    assert runs_in(folder.agents_archive) == [0, 1, 2] and not folder.agent_parts.exists()
    for run, agent in enumerate(agents):
        fresh = DynaQ(env, seed=99)
        load_saved_agent(fresh, str(tmp_path), run)
        np.testing.assert_array_equal(fresh.Q, agent.Q)
    # a tampered state is refused with the archive and run named
    arrays, meta = read_agent(folder.agents_archive, 1)
    arrays["Q"] = np.full_like(arrays["Q"], np.nan)
    with pytest.raises(ConfigError, match=r"agents.npz \(run 1\).*'Q'"):
        DynaQ(env).load_state(arrays, meta, source=f"{folder.agents_archive} (run 1)")
    # agents whose arrays differ in size between runs (MFEC buffers) fit the run axis
    m_env = GridWorldEnv(tmaze_paper())
    mfec = [MFEC(m_env, seed=s) for s in range(2)]
    mfec[0].train(3, 35)
    arch = AgentArchive(tmp_path / "m.npz", tmp_path / "mparts")
    for run, agent in enumerate(mfec):
        arch.add(run, agent.get_state(), agent.saved_meta())
    arch.close()
    a0, _ = read_agent(tmp_path / "m.npz", 0)
    a1, _ = read_agent(tmp_path / "m.npz", 1)
    assert (
        a0["a0.values"].shape != a1["a0.values"].shape
        or a0["a1.values"].shape != a1["a1.values"].shape
    )


def test_archive_keeps_each_runs_state_and_metadata_as_added(tmp_path):
    """Metadata shared by runs is encoded once, yet a run whose metadata differs (here changed
    in place after the previous add) keeps its own, and arrays are copied at the add."""
    from cobelrun.io.agents_archive import AgentArchive, read_agent

    arch = AgentArchive(tmp_path / "a.npz", tmp_path / "parts")
    meta = {"agent": "x", "hyperparameters": {"lr": 0.5}, "state": {"seen": [1]}}
    state = {"Q": np.arange(4.0)}
    arch.add(0, state, meta)
    meta["state"]["seen"].append(2)
    state["Q"][:] = -1.0
    arch.add(1, state, meta)
    arch.add(2, state, meta)
    arch.close()
    got = [read_agent(tmp_path / "a.npz", r) for r in range(3)]
    assert [m["state"]["seen"] for _, m in got] == [[1], [1, 2], [1, 2]]
    np.testing.assert_array_equal(got[0][0]["Q"], np.arange(4.0))
    np.testing.assert_array_equal(got[2][0]["Q"], np.full(4, -1.0))


def test_archive_stores_arrays_that_do_not_compress_and_deflates_the_others(tmp_path):
    """Network weights (float noise) are stored as they are, a sparse Q table is deflated;
    both read back exactly."""
    import zipfile

    from cobelrun.io.agents_archive import AgentArchive, read_agent

    rng = np.random.default_rng(0)
    states = [{"weights": rng.normal(size=(64, 64)).astype(np.float32),
               "Q": np.where(rng.random((200, 4)) < 0.05, rng.random((200, 4)), 0.0)}
              for _ in range(3)]  # fmt: skip
    arch = AgentArchive(tmp_path / "a.npz", tmp_path / "parts", max_bytes=1)
    for run, state in enumerate(states):
        if arch.add(run, state, {"agent": "x"}):
            arch.write_batch(arch.take())
    arch.close()
    with zipfile.ZipFile(tmp_path / "a.npz") as zf:
        codec = {i.filename: i.compress_type for i in zf.infolist()}
    assert codec["weights.npy"] == zipfile.ZIP_STORED
    assert codec["Q.npy"] == zipfile.ZIP_DEFLATED
    for run, state in enumerate(states):
        got, _ = read_agent(tmp_path / "a.npz", run)
        np.testing.assert_array_equal(got["weights"], state["weights"])
        np.testing.assert_array_equal(got["Q"], state["Q"])


def _run_in_process(tmp_path, name, overrides, background=True):
    from cobelrun.api import compose
    from cobelrun.runner import build_task, execute

    task = build_task(compose("tmaze_extinction", overrides))
    out = tmp_path / name
    out.mkdir()
    execute(task, out, background_writes=background)
    return out


SMALL = ["task.runs=6", "task.protocol.phases.0.trials=12", "task.protocol.phases.1.trials=7"]


@pytest.mark.parametrize(("every", "writer"), [(1, "thread"), (3, "thread"), (1, "process"),
                                               (3, "process")])  # fmt: skip
def test_step_rows_built_in_bulk_equal_rows_built_per_batch(tmp_path, monkeypatch, every, writer):
    """The trajectory monitor's rows, built from joined batches on the writer thread or in the
    step writer process (parts of a few batches each; with 300 steps per join the process
    waits for free slots), are the rows it builds batch by batch: every step row, in order."""
    from cobelrun.monitors import TrajectoryMonitor

    overrides = [*SMALL, f"task.record.trial_every={every}", "task.save_agents=none",
                 f"task.record.step_writer={writer}"]  # fmt: skip
    monkeypatch.setattr(RunRecorder, "JOIN_STEPS", 300)  # many joins, each of several batches
    joined = _run_in_process(tmp_path, "joined", overrides)
    monkeypatch.setattr(TrajectoryMonitor, "joinable", False)
    per_batch = _run_in_process(tmp_path, "per_batch", overrides, background=False)
    a = pq.read_table(joined / "steps.parquet").to_pandas()
    b = pq.read_table(per_batch / "steps.parquet").to_pandas()
    assert len(a) > 1000
    assert a.equals(b)
    trials = pq.read_table(joined / "trials.parquet").to_pandas()
    kept = trials[(trials["trial"] - 1) % every == 0]
    assert len(a) == kept["steps"].sum()  # every step row of every kept trial
    counts = a.groupby(["run", "trial"]).size()
    expected = kept.set_index(["run", "trial"])["steps"]
    assert counts.reindex(expected.index, fill_value=0).tolist() == expected.tolist()
    assert (a.groupby(["run", "trial"])["step"].max() == counts).all()
    assert set(a["run"]) == set(range(6))
    meta = pq.ParquetFile(joined / "steps.parquet").metadata
    assert meta.row_group(0).column(0).encodings.count("RLE_DICTIONARY") == 1


def test_every_runs_trials_go_to_the_mcap_as_trial_tables(tmp_path):
    """Poses and per-trial events only for the first mcap_runs runs; every run's trials as
    one cobel.TrialTable per run and phase (run 0's phases in pieces: the runner times them),
    equal to trials.parquet."""
    out = _run_in_process(tmp_path, "run", [*SMALL, "task.record.mcap_runs=2"])
    trials = pq.read_table(out / "trials.parquet").to_pandas()
    messages = read_mcap(out / "run.mcap")
    topics = {m[0] for m in messages}
    assert topics == {"/maze", "/trial", "/trials", "/run_0000/pose", "/run_0001/pose"}
    events = [m[3] for m in messages if m[0] == "/trial"]
    assert {e["run"] for e in events} == {0, 1}
    tables = [m for m in messages if m[0] == "/trials"]
    assert {m[1] for m in tables} == {"cobel.TrialTable"}
    pieces = {(m[3].run, m[3].phase) for m in tables}
    assert len(pieces) == 6 * 2  # run 0's phases: 8 trials, then what the runner's timing says
    rows = []
    for _, _, log_time, msg in tables:
        t0 = msg.timestamp.seconds * 10**9 + msg.timestamp.nanos
        assert t0 == log_time
        offsets = np.concatenate([[0], np.cumsum(msg.steps)[:-1]]) + np.arange(len(msg.steps))
        for i in range(len(msg.steps)):
            rows.append({"run": msg.run, "trial": msg.first_trial + i, "phase": msg.phase,
                         "steps": msg.steps[i], "reward": msg.reward[i],
                         "start_state": msg.start_state[i], "end_state": msg.end_state[i],
                         "terminated": msg.terminated[i], "response": msg.response[i],
                         "t_start": t0 + int(offsets[i]) * 100_000_000})  # fmt: skip
    got = pd.DataFrame(rows).sort_values(["run", "trial"]).reset_index(drop=True)
    cols = ["run", "trial", "phase", "steps", "reward", "start_state", "end_state",
            "terminated", "response"]  # fmt: skip
    want = trials.sort_values(["run", "trial"]).reset_index(drop=True)[cols]
    pd.testing.assert_frame_equal(got[cols], want, check_dtype=False)
    # the documented trial start times agree with the start events of the runs kept in full
    starts = {(e["run"], e["trial"]): t for (topic, _, t, e) in messages
              if topic == "/trial" and e["event"] == "start"}  # fmt: skip
    kept = got[got["run"] < 2]
    assert [starts[(r, t)] for r, t in zip(kept["run"], kept["trial"], strict=True)] == list(
        kept["t_start"]
    )
    assert got["t_start"].is_monotonic_increasing


def test_streamed_summary_equals_the_summary_of_the_whole_table(tmp_path):
    """What `cobel run` logs and prints at the end is read in batches of rows (flat memory)
    and equals the pandas summary of the whole table, also for a table of several batches."""
    from cobelrun.run_summary import read_phase_rows, summary

    rng = np.random.default_rng(3)
    runs, per_phase = 700, 100  # 140,000 rows: three batches of 65,536
    rows = pd.DataFrame({
        "run": np.repeat(np.arange(runs, dtype=np.int32), 2 * per_phase),
        "trial": np.tile(np.arange(1, 2 * per_phase + 1, dtype=np.int32), runs),
        "phase": np.tile(np.repeat(["acquisition", "extinction"], per_phase), runs),
        "reward": rng.random(runs * 2 * per_phase), "steps": rng.integers(1, 35, runs * 2 * per_phase),
        "response": rng.integers(0, 2, runs * 2 * per_phase).astype(np.int8),
    })  # fmt: skip
    rows.loc[rows["run"] == 5, "reward"] = np.nan  # skipped, as pandas' mean does
    path = tmp_path / "trials.parquet"
    rows.to_parquet(path, row_group_size=50_000)
    got = pd.DataFrame(read_phase_rows(path))
    pd.testing.assert_frame_equal(got, summary(rows), check_dtype=False)
    assert list(got["phase"]) == ["acquisition", "extinction"] and got["runs"].tolist() == [700] * 2


def test_step_writer_process_reports_its_error_and_ends(tmp_path, monkeypatch):
    """A write that fails in the step writer process (a full disk) fails the run in the
    parent with that error at its next flush, as the writer thread's errors do; the child is
    gone afterwards, and the trials written up to then are a finished table."""
    import errno
    import multiprocessing

    from cobelrun.io.parquet import PartedTableWriter

    write_part = PartedTableWriter.write_part

    def full_disk(self, columns):
        if self.path.name == "steps.parquet":
            raise OSError(errno.ENOSPC, "No space left on device")
        return write_part(self, columns)

    monkeypatch.setattr(PartedTableWriter, "write_part", full_disk)  # inherited by the fork
    monkeypatch.setattr(RunRecorder, "JOIN_STEPS", 300)
    with pytest.raises(OSError, match="No space left"):
        _run_in_process(tmp_path, "run", [*SMALL, "task.record.step_writer=process"])
    assert multiprocessing.active_children() == []
    trials = pq.read_table(tmp_path / "run" / "trials.parquet")
    assert 0 < trials.num_rows < 6 * (12 + 7)


def test_step_writer_process_only_when_asked(tmp_path, monkeypatch):
    """record.step_writer: the thread by default; the process when asked, and then the
    manifest's CPU times name it."""
    from cobelrun import step_writer
    from cobelrun.api import compose
    from cobelrun.runner import build_task, execute

    started = []
    monkeypatch.setattr(step_writer.StepWriterProcess, "__init__", _record_start(started))
    for writer, expect in (("thread", []), ("process", [True])):
        started.clear()
        task = build_task(
            compose("tmaze_extinction", [*SMALL, f"task.record.step_writer={writer}"])
        )
        out = tmp_path / writer
        out.mkdir()
        cpu: dict[str, float] = {}
        execute(task, out, cpu_times=cpu)
        assert started == expect
        assert ("step_writer_process" in cpu) == bool(expect)
        assert pq.read_table(out / "steps.parquet").num_rows > 0


def _record_start(started):
    from cobelrun.step_writer import StepWriterProcess

    init = StepWriterProcess.__init__

    def wrapped(self, *args, **kwargs):
        started.append(True)
        init(self, *args, **kwargs)

    return wrapped
