"""Per-run tables of long sweeps (``python -m cobelrun.figures.data NAME --runs ...``), on real
tiny runs: the per-run numbers are the runs' own, the summaries are their means, unfinished runs
are named and never averaged, and the run folders are only read."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from cobelrun import api, runner
from cobelrun.errors import CobelError
from cobelrun.figures import data, run_import
from tests.inprocess import cli  # noqa: F401 (fixture)

#: Dyna-Q in the gridworld T-maze: the extinction protocol (100 + 100 trials), one run a job
FIG6A_TINY = ["task=tmaze_extinction", "task.runs=1", "task.record.steps=false",
              "task.record.mcap=false"]  # fmt: skip


def tree(folder: Path) -> dict[str, tuple[int, int]]:
    """Every file under ``folder`` with its size and modification time (ns)."""
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in sorted(folder.rglob("*")) if p.is_file()}  # fmt: skip


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    """A finished two-job sweep (seeds 0, 1) made by ``cobel run -m`` in this process, shared
    by the tests of this module (they only read it)."""
    import sys

    from typer.testing import CliRunner

    from cobelrun.cli import app

    root = tmp_path_factory.mktemp("fig6a_sweep")
    with pytest.MonkeyPatch.context() as m:
        m.chdir(root)
        m.setenv("COBEL_RESULTS", str(root / "results"))
        m.delenv("HYDRA_FULL_ERROR", raising=False)
        args = ["run", "-m", *FIG6A_TINY, "seed=0,1", "hydra/launcher=basic",
                f"hydra.sweep.dir={root / 'sweep'}"]  # fmt: skip
        m.setattr(sys, "argv", ["cobel", *args])
        out = CliRunner().invoke(app, args)
    assert out.exit_code == 0, out.stdout
    return root / "sweep"


def test_fig6a_tables_are_the_runs_own_numbers(sweep, tmp_path):
    before = tree(sweep)
    written = run_import.import_runs("fig6a", [sweep], out_dir=tmp_path / "out")
    assert tree(sweep) == before  # read only: nothing written, repaired or locked
    assert sorted(p.name for p in written) == ["fig6a.csv", "fig6a_runs.csv"]
    per_run = pd.read_csv(tmp_path / "out" / "fig6a_runs.csv")
    assert per_run["seed"].tolist() == [0, 1] and per_run["job"].tolist() == [0, 1]
    for row in per_run.to_dict("records"):
        trials = pd.read_parquet(sweep / str(row["job"]) / "trials.parquet")
        ext = trials[trials["trial"] > 100]
        assert row["right_181_200"] == pytest.approx(
            trials.loc[trials["trial"].between(181, 200), "response"].mean()
        )
        block = trials[trials["trial"].between(181, 200)]
        assert row["rewarded_181_200"] == pytest.approx((block["reward"] > 0).mean())
        assert "rewarded_81_100" not in row  # acquisition: the right arm is the response
        assert row["latency_181_200"] == pytest.approx(block["steps"].mean())
        assert row["acquisition_steps"] == trials.loc[trials["trial"] <= 100, "steps"].sum()
        assert row["steps"] == trials["steps"].sum() and row["trials"] == 200
        first_left = ext.loc[ext["response"] == 0, "trial"].min() - 100
        assert row["trials_to_extinction"] == first_left
        manifest = json.loads((sweep / str(row["job"]) / "manifest.json").read_text())
        assert row["wall_time_s"] == pytest.approx(manifest["wall_time_s"])
    assert (per_run["task"] == "tmaze_extinction").all()
    summary = pd.read_csv(tmp_path / "out" / "fig6a.csv")
    assert (summary["task"] == "tmaze_extinction").all()
    summary = summary.set_index("measure")
    for col in ("right_1_20", "right_101_110", "rewarded_181_200", "trials_to_extinction"):
        assert summary.loc[col, "mean"] == pytest.approx(per_run[col].mean(), rel=1e-5)
        assert summary.loc[col, "runs"] == 2
    assert summary.loc["lowest_right_81_100", "mean"] == per_run["right_81_100"].min()
    assert (
        summary.loc["runs_right_181_200_at_most_half", "mean"]
        == (per_run["right_181_200"] <= 0.5).sum()
    )
    prov = json.loads((tmp_path / "out" / "fig6a.provenance.json").read_text())
    assert prov["source"] == "run" and prov["runs_used"] == prov["runs_total"] == 2
    assert prov["seeds"] == [0, 1] and not prov["partial"] and prov["unfinished"] == []
    hashes = {json.loads((sweep / j / "manifest.json").read_text())["config_hash"] for j in "01"}
    assert set(prov["config_hashes"]) == hashes
    assert "seed=0,1" in prov["sweeps"][0]["command"] and prov["runs"][0]["command"]
    assert [len(r["launches"]) for r in prov["runs"]] == [1, 1]  # from each job's cobel.log


def test_an_unfinished_run_is_named_and_never_averaged(sweep, tmp_path, monkeypatch, capsys):
    """A run stopped mid-way (its checkpoint kept): the import refuses and writes nothing;
    with --finished-only it uses the finished runs, as *_partial tables saying so."""
    from tests.test_resume import FAST, stop_at

    stopped = tmp_path / "stopped"
    with monkeypatch.context() as m:
        stop_at(m, 2)
        with pytest.raises(KeyboardInterrupt):
            runner.run(api.compose(None, [*FIG6A_TINY, "seed=7", *FAST]), stopped)
    before = tree(stopped)
    out = tmp_path / "out"
    with pytest.raises(
        CobelError,
        match=r"1 of 3 runs are not finished: .*stopped "
        r"\(interrupted, trial \d+\).*--finished-only to use the 2 finished",
    ):
        run_import.import_runs("fig6a", [sweep, stopped], out_dir=out)
    assert not out.exists()
    written = run_import.import_runs("fig6a", [sweep, stopped], out_dir=out, finished_only=True)
    assert sorted(p.name for p in written) == ["fig6a_partial.csv", "fig6a_runs_partial.csv"]
    assert tree(stopped) == before
    assert (
        "1 of 3 runs are not finished; the means are over the 2 finished" in capsys.readouterr().err
    )
    assert pd.read_csv(out / "fig6a_runs_partial.csv")["seed"].tolist() == [0, 1]
    prov = json.loads((out / "fig6a_partial.provenance.json").read_text())
    assert (prov["runs_used"], prov["runs_total"], prov["partial"]) == (2, 3, True)
    (left,) = prov["unfinished"]
    assert left["seed"] == 7 and left["status"] == "interrupted" and 0 < left["last_trial"] < 200
    assert prov["seeds"] == [0, 1]


def test_fig6a_paper_tables_have_their_own_names_and_tasks_are_checked(sweep, tmp_path):
    """The paper scale's import writes fig6a_paper tables (the same reduction), never the CPU
    default's fig6a ones; a run of the paper's task given to fig6a is refused, naming the
    figure it belongs to, before anything is written."""
    import shutil

    written = run_import.import_runs("fig6a_paper", [sweep], out_dir=tmp_path / "paper")
    assert sorted(p.name for p in written) == ["fig6a_paper.csv", "fig6a_paper_runs.csv"]
    run_import.import_runs("fig6a", [sweep], out_dir=tmp_path / "cpu")
    for table in ("", "_runs"):
        pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "paper" / f"fig6a_paper{table}.csv"),
                                      pd.read_csv(tmp_path / "cpu" / f"fig6a{table}.csv"))  # fmt: skip
    prov = json.loads((tmp_path / "paper" / "fig6a_paper.provenance.json").read_text())
    assert prov["table"] == "fig6a_paper" and prov["command"].startswith(
        "python -m cobelrun.figures.data fig6a_paper --runs"
    )
    paper_run = tmp_path / "paper_run"
    shutil.copytree(sweep / "0", paper_run)
    manifest = json.loads((paper_run / "manifest.json").read_text())
    (paper_run / "manifest.json").write_text(
        json.dumps({**manifest, "task": "tmaze_extinction_3d_paper"})
    )
    out = tmp_path / "out"
    with pytest.raises(CobelError, match=r"task=tmaze_extinction_3d_paper, not of fig6a's tasks "
                       r"\(tmaze_extinction, tmaze_extinction_3d\); these are fig6a_paper's runs"):  # fmt: skip
        run_import.import_runs("fig6a", [sweep, paper_run], out_dir=out)
    assert not out.exists()
    assert run_import.import_runs("fig6a_paper", [paper_run], out_dir=out)


def test_cli_errors_are_one_line(tmp_path, capsys):
    assert data.main(["fig6c", "--runs", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert "no run import for figure 'fig6c'" in capsys.readouterr().err
    assert data.main(["fig8", "--runs", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 2
    assert "no such folder" in capsys.readouterr().err
    assert data.main(["fig8", "--runs", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert "neither a sweep folder" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_a_folder_of_sweeps_names_them(sweep, tmp_path):
    """A figure's sweeps folder (figures/sweeps/NAME, one sweep per label) is not a sweep: the
    error names the sweeps inside to give instead."""
    with pytest.raises(CobelError, match=rf"holds the sweeps {sweep.name} .*--runs {sweep}$"):
        run_import.import_runs("fig6a", [sweep.parent], out_dir=tmp_path / "o")


def test_a_run_given_twice_is_refused(sweep, tmp_path):
    """A sweep and one of its jobs (or one folder twice) would count that run twice in every
    mean: refused in one line, nothing written."""
    for paths in ([sweep, sweep / "0"], [sweep / "1", sweep / "1"]):
        with pytest.raises(CobelError, match=r"run folder .* is given twice"):
            run_import.import_runs("fig6a", paths, out_dir=tmp_path / "o")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("flag", [["--quick"], ["--labels", "dqn"], ["--no-build"]])
def test_export_flags_are_refused_with_runs(sweep, tmp_path, capsys, flag):
    """--quick (or --labels, --no-build) with --runs would be ignored: a quick sweep's runs would
    write fig6a.csv, the full table's name; refused in one line, nothing written."""
    assert data.main(["fig6a", "--runs", str(sweep), *flag, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert f"{flag[0]} cannot be combined with --runs" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "o").exists()


def test_fig8_trend_counts_dead_layers_against_the_rise():
    trials = [0, 800, 1600, 2400]
    counts = {1: [0, 2, 5, 9], 2: [0, 1, 1, 3], 3: [3, 2, 1, 0], 4: [0, 0, 0, 0]}  # 4: dead
    per_run = pd.DataFrame([{"seed": s, "trial": t, "place_cells": c}
                            for s, cs in counts.items() for t, c in zip(trials, cs, strict=True)])  # fmt: skip
    trend = data.fig8_trend(per_run)
    rhos = [stats.spearmanr(trials, counts[s]).statistic for s in (1, 2, 3)] + [0.0]
    assert trend["runs_trend_test"] == 4 and trend["runs_rising"] == 2
    assert trend["median_run_rho"] == pytest.approx(np.median(rhos), abs=1e-4)
    assert trend["sign_test_p"] == pytest.approx(stats.binomtest(2, 4, alternative="greater").pvalue,
                                                 abs=1e-4)  # fmt: skip
    want = stats.wilcoxon(rhos, zero_method="zsplit", alternative="greater").pvalue
    assert trend["wilcoxon_p"] == pytest.approx(want, abs=1e-4)
    # an unfinished run's rows are listed but not averaged
    more = per_run.assign(complete=True)
    more = pd.concat([more, pd.DataFrame({"seed": [9], "trial": [0], "place_cells": [40],
                                          "complete": [False]})])  # fmt: skip
    summary = data.fig8_summary(more).set_index("trial")
    assert summary.loc[0, "runs"] == 4 and summary.loc[0, "mean"] == pytest.approx(0.75)
    assert summary.loc[2400, "mean"] == pytest.approx(np.mean([9, 3, 0, 0]))


@pytest.mark.slow
def test_fig8_runs_from_real_runs(cli, tmp_path):  # noqa: F811 (fixture)
    """Two tiny Fig. 8 runs (the original's task, 4 trials, maps every 2 on a 3 x 3 grid):
    the per-snapshot counts are the classifier's on the run's own maps."""
    from cobelrun.analysis.maps import classify_snapshots, load_activity_maps
    from cobelrun.analysis.place_cells import PlaceCellCriterion

    tiny = ["task=place_cells_original", "task.protocol.phases=[{name: training, trials: 4}]",
            "task.protocol.max_steps=12", "agent.learning_starts=8", "agent.batch_size=8",
            "task.monitors.maps.grid=[3,3]", "task.monitors.maps.headings=2",
            "task.monitors.maps.every=2", "task.record.steps=false", "task.runs=1"]  # fmt: skip
    out = cli("run", "-m", *tiny, "seed=0,1", f"hydra.sweep.dir={tmp_path / 'sweep'}")
    assert out.returncode == 0, out.stdout + out.stderr
    assert data.main(["fig8", "--runs", str(tmp_path / "sweep"), "--out", str(tmp_path / "o")]) == 0
    per_run = pd.read_csv(tmp_path / "o" / "fig8_runs.csv")
    assert per_run["trial"].tolist() == [0, 2, 4, 0, 2, 4] and per_run["complete"].all()
    assert (per_run["last_trial"] == 4).all() and (per_run["units"] == 50).all()
    for seed, rows in per_run.groupby("seed"):
        df, grid = load_activity_maps(tmp_path / "sweep" / str(seed))
        units, snaps = classify_snapshots(
            df, grid, criterion=PlaceCellCriterion(box_measure="area"), rsa=False
        )
        assert rows["place_cells"].tolist() == snaps["place_cells"].tolist()
        live = units[[c for c in units if c.startswith("n_blobs_")]].gt(0).any(axis=1)
        assert rows["live_units"].tolist() == live.groupby(units["trial"]).sum().tolist()
    summary = pd.read_csv(tmp_path / "o" / "fig8.csv")
    assert summary["runs"].tolist() == [2, 2, 2]
    np.testing.assert_allclose(summary["mean"], per_run.groupby("trial")["place_cells"].mean())
    prov = json.loads((tmp_path / "o" / "fig8.provenance.json").read_text())
    assert (
        prov["runs_used"] == 2
        and prov["cpu_time_s"] > 0
        and os.path.isabs(prov["runs"][0]["run_dir"])
    )


def maps_folder(path: Path, place_cells_at: dict[int, int], units: int = 8, bands: int = 0) -> None:
    """Activity maps of Fig. 8's probe grid in which, at trial t, the first
    ``place_cells_at[t]`` units have one Gaussian field (the same at every heading), the next
    ``bands`` a thin band along x across the grid (small in area, wide in extent), and the
    others uniform noise (as tests/test_fig8.py's folders, built in one go)."""
    from cobelrun.analysis.maps import GRID_TABLE, MAPS_TABLE, probe_grid
    from cobelrun.envs import topology as topo

    rng = np.random.default_rng(0)
    grid = probe_grid(topo.hexagonal().positions)
    iy, ix = np.nonzero(grid.inside)
    heads = np.arange(6) * 60.0
    frames = []
    for trial, n_cells in place_cells_at.items():
        for u in range(units):
            if u < n_cells:
                cy, cx = rng.uniform(5, 20, 2)
                field = np.exp(-((iy - cy) ** 2 + (ix - cx) ** 2) / (2 * 2.0**2))
                values = np.tile(field, len(heads))
            elif u < n_cells + bands:
                cy = rng.uniform(8, 16)
                field = np.exp(-((iy - cy) ** 2) / (2 * 1.0**2))
                values = np.tile(field, len(heads))
            else:
                values = rng.random(len(heads) * len(iy))
            frames.append(pd.DataFrame({
                "run": 0, "trial": trial, "layer": "analysis", "unit": u,
                "heading": np.repeat(heads, len(iy)), "ix": np.tile(ix, len(heads)),
                "iy": np.tile(iy, len(heads)), "x": np.tile(grid.x_centres[ix], len(heads)),
                "y": np.tile(grid.y_centres[iy], len(heads)), "value": values,
            }))  # fmt: skip
    path.mkdir(parents=True)
    pd.concat(frames).to_parquet(path / f"{MAPS_TABLE}.parquet")
    gy, gx = (a.ravel() for a in np.indices((grid.ny, grid.nx)))
    pd.DataFrame({"ix": gx, "iy": gy, "x0": grid.x_edges[gx], "x1": grid.x_edges[gx + 1],
                  "y0": grid.y_edges[gy], "y1": grid.y_edges[gy + 1],
                  "explored": grid.inside.ravel()}).to_parquet(path / f"{GRID_TABLE}.parquet")  # fmt: skip


def test_fig8_lists_unfinished_runs_without_averaging_them(tmp_path, capsys):
    """A Fig. 8 run still going (activity maps with 0, 3 and 6 place cells so far, its
    manifest saying ``running``): refused without --finished-only; with it, the per-run table
    lists its snapshots (``complete`` false) and no summary is written."""
    run = tmp_path / "run"
    maps_folder(run, {0: 0, 800: 3, 1600: 6})
    (run / "manifest.json").write_text(json.dumps({"status": "running", "seed": 3}))
    before = tree(run)
    with pytest.raises(CobelError, match=r"1 of 1 runs are not finished: .*\(running\)"):
        run_import.import_runs("fig8", [run], out_dir=tmp_path / "out")
    written = run_import.import_runs("fig8", [run], out_dir=tmp_path / "out", finished_only=True)
    assert [p.name for p in written] == ["fig8_runs_partial.csv"] and tree(run) == before
    listed = pd.read_csv(written[0])
    assert listed["place_cells"].tolist() == [0, 3, 6] and listed["seed"].tolist() == [3] * 3
    assert not listed["complete"].any() and (listed["live_units"] >= listed["place_cells"]).all()
    assert "no means" in capsys.readouterr().err


def test_fig8_stable_counts_place_cells_as_its_figure_does(tmp_path):
    """fig8 compares the blob's box by area (the original's script), fig8_stable by extent (its
    figure's reading): each import's counts are the classifier's with that setting."""
    from cobelrun.analysis.maps import classify_snapshots, load_activity_maps
    from cobelrun.analysis.place_cells import PlaceCellCriterion

    run = tmp_path / "run"
    maps_folder(run, {0: 0, 800: 3, 1600: 6}, bands=2)
    (run / "manifest.json").write_text(json.dumps({"status": "running", "seed": 3}))
    df, grid = load_activity_maps(run)
    counts = {}
    for name, measure in (("fig8", "area"), ("fig8_stable", "extent")):
        (written,) = run_import.import_runs(
            name, [run], out_dir=tmp_path / name, finished_only=True
        )
        assert written.name == f"{name}_runs_partial.csv"
        _, snaps = classify_snapshots(df, grid, criterion=PlaceCellCriterion(box_measure=measure),
                                      rsa=False)  # fmt: skip
        counts[name] = pd.read_csv(written)["place_cells"].tolist()
        assert counts[name] == snaps["place_cells"].tolist()
    assert counts["fig8"] != counts["fig8_stable"]  # the bands pass by area only


@pytest.mark.parametrize(("name", "task", "owner"), [("fig8", "place_cells", "fig8_stable"),
                                                     ("fig8_stable", "place_cells_original", "fig8")])  # fmt: skip
def test_fig8_and_fig8_stable_refuse_each_others_runs(tmp_path, name, task, owner):
    """fig8 (the original's training) and fig8_stable (cobel's) count place cells differently
    and write different tables: a run of the other figure's task is refused, naming its
    figure, before anything is written (as fig6a and fig6a_paper do)."""
    run = tmp_path / "run"
    maps_folder(run, {0: 0, 800: 3})
    (run / "manifest.json").write_text(json.dumps({"status": "running", "seed": 3, "task": task}))
    out = tmp_path / "out"
    with pytest.raises(
        CobelError, match=rf"task={task}, not of {name}'s tasks .*give {owner} --runs"
    ):
        run_import.import_runs(name, [run], out_dir=out, finished_only=True)
    assert not out.exists()
