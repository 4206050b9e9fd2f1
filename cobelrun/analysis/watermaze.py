"""Morris water maze measures: plain functions over pose arrays and trial tables.

Every function takes positions as an (n, 2) or (n, 3) array (x, y[, heading]) of one trial, the
start position first, in world units (metres in the water-maze task), and the platform as a
centre and radius. :func:`trial_measures` applies them to every trial of a run and returns a
DataFrame; :class:`cobelrun.monitors.watermaze.WaterMazeMonitor` writes the same numbers as
columns of ``trials.parquet``.

Definitions:

- escape latency: time to reach the platform, ``steps * dt`` (seconds); a trial that times out
  counts its full length (Morris 1984);
- path length: summed distance swum;
- mean distance to the platform: the mean over the trial's positions of the distance to the
  platform centre (Gallagher, Burwell & Burchinal 1993's proximity measure, sampled every step);
- quadrant occupancy: the fraction of positions in each of four 90-degree sectors around the
  pool centre, the target sector centred on the platform; chance is 0.25 (docs/paper-settings.md);
- platform crossings: entries into the platform's area (a probe trial has no platform, so these
  are passes over where it was);
- annulus crossings: the same count for the platform's site and its three rotations by 90
  degrees about the pool centre; the annulus crossing index is the target count minus the mean
  of the other three (Spooner et al. 1994's "annulus crossing index").
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

#: quadrant labels in order target, then counter-clockwise from it
QUADRANTS = ("target", "adjacent_ccw", "opposite", "adjacent_cw")

__all__ = [
    "QUADRANTS",
    "add_days",
    "annulus_crossings",
    "escape_latency_s",
    "mean_distance_to_platform",
    "path_length",
    "platform_crossings",
    "quadrant_occupancy",
    "split_trials",
    "target_quadrant_fraction",
    "trial_measures",
]


def _xy(positions: np.ndarray) -> np.ndarray:
    p = np.asarray(positions, np.float64)
    if p.ndim != 2 or p.shape[1] not in (2, 3):
        raise ValueError(f"positions must be an (n, 2) or (n, 3) array, got shape {p.shape}")
    return p[:, :2]


def escape_latency_s(steps: np.ndarray | int, dt: float) -> np.ndarray:
    """Escape latency in seconds: steps taken times the step duration ``dt``."""
    return np.asarray(steps, np.float64) * float(dt)


def path_length(positions: np.ndarray) -> float:
    """Total distance travelled along the positions (world units)."""
    xy = _xy(positions)
    if len(xy) < 2:
        return 0.0
    return float(np.sum(np.hypot(*np.diff(xy, axis=0).T)))


def mean_distance_to_platform(positions: np.ndarray, platform: Sequence[float]) -> float:
    """Mean distance of the positions to the platform centre (Gallagher et al. 1993)."""
    xy = _xy(positions)
    return float(np.mean(np.hypot(xy[:, 0] - platform[0], xy[:, 1] - platform[1])))


def quadrant_occupancy(
    positions: np.ndarray, platform: Sequence[float], centre: Sequence[float] = (0.0, 0.0)
) -> dict[str, float]:
    """Fraction of positions in each quadrant: ``target`` (the 90-degree sector centred on the
    platform's direction from the pool centre), then ``adjacent_ccw``, ``opposite``,
    ``adjacent_cw``. Positions exactly at the centre count towards none."""
    xy = _xy(positions)
    target = np.arctan2(platform[1] - centre[1], platform[0] - centre[0])
    ang = np.arctan2(xy[:, 1] - centre[1], xy[:, 0] - centre[0]) - target
    sector = np.floor(((ang + np.pi / 4) % (2 * np.pi)) / (np.pi / 2)).astype(np.int64) % 4
    at_centre = np.hypot(xy[:, 0] - centre[0], xy[:, 1] - centre[1]) == 0
    counts = np.bincount(sector[~at_centre], minlength=4)
    n = max(len(xy), 1)
    return {q: float(counts[i]) / n for i, q in enumerate(QUADRANTS)}


def target_quadrant_fraction(
    positions: np.ndarray, platform: Sequence[float], centre: Sequence[float] = (0.0, 0.0)
) -> float:
    """Fraction of positions in the target quadrant (chance 0.25)."""
    return quadrant_occupancy(positions, platform, centre)["target"]


def platform_crossings(positions: np.ndarray, platform: Sequence[float], radius: float) -> int:
    """Number of entries into the disc of ``radius`` around ``platform`` (a start inside
    counts as one)."""
    xy = _xy(positions)
    inside = np.hypot(xy[:, 0] - platform[0], xy[:, 1] - platform[1]) <= radius
    if not inside.size:
        return 0
    return int(inside[0]) + int(np.sum(inside[1:] & ~inside[:-1]))


def annulus_crossings(
    positions: np.ndarray,
    platform: Sequence[float],
    radius: float,
    centre: Sequence[float] = (0.0, 0.0),
) -> dict[str, float]:
    """Crossings of the platform site and of its rotations by 90, 180, 270 degrees about the
    pool centre (keys as :data:`QUADRANTS`), and ``index``: target minus the mean of the
    other three."""
    px, py = platform[0] - centre[0], platform[1] - centre[1]
    out: dict[str, float] = {}
    for k, q in enumerate(QUADRANTS):
        a = k * np.pi / 2
        site = (
            centre[0] + px * np.cos(a) - py * np.sin(a),
            centre[1] + px * np.sin(a) + py * np.cos(a),
        )
        out[q] = float(platform_crossings(positions, site, radius))
    out["index"] = out["target"] - np.mean([out[q] for q in QUADRANTS[1:]])
    return out


def split_trials(poses: np.ndarray, steps: np.ndarray) -> list[np.ndarray]:
    """Cut time-ordered poses (each trial's start, then one per step) into per-trial arrays."""
    bounds = np.concatenate([[0], np.cumsum(np.asarray(steps, np.int64) + 1)])
    if bounds[-1] != len(poses):
        raise ValueError(
            f"{len(poses)} poses do not match steps summing to {bounds[-1] - len(steps)}"
        )
    return [poses[bounds[i] : bounds[i + 1]] for i in range(len(steps))]


def trial_measures(
    trials: Sequence[np.ndarray],
    platform: Sequence[float],
    platform_radius: float,
    dt: float,
    centre: Sequence[float] = (0.0, 0.0),
    crossing_radius: float | None = None,
) -> pd.DataFrame:
    """Every measure for each trial's positions: one row per trial.

    Parameters
    ----------
    trials
        Per-trial (n_steps + 1, 2 or 3) positions (start first).
    platform, platform_radius
        Platform centre and radius (the target; in a probe, where the platform was).
    dt
        Seconds per step.
    centre
        Pool centre (quadrants and annulus sites are taken about it).
    crossing_radius
        Radius of the crossing zones (default the platform radius).
    """
    r = platform_radius if crossing_radius is None else crossing_radius
    rows = []
    for p in trials:
        occ = quadrant_occupancy(p, platform, centre)
        ann = annulus_crossings(p, platform, r, centre)
        rows.append({
            "escape_latency_s": float(escape_latency_s(len(p) - 1, dt)),
            "path_length": path_length(p),
            "mean_distance_to_platform": mean_distance_to_platform(p, platform),
            **{f"{q}_quadrant_fraction": occ[q] for q in QUADRANTS},
            "platform_crossings": int(ann["target"]),
            "annulus_crossing_index": float(ann["index"]),
        })  # fmt: skip
    return pd.DataFrame(rows, columns=list(MEASURE_COLUMNS))


#: the columns of :func:`trial_measures` (and of the water-maze monitor)
MEASURE_COLUMNS = (
    "escape_latency_s",
    "path_length",
    "mean_distance_to_platform",
    *(f"{q}_quadrant_fraction" for q in QUADRANTS),
    "platform_crossings",
    "annulus_crossing_index",
)


def add_days(trials: pd.DataFrame, trials_per_day: int = 4) -> pd.DataFrame:
    """A copy of a trials table with ``day`` (1-based within each phase) from ``trial_in_phase``."""
    out = trials.copy()
    out["day"] = (out["trial_in_phase"].to_numpy() - 1) // int(trials_per_day) + 1
    return out
