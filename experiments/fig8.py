"""Fig. 8: place cells emerge in a DQN trained on camera images of a hexagonal maze.

A: place cells among the 50 analysis units per snapshot (mean ± SD over runs; grey: each run);
B: the spatial information (Skaggs) of all units per snapshot; C: representational similarity of
the population activity with the positions' distances (rsatoolbox); bottom: activity maps of
up to three place cells at the last snapshot (6 headings + mean). The criterion is the paper's
(cobelrun/analysis/place_cells.py, docs/place_cells.md).

``fig8`` trains with the original's settings in an approximation of its room
(``task=place_cells_original``) and compares the bounding boxes by area, as the original's
plot script; ``fig8_stable`` is cobel's stabilised training (``task=place_cells``: the analysis
layer survives in most runs, but no place cells emerge) with boxes compared by extent.

The CSV has one row per (run, snapshot): ``trial``, ``place_cells``, ``units``,
``place_cell_fraction``, ``spatial_information_median``, ``rsa_spatial``, and the Spearman rho
of the mean count over snapshots (``spearman_rho_mean_count``, the same on every row).
"""

from __future__ import annotations

import functools

import numpy as np
import pandas as pd

from cobelrun.figures.registry import Figure, FigureData

TITLE = "Fig. 8: place cells in a DQN on a hexagonal maze (camera images)"


def draw(data: FigureData, *, box_measure: str = "extent", title: str = TITLE):
    """The figure; ``box_measure`` picks how the criterion compares the largest blob's bounding
    box with the explored area's (``extent``: cobel's default, ``area``: the original script's)."""
    import matplotlib.pyplot as plt

    from cobelrun.analysis.maps import classify_snapshots, load_activity_maps, maps_array
    from cobelrun.analysis.place_cells import PlaceCellCriterion
    from cobelrun.figures.place_cells import plot_summary_panels, plot_unit_maps

    # panel D shows the run with the most place cells at its last snapshot (the first such
    # run); only that run's maps are kept in memory
    units, snaps, last, best = [], [], None, -1
    for ref in data.runs["dqn"]:
        df, grid = load_activity_maps(ref.run_dir)
        u, s = classify_snapshots(df, grid, criterion=PlaceCellCriterion(box_measure=box_measure))
        u.insert(0, "job", ref.job)
        s.insert(0, "job", ref.job)
        units.append(u)
        snaps.append(s)
        for run, rows in s.groupby("run", sort=True):
            count = int(rows.loc[rows["trial"].idxmax(), "place_cells"])
            if count > best:
                best, last = count, (df, grid, ref.job, int(run))
    unit_table = pd.concat(units, ignore_index=True)
    snapshots = pd.concat(snaps, ignore_index=True)
    # runs of several jobs (one per seed) numbered 0, 1, ... in (job, run) order
    pairs = sorted(set(zip(snapshots["job"], snapshots["run"], strict=True)))
    number = {key: k for k, key in enumerate(pairs)}
    for t in (snapshots, unit_table):
        t["run"] = [number[key] for key in zip(t["job"], t["run"], strict=True)]
    fig = plt.figure(figsize=(7.2, 6.4), layout="constrained")
    sub_top, sub_maps = fig.subfigures(2, 1, height_ratios=[1.0, 1.2])
    rho = plot_summary_panels(snapshots, unit_table, sub_top.subplots(1, 3))

    # example maps: that run's last snapshot, its place cells with the most information
    assert last is not None
    df, grid, job, run_in_job = last
    t_last = int(df.loc[df["run"] == run_in_job, "trial"].max())
    snap = df[(df["run"] == run_in_job) & (df["trial"] == t_last)]
    maps, explored, unit_ids, heads = maps_array(snap, grid)
    run0 = number[(job, run_in_job)]
    first = unit_table[(unit_table["run"] == run0) & (unit_table["trial"] == t_last)]
    cells = first[first["is_place_cell"]].sort_values("spatial_information", ascending=False)
    picks = cells["unit"].head(3).tolist()
    note = "place cells" if picks else "no place cells: units with the most information"
    if not picks:
        picks = first.sort_values("spatial_information", ascending=False)["unit"].head(3).tolist()
    grid_axes = sub_maps.subplots(3, len(heads) + 1)
    for row in range(3):
        axes = list(grid_axes[row])
        if row < len(picks):
            k = int(np.searchsorted(unit_ids, picks[row]))
            plot_unit_maps(maps[k], explored, heads, axes, label=f"unit {picks[row]}")
        else:
            for ax in axes:
                ax.axis("off")
    sub_maps.suptitle(f"D  activity maps at trial {t_last} (run {run0}; {note})", fontsize=8)
    sub_top.suptitle(title, fontsize=9)

    table = snapshots[["job", "run", "trial", "place_cells", "units", "place_cell_fraction",
                       "spatial_information_median", "rsa_spatial"]].copy()  # fmt: skip
    table["spearman_rho_mean_count"] = rho
    return fig, table


# CI budget of fig8_stable: 2 runs x 500 trials (one job, seed 0), snapshots every 100
# (docs/place_cells.md: runtime)
_QUICK_STABLE = {
    "*": [
        "seed=0",
        "task.runs=2",
        "task.protocol.phases.0.trials=500",
        "task.monitors.maps.every=100",
        "task.record.steps=false",
    ]
}

# fig8 --quick: the figure's first two jobs (seeds 0 and 1) for 300 trials, snapshots every 50:
# the collapse of the analysis layer and, where it comes back, the first place cells (seed 0's
# layer dies for good: its trials time out); one process per core, 14 min 46 s on 2 free cores
_QUICK = {
    "*": [
        "seed=range(0,2)",
        "task.protocol.phases.0.trials=300",
        "task.monitors.maps.every=50",
        "task.record.steps=false",
    ]
}

FIGURES = [
    # the original's training settings and an approximation of its room, classified with the
    # original script's box comparison (docs/place_cells.md, "Place cells with the original's
    # settings"); one job per run (seeds 0-4): a finished run is kept when the figure is
    # stopped, and the jobs run side by side (one process per core, or a `cobel run -m` sweep
    # on a cluster, then --from); a run whose layer dies times out on every trial (~3 h here)
    Figure(
        name="fig8",
        title="Place cells in a DQN on a hexagonal maze, the original's training (counts, maps, RSA)",
        runs={"dqn": ["task=place_cells_original", "task.runs=1", "seed=range(0,5)"]},
        quick=_QUICK,
        jobs=0,
        draw=functools.partial(draw, box_measure="area"),
    ),
    # cobel's stabilised training (Q from -5, Adam 3e-5, cobel's scene): the layer survives in
    # most runs (9 of 10 measured), the units code value rather than place; boxes by extent
    Figure(
        name="fig8_stable",
        title="Fig. 8 with cobel's stabilised training (task=place_cells; boxes by extent)",
        runs={"dqn": ["task=place_cells", "task.runs=1", "seed=range(0,5)"]},
        quick=_QUICK_STABLE,
        jobs=0,
        draw=functools.partial(
            draw,
            title="Fig. 8 with cobel's stabilised training: place cells in a DQN "
            "(blob boxes compared by extent)",
        ),
    ),
]
