"""Names for the lateral modes of a two-wheeler (wobble, weave, capsize, ...)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# A weave is a low-frequency roll/yaw/steer oscillation; wobble a front-frame
# shimmy well above it. 5 Hz separates them for road vehicles of this size.
WEAVE_WOBBLE_SPLIT_HZ = 5.0


@dataclass(frozen=True)
class Mode:
    name: str
    eigenvalue: complex

    @property
    def frequency_hz(self) -> float:
        return abs(self.eigenvalue.imag) / (2 * np.pi)

    @property
    def damping_ratio(self) -> float:
        return -self.eigenvalue.real / abs(self.eigenvalue) if self.eigenvalue != 0 else 0.0

    @property
    def stable(self) -> bool:
        return self.eigenvalue.real < 0


def classify_modes(eigenvalues: np.ndarray, speed: float, relaxation_lengths: tuple[float, float]) -> list[Mode]:
    """One Mode per eigenvalue (upper half-plane member of each complex pair).

    Complex: the highest-frequency pair above 5 Hz is wobble, the lowest below
    5 Hz weave, others are tyre-coupled steer oscillations. Real: the slowest is
    capsize, those within 35 % of u/sigma tyre relaxation, the rest roll-steer.
    """
    ev = np.asarray(eigenvalues)
    pairs = sorted([v for v in ev if v.imag > 1e-9], key=lambda v: -v.imag)
    reals = sorted([complex(v.real, 0.0) for v in ev if abs(v.imag) <= 1e-9], key=lambda v: abs(v.real))
    modes: list[Mode] = []
    for i, v in enumerate(pairs):
        f = v.imag / (2 * np.pi)
        if i == 0 and f >= WEAVE_WOBBLE_SPLIT_HZ:
            name = "wobble"
        elif i == len(pairs) - 1 and f < WEAVE_WOBBLE_SPLIT_HZ:
            name = "weave"
        else:
            name = "steer-tyre"
        modes.append(Mode(name, complex(v)))
    relax = [speed / s for s in relaxation_lengths if s > 0]
    for i, v in enumerate(reals):
        if i == 0:
            name = "capsize"
        elif any(abs(abs(v.real) - r) < 0.35 * r for r in relax):
            name = "tyre relaxation"
        else:
            name = "roll-steer"
        modes.append(Mode(name, v))
    return modes
