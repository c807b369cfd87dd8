"""Ride scenarios: a path, a speed plan, a friction profile and (optionally) sensor faults.

A scenario builds a ``Plan`` for a given duration. Paths are either drawn in the road plane (lane
changes, slalom: ``path_from_xy``) or laid down by a speed plan and a lateral-acceleration plan in
time (``plan_from_segments``: curvature = a_lat / v^2, integrated to heading and position), so
every curve is ridden at the lean it was designed for (lean ~ atan(a_lat / g)).

Ground frame: X north, Y east, heading psi clockwise from north (SAE z down): a right turn has
positive curvature, yaw rate and roll.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

PLAN_DT = 0.01  # s, sampling of the time-based plan arrays
PATH_DS = 0.2  # m, sampling of the path
PLAN_MARGIN = 10.0  # s of plan beyond the ride's end
KMH = 1.0 / 3.6


@dataclass(frozen=True)
class FaultEvent:
    """A sensor/bus fault the sensor model injects (see sensors.apply_faults)."""

    kind: str  # gps_dropout | counter_frozen | silent | corrupt | wrong_dlc
    start: float  # s
    end: float  # s
    message: str  # DBC message name
    detail: str = ""
    dlc: int | None = None  # wrong_dlc: the length sent instead of the DBC's


@dataclass
class Path:
    """Uniformly sampled path: position, heading (unwrapped) and curvature against arc length."""

    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    curvature: np.ndarray
    ds: float = PATH_DS

    @property
    def length(self) -> float:
        return (len(self.x) - 1) * self.ds

    @property
    def curvature_rate(self) -> np.ndarray:
        """d kappa / d s [1/m^2]."""
        return np.gradient(self.curvature, self.ds)


@dataclass
class Plan:
    """Everything the ride loop needs from a scenario (time arrays sampled every PLAN_DT)."""

    path: Path
    speed: np.ndarray  # m/s reference
    accel: np.ndarray  # m/s^2, its derivative (feed-forward)
    mu: np.ndarray  # road friction
    initial_speed: float
    faults: list[FaultEvent] = field(default_factory=list)

    @property
    def length_s(self) -> float:
        """Time covered by the plan arrays (the ride plus PLAN_MARGIN)."""
        return (len(self.speed) - 1) * PLAN_DT


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    duration: float  # s, default
    seed: int  # default noise/bias seed
    build: Callable[[float], Plan]
    epoch_offset: float  # s added to the log's epoch base, so scenarios do not share time stamps


# ----- path construction -----------------------------------------------------------------------


def _smooth(k: np.ndarray, half_width_m: float = 1.0) -> np.ndarray:
    w = max(3, int(2 * half_width_m / PATH_DS) | 1)
    kernel = np.hanning(w + 2)[1:-1]
    kernel /= kernel.sum()
    return np.convolve(np.pad(k, w // 2, mode="edge"), kernel, mode="valid")


def _resample(
    s: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    extend: float,
    heading: np.ndarray | None = None,
    curvature: np.ndarray | None = None,
) -> Path:
    """Uniform-ds path through (x, y) sampled at increasing arc length s, plus a straight run-out.

    Heading and curvature are interpolated when given (paths laid down from a curvature plan),
    otherwise taken from finite differences of the resampled points (paths drawn in the plane).
    """
    keep = np.concatenate([[True], np.diff(s) > 1e-9])
    s, x, y = s[keep], x[keep], y[keep]
    n = int(s[-1] / PATH_DS) + 1
    su = np.arange(n) * PATH_DS
    xu = np.interp(su, s, x)
    yu = np.interp(su, s, y)
    if heading is None:
        h = np.unwrap(np.arctan2(np.gradient(yu, PATH_DS), np.gradient(xu, PATH_DS)))
        k = None
    else:
        h = np.interp(su, s, heading[keep])
        k = np.interp(su, s, curvature[keep]) if curvature is not None else None
    # straight run-out so the rider never leaves the end of the path
    m = int(extend / PATH_DS)
    if m > 0:
        steps = np.arange(1, m + 1) * PATH_DS
        xu = np.concatenate([xu, xu[-1] + steps * math.cos(h[-1])])
        yu = np.concatenate([yu, yu[-1] + steps * math.sin(h[-1])])
        h = np.concatenate([h, np.full(m, h[-1])])
        if k is not None:
            k = np.concatenate([k, np.zeros(m)])
    if k is None:
        k = np.gradient(h, PATH_DS)
    return Path(xu, yu, h, _smooth(k))


def path_from_xy(x: np.ndarray, y: np.ndarray, extend: float = 300.0) -> Path:
    s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
    return _resample(s, x, y, extend)


@dataclass(frozen=True)
class Seg:
    """One segment of a time-based plan.

    Over ``duration`` seconds the speed goes smoothly (S-curve) to ``kmh``; the lateral acceleration
    goes linearly to ``lat`` [m/s^2, + = right turn] during the first ``ramp`` seconds, then holds.
    """

    duration: float
    kmh: float
    lat: float = 0.0
    ramp: float = 1.0


def plan_from_segments(
    segs: list[Seg], duration: float, v0_kmh: float, heading0_deg: float = 20.0, mu: float = 1.0
) -> Plan:
    """The plan laid out over duration + PLAN_MARGIN, so no look-ahead ever sees the end of the path."""
    n = int(round((duration + PLAN_MARGIN) / PLAN_DT)) + 1
    t = np.arange(n) * PLAN_DT
    v = np.empty(n)
    a_lat = np.empty(n)
    v_prev, a_prev, t0 = v0_kmh * KMH, 0.0, 0.0
    bounds = []
    for sg in segs:
        bounds.append((t0, t0 + sg.duration, v_prev, sg.kmh * KMH, a_prev, sg.lat, sg.ramp))
        v_prev, a_prev, t0 = sg.kmh * KMH, sg.lat, t0 + sg.duration
    # after the last segment: hold its end speed, go straight
    bounds.append((t0, math.inf, v_prev, v_prev, a_prev, 0.0, 2.0))
    for tb0, tb1, va, vb, aa, ab, ramp in bounds:
        m = (t >= tb0) & (t < tb1)
        if not m.any():
            continue
        tau = t[m] - tb0
        z = np.clip(tau / (tb1 - tb0), 0.0, 1.0) if math.isfinite(tb1) else np.ones_like(tau)
        v[m] = va + (vb - va) * z * z * (3.0 - 2.0 * z)
        a_lat[m] = aa + (ab - aa) * np.clip(tau / max(ramp, 1e-6), 0.0, 1.0)
    accel = np.gradient(v, PLAN_DT)
    # lay the path down: curvature = a_lat / v^2 (no turning when (nearly) stopped)
    vk = np.maximum(v, 3.0)
    kappa = np.where(v > 1.0, a_lat / vk**2, 0.0)
    psi = (
        math.radians(heading0_deg)
        + np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] * kappa[1:] + v[:-1] * kappa[:-1]))]) * PLAN_DT
    )
    s = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * PLAN_DT)])
    x = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.cos(0.5 * (psi[1:] + psi[:-1])) * PLAN_DT)])
    y = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.sin(0.5 * (psi[1:] + psi[:-1])) * PLAN_DT)])
    if s[-1] < 1.0:  # a plan that never moves still needs a path ahead
        s = np.array([0.0, 1.0])
        x = np.array([0.0, math.cos(psi[0])])
        y = np.array([0.0, math.sin(psi[0])])
        psi = np.full(2, psi[0])
        kappa = np.zeros(2)
    path = _resample(s, x, y, extend=300.0 + 5.0 * float(v.max()), heading=psi, curvature=kappa)
    return Plan(path, v, accel, np.full(n, mu), v[0])


def turn(angle_deg: float, kmh: float, lat: float, ramp: float = 1.0) -> list[Seg]:
    """Segments for a turn of ``angle_deg`` (+ right) at constant speed and |lateral acceleration|."""
    v = kmh * KMH
    rate = abs(lat) / v  # heading rate while holding lat
    # heading gained: ramp in (rate*ramp/2) + hold (rate*T) + ramp out (rate*ramp/2)
    hold = max(math.radians(abs(angle_deg)) / rate - ramp, 0.0)
    sign = 1.0 if angle_deg >= 0 else -1.0
    return [Seg(ramp + hold, kmh, sign * abs(lat), ramp), Seg(ramp, kmh, 0.0, ramp)]


def _constant_speed_plan(path: Path, kmh: float, duration: float, mu: float = 1.0) -> Plan:
    n = int(round((duration + PLAN_MARGIN) / PLAN_DT)) + 1
    v = np.full(n, kmh * KMH)
    return Plan(path, v, np.zeros(n), np.full(n, mu), kmh * KMH)


def _rotate(x: np.ndarray, y: np.ndarray, heading_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Rotate a path drawn along +x (local right = +y) to start with the given heading."""
    c, s = math.cos(math.radians(heading_deg)), math.sin(math.radians(heading_deg))
    return c * x - s * y, s * x + c * y


# ----- the scenarios ---------------------------------------------------------------------------


def _dlc(kmh: float) -> Callable[[float], Plan]:
    def build(duration: float) -> Plan:
        u = kmh * KMH
        offset = -3.5  # left first (ISO 3888-style lane change to the left and back)
        lane_change = 2.25 * u  # quintic transition: peak path acceleration 5.77*3.5/2.25^2 = 4.0 m/s^2
        hold = max(u * 1.0, 15.0)
        entry = 3.0 * u
        x = np.arange(0.0, entry + 2 * lane_change + hold + 40.0 * u, 0.05)

        def quintic(z):
            z = np.clip(z, 0.0, 1.0)
            return z**3 * (10 - 15 * z + 6 * z * z)

        y = offset * (quintic((x - entry) / lane_change) - quintic((x - entry - lane_change - hold) / lane_change))
        xr, yr = _rotate(x, y, 15.0)
        return _constant_speed_plan(path_from_xy(xr, yr), kmh, duration)

    return build


def _slalom(duration: float) -> Plan:
    kmh, amp, wavelength = 30.0, 1.2, 30.0
    u = kmh * KMH
    entry = 2.5 * u
    x = np.arange(0.0, entry + u * (duration + 20.0), 0.05)
    z = np.clip((x - entry) / wavelength, 0.0, None)
    envelope = np.clip(z, 0.0, 1.0) ** 2 * (3 - 2 * np.clip(z, 0.0, 1.0))
    y = amp * envelope * np.sin(2 * math.pi * z)
    xr, yr = _rotate(x, y, 100.0)
    return _constant_speed_plan(path_from_xy(xr, yr), kmh, duration)


def _radius_accel(duration: float) -> Plan:
    radius = 150.0
    a50 = (50 * KMH) ** 2 / radius
    segs = [Seg(3.0, 50), Seg(3.0, 50, a50, 3.0), Seg(5.0, 50, a50, 0.1)]
    # accelerate 50 -> 100 km/h on the same circle: lateral acceleration follows v^2 / R
    steps = 20
    for i in range(1, steps + 1):
        v = 50 + 50 * i / steps
        segs.append(Seg(1.0, v, (v * KMH) ** 2 / radius, 1.0))
    segs.append(Seg(60.0, 100, (100 * KMH) ** 2 / radius, 0.1))
    plan = plan_from_segments(segs, duration, 50, heading0_deg=350.0)
    return plan


def _handling(duration: float) -> Plan:
    """Handling circuit, 40-120 km/h, curves of both hands, chicanes, mu = 0.9 (seed 001's setup)."""
    segs = [
        Seg(4.0, 60),
        Seg(5.0, 80, 3.0, 1.5),  # long right
        Seg(3.0, 80, -3.5, 1.5),  # swap to left
        Seg(4.0, 90, 0.0, 1.2),
        Seg(7.0, 120, 0.0),  # straight, accelerate
        Seg(6.0, 120, 3.0, 2.0),  # fast right sweeper
        Seg(2.0, 120, 0.0, 1.5),
        Seg(5.0, 70, 0.0),  # brake
        Seg(2.5, 70, -4.0, 1.0),  # chicane left-right-left
        Seg(2.5, 70, 4.0, 1.2),
        Seg(2.5, 70, -4.0, 1.2),
        Seg(2.0, 70, 0.0, 1.0),
        Seg(4.0, 45, 0.0),  # brake to the hairpin
        Seg(6.0, 40, 4.0, 1.2),  # hairpin right
        Seg(1.5, 45, 0.0, 1.2),
        Seg(8.0, 100, 1.0, 2.0),  # accelerate out on a gentle right
        Seg(4.0, 100, -3.5, 1.5),  # left sweeper
        Seg(3.0, 100, 2.5, 1.5),  # S
        Seg(3.0, 90, -2.0, 1.5),
        Seg(2.0, 85, 0.0, 1.0),
        Seg(5.0, 60, 0.0),  # brake
        Seg(3.0, 60, 4.5, 1.0),  # tight right
        Seg(3.0, 60, -4.5, 1.4),  # tight left
        Seg(2.0, 65, 0.0, 1.2),
        Seg(6.0, 110, 0.0),
        Seg(5.0, 110, -3.0, 1.5),  # fast left
        Seg(4.0, 110, 2.0, 1.5),
        Seg(3.0, 90, 0.0, 1.2),
        Seg(3.0, 70, 3.5, 1.0),
        Seg(3.0, 70, -3.5, 1.2),
        Seg(2.0, 70, 0.0, 1.0),
        Seg(6.0, 50, 0.0),
        Seg(6.0, 50, 3.0, 1.0),
        Seg(2.0, 60, 0.0, 1.0),
    ]
    return plan_from_segments(segs, duration, 60, heading0_deg=40.0, mu=0.9)


def _urban(duration: float) -> Plan:
    segs = [
        Seg(2.0, 0),  # at rest
        Seg(6.0, 40),  # pull away
        Seg(5.0, 40),
        Seg(4.0, 20),  # brake for a right turn
        *turn(90, 20, 2.0),
        Seg(6.0, 50),
        Seg(5.0, 50),
        Seg(6.0, 0),  # stop at a light
        Seg(4.0, 0),
        Seg(7.0, 35),
        Seg(3.0, 25),
        *turn(-90, 25, 2.2),
        Seg(5.0, 45),
        Seg(3.0, 45, 1.5, 1.5),  # bend right
        Seg(3.0, 45, -1.5, 1.5),  # bend left
        Seg(2.0, 45, 0.0, 1.5),
        Seg(6.0, 0),  # stop
        Seg(3.0, 0),
        Seg(6.0, 30),
        Seg(3.0, 22),
        *turn(90, 22, 2.0),
        Seg(5.0, 40),
        Seg(6.0, 0),
    ]
    return plan_from_segments(segs, duration, 0, heading0_deg=80.0)


def _mu_drop(duration: float) -> Plan:
    """Steady right-hand cornering at 50 km/h (a_lat 1.8 +- 0.6 m/s^2 weaving), mu 0.9 -> 0.5 at 20 s."""
    segs = [Seg(3.0, 50), Seg(3.0, 50, 1.8, 2.0)]
    t = 6.0
    k = 0
    while t < duration + PLAN_MARGIN + 5.0:
        segs.append(Seg(1.25, 50, 1.8 + (0.6 if k % 2 == 0 else -0.6), 1.25))
        t += 1.25
        k += 1
    plan = plan_from_segments(segs, duration, 50, heading0_deg=200.0, mu=0.9)
    tt = np.arange(len(plan.mu)) * PLAN_DT
    drop_at = min(20.0, 0.5 * duration)
    plan.mu = np.interp(tt, [0.0, drop_at, drop_at + 0.5, 1e9], [0.9, 0.9, 0.5, 0.5])
    return plan


def _faults(duration: float) -> Plan:
    segs = [
        Seg(3.0, 50),
        Seg(6.0, 70),
        Seg(5.0, 70, 2.5, 1.5),
        Seg(5.0, 70, -2.5, 1.5),
        Seg(3.0, 60, 0.0, 1.2),
        Seg(6.0, 60, 3.0, 1.5),
        Seg(3.0, 80, 0.0, 1.5),
        Seg(6.0, 80, -2.0, 1.5),
        Seg(4.0, 80, 0.0, 1.5),
        Seg(6.0, 60, 3.0, 1.5),
        Seg(3.0, 60, 0.0, 1.5),
        Seg(6.0, 70, -3.0, 1.5),
        Seg(4.0, 70, 0.0, 1.5),
    ]
    plan = plan_from_segments(segs, duration, 50, heading0_deg=300.0)
    f = max(duration / 60.0, 0.0)
    plan.faults = [
        FaultEvent("gps_dropout", 15.0 * f, 15.0 * f + 4.0, "GPS_Velocity", "FixType 0 then 1, no satellites"),
        FaultEvent("counter_frozen", 25.0 * f, 25.0 * f + 0.5, "IMU_Rates", "the last frame repeated"),
        FaultEvent("silent", 32.0 * f, 32.0 * f + 1.0, "Steer_Encoder", "no frames"),
        FaultEvent("corrupt", 40.0 * f, 40.0 * f + 0.3, "IMU_Accel", "random payload bytes"),
        FaultEvent("corrupt", 40.0 * f, 40.0 * f + 0.3, "Steer_Encoder", "random payload bytes"),
        FaultEvent("wrong_dlc", 40.1 * f, 40.1 * f + 0.3, "IMU_Rates", "DLC 5 (truncated)", dlc=5),
        FaultEvent("wrong_dlc", 40.1 * f, 40.1 * f + 0.3, "Steer_Encoder", "DLC 8 (zero-padded)", dlc=8),
    ]
    return plan


SCENARIOS: dict[str, Scenario] = {
    s.name: s
    for s in [
        Scenario(
            "dlc_50",
            "double lane change (ISO 3888 style, 3.5 m to the left and back) at constant 50 km/h",
            20.0,
            1001,
            _dlc(50.0),
            0.0,
        ),
        Scenario(
            "dlc_100",
            "double lane change (3.5 m to the left and back) at constant 100 km/h",
            20.0,
            1002,
            _dlc(100.0),
            1000.0,
        ),
        Scenario(
            "radius_accel",
            "constant radius 150 m to the right, accelerating 50 -> 100 km/h (lean 7.4 -> 27.6 deg)",
            45.0,
            1003,
            _radius_accel,
            2000.0,
        ),
        Scenario(
            "handling_40_120",
            "handling circuit: curves of both hands, chicanes, hairpin; 40-120 km/h, mu 0.9 (seed 001)",
            120.0,
            1004,
            _handling,
            3000.0,
        ),
        Scenario("slalom_30", "slalom at 30 km/h, 1.2 m amplitude, 30 m wavelength", 30.0, 1005, _slalom, 4000.0),
        Scenario(
            "urban",
            "stop-and-go 0-50 km/h with 90-degree turns, bends and three stops (standstill included)",
            110.0,
            1006,
            _urban,
            5000.0,
        ),
        Scenario(
            "mu_drop",
            "cornering at 50 km/h (weaving 1.2-2.4 m/s^2 around a 107 m radius), friction 0.9 -> 0.5 at t = 20 s",
            40.0,
            1007,
            _mu_drop,
            6000.0,
        ),
        Scenario(
            "sensor_faults",
            "a 50-80 km/h country ride with GPS dropout, frozen IMU counter, silent encoder, "
            "corrupted frames and wrong DLCs",
            60.0,
            1008,
            _faults,
            7000.0,
        ),
    ]
}
