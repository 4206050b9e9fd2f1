"""Tests of the run-folder writers: Parquet stream, manifest (MCAP: ``test_mcap.py``)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import cobelrun
from cobelrun.io import Manifest, ParquetStreamWriter, config_hash

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


# MCAP: tests/test_mcap.py


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


def test_string_columns_of_few_values_keep_every_row(tmp_path):
    """The phase column (few distinct strings) is built by index; values, order, non-ASCII
    text and missing values come out as written, and the table reads back the same."""
    from cobelrun.io.parquet import PartedTableWriter

    schema = pa.schema([("phase", pa.string()), ("trial", pa.int32())])
    writer = PartedTableWriter(tmp_path / "t.parquet", tmp_path / "parts", schema)
    rng = np.random.default_rng(0)
    phases = np.array(["acquisition", "extinction", "räume"], dtype=object)[
        rng.integers(0, 3, 5000)
    ]
    unicode_phases = phases.astype(str)  # the same values as a numpy unicode array
    with_none = phases.copy()
    with_none[7] = None
    for column in (phases, unicode_phases, with_none):
        table = writer.to_table({"phase": column, "trial": np.arange(5000)})
        assert table.column("phase").type == pa.string()
        assert table.column("phase").to_pylist() == list(column)
    writer.write_part({"phase": phases, "trial": np.arange(5000)})
    writer.close()
    assert pq.read_table(tmp_path / "t.parquet").column("phase").to_pylist() == list(phases)


@pytest.mark.parametrize("dtype", [object, str])
def test_string_columns_of_long_runs_keep_every_row(tmp_path, dtype):
    """Columns of long runs of one value (the phase of each run's batches) are built from
    their runs; runs of different lengths, a value that comes back, non-ASCII and empty
    text, a missing value inside a run and too many runs (the other paths) all come out as
    written."""
    from cobelrun.io.parquet import PartedTableWriter

    schema = pa.schema([("phase", pa.string())])
    writer = PartedTableWriter(tmp_path / "t.parquet", tmp_path / "parts", schema)
    rng = np.random.default_rng(1)
    values = np.array(["training", "räume", "", "training2"], dtype=object)
    lengths = rng.integers(16, 300, 60)
    runs = np.repeat(values[rng.integers(0, 4, 60)], lengths).astype(dtype)
    short = np.repeat(values[rng.integers(0, 4, 600)], 2).astype(dtype)
    columns = [runs, short, runs[:1], runs[:0]]
    if dtype is object:
        with_none = runs.copy()
        with_none[40] = None
        columns.append(with_none)
    for column in columns:
        table = writer.to_table({"phase": column})
        assert table.column("phase").type == pa.string()
        assert table.column("phase").to_pylist() == list(column)
    writer.write_part({"phase": runs})
    writer.close()
    assert pq.read_table(tmp_path / "t.parquet").column("phase").to_pylist() == list(runs)
