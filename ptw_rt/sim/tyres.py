"""Saturating lateral tyre law of the simulated plant (Magic-Formula type, side slip + camber thrust).

    F_ss = D sin( C_a atan(B_a alpha) + C_g atan(B_g gamma) ),   D = mu F_z,
    B_a = C_alpha / (C_a F_z),   B_g = C_gamma / (C_g F_z)

(Pacejka's motorcycle form: slip and camber share one sine, so their sum saturates at mu F_z.)
Small-slip slopes are exactly ``dF/dalpha = mu C_alpha`` and ``dF/dgamma = mu C_gamma`` whatever
the shape factors: the truth stiffnesses are mu times the (perturbed) nominal ones, and the
peak force is mu F_z. The force state follows F_ss through the relaxation length (see plant.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from numba import njit


@dataclass(frozen=True)
class TyreShape:
    """Shape factors of the saturating law (dimensionless). Defaults: slip peak ~11-13 deg at F_z."""

    slip_shape: float = 1.5  # C_a: with B_a fixed by the slope, sets where the slip force peaks
    camber_shape: float = 1.0  # C_g: 1.0 keeps camber thrust nearly linear up to ~40 deg lean
    min_mu: float = 0.05  # friction never below this (keeps B finite and the law well posed)


@njit(cache=True)
def lateral_force(alpha, gamma, mu, fz, c_alpha, c_gamma, slip_shape, camber_shape, min_mu):
    """Steady-state lateral force [N] (positive to the right) and the available peak mu*F_z."""
    m = mu if mu > min_mu else min_mu
    d = m * fz
    b_a = c_alpha / (slip_shape * fz)
    b_g = c_gamma / (camber_shape * fz)
    arg = slip_shape * math.atan(b_a * alpha) + camber_shape * math.atan(b_g * gamma)
    # beyond the peak the sine would fall and then change sign (arg > pi): hold the peak's far side
    # at a sliding level instead, so a large slip never pushes the wrong way
    lim = 0.5 * math.pi + 0.5 * (0.5 * math.pi)
    if arg > lim:
        arg = lim
    elif arg < -lim:
        arg = -lim
    return d * math.sin(arg), d
