"""Representational similarity analysis of activity maps with rsatoolbox.

The population activity at each probe position (the units' activations, averaged over headings)
is a pattern; its representational dissimilarity matrix (RDM, rsatoolbox ``calc_rdm``) is
compared with the RDM of the positions' spatial distances (rsatoolbox ``compare``, Spearman
rank correlation by default). A population that codes space has a high correlation: positions
that are far apart evoke dissimilar patterns. Recordings analysed the same way (e.g. a place-cell
population's rate maps) are directly comparable.

Needs the ``analysis`` extra (``pip install 'cobelrun[analysis]'``).
"""

from __future__ import annotations

import numpy as np

from cobelrun.errors import CobelError, ConfigError

__all__ = ["population_rdm", "spatial_rdm", "spatial_rsa"]


def _rsatoolbox():
    try:
        import rsatoolbox
    except ImportError:
        raise CobelError(
            "representational similarity analysis needs rsatoolbox: "
            "pip install 'cobelrun[analysis]'"
        ) from None
    return rsatoolbox


def population_rdm(patterns: np.ndarray, method: str = "euclidean"):
    """RDM of ``patterns`` ``(conditions, units)`` (rsatoolbox ``RDMs``; ``method`` as
    rsatoolbox's ``calc_rdm``: euclidean, correlation, mahalanobis, ...)."""
    rsa = _rsatoolbox()
    patterns = np.asarray(patterns, np.float64)
    if patterns.ndim != 2 or patterns.shape[0] < 3:
        raise ConfigError(f"population_rdm needs (conditions >= 3, units), got {patterns.shape}")
    data = rsa.data.Dataset(patterns)
    return rsa.rdm.calc_rdm(data, method=method)


def spatial_rdm(points: np.ndarray):
    """RDM of the Euclidean distances between ``points`` ``(conditions, 2)``."""
    rsa = _rsatoolbox()
    pts = np.asarray(points, np.float64)
    d = np.hypot(*(pts[:, None, :] - pts[None, :, :]).transpose(2, 0, 1))
    iu = np.triu_indices(len(pts), k=1)
    return rsa.rdm.RDMs(d[iu][None, :], dissimilarity_measure="euclidean distance")


def spatial_rsa(
    maps: np.ndarray,
    explored: np.ndarray,
    points: np.ndarray,
    *,
    method: str = "euclidean",
    compare: str = "spearman",
) -> float:
    """Similarity of the population RDM and the spatial-distance RDM for one snapshot.

    Parameters
    ----------
    maps : (units, headings, H, W)
        Activity maps (NaN outside ``explored``).
    explored : (H, W) bool
        Probed positions; their order (row-major) must match ``points``.
    points : (M, 2)
        World positions of the ``M = explored.sum()`` probed bins.
    method : str
        Pattern dissimilarity (rsatoolbox ``calc_rdm``; default euclidean, which stays defined
        when every unit is silent at a position, where the correlation distance is not).
    compare : str
        RDM comparison (rsatoolbox ``compare``; default spearman).

    Returns
    -------
    float
        The comparison value (NaN when the population is silent everywhere).
    """
    rsa = _rsatoolbox()
    maps = np.asarray(maps, np.float64)
    explored = np.asarray(explored, bool)
    patterns = np.nanmean(maps[:, :, explored], axis=1).T  # (positions, units)
    if patterns.shape[0] != len(points):
        raise ConfigError(
            f"spatial_rsa: {patterns.shape[0]} explored positions but {len(points)} points"
        )
    if not np.any(np.nanstd(patterns, axis=0) > 0):
        return float("nan")
    value = rsa.rdm.compare(population_rdm(patterns, method), spatial_rdm(points), method=compare)
    return float(np.asarray(value).reshape(-1)[0])
