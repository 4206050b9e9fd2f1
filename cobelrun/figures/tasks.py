"""The default figure of any run, chosen from what its monitors and protocol recorded.

``cobel plot RUN`` comes here for every task without a figure of its own
(:data:`cobelrun.figures.PLOTS_BY_TASK`):

- a response monitor (``cumulative_response``): Fig. 6B, cumulative responses and latency;
- the water-maze monitor (``escape_latency_s`` and quadrant fractions): latency in seconds by
  day (acquisition, reversal) and the probe's quadrant occupancy;
- a replay monitor (a ``replays`` table, dyna_maze / linear_track): steps per episode and the
  direction of replay events at trial start and end;
- a revaluation job (``revaluation_scores.csv``): the score of each agent;
- otherwise: steps per trial and reward per trial (95 % CI over runs).

:mod:`cobelrun.figures.kinds` lists what ``--kind`` can draw for a run. Functions read folders
only through the validated readers.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd

from cobelrun.errors import CobelError
from cobelrun.figures.titles import overrides_of as overrides_of  # re-exported (web)
from cobelrun.figures.titles import run_title as _title
from cobelrun.io.run_folder import RunFolder

#: the revaluation job's score file (``cobelrun.revaluation``)
REVALUATION_SCORES = "revaluation_scores.csv"
#: the largest score file read (a job writes a few kB)
MAX_SCORES_BYTES = 4 << 20
WATERMAZE_COLUMNS = {"escape_latency_s", "path_length", "target_quadrant_fraction"}


def read_scores(run_dir: str | Path) -> pd.DataFrame:
    """A revaluation job's scores, checked: a regular file of at most 4 MB with the columns
    ``design, agent, replay_budget, score``."""
    p = Path(run_dir) / REVALUATION_SCORES
    if not p.is_file():
        raise CobelError(f"{Path(run_dir)} has no {REVALUATION_SCORES}")
    if p.stat().st_size > MAX_SCORES_BYTES:
        raise CobelError(f"{p} is larger than {MAX_SCORES_BYTES >> 20} MB; not a score file")
    try:
        scores = pd.read_csv(p)
    except Exception as exc:
        raise CobelError(f"cannot read {p}: {str(exc).strip().splitlines()[0]}") from None
    need = {"design", "agent", "replay_budget", "score"}
    if not need <= set(scores):
        raise CobelError(f"{p} lacks the columns {sorted(need - set(scores))}")
    return scores


def trials_columns(run_dir: Path) -> set[str]:
    """The trials table's column names (from its footer; no rows read)."""
    import pyarrow.parquet as pq

    from cobelrun.io.validate import check_table

    p = RunFolder(run_dir).table("trials")
    if not p.is_file():
        return set()
    check_table(p)
    return set(pq.read_schema(p).names)


def plot_run(run_dir: str | Path, out: str | Path | None = None) -> Path:
    """The run's default figure, chosen from what it recorded (see the module docstring)."""
    import matplotlib.pyplot as plt

    from cobelrun.figures import save_figure

    run_dir = Path(run_dir)
    folder = RunFolder(run_dir)
    if not folder.table("trials").is_file() and (run_dir / REVALUATION_SCORES).is_file():
        fig = _revaluation(run_dir)
    else:
        cols = trials_columns(run_dir)
        if not cols:
            raise CobelError(f"{run_dir} is not a cobel run folder (no trials table)")
        if "cumulative_response" in cols:
            from cobelrun.figures import extinction

            return extinction.plot_run(run_dir, out)
        if WATERMAZE_COLUMNS <= cols:
            fig = _watermaze(run_dir)
        elif folder.table("replays").is_file():
            fig = _replay(run_dir)
        else:
            fig = _curves(run_dir, cols)
    try:
        fig.suptitle(_title(run_dir), fontsize=9)
        fig.tight_layout()
    except BaseException:
        plt.close(fig)
        raise
    return save_figure(fig, Path(out) if out else run_dir / "plot.png")


def _curves(run_dir: Path, cols: set[str]) -> Any:
    import matplotlib.pyplot as plt

    from cobelrun.figures.runs import plot_curves
    from cobelrun.results import load_trials

    trials = load_trials(run_dir)
    shown = [(c, lab) for c, lab in (("steps", "steps per trial"), ("reward", "reward per trial"))
             if c in cols]  # fmt: skip
    if not shown:
        raise CobelError(f"{run_dir}: the trials table has neither steps nor reward")
    fig, axes = plt.subplots(1, len(shown), figsize=(5 * len(shown), 3.6), squeeze=False)
    try:
        for ax, (c, lab) in zip(axes[0], shown, strict=True):
            plot_curves(trials, c, ax, ylabel=lab, label=c)
    except BaseException:
        plt.close(fig)
        raise
    return fig


def _watermaze(run_dir: Path) -> Any:
    import matplotlib.pyplot as plt

    from cobelrun.figures import watermaze
    from cobelrun.results import load_trials

    trials = load_trials(run_dir)
    has_probe = bool((trials["phase"] == "probe").any())
    fig, axes = plt.subplots(1, 2 if has_probe else 1, figsize=(9 if has_probe else 5, 3.6),
                             squeeze=False)  # fmt: skip
    try:
        summary = watermaze.daily_summary(trials)
        watermaze.plot_learning_curve(summary, axes[0][0], "escape_latency_s",
                                      "escape latency [s] (mean, 95% CI)")  # fmt: skip
        if has_probe:
            watermaze.plot_quadrants(watermaze.probe_quadrants(trials), axes[0][1])
    except BaseException:
        plt.close(fig)
        raise
    return fig


def _replay(run_dir: Path) -> Any:
    import matplotlib.pyplot as plt

    from cobelrun.analysis.replay import replay_events
    from cobelrun.figures.replay import plot_direction, plot_steps_per_trial
    from cobelrun.results import load_table, load_trials

    trials = load_trials(run_dir)
    replays = load_table(run_dir, "replays")
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    try:
        plot_steps_per_trial(trials, axes[0], "median over runs (IQR)", "tab:blue")
        axes[0].set_ylabel("steps per episode")
        axes[0].legend(loc="upper right")
        events = replay_events(replays)
        n_trials = int(trials.groupby("run")["trial"].nunique().sum())
        plot_direction(events, n_trials, axes[1])
        axes[1].set_title(f"replay events ({len(replays):,} replayed experiences)")
    except BaseException:
        plt.close(fig)
        raise
    return fig


def _revaluation(run_dir: Path) -> Any:
    import matplotlib.pyplot as plt

    from cobelrun.figures.replay import plot_revaluation

    scores = read_scores(run_dir)
    designs = list(dict.fromkeys(scores["design"]))
    fig, axes = plt.subplots(1, len(designs), figsize=(5 * len(designs), 4), squeeze=False)
    try:
        for ax, design in zip(axes[0], designs, strict=True):
            plot_revaluation(scores, design, ax)
            ax.set_ylabel("revaluation score")
    except BaseException:
        plt.close(fig)
        raise
    return fig
