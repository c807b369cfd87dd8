"""Invariant zeros, vector relative degree and decoupling matrix (seed 000, sec. III).

Offline tools: they use scipy's generalised eigenvalue solver on the
Rosenbrock pencil and are never imported by the runtime.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla

from ptw_rt.model.sharp import UnknownInputSystem


def invariant_zeros(sys: UnknownInputSystem) -> np.ndarray:
    """Finite s where rank [[sI - A, -D], [C, 0]] drops (square systems: #inputs = #outputs)."""
    n, m = sys.D.shape
    p = sys.C.shape[0]
    pencil_a = np.block([[sys.A, sys.D], [sys.C, np.zeros((p, m))]])
    pencil_b = np.zeros((n + p, n + m))
    pencil_b[:n, :n] = np.eye(n)
    values = sla.eig(pencil_a, pencil_b, right=False)
    finite = values[np.isfinite(values) & (np.abs(values) < 1e9)]
    return finite[np.lexsort((finite.imag, finite.real))]


def relative_degree(sys: UnknownInputSystem, tol: float = 1e-9) -> list[int]:
    """Per-output relative degree with respect to the whole unknown-input vector."""
    n = sys.A.shape[0]
    d_norm = np.linalg.norm(sys.D)
    degrees = []
    for c in sys.C:
        row = c.copy()
        for k in range(1, n + 1):
            markov = row @ sys.D
            if np.linalg.norm(markov) > tol * np.linalg.norm(row) * d_norm:
                degrees.append(k)
                break
            row = row @ sys.A
        else:
            raise ValueError("output has no relative degree with respect to the unknown inputs")
    return degrees


def decoupling_matrix(sys: UnknownInputSystem, degrees: list[int]) -> np.ndarray:
    """Rows C_i A^(r_i - 1) D: non-singular iff the vector relative degree exists."""
    rows = [c @ np.linalg.matrix_power(sys.A, r - 1) @ sys.D for c, r in zip(sys.C, degrees, strict=True)]
    return np.array(rows)


def is_strongly_detectable(sys: UnknownInputSystem) -> bool:
    """Vector relative degree exists and every invariant zero is in the open left half-plane."""
    try:
        degrees = relative_degree(sys)
    except ValueError:
        return False
    if abs(np.linalg.det(decoupling_matrix(sys, degrees))) < 1e-12:
        return False
    return bool(np.all(invariant_zeros(sys).real < 0))
