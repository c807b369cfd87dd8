"""Spectral radii of discrete error dynamics, numpy alone: the design's checks use them, and so does the design
file's load (`ptw_rt.design.file`), which the runtime runs without scipy."""

from __future__ import annotations

import math

import numpy as np


def spectral_radius(M: np.ndarray) -> float:
    """Largest |eigenvalue| (of the largest over a stack of matrices); infinite for a matrix that is not finite (a
    design that overflowed is not stable); 0 for none."""
    if not M.size:
        return 0.0
    if not np.all(np.isfinite(M)):
        return math.inf
    return float(np.max(np.abs(np.linalg.eigvals(M))))
