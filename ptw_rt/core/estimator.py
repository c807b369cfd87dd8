"""The estimator: one Sample in, one Estimates out, every 10 ms, in one jitted call of eight stages.

Per cycle (`packed_step`), one jitted function per stage, in this order (`STAGES`):

  1. inputs (`ptw_rt.core.inputs`): non-finite or implausible values replaced by the last good ones and
     flagged; stale and suspect messages held; steer-encoder jumps; GPS age;
  2. speed (`ptw_rt.core.speed`): GPS + longitudinal accelerometer, latency compensated;
  3. attitude (`ptw_rt.core.attitude`): roll and the gyro and accelerometer biases from kinematics alone;
  4. conditioning (`ptw_rt.core.conditioning`): steer angle, bias-corrected rates and their derivatives,
     a_y at the centre of mass, whether the model-based observers run, the published roll;
  5. diagnostics (`ptw_rt.core.diagnostics`): seed 000's UIHOSMO and seed 003's super-twisting force
     observer, unpublished cross-checks;
  6. lateral (`ptw_rt.core.lateral`): the fusion filter on the Sharp model (torque, steer rate, v_y, forces);
  7. stiffness (`ptw_rt.core.stiffness`): seed 001's adaptive observer, driven by the fusion filter's torque;
  8. supervisor (`ptw_rt.core.supervisor`): mode, reason bits, per-signal validity;

then `publish` copies the stages' outputs into the Estimates record (`ptw_rt.core.layout`). A stage reads only
the named outputs of the stages before it (docs/estimator.md, "Stages"). Below the model's validity speed
the observers are held in reset: roll is the attitude filter's (or the gyro fallback), torque and tyre
quantities are flagged invalid.

**Adding a stage** (e.g. a stiffness learner): a module with its ``STATE``/``PARAMS``/``OUTPUTS`` layouts,
``build_params(settings, design)``, optional ``TABLES``, a jitted ``*_stage`` function and a ``STAGE =
Stage(...)`` (`ptw_rt.core.stage`); add ``STAGE`` to ``STAGES`` below and an index name to the unpacking
under it; call its function in `packed_step` where its inputs are ready; read its outputs in later stages
or in `publish`. The buffers, index rows, `Estimator.reset` and the layout tests follow from ``STAGES``.

**Packed call.** numba unboxes every array argument on each call from Python (~0.15 us each): the
`Estimator` keeps every stage's state and outputs in one flat buffer and every stage's parameters and tables
in another, and calls `packed_step` with 6 arguments; the views are rebuilt inside compiled code
(`ptw_rt.core.stage`). Index rows: state buffer ``2 k`` the state of stage k, ``2 k + 1`` its outputs;
table buffer ``k`` the parameters of stage k, then each stage's tables from row ``TABLE_ROW0[k]``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ptw_rt.core import attitude as att
from ptw_rt.core import channel_kinematics as ck
from ptw_rt.core import conditioning as cnd
from ptw_rt.core import diagnostics as dia
from ptw_rt.core import inputs as inp
from ptw_rt.core import kalman as kf
from ptw_rt.core import lateral as lat
from ptw_rt.core import speed as spd
from ptw_rt.core import stiffness as stf
from ptw_rt.core import supervisor as sup
from ptw_rt.core import uio_sensors as cus
from ptw_rt.core.conditioning import ground_yaw_rate
from ptw_rt.core.layout import (
    E_C_ALPHA_FRONT,
    E_C_ALPHA_FRONT_SEED001,
    E_C_ALPHA_REAR,
    E_C_ALPHA_REAR_SEED001,
    E_C_GAMMA_FRONT,
    E_C_GAMMA_FRONT_SEED001,
    E_C_GAMMA_REAR,
    E_C_GAMMA_REAR_SEED001,
    E_EXCITATION,
    E_FY_FRONT,
    E_FY_FRONT_ADAPTIVE,
    E_FY_FRONT_STA,
    E_FY_REAR,
    E_FY_REAR_ADAPTIVE,
    E_FY_REAR_STA,
    E_LAT_ACCEL,
    E_LAT_ACCEL_BIAS,
    E_LAT_VEL,
    E_LAT_VEL_ADAPTIVE,
    E_MODE,
    E_PITCH_DOUBTED,
    E_PITCH_GYRO_BIAS,
    E_PLAUSIBILITY,
    E_REASONS,
    E_RIDER_TORQUE,
    E_ROLL,
    E_ROLL_ADAPTIVE,
    E_ROLL_FUSION,
    E_ROLL_GYRO_BIAS,
    E_ROLL_RATE,
    E_ROLL_RATE_MEASURED,
    E_ROLL_SD,
    E_ROLL_UIHOSMO,
    E_ROLL_UIO_SENSORS,
    E_SPEED,
    E_STEER,
    E_STEER_RATE,
    E_STEER_RESIDUAL,
    E_STEER_ZERO_DOUBTED,
    E_STEER_ZERO_ERROR,
    E_STEER_ZERO_ERROR_SD,
    E_TORQUE_RESIDUAL,
    E_TORQUE_UIHOSMO,
    E_TORQUE_UIO_SENSORS,
    E_TYRE_BALANCE,
    E_TYRE_BALANCE_DOUBTED,
    E_TYRE_BALANCE_LOG_SD,
    E_TYRE_CHANGE,
    E_TYRE_LEARNING,
    E_TYRE_LOG_SD,
    E_TYRE_NIS,
    E_TYRE_SCALE,
    E_VALID,
    E_Y_A,
    E_YAW_GYRO_BIAS,
    E_YAW_RATE,
    ESTIMATES_SIZE,
)
from ptw_rt.core.stage import Stage, borrowed, pack, v1

# share of the configured initial bias uncertainty a bias restored from the state file starts with
RESTORED_BIAS_SHARE = 0.3

# the stages, in the order they run; the names below index every per-stage row
STAGES: tuple[Stage, ...] = (
    inp.STAGE,
    spd.STAGE,
    att.STAGE,
    cnd.STAGE,
    dia.STAGE,
    lat.STAGE,
    stf.STAGE,
    sup.STAGE,
)
INPUTS, SPEED, ATTITUDE, CONDITIONING, DIAGNOSTICS, LATERAL, STIFFNESS, SUPERVISOR = range(len(STAGES))
N_STAGES = len(STAGES)
STAGE_NAMES = tuple(s.name for s in STAGES)
# first table row of each stage in the table buffer (its parameters are row k)
TABLE_ROW0 = tuple(N_STAGES + sum(len(s.tables) for s in STAGES[:k]) for k in range(N_STAGES))


@njit(cache=True, inline="always")
def _state(s: np.ndarray, si: np.ndarray, k: int) -> np.ndarray:
    return v1(s, si, 2 * k)


@njit(cache=True, inline="always")
def _out(s: np.ndarray, si: np.ndarray, k: int) -> np.ndarray:
    return v1(s, si, 2 * k + 1)


@njit(cache=True)
def publish(
    est: np.ndarray,
    o_in: np.ndarray,
    o_spd: np.ndarray,
    o_att: np.ndarray,
    o_cnd: np.ndarray,
    o_dia: np.ndarray,
    o_lat: np.ndarray,
    o_stf: np.ndarray,
    o_sup: np.ndarray,
) -> None:
    """The Estimates record from the stages' outputs; nothing non-finite leaves the step."""
    run = o_lat[lat.OUT_RAN] != 0.0  # the filters ran: on every sensor, or coasting through a silent one
    z = o_lat[lat.OUT_Z : lat.OUT_Z + kf.N_Z]  # the fusion filter's (docs/estimator.md, what is published)
    raw = o_in[inp.OUT_RAW : inp.OUT_RAW + inp.N_RAW]
    roll = o_cnd[cnd.OUT_ROLL]
    est[E_ROLL] = roll
    est[E_ROLL_RATE] = o_cnd[cnd.OUT_ROLL_RATE]
    est[E_RIDER_TORQUE] = z[kf.TAU] if run else 0.0
    est[E_STEER] = z[kf.DELTA] if run else o_cnd[cnd.OUT_STEER]
    est[E_STEER_RATE] = z[kf.DELTA_DOT] if run else 0.0
    est[E_LAT_VEL] = z[kf.VY] if run else 0.0
    est[E_FY_FRONT] = z[kf.FYF] if run else 0.0
    est[E_FY_REAR] = z[kf.FYR] if run else 0.0
    est[E_C_ALPHA_FRONT] = o_lat[lat.OUT_TYRE_STIFFNESS + 0]  # the tyre bank's (lateral stage)
    est[E_C_GAMMA_FRONT] = o_lat[lat.OUT_TYRE_STIFFNESS + 1]
    est[E_C_ALPHA_REAR] = o_lat[lat.OUT_TYRE_STIFFNESS + 2]
    est[E_C_GAMMA_REAR] = o_lat[lat.OUT_TYRE_STIFFNESS + 3]
    est[E_TYRE_SCALE] = o_lat[lat.OUT_TYRE_SCALE]
    est[E_TYRE_LOG_SD] = o_lat[lat.OUT_TYRE_LOG_SD]
    est[E_TYRE_NIS] = o_lat[lat.OUT_TYRE_NIS]
    est[E_TYRE_LEARNING] = o_lat[lat.OUT_TYRE_LEARNING]
    est[E_TYRE_CHANGE] = o_lat[lat.OUT_TYRE_CHANGE]
    est[E_TYRE_BALANCE] = math.exp(o_lat[lat.OUT_TYRE_BALANCE_LOG])  # a check: not applied to the front
    est[E_TYRE_BALANCE_DOUBTED] = o_sup[sup.OUT_TYRE_BALANCE_DOUBTED]
    est[E_STEER_ZERO_ERROR] = o_lat[lat.OUT_TYRE_ZERO_ERROR]
    est[E_STEER_ZERO_DOUBTED] = o_sup[sup.OUT_STEER_ZERO_DOUBTED]
    est[E_TYRE_BALANCE_LOG_SD] = o_lat[lat.OUT_TYRE_BALANCE_LOG_SD]
    est[E_STEER_ZERO_ERROR_SD] = o_lat[lat.OUT_TYRE_ZERO_ERROR_SD]
    est[E_PITCH_DOUBTED] = 1.0 if att.pitch_doubted(o_att) else 0.0  # the lateral stage's learning gate
    est[E_C_ALPHA_FRONT_SEED001] = o_stf[stf.OUT_STIFFNESS + 0]  # seed 001's adaptive observer (diagnostic)
    est[E_C_GAMMA_FRONT_SEED001] = o_stf[stf.OUT_STIFFNESS + 1]
    est[E_C_ALPHA_REAR_SEED001] = o_stf[stf.OUT_STIFFNESS + 2]
    est[E_C_GAMMA_REAR_SEED001] = o_stf[stf.OUT_STIFFNESS + 3]
    est[E_SPEED] = o_spd[spd.OUT_U]
    est[E_YAW_RATE] = ground_yaw_rate(raw[inp.RAW_Q], raw[inp.RAW_R], roll)  # as measured: the baselines' input
    est[E_ROLL_RATE_MEASURED] = raw[inp.RAW_P]
    est[E_YAW_GYRO_BIAS] = o_att[att.OUT_BR]
    est[E_ROLL_GYRO_BIAS] = o_att[att.OUT_BP]
    est[E_PITCH_GYRO_BIAS] = o_att[att.OUT_BQ]
    est[E_LAT_ACCEL_BIAS] = o_att[att.OUT_BAY]
    est[E_ROLL_SD] = o_sup[sup.OUT_ROLL_SD]
    est[E_ROLL_FUSION] = z[kf.PHI] if run else 0.0
    est[E_MODE] = o_sup[sup.OUT_MODE]
    est[E_REASONS] = o_sup[sup.OUT_REASONS]
    est[E_VALID] = o_sup[sup.OUT_VALID]
    est[E_ROLL_UIHOSMO] = o_dia[dia.OUT_ROLL]
    est[E_LAT_ACCEL] = o_cnd[cnd.OUT_A_Y]
    est[E_EXCITATION] = o_stf[stf.OUT_EXCITATION]
    est[E_ROLL_ADAPTIVE] = o_stf[stf.OUT_ROLL]
    est[E_TORQUE_UIHOSMO] = o_dia[dia.OUT_TORQUE]
    est[E_FY_FRONT_STA] = o_dia[dia.OUT_FY_FRONT]
    est[E_FY_REAR_STA] = o_dia[dia.OUT_FY_REAR]
    est[E_LAT_VEL_ADAPTIVE] = o_stf[stf.OUT_LAT_VEL]
    est[E_FY_FRONT_ADAPTIVE] = o_stf[stf.OUT_FY_FRONT]
    est[E_FY_REAR_ADAPTIVE] = o_stf[stf.OUT_FY_REAR]
    est[E_Y_A] = o_stf[stf.OUT_Y_A]
    us = o_dia[dia.OUT_US : dia.OUT_US + cus.OUT_SIZE]
    est[E_TORQUE_UIO_SENSORS] = us[cus.OUT_TORQUE] if us[cus.OUT_VALID] != 0.0 else 0.0
    ch = o_dia[dia.OUT_CH : dia.OUT_CH + ck.OUT_SIZE]
    est[E_ROLL_UIO_SENSORS] = ch[ck.OUT_ROLL] if ch[ck.OUT_VALID] != 0.0 else 0.0
    est[E_TORQUE_RESIDUAL] = o_sup[sup.OUT_TORQUE_RESIDUAL]
    est[E_PLAUSIBILITY] = o_sup[sup.OUT_PLAUSIBILITY]
    est[E_STEER_RESIDUAL] = o_sup[sup.OUT_STEER_RESIDUAL]
    # last line of defence: nothing non-finite leaves the step
    for k in range(ESTIMATES_SIZE):
        if not math.isfinite(est[k]):
            est[k] = 0.0


@njit(cache=True)
def packed_step(
    sample: np.ndarray,
    est: np.ndarray,
    s: np.ndarray,
    si: np.ndarray,
    t: np.ndarray,
    ti: np.ndarray,
) -> None:
    """One cycle: every stage on views of the two flat buffers (state `s`, tables `t`, and their index rows)."""
    # no reference counting on anything handed on (`stage.borrowed`): the caller holds the arrays
    sample, est, s, si, t, ti = borrowed(sample), borrowed(est), borrowed(s), borrowed(si), borrowed(t), borrowed(ti)
    o_in = _out(s, si, INPUTS)
    o_spd = _out(s, si, SPEED)
    o_att = _out(s, si, ATTITUDE)
    o_cnd = _out(s, si, CONDITIONING)
    o_dia = _out(s, si, DIAGNOSTICS)
    o_lat = _out(s, si, LATERAL)
    o_stf = _out(s, si, STIFFNESS)
    o_sup = _out(s, si, SUPERVISOR)
    inp.inputs_stage(sample, _state(s, si, INPUTS), v1(t, ti, INPUTS), o_in)
    # the IMU's pitch and what the turn adds along x, of the cycle before (the attitude stage runs after the speed
    # stage, which it needs)
    pitch_before = o_att[att.OUT_PITCH] if o_att[att.OUT_OK] != 0.0 else 0.0
    turn_before = att.turn_accel_of(o_att, v1(t, ti, ATTITUDE), o_cnd[cnd.OUT_YAW_ACCEL])
    spd.speed_stage(_state(s, si, SPEED), v1(t, ti, SPEED), o_spd, o_in, pitch_before, turn_before)
    att.attitude_stage(_state(s, si, ATTITUDE), v1(t, ti, ATTITUDE), o_att, o_in, o_spd)
    # the steer zero error the tyre bank's check pointed to the cycle before, if the bank ran (the lateral stage runs
    # after this one; a bank that did not run has not re-centred its evidence on the zero it moved)
    zero_error = o_lat[lat.OUT_TYRE_ZERO_ERROR] if o_lat[lat.OUT_RAN] != 0.0 else math.nan
    cnd.conditioning_stage(
        sample,
        _state(s, si, CONDITIONING),
        v1(t, ti, CONDITIONING),
        o_cnd,
        o_in,
        o_spd,
        o_att,
        zero_error,
        o_lat[lat.OUT_TYRE_ZERO_ERROR_SD],
    )
    dia.diagnostics_stage(
        _state(s, si, DIAGNOSTICS),
        v1(t, ti, DIAGNOSTICS),
        o_dia,
        t,
        ti,
        TABLE_ROW0[DIAGNOSTICS],
        o_in,
        o_spd,
        o_att,
        o_cnd,
    )
    lat.lateral_stage(
        _state(s, si, LATERAL), v1(t, ti, LATERAL), o_lat, t, ti, TABLE_ROW0[LATERAL], o_in, o_spd, o_att, o_cnd
    )
    stf.stiffness_stage(
        _state(s, si, STIFFNESS),
        v1(t, ti, STIFFNESS),
        o_stf,
        t,
        ti,
        TABLE_ROW0[STIFFNESS],
        o_in,
        o_spd,
        o_cnd,
        o_lat,
    )
    sup.supervisor_stage(
        _state(s, si, SUPERVISOR), v1(t, ti, SUPERVISOR), o_sup, o_in, o_spd, o_att, o_cnd, o_dia, o_lat
    )
    publish(est, o_in, o_spd, o_att, o_cnd, o_dia, o_lat, o_stf, o_sup)


class Estimator:
    """Owns the preallocated buffers of one estimator and the bound arguments of its jitted step.

    ``states[name]``, ``outputs[name]`` and ``params[name]`` are views of stage ``name``'s arrays in the flat
    buffers (writes through them reach the step).
    """

    def __init__(self, settings, design) -> None:
        self.settings = settings
        self.design = design
        self.sample_time = float(design.sample_time)
        parts = []
        for stage in STAGES:
            parts.append(stage.initial_state(settings, design))
            parts.append(np.zeros(stage.outputs.size))
        self._state, self._state_index = pack(parts)
        tables = [stage.params_vector(settings, design) for stage in STAGES]
        for stage in STAGES:
            tables.extend(stage.table_arrays(design))
        self._tables, self._table_index = pack(tables)
        self.states = {name: self._view(self._state, self._state_index, 2 * k) for k, name in enumerate(STAGE_NAMES)}
        self.outputs = {
            name: self._view(self._state, self._state_index, 2 * k + 1) for k, name in enumerate(STAGE_NAMES)
        }
        self.params = {name: self._view(self._tables, self._table_index, k) for k, name in enumerate(STAGE_NAMES)}

    @staticmethod
    def _view(buf: np.ndarray, index: np.ndarray, row: int) -> np.ndarray:
        return buf[index[row, 0] : index[row, 1]]

    def reset(self) -> None:
        """Forget everything but the learned stiffness and the sensor biases (each stage's `reset`)."""
        for stage in STAGES:
            stage.reset_state(self.states[stage.name], self.params[stage.name])
            self.outputs[stage.name][:] = 0.0

    def step(self, sample: np.ndarray, estimates: np.ndarray) -> None:
        packed_step(sample, estimates, self._state, self._state_index, self._tables, self._table_index)

    def buffers(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(state, state index, tables, table index)``: the last four arguments of ``packed_step``, for a
        compiled loop that calls the step itself (``ptw_rt.edge.drive``)."""
        return self._state, self._state_index, self._tables, self._table_index

    def learned_stiffness(self) -> np.ndarray:
        """[C_af, C_gf, C_ar, C_gr] in N/rad: the tyre bank's scale times the nominal file's."""
        k = lat.scale_estimate(self.states["lateral"], self.params["lateral"], self.outputs["lateral"])
        return k * np.asarray(self.settings.vehicle.nominal_stiffness())

    def learned_sensor_biases(self) -> tuple[float, float, float, float] | None:
        """(b_p, b_q, b_r [rad/s], b_ay [m/s^2]) the attitude filter has learned, or None while it has no sound
        estimate (not initialised, or its consistency monitor doubts it): what the state file may keep."""
        out = self.outputs["attitude"]
        if out[att.OUT_OK] == 0.0 or out[att.OUT_INCONSISTENT] != 0.0:
            return None
        return float(out[att.OUT_BP]), float(out[att.OUT_BQ]), float(out[att.OUT_BR]), float(out[att.OUT_BAY])

    def learned_accel_biases(self) -> tuple[float, float] | None:
        """(b_ax, b_az [m/s^2]) the attitude filter has learned, under the same conditions as
        `learned_sensor_biases`: what the state file may keep beside them (the IMU's, like the others; the pitch is
        the road's and the mount's, and is not kept)."""
        if self.learned_sensor_biases() is None:
            return None
        x = self.states["attitude"][att.ST_X : att.ST_X + att.N_X]
        return float(x[att.X_BAX]), float(x[att.X_BAZ])

    def restore_sensor_biases(self, values, accel_biases=None) -> None:
        """Start the attitude filter from sensor biases learned on an earlier ride (the state file), with
        RESTORED_BIAS_SHARE of the configured initial uncertainty: a bias drifts between rides (temperature),
        so the ride confirms or corrects it. `accel_biases` = (b_ax, b_az), if the file kept them (else their
        prior)."""
        values = np.asarray(values, dtype=float)
        if values.shape != (4,) or not np.all(np.isfinite(values)):
            raise ValueError("expected four finite sensor biases")
        accel = np.full(2, np.nan)  # not kept: their prior
        if accel_biases is not None:
            accel = np.asarray(accel_biases, dtype=float)
            if accel.shape != (2,) or not np.all(np.isfinite(accel)):
                raise ValueError("expected two finite accelerometer biases")
        tuning = self.settings.estimator.attitude
        att.set_biases(
            self.states["attitude"],
            *values,
            *accel,
            RESTORED_BIAS_SHARE * tuning.initial_gyro_bias_sd,
            RESTORED_BIAS_SHARE * tuning.initial_accel_bias_sd,
            tuning.initial_accel_bias_sd,
        )

    def learned_steer_zero(self) -> tuple[float, float] | None:
        """(configured zero count, learned zero error [rad]) once the conditioning has learned it for a time
        constant of straight riding (or it was restored), or the tyre bank's zero check knows it within its valid
        spread (learned in corners), else None: what the state file may keep."""
        st = self.states["conditioning"]
        # (a spread of 0: the bank has not run, its outputs are still the zeros they start from)
        known_in_corners = (
            0.0
            < self.outputs["lateral"][lat.OUT_TYRE_ZERO_ERROR_SD]
            <= self.params["conditioning"][cnd.P_STEER_ZERO_EVIDENCE_SD]
        )
        if st[cnd.ST_STEER_ZERO_SECONDS] < self.settings.sensors.steer_zero_time_constant and not known_in_corners:
            return None
        return float(self.settings.sensors.steer_zero_count), float(st[cnd.ST_STEER_ZERO_SHIFT])

    def steer_zero_max_shift(self) -> float:
        """rad: how far the conditioning may move the steer zero (the configured counts, as the stage has them)."""
        return float(self.params["conditioning"][cnd.P_STEER_ZERO_MAX_SHIFT])

    def restore_steer_zero(self, zero_count: float, shift: float) -> bool:
        """Start from a steer zero error learned on earlier rides, if it was learned against the zero count the
        configuration has now (False, nothing restored, if not: the encoder was re-zeroed in the file). Raises
        ValueError for a non-finite value or one beyond what the conditioning may learn."""
        if not (math.isfinite(zero_count) and math.isfinite(shift)):
            raise ValueError("expected a finite steer zero")
        bound = self.steer_zero_max_shift()
        if abs(shift) > bound * (1.0 + 1e-9):
            raise ValueError(f"steer zero error {shift:.6g} rad beyond the learnable {bound:.6g} rad")
        if zero_count != self.settings.sensors.steer_zero_count:
            return False
        st = self.states["conditioning"]
        st[cnd.ST_STEER_ZERO_SHIFT] = shift
        st[cnd.ST_STEER_ZERO_SECONDS] = self.settings.sensors.steer_zero_time_constant
        return True

    def learned_tyre_scale(self) -> float:
        return lat.scale_estimate(self.states["lateral"], self.params["lateral"], self.outputs["lateral"])

    def _start_tyres(self, scale: float, restored: bool) -> None:
        lo, hi = float(self.design.tb_scale[0]), float(self.design.tb_scale[-1])
        if not (math.isfinite(scale) and scale > 0.0):
            raise ValueError(f"tyre scale must be finite and > 0, got {scale}")
        lat.set_prior(
            self.states["lateral"], self.params["lateral"], self.design.tb_scale, min(max(scale, lo), hi), restored
        )
        self.outputs["lateral"][lat.OUT_TYRE_SCALE] = 0.0  # the prior's centre until the bank runs

    def restore_stiffness(self, values) -> None:
        """Start from stiffness learned earlier: the tyre bank's prior around it (restored_sd), and seed 001's
        adaptive observer from it (clipped to its bounds). Not valid until the ride confirms it."""
        values = np.asarray(values, dtype=float)
        if values.shape != (4,) or not np.all(np.isfinite(values)) or not np.all(values > 0.0):
            raise ValueError("expected four finite, positive stiffness values")
        ratios = values / np.asarray(self.settings.vehicle.nominal_stiffness())
        self._start_tyres(float(np.exp(np.mean(np.log(ratios)))), restored=True)
        stf.restore(self.states["stiffness"], values, self.design)

    def set_initial_stiffness_scale(self, front: float, rear: float) -> None:
        """Start from the nominal tyres times `front` (C_af, C_gf) and `rear` (C_ar, C_gr); the tyre bank learns
        one scale for all four, so it starts from their geometric mean with its ordinary prior spread; not
        marked restored or learned (the evaluation's wrong-start check)."""
        stf.start_from_scale(self.states["stiffness"], front, rear, self.design)
        self._start_tyres(math.sqrt(float(front) * float(rear)), restored=False)
