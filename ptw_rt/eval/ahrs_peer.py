"""The peer of issue #12: x-io Technologies' Fusion AHRS (PyPI ``imufusion``) on the estimator's own inputs.

What a user would pick instead of ptw-rt for roll. Evaluation only: ``imufusion`` is in the ``eval``
extra, imported inside :func:`run_peer`, never by the daemon.

Inputs are exactly what the estimator receives: the Sample of every 10 ms cycle (DBC-decoded CAN
frames, newest value of each message, held while a message is late; ``ptw_rt/core/layout.py``).
The motion terms are removed from the accelerometer with GPS speed alone (no model, no steer):

* ``u`` and ``u'`` from the 10 Hz GPS speed: a least-squares line through the last
  ``speed_window`` fixes gives ``u'`` (its slope); ``u`` is that line extrapolated to the cycle's
  time, with the receiver's latency (``sensors.gps_latency``) compensated when
  ``latency_compensated`` (the fix describes the vehicle ``gps_latency`` before its frame);
* the acceleration of the reference point (on the ground, under the IMU's ``imu_forward``
  offset) in body axes ``(u', 0, 0) + omega x (u, 0, 0) = (u', r u, -q u)``, with the body rates
  ``omega = (p, q, r)`` of the gyro: the lateral velocity is unknown to a GPS-only user and ignored;
* the IMU's lever arm ``rho = (imu_forward, 0, -imu_height)`` (SAE body axes, z down):
  ``omega' x rho + omega x (omega x rho)``, ``omega'`` a two-step difference of the gyro. On a lane
  change the roll acceleration times the IMU height is up to ~1 m/s^2 on the lateral axis.

What is left is the specific force of gravity alone, ``-g_body`` (at rest (0, 0, -g)). Axes: SAE
body = NED body (x forward, y right, z down); the gyro in deg/s, the accelerometer in g. Fusion's
roll is positive right side down, as ours (checked on a steady right-hand turn in the tests).

Sign of the accelerometer: imufusion 1.3 aligns the accelerometer vector with the *down* axis of
the body in every convention (fed a sensor rolled right by 11.5 deg as the physical specific force
(0, -0.199, -0.980) g with ``CONVENTION_NED`` it converges to roll -168.5 deg; fed
(0, +0.199, +0.980) it gives +11.5 deg, and the gyro integrates a positive roll rate to a positive
roll). So the vector fed is ``-f/g``: gravity in body axes, which is what the library expects; a
user who fed the raw specific force would see the roll flip on the first tilt and fix it the same
way. Older imufusion (< 1.3, ``Settings``/``update_no_magnetometer(gyro, accel, dt)``) are also
supported; the sign is found by the same static check at run time (:func:`accelerometer_sign`).

Settings (``PeerSettings``): tried on the nominal matrix row (``ptw-rt evaluate --matrix``), kept
the best; see ``docs/results.md``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from ptw_rt.core import layout as L  # noqa: N812 - the Sample index table

G0 = 9.80665  # m/s^2 per g (imufusion's unit)


@dataclass(frozen=True)
class PeerSettings:
    gain: float = 0.5  # Fusion's default: the accelerometer correction weight
    acceleration_rejection: float = 10.0  # deg: Fusion's recommended value for a moving platform
    rejection_timeout: float = 5.0  # s before a rejected accelerometer is forced back in (recovery)
    gyroscope_range: float = 2000.0  # deg/s, the sensor's range (saturation -> angular-rate recovery)
    latency_compensated: bool = False  # GPS speed extrapolated over the receiver's latency (no gain measured)
    speed_window: int = 5  # GPS fixes (0.5 s) in the least-squares line giving u and u'
    lever_arm: bool = True  # remove omega' x rho + omega x (omega x rho)
    bias: bool = True  # imufusion.Bias: gyro offset learned while stationary

    def as_dict(self) -> dict:
        return asdict(self)


def available() -> bool:
    """True when imufusion can be imported (the ``eval`` extra)."""
    try:
        import imufusion  # noqa: F401
    except ImportError:
        return False
    return True


def gps_speed_and_derivative(
    t: np.ndarray,
    gps_speed: np.ndarray,
    fresh: np.ndarray,
    stale: np.ndarray,
    latency: float,
    window: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Causal ``u`` and ``u'`` at every cycle from the GPS fixes alone.

    ``fresh``: the cycle received a GPS frame; ``stale``: the GPS is timed out (then ``u'`` = 0 and
    ``u`` holds). ``latency``: age of the fix's epoch at its frame (0: not compensated).
    """
    n = t.shape[0]
    u = np.empty(n)
    du = np.zeros(n)
    fix_t: list[float] = []
    fix_v: list[float] = []
    slope, intercept, t_ref = 0.0, float(gps_speed[0]) if n else 0.0, float(t[0]) if n else 0.0
    for k in range(n):
        if fresh[k]:
            fix_t.append(float(t[k]) - latency)
            fix_v.append(float(gps_speed[k]))
            if len(fix_t) > window:
                del fix_t[0], fix_v[0]
            if len(fix_t) >= 2:
                tt = np.asarray(fix_t)
                vv = np.asarray(fix_v)
                tm = tt.mean()
                d = tt - tm
                slope = float(np.dot(d, vv - vv.mean()) / np.dot(d, d))
                intercept, t_ref = float(vv.mean()), float(tm)
            else:
                slope, intercept, t_ref = 0.0, fix_v[-1], fix_t[-1]
        if stale[k]:
            slope = 0.0
            du[k] = 0.0
            u[k] = max(intercept, 0.0)
            t_ref = float(t[k])
            continue
        du[k] = slope
        u[k] = max(intercept + slope * (float(t[k]) - t_ref), 0.0)
    return u, du


def gravity_specific_force(
    samples: np.ndarray,
    dt: float,
    imu_height: float,
    imu_forward: float,
    gps_latency: float,
    settings: PeerSettings,
) -> tuple[np.ndarray, np.ndarray]:
    """(gyro [rad/s], specific force of gravity [m/s^2]) per cycle, SAE body axes, motion terms removed."""
    t = samples[:, L.S_TIME]
    gyro = samples[:, [L.S_ROLL_RATE_BODY, L.S_PITCH_RATE_BODY, L.S_YAW_RATE_BODY]].astype(float)
    f = samples[:, [L.S_ACCEL_X, L.S_ACCEL_Y, L.S_ACCEL_Z]].astype(float)
    fresh = (samples[:, L.S_FRESH].astype(np.int64) & L.MSG_GPS) != 0
    stale = (samples[:, L.S_STALE].astype(np.int64) & L.MSG_GPS) != 0
    latency = gps_latency if settings.latency_compensated else 0.0
    u, du = gps_speed_and_derivative(t, samples[:, L.S_GPS_SPEED], fresh, stale, latency, settings.speed_window)
    q, r = gyro[:, 1], gyro[:, 2]
    motion = np.column_stack([du, r * u, -q * u])
    if settings.lever_arm:
        rho = np.array([imu_forward, 0.0, -imu_height])
        dw = np.zeros_like(gyro)
        if gyro.shape[0] > 2:
            dw[2:] = (gyro[2:] - gyro[:-2]) / (2.0 * dt)  # causal two-step difference (5 ms behind)
        w_rho = np.cross(gyro, rho)
        motion += np.cross(dw, rho) + np.cross(gyro, w_rho)
    return gyro, f - motion


def _new_ahrs(imufusion, settings: PeerSettings, dt: float):
    """An Ahrs with the settings, for imufusion >= 1.3 (AhrsSettings) or older (Settings)."""
    ahrs = imufusion.Ahrs()
    if hasattr(imufusion, "AhrsSettings"):
        ahrs.set_settings(
            imufusion.AhrsSettings(
                sample_rate=1.0 / dt,
                convention=imufusion.CONVENTION_NED,
                gain=settings.gain,
                gyroscope_range=settings.gyroscope_range,
                acceleration_rejection=settings.acceleration_rejection,
                magnetic_rejection=0.0,
                rejection_timeout=settings.rejection_timeout,
            )
        )
        return ahrs, lambda g, a: ahrs.update_no_magnetometer(g, a)
    ahrs.settings = imufusion.Settings(  # pragma: no cover - imufusion < 1.3
        imufusion.CONVENTION_NED,
        settings.gain,
        settings.gyroscope_range,
        settings.acceleration_rejection,
        0.0,
        int(round(settings.rejection_timeout / dt)),
    )
    return ahrs, lambda g, a: ahrs.update_no_magnetometer(g, a, dt)  # pragma: no cover


def _quaternion(ahrs) -> np.ndarray:
    if hasattr(ahrs, "get_quaternion"):
        return np.asarray(ahrs.get_quaternion(), dtype=float)
    q = ahrs.quaternion  # pragma: no cover - imufusion < 1.3
    return np.array([q.w, q.x, q.y, q.z])  # pragma: no cover


def _roll_pitch(q: np.ndarray) -> tuple[float, float]:
    """Roll and pitch [rad] of a unit quaternion (w, x, y, z), aerospace sequence (yaw, pitch, roll)."""
    w, x, y, z = q
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    return roll, pitch


_SIGN_CACHE: dict[str, float] = {}


def accelerometer_sign() -> float:
    """+1 if imufusion (NED) expects the specific force, -1 if it expects gravity (-f): a static tilt test."""
    import imufusion

    key = getattr(imufusion, "__version__", "") + str(hasattr(imufusion, "AhrsSettings"))
    if key not in _SIGN_CACHE:
        tilt = math.radians(10.0)
        f = np.array([0.0, -math.sin(tilt), -math.cos(tilt)])  # specific force of a sensor rolled right, in g
        ahrs, update = _new_ahrs(imufusion, PeerSettings(acceleration_rejection=0.0), 0.01)
        for _ in range(400):
            update(np.zeros(3), f)
        roll, _ = _roll_pitch(_quaternion(ahrs))
        _SIGN_CACHE[key] = 1.0 if abs(roll - tilt) < math.radians(1.0) else -1.0
    return _SIGN_CACHE[key]


def run_peer(
    samples: np.ndarray,
    dt: float,
    imu_height: float,
    imu_forward: float,
    gps_latency: float,
    settings: PeerSettings | None = None,
) -> dict[str, np.ndarray]:
    """The Fusion AHRS over the cycles' Samples: roll and pitch [rad] per cycle (SAE: roll > 0 leaning right)."""
    import imufusion  # lazy: the eval extra, never loaded by the daemon

    settings = settings or PeerSettings()
    gyro, f_grav = gravity_specific_force(samples, dt, imu_height, imu_forward, gps_latency, settings)
    gyro_dps = np.ascontiguousarray(np.degrees(gyro))
    acc_g = np.ascontiguousarray(accelerometer_sign() * f_grav / G0)
    ahrs, update = _new_ahrs(imufusion, settings, dt)
    bias = None
    if settings.bias and hasattr(imufusion, "Bias"):
        bias = imufusion.Bias()
        if hasattr(imufusion, "BiasSettings"):
            bias.set_settings(imufusion.BiasSettings(sample_rate=1.0 / dt))
    n = gyro.shape[0]
    roll = np.empty(n)
    pitch = np.empty(n)
    for k in range(n):
        g = gyro_dps[k]
        if bias is not None:
            g = np.asarray(bias.update(g), dtype=float)
        update(g, acc_g[k])
        roll[k], pitch[k] = _roll_pitch(_quaternion(ahrs))
    return {"roll": roll, "pitch": pitch}
