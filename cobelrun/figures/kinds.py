"""``cobel plot RUN --kind KIND``: which kinds a run offers, and drawing one of them.

Curves, occupancy and trajectories come from :mod:`cobelrun.figures.runs`; value, policy, Q,
SR and rate maps from :mod:`cobelrun.figures.learned`. A kind the run has no data for is
refused in one line that names the kinds it offers.
"""

from __future__ import annotations

from pathlib import Path

from cobelrun.errors import CobelError
from cobelrun.io.run_folder import RunFolder

__all__ = ["KINDS", "available_kinds", "check_kind", "plot_kind", "plot_selection"]


#: every ``--kind`` (a run offers those it has the data for: :func:`available_kinds`)
KINDS = ("occupancy", "trajectories", "latency", "response", "reward", "value", "policy", "q",
         "sr", "rate")  # fmt: skip


def available_kinds(run_dir: str | Path) -> list[str]:
    """What ``cobel plot RUN --kind`` can draw for this run."""
    from cobelrun.figures import learned
    from cobelrun.figures.tasks import trials_columns

    run_dir = Path(run_dir)
    folder = RunFolder(run_dir)
    cols = trials_columns(run_dir)
    kinds = []
    if folder.world.is_file() and folder.table("steps").is_file():
        kinds += ["occupancy", "trajectories"]
    kinds += [k for k, c in (("latency", "steps"), ("response", "cumulative_response"),
                             ("reward", "reward")) if c in cols]  # fmt: skip
    kinds += learned.available(run_dir)
    return kinds


def check_kind(run_dir: str | Path, kind: str) -> None:
    """A one-line CobelError when this run cannot draw ``kind``, naming what it can."""
    have = available_kinds(run_dir)
    if kind not in have:
        raise CobelError(
            f"{Path(run_dir)} has nothing for --kind {kind}; this run offers: "
            f"{', '.join(have) or 'no --kind (draw its task figure without --kind)'}"
        )


def plot_kind(run_dir: str | Path, kind: str, out: str | Path | None = None) -> Path:
    """Draw ``kind`` of the run (default ``RUN_DIR/plot_<kind>.png``); an unknown kind or one
    the run has no data for is a one-line CobelError naming the alternatives."""
    from cobelrun.errors import allowed_list, suggest
    from cobelrun.figures import learned, runs

    if kind not in KINDS:
        raise CobelError(f"unknown plot kind {kind!r}{suggest(kind, KINDS)}; allowed: "
                         f"{allowed_list(KINDS)}")  # fmt: skip
    check_kind(run_dir, kind)
    if kind in learned.KINDS:
        return learned.plot_learned(run_dir, kind, out)
    return runs.plot_kind(run_dir, kind, out)


def plot_selection(
    run_dir: str | Path,
    kind: str,
    out: str | Path | None = None,
    *,
    run: int | None = None,
    trials: str | None = None,
    state: int | None = None,
) -> Path:
    """``cobel plot RUN --kind KIND`` with ``--run``, ``--trials`` (``A:B``) or ``--state``:
    trajectories of a chosen run and trial range, or a saved agent's kind for a chosen run."""
    import matplotlib.pyplot as plt

    from cobelrun.figures import learned, save_figure
    from cobelrun.figures.runs import load_geometry, plot_trajectories
    from cobelrun.figures.titles import run_title as _title

    run_dir = Path(run_dir)
    if kind in learned.KINDS:
        check_kind(run_dir, kind)
        return learned.plot_learned(run_dir, kind, out, run=run or 0, trials=trials, state=state)
    if kind != "trajectories":
        raise CobelError(f"--run/--trials/--state go with --kind trajectories or "
                         f"{', '.join(learned.KINDS)}, not {kind}")  # fmt: skip
    if state is not None:
        raise CobelError("--state goes with --kind sr")
    check_kind(run_dir, kind)
    from cobelrun.results import load_steps

    steps = load_steps(run_dir)
    r = 0 if run is None else int(run)
    runs = sorted(steps["run"].unique())
    if r not in runs:
        raise CobelError(f"run {r} has no recorded steps; recorded runs: "
                         f"{', '.join(map(str, runs[:20]))}")  # fmt: skip
    first, last = learned.parse_trials(trials)
    part = steps[steps["run"] == r]
    if first is not None:
        part = part[part["trial"] >= first]
    if last is not None:
        part = part[part["trial"] <= last]
    if part.empty:
        have = sorted(steps.loc[steps["run"] == r, "trial"].unique())
        raise CobelError(f"--trials {trials}: run {r} has recorded steps for trials "
                         f"{have[0]}..{have[-1]}")  # fmt: skip
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    try:
        plot_trajectories(part, load_geometry(run_dir), ax, run=r)
        ax.set_title(f"{_title(run_dir)}: trajectories, run {r}" + (f", trials {trials}" if trials
                                                                      else ""), fontsize=9)  # fmt: skip
        fig.tight_layout()
    except BaseException:
        plt.close(fig)
        raise
    return save_figure(fig, Path(out) if out else run_dir / "plot_trajectories.png")
