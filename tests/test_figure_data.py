"""The committed figure tables agree with each other, and the statistics that compare them are
right: summaries are the means of their per-run tables, derived tables are up to date with
their sources, and two_sample / welch_from_stats match scipy on known samples."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cobelrun.errors import CobelError
from cobelrun.figures import data
from cobelrun.figures.twosample import FIELDS, two_sample, welch_from_stats

DATA = Path(__file__).resolve().parents[1] / "docs" / "figures" / "data"


@pytest.mark.parametrize(("summary", "runs"), [("fig6b", "fig6b_runs"), ("fig9", "fig9_runs"),
                                               ("fig9_seeds", "fig9_seeds_runs")])  # fmt: skip
def test_summaries_are_the_means_of_their_runs(summary, runs):
    means = pd.read_csv(DATA / f"{summary}.csv").set_index("measure")
    per_run = pd.read_csv(DATA / f"{runs}.csv")
    for measure, row in means.iterrows():
        if measure in per_run:
            assert row["runs"] == per_run[measure].count()
            assert row["mean"] == pytest.approx(per_run[measure].mean(), rel=1e-5)


@pytest.mark.parametrize(
    "name",
    [
        pytest.param(n, marks=pytest.mark.slow) if n.endswith("_compare") else n
        for n in data.DERIVED
    ],
)  # the bootstraps of fig6b_compare's and fig9_compare's measures take seconds: slow
def test_derived_tables_are_up_to_date(name):
    source, fn = data.DERIVED[name]
    derived = fn(pd.read_csv(DATA / f"{source}.csv"))
    committed = pd.read_csv(DATA / f"{name}.csv")
    assert list(derived.columns) == list(committed.columns), name
    pd.testing.assert_frame_equal(derived.reset_index(drop=True), committed,
                                  check_dtype=False, rtol=1e-5)  # fmt: skip


def test_fig8_mean_counts_only_the_runs_measured():
    per_run = pd.DataFrame({"seed": [0, 1, 0, 1, 1], "trial": [0, 0, 800, 800, 1600],
                            "place_cells": [0, 0, 0, 4, 8]})  # fmt: skip
    out = data.fig8_summary(per_run).set_index("trial")
    assert out.loc[800, "mean"] == 2 and out.loc[1600, "runs"] == 1
    assert out.loc[1600, "mean"] == 8  # seed 0 not run there: no derived zero


def test_two_sample_matches_scipy():
    from scipy import stats

    rng = np.random.default_rng(1)
    a, b = rng.normal(0, 1, 30), rng.normal(0.8, 2, 25)
    out = two_sample(a, b, seed=3)
    assert list(out) == list(FIELDS)
    welch = stats.ttest_ind(a, b, equal_var=False)
    assert out["welch_p"] == pytest.approx(welch.pvalue)
    assert (out["diff_lo"], out["diff_hi"]) == pytest.approx(tuple(welch.confidence_interval()))
    u = stats.mannwhitneyu(a, b).statistic
    assert out["p_superiority"] == pytest.approx(u / (30 * 25))
    assert out["ps_lo"] <= out["p_superiority"] <= out["ps_hi"]
    assert two_sample(a, b, seed=3) == out  # seeded bootstrap
    same = welch_from_stats(a.mean(), a.std(ddof=1), 30, b.mean(), b.std(ddof=1), 25)
    assert (same["diff_lo"], same["diff_hi"], same["welch_p"]) == pytest.approx(
        (out["diff_lo"], out["diff_hi"], out["welch_p"])
    )


def test_two_sample_constant_samples_and_bad_input():
    out = two_sample([1.0, 1.0, 1.0], [1.0, 1.0])
    assert out["diff"] == 0 and out["welch_p"] == 1.0 and out["p_superiority"] == 0.5
    with pytest.raises(CobelError, match="2 or more finite values"):
        two_sample([1.0], [1.0, 2.0])
    with pytest.raises(CobelError, match="2 or more finite values"):
        two_sample([1.0, np.nan], [1.0, 2.0])


def test_fig9_original_tables_agree_and_feed_the_figure():
    """The original's per-agent blocks and per-trial means (both from
    benchmarks/original_fig9_runs.py) describe the same agents, and the figure's comparison
    line is fig9_compare's two_sample on them."""
    runs, per_trial = data.fig9_original_tables()
    assert (per_trial["agents"] == len(runs)).all() and len(per_trial) == 50
    for lo, hi in ((6, 10), (41, 50)):
        block = per_trial[per_trial["trial"].between(lo, hi)]
        assert block["reward_mean"].mean() == pytest.approx(
            runs[f"reward_{lo}_{hi}"].mean(), abs=1e-5
        )
        assert block["greedy_mean"].mean() == pytest.approx(
            runs[f"greedy_{lo}_{hi}"].mean(), abs=1e-5
        )
    ours = pd.read_csv(DATA / "fig9_runs.csv")
    trials = pd.DataFrame({"run": np.repeat(ours["run"], 5), "trial": np.tile(np.arange(6, 11), len(ours)),
                           "reward": np.repeat(ours["reward_6_10"], 5)})  # fmt: skip
    c = two_sample(ours["reward_6_10"], runs["reward_6_10"])
    assert data.fig9_compare_note(trials, runs) == (
        f"vs original ({len(runs)} agents), trials 6-10: {c['diff']:+.3f} "
        f"[{c['diff_lo']:+.3f}, {c['diff_hi']:+.3f}], P(cobel > orig.) {c['p_superiority']:.2f}"
    )


def test_fig4_medians_are_those_of_its_repetitions():
    """fig4.csv's frame times and ratios are the medians over the repetitions it was made from
    (fig4_repetitions.csv, the two runs' frame_times.csv)."""
    reps = pd.read_csv(DATA / "fig4_repetitions.csv")
    assert reps["rep"].nunique() == 5 and set(reps["clock"]) == {"wall"}
    med = reps.groupby(["agent", "height", "width", "mode"])["frame_ms_mean"].median()
    fig4 = pd.read_csv(DATA / "fig4.csv").set_index("size")
    for (agent, h, w, mode), value in med.items():
        col = f"{agent}_{'norender' if mode == 'none' else mode}_ms"
        assert fig4.loc[f"{h}x{w}", col] == pytest.approx(value, rel=1e-5), (agent, h, w, mode)
    for agent in ("mfec", "dqn"):
        ratio = med.xs(agent).unstack("mode")
        ratio = ratio["offline"] / ratio["online"]
        for (h, w), value in ratio.items():
            assert fig4.loc[f"{h}x{w}", f"{agent}_offline_over_online"] == pytest.approx(
                value, rel=1e-4
            )
    steps = reps.groupby("agent")["steps"].max()
    assert (fig4["mfec_steps_per_repetition"] == steps["mfec"]).all()
    assert (fig4["dqn_steps_per_repetition"] == steps["dqn"]).all()
