"""Exact zero-order-hold discretisation and spectral checks (offline, scipy)."""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla

from ptw_rt.design.stability import spectral_radius

__all__ = ["interpolate", "ramp_response", "spectral_radius", "zoh"]


def zoh(A: np.ndarray, B: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """(Phi, Gamma) with x[k+1] = Phi x[k] + Gamma u[k] for u held over [k dt, (k+1) dt).

    Exact for any A (no step-size condition), unlike forward Euler, which is
    unstable at 10 ms for every pole faster than -200 1/s and inaccurate long before.
    """
    n = A.shape[0]
    B2 = B.reshape(n, -1)
    m = B2.shape[1]
    block = np.zeros((n + m, n + m))
    block[:n, :n] = A
    block[:n, n:] = B2
    expm = sla.expm(block * dt)
    return expm[:n, :n], expm[:n, n:].reshape(B.shape)


def ramp_response(A: np.ndarray, B: np.ndarray, dt: float) -> np.ndarray:
    """Integral of e^{A (dt - s)} B s over [0, dt]: the response to an input ramping from 0 within one step.

    With it an input that varies within the sample (slope known or extrapolated)
    is integrated exactly to first order: x[k+1] = Phi x + Gamma u[k] + Ramp u_dot[k].
    """
    n = A.shape[0]
    B2 = B.reshape(n, -1)
    m = B2.shape[1]
    block = np.zeros((n + 2 * m, n + 2 * m))
    block[:n, :n] = A * dt
    block[:n, n : n + m] = B2 * dt
    block[n : n + m, n + m :] = np.eye(m) * dt
    return sla.expm(block)[:n, n + m :].reshape(B.shape)


def interpolate(grid: np.ndarray, table: np.ndarray, u: float) -> np.ndarray:
    """Linear interpolation of per-grid-point matrices, clamped at the ends (the runtime's rule)."""
    u = float(np.clip(u, grid[0], grid[-1]))
    i = int(np.clip(np.searchsorted(grid, u) - 1, 0, len(grid) - 2))
    w = (u - grid[i]) / (grid[i + 1] - grid[i])
    return (1.0 - w) * table[i] + w * table[i + 1]
