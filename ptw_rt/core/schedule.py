"""Gain scheduling over forward speed: where a speed sits on the design grid, and interpolation.

The design file stores every matrix per grid speed; the runtime interpolates
linearly between the two neighbours (clamped at the ends), the same rule
`ptw-rt design --check` verifies for stability between grid points.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def grid_position(grid: np.ndarray, u: float) -> tuple[int, float]:
    """Index of the grid interval holding u and the weight of its upper end (uniform grid, clamped)."""
    n = grid.shape[0]
    step = (grid[n - 1] - grid[0]) / (n - 1)
    s = (u - grid[0]) / step
    if not s > 0.0:  # also catches NaN
        return 0, 0.0
    if s >= n - 1:
        return n - 2, 1.0
    i = int(s)
    return i, s - i


@njit(cache=True, inline="always")  # an array passed to a call costs atomic reference counting
def lerp(table: np.ndarray, i: int, w: float, r: int, c: int) -> float:
    """Entry (r, c) of the matrix interpolated between grid points i and i + 1."""
    return (1.0 - w) * table[i, r, c] + w * table[i + 1, r, c]
