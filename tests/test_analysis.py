"""Place-cell / head-direction classification on synthetic maps with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from cobelrun.analysis.place_cells import (
    PlaceCellCriterion,
    blob_stats,
    head_direction,
    map_table,
    place_cells,
    smooth_map,
    spatial_metrics,
)
from cobelrun.errors import ConfigError

H = W = 25
YY, XX = np.mgrid[0:H, 0:W]
EXPLORED = np.ones((H, W), bool)


def bump(row: float, col: float, width: float = 2.5) -> np.ndarray:
    return np.exp(-((YY - row) ** 2 + (XX - col) ** 2) / (2 * width**2))


def unit(per_heading: list[np.ndarray]) -> np.ndarray:
    return np.stack(per_heading)[None]


def test_one_bump_is_a_place_cell():
    maps = unit([bump(8, 15)] * 6)
    row = place_cells(maps, EXPLORED).iloc[0]
    assert row["is_place_cell"]
    assert row["maps_passed"] == 7
    assert row["n_blobs_mean"] == 1 and all(row[f"n_blobs_h{k}"] == 1 for k in range(6))
    assert row["peak_spread"] == 0
    assert 0.3 < row["largest_blob_fraction"] < 0.5  # 11 of 25 bins wide after smoothing
    assert row["spatial_information"] > 2  # a compact field on 625 bins: several bits
    assert row["sparsity"] < 0.2  # ~ 4 pi w^2 / 625 = 0.13
    assert row["peak_rate"] == pytest.approx(1.0)
    assert 60 < row["field_size"] < 120  # radius ~5.3 bins after smoothing: ~90 bins
    assert row["hd_mrl"] == pytest.approx(0.0, abs=1e-12)  # the same in every direction


def test_two_far_bumps_pass_but_five_bumps_fail():
    two = bump(5, 5) + bump(19, 19)
    st = blob_stats(two, EXPLORED)
    assert st.n_blobs == 2
    assert place_cells(unit([two] * 6), EXPLORED).iloc[0]["is_place_cell"]
    five = sum(bump(r, c, 1.5) for r, c in ((4, 4), (4, 20), (20, 4), (20, 20), (12, 12)))
    row = place_cells(unit([five] * 6), EXPLORED).iloc[0]
    assert row["n_blobs_mean"] == 5
    assert not row["is_place_cell"]
    assert row["maps_passed"] == 0


def test_a_band_across_the_maze_fails_the_box_criterion():
    band = np.exp(-((XX - 12) ** 2) / (2 * 2.0**2)) * np.ones((H, 1))
    st = blob_stats(band, EXPLORED)
    assert st.n_blobs == 1
    assert st.box_fraction == 1.0  # spans every row
    assert not place_cells(unit([band] * 6), EXPLORED).iloc[0]["is_place_cell"]
    # compared by area, a thin band passes: that is why extents are the default
    area = PlaceCellCriterion(box_measure="area")
    assert blob_stats(band, EXPLORED, area).box_fraction == pytest.approx(0.36)
    assert place_cells(unit([band] * 6), EXPLORED, area).iloc[0]["is_place_cell"]


def test_noise_is_not_a_place_cell():
    rng = np.random.default_rng(0)
    noise = rng.random((6, H, W))
    row = place_cells(noise[None], EXPLORED).iloc[0]
    assert not row["is_place_cell"]
    assert row["spatial_information"] < 0.3


def test_bump_that_moves_with_heading_fails_the_peak_spread():
    # a "vector" response: the field sits 8 bins ahead of the agent's heading
    centre = np.array([12.0, 12.0])
    per = []
    for k in range(6):
        th = k * np.pi / 3
        per.append(bump(centre[0] - 8 * np.sin(th), centre[1] + 8 * np.cos(th)))
    row = place_cells(unit(per), EXPLORED).iloc[0]
    assert row["peak_spread"] > 10
    assert not row["is_place_cell"]
    # each heading map alone looks like a place field
    table = map_table(unit(per), EXPLORED)
    assert table[table["map"] != "mean"]["passes"].all()


def test_silent_unit_has_no_blobs_and_nan_metrics():
    row = place_cells(np.zeros((1, 6, H, W)), EXPLORED).iloc[0]
    assert row["n_blobs_mean"] == 0 and not row["is_place_cell"]
    assert np.isnan(row["spatial_information"]) and np.isnan(row["peak_spread"])


def test_explored_mask_limits_the_box_and_ignores_outside_values():
    explored = np.zeros((H, W), bool)
    explored[:, :10] = True  # a narrow corridor
    m = bump(12, 5)
    m[:, 10:] = np.nan  # outside: never looked at
    st = blob_stats(m, explored)
    assert st.n_blobs == 1
    # relative to the corridor's box the field is big
    assert st.box_fraction > blob_stats(bump(12, 5), EXPLORED).box_fraction


def test_smoothing_is_normalised_inside_the_mask():
    explored = np.zeros((H, W), bool)
    explored[5:20, 5:20] = True
    flat = np.ones((H, W))
    sm = smooth_map(flat, explored, 2.0)
    assert np.allclose(sm[explored], 1.0)  # no fall-off at the walls
    assert np.all(sm[~explored] == 0)


def test_head_direction_mrl_and_preferred_direction():
    per = [np.full((H, W), 1.0 if k == 2 else 0.0) for k in range(6)]
    hd = head_direction(unit(per), EXPLORED)
    assert hd.loc[0, "hd_mrl"] == pytest.approx(1.0)
    assert hd.loc[0, "preferred_heading_deg"] == pytest.approx(120.0)
    cos_tuned = [np.full((H, W), 1 + np.cos(k * np.pi / 3)) for k in range(6)]
    # a_h = 1 + cos(theta_h): R = (sum cos^2) / (sum 1) = 3 / 6
    assert head_direction(unit(cos_tuned), EXPLORED).loc[0, "hd_mrl"] == pytest.approx(0.5)


def test_skaggs_information_of_a_uniform_and_a_single_bin_map():
    flat = spatial_metrics(np.ones((H, W)), EXPLORED)
    assert flat["spatial_information"] == pytest.approx(0.0)
    assert flat["sparsity"] == pytest.approx(1.0)
    one = np.zeros((H, W))
    one[3, 4] = 2.0
    single = spatial_metrics(one, EXPLORED)
    assert single["spatial_information"] == pytest.approx(np.log2(H * W))
    assert single["sparsity"] == pytest.approx(1 / (H * W))
    assert single["selectivity"] == pytest.approx(H * W)


def test_metrics_agree_with_opexebo_where_installed():
    opexebo = pytest.importorskip("opexebo")
    m = bump(8, 15) + 0.05
    ours = spatial_metrics(m, EXPLORED)
    theirs = opexebo.analysis.rate_map_stats(m, np.ones((H, W)))
    assert ours["sparsity"] == pytest.approx(theirs["sparsity"])
    assert ours["selectivity"] == pytest.approx(theirs["selectivity"])
    # opexebo sets log2(r_i / r) to 0 for bins below the mean (log argument clipped at 1), so
    # its "information content" is the Skaggs sum over the above-mean bins only; ours is the
    # full sum (docs/place_cells.md)
    ratio = m / m.mean()
    above = ratio > 1
    partial = float(np.sum(ratio[above] * np.log2(ratio[above])) / m.size)
    assert theirs["spatial_information_content"] == pytest.approx(partial)
    assert ours["spatial_information"] < theirs["spatial_information_content"]


def test_bad_input_is_a_config_error():
    with pytest.raises(ConfigError, match="units, headings, H, W"):
        place_cells(np.zeros((6, H, W)), EXPLORED)
    with pytest.raises(ConfigError, match="explored mask has shape"):
        place_cells(np.zeros((1, 6, H, W)), np.ones((5, 5), bool))
    with pytest.raises(ConfigError, match="threshold"):
        PlaceCellCriterion(threshold=1.5)
