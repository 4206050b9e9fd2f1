"""Figures as data: each figure's summary table as a small CSV with a provenance sidecar.

``python -m cobelrun.figures.data NAME [--quick] [--out DIR]`` builds figure ``NAME`` as
``cobel figure NAME`` does (finished runs are reused by config hash), then reduces the figure's
runs to the tables the docs quote and writes, per table, ``DIR/TABLE.csv`` and
``DIR/TABLE.provenance.json`` (default ``DIR``: ``docs/figures/data`` of the source checkout).

A sidecar holds what made the table: the command, the figure's runs (label, job, seed, config
hash, run folder name), the cobel commit and whether the tree was dirty (from the runs'
manifests), the machine, the date and the runs' wall time. Tables that could not be run again
here (e.g. Fig. 8's 6000-trial runs) are transcribed by hand from the docs that recorded them;
their sidecars say ``"source": "transcribed"`` and name the doc and the original run.

The reductions (``SUMMARIES``) are per figure: a function ``FigureData -> {table name: frame}``;
every table also gets a ``quick`` flag in its sidecar, and ``--quick`` tables are written with a
``_quick`` suffix (``tests/test_figure_data_quick.py`` compares their columns with the
committed tables').

``python -m cobelrun.figures.data NAME --runs SWEEP_DIR [--finished-only]`` reads the runs of a
long sweep (Fig. 6A at the paper's scale, Fig. 8's 10 runs) from its folders, also while it
runs, without writing to them: :mod:`cobelrun.figures.run_import`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cobelrun.errors import CobelError, allowed_list, suggest
from cobelrun.figures import registry
from cobelrun.figures.tables import fig8_summary, fig8_trend, write_table  # noqa: F401 (re-exported)

#: the committed tables, beside the figure pages
DATA_DIR = Path(__file__).resolve().parents[2] / "docs" / "figures" / "data"

Summary = Callable[[registry.FigureData], dict[str, pd.DataFrame]]


# -- reductions per figure --------------------------------------------------------------------


def _block_mean(trials: pd.DataFrame, column: str, lo: int, hi: int) -> pd.Series:
    """Per run: mean of ``column`` over trials ``lo``..``hi`` (trials count from 1)."""
    rows = trials[trials["trial"].between(lo, hi)]
    return rows.groupby("run")[column].mean()


#: Fig. 6B's per-run measures (as ``fig6b_runs.csv`` and the original's
#: ``fig6b_original_runs.csv``): right-arm rate and latency per block, cumulative responses
FIG6B_RIGHT_BLOCKS = ((91, 100), (101, 110), (111, 120), (191, 200))
FIG6B_LATENCY_BLOCKS = ((11, 20), (21, 30), (91, 100), (191, 200))
FIG6B_CUMULATIVE_AT = (100, 200)


def fig6b_per_run(trials: pd.DataFrame) -> pd.DataFrame:
    """Fig. 6B per run (``run``) of a trials table: right-arm response rate and escape latency
    per block of trials, and the cumulative responses at trials 100 and 200."""
    per_run = pd.DataFrame({"run": np.sort(trials["run"].unique())}).set_index("run")
    for lo, hi in FIG6B_RIGHT_BLOCKS:
        per_run[f"right_{lo}_{hi}"] = _block_mean(trials, "response", lo, hi)
    for t in FIG6B_CUMULATIVE_AT:
        per_run[f"cumulative_{t}"] = trials[trials["trial"] == t].set_index("run")[
            "cumulative_response"
        ]
    for lo, hi in FIG6B_LATENCY_BLOCKS:
        per_run[f"latency_{lo}_{hi}"] = _block_mean(trials, "steps", lo, hi)
    return per_run.reset_index()


def summary_fig6b(data: registry.FigureData) -> dict[str, pd.DataFrame]:
    """Fig. 6B per run (:func:`fig6b_per_run`) and the means over the runs, with the first
    trial at which the mean latency is at most 10 steps."""
    from cobelrun.figures.extinction import summarize

    trials = data.trials("dyna_q")
    per_run = fig6b_per_run(trials)
    lat = summarize(trials, "steps")["mean"]
    first10 = int(lat.index[lat.to_numpy() <= 10][0]) if (lat <= 10).any() else -1
    summary = _means(per_run, extra={"first_trial_mean_latency_le_10": first10})
    return {"fig6b_runs": per_run, "fig6b": summary}


def summary_morris(data: registry.FigureData) -> dict[str, pd.DataFrame]:
    """Water maze: per run and day the mean latency and path length (acquisition and
    reversal), per run the probe's quadrant occupancy, and the figure's own daily means."""
    from cobelrun.analysis.watermaze import QUADRANTS, add_days
    from cobelrun.figures.watermaze import CURVE_PHASES, daily_summary, probe_quadrants

    trials = data.trials("actor_critic")
    days = add_days(trials[trials["phase"].isin(CURVE_PHASES)], 4)
    per_run = (
        days.groupby(["phase", "day", "run"], sort=False)[["escape_latency_s", "path_length"]]
        .mean()
        .reset_index()
    )
    probe = trials[trials["phase"] == "probe"]
    cols = {f"{q}_quadrant_fraction": q for q in QUADRANTS}
    per_run_probe = probe.groupby("run")[list(cols)].mean().rename(columns=cols).reset_index()
    daily = daily_summary(trials)
    return {"morris_runs": per_run, "morris_probe_runs": per_run_probe, "morris": daily,
            "morris_probe": probe_quadrants(trials)}  # fmt: skip


def summary_fig7(data: registry.FigureData) -> dict[str, pd.DataFrame]:
    """Fig. 7 per run: latency over the first 10 and the last 10 rewarded trials (both
    groups), the spread of the start state's SR (latent group) at the end of exploration and
    at the end; and the latent-vs-direct comparison (:func:`two_sample`)."""
    from cobelrun.figures.latent import world_of
    from cobelrun.figures.latent_stats import per_run_latency, runs_as_jobs, sr_spread
    from cobelrun.figures.twosample import two_sample

    one_per_job = all(len(data.runs[g]) > 1 for g in ("latent", "direct"))
    fix = runs_as_jobs if one_per_job else (lambda t: t)
    frames = []
    for g in ("latent", "direct"):
        frames.append(per_run_latency(fix(data.trials(g))).assign(group=g))
    per_run = pd.concat(frames, ignore_index=True)
    activity = fix(data.activity("latent"))
    world = world_of(data.run_dirs("latent")[0])
    trials = fix(data.trials("latent"))
    explore_end = int(trials.loc[trials["phase"] != "rewarded", "trial"].max())
    snaps = np.sort(activity["trial"].unique())
    sr = []
    for label, t in (("end of exploration", explore_end), ("end", int(trials["trial"].max()))):
        snap = int(snaps[snaps <= t].max())
        sr.append(sr_spread(activity, world, snap).assign(snapshot=label))
    lat, dire = (per_run.loc[per_run["group"] == g, "first10"] for g in ("latent", "direct"))
    comparison = pd.DataFrame(
        [{"measure": "first10", "a": "latent", "b": "direct", "test": "independent",
          **two_sample(lat, dire)}]
    )  # fmt: skip
    spread = pd.concat(sr, ignore_index=True)
    comparison = pd.concat([comparison, pd.DataFrame([paired_sr(spread)])], ignore_index=True)
    means = pd.concat(
        [
            per_run.groupby("group", sort=False)[["first10", "last10"]].agg(["count", "mean"]),
            spread.groupby("snapshot", sort=False)[["mean_distance", "goal_over_start"]].agg(
                ["count", "mean"]
            ),
        ]
    )
    means.columns = [f"{a}_{b}" for a, b in means.columns]
    means = means.reset_index(names="series")
    return {"fig7_runs": per_run, "fig7_sr": spread, "fig7_compare": comparison, "fig7": means}


def summary_pma(data: registry.FigureData) -> dict[str, pd.DataFrame]:
    """Mattar & Daw: per agent and run the first episode within 20 % of the 14-step path; PMA's
    replay events of >= 5 experiences per ``when`` x direction (all runs); and the figure's
    own table (median steps per trial, event rates)."""
    from cobelrun.analysis.replay import direction_counts, replay_events
    from cobelrun.results import load_table

    shortest = 14
    rows = []
    for label in ("pma", "dyna_q", "q_learning"):
        trials = data.trials(label)
        for run, g in trials.groupby("run"):
            ok = g.loc[g["steps"] <= 1.2 * shortest, "trial"]
            rows.append({"agent": label, "run": int(run),
                         "criterion_trial": int(ok.min()) if len(ok) else -1})  # fmt: skip
    per_run = pd.DataFrame(rows)
    agg = per_run.groupby("agent", sort=False)["criterion_trial"]
    criterion = pd.DataFrame({"median": agg.median(), "mean": agg.mean()}).reset_index()
    pma = data.trials("pma")
    late = pma[pma["trial"] >= 3].groupby("trial")["steps"].median()
    criterion["median_steps_from_trial_3"] = np.where(
        criterion["agent"] == "pma", float(late.median()), np.nan
    )
    replays = pd.concat([load_table(d, "replays") for d in data.run_dirs("pma")])
    counts = direction_counts(replay_events(replays), 5).reset_index(names="when")
    return {"pma_runs": per_run, "pma_criterion": criterion, "pma_events": counts,
            "pma": figure_table("pma")(data)["pma"]}  # fmt: skip


def summary_revaluation(data: registry.FigureData) -> dict[str, pd.DataFrame]:
    """Russek et al.: per design, agent, budget and run the greedy choice before and after
    (each run's ``revaluation.csv``), and the scores (``revaluation_scores.csv``), for the
    designs built: the graph ones as ``revaluation_runs`` and ``revaluation`` (``--labels
    reward,transition,policy``), the grid ones (labels ``*_grid``) as ``revaluation_grid_runs``
    and ``revaluation_grid``, so that building one never replaces the other's tables."""
    tables: dict[str, pd.DataFrame] = {}
    for stem, grid in (("revaluation", False), ("revaluation_grid", True)):
        labels = [x for x in data.runs if x.endswith("_grid") == grid]
        runs, scores = [], []
        for label in labels:
            for d in data.run_dirs(label):
                runs.append(pd.read_csv(d / "revaluation.csv").assign(design=label))
                scores.append(pd.read_csv(d / "revaluation_scores.csv").assign(design=label))
        if runs:
            tables[f"{stem}_runs"] = pd.concat(runs, ignore_index=True)
            tables[stem] = pd.concat(scores, ignore_index=True)
    return tables


def summary_fig4(data: registry.FigureData) -> dict[str, pd.DataFrame]:
    """Fig. 4 per image size: each agent's median frame time per mode (online, offline, no
    render) over the repetitions, offline / online and offline / no-render, MFEC's online /
    offline, DQN's saving offline in percent, and the budget (steps per repetition per agent,
    repetitions)."""
    from cobelrun.render.benchmark import load_table, ratios

    table = pd.concat([load_table(ref.run_dir) for refs in data.runs.values() for ref in refs],
                      ignore_index=True)  # fmt: skip
    rat = ratios(table)
    out = pd.DataFrame()
    for agent, g in rat.groupby("agent", sort=False):
        g = g.assign(size=g["height"].astype(str) + "x" + g["width"].astype(str)).set_index("size")
        cols = {"online_ms": "online_ms", "offline_ms": "offline_ms", "none_ms": "norender_ms",
                "offline_over_online": "offline_over_online",
                "offline_over_none": "offline_over_norender"}  # fmt: skip
        part = g[list(cols)].rename(columns={c: f"{agent}_{n}" for c, n in cols.items()})
        out = part if out.empty else out.join(part, how="outer")
    out = out.reset_index()
    pixels = out["size"].str.split("x").map(lambda hw: int(hw[0]) * int(hw[1]))
    out = out.iloc[np.argsort(pixels.to_numpy(), kind="stable")].reset_index(drop=True)
    if "mfec_offline_over_online" in out:
        out["mfec_online_over_offline"] = 1 / out["mfec_offline_over_online"]
    for agent, g in table.groupby("agent", sort=False):
        out[f"{agent}_steps_per_repetition"] = int(g["steps"].max())
    out["repetitions"] = int(table["rep"].nunique())
    if "dqn_offline_over_online" in out:
        out["dqn_offline_saves_pct"] = (1 - out["dqn_offline_over_online"]) * 100
    return {"fig4": out}


def summary_fig9(name: str, per_seed: bool = False) -> Summary:
    """Fig. 9 per agent: mean training reward and greedy choice correct per block of trials
    (1-5, 6-10, 11-20, 21-30, 31-40, 41-50); and the block means over agents (``per_seed``:
    per seed, a row per seed with its number of agents)."""

    def summary(data: registry.FigureData) -> dict[str, pd.DataFrame]:
        trials = data.trials("dqn")
        size = int(trials["run"].max()) + 1
        seeds = [ref.params.get("seed", 0) for ref in data.runs["dqn"]]
        trials = trials.assign(seed=trials["job"].map(dict(enumerate(seeds))),
                               run=trials["job"] * size + trials["run"])  # fmt: skip
        blocks = ((1, 5), (6, 10), (11, 20), (21, 30), (31, 40), (41, 50))
        per_run = trials.groupby("run")[["seed"]].first()
        for lo, hi in blocks:
            per_run[f"reward_{lo}_{hi}"] = _block_mean(trials, "reward", lo, hi)
            if "greedy_correct" in trials:
                per_run[f"greedy_{lo}_{hi}"] = _block_mean(trials, "greedy_correct", lo, hi)
        per_run = per_run.reset_index()
        if per_seed:
            g = per_run.drop(columns="run").groupby("seed")
            means = g.mean().round(6).reset_index()
            means.insert(1, "agents", g.size().to_numpy())
        else:
            means = _means(per_run.drop(columns="seed"))
        return {f"{name}_runs": per_run, name: means}

    return summary


def figure_table(name: str) -> Summary:
    """The figure's own plotted numbers (what ``cobel figure NAME`` writes as ``NAME.csv``)."""

    def summary(data: registry.FigureData) -> dict[str, pd.DataFrame]:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, table = registry.get(name).draw(data)
        plt.close(fig)
        return {name: table}

    return summary


def paired_sr(spread: pd.DataFrame) -> dict[str, Any]:
    """The SR-weighted distance of the start state's SR at the end minus at the end of
    exploration, per run (paired t interval; Wilcoxon signed-rank p)."""
    from scipy import stats

    wide = spread.pivot(index="run", columns="snapshot", values="mean_distance").dropna()
    end, explore = wide["end"], wide["end of exploration"]
    t = stats.ttest_rel(end, explore)
    ci = t.confidence_interval(0.95)
    d = end - explore
    return {"measure": "sr_mean_distance", "a": "end", "b": "end of exploration",
            "test": "paired", "n_a": len(end), "n_b": len(explore),
            "mean_a": float(end.mean()), "mean_b": float(explore.mean()),
            "diff": float(d.mean()), "diff_lo": float(ci.low), "diff_hi": float(ci.high),
            "welch_p": float("nan"), "paired_t_p": float(t.pvalue),
            "wilcoxon_p": float(stats.wilcoxon(end, explore).pvalue) if len(d) > 1 else float("nan"),
            "p_superiority": float((d > 0).mean() + (d == 0).mean() / 2)}  # fmt: skip


def _means(per_run: pd.DataFrame, extra: Mapping[str, float] | None = None) -> pd.DataFrame:
    """Long table ``measure, runs, mean`` of every column but ``run`` (plus ``extra``)."""
    cols = [c for c in per_run.columns if c != "run"]
    rows = [{"measure": c, "runs": int(per_run[c].count()), "mean": float(per_run[c].mean())}
            for c in cols]  # fmt: skip
    for k, v in (extra or {}).items():
        rows.append({"measure": k, "runs": len(per_run), "mean": float(v)})
    return pd.DataFrame(rows)


def summary_from_runs(name: str) -> Summary:
    """The tables :mod:`cobelrun.figures.run_import` writes for ``name`` (``fig6a``, ``fig8``)
    from a long sweep's folders, here from the figure's own runs (every label), so the figure
    path and ``--runs`` give the same tables."""

    def summary(data: registry.FigureData) -> dict[str, pd.DataFrame]:
        from cobelrun.figures import run_import

        runs = [run_import.run_info(ref.run_dir, ref.job, ref.params.get("seed"))
                for refs in data.runs.values() for ref in refs]  # fmt: skip
        return run_import.IMPORTERS[name](runs, runs)

    return summary


SUMMARIES: dict[str, Summary] = {
    "fig4": summary_fig4,
    "fig6a": summary_from_runs("fig6a"),
    "fig6a_paper": summary_from_runs("fig6a_paper"),
    "fig8": summary_from_runs("fig8"),
    "fig8_stable": summary_from_runs("fig8_stable"),
    "fig6b": summary_fig6b,
    "morris": summary_morris,
    "fig7": summary_fig7,
    "fig7_paper": summary_fig7,
    "pma": summary_pma,
    "revaluation": summary_revaluation,
    "fig9": summary_fig9("fig9"),
    "fig9_fast": summary_fig9("fig9_fast"),
    "fig9_seeds": summary_fig9("fig9_seeds"),
    "fig9_fast_seeds": summary_fig9("fig9_fast_seeds", per_seed=True),
}


def fig9_compare(per_run: pd.DataFrame, original: pd.DataFrame) -> pd.DataFrame:
    """cobel's per-agent block means (``fig9_seeds_runs``) against the original's
    (``fig9_original_runs``, CoBeL-RL v2.0.0 + keras-rl2 through
    ``benchmarks/original_fig9_runs.py``), measure by measure (training reward and greedy
    choice correct per block of trials): :func:`~cobelrun.figures.twosample.two_sample`
    (a = cobel, b = the original)."""
    from cobelrun.figures.twosample import two_sample

    rows = []
    for col in (c for c in per_run.columns if c not in ("run", "seed") and c in original):
        rows.append({"measure": col, **two_sample(per_run[col].dropna(), original[col].dropna())})
    return pd.DataFrame(rows)


def fig9_compare_table(per_run: pd.DataFrame) -> pd.DataFrame:
    """:func:`fig9_compare` against the committed ``fig9_original_runs.csv``."""
    return fig9_compare(per_run, pd.read_csv(DATA_DIR / "fig9_original_runs.csv"))


def fig9_original_summary(per_run: pd.DataFrame) -> pd.DataFrame:
    """The original's block means over its agents (``fig9_original_runs``): per block of
    trials the agents, the mean training reward and its standard error, the mean greedy
    choice correct."""
    rows = []
    for col in (c for c in per_run.columns if c.startswith("reward_")):
        lo, hi = col.split("_")[1:]
        r, g = per_run[col], per_run[f"greedy_{lo}_{hi}"]
        rows.append({"trials": f"{lo}-{hi}", "agents": int(r.count()), "reward_mean": r.mean(),
                     "reward_se": r.std(ddof=1) / np.sqrt(r.count()), "greedy_correct": g.mean()})  # fmt: skip
    return pd.DataFrame(rows)


def fig9_original_tables() -> tuple[pd.DataFrame, pd.DataFrame] | None:
    """The original's agents (``fig9_original_runs.csv``: block means per agent) and its means
    per trial (``fig9_original_runs_trials.csv``), from the committed figure data; None where
    they are not there (an installed wheel ships no docs)."""
    runs, per_trial = (
        DATA_DIR / "fig9_original_runs.csv",
        DATA_DIR / "fig9_original_runs_trials.csv",
    )
    if not (runs.is_file() and per_trial.is_file()):
        return None
    return pd.read_csv(runs), pd.read_csv(per_trial)


def fig9_compare_note(
    trials: pd.DataFrame, original: pd.DataFrame, lo: int = 6, hi: int = 10
) -> str:
    """One line: the figure's agents against the original's over trials ``lo``-``hi``."""
    from cobelrun.figures.twosample import two_sample

    ours = trials[trials["trial"].between(lo, hi)].groupby("run")["reward"].mean()
    c = two_sample(ours, original[f"reward_{lo}_{hi}"])
    return (f"vs original ({c['n_b']} agents), trials {lo}-{hi}: {c['diff']:+.3f} "
            f"[{c['diff_lo']:+.3f}, {c['diff_hi']:+.3f}], P(cobel > orig.) {c['p_superiority']:.2f}")  # fmt: skip


def fig6b_original_table() -> pd.DataFrame | None:
    """The original's Fig. 6B runs (``fig6b_original_runs.csv``: CoBeL-RL v2.0.0's Dyna-Q,
    block measures per run) from the committed figure data; None where it is not there (an
    installed wheel ships no docs)."""
    path = DATA_DIR / "fig6b_original_runs.csv"
    return pd.read_csv(path) if path.is_file() else None


def diff_and_superiority(a: pd.Series, b: pd.Series) -> dict[str, float]:
    """The parts of :func:`~cobelrun.figures.twosample.two_sample` a figure shows, without its
    bootstrap (seconds): ``diff`` = mean a - mean b with Welch's 95 % interval (``diff_lo``,
    ``diff_hi``) and the probability of superiority P(a > b) (Mann-Whitney U / n_a n_b)."""
    from scipy import stats

    x, y = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    ci = stats.ttest_ind(x, y, equal_var=False).confidence_interval(0.95)
    u = stats.mannwhitneyu(x, y, alternative="two-sided").statistic
    return {"diff": float(x.mean() - y.mean()), "diff_lo": float(ci.low),
            "diff_hi": float(ci.high), "p_superiority": float(u / (x.size * y.size))}  # fmt: skip


#: the measures Fig. 6B's title compares with the original (column, as shown)
FIG6B_NOTE = (("right_101_110", "right arm 101-110"), ("cumulative_200", "cum. at 200"),
              ("latency_11_20", "latency 11-20"), ("latency_91_100", "91-100"))  # fmt: skip


def fig6b_compare_note(per_run: pd.DataFrame, original: pd.DataFrame) -> str:
    """Three lines: the figure's runs (:func:`fig6b_per_run`) against the original's on
    :data:`FIG6B_NOTE` (:func:`diff_and_superiority`: cobel - original with Welch's 95 %
    interval, P(cobel > original))."""
    parts = []
    for col, what in FIG6B_NOTE:
        c = diff_and_superiority(per_run[col], original[col])
        parts.append(f"{what} {c['diff']:+.3f} [{c['diff_lo']:+.3f}, {c['diff_hi']:+.3f}], "
                     f"P {c['p_superiority']:.2f}")  # fmt: skip
    head = f"vs original ({len(original)} runs): cobel - original [95% CI], P(cobel > orig.)"
    return f"{head}:\n{'; '.join(parts[:2])}\n{'; '.join(parts[2:])}"


def fig6b_compare(per_run: pd.DataFrame) -> pd.DataFrame:
    """cobel's Fig. 6B runs (``fig6b_runs``) against the original's (``fig6b_original_runs``,
    CoBeL-RL v2.0.0's Dyna-Q through ``benchmarks/original_fig6b_runs.py``), measure by
    measure: :func:`~cobelrun.figures.twosample.two_sample` (a = cobel, b = the original)."""
    from cobelrun.figures.twosample import two_sample

    original = fig6b_original_table()
    if original is None:
        raise CobelError(f"fig6b_compare: no {DATA_DIR / 'fig6b_original_runs.csv'}")
    rows = []
    for col in (c for c in per_run.columns if c != "run" and c in original):
        rows.append({"measure": col, **two_sample(per_run[col], original[col])})
    return pd.DataFrame(rows)


#: tables derived from committed ones (transcribed, or two tables compared): name -> (source table, function)
DERIVED: dict[str, tuple[str, Callable[[pd.DataFrame], pd.DataFrame]]] = {
    "fig8": ("fig8_runs", fig8_summary),
    "fig9_compare": ("fig9_seeds_runs", fig9_compare_table),
    "fig9_original": ("fig9_original_runs", fig9_original_summary),
    "fig6b_compare": ("fig6b_runs", fig6b_compare),
}


def derive(out_dir: Path = DATA_DIR) -> list[Path]:
    """Write the tables of :data:`DERIVED` from their committed source tables; the sidecar
    copies the source's provenance and names the derivation."""
    written = []
    for name, (source, fn) in DERIVED.items():
        if not (out_dir / f"{source}.csv").is_file():
            continue
        needs = {
            "fig6b_compare": "fig6b_original_runs.csv",
            "fig9_compare": "fig9_original_runs.csv",
        }
        if name in needs and not (out_dir / needs[name]).is_file():
            continue
        prov = json.loads((out_dir / f"{source}.provenance.json").read_text())
        prov = {**prov, "table": name,
                "derived": f"cobelrun.figures.data.{fn.__name__}({source}.csv)"
                + {"fig9_compare": " and fig9_original_runs.csv (the original, run)",
                   "fig6b_compare": " and fig6b_original_runs.csv (the original, run)"}.get(name, ""),
                "command": "python -m cobelrun.figures.data --derive"}  # fmt: skip
        written.append(write_table(fn(pd.read_csv(out_dir / f"{source}.csv")), prov, out_dir, name))
    return written


def frame_time_ratios(runs: Mapping[str, Path]) -> pd.DataFrame:
    """Fig. 4-style medians from ``render_benchmark`` run folders (label -> folder, e.g.
    ``memo0`` and ``memo4096``): per label, agent and size the median frame time of each
    mode over the repetitions, and offline / online and online / offline."""
    rows = []
    for label, folder in runs.items():
        ft = pd.read_csv(Path(folder) / "frame_times.csv")
        med = ft.groupby(["agent", "height", "width", "mode"])["frame_ms_median"].median()
        for (agent, h, w), g in med.groupby(level=[0, 1, 2]):
            m = g.droplevel([0, 1, 2])
            rows.append({"label": label, "agent": agent, "size": f"{h}x{w}",
                         "online_ms": m.get("online"), "offline_ms": m.get("offline"),
                         "norender_ms": m.get("none"),
                         "offline_over_online": m.get("offline") / m.get("online"),
                         "online_over_offline": m.get("online") / m.get("offline"),
                         "repetitions": int(ft["rep"].nunique()),
                         "steps": int(ft["steps"].max()), "clock": ft["clock"].iloc[0]})  # fmt: skip
    return pd.DataFrame(rows)


def export_run_folders(
    table: str,
    runs: Mapping[str, Path],
    fn: Callable[[Mapping[str, Path]], pd.DataFrame],
    out_dir: Path = DATA_DIR,
    command: str = "",
) -> Path:
    """A table made from plain run folders (not a figure's), its sidecar from their manifests."""
    started, wall, commits, machines, entries = [], 0.0, set(), set(), []
    for label, folder in runs.items():
        m = json.loads((Path(folder) / "manifest.json").read_text())
        git = (m.get("git") or {}).get("cobelrun") or {}
        commits.add(f"{git.get('commit')}{' (dirty)' if git.get('dirty') else ''}")
        machines.add(f"{m.get('hostname')} ({m.get('platform')})")
        started.append(m.get("started_at"))
        wall += float(m.get("wall_time_s") or 0.0)
        entries.append({"label": label, "seed": m.get("seed"), "config_hash": m.get("config_hash"),
                        "command": " ".join(m.get("command") or [])})  # fmt: skip
    prov = {"table": table, "source": "run", "command": command, "runs": entries,
            "seeds": sorted({e["seed"] for e in entries if e["seed"] is not None}),
            "cobel_commit": sorted(commits), "machine": sorted(machines), "cpus": os.cpu_count(),
            "runs_started": [min(started), max(started)],
            "exported": datetime.now(UTC).isoformat(timespec="seconds"),
            "wall_time_s": round(wall, 1)}  # fmt: skip
    return write_table(fn(runs), prov, out_dir, table)


# -- provenance and writing -------------------------------------------------------------------


def figure_data(
    figure: registry.Figure, *, quick: bool, root: Path, finished_only: bool = False
) -> registry.FigureData:
    """The figure's planned runs as :class:`FigureData`; a CobelError if one is unfinished
    (``finished_only``: the finished ones, at least one per label)."""
    from cobelrun.io.sweep_folder import is_complete

    data = registry.FigureData(quick=quick, runs={})
    for p in registry.plan_runs(figure, quick=quick, root=root):
        if not is_complete(p.run_dir, p.config_hash):
            if finished_only:
                continue
            raise CobelError(f"{figure.name}: run {p.run_dir} is not finished; build it first")
        ref = registry.RunRef(p.label, p.job, tuple(p.overrides), p.params, p.run_dir,
                              p.config_hash, reused=True)  # fmt: skip
        data.runs.setdefault(p.label, []).append(ref)
    missing = [label for label in figure.runs if label not in data.runs]
    if missing:
        raise CobelError(f"{figure.name}: no finished run of {', '.join(missing)}")
    return data


def provenance(
    figure: registry.Figure, data: registry.FigureData, *, command: str, table: str
) -> dict[str, Any]:
    """The sidecar of one table built from ``data``'s runs (read from their manifests)."""
    runs, commits, wall, started, machines = [], set(), 0.0, [], set()
    for label, refs in data.runs.items():
        for ref in refs:
            m = json.loads((ref.run_dir / "manifest.json").read_text())
            git = (m.get("git") or {}).get("cobelrun") or {}
            commits.add(f"{git.get('commit')}{' (dirty)' if git.get('dirty') else ''}")
            wall += float(m.get("wall_time_s") or 0.0)
            started.append(m.get("started_at"))
            machines.add(f"{m.get('hostname')} ({m.get('platform')})")
            runs.append({"label": label, "job": ref.job, "seed": m.get("seed"),
                         "runs": m.get("runs"), "config_hash": ref.config_hash,
                         "overrides": list(ref.overrides)})  # fmt: skip
    return {
        "table": table,
        "figure": figure.name,
        "source": "run",
        "quick": data.quick,
        "command": command,
        "runs": runs,
        "seeds": sorted({r["seed"] for r in runs if r["seed"] is not None}),
        "cobel_commit": sorted(commits),
        "machine": sorted(machines),
        "cpus": os.cpu_count(),
        "runs_started": [min(s for s in started if s), max(s for s in started if s)],
        "exported": datetime.now(UTC).isoformat(timespec="seconds"),
        "wall_time_s": round(wall, 1),
        "wall_time_note": "sum of the runs' wall times (their manifests)",
    }


def run_missing(
    figure: registry.Figure,
    *,
    quick: bool,
    root: Path,
    log: Callable[[str], None] | None = None,
) -> int:
    """Run the figure's unfinished runs as ``cobel figure`` runs them: each label's missing
    jobs as a sweep of its overrides through Hydra's launcher (:func:`registry.run_label`,
    resumed like any sweep); returns how many were missing."""
    from cobelrun.io.sweep_folder import is_complete

    planned = registry.plan_runs(figure, quick=quick, root=root)
    todo = [p for p in planned if not is_complete(p.run_dir, p.config_hash)]
    for label in figure.runs:
        missing = [p for p in todo if p.label == label]
        if missing:
            registry.run_label(figure, label, missing, quick=quick, root=root,
                               launcher=registry.launcher_overrides(1), log=log)  # fmt: skip
    return len(todo)


def export(
    name: str,
    *,
    quick: bool = False,
    out_dir: Path = DATA_DIR,
    root: Path | None = None,
    build: bool = True,
    labels: Sequence[str] | None = None,
    finished_only: bool = False,
    log: Callable[[str], None] | None = None,
) -> list[Path]:
    """Build figure ``name`` (unless ``build`` is False: its runs must be finished) and write
    its summary tables with their sidecars; returns the CSVs written. ``labels``: only these
    of the figure's run labels (e.g. revaluation's graph designs without the grid ones).
    ``finished_only``: run nothing and use the runs finished so far (tables ``NAME_partial``,
    the sidecar lists the runs used)."""
    if name not in SUMMARIES:
        raise CobelError(
            f"no summary tables for figure {name!r}{suggest(name, SUMMARIES)}; "
            f"allowed: {allowed_list(SUMMARIES)}"
        )
    figure = registry.get(name)
    if labels:
        unknown = [x for x in labels if x not in figure.runs]
        if unknown:
            raise CobelError(
                f"{name} has no run label {unknown[0]!r}{suggest(unknown[0], figure.runs)}; "
                f"allowed: {allowed_list(figure.runs)}"
            )
        figure = dataclasses.replace(figure, runs={x: figure.runs[x] for x in labels})
    root = root or registry.results_root()
    t0 = time.perf_counter()
    if build and not finished_only:
        run_missing(figure, quick=quick, root=root, log=log)
        if not labels:  # the whole figure: draw it as `cobel figure` does (its runs are reused)
            registry.build(figure, quick=quick, root=root, log=log)
    data = figure_data(figure, quick=quick, root=root, finished_only=finished_only)
    tables = SUMMARIES[name](data)
    command = f"python -m cobelrun.figures.data {name}" + (" --quick" if quick else "")
    command += f" --labels {','.join(labels)}" if labels else ""
    command += " --finished-only" if finished_only else ""
    written = []
    for table, frame in tables.items():
        stem = f"{table}_quick" if quick else table
        stem += "_partial" if finished_only else ""
        prov = provenance(figure, data, command=command, table=stem)
        prov["export_wall_time_s"] = round(time.perf_counter() - t0, 1)
        written.append(write_table(frame, prov, out_dir, stem))
    return written


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m cobelrun.figures.data NAME [--quick] [--out DIR] [--no-build]``."""
    parser = argparse.ArgumentParser(prog="python -m cobelrun.figures.data",
                                     description=__doc__.split("\n\n")[0])  # fmt: skip
    parser.add_argument("name", nargs="?", help=f"figure: {', '.join(SUMMARIES)}")
    parser.add_argument("--derive", action="store_true",
                        help=f"write the derived tables ({', '.join(DERIVED)})")  # fmt: skip
    parser.add_argument("--quick", action="store_true", help="the figure's quick budget")
    parser.add_argument("--out", type=Path, default=DATA_DIR, help="output folder")
    parser.add_argument("--no-build", action="store_true", help="only finished runs")
    parser.add_argument("--labels", help="comma-separated run labels (default: all)")
    parser.add_argument("--finished-only", action="store_true",
                        help="run nothing; tables NAME_partial from the runs finished so far")  # fmt: skip
    parser.add_argument("--runs", nargs="+", type=Path, metavar="PATH",
                        help="read NAME's runs from these sweep or run folders, never writing "
                        "to them (cobelrun.figures.run_import: fig6a, fig8)")  # fmt: skip
    args = parser.parse_args(argv)
    if args.derive:
        for path in derive(args.out):
            print(path)
        return 0
    if not args.name:
        parser.error("give a figure NAME or --derive")
    if args.runs:
        from cobelrun.figures.run_import import import_runs

        ignored = [flag for flag, on in (("--quick", args.quick), ("--labels", args.labels),
                                         ("--no-build", args.no_build)) if on]  # fmt: skip
        if ignored:  # else a quick sweep's runs would write the full tables (fig6a.csv)
            print(f"cobel: error: {', '.join(ignored)} cannot be combined with --runs, which "
                  "reads the given runs as they are into NAME's tables (NAME_partial with "
                  "--finished-only); write them elsewhere with --out DIR", file=sys.stderr)  # fmt: skip
            return 2

        try:
            for path in import_runs(args.name, args.runs, out_dir=args.out,
                                    finished_only=args.finished_only):  # fmt: skip
                print(path)
        except CobelError as exc:
            print(f"cobel: error: {exc}", file=sys.stderr)
            return 2
        return 0
    try:
        for path in export(args.name, quick=args.quick, out_dir=args.out,
                           build=not args.no_build,
                           labels=args.labels.split(",") if args.labels else None,
                           finished_only=args.finished_only, log=lambda s: print(s, file=sys.stderr)):  # fmt: skip
            print(path)
    except CobelError as exc:
        print(f"cobel: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
