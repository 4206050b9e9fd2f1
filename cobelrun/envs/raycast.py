"""Compiled segment casting against an arena's wall segments.

One intersection test serves both users: moves in the continuous arena (stop before the first
wall crossed) and boundary-vector cells (distance to the first wall along each direction). They
live in one module because numba's on-disk cache decides staleness per source file: a kernel
that calls a helper from another file would not be recompiled when the helper changes.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, fastmath=False)
def first_wall_hit(
    x: float, y: float, dx: float, dy: float, walls: np.ndarray, t_max: float, touch: bool
) -> float:
    """Smallest ``t`` in ``[0, t_max]`` (``(0, t_max]`` unless ``touch``) at which
    ``(x, y) + t (dx, dy)`` crosses a wall segment; ``inf`` when none does.

    ``walls`` is (m, 4): ``x0, y0, x1, y1`` per segment. Parallel segments never count.
    """
    best = np.inf
    for i in range(walls.shape[0]):
        ex = walls[i, 2] - walls[i, 0]
        ey = walls[i, 3] - walls[i, 1]
        den = dx * ey - dy * ex
        if den == 0.0:
            continue
        wx = walls[i, 0] - x
        wy = walls[i, 1] - y
        t = (wx * ey - wy * ex) / den
        if t > t_max or t >= best or t < 0.0 or (t == 0.0 and not touch):
            continue
        u = (wx * dy - wy * dx) / den
        if 0.0 <= u <= 1.0:
            best = t
    return best


@numba.njit(cache=True, fastmath=False)
def move_kernel(
    x: float, y: float, dx: float, dy: float, walls: np.ndarray, margin: float
) -> tuple[float, float, bool]:
    """Move from ``(x, y)`` by ``(dx, dy)``, stopping ``margin`` before the first wall crossed.

    ``walls`` is (m, 4) ``x0, y0, x1, y1``. Returns the new position and whether a wall was hit.
    """
    t_hit = first_wall_hit(x, y, dx, dy, walls, 1.0, True)
    if t_hit > 1.0:
        return x + dx, y + dy, False
    length = np.sqrt(dx * dx + dy * dy)
    t = max(t_hit - margin / length, 0.0)
    return x + t * dx, y + t * dy, True


@numba.njit(cache=True)
def ray_distances(x: float, y: float, cos_a: np.ndarray, sin_a: np.ndarray,
                  walls: np.ndarray, out: np.ndarray) -> None:  # fmt: skip
    """Distance to the first wall along each direction (inf where none)."""
    for j in range(cos_a.shape[0]):
        out[j] = first_wall_hit(x, y, cos_a[j], sin_a[j], walls, np.inf, False)
