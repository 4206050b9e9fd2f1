"""Tests of the run-folder writers: Parquet stream, MCAP stream, manifest."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from mcap.reader import make_reader

import cobelrun
from cobelrun.io import Manifest, McapStreamWriter, ParquetStreamWriter, config_hash

SCHEMA = pa.schema(
    [
        ("trial", pa.int64()),
        ("state", pa.int32()),
        ("reward", pa.float64()),
        ("terminated", pa.bool_()),
        ("phase", pa.string()),
    ]
)


def _cols(start: int, n: int) -> dict[str, np.ndarray]:
    idx = np.arange(start, start + n)
    return {
        "trial": idx,
        "state": (idx % 7).astype(np.int64),
        "reward": idx * 0.5,
        "terminated": idx % 2 == 0,
        "phase": np.array(["acq" if i < 1000 else "ext" for i in idx], dtype=object),
    }


# --------------------------------------------------------------------------- parquet
def test_parquet_round_trip_and_row_groups(tmp_path: Path) -> None:
    path = tmp_path / "steps.parquet"
    with ParquetStreamWriter(path, SCHEMA, row_group_rows=500) as w:
        start = 0
        for n in (1, 333, 0, 700, 1200, 17):
            w.write(_cols(start, n))
            start += n
        assert w.rows_written == start
    assert w.closed
    w.close()  # idempotent
    meta = pq.ParquetFile(path).metadata
    assert meta.num_row_groups > 1
    assert meta.num_rows == start
    # full row groups except the last one
    sizes = [meta.row_group(i).num_rows for i in range(meta.num_row_groups)]
    assert all(s == 500 for s in sizes[:-1]) and sizes[-1] <= 500
    assert meta.row_group(0).column(0).compression == "ZSTD"
    df = pd.read_parquet(path)
    expected = pd.DataFrame(_cols(0, start))
    assert list(df.columns) == SCHEMA.names
    np.testing.assert_array_equal(df["trial"], expected["trial"])
    np.testing.assert_array_equal(df["state"], expected["state"])
    np.testing.assert_array_equal(df["reward"], expected["reward"])
    np.testing.assert_array_equal(df["terminated"], expected["terminated"])
    assert df["phase"].tolist() == expected["phase"].tolist()
    assert df["state"].dtype == np.int32


def test_parquet_scalar_broadcast_and_flush(tmp_path: Path) -> None:
    path = tmp_path / "t.parquet"
    w = ParquetStreamWriter(path, SCHEMA)
    w.write({"trial": np.arange(3), "state": 1, "reward": 0.0, "terminated": True, "phase": "x"})
    w.flush()
    w.close()
    df = pd.read_parquet(path)
    assert df["state"].tolist() == [1, 1, 1] and df["phase"].tolist() == ["x"] * 3


def test_parquet_schema_mismatch(tmp_path: Path) -> None:
    with ParquetStreamWriter(tmp_path / "t.parquet", SCHEMA) as w:
        cols = _cols(0, 3)
        del cols["reward"]
        cols["rewrd"] = np.zeros(3)
        with pytest.raises(ValueError, match=r"missing columns \['reward'\].*unknown columns"):
            w.write(cols)
        bad = _cols(0, 3)
        bad["state"] = np.arange(4)
        with pytest.raises(ValueError, match="'state' has 4 rows"):
            w.write(bad)
        bad = _cols(0, 3)
        bad["trial"] = np.array(["a", "b", "c"])
        with pytest.raises(ValueError, match=r"'trial'.*int64"):
            w.write(bad)
        w.write(_cols(0, 3))  # the writer is still usable
    assert len(pd.read_parquet(tmp_path / "t.parquet")) == 3
    with pytest.raises(RuntimeError, match="closed"):
        w.write(_cols(0, 3))


@pytest.mark.parametrize("exc", [RuntimeError, KeyboardInterrupt])
def test_parquet_readable_after_exception(tmp_path: Path, exc: type[BaseException]) -> None:
    path = tmp_path / "t.parquet"
    with pytest.raises(exc), ParquetStreamWriter(path, SCHEMA, row_group_rows=100) as w:
        w.write(_cols(0, 250))
        w.write(_cols(250, 30))
        raise exc()
    df = pd.read_parquet(path)
    assert df["trial"].tolist() == list(range(280))


def test_parquet_empty_file_is_valid(tmp_path: Path) -> None:
    path = tmp_path / "t.parquet"
    ParquetStreamWriter(path, SCHEMA).close()
    df = pd.read_parquet(path)
    assert len(df) == 0 and list(df.columns) == SCHEMA.names


# --------------------------------------------------------------------------- mcap
def _read_mcap(path: Path) -> list[tuple[str, str, str, int, dict]]:
    out = []
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            out.append(
                (
                    channel.topic,
                    schema.name,
                    schema.encoding,
                    message.log_time,
                    json.loads(message.data),
                )
            )
    return out


def _pose_data(n: int, seed: int = 0) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, 10**12, n)).astype(np.int64)
    x = rng.normal(0, 5, n)
    y = rng.normal(0, 50, n)
    h = rng.uniform(-math.pi, math.pi, n)
    x[:3] = [0.0, -0.0000000004, -123.5]  # zero, negative rounding to zero, negative
    return t, x, y, h


@pytest.mark.parametrize("bulk", [True, False])
def test_mcap_poses_and_trials(tmp_path: Path, bulk: bool) -> None:
    path = tmp_path / "run.mcap"
    t, x, y, h = _pose_data(3000)
    # small chunks: the poses span many chunks
    with McapStreamWriter(path, chunk_size=16_384, bulk_append=bulk) as w:
        assert (w._fast is not None) == bulk  # the installed mcap has the internals we use
        w.write_trial_event(0, run=0, trial=0, phase="acquisition", event="start", start_state=4)
        assert w.write_poses(t[:1000], x[:1000], y[:1000], h[:1000]) == 1000
        w.write_poses(t[1000:], x[1000:], y[1000:])  # no heading: identity orientation
        w.write_poses(t[:0], x[:0], y[:0])
        w.write_trial_event(
            int(t[-1]),
            run=0,
            trial=0,
            phase="acquisition",
            event="end",
            steps=np.int64(3000),
            reward=np.float64(1.0),
            response="right",
            start_state=4,
            end_state=np.int64(9),
        )
    w.close()  # idempotent
    msgs = _read_mcap(path)
    poses = [m for m in msgs if m[0] == "/pose"]
    trials = [m for m in msgs if m[0] == "/trial"]
    assert len(poses) == 3000 and len(trials) == 2
    assert {m[1] for m in poses} == {"foxglove.PoseInFrame"}
    assert {m[1] for m in trials} == {"cobel.TrialEvent"}
    assert {m[2] for m in msgs} == {"jsonschema"}
    assert [m[3] for m in poses] == t.tolist()
    for i, (*_, p) in enumerate(poses):
        assert p["timestamp"] == {"sec": int(t[i]) // 10**9, "nsec": int(t[i]) % 10**9}
        assert p["frame_id"] == "maze"
        pos, q = p["pose"]["position"], p["pose"]["orientation"]
        assert pos["x"] == pytest.approx(x[i], abs=1e-9)
        assert pos["y"] == pytest.approx(y[i], abs=1e-9)
        assert pos["z"] == 0.0
        assert q["x"] == 0.0 and q["y"] == 0.0
        if i < 1000:
            assert q["z"] == pytest.approx(math.sin(h[i] / 2), abs=1e-9)
            assert q["w"] == pytest.approx(math.cos(h[i] / 2), abs=1e-9)
        else:
            assert (q["z"], q["w"]) == (0.0, 1.0)
    start, end = trials[0][4], trials[1][4]
    assert start == {
        "run": 0,
        "trial": 0,
        "phase": "acquisition",
        "event": "start",
        "start_state": 4,
    }
    assert end["steps"] == 3000 and end["response"] == "right" and end["end_state"] == 9

    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    assert summary.statistics.message_count == 3002
    assert summary.statistics.chunk_count > 1
    assert summary.statistics.message_start_time == 0
    assert summary.statistics.message_end_time == int(t.max())
    assert {s.name for s in summary.schemas.values()} == {
        "foxglove.PoseInFrame",
        "cobel.TrialEvent",
    }
    pose_schema = next(s for s in summary.schemas.values() if s.name == "foxglove.PoseInFrame")
    assert json.loads(pose_schema.data)["required"] == ["timestamp", "frame_id", "pose"]
    # time-ordered reading (uses the chunk message indexes) sees every message once
    with open(path, "rb") as f:
        times = [m.log_time for _, _, m in make_reader(f).iter_messages(log_time_order=True)]
    assert times == sorted([0, *t.tolist(), int(t[-1])])


def test_mcap_bulk_and_per_message_paths_agree(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    t, x, y, h = _pose_data(500, seed=1)
    out = []
    for bulk, batch in ((True, 1 << 16), (False, 1 << 16), (True, 37)):
        monkeypatch.setattr("cobelrun.io.mcap._POSE_BATCH", batch)
        path = tmp_path / f"{bulk}{batch}.mcap"
        with McapStreamWriter(path, chunk_size=4096, bulk_append=bulk, frame_id='a"b%d') as w:
            w.write_poses(t, x, y, h)
        out.append(_read_mcap(path))
    assert out[0] == out[1] == out[2]
    assert out[0][0][4]["frame_id"] == 'a"b%d'


def test_mcap_huge_coordinates_use_exact_repr(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    with McapStreamWriter(path) as w:
        w.write_poses(np.array([5, 6]), np.array([1e12, -2.5]), np.array([0.1, 3.0]), z=1.5)
    poses = [m[4]["pose"]["position"] for m in _read_mcap(path)]
    assert poses == [{"x": 1e12, "y": 0.1, "z": 1.5}, {"x": -2.5, "y": 3.0, "z": 1.5}]


def test_mcap_generic_channel_and_errors(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    schema = {"type": "object", "properties": {"units": {"type": "array"}}}
    with McapStreamWriter(path) as w:
        w.add_channel("/activity", "cobel.Activity", schema)
        w.write_json("/activity", 10, {"units": np.arange(3, dtype=np.float32)})
        w.add_metadata("run", {"seed": 3, "task": "tmaze"})
        with pytest.raises(ValueError, match="not registered"):
            w.write_json("/nope", 0, {})
        with pytest.raises(ValueError, match="already registered"):
            w.add_channel("/activity", "x", {})
        with pytest.raises(ValueError, match="unknown TrialEvent fields"):
            w.write_trial_event(0, trial=1, event="start", rewrd=1)
        with pytest.raises(ValueError, match="'start' or 'end'"):
            w.write_trial_event(0, trial=1, event="begin")
        with pytest.raises(ValueError, match="finite"):
            w.write_poses(np.array([0]), np.array([np.nan]), np.array([0.0]))
        with pytest.raises(ValueError, match="equal length"):
            w.write_poses(np.array([0, 1]), np.array([0.0]), np.array([0.0]))
        with pytest.raises(ValueError, match=">= 0"):
            w.write_poses(np.array([-1]), np.array([0.0]), np.array([0.0]))
    msgs = _read_mcap(path)
    assert msgs == [("/activity", "cobel.Activity", "jsonschema", 10, {"units": [0.0, 1.0, 2.0]})]
    with open(path, "rb") as f:
        meta = list(make_reader(f).iter_metadata())
    assert meta[0].name == "run" and meta[0].metadata == {"seed": "3", "task": "tmaze"}
    with pytest.raises(RuntimeError, match="closed"):
        w.write_json("/activity", 0, {})


def test_mcap_readable_after_exception(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    with pytest.raises(KeyboardInterrupt), McapStreamWriter(path) as w:
        w.write_poses(np.arange(10), np.zeros(10), np.ones(10))
        raise KeyboardInterrupt
    assert len(_read_mcap(path)) == 10


# --------------------------------------------------------------------------- manifest
def test_config_hash() -> None:
    a = {"env": {"name": "tmaze", "size": [3, 4]}, "agent": {"lr": 0.1}, "seed": 1}
    b = {"seed": 1, "agent": {"lr": 0.1}, "env": {"size": (3, 4), "name": "tmaze"}}
    assert config_hash(a) == config_hash(b)
    assert len(config_hash(a)) == 64
    c = {**a, "agent": {"lr": 0.2}}
    assert config_hash(c) != config_hash(a)
    assert config_hash({"x": 1}) != config_hash({"x": "1"})
    assert config_hash({"x": np.float64(0.5)}) == config_hash({"x": 0.5})


def test_config_hash_omegaconf() -> None:
    omegaconf = pytest.importorskip("omegaconf")
    cfg = omegaconf.OmegaConf.create({"a": {"b": 1, "c": "${a.b}"}, "l": [1, 2]})
    assert config_hash(cfg) == config_hash({"a": {"b": 1, "c": 1}, "l": [1, 2]})


def test_manifest_start_finish(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    m = Manifest(run_dir)
    cfg = {"task": "tmaze", "agent": {"lr": 0.1}}
    m.start(config=cfg, seed=3, task="tmaze", extra={"job": 7})
    data = json.loads((run_dir / "manifest.json").read_text())
    assert data["status"] == "running"
    assert data["seed"] == 3 and data["task"] == "tmaze" and data["job"] == 7
    assert data["config"] == cfg
    assert data["config_hash"] == config_hash(cfg)
    assert data["cobelrun_version"] == cobelrun.__version__
    versions = data["versions"]
    for name in ("python", "numpy", "pandas", "pyarrow", "mcap"):
        assert name in versions
    assert data["started_at"].endswith("+00:00")
    assert data["hostname"] and data["platform"] and isinstance(data["command"], list)
    assert set(data["git"]) == {"cwd", "cobelrun"}
    src_git = data["git"]["cobelrun"]
    if src_git is not None:  # running from a checkout
        assert len(src_git["commit"]) == 40 and isinstance(src_git["dirty"], bool)
    assert [p.name for p in run_dir.iterdir()] == ["manifest.json"]  # no temp files left

    out = m.finish("failed", error="ValueError: boom")
    again = json.loads((run_dir / "manifest.json").read_text())
    assert again == json.loads(json.dumps(out))
    assert again["status"] == "failed" and again["error"] == "ValueError: boom"
    assert again["duration_s"] >= 0 and again["ended_at"] >= again["started_at"]

    # a new Manifest object (e.g. another process) can finish from the file on disk
    m2 = Manifest(run_dir)
    m2.finish("completed", n_trials=10)
    final = m2.read()
    assert final["status"] == "completed" and final["n_trials"] == 10 and final["seed"] == 3
    with pytest.raises(ValueError, match="status must be one of"):
        m2.finish("done")
    with pytest.raises(ValueError, match="replace standard fields"):
        Manifest(tmp_path / "other").start(config={}, seed=0, task="t", extra={"seed": 1})


def test_manifest_atomic_write(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    m = Manifest(tmp_path)
    m.start(config={"a": 1}, seed=0, task="t")
    before = (tmp_path / "manifest.json").read_text()

    def broken_replace(src: str, dst: str) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(OSError, match="disk full"):
        m.finish("completed")
    assert (tmp_path / "manifest.json").read_text() == before  # old file intact
    assert [p.name for p in tmp_path.iterdir()] == ["manifest.json"]  # temp file removed
