"""Sensor models: chassis IMU (body axes, lever arm), 10-bit steering encoder, GPS velocity, bus timing.

Everything is sampled from the 1 kHz record of the ride loop (linear interpolation at each frame's
own sample instant), so every sensor has its own phase, jitter and latency.

IMU (mount point ``imu_forward`` ahead of the reference point, ``imu_height`` above ground, leaning
with the chassis, zero pitch). With ``h`` the height, ``x_i`` the forward offset, yaw-frame axes
(x along the heading, y right, z down) and ``a_x = u_dot - v_y r``, ``a_y = v_y_dot + u r`` at the
reference point:

    a_x = u_dot - v_y r - r_dot h sin(phi) - r^2 x_i - 2 r h cos(phi) phi_dot
    a_y = v_y_dot + u r + r_dot x_i - r^2 h sin(phi) + h (cos(phi) phi_ddot - sin(phi) phi_dot^2)
    a_z = h (sin(phi) phi_ddot + cos(phi) phi_dot^2)
    f   = a - (0, 0, g)                              (specific force, z down)
    AccelX = f_x,  AccelY = f_y cos(phi) + f_z sin(phi),  AccelZ = -f_y sin(phi) + f_z cos(phi)
    RollRate = phi_dot,  PitchRate = r sin(phi),  YawRate = r cos(phi)

plus white noise and a constant per-run bias drawn from the seed. At rest AccelZ = -g.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ptw_rt.model.parameters import VehicleParameters
from ptw_rt.sim import loop
from ptw_rt.sim.plant import DELTA, PHI, PHI_DOT, PSI, VY, R, U
from ptw_rt.sim.scenarios import FaultEvent

MESSAGES = ("IMU_Rates", "IMU_Accel", "Steer_Encoder", "GPS_Velocity")
COUNTER_SIGNAL = {
    "IMU_Rates": "IMU_Counter",
    "IMU_Accel": "Accel_Counter",
    "Steer_Encoder": "Steer_Counter",
    "GPS_Velocity": "GPS_Counter",
}
DLC = {"IMU_Rates": 7, "IMU_Accel": 7, "Steer_Encoder": 2, "GPS_Velocity": 6}  # the DBC's (used for faults)
COUNTER_MODULUS = 16  # 4-bit rolling counters of the sensor messages (wrap 15 -> 0)


@dataclass(frozen=True)
class SensorConfig:
    # IMU mount: near the rear-frame CoM (h = 0.561 m) on the chassis
    imu_height: float = 0.5  # m above ground
    imu_forward: float = 0.0  # m ahead of the model's reference point (under the rear-frame CoM)
    gyro_noise: float = 0.002  # rad/s rms, white, per sample
    accel_noise: float = 0.03  # m/s^2 rms
    gyro_bias: float = 0.003  # rad/s rms of the per-run constant bias (each axis)
    accel_bias: float = 0.05  # m/s^2 rms
    imu_period: float = 0.01
    imu_delay: float = 0.0006  # s from sampling to the frame on the bus
    # steering encoder
    steer_zero: int = 512
    counts_per_rev: int = 1024
    steer_period: float = 0.01
    steer_delay: float = 0.0002
    # GPS
    gps_period: float = 0.1
    gps_latency: float = 0.1  # s: the velocity solution describes the vehicle this long before the frame
    gps_speed_noise: float = 0.05  # m/s rms
    gps_course_noise: float = 0.3  # deg rms at speed (grows as 1/V below 2 m/s)
    gps_min_course_speed: float = 0.5  # m/s: below, the receiver holds its last course
    satellites: int = 12
    # bus timing: per-message phase [s] (each run adds a seed-drawn shift of +-phase_spread) and jitter rms
    phase: dict[str, float] = field(
        default_factory=lambda: {
            "IMU_Rates": 0.00213,
            "IMU_Accel": 0.00241,
            "Steer_Encoder": 0.00672,
            "GPS_Velocity": 0.04377,
        }
    )
    phase_spread: float = 0.0002
    jitter: dict[str, float] = field(
        default_factory=lambda: {
            "IMU_Rates": 40e-6,
            "IMU_Accel": 40e-6,
            "Steer_Encoder": 90e-6,
            "GPS_Velocity": 250e-6,
        }
    )


@dataclass(frozen=True)
class SensorFrame:
    """One frame as the bus sees it: encode ``signals`` (+ ``counter``), or send ``raw`` as is.

    ``dlc`` (if not None) overrides the DBC length: the encoded payload is cut or zero-padded to it.
    ``fault`` names the injected fault ('' for a normal frame).
    """

    t: float
    message: str
    signals: dict[str, float] | None
    counter: int
    raw: bytes | None = None
    dlc: int | None = None
    fault: str = ""


@dataclass
class MessageStream:
    """All frames of one message as arrays (time order)."""

    name: str
    t: np.ndarray  # frame time [s, sim time]
    signals: dict[str, np.ndarray]  # signal name -> values (physical units; counters excluded)
    counter: np.ndarray  # int rolling counter 0..15
    raw: dict[int, bytes] = field(default_factory=dict)  # frame index -> payload replacing the encoding
    dlc: dict[int, int] = field(default_factory=dict)  # frame index -> DLC override
    fault: dict[int, str] = field(default_factory=dict)  # frame index -> fault tag

    @property
    def counter_signal(self) -> str:
        return COUNTER_SIGNAL[self.name]

    def frame(self, i: int) -> SensorFrame:
        raw = self.raw.get(i)
        return SensorFrame(
            t=float(self.t[i]),
            message=self.name,
            signals=None if raw is not None else {k: float(v[i]) for k, v in self.signals.items()},
            counter=int(self.counter[i]),
            raw=raw,
            dlc=self.dlc.get(i),
            fault=self.fault.get(i, ""),
        )

    def select(self, keep: np.ndarray) -> None:
        """Keep only the frames where ``keep`` is True (re-indexing the overrides)."""
        idx = np.flatnonzero(keep)
        new_index = {int(old): new for new, old in enumerate(idx)}
        self.t = self.t[idx]
        self.signals = {k: v[idx] for k, v in self.signals.items()}
        self.counter = self.counter[idx]
        self.raw = {new_index[i]: b for i, b in self.raw.items() if i in new_index}
        self.dlc = {new_index[i]: d for i, d in self.dlc.items() if i in new_index}
        self.fault = {new_index[i]: f for i, f in self.fault.items() if i in new_index}


def frame_times(rng: np.random.Generator, period: float, phase: float, jitter: float, duration: float) -> np.ndarray:
    n = int(math.floor((duration - phase) / period)) + 1
    base = phase + period * np.arange(max(n, 0))
    j = np.clip(rng.standard_normal(base.shape) * jitter, -3 * jitter, 3 * jitter)
    t = base + j
    return t[(t >= 0.0) & (t <= duration)]


def _sample(rec: np.ndarray, col: int, ts: np.ndarray) -> np.ndarray:
    return np.interp(ts, rec[:, loop.REC_T], rec[:, col])


def road_grade(pert, rec: np.ndarray, ts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The road's grade [rad, uphill positive] under the vehicle and the rate it pitches the chassis at [rad/s], at
    times ts: ``road_slope`` on average, swinging by ``road_slope_swing`` over every ``road_slope_length`` metres
    ridden (a hilly road: crests and dips; standing still, the chassis does not pitch)."""
    mean, swing = math.radians(pert.road_slope), math.radians(pert.road_slope_swing)
    if swing == 0.0:
        return np.full(len(ts), mean), np.zeros(len(ts))
    t, u = rec[:, loop.REC_T], rec[:, loop.REC_X0 + U]
    ridden = np.concatenate(([0.0], np.cumsum(0.5 * (u[1:] + u[:-1]) * np.diff(t))))
    k = 2.0 * math.pi / pert.road_slope_length
    phase = k * np.interp(ts, t, ridden)
    return mean + swing * np.sin(phase), swing * k * np.cos(phase) * np.interp(ts, t, u)


def imu_readings(
    rec: np.ndarray,
    ts: np.ndarray,
    g: float,
    height: float,
    forward: float,
    slope: float | np.ndarray = 0.0,
    slope_rate: float | np.ndarray = 0.0,
) -> dict[str, np.ndarray]:
    """Noise-free body-frame rates and specific force of the IMU at times ts (hand-derived kinematics), on a road
    of grade ``slope`` [rad, uphill positive] changing at ``slope_rate`` [rad/s]: the vehicle turns about the
    vertical, which its pitched roll axis sees a part of (roll rate p = roll' - r sin(slope)), gravity has a part
    along it, and a grade that changes pitches the chassis (its rate on the pitch and yaw gyros, and the path's
    curvature u slope' normal to the road: a crest lightens the vehicle)."""
    X = loop.REC_X0
    phi = _sample(rec, X + PHI, ts)
    p = _sample(rec, X + PHI_DOT, ts)
    r = _sample(rec, X + R, ts)
    u = _sample(rec, X + U, ts)
    vy = _sample(rec, X + VY, ts)
    dvy = _sample(rec, loop.REC_DVY, ts)
    dr = _sample(rec, loop.REC_DR, ts)
    dp = _sample(rec, loop.REC_DP, ts)
    du = _sample(rec, loop.REC_DU, ts)
    sp, cp = np.sin(phi), np.cos(phi)
    h, xi = height, forward
    ax = du - vy * r - dr * h * sp - r * r * xi - 2.0 * r * h * cp * p
    ay = dvy + u * r + dr * xi - r * r * h * sp + h * (cp * dp - sp * p * p)
    az = h * (sp * dp + cp * p * p) - u * slope_rate
    cs, ss = np.cos(slope), np.sin(slope)
    fx, fy, fz = ax + g * ss, ay, az - g * cs
    return {
        "RollRate": p - r * ss,
        "PitchRate": r * sp * cs + slope_rate * cp,
        "YawRate": r * cp * cs - slope_rate * sp,
        "AccelX": fx,
        "AccelY": fy * cp + fz * sp,
        "AccelZ": -fy * sp + fz * cp,
    }


def mounted(vector: tuple[np.ndarray, np.ndarray, np.ndarray], roll: float, pitch: float) -> tuple[np.ndarray, ...]:
    """A chassis-axes vector (x, y, z) as an IMU reads it when mounted rolled by ``roll`` (right side down) and then
    pitched by ``pitch`` (nose up) off the chassis axes [rad]: an installation that is not square."""
    x, y, z = vector
    cr, sr, cq, sq = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    y, z = y * cr + z * sr, -y * sr + z * cr
    x, z = x * cq - z * sq, x * sq + z * cq
    return x, y, z


def steer_counts(delta: np.ndarray, zero: int, offset: int, counts_per_rev: int) -> np.ndarray:
    """Absolute encoder reading: rises when steering right, wraps modulo counts_per_rev."""
    c = zero + offset + np.round(np.asarray(delta) * counts_per_rev / (2.0 * math.pi))
    return np.mod(c, counts_per_rev).astype(np.int64)


def _counters(n: int, start: int) -> np.ndarray:
    return (start + np.arange(n)) % COUNTER_MODULUS


def make_sensor_streams(
    rec: np.ndarray,
    p: VehicleParameters,
    cfg: SensorConfig,
    pert,
    rng: np.random.Generator,
    faults: list[FaultEvent],
    duration: float,
) -> tuple[dict[str, MessageStream], dict[str, object]]:
    """The four input messages of the contract, with noise, bias, latency, timing and faults."""
    X = loop.REC_X0
    phases = {m: cfg.phase[m] + rng.uniform(-cfg.phase_spread, cfg.phase_spread) for m in MESSAGES}
    starts = {m: int(rng.integers(0, COUNTER_MODULUS)) for m in MESSAGES}
    gyro_bias = rng.standard_normal(3) * cfg.gyro_bias * pert.imu_bias
    accel_bias = rng.standard_normal(3) * cfg.accel_bias * pert.imu_bias
    streams: dict[str, MessageStream] = {}

    # --- IMU: two messages from one sensor (the accel frame follows the rates frame)
    t_rates = frame_times(rng, cfg.imu_period, phases["IMU_Rates"], cfg.jitter["IMU_Rates"], duration)
    t_acc = frame_times(rng, cfg.imu_period, phases["IMU_Accel"], cfg.jitter["IMU_Accel"], duration)
    for name, tt, keys, bias, sigma in (
        ("IMU_Rates", t_rates, ("RollRate", "PitchRate", "YawRate"), gyro_bias, cfg.gyro_noise),
        ("IMU_Accel", t_acc, ("AccelX", "AccelY", "AccelZ"), accel_bias, cfg.accel_noise),
    ):
        ts = np.maximum(tt - cfg.imu_delay, 0.0)
        clean = imu_readings(rec, ts, p.g, cfg.imu_height, cfg.imu_forward, *road_grade(pert, rec, ts))
        if pert.imu_mount_roll != 0.0 or pert.imu_mount_pitch != 0.0:
            turned = mounted(
                tuple(clean[k] for k in keys), math.radians(pert.imu_mount_roll), math.radians(pert.imu_mount_pitch)
            )
            clean = dict(zip(keys, turned, strict=True))
        sig = {}
        for j, k in enumerate(keys):
            sig[k] = clean[k] + bias[j] + rng.standard_normal(len(tt)) * sigma * pert.imu_noise
        if name == "IMU_Rates":  # faults no plausibility check can see, from fault_at on
            after = tt >= pert.fault_at
            sig["YawRate"] = np.where(
                after, sig["YawRate"] + (pert.yaw_gyro_scale - 1.0) * clean["YawRate"], sig["YawRate"]
            )
            # a bias that steps within a sample, or grows linearly over roll_gyro_bias_ramp (a thermal transient)
            grown = (tt - pert.fault_at) / pert.roll_gyro_bias_ramp if pert.roll_gyro_bias_ramp > 0.0 else 1.0
            bias_now = pert.roll_gyro_bias_step * np.clip(grown, 0.0, 1.0)
            sig["RollRate"] = sig["RollRate"] + np.where(after, bias_now, 0.0)
            sig["YawRate"] = sig["YawRate"] + np.where(after, pert.yaw_gyro_bias_step, 0.0)
        streams[name] = MessageStream(name, tt, sig, _counters(len(tt), starts[name]))

    # --- steering encoder
    tt = frame_times(rng, cfg.steer_period, phases["Steer_Encoder"], cfg.jitter["Steer_Encoder"], duration)
    delta = _sample(rec, X + DELTA, np.maximum(tt - cfg.steer_delay, 0.0))
    counts = steer_counts(delta, cfg.steer_zero, int(pert.steer_offset), cfg.counts_per_rev)
    if pert.steer_offset_step:
        counts = np.where(tt >= pert.fault_at, (counts + int(pert.steer_offset_step)) % cfg.counts_per_rev, counts)
    streams["Steer_Encoder"] = MessageStream(
        "Steer_Encoder", tt, {"SteerCount": counts.astype(float)}, _counters(len(tt), starts["Steer_Encoder"])
    )

    # --- GPS velocity (latency: the solution describes t - latency)
    tt = frame_times(rng, cfg.gps_period, phases["GPS_Velocity"], cfg.jitter["GPS_Velocity"], duration)
    ts = np.maximum(tt - cfg.gps_latency, 0.0)
    u = _sample(rec, X + U, ts)
    vy = _sample(rec, X + VY, ts)
    psi = _sample(rec, X + PSI, ts)
    speed = np.hypot(u, vy) * np.cos(road_grade(pert, rec, ts)[0])  # the receiver's speed is the horizontal one
    sog = np.maximum(speed + rng.standard_normal(len(tt)) * cfg.gps_speed_noise, 0.0)
    course_noise = cfg.gps_course_noise * np.maximum(1.0, 2.0 / np.maximum(speed, 1e-3))
    course = np.degrees(psi + np.arctan2(vy, np.maximum(u, 1e-6))) + rng.standard_normal(len(tt)) * course_noise
    # below the minimum speed the receiver holds its last course
    last = float(np.mod(course[0], 360.0))
    cog = np.empty(len(tt))
    for i in range(len(tt)):
        if speed[i] >= cfg.gps_min_course_speed:
            last = float(np.mod(course[i], 360.0))
        cog[i] = last
    cog = np.where(cog >= 359.995, 0.0, cog)  # 360 deg is 0 deg (DBC range 0..360, 0.01 resolution)
    sats = np.clip(cfg.satellites + np.round(np.cumsum(rng.choice([-1, 0, 0, 0, 0, 0, 1], len(tt)))), 7, 18)
    streams["GPS_Velocity"] = MessageStream(
        "GPS_Velocity",
        tt,
        {
            "SpeedOverGround": sog,
            "CourseOverGround": cog,
            "FixType": np.full(len(tt), 3.0),
            "NumSatellites": sats.astype(float),
        },
        _counters(len(tt), starts["GPS_Velocity"]),
    )

    apply_faults(streams, faults, rng)
    meta = {
        "gyro_bias": gyro_bias.tolist(),
        "accel_bias": accel_bias.tolist(),
        "steer_zero": cfg.steer_zero + int(pert.steer_offset),
        "phase_s": phases,
        "imu_height": cfg.imu_height,
        "imu_forward": cfg.imu_forward,
        "gps_latency": cfg.gps_latency,
    }
    return streams, meta


def apply_faults(streams: dict[str, MessageStream], faults: list[FaultEvent], rng: np.random.Generator) -> None:
    """Inject the scenario's faults into the streams (in place)."""
    drop = {name: np.zeros(len(s.t), dtype=bool) for name, s in streams.items()}
    for f in faults:
        st = streams.get(f.message)
        if st is None:
            raise ValueError(f"fault on unknown message {f.message!r}")
        win = np.flatnonzero((st.t >= f.start) & (st.t < f.end))
        if win.size == 0:
            continue
        if f.kind == "gps_dropout":
            # first 60 %: no fix; then dead reckoning; speed/course not usable either way
            split = win[0] + int(0.6 * win.size)
            last_good = win[0] - 1 if win[0] > 0 else win[0]
            for i in win:
                no_fix = i < split
                st.signals["FixType"][i] = 0.0 if no_fix else 1.0
                st.signals["NumSatellites"][i] = float(rng.integers(0, 3)) if no_fix else 3.0
                st.signals["SpeedOverGround"][i] = 0.0 if no_fix else st.signals["SpeedOverGround"][last_good]
                st.signals["CourseOverGround"][i] = 0.0 if no_fix else st.signals["CourseOverGround"][last_good]
                st.fault[i] = "gps_no_fix" if no_fix else "gps_dead_reckoning"
        elif f.kind == "counter_frozen":
            # the sensor hangs: its last frame (payload and counter) is sent again and again
            src = win[0] - 1 if win[0] > 0 else win[0]
            for i in win:
                for k in st.signals:
                    st.signals[k][i] = st.signals[k][src]
                st.counter[i] = st.counter[src]
                st.fault[i] = "counter_frozen"
            # after the hang the counter resumes where it would have been (a jump)
        elif f.kind == "silent":
            drop[f.message][win] = True
        elif f.kind == "corrupt":
            n = DLC[f.message]
            for i in win:
                if rng.random() < 0.6:
                    st.raw[int(i)] = rng.bytes(n)
                    st.fault[int(i)] = "corrupt"
        elif f.kind == "wrong_dlc":
            if f.dlc is None or not 0 <= f.dlc <= 8:
                raise ValueError(f"wrong_dlc fault needs a dlc in 0..8, got {f.dlc!r}")
            for i in win[::2]:
                st.dlc[int(i)] = f.dlc
                st.fault[int(i)] = (st.fault.get(int(i), "") + " wrong_dlc").strip()
        else:
            raise ValueError(f"unknown fault kind {f.kind!r}")
    for name, d in drop.items():
        if d.any():
            streams[name].select(~d)
