"""``cobel figure``: the spec registry, a quick Fig. 6B build, reuse of finished runs."""

from __future__ import annotations

import pandas as pd

from cobelrun.figures.registry import Figure, figures


def test_registry_finds_fig6b_and_specs_are_well_formed():
    known = figures()
    assert "fig6b" in known
    for fig in known.values():
        assert isinstance(fig, Figure) and fig.runs and callable(fig.draw)
        assert fig.source is not None and fig.source.suffix == ".py"


def test_figure_fig6b_quick_writes_png_pdf_csv_and_reuses_runs(cobel, tmp_path):
    proc = cobel("figure", "fig6b", "--quick")
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
    runs = list((out / "runs").iterdir())
    assert len(runs) == 1 and (runs[0] / ".done").is_file()
    stamp = (runs[0] / "trials.parquet").stat().st_mtime_ns
    again = cobel("figure", "fig6b", "--quick")
    assert again.returncode == 0 and "1 reused, 0 to run" in again.stderr
    assert (runs[0] / "trials.parquet").stat().st_mtime_ns == stamp


def test_figure_list_and_unknown_name(cobel):
    listing = cobel("figure", "--list")
    assert listing.returncode == 0 and "fig6b" in listing.stdout
    bad = cobel("figure", "fig6")
    assert bad.returncode == 2 and "unknown figure 'fig6' (did you mean 'fig6b'?)" in bad.stderr


def test_user_experiments_folder_adds_a_figure(cobel, tmp_path):
    (tmp_path / "experiments").mkdir()
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
        " 'task.protocol.phases.1.trials=5']}, draw=draw)\n"
    )
    proc = cobel("figure", "mine")
    assert proc.returncode == 0, proc.stderr
    table = pd.read_csv(tmp_path / "results" / "figures" / "mine.csv")
    assert sorted(table["seed"].unique()) == [1, 2] and len(table) == 20
