"""The figures' ``--quick`` paths through ``python -m cobelrun.figures.data``: every summary
table they write has the committed table's columns, in the same order, and a provenance
sidecar. The quick builds are slow on a loaded machine (tens of seconds each): ``slow``; the
check that every exported figure has its committed tables is fast."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cobelrun.figures import data

DATA = Path(__file__).resolve().parents[1] / "docs" / "figures" / "data"
#: figure -> run labels to build (None: all); revaluation: its graph designs (the grid ones are
#: committed as revaluation_grid; their quick build is not part of this test)
QUICK = {
    "fig4": None,
    "fig6b": None,
    "morris": None,
    "pma": None,
    "fig9": None,
    "fig9_seeds": None,
    "fig9_fast": None,
    "fig9_fast_seeds": None,
    "revaluation": ["reward", "transition", "policy"],
    "fig7_paper": None,
}
#: figures whose committed tables are still transcribed (none: Fig. 4 was measured again with
#: ``python -m cobelrun.figures.data fig4`` on 2026-11-28)
TRANSCRIBED: set[str] = set()
#: committed tables of each figure (its summary function's table names)
TABLES = {
    "fig4": ["fig4"],
    "fig6b": ["fig6b", "fig6b_runs"],
    "morris": ["morris", "morris_runs", "morris_probe", "morris_probe_runs"],
    "pma": ["pma", "pma_runs", "pma_criterion", "pma_events"],
    "fig9": ["fig9", "fig9_runs"],
    "fig9_seeds": ["fig9_seeds", "fig9_seeds_runs"],
    "fig9_fast": ["fig9_fast", "fig9_fast_runs"],
    "fig9_fast_seeds": ["fig9_fast_seeds", "fig9_fast_seeds_runs"],
    "revaluation": ["revaluation", "revaluation_runs"],
    "fig7_paper": ["fig7", "fig7_runs", "fig7_sr", "fig7_compare"],
}


def test_every_exported_figure_has_its_committed_tables():
    assert set(QUICK) <= set(data.SUMMARIES)
    for name, tables in TABLES.items():
        for table in tables:
            assert (DATA / f"{table}.csv").is_file(), f"{name}: {table}.csv not committed"
            prov = json.loads((DATA / f"{table}.provenance.json").read_text())
            if name in TRANSCRIBED:  # not run again yet: the transcription names its source
                assert prov["source"] == "transcribed" and prov["transcribed_from"]
                continue
            assert prov["source"] == "run" and prov["figure"] == name and not prov["quick"]


def test_export_rejects_an_unknown_figure_and_label(tmp_path):
    from cobelrun.errors import CobelError

    with pytest.raises(CobelError, match=r"no summary tables for figure 'fig6c'.*fig6b"):
        data.export("fig6c", out_dir=tmp_path)
    with pytest.raises(CobelError, match=r"no run label 'rewrd'.*reward"):
        data.export("revaluation", labels=["rewrd"], out_dir=tmp_path, build=False)
    assert not list(tmp_path.iterdir())


@pytest.mark.slow
@pytest.mark.parametrize("name", list(QUICK))
def test_quick_tables_match_the_committed_schema(tmp_path, name):
    written = data.export(name, quick=True, out_dir=tmp_path / "out", root=tmp_path / "res",
                          labels=QUICK[name])  # fmt: skip
    assert sorted(p.name for p in written) == sorted(f"{t}_quick.csv" for t in TABLES[name])
    for path in written:
        committed = pd.read_csv(DATA / path.name.replace("_quick.csv", ".csv"))
        quick = pd.read_csv(path)
        assert list(quick.columns) == list(committed.columns), path.name
        assert len(quick) > 0
        prov = json.loads(path.with_suffix(".provenance.json").read_text())
        assert prov["quick"] is True and prov["source"] == "run"
        assert prov["command"].endswith("--quick" + (f" --labels {','.join(QUICK[name])}"
                                                     if QUICK[name] else ""))  # fmt: skip


#: figures whose committed tables wait for a long sweep (transcribed until then, in their own
#: columns): their tables come from ``cobelrun.figures.run_import``, by the figure path and by
#: ``--runs`` alike (Fig. 8's quick paths: test_fig8_quick_tables_match_the_committed_schema).
LONG_SWEEPS = {"fig6a": ["fig6a", "fig6a_runs"]}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(LONG_SWEEPS))
def test_quick_tables_of_long_sweeps_equal_the_run_import(tmp_path, name):
    from cobelrun.figures import registry, run_import

    written = data.export(name, quick=True, out_dir=tmp_path / "out", root=tmp_path / "res")
    assert sorted(p.name for p in written) == sorted(f"{t}_quick.csv" for t in LONG_SWEEPS[name])
    figure = registry.get(name)
    sweeps = [registry.sweep_dir(figure, label, quick=True, root=tmp_path / "res")
              for label in figure.runs]  # fmt: skip
    imported = run_import.import_runs(name, sweeps, out_dir=tmp_path / "imp")
    assert sorted(p.name for p in imported) == sorted(f"{t}.csv" for t in LONG_SWEEPS[name])
    for path in imported:
        quick = pd.read_csv(tmp_path / "out" / path.name.replace(".csv", "_quick.csv"))
        pd.testing.assert_frame_equal(quick, pd.read_csv(path), obj=path.name)
        assert len(quick) > 0


#: Fig. 8's quick paths: fig8 (the original's training, seeds 0 and 1 x 300 trials, maps every
#: 50) and fig8_stable (cobel's stabilised training, one job of 2 runs x 500 trials, maps every
#: 100); ~12-15 min each on 2 free cores. Their summaries have the committed fig8.csv's
#: columns; the committed fig8_runs.csv is transcribed (seed, trial, place cells, live units,
#: units), so the quick per-run table must start with its columns.
FIG8_QUICK = {"fig8": ([0, 1], list(range(0, 301, 50))),
              "fig8_stable": ([0], list(range(0, 501, 100)))}  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("name", list(FIG8_QUICK))
def test_fig8_quick_tables_match_the_committed_schema(tmp_path, name):
    written = data.export(name, quick=True, out_dir=tmp_path / "out", root=tmp_path / "res")
    assert sorted(p.name for p in written) == [f"{name}_quick.csv", f"{name}_runs_quick.csv"]
    summary = pd.read_csv(tmp_path / "out" / f"{name}_quick.csv")
    assert list(summary.columns) == list(pd.read_csv(DATA / "fig8.csv").columns)
    per_run = pd.read_csv(tmp_path / "out" / f"{name}_runs_quick.csv")
    committed = list(pd.read_csv(DATA / "fig8_runs.csv").columns)
    assert list(per_run.columns[: len(committed)]) == committed
    seeds, snapshots = FIG8_QUICK[name]
    assert sorted(per_run["seed"].unique()) == seeds and per_run["complete"].all()
    assert len(per_run[["seed", "run"]].drop_duplicates()) == 2  # two runs either way
    assert sorted(per_run["trial"].unique()) == snapshots and (per_run["units"] == 50).all()
    assert (per_run["live_units"] >= per_run["place_cells"]).all()
    means = per_run.groupby("trial")["place_cells"].mean()
    np.testing.assert_allclose(summary.set_index("trial")["mean"], means)
    assert (summary["runs"] == 2).all()
    prov = json.loads((tmp_path / "out" / f"{name}_quick.provenance.json").read_text())
    assert prov["quick"] is True and prov["source"] == "run" and prov["figure"] == name
