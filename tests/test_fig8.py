"""The fig8 figure on synthetic activity maps with a known number of place cells per snapshot."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cobelrun.analysis.maps import GRID_TABLE, MAPS_TABLE, classify_snapshots, probe_grid
from cobelrun.envs import topology as topo

pytest.importorskip("rsatoolbox")

N_UNITS, HEADS = 10, np.arange(6) * 60.0


def synthetic_run_folder(path: Path, place_cells_at: dict[int, int], seed: int) -> None:
    """A run folder whose snapshot at trial t has ``place_cells_at[t]`` bump units; the other
    units are noise."""
    rng = np.random.default_rng(seed)
    grid = probe_grid(topo.hexagonal().positions)
    iy, ix = np.nonzero(grid.inside)
    yy, xx = np.mgrid[0 : grid.ny, 0 : grid.nx]
    rows = []
    for trial, n_cells in place_cells_at.items():
        for u in range(N_UNITS):
            if u < n_cells:
                cy, cx = rng.uniform(5, 20, 2)
                m = np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * 2.0**2))
                stack = np.repeat(m[None], len(HEADS), axis=0)
            else:
                stack = rng.random((len(HEADS), grid.ny, grid.nx))
            for h, deg in enumerate(HEADS):
                rows.append(pd.DataFrame({
                    "run": 0, "trial": trial, "layer": "analysis", "unit": u, "heading": deg,
                    "ix": ix, "iy": iy, "x": grid.x_centres[ix], "y": grid.y_centres[iy],
                    "value": stack[h, iy, ix],
                }))  # fmt: skip
    path.mkdir(parents=True)
    pd.concat(rows).to_parquet(path / f"{MAPS_TABLE}.parquet")
    gy, gx = np.indices((grid.ny, grid.nx))
    pd.DataFrame({
        "ix": gx.ravel(), "iy": gy.ravel(),
        "x0": grid.x_edges[gx.ravel()], "x1": grid.x_edges[gx.ravel() + 1],
        "y0": grid.y_edges[gy.ravel()], "y1": grid.y_edges[gy.ravel() + 1],
        "explored": grid.inside.ravel(),
    }).to_parquet(path / f"{GRID_TABLE}.parquet")  # fmt: skip


def test_classify_snapshots_counts_the_place_cells(tmp_path):
    from cobelrun.analysis.maps import load_activity_maps

    synthetic_run_folder(tmp_path / "r", {0: 0, 800: 3, 1600: 6}, seed=0)
    df, grid = load_activity_maps(tmp_path / "r")
    units, snaps = classify_snapshots(df, grid)
    assert snaps["place_cells"].tolist() == [0, 3, 6]
    assert snaps["units"].tolist() == [N_UNITS] * 3
    assert len(units) == 3 * N_UNITS
    assert np.isfinite(snaps["rsa_spatial"]).all()


def test_spatial_rsa_of_tiled_place_fields_and_of_noise():
    from cobelrun.analysis.rsa import spatial_rsa

    grid = probe_grid(topo.hexagonal().positions)
    yy, xx = np.mgrid[0 : grid.ny, 0 : grid.nx]
    centres = [(a, b) for a in np.linspace(2, 22, 6) for b in np.linspace(2, 22, 6)]
    tiled = np.stack([np.exp(-((yy - a) ** 2 + (xx - b) ** 2) / (2 * 3.0**2)) for a, b in centres])
    tiled = np.repeat(tiled[:, None], 6, axis=1)
    assert spatial_rsa(tiled, grid.inside, grid.points()) > 0.3
    noise = np.random.default_rng(0).random((36, 6, grid.ny, grid.nx))
    assert abs(spatial_rsa(noise, grid.inside, grid.points())) < 0.05
    assert np.isnan(spatial_rsa(np.zeros((5, 6, grid.ny, grid.nx)), grid.inside, grid.points()))


def test_fig8_draw_writes_counts_and_spearman(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cobelrun.figures.registry import FigureData, RunRef, get

    refs = []
    for job, counts in enumerate(({0: 0, 800: 2, 1600: 5}, {0: 1, 800: 3, 1600: 4})):
        synthetic_run_folder(tmp_path / f"r{job}", counts, seed=job)
        refs.append(RunRef("dqn", job, (), {}, tmp_path / f"r{job}", "hash"))
    fig, table = get("fig8_stable").draw(FigureData(runs={"dqn": refs}))
    plt.close(fig)
    assert {"trial", "place_cells", "units", "rsa_spatial", "spearman_rho_mean_count"} <= set(table)
    assert len(table) == 6
    assert table.groupby("trial")["place_cells"].mean().tolist() == [0.5, 2.5, 4.5]
    assert table["spearman_rho_mean_count"].iloc[0] == pytest.approx(1.0)


def test_fig8_maps_panel_shows_the_run_with_the_most_place_cells(tmp_path):
    """Panel D: the place cells of the run with the most of them at its last snapshot (a run
    whose layer died shows nothing), here the second."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cobelrun.figures.registry import FigureData, RunRef, get

    refs = []
    for job, counts in enumerate(({0: 0, 800: 0}, {0: 0, 800: 3})):
        synthetic_run_folder(tmp_path / f"r{job}", counts, seed=job)
        refs.append(RunRef("dqn", job, (), {}, tmp_path / f"r{job}", "hash"))
    fig, table = get("fig8").draw(FigureData(runs={"dqn": refs}))
    titles = [sub.get_suptitle() for sub in fig.subfigs]
    plt.close(fig)
    assert table.groupby("run")["place_cells"].max().tolist() == [0, 3]
    assert "D  activity maps at trial 800 (run 1; place cells)" in titles


def test_fig8_compares_boxes_by_area_and_fig8_stable_by_extent(tmp_path):
    """fig8 classifies with the original script's box comparison: a band across most of the
    maze's width (21% of its area) passes by area; fig8_stable compares extents: it fails."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cobelrun.analysis.maps import load_activity_maps
    from cobelrun.figures.registry import FigureData, RunRef, get

    synthetic_run_folder(tmp_path / "r", {0: 0, 800: 2}, seed=0)
    df, grid = load_activity_maps(tmp_path / "r")
    df = df.reset_index(drop=True)
    band = np.zeros((grid.ny, grid.nx))
    band[9:16, 3:22] = 1.0  # 7 bins high, 19 wide: > half the width, 21% of the area
    rows = ((df.trial == 800) & (df.unit == N_UNITS - 1)).to_numpy()  # a noise unit
    df.loc[rows, "value"] = band[df.loc[rows, "iy"], df.loc[rows, "ix"]]
    df.to_parquet(tmp_path / "r" / f"{MAPS_TABLE}.parquet")
    ref = RunRef("dqn", 0, (), {}, tmp_path / "r", "hash")
    _, by_extent = get("fig8_stable").draw(FigureData(runs={"dqn": [ref]}))
    _, by_area = get("fig8").draw(FigureData(runs={"dqn": [ref]}))
    plt.close("all")
    assert by_extent["place_cells"].tolist() == [0, 2]
    assert by_area["place_cells"].tolist() == [0, 3]
