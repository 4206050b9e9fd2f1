"""What an agent learned, drawn on the maze from its saved arrays (``agents.npz``).

``cobel plot RUN --kind value|policy|q|sr|rate [--run R] [--trials A:B] [--state S]``:

- ``value``: V(s) = max_a Q(s, a) on each state's place;
- ``policy``: the greedy action of each state as an arrow (ties: no arrow);
- ``q``: one panel per action, Q(s, a);
- ``sr``: the successor-representation row of state ``--state`` (mean over actions of
  M[s, a, :]), i.e. the expected discounted future occupancy of every state;
- ``rate``: rate maps of recorded units (an ``activity_maps`` table), the snapshot trial
  chosen by ``--trials``; for a 2D arena run without recorded units, the rate maps of the
  arena's place, grid and boundary cells (:mod:`cobelrun.figures.arena_cells`).

Q comes from a tabular agent's ``Q`` or, for SR agents, from ``M`` and ``w``
(Q[s, a] = sum_s' M[s, a, s'] w[s']). States are placed where the recorded ``steps`` saw them
(``state``/``x``/``y``); action directions are the moves the steps show for each action.
Nothing is composed or instantiated: arrays come from :func:`cobelrun.io.agents_archive.read_agent`
(every header checked before a value is read).
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cobelrun.errors import CobelError
from cobelrun.io.run_folder import RunFolder

#: ``--kind`` values drawn here
KINDS = ("value", "policy", "q", "sr", "rate")


def _archive_keys(run_dir: Path) -> set[str]:
    p = RunFolder(run_dir).agents_archive
    if not p.is_file():
        return set()
    try:
        with zipfile.ZipFile(p) as zf:
            return {n[: -len(".npy")] for n in zf.namelist() if n.endswith(".npy")}
    except (OSError, zipfile.BadZipFile):
        return set()


def available(run_dir: str | Path) -> list[str]:
    """The kinds of this module the run can draw."""
    run_dir = Path(run_dir)
    folder = RunFolder(run_dir)
    keys = _archive_keys(run_dir)
    placed = folder.table("steps").is_file()
    out = []
    if placed and ("Q" in keys or {"M", "w"} <= keys):
        out += ["value", "policy", "q"]
    if placed and "M" in keys:
        out.append("sr")
    if folder.table("activity_maps").is_file():
        out.append("rate")
    else:
        from cobelrun.figures.arena_cells import has_spatial_cells

        if has_spatial_cells(run_dir):
            out.append("rate")
    return out


def load_agent(run_dir: str | Path, run: int = 0) -> dict[str, np.ndarray]:
    """Run ``run``'s saved agent arrays in their real shapes (e.g. ``Q`` (S, A), ``M``
    (S, A, S)); a one-line CobelError names the saved runs when ``run`` is not one."""
    from cobelrun.io.agents_archive import read_agent, runs_in

    p = RunFolder(run_dir).agents_archive
    if not p.is_file():
        raise CobelError(f"{Path(run_dir)} has no saved agents ({RunFolder.AGENTS_ARCHIVE}); "
                         "run with task.save_agents=all")  # fmt: skip
    try:
        got = read_agent(p, int(run))
        if got is None:
            runs = runs_in(p)
            raise CobelError(f"run {run} has no saved agent in {p}; saved runs: "
                             f"{', '.join(map(str, runs[:20]))}{' ...' if len(runs) > 20 else ''}")  # fmt: skip
    except ValueError as exc:
        raise CobelError(f"{p}: {exc}") from None
    return got[0]


def q_table(arrays: dict[str, np.ndarray]) -> np.ndarray:
    """Q (S, A) of a tabular agent (``Q``) or an SR agent (``M``, ``w``)."""
    if "Q" in arrays and arrays["Q"].ndim == 2:
        return np.asarray(arrays["Q"], float)
    if "M" in arrays and "w" in arrays and arrays["M"].ndim == 3:
        return np.einsum("sat,t->sa", arrays["M"], arrays["w"])
    raise CobelError(f"the saved agent has no Q table nor SR (M, w); it has: {sorted(arrays)}")


def state_positions(steps: pd.DataFrame) -> dict[int, tuple[float, float]]:
    """Each recorded state's place (x, y), from the steps table: the states steps were taken
    in and, where the table records the pose after each step, the states they led to (so
    terminal goals, where no step is taken, are placed too)."""
    from cobelrun.analysis.paths import has_arrivals

    places = steps[["state", "x", "y"]]
    if has_arrivals(steps) and "next_state" in steps:
        after = steps[["next_state", "next_x", "next_y"]]
        after = after.set_axis(["state", "x", "y"], axis=1)
        places = pd.concat([places, after], ignore_index=True)
    first = places.drop_duplicates("state")
    return {int(s): (float(x), float(y)) for s, x, y in first.itertuples(index=False)}


def action_vectors(steps: pd.DataFrame, n_actions: int) -> np.ndarray:
    """(A, 2) unit vector of each action's move, as the recorded steps show it (zeros where an
    action never moved the agent)."""
    s = steps.sort_values(["run", "trial", "step"])
    same = (s["run"].to_numpy()[1:] == s["run"].to_numpy()[:-1]) & (
        s["trial"].to_numpy()[1:] == s["trial"].to_numpy()[:-1]
    )
    dx = np.diff(s["x"].to_numpy())[same]
    dy = np.diff(s["y"].to_numpy())[same]
    act = s["action"].to_numpy()[:-1][same]
    out = np.zeros((n_actions, 2))
    moved = np.hypot(dx, dy) > 1e-9
    for a in range(n_actions):
        m = moved & (act == a)
        if m.any():
            v = np.array([np.median(dx[m]), np.median(dy[m])])
            n = np.hypot(*v)
            out[a] = v / n if n > 0 else 0
    return out


def parse_trials(text: str | None) -> tuple[int | None, int | None]:
    """``"A:B"`` (either side may be empty) or ``"N"`` -> (first, last) inclusive."""
    if text is None or text.strip() == "":
        return None, None
    try:
        if ":" in text:
            a, b = text.split(":", 1)
            return (int(a) if a.strip() else None, int(b) if b.strip() else None)
        n = int(text)
        return n, n
    except ValueError:
        raise CobelError(f"--trials {text!r}: give A:B, A:, :B or N (trial numbers)") from None


def _map(ax: Any, geometry: Any, pos: dict[int, tuple[float, float]], values: np.ndarray,
         label: str, cmap: str = "viridis") -> None:  # fmt: skip
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Rectangle

    from cobelrun.figures.runs import draw_geometry

    draw_geometry(geometry, ax, labels=len(geometry.regions) <= 12)
    cs = (
        geometry.cell_size
        if geometry.kind == "grid"
        else 0.04
        * max(geometry.bounds[2] - geometry.bounds[0], geometry.bounds[3] - geometry.bounds[1])
    )
    states = [s for s in sorted(pos) if s < len(values)]
    patches = [Rectangle((pos[s][0] - cs / 2, pos[s][1] - cs / 2), cs, cs) for s in states]
    coll = PatchCollection(patches, cmap=cmap, zorder=2, alpha=0.9)
    coll.set_array(np.asarray([values[s] for s in states], float))
    ax.add_collection(coll)
    ax.figure.colorbar(coll, ax=ax, label=label)
    ax.set_xlabel("x [cells]" if geometry.kind == "grid" else "x [m]")
    ax.set_ylabel("y [cells]" if geometry.kind == "grid" else "y [m]")


def plot_learned(
    run_dir: str | Path,
    kind: str,
    out: str | Path | None = None,
    *,
    run: int = 0,
    trials: str | None = None,
    state: int | None = None,
) -> Path:
    """Draw ``kind`` (see the module docstring) for run ``run``; returns the PNG written
    (default ``RUN_DIR/plot_<kind>.png``)."""

    from cobelrun.figures import save_figure

    run_dir = Path(run_dir)
    if kind not in KINDS:
        raise CobelError(f"unknown kind {kind!r}; these come from saved agents: {', '.join(KINDS)}")
    have = available(run_dir)
    if kind not in have:  # cobel plot names every kind the run offers (figures.kinds)
        raise CobelError(f"{run_dir} has nothing for --kind {kind}; of the saved-agent kinds "
                         f"it offers: {', '.join(have) or 'none'}")  # fmt: skip
    if kind == "rate" and not RunFolder(run_dir).table("activity_maps").is_file():
        from cobelrun.figures.arena_cells import plot_cell_rate_maps

        fig = plot_cell_rate_maps(run_dir)
    elif kind == "rate":
        fig = _rate(run_dir, run, trials)
    else:
        fig = _tabular(run_dir, kind, run, state)
    fig.tight_layout()
    return save_figure(fig, Path(out) if out else run_dir / f"plot_{kind}.png")


def _tabular(run_dir: Path, kind: str, run: int, state: int | None) -> Any:
    import matplotlib.pyplot as plt

    from cobelrun.figures.runs import draw_geometry, load_geometry
    from cobelrun.results import load_steps

    arrays = load_agent(run_dir, run)
    geometry = load_geometry(run_dir)
    steps = load_steps(run_dir)
    pos = state_positions(steps)
    if kind == "sr":
        M = np.asarray(arrays["M"], float)
        s0 = int(steps["state"].iloc[0]) if state is None else int(state)
        if not 0 <= s0 < M.shape[0]:
            raise CobelError(f"--state {s0} is not a state (0..{M.shape[0] - 1})")
        fig, ax = plt.subplots(figsize=(5.5, 4.5))
        _map(ax, geometry, pos, M[s0].mean(axis=0), "expected discounted visits", "magma")
        if s0 in pos:
            ax.plot(*pos[s0], "o", mfc="none", mec="tab:cyan", ms=10, mew=2, zorder=5)
        ax.set_title(f"SR row of state {s0}, run {run}")
        return fig
    Q = q_table(arrays)
    if kind == "q":
        n = Q.shape[1]
        fig, axes = plt.subplots(1, n, figsize=(3.6 * n, 3.6), squeeze=False)
        vec = action_vectors(steps, n)
        for a, ax in enumerate(axes[0]):
            _map(ax, geometry, pos, Q[:, a], "Q(s, a)")
            ax.set_title(f"action {a} (move {vec[a][0]:+.0f}, {vec[a][1]:+.0f}), run {run}")
        return fig
    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    if kind == "value":
        _map(ax, geometry, pos, Q.max(axis=1), "V(s) = max_a Q(s, a)")
        ax.set_title(f"state value, run {run}")
        return fig
    draw_geometry(geometry, ax, labels=len(geometry.regions) <= 12)
    vec = action_vectors(steps, Q.shape[1])
    xs, ys, us, vs = [], [], [], []
    for s, (x, y) in pos.items():
        if s >= Q.shape[0]:
            continue
        q = Q[s]
        best = np.flatnonzero(q == q.max())
        if len(best) == 1 and np.any(vec[best[0]]):
            xs.append(x)
            ys.append(y)
            us.append(vec[best[0]][0])
            vs.append(vec[best[0]][1])
    scale = geometry.cell_size if geometry.kind == "grid" else 1.0
    ax.quiver(xs, ys, np.multiply(us, 0.4 * scale), np.multiply(vs, 0.4 * scale), angles="xy",
              scale_units="xy", scale=1, color="tab:blue", zorder=4, pivot="middle")  # fmt: skip
    ax.set_title(f"greedy policy, run {run} ({len(xs)} of {len(pos)} states; ties: no arrow)")
    ax.set_xlabel("x [cells]" if geometry.kind == "grid" else "x [m]")
    ax.set_ylabel("y [cells]" if geometry.kind == "grid" else "y [m]")
    return fig


def _rate(run_dir: Path, run: int, trials: str | None, units: int = 16) -> Any:
    import matplotlib.pyplot as plt

    from cobelrun.results import load_table

    maps = load_table(run_dir, "activity_maps")
    part = maps[maps["run"] == run]
    if part.empty:
        raise CobelError(f"no rate maps for run {run}; runs: {sorted(maps['run'].unique())[:20]}")
    snaps = sorted(part["trial"].unique())
    first, last = parse_trials(trials)
    chosen = [t for t in snaps if (first is None or t >= first) and (last is None or t <= last)]
    if not chosen:
        raise CobelError(f"--trials {trials}: no snapshot there; snapshots at trials {snaps}")
    trial = chosen[-1]
    snap = part[part["trial"] == trial]
    ids = sorted(snap["unit"].unique())[:units]
    cols = 4
    rows = int(np.ceil(len(ids) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(2.4 * cols, 2.2 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.set_axis_off()
    for ax, u in zip(axes.ravel(), ids, strict=False):
        m = snap[snap["unit"] == u].groupby(["iy", "ix"])["value"].mean().unstack()
        x0, x1 = snap["x"].min(), snap["x"].max()
        y0, y1 = snap["y"].min(), snap["y"].max()
        ax.set_axis_on()
        im = ax.imshow(m.to_numpy(), origin="lower", extent=(x0, x1, y0, y1), cmap="jet")
        fig.colorbar(im, ax=ax, fraction=0.046)
        ax.set_title(f"unit {u}", fontsize=8)
        ax.set_xlabel("x [m]", fontsize=7)
        ax.set_ylabel("y [m]", fontsize=7)
        ax.tick_params(labelsize=6)
    fig.suptitle(f"rate maps, run {run}, trial {trial} (layer {snap['layer'].iloc[0]})", fontsize=9)
    return fig
