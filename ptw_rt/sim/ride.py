"""Simulate a ride: scenario -> plan -> jitted rider + plant loop -> truth -> sensor frames.

>>> ride = simulate("dlc_100", seed=3)                       # doctest: +SKIP
>>> ride.truth["roll"], ride.streams["IMU_Rates"].signals["YawRate"]  # doctest: +SKIP
>>> for frame in ride.frames(): ...                          # doctest: +SKIP
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ptw_rt.errors import UserFacingError
from ptw_rt.model.parameters import VehicleParameters, load_vehicle
from ptw_rt.paths import DEFAULT_CONFIG
from ptw_rt.sim import loop
from ptw_rt.sim.plant import NX, PSI, XPOS, YPOS, Longitudinal, LowSpeed, PlantConfig, U, effective_mass, pack
from ptw_rt.sim.rider import NCS, RiderConfig, design_lean_schedule, ou_noise, pack_rider
from ptw_rt.sim.routes import MAX_ROUTE, ROUTE_PREFIX, route_scenario
from ptw_rt.sim.scenarios import PLAN_DT, SCENARIOS, FaultEvent, Plan, Scenario
from ptw_rt.sim.sensors import MessageStream, SensorConfig, SensorFrame, make_sensor_streams
from ptw_rt.sim.tyres import TyreShape
from ptw_rt.untrusted import excerpt

PLANT_DT = 1e-3  # s, RK4 step (1 kHz)
TRUTH_DT = 0.01  # s, truth sampling (100 Hz)
EPOCH_BASE = 1_700_000_000.0  # s, log time of t = 0 (plus the scenario's offset)

# Truth columns, in CSV order: the contract's first, then extras.
TRUTH_COLUMNS = (
    "t",
    "speed",
    "roll",
    "roll_rate",
    "steer",
    "steer_rate",
    "yaw_rate",
    "lat_vel",
    "fy_front",
    "fy_rear",
    "rider_torque",
    "c_alpha_front",
    "c_alpha_rear",
    "c_gamma_front",
    "c_gamma_rear",
    "mu",
    # extras
    "x",
    "y",
    "heading",
    "long_force",
    "long_accel",
    "lat_accel",
    "slip_front",
    "slip_rear",
    "camber_front",
    "camber_rear",
    "fy_front_ss",
    "fy_rear_ss",
    "grip_used_front",
    "grip_used_rear",
    "roll_ref",
    "path_error",
    "speed_ref",
    "support",
)
TRUTH_UNITS = {
    "t": "s",
    "speed": "m/s",
    "roll": "rad",
    "roll_rate": "rad/s",
    "steer": "rad",
    "steer_rate": "rad/s",
    "yaw_rate": "rad/s",
    "lat_vel": "m/s",
    "fy_front": "N",
    "fy_rear": "N",
    "rider_torque": "N m",
    "c_alpha_front": "N/rad",
    "c_alpha_rear": "N/rad",
    "c_gamma_front": "N/rad",
    "c_gamma_rear": "N/rad",
    "mu": "-",
    "x": "m",
    "y": "m",
    "heading": "rad",
    "long_force": "N",
    "long_accel": "m/s^2",
    "lat_accel": "m/s^2",
    "slip_front": "rad",
    "slip_rear": "rad",
    "camber_front": "rad",
    "camber_rear": "rad",
    "fy_front_ss": "N",
    "fy_rear_ss": "N",
    "grip_used_front": "-",
    "grip_used_rear": "-",
    "roll_ref": "rad",
    "path_error": "m",
    "speed_ref": "m/s",
    "support": "-",
}

PERTURB_KEYS = {
    "mass_inertia": "factor on every mass, inertia and the static front load (seed 000: 1.2)",
    "stiffness": "factor on all four tyre stiffnesses (seed 001: 0.5 .. 1.5)",
    "front_stiffness": "factor on the front tyre's two stiffnesses, times `stiffness` (tyres that differ by axle)",
    "rear_stiffness": "factor on the rear tyre's two stiffnesses, times `stiffness` (a worn or soft rear)",
    "added_mass": "kg added at the rear-frame CoM (rider/luggage; seed 001: -50 .. +50)",
    "mu": "constant road friction replacing the scenario's profile",
    "mu_scale": "factor on the scenario's friction profile",
    "imu_noise": "factor on the IMU white noise (gyro 0.002 rad/s, accel 0.03 m/s^2 rms)",
    "imu_bias": "factor on the IMU per-run bias (gyro 0.003 rad/s, accel 0.05 m/s^2 rms)",
    "steer_offset": "steering encoder calibration offset in counts (straight ahead reads 512 + offset)",
    "rider_noise": "factor on the rider's torque noise and line wander",
    "road_slope": "deg of the road's grade, uphill positive (the IMU and GPS readings; the plant keeps its speed)",
    "road_slope_swing": "deg the grade swings about road_slope, a sine over road_slope_length (hills: crests, dips)",
    "road_slope_length": "m ridden over one swing of the grade (default 500)",
    "imu_mount_roll": "deg the IMU is mounted rolled (right side down) off the chassis axes (an installation error)",
    "imu_mount_pitch": "deg the IMU is mounted pitched (nose up) off the chassis axes",
    # sensor faults the sensors' own checks cannot see (counters, ranges and timing stay right), from fault_at on
    "fault_at": "s into the ride at which the faults below appear (0: from the start)",
    "yaw_gyro_scale": "factor on the yaw-rate gyro's reading (a scale error)",
    "roll_gyro_bias_step": "rad/s added to the roll-rate gyro's reading (a bias step)",
    "roll_gyro_bias_ramp": "s over which that bias grows from 0 to its size (0: a step within one sample)",
    "yaw_gyro_bias_step": "rad/s added to the yaw-rate gyro's reading (a bias step)",
    "steer_offset_step": "counts added to the steering encoder's reading (a slipped encoder)",
}

MIN_DURATION = 1.0  # s of a simulated ride
MAX_SEED = 2**63  # numpy's generators take non-negative seeds


@dataclass(frozen=True)
class Perturbation:
    mass_inertia: float = 1.0
    stiffness: float = 1.0
    front_stiffness: float = 1.0
    rear_stiffness: float = 1.0
    added_mass: float = 0.0
    mu: float | None = None
    mu_scale: float = 1.0
    imu_noise: float = 1.0
    imu_bias: float = 1.0
    steer_offset: float = 0.0
    rider_noise: float = 1.0
    road_slope: float = 0.0
    road_slope_swing: float = 0.0
    road_slope_length: float = 500.0
    imu_mount_roll: float = 0.0
    imu_mount_pitch: float = 0.0
    fault_at: float = 0.0
    yaw_gyro_scale: float = 1.0
    roll_gyro_bias_step: float = 0.0
    roll_gyro_bias_ramp: float = 0.0
    yaw_gyro_bias_step: float = 0.0
    steer_offset_step: float = 0.0

    def as_dict(self) -> dict[str, float | None]:
        return {k: getattr(self, k) for k in PERTURB_KEYS}

    @property
    def injects_fault(self) -> bool:
        """A sensor fault no input check can see is injected at `fault_at` (a yaw-gyro scale, a gyro bias step, a
        slipped encoder; `roll_gyro_bias_ramp` only shapes the roll gyro's)."""
        return (
            self.yaw_gyro_scale != 1.0
            or self.roll_gyro_bias_step != 0.0
            or self.yaw_gyro_bias_step != 0.0
            or self.steer_offset_step != 0.0
        )


def parse_perturbations(items: list[str] | None) -> Perturbation:
    """``["mass_inertia=1.2", "stiffness=0.5"]`` -> Perturbation; clear errors for unknown keys/values."""
    values: dict[str, float] = {}
    for item in items or []:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise UserFacingError(f"--perturb {item!r}: expected KEY=VALUE, e.g. stiffness=0.5")
        if key not in PERTURB_KEYS:
            known = ", ".join(PERTURB_KEYS)
            raise UserFacingError(f"--perturb {item!r}: unknown key {key!r}; known keys: {known}")
        try:
            value = float(text)
        except ValueError:
            raise UserFacingError(f"--perturb {item!r}: {text!r} is not a number") from None
        if not math.isfinite(value):
            raise UserFacingError(f"--perturb {item!r}: value must be finite")
        if key in ("mass_inertia", "stiffness", "front_stiffness", "rear_stiffness") and not 0.2 <= value <= 5.0:
            raise UserFacingError(f"--perturb {item!r}: {key} is a factor, expected 0.2 .. 5")
        if key in ("mu", "mu_scale") and not 0.05 <= value <= 1.5:
            raise UserFacingError(f"--perturb {item!r}: {key} must be within 0.05 .. 1.5")
        if key in ("imu_noise", "imu_bias", "rider_noise") and not 0.0 <= value <= 100.0:
            raise UserFacingError(f"--perturb {item!r}: {key} is a factor, expected 0 .. 100")
        if key in ("road_slope", "imu_mount_roll", "imu_mount_pitch") and not abs(value) <= 20.0:
            raise UserFacingError(f"--perturb {item!r}: {key} must be within -20 .. 20 deg")
        if key == "road_slope_swing" and not 0.0 <= value <= 20.0:
            raise UserFacingError(f"--perturb {item!r}: road_slope_swing must be within 0 .. 20 deg")
        if key == "road_slope_length" and not 20.0 <= value <= 100_000.0:
            raise UserFacingError(f"--perturb {item!r}: road_slope_length must be within 20 .. 100000 m")
        if key == "added_mass" and not -150.0 <= value <= 300.0:
            raise UserFacingError(f"--perturb {item!r}: added_mass must be within -150 .. 300 kg")
        if key == "fault_at" and not 0.0 <= value <= 3600.0:
            raise UserFacingError(f"--perturb {item!r}: fault_at must be within 0 .. 3600 s")
        if key == "yaw_gyro_scale" and not 0.2 <= value <= 5.0:
            raise UserFacingError(f"--perturb {item!r}: yaw_gyro_scale is a factor, expected 0.2 .. 5")
        if key in ("roll_gyro_bias_step", "yaw_gyro_bias_step") and not abs(value) <= 1.0:
            raise UserFacingError(f"--perturb {item!r}: {key} must be within -1 .. 1 rad/s")
        if key == "roll_gyro_bias_ramp" and not 0.0 <= value <= 3600.0:
            raise UserFacingError(f"--perturb {item!r}: roll_gyro_bias_ramp must be within 0 .. 3600 s")
        if key in ("steer_offset", "steer_offset_step") and not (-100 <= value <= 100 and value == int(value)):
            raise UserFacingError(f"--perturb {item!r}: {key} is an integer number of counts, |.| <= 100")
        if key in values and values[key] != value:  # which one was meant? (the last one won, silently)
            raise UserFacingError(f"--perturb {key} given twice ({values[key]:g} and {value:g})")
        values[key] = value
    return Perturbation(**values)


def perturbed_vehicle(p: VehicleParameters, pert: Perturbation) -> VehicleParameters:
    q = p.scaled(pert.mass_inertia, pert.stiffness, pert.front_stiffness, pert.rear_stiffness)
    if pert.added_mass:
        try:
            q = q.with_added_mass(pert.added_mass)  # a point mass at the rear-frame CoM, as the file's `added_mass`
        except ValueError as exc:
            raise UserFacingError(f"added_mass {exc}") from None
    return q


class NoRiderError(UserFacingError):
    """The simulated rider (an LQR) cannot be designed for this vehicle."""


@dataclass
class Ride:
    """One simulated ride: truth at 100 Hz, sensor streams, and what produced them."""

    scenario: str
    description: str
    seed: int
    duration: float
    epoch: float  # log time stamp of t = 0 [s]
    vehicle: VehicleParameters  # the plant's (perturbed) parameters
    perturbation: Perturbation
    truth: dict[str, np.ndarray]  # TRUTH_COLUMNS -> arrays at 100 Hz
    streams: dict[str, MessageStream]  # DBC message name -> frames of that message
    faults: list[FaultEvent]
    sensor_meta: dict[str, object]  # biases, offsets, phases drawn for this run
    crashed_at: float | None = None  # s, if the rider lost it (|roll| > 69 deg or non-finite state)
    wall_time: float = 0.0  # s spent simulating (loop + sensors)
    record: np.ndarray | None = field(default=None, repr=False)  # 1 kHz record (loop.REC_* columns)

    @property
    def real_time_factor(self) -> float:
        return self.duration / self.wall_time if self.wall_time > 0 else math.inf

    def frames(self) -> Iterator[SensorFrame]:
        """All sensor frames of all messages, in time order (ties: DBC order of the messages)."""
        items = []
        for order, (name, st) in enumerate(self.streams.items()):
            for i in range(len(st.t)):
                items.append((st.t[i], order, name, i))
        items.sort()
        for _, _, name, i in items:
            yield self.streams[name].frame(i)

    def n_frames(self) -> int:
        return sum(len(s.t) for s in self.streams.values())


def get_scenario(name: str) -> Scenario:
    """One of the eight scenarios, or ``route_N``: random route N (``ptw_rt.sim.routes``)."""
    if name in SCENARIOS:
        return SCENARIOS[name]
    number = name[len(ROUTE_PREFIX) :] if name.startswith(ROUTE_PREFIX) else ""
    if number.isascii() and number.isdigit() and len(number) <= 9:
        return route_scenario(int(number))
    raise UserFacingError(
        f"unknown scenario {excerpt(name, 40)}; available: {', '.join(SCENARIOS)}, or {ROUTE_PREFIX}N (a random route, "
        f"N = 0..{MAX_ROUTE - 1})"
    )


def _progress(label: str, frac: float, enabled: bool) -> None:
    if not enabled or frac > 1.0:
        return
    width = 30
    filled = int(round(frac * width))
    sys.stderr.write(f"\r{label:<24} [{'#' * filled}{'.' * (width - filled)}] {100 * frac:5.1f}%")
    if frac >= 1.0:
        sys.stderr.write("\n")
    sys.stderr.flush()


def simulate(
    scenario: str | Scenario,
    *,
    seed: int | None = None,
    duration: float | None = None,
    vehicle: VehicleParameters | str | Path | None = None,
    perturbation: Perturbation | None = None,
    sensors: SensorConfig | None = None,
    rider: RiderConfig | None = None,
    longitudinal: Longitudinal | None = None,
    low_speed: LowSpeed | None = None,
    tyre: TyreShape | None = None,
    progress: bool = False,
    keep_record: bool = False,
) -> Ride:
    sc = get_scenario(scenario) if isinstance(scenario, str) else scenario
    seed = sc.seed if seed is None else int(seed)
    if not 0 <= seed < MAX_SEED:
        raise UserFacingError(f"seed must be within 0-{MAX_SEED - 1}, got {seed}")
    duration = sc.duration if duration is None else float(duration)
    if not (MIN_DURATION <= duration <= 3600.0):  # below a second the sensors' first GPS fix is not even due
        raise UserFacingError(f"duration must be within {MIN_DURATION:g}-3600 s, got {duration}")
    pert = perturbation or Perturbation()
    if vehicle is None or isinstance(vehicle, (str, Path)):
        nominal = load_vehicle(vehicle or DEFAULT_CONFIG)
    else:
        nominal = vehicle
    p = perturbed_vehicle(nominal, pert)
    sensors = sensors or SensorConfig()
    rider = rider or RiderConfig()
    plant_cfg = PlantConfig(
        p, longitudinal or Longitudinal(), low_speed or LowSpeed(), tyre or TyreShape(), hold_speed=False
    )
    t_start = time.perf_counter()

    plan: Plan = sc.build(duration)
    mu = plan.mu.copy() if pert.mu is None else np.full_like(plan.mu, pert.mu)
    mu *= pert.mu_scale
    n_plan = len(plan.speed)

    rng = np.random.default_rng(seed)
    rider_rng = np.random.default_rng([seed, 1])
    noise = ou_noise(rider_rng, n_plan, PLAN_DT, rider.torque_noise * pert.rider_noise, rider.torque_noise_time)
    wander = ou_noise(rider_rng, n_plan, PLAN_DT, rider.line_wander * pert.rider_noise, rider.line_wander_time)
    wander -= wander[0]  # start on the line

    # the rider knows the bike (perturbed parameters) and the road he starts on. He is an LQR designed for it: a
    # vehicle the config's ranges let through (or a perturbation of it) may have none, which is one line for the
    # user, whichever command simulated
    try:
        with np.errstate(all="ignore"):
            schedule = design_lean_schedule(plant_cfg, rider, float(mu[0]))
            pp, m4inv = pack(plant_cfg)
            lon = plant_cfg.longitudinal
            rp = pack_rider(rider, p, effective_mass(p), lon.air_density * lon.drag_area, lon.rolling_resistance)
    except (np.linalg.LinAlgError, ArithmeticError, ValueError) as exc:
        raise NoRiderError(f"{sc.name}: no simulated rider can ride this vehicle ({exc})") from None

    path = plan.path
    x = np.zeros(NX)
    x[U] = plan.initial_speed
    x[PSI] = path.heading[0]
    x[XPOS] = path.x[0]
    x[YPOS] = path.y[0]
    cs = np.zeros(NCS)

    n_steps = int(round(duration / PLANT_DT)) + 1
    rec = np.zeros((n_steps, loop.NREC))
    chunk = max(1, int(round(5.0 / PLANT_DT)))
    crash = -1
    show = progress and duration >= 20.0
    for k0 in range(0, n_steps, chunk):
        k1 = min(n_steps, k0 + chunk)
        crash = loop.ride_chunk(
            k0,
            k1,
            PLANT_DT,
            x,
            cs,
            pp,
            m4inv,
            rp,
            schedule.gains,
            schedule.trims,
            schedule.preview,
            path.x,
            path.y,
            path.heading,
            path.curvature,
            path.curvature_rate,
            path.ds,
            PLAN_DT,
            plan.speed,
            plan.accel,
            mu,
            noise,
            wander,
            rec,
        )
        if crash >= 0:
            break
        _progress(f"{sc.name}: riding", k1 / n_steps, show)
    crashed_at = None
    if crash >= 0:
        crashed_at = crash * PLANT_DT
        rec[crash + 1 :] = rec[crash]
        rec[crash + 1 :, loop.REC_T] = np.arange(crash + 1, n_steps) * PLANT_DT
        _progress(f"{sc.name}: riding", 1.0, show)

    truth = truth_from_record(rec, p)
    streams, meta = make_sensor_streams(rec, p, sensors, pert, rng, plan.faults, duration)
    wall = time.perf_counter() - t_start
    return Ride(
        scenario=sc.name,
        description=sc.description,
        seed=seed,
        duration=duration,
        epoch=EPOCH_BASE + sc.epoch_offset,
        vehicle=p,
        perturbation=pert,
        truth=truth,
        streams=streams,
        faults=list(plan.faults),
        sensor_meta=meta,
        crashed_at=crashed_at,
        wall_time=wall,
        record=rec if keep_record else None,
    )


def truth_from_record(rec: np.ndarray, p: VehicleParameters) -> dict[str, np.ndarray]:
    step = int(round(TRUTH_DT / PLANT_DT))
    r = rec[::step]
    X = loop.REC_X0
    mu = r[:, loop.REC_MU]
    u = r[:, X + U]
    vy = r[:, X + 2]
    yaw = r[:, X + 3]
    peak_f = np.maximum(r[:, loop.REC_PEAK_F], 1e-9)
    peak_r = np.maximum(r[:, loop.REC_PEAK_R], 1e-9)
    cols = {
        "t": r[:, loop.REC_T],
        "speed": u,
        "roll": r[:, X + 0],
        "roll_rate": r[:, X + 4],
        "steer": r[:, X + 1],
        "steer_rate": r[:, X + 5],
        "yaw_rate": yaw,
        "lat_vel": vy,
        "fy_front": r[:, X + 6],
        "fy_rear": r[:, X + 7],
        "rider_torque": r[:, loop.REC_TAU],
        "c_alpha_front": mu * p.c_af,
        "c_alpha_rear": mu * p.c_ar,
        "c_gamma_front": mu * p.c_gf,
        "c_gamma_rear": mu * p.c_gr,
        "mu": mu,
        "x": r[:, X + XPOS],
        "y": r[:, X + YPOS],
        "heading": r[:, X + PSI],
        "long_force": r[:, loop.REC_FX],
        "long_accel": r[:, loop.REC_DU] - vy * yaw,
        "lat_accel": r[:, loop.REC_DVY] + u * yaw,
        "slip_front": r[:, loop.REC_ALPHA_F],
        "slip_rear": r[:, loop.REC_ALPHA_R],
        "camber_front": r[:, loop.REC_GAMMA_F],
        "camber_rear": r[:, loop.REC_GAMMA_R],
        "fy_front_ss": r[:, loop.REC_FSS_F],
        "fy_rear_ss": r[:, loop.REC_FSS_R],
        "grip_used_front": np.abs(r[:, loop.REC_FSS_F]) / peak_f,
        "grip_used_rear": np.abs(r[:, loop.REC_FSS_R]) / peak_r,
        "roll_ref": r[:, loop.REC_PHI_REF],
        "path_error": r[:, loop.REC_EY],
        "speed_ref": r[:, loop.REC_VREF],
        "support": 1.0 - r[:, loop.REC_W],
    }
    return {k: np.ascontiguousarray(cols[k]) for k in TRUTH_COLUMNS}
