"""Discrete homogeneous differentiator (Livne & Levant 2014) for the 100 Hz hot path.

Levant's arbitrary-order robust exact differentiator of order ``n`` estimates
``f, f', ..., f^(n)`` of a signal whose ``(n+1)``-th derivative is bounded by
``L``. Seed 000 (eq. 8, 13-15) runs it, in Levant's *recursive* form, on the
UIHOSMO output errors: order 3 on the steer channel, order 2 on the yaw-rate
channel, both with the same ``L`` (the paper's ``lambda = 5000``).

The product samples at ``tau = 10 ms``. Forward Euler of the continuous form
drops the ``tau^j/j! z_{i+j}`` terms that a sampled polynomial needs, so its
estimates pick up a bias that depends on the signal, not on ``L``. The
*homogeneous discrete differentiator* (HDD) of

    D. Livne, A. Levant, "Proper discretization of homogeneous differentiators",
    Automatica 50(8), 2007-2014, 2014

keeps those Taylor terms and uses the non-recursive form::

    s = z_0(k) - f(k)
    z_i(k+1) = z_i(k) + sum_{j=1}^{n-i} tau^j/j! z_{i+j}(k)
               - tau lam_{n-i} L^{(i+1)/(n+1)} |s|^{(n-i)/(n+1)} sign(s),   i = 0..n-1
    z_n(k+1) = z_n(k) - tau lam_0 L sign(s)

Properties used by the estimator and checked in ``tests/test_differentiator.py``:

* Polynomial exactness: for ``f`` a polynomial of degree ``<= n`` the error
  ``e_i = z_i - f^(i)`` obeys exactly the HDD with input ``f = 0`` (the Taylor
  step is exact), so the error does not depend on the signal; in particular
  the true derivatives are an invariant trajectory.
* Asymptotic accuracy, noise-free, ``|f^(n+1)| <= L``:
  ``|z_i - f^(i)| <= mu_i L tau^(n+1-i)``.
* With sample noise (or quantisation) bounded by ``eps`` the bound becomes
  ``mu_i L^(i/(n+1)) eps^((n+1-i)/(n+1))`` (whichever of the two is larger).

Gains. Levant's recursive sequence (Levant 2003, IJC 76(9/10)) is
``lam_rec = 1.1, 1.5, 2, 3, 5, 8`` (``lam_rec[j]`` multiplies the level with
exponent ``j/(j+1)``); seed 000 eq. 13/14 use exactly its first 4 / 3 entries.
The non-recursive gains follow by substituting each level into the next::

    lam[n] = lam_rec[n],   lam[i] = lam_rec[i] * lam[i+1]^(i/(i+1)),  i = n-1..0

which reproduces the published non-recursive table (Livne & Levant 2014;
Levant 2017/2018): ``n=1: 1.1, 1.5``; ``n=2: 1.1, 2.12, 2``;
``n=3: 1.1, 3.06, 4.16, 3``; ``n=4: 1.1, 4.57, 9.30, 10.03, 5``. ``HDD_LAMBDA``
holds the unrounded conversions, ascending in ``i`` (``lam[0]`` is the sign term).

Robustness contract of the jitted steps (no allocation, no exceptions):
a non-finite sample ``f``, a non-finite or negative ``L``, a non-finite or
non-positive ``tau`` or ``substeps < 1`` leave the state untouched ("hold").
``L = 0`` is legal (pure Taylor prediction, no correction). If an update
would overflow to a non-finite state (absurd inputs such as ``f ~ 1e308``),
the state is re-initialised on the current sample instead.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# Levant's recursive gain sequence lam_rec[0..5] (Levant 2003). Seed 000 eq. 13 uses (3, 2, 1.5, 1.1) top-down.
LEVANT_LAMBDA_RECURSIVE = np.array([1.1, 1.5, 2.0, 3.0, 5.0, 8.0])
MAX_ORDER = 4


def recursive_to_nonrecursive(lam_rec: np.ndarray, n: int) -> np.ndarray:
    """Non-recursive gains ``lam[0..n]`` of the order-``n`` differentiator from recursive ones ``lam_rec[0..n]``.

    The recursive level ``i`` reads ``lam_rec[n-i] L^(1/(n+1-i)) |z_i - v_{i-1}|^((n-i)/(n+1-i))``; substituting
    ``z_i - v_{i-1}`` from the level above gives ``lam[n-i]`` of the non-recursive form.
    """
    lam_rec = np.asarray(lam_rec, dtype=np.float64)
    if n < 0 or lam_rec.shape[0] < n + 1:
        raise ValueError(f"need {n + 1} recursive gains for order {n}, got {lam_rec.shape[0]}")
    lam = np.empty(n + 1)
    lam[n] = lam_rec[n]
    for i in range(n - 1, -1, -1):
        lam[i] = lam_rec[i] * lam[i + 1] ** (i / (i + 1.0))
    return lam


# Recursive (seed 000's form) and non-recursive (HDD) gains for orders 1..4, ascending in i.
HDD_LAMBDA_RECURSIVE = {n: LEVANT_LAMBDA_RECURSIVE[: n + 1].copy() for n in range(1, MAX_ORDER + 1)}
HDD_LAMBDA = {n: recursive_to_nonrecursive(LEVANT_LAMBDA_RECURSIVE, n) for n in range(1, MAX_ORDER + 1)}


def hdd_lambda(n: int, recursive: bool = False) -> np.ndarray:
    """A fresh copy of the standard gains for order ``n`` (1..4): non-recursive (HDD) or recursive (Euler form)."""
    table = HDD_LAMBDA_RECURSIVE if recursive else HDD_LAMBDA
    if n not in table:
        raise ValueError(f"differentiator order must be 1..{MAX_ORDER}, got {n}")
    return table[n].copy()


# ----- jitted kernels ------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def hdd_init(z: np.ndarray, f: float) -> None:
    """Initialise on a sample: ``z_0 = f``, derivatives 0. A non-finite ``f`` gives ``z_0 = 0``."""
    for i in range(z.shape[0]):
        z[i] = 0.0
    if math.isfinite(f):
        z[0] = f


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _valid_inputs(f: float, L: float, tau: float, substeps: int) -> bool:
    return math.isfinite(f) and math.isfinite(L) and L >= 0.0 and math.isfinite(tau) and tau > 0.0 and substeps >= 1


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _state_finite(z: np.ndarray) -> bool:
    for i in range(z.shape[0]):
        if not math.isfinite(z[i]):
            return False
    return True


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _hdd_update(z: np.ndarray, f: float, L: float, h: float, lam: np.ndarray) -> None:
    """One HDD step of length ``h`` on the held sample ``f`` (in place, ascending i: z_{i+j} are still old)."""
    n = z.shape[0] - 1
    s = z[0] - f
    a = abs(s)
    sg = 1.0 if s > 0.0 else (-1.0 if s < 0.0 else 0.0)
    inv = 1.0 / (n + 1.0)
    a_root = a**inv  # |s|^(1/(n+1))
    l_root = L**inv  # L^(1/(n+1))
    # powers |s|^((n-i)/(n+1)) = a_root^(n-i) and L^((i+1)/(n+1)) = l_root^(i+1), built incrementally
    l_pow = 1.0
    for i in range(n):
        l_pow *= l_root
        a_pow = 1.0
        for _ in range(n - i):
            a_pow *= a_root
        # Taylor terms sum_{j=1}^{n-i} h^j/j! z_{i+j}, Horner form
        acc = 0.0
        for j in range(n - i, 0, -1):
            acc = h / j * (z[i + j] + acc)
        z[i] = z[i] + acc - h * lam[n - i] * l_pow * a_pow * sg
    z[n] = z[n] - h * lam[0] * L * sg


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def hdd_step(z: np.ndarray, f: float, L: float, tau: float, lam: np.ndarray, substeps: int = 1) -> None:
    """Advance the order-``n`` HDD (``n = len(z) - 1``) by one sample period ``tau`` on the sample ``f``.

    ``z`` (float64, length ``n+1``) holds the estimates of ``f, f', ..., f^(n)`` at the sample time and is
    updated in place to the next sample time. ``lam`` holds ``lam[0..n]`` (non-recursive, e.g.
    ``HDD_LAMBDA[n]``). ``L`` may change from call to call. With ``substeps = m > 1`` the same held sample is
    integrated ``m`` times with ``tau/m`` (comparison only: holding ``f`` costs accuracy, see docs).
    Invalid inputs hold the state (module docstring).
    """
    if not _valid_inputs(f, L, tau, substeps):
        return
    h = tau / substeps
    for _ in range(substeps):
        _hdd_update(z, f, L, h, lam)
    if not _state_finite(z):
        hdd_init(z, f)


@njit(cache=True)
def _euler_update(z: np.ndarray, f: float, L: float, h: float, lam_rec: np.ndarray) -> None:
    """Forward Euler of the recursive form (seed 000 eq. 13), in place: v_i uses old z_i, z_{i+1} and v_{i-1}."""
    n = z.shape[0] - 1
    v_prev = f  # level 0 compares z_0 with f
    for i in range(n + 1):
        d = z[i] - v_prev
        a = abs(d)
        sg = 1.0 if d > 0.0 else (-1.0 if d < 0.0 else 0.0)
        m = n + 1 - i  # this level's homogeneity: gain L^(1/m), exponent (m-1)/m
        g = lam_rec[n - i] * L ** (1.0 / m) * a ** ((m - 1.0) / m) * sg
        v = (z[i + 1] if i < n else 0.0) - g
        z[i] = z[i] + h * v
        v_prev = v


@njit(cache=True)
def levant_euler_step(z: np.ndarray, f: float, L: float, tau: float, lam_rec: np.ndarray, substeps: int = 1) -> None:
    """COMPARISON ONLY: forward Euler of Levant's continuous recursive differentiator (seed 000 eq. 13/14).

    ``lam_rec`` holds the recursive gains ascending (``HDD_LAMBDA_RECURSIVE[n]``, i.e. ``(1.1, 1.5, 2, 3)`` for
    ``n = 3``). Same robustness contract as ``hdd_step``.
    """
    if not _valid_inputs(f, L, tau, substeps):
        return
    h = tau / substeps
    for _ in range(substeps):
        _euler_update(z, f, L, h, lam_rec)
    if not _state_finite(z):
        hdd_init(z, f)


@njit(cache=True)
def _run(f: np.ndarray, L: np.ndarray, tau: float, lam: np.ndarray, z0: np.ndarray, substeps: int, euler: bool):
    n1 = z0.shape[0]
    out = np.empty((f.shape[0], n1))
    z = z0.copy()
    for k in range(f.shape[0]):
        for i in range(n1):
            out[k, i] = z[i]
        if euler:
            levant_euler_step(z, f[k], L[k], tau, lam, substeps)
        else:
            hdd_step(z, f[k], L[k], tau, lam, substeps)
    return out


def _prepare(f, L, order, z0):
    f = np.ascontiguousarray(f, dtype=np.float64)
    L_arr = np.broadcast_to(np.asarray(L, dtype=np.float64), f.shape).copy()
    if z0 is None:
        z = np.zeros(order + 1)
        hdd_init(z, float(f[0]) if f.size else 0.0)
    else:
        z = np.array(z0, dtype=np.float64)
        if z.shape != (order + 1,):
            raise ValueError(f"z0 must have {order + 1} entries")
    return f, L_arr, z


def run_hdd(f, L, tau: float, order: int, lam=None, z0=None, substeps: int = 1) -> np.ndarray:
    """Run the HDD over a sampled signal. Row ``k`` holds the estimates at ``t_k`` (before sample ``k`` is used).

    ``L`` is a scalar or an array like ``f`` (time-varying). ``z0`` defaults to ``hdd_init`` on ``f[0]``.
    Returns an array ``(len(f), order+1)``.
    """
    lam = hdd_lambda(order) if lam is None else np.asarray(lam, dtype=np.float64)
    f, L_arr, z = _prepare(f, L, order, z0)
    return _run(f, L_arr, float(tau), lam, z, int(substeps), False)


def run_levant_euler(f, L, tau: float, order: int, lam_rec=None, z0=None, substeps: int = 1) -> np.ndarray:
    """COMPARISON ONLY: ``run_hdd`` with forward Euler of the recursive form."""
    lam_rec = hdd_lambda(order, recursive=True) if lam_rec is None else np.asarray(lam_rec, dtype=np.float64)
    f, L_arr, z = _prepare(f, L, order, z0)
    return _run(f, L_arr, float(tau), lam_rec, z, int(substeps), True)
