"""The end-of-run phase summary (``cobelrun.run_summary``): arrays, Parquet and DataFrame
inputs agree with a direct pandas computation, missing values included."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from cobelrun.run_summary import phase_rows, read_phase_rows, summary


def _reference(trials: pd.DataFrame, last: int) -> list[dict]:
    """The summary written out with pandas group-bys (the definition)."""
    rows = []
    order = trials.drop_duplicates("phase", keep="first").sort_values("trial")["phase"]
    for phase in order:
        part = trials[trials["phase"] == phase]
        tail = part[part["trial"] >= part["trial"].max() - last + 1]
        row = {"phase": phase, "runs": part["run"].nunique(),
               "trials": part.groupby("run")["trial"].nunique().max()}  # fmt: skip
        for col, name in (("reward", "reward"), ("steps", "latency"), ("response", "response")):
            if col in part:
                row[name] = tail[col].astype("Float64").mean()
        rows.append(row)
    return rows


def _table(seed: int) -> pd.DataFrame:
    """Three runs of two phases (the second run stops early), rows shuffled within runs."""
    rng = np.random.default_rng(seed)
    parts = []
    for run, n2 in ((0, 30), (1, 12), (2, 30)):
        for phase, lo, n in (("acquisition", 1, 25), ("extinction", 26, n2)):
            trial = np.arange(lo, lo + n)
            parts.append(pd.DataFrame({
                "run": run, "trial": trial, "phase": phase,
                "reward": rng.random(n), "steps": rng.integers(3, 40, n),
                "response": pd.array(rng.integers(0, 2, n), dtype="Int8"),
            }))  # fmt: skip
    df = pd.concat(parts, ignore_index=True)
    df.loc[[3, 40, 77], "response"] = pd.NA
    return df.sample(frac=1.0, random_state=seed).sort_values("run", kind="stable")


@pytest.mark.parametrize("last", [1, 10, 100])
def test_phase_rows_match_a_pandas_reference(tmp_path, last: int) -> None:
    df = _table(3)
    want = _reference(df, last)
    got_df = summary(df, last).to_dict("records")
    path = tmp_path / "trials.parquet"
    pq.write_table(pa.Table.from_pandas(df, preserve_index=False), path)
    got_file = read_phase_rows(path, last)
    many = tmp_path / "groups.parquet"  # row groups (chunks) with their own dictionaries
    pq.write_table(pa.Table.from_pandas(df, preserve_index=False), many, row_group_size=17)
    got_groups = read_phase_rows(many, last)
    for got in (got_df, got_file, got_groups):
        assert [r["phase"] for r in got] == ["acquisition", "extinction"]
        for g, w in zip(got, want, strict=True):
            assert g["runs"] == w["runs"] == 3
            assert g["trials"] == w["trials"]
            for key in ("reward", "latency", "response"):
                assert g[key] == pytest.approx(float(w[key]), rel=1e-12)
    assert got_df[1]["trials"] == 30  # the longest run's count


def test_phase_rows_without_measures_and_empty() -> None:
    rows = phase_rows({"phase": ["b", "b", "a"], "run": [0, 1, 0], "trial": [5, 5, 9]})
    assert rows == [{"phase": "b", "runs": 2, "trials": 1}, {"phase": "a", "runs": 1, "trials": 1}]
    assert phase_rows({"phase": [], "run": [], "trial": []}) == []
    empty = summary(pd.DataFrame(columns=["phase", "run", "trial"]))
    assert list(empty.columns) == ["phase", "runs", "trials"] and empty.empty


def test_reading_the_summary_does_not_import_pandas(tmp_path) -> None:
    """The end of every ``cobel run`` reads it: pandas (~0.3 s) stays unimported."""
    import subprocess
    import sys

    df = _table(1)
    path = tmp_path / "trials.parquet"
    table = pa.Table.from_pandas(df, preserve_index=False)
    table = table.set_column(2, "phase", table.column("phase").dictionary_encode())
    pq.write_table(table, path)
    want = summary(df).to_dict("records")
    code = (
        "import sys, json; from cobelrun.run_summary import read_phase_rows; "
        f"print(json.dumps(read_phase_rows({str(path)!r}))); "
        "assert 'pandas' not in sys.modules"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    import json

    got = json.loads(proc.stdout)
    assert [r["phase"] for r in got] == [r["phase"] for r in want]
    for g, w in zip(got, want, strict=True):
        assert g == pytest.approx(w)
