"""``cobel figure``: the spec registry, a quick Fig. 6B build, reuse of finished runs."""

from __future__ import annotations

import os

import pandas as pd

from cobelrun.figures.registry import Figure, figures
from tests import inprocess

cli = inprocess.cli  # fixture: cobel in this process (figures run their sweeps in it too)


def job_dirs(figures_dir, stem: str) -> list:
    """The run folders of a figure's sweeps (``figures/sweeps/STEM/<label>/<job>``)."""
    return sorted(p for p in figures_dir.glob(f"sweeps/{stem}/*/*") if p.name.isdigit())


def test_registry_finds_fig6b_and_specs_are_well_formed():
    known = figures()
    assert "fig6b" in known
    for fig in known.values():
        assert isinstance(fig, Figure) and fig.runs and callable(fig.draw)
        assert fig.source is not None and fig.source.suffix == ".py"


def test_figure_fig6b_quick_writes_png_pdf_csv_and_reuses_runs(cli, tmp_path):
    proc = cli("figure", "fig6b", "--quick")
    assert proc.returncode == 0, proc.stderr
    out = tmp_path / "results" / "figures"
    for suffix in ("png", "pdf", "csv"):
        f = out / f"fig6b_quick.{suffix}"
        assert f.is_file() and f.stat().st_size > 1000, f
    assert (out / "fig6b_quick.pdf").read_bytes().startswith(b"%PDF")
    table = pd.read_csv(out / "fig6b_quick.csv")
    assert len(table) == 200 and table["runs"].eq(5).all()
    assert {"trial", "phase", "cumulative_response_mean", "latency_mean"} <= set(table.columns)
    # learnt before the switch: nearly every trial ends in the right arm
    before = table.set_index("trial")["cumulative_response_mean"]
    assert before[100] - before[50] > 45
    runs = job_dirs(out, "fig6b_quick")  # its runs are a `cobel run -m` sweep of its overrides
    assert len(runs) == 1 and (runs[0] / ".done").is_file()
    assert (runs[0].parent / "sweep.json").is_file() and "1 of 1 jobs done" in proc.stderr
    stamp = (runs[0] / "trials.parquet").stat().st_mtime_ns
    again = cli("figure", "fig6b", "--quick")
    assert again.returncode == 0 and "1 reused, 0 to run" in again.stderr
    assert (runs[0] / "trials.parquet").stat().st_mtime_ns == stamp


def test_figure_from_takes_the_finished_runs_of_a_sweep(cli, tmp_path):
    """`cobel figure NAME --from SWEEP`: the jobs of a `cobel run -m` of the figure's overrides
    (e.g. run in parallel or on a cluster) are copied into the run store by config hash, so the
    figure runs nothing itself and draws the same table as from its own runs."""
    sweep = tmp_path / "sweep"
    quick = ["task=tmaze_extinction", "task.runs=5", "task.record.steps=false",
             "task.record.mcap=false"]  # fmt: skip
    proc = cli("run", "-m", *quick, "seed=0", "hydra/launcher=basic", f"hydra.sweep.dir={sweep}")
    assert proc.returncode == 0, proc.stderr
    proc = cli("figure", "fig6b", "--quick", "--from", str(sweep), "--out", str(tmp_path / "a"))
    assert proc.returncode == 0, proc.stderr
    assert "1 runs taken from" in proc.stderr and "1 reused, 0 to run" in proc.stderr
    own = cli("figure", "fig6b", "--quick", "--out", str(tmp_path / "b"),
                env={"COBEL_RESULTS": str(tmp_path / "own")})  # fmt: skip
    assert own.returncode == 0 and "0 reused, 1 to run" in own.stderr
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "a" / "fig6b_quick.csv"),
                                  pd.read_csv(tmp_path / "b" / "fig6b_quick.csv"))  # fmt: skip
    bad = cli("figure", "fig6b", "--quick", "--from", str(tmp_path / "nope"))
    assert bad.returncode != 0
    assert "no such folder" in bad.stderr and "Traceback" not in bad.stderr


def test_figure_list_and_unknown_name(cli):
    listing = cli("figure", "--list")
    assert listing.returncode == 0 and "fig6b" in listing.stdout
    bad = cli("figure", "fig6")
    assert bad.returncode == 2 and "unknown figure 'fig6' (did you mean 'fig6b'?)" in bad.stderr


def write_mine(tmp_path, jobs=1):
    """A user figure in ./experiments: two jobs (seeds 1 and 2) of a short T-maze run."""
    (tmp_path / "experiments").mkdir(exist_ok=True)
    (tmp_path / "experiments" / "mine.py").write_text(
        "import pandas as pd\n"
        "from cobelrun.figures.registry import Figure\n"
        "def draw(data):\n"
        "    import matplotlib.pyplot as plt\n"
        "    t = data.trials('a')\n"
        "    fig, ax = plt.subplots()\n"
        "    m = t.groupby(['seed', 'trial'])['steps'].mean().reset_index()\n"
        "    ax.plot(m['trial'], m['steps'])\n"
        "    return fig, m\n"
        "FIGURE = Figure(name='mine', title='mine', runs={'a': ['task=tmaze_extinction',"
        " 'seed=1,2', 'task.runs=1', 'task.protocol.phases.0.trials=5',"
        f" 'task.protocol.phases.1.trials=5']}}, draw=draw, jobs={jobs})\n"
    )


def test_user_experiments_folder_adds_a_figure(cli, tmp_path):
    write_mine(tmp_path)
    proc = cli("figure", "mine")
    assert proc.returncode == 0, proc.stderr
    table = pd.read_csv(tmp_path / "results" / "figures" / "mine.csv")
    assert sorted(table["seed"].unique()) == [1, 2] and len(table) == 20


def test_figure_jobs_runs_in_parallel_processes_with_the_same_tables(cli, tmp_path):
    """`cobel figure --jobs 2` (or a figure's own ``jobs=0``: one process per core): the two
    runs go through Hydra's joblib launcher as `cobel run -m` does, in two worker processes,
    and give the same CSV as one after another (the basic launcher); a bad --jobs is one
    line."""
    write_mine(tmp_path)
    seq = cli("figure", "mine", "--out", str(tmp_path / "seq"))
    assert seq.returncode == 0, seq.stderr
    assert "hydra/launcher=basic" in seq.stderr
    par = cli("figure", "mine", "--jobs", "2", "--out", str(tmp_path / "par"),
                env={"COBEL_RESULTS": str(tmp_path / "par_results")})  # fmt: skip
    assert par.returncode == 0, par.stderr
    assert "2 runs to run" in par.stderr and "hydra.launcher.n_jobs=2" in par.stderr
    assert "2 of 2 jobs done" in par.stderr
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "seq" / "mine.csv"),
                                  pd.read_csv(tmp_path / "par" / "mine.csv"))  # fmt: skip
    runs = job_dirs(tmp_path / "par_results" / "figures", "mine")
    assert len(runs) == 2 and all((r / ".done").is_file() for r in runs)
    write_mine(tmp_path, jobs=0)  # the figure's default: one process per core (2 runs: 2 here)
    own = cli("figure", "mine", "--out", str(tmp_path / "own"),
                env={"COBEL_RESULTS": str(tmp_path / "own_results")})  # fmt: skip
    assert own.returncode == 0, own.stderr
    assert f"hydra.launcher.n_jobs={min(2, os.cpu_count() or 1)}" in own.stderr or (
        os.cpu_count() == 1 and "hydra/launcher=basic" in own.stderr
    )
    bad = cli("figure", "mine", "--jobs", "0")
    assert bad.returncode != 0 and "--jobs 0: give 1 or more" in bad.stderr
    assert "Traceback" not in bad.stderr


def test_figure_finished_only_draws_what_is_done_and_runs_nothing(cli, tmp_path):
    """`cobel figure NAME --finished-only`: the figure from the runs already finished (here one
    job taken from a sweep), to NAME_partial.*, naming the runs left out; nothing finished is
    one line."""
    write_mine(tmp_path)
    none = cli("figure", "mine", "--finished-only")
    assert none.returncode != 0 and "Traceback" not in none.stderr
    assert "mine: no finished run for 'a' to draw" in none.stderr
    sweep = tmp_path / "sweep"
    one = ["task=tmaze_extinction", "seed=1", "task.runs=1", "task.protocol.phases.0.trials=5",
           "task.protocol.phases.1.trials=5"]  # fmt: skip
    proc = cli("run", "-m", *one, "hydra/launcher=basic", f"hydra.sweep.dir={sweep}")
    assert proc.returncode == 0, proc.stderr
    part = cli("figure", "mine", "--finished-only", "--from", str(sweep))
    assert part.returncode == 0, part.stderr
    assert (
        "drawing the 1 finished of 2 runs, running nothing; not finished: a job 1 (seed=2)"
        in part.stderr
    )
    out = tmp_path / "results" / "figures"
    table = pd.read_csv(out / "mine_partial.csv")
    assert table["seed"].unique().tolist() == [1] and not (out / "mine.csv").exists()
    assert len(job_dirs(out, "mine")) == 1  # the missing run was not started


def test_figure_fig7_quick_writes_latency_and_sr_panels(cli, tmp_path):
    proc = cli("figure", "fig7", "--quick")
    assert proc.returncode == 0, proc.stderr
    out = tmp_path / "results" / "figures"
    for suffix in ("png", "pdf", "csv"):
        f = out / f"fig7_quick.{suffix}"
        assert f.is_file() and f.stat().st_size > 1000, f
    table = pd.read_csv(out / "fig7_quick.csv")
    b, c = table[table["panel"] == "7B"], table[table["panel"] == "7C"]
    # 7B: latent trials -10..9 (exploration negative), direct 0..9, aligned on the first reward
    assert sorted(b.loc[b["series"] == "latent", "trial"]) == list(range(-10, 10))
    assert sorted(b.loc[b["series"] == "direct", "trial"]) == list(range(10))
    assert (b["runs"] == 2).all() and (b["mean"] >= 1).all()
    # 7C: SR of the start state over the 40 maze states at the end of exploration and the end
    assert set(c["series"]) == {"end of exploration", "end of training"}
    assert len(c) == 2 * 40 and set(c["trial"]) == {10, 20}
    # the two folders drawn together by `cobel plot LATENT_DIR DIRECT_DIR`
    runs = job_dirs(out, "fig7_quick")
    assert len(runs) == 2
    plot = cli("plot", *map(str, runs), "-o", str(tmp_path / "fig7.png"))
    assert plot.returncode == 0, plot.stderr
    assert (tmp_path / "fig7.png").stat().st_size > 1000
    twice = cli("plot", str(runs[0]), str(runs[0]))
    assert twice.returncode == 2 and "give one of each" in twice.stderr


def test_figure_fig9_quick_writes_reward_and_greedy_probe(cli, tmp_path):
    proc = cli("figure", "fig9", "--quick")
    assert proc.returncode == 0, proc.stderr
    out = tmp_path / "results" / "figures"
    for suffix in ("png", "pdf", "csv"):
        f = out / f"fig9_quick.{suffix}"
        assert f.is_file() and f.stat().st_size > 1000, f
    table = pd.read_csv(out / "fig9_quick.csv")
    assert len(table) == 50 and table["runs"].eq(10).all()
    assert {"reward_mean", "reward_sem", "greedy_correct_mean", "greedy_correct_sem"} <= set(
        table.columns
    )
    assert table["greedy_correct_mean"].between(0, 1).all()
    assert table["greedy_correct_mean"].iloc[-10:].mean() >= 0.8


def test_runs_taken_from_elsewhere_are_plain_folders(tmp_path, monkeypatch):
    """A finished run found by config hash (--from, another figure's sweeps) is copied into the
    figure's sweep only when it holds plain files: a link inside it could bring any file of
    the machine into the results (the run is made again instead)."""
    from cobelrun.figures import registry

    src = tmp_path / "elsewhere" / "run"
    src.mkdir(parents=True)
    (src / "trials.parquet").write_bytes(b"PAR1")
    monkeypatch.setattr(registry, "finished_runs", lambda folders: {"abc": src})
    planned = registry._Planned("a", 0, [], {}, None, "abc", tmp_path / "sweep" / "0")
    assert registry.import_runs([planned], [tmp_path / "elsewhere"]) == 1  # plain: copied
    assert (tmp_path / "sweep" / "0" / "trials.parquet").read_bytes() == b"PAR1"
    (src / "secret").symlink_to("/etc/hostname")
    other = registry._Planned("a", 1, [], {}, None, "abc", tmp_path / "sweep" / "1")
    assert registry.import_runs([other], [tmp_path / "elsewhere"]) == 0  # a link: not copied
    assert not (tmp_path / "sweep" / "1").exists()
