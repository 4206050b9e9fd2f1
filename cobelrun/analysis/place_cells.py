"""Place-cell and head-direction classification of spatial activity maps (paper Fig. 8).

Input everywhere is ``maps`` of shape ``(units, headings, H, W)``: the activation of each unit
with the agent placed at each of ``H x W`` grid positions facing each heading, and ``explored``,
an ``(H, W)`` bool mask of the positions that lie inside the maze (positions outside it are
ignored; their values may be NaN).

The place-cell criterion is the one used for the paper's figure (docs/paper-settings.md,
Fig. 8). Each unit has one map per heading plus their mean (7 maps for 6 headings). Each map is

1. smoothed with a Gaussian of ``sigma = 2`` bins (:func:`smooth_map`),
2. thresholded: everything under ``0.25 x`` the map's maximum is set to zero,
3. labelled into connected blobs (``scipy.ndimage.label``, 4-connectivity).

A map *passes* if it has between 1 and 4 blobs and the bounding box of its largest blob is not
larger than ``0.5 x`` the bounding box of the explored area. The paper's settings
(docs/paper-settings.md) do not say how two boxes are compared; the default compares extents
(the blob's box is too large if its width exceeds half the explored box's width *or* its height
half its height), so a band across the maze fails however thin it is. ``box_measure="area"``
compares areas instead. A unit is a place cell if all 7 maps pass and the peaks of the largest
blobs of the heading maps all lie within 10 bins of one another (largest pairwise distance,
``peak_spread``).

Field metrics use the unit's mean map with uniform occupancy over the explored bins (the agent is
placed at every position for the same time): Skaggs spatial information (Skaggs et al. 1993,
bits per unit of activity), sparsity (Skaggs et al. 1996), selectivity (max / mean), peak rate and
field size (bins of the largest blob of the smoothed mean map). They are computed here in numpy;
``tests/test_analysis.py`` checks them against opexebo's ``rate_map_stats`` where opexebo is
installed (docs/place_cells.md says why opexebo is not a dependency).

Head-direction selectivity is the mean resultant length of a unit's mean activity per heading
(:func:`head_direction`): 0 for equal activity in every direction, 1 for activity in only one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import ndimage

from cobelrun.errors import ConfigError

__all__ = [
    "PlaceCellCriterion",
    "blob_stats",
    "box_fraction",
    "head_direction",
    "map_table",
    "place_cells",
    "smooth_map",
    "spatial_metrics",
]


#: How the largest blob's bounding box is compared with the explored area's.
BOX_MEASURES = ("extent", "area")


@dataclass(frozen=True)
class PlaceCellCriterion:
    """Parameters of the place-cell criterion (defaults: the paper's; docs/paper-settings.md,
    Fig. 8).

    Attributes
    ----------
    sigma : float
        Gaussian smoothing width in grid bins (2).
    threshold : float
        Fraction of a map's maximum below which it is set to zero before labelling (0.25).
    max_blobs : int
        A map with more blobs fails (4); a map with none fails too.
    max_box_fraction : float
        A map fails if its largest blob's bounding box exceeds this fraction of the explored
        area's bounding box (0.5), measured by ``box_measure``.
    box_measure : {"extent", "area"}
        ``extent``: the larger of the width ratio and the height ratio of the two boxes
        (default); ``area``: the ratio of their areas.
    max_peak_spread : float
        Largest allowed distance in bins between the peaks of the heading maps' largest
        blobs (10).
    """

    sigma: float = 2.0
    threshold: float = 0.25
    max_blobs: int = 4
    max_box_fraction: float = 0.5
    max_peak_spread: float = 10.0
    box_measure: str = "extent"

    def __post_init__(self) -> None:
        if self.box_measure not in BOX_MEASURES:
            raise ConfigError(
                f"place-cell box_measure {self.box_measure!r} is unknown; allowed: 'extent', 'area'"
            )
        if not self.sigma >= 0:
            raise ConfigError(f"place-cell sigma must be >= 0 bins, got {self.sigma}")
        if not 0 < self.threshold < 1:
            raise ConfigError(f"place-cell threshold must be in (0, 1), got {self.threshold}")
        if int(self.max_blobs) < 1:
            raise ConfigError(f"place-cell max_blobs must be >= 1, got {self.max_blobs}")
        if not 0 < self.max_box_fraction <= 1:
            raise ConfigError(
                f"place-cell max_box_fraction must be in (0, 1], got {self.max_box_fraction}"
            )
        if not self.max_peak_spread >= 0:
            raise ConfigError(
                f"place-cell max_peak_spread must be >= 0 bins, got {self.max_peak_spread}"
            )


def _check(maps: np.ndarray, explored: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    maps = np.asarray(maps, dtype=np.float64)
    explored = np.asarray(explored, dtype=bool)
    if maps.ndim != 4:
        raise ConfigError(f"maps must have shape (units, headings, H, W), got {maps.shape}")
    if explored.shape != maps.shape[2:]:
        raise ConfigError(
            f"explored mask has shape {explored.shape}, the maps are {maps.shape[2:]} (H, W)"
        )
    if not explored.any():
        raise ConfigError("the explored mask is empty: no position lies inside the maze")
    return maps, explored


def smooth_map(rate_map: np.ndarray, explored: np.ndarray, sigma: float = 2.0) -> np.ndarray:
    """Gaussian smoothing restricted to the explored bins (normalised convolution).

    ``smooth(m * mask) / smooth(mask)`` inside the mask, 0 outside: bins next to a wall are
    averaged over their explored neighbours only, so the border is not pulled towards zero
    (plain zero-padded smoothing would). Where every bin is explored and far from the edges
    this is ``scipy.ndimage.gaussian_filter``.
    """
    m = np.where(explored, np.nan_to_num(np.asarray(rate_map, np.float64)), 0.0)
    if sigma == 0:
        return m
    w = ndimage.gaussian_filter(explored.astype(np.float64), sigma, mode="constant")
    s = ndimage.gaussian_filter(m, sigma, mode="constant")
    out = np.zeros_like(m)
    ok = explored & (w > 1e-12)
    out[ok] = s[ok] / w[ok]
    return out


def _box(mask: np.ndarray) -> tuple[int, int]:
    """(height, width) in bins of the bounding box of ``mask``'s True bins."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return 0, 0
    return int(rows[-1] - rows[0] + 1), int(cols[-1] - cols[0] + 1)


def box_fraction(blob: np.ndarray, explored: np.ndarray, measure: str = "extent") -> float:
    """Size of ``blob``'s bounding box relative to ``explored``'s (see ``box_measure``)."""
    (bh, bw), (eh, ew) = _box(blob), _box(explored)
    if measure == "area":
        return bh * bw / (eh * ew)
    return max(bh / eh, bw / ew)


@dataclass(frozen=True)
class BlobStats:
    """Blobs of one thresholded map.

    Attributes
    ----------
    n_blobs : int
    largest_size : int
        Bins of the largest blob (0 without blobs).
    box_fraction : float
        Bounding box of the largest blob relative to the explored region's
        (:func:`box_fraction`; NaN without blobs).
    peak : tuple (row, col) or None
        Bin of the smoothed map's maximum inside the largest blob.
    """

    n_blobs: int
    largest_size: int
    box_fraction: float
    peak: tuple[int, int] | None


def blob_stats(
    rate_map: np.ndarray, explored: np.ndarray, criterion: PlaceCellCriterion | None = None
) -> BlobStats:
    """Smooth, threshold and label one ``(H, W)`` map (steps 1-3 of the module docstring)."""
    crit = criterion or PlaceCellCriterion()
    explored = np.asarray(explored, bool)
    sm = smooth_map(rate_map, explored, crit.sigma)
    top = sm[explored].max()
    if not np.isfinite(top) or top <= 0:
        return BlobStats(0, 0, float("nan"), None)
    above = explored & (sm >= crit.threshold * top)
    labels, n = ndimage.label(above)
    if n == 0:
        return BlobStats(0, 0, float("nan"), None)
    sizes = np.bincount(labels.ravel())[1:]
    biggest = int(np.argmax(sizes)) + 1
    blob = labels == biggest
    frac = box_fraction(blob, explored, crit.box_measure)
    peak = np.unravel_index(np.argmax(np.where(blob, sm, -np.inf)), sm.shape)
    return BlobStats(int(n), int(sizes[biggest - 1]), float(frac), (int(peak[0]), int(peak[1])))


def _passes(b: BlobStats, crit: PlaceCellCriterion) -> bool:
    return 1 <= b.n_blobs <= crit.max_blobs and b.box_fraction <= crit.max_box_fraction


def _spread(peaks: list[tuple[int, int] | None]) -> float:
    if any(p is None for p in peaks) or not peaks:
        return float("nan")
    pts = np.asarray(peaks, dtype=np.float64)
    d = np.hypot(*(pts[:, None, :] - pts[None, :, :]).transpose(2, 0, 1))
    return float(d.max())


def map_table(
    maps: np.ndarray, explored: np.ndarray, criterion: PlaceCellCriterion | None = None
) -> pd.DataFrame:
    """One row per (unit, map): the blob statistics behind :func:`place_cells`.

    ``map`` is the heading index (0..headings-1) or ``"mean"``; columns ``n_blobs``,
    ``largest_blob_size``, ``largest_blob_fraction``, ``peak_row``, ``peak_col``, ``passes``.
    """
    crit = criterion or PlaceCellCriterion()
    maps, explored = _check(maps, explored)
    rows = []
    for u in range(maps.shape[0]):
        stack = [*maps[u], np.nanmean(np.where(explored, maps[u], np.nan), axis=0)]
        for k, m in enumerate(stack):
            b = blob_stats(m, explored, crit)
            rows.append({
                "unit": u, "map": "mean" if k == maps.shape[1] else str(k),
                "n_blobs": b.n_blobs, "largest_blob_size": b.largest_size,
                "largest_blob_fraction": b.box_fraction,
                "peak_row": -1 if b.peak is None else b.peak[0],
                "peak_col": -1 if b.peak is None else b.peak[1],
                "passes": _passes(b, crit),
            })  # fmt: skip
    return pd.DataFrame(rows)


def spatial_metrics(rate_map: np.ndarray, explored: np.ndarray) -> dict[str, float]:
    """Skaggs spatial information, sparsity, selectivity and peak rate of one map.

    Occupancy is uniform over the explored bins; negative activations are clipped to 0 (rates
    are non-negative; ReLU units already are).

    - spatial information (Skaggs et al. 1993): ``sum_i p_i (r_i / r) log2(r_i / r)`` with
      ``r = sum_i p_i r_i``, in bits per unit of activity (bits/spike for spiking data);
    - sparsity (Skaggs et al. 1996): ``(sum_i p_i r_i)^2 / sum_i p_i r_i^2``, in (0, 1];
      small for a compact field;
    - selectivity: ``max_i r_i / r``.

    A silent map (mean 0) gives NaN information, sparsity and selectivity.
    """
    r = np.clip(
        np.nan_to_num(np.asarray(rate_map, np.float64)[np.asarray(explored, bool)]), 0, None
    )
    p = 1.0 / r.size
    mean = float(r.sum() * p)
    peak = float(r.max())
    if mean <= 0:
        nan = float("nan")
        return {"spatial_information": nan, "sparsity": nan, "selectivity": nan, "peak_rate": peak}
    ratio = r / mean
    with np.errstate(divide="ignore", invalid="ignore"):
        info = float(np.sum(np.where(ratio > 0, p * ratio * np.log2(ratio), 0.0)))
    sparsity = mean**2 / float(np.sum(p * r**2))
    return {"spatial_information": info, "sparsity": sparsity, "selectivity": peak / mean,
            "peak_rate": peak}  # fmt: skip


def head_direction(
    maps: np.ndarray, explored: np.ndarray, headings_rad: np.ndarray | None = None
) -> pd.DataFrame:
    """Head-direction selectivity per unit: mean resultant length over headings.

    ``a_h`` is the unit's mean activation (clipped at 0) over the explored positions at heading
    ``h``; ``mrl = |sum_h a_h exp(i theta_h)| / sum_h a_h`` (0: no preferred direction,
    1: active in one direction only) and ``preferred_heading_deg`` the angle of that sum.
    ``headings_rad`` default: evenly spaced from 0 (6 headings: 0, 60, ..., 300 degrees).

    Returns one row per unit: ``unit``, ``hd_mrl``, ``preferred_heading_deg``.
    """
    maps, explored = _check(maps, explored)
    n_head = maps.shape[1]
    theta = (
        np.arange(n_head) * (2 * np.pi / n_head)
        if headings_rad is None
        else np.asarray(headings_rad, np.float64)
    )
    if theta.shape != (n_head,):
        raise ConfigError(f"headings_rad needs {n_head} angles, got {theta.shape}")
    a = np.clip(np.nan_to_num(maps[:, :, explored]), 0, None).mean(axis=2)  # (units, headings)
    total = a.sum(axis=1)
    vec = (a * np.exp(1j * theta)[None, :]).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mrl = np.where(total > 0, np.abs(vec) / total, np.nan)
    pref = np.where(total > 0, np.rad2deg(np.angle(vec)) % 360.0, np.nan)
    return pd.DataFrame({"unit": np.arange(maps.shape[0]), "hd_mrl": mrl,
                         "preferred_heading_deg": pref})  # fmt: skip


def place_cells(
    maps: np.ndarray,
    explored: np.ndarray,
    criterion: PlaceCellCriterion | None = None,
    headings_rad: np.ndarray | None = None,
) -> pd.DataFrame:
    """Classify every unit of ``maps`` ``(units, headings, H, W)``; one row per unit.

    Parameters
    ----------
    maps : (units, headings, H, W) array
        Activity maps; values outside ``explored`` are ignored.
    explored : (H, W) bool array
        Positions inside the maze.
    criterion : PlaceCellCriterion, optional
        Default: the paper's (module docstring).
    headings_rad : (headings,) array, optional
        Heading angles for the head-direction columns (default evenly spaced from 0).

    Returns
    -------
    pandas.DataFrame
        ``unit``; ``n_blobs_h0`` .. ``n_blobs_h{D-1}`` and ``n_blobs_mean`` (blobs per map);
        ``largest_blob_fraction`` (the largest over the maps; NaN if a map has no blob);
        ``maps_passed`` (of ``D + 1``); ``peak_spread`` (bins; NaN if a heading map has no
        blob); ``is_place_cell``; from the mean map ``spatial_information``, ``sparsity``,
        ``selectivity``, ``peak_rate``, ``field_size`` (bins of its largest blob),
        ``field_fraction`` (of the explored bins); ``hd_mrl``, ``preferred_heading_deg``.
    """
    crit = criterion or PlaceCellCriterion()
    maps, explored = _check(maps, explored)
    n_units, n_head = maps.shape[:2]
    hd = head_direction(maps, explored, headings_rad)
    n_explored = int(explored.sum())
    rows = []
    for u in range(n_units):
        mean_map = np.nanmean(np.where(explored, maps[u], np.nan), axis=0)
        stats = [blob_stats(m, explored, crit) for m in (*maps[u], mean_map)]
        passed = [_passes(b, crit) for b in stats]
        spread = _spread([b.peak for b in stats[:n_head]])
        fractions = [b.box_fraction for b in stats]
        row: dict[str, float | int | bool] = {"unit": u}
        for k, b in enumerate(stats[:n_head]):
            row[f"n_blobs_h{k}"] = b.n_blobs
        row["n_blobs_mean"] = stats[-1].n_blobs
        row["largest_blob_fraction"] = (
            float("nan") if any(np.isnan(fractions)) else float(max(fractions))
        )
        row["maps_passed"] = int(sum(passed))
        row["peak_spread"] = spread
        row["is_place_cell"] = bool(all(passed) and spread <= crit.max_peak_spread)
        row.update(spatial_metrics(mean_map, explored))
        row["field_size"] = stats[-1].largest_size
        row["field_fraction"] = stats[-1].largest_size / n_explored
        rows.append(row)
    out = pd.DataFrame(rows)
    out["hd_mrl"] = hd["hd_mrl"].to_numpy()
    out["preferred_heading_deg"] = hd["preferred_heading_deg"].to_numpy()
    return out
