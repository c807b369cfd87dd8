"""Stage 2, speed: forward speed at 100 Hz from 10 Hz GPS and the longitudinal accelerometer (jitted).

A complementary filter whose GPS correction is applied against the prediction made when the fix was valid
(latency compensation through a ring buffer of past predictions). A GPS speed farther from the prediction than
the vehicle can have moved is refused (``GATE_*``), until enough in a row say the estimate is what is wrong.
In a GPS dropout the prediction is held (accelerometer only, with a slow decay of the correction) and the inputs
stage flags it. It runs before the attitude stage, which needs the speed (the lateral specific force has a u r
term).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ptw_rt.core import inputs as inp
from ptw_rt.core.stage import Layout, Stage

# ---- state: the filter's fixed part, then a ring of past predictions (`new_speed_state`: latency + 2 long) ----
STATE = Layout(
    "SPD_",
    u=1,
    bias=1,
    head=1,
    init=1,
    refused=1,  # GPS speeds refused in a row (outside the gate) that agree with one another
    refused_last=1,  # m/s, the last of them
    since=1,  # s since the last GPS speed taken
    refused_share=1,  # share of the recent fixes refused (exponentially weighted over ~DOUBT_FIXES fixes)
    # the longitudinal offset, OFFSET_TIME's running means: of the accelerometer (every cycle) and of the GPS speed
    # (every fix taken), whose rate is the speed's; their difference is what the accelerometer reads beyond it
    mean_accel=1,
    mean_speed=1,
    offset=1,
    offset_age=1,  # s since the GPS speed's running mean (re)started: the offset's window is full after OFFSET_TIME
    ring0=1,
)
(
    SPD_U,
    SPD_BIAS,
    SPD_HEAD,
    SPD_INIT,
    SPD_REFUSED,
    SPD_REFUSED_LAST,
    SPD_SINCE,
    SPD_REFUSED_SHARE,
    SPD_MEAN_ACCEL,
    SPD_MEAN_SPEED,
    SPD_OFFSET,
    SPD_OFFSET_AGE,
    SPD_RING0,
) = STATE.offsets

# The gate on a GPS speed's innovation: what the accelerometer-propagated speed can be off by, GPS noise and a
# drift of the accelerometer's bias over the time since the last fix taken. A fix beyond it is not a speed the
# vehicle can have had (one sample of 0 m/s at 20 m/s is a receiver glitch, not a 20 g stop) and is refused;
# REACQUIRE_FIXES refused in a row that agree with one another mean the estimate is what is wrong (a long outage):
# it is re-taken from GPS.
GATE_SPEED = 3.0  # m/s
GATE_DRIFT = 1.0  # m/s^2
GATE_DRIFT_MAX_S = 5.0  # s: the gate stops widening here (a longer outage's error beyond it is re-taken as above; a
# gate that kept widening let a doubted receiver's garbage back in once it spanned most of its range)
REACQUIRE_FIXES = 10
# A receiver most of whose recent fixes are refused is not believed at all: the few of its fixes that fall inside
# the gate are chance, not measurements (random 0-100 m/s at 10 Hz, counters and checksums right: the in-gate ones
# walked the speed 6 m/s off over 57 s). Its fixes are then not taken and the speed dead-reckons as in an outage,
# until the share of refusals falls back (a healthy receiver's glitch is one fix in many) or REACQUIRE_FIXES
# refused fixes agree (a receiver that is right after all).
# The offset (OUTPUTS accel_offset) is its own estimate, not the filter's bias: that one learns slowly on purpose
# (a garbage fix inside the gate moves it), and what the attitude filter needs is a road's slope within seconds.
# Running means over OFFSET_TIME of the accelerometer and of the GPS speed: the rate of the speed's running mean is
# the running mean of its rate, (u - mean) / OFFSET_TIME, so their difference is the running mean of the offset
# (GPS noise 0.05 m/s: 0.02 m/s^2 of it). It does not feed the speed.
OFFSET_TIME = 3.0  # s
OFFSET_MAX_GAP = 0.5  # s between fixes taken beyond which the speed's running mean starts again
DOUBT_FIXES = 10.0  # fixes: the memory of the refusal share
DOUBT_SHARE = 0.5  # beyond this share of refusals the receiver is doubted (7 refusals in a row from none)

PARAMS = Layout(
    "P_",
    dt=1,
    gain=1,  # share of a GPS innovation applied to the speed
    bias_gain=1,  # ... to the accelerometer bias
    latency_samples=1,  # GPS latency in cycles
    gps_hold=1,  # s without a GPS speed taken before the GPS counts as lost (estimator.supervisor.gps_hold_time)
    g=1,  # m/s^2
)
P_DT, P_GAIN, P_BIAS_GAIN, P_LATENCY_SAMPLES, P_GPS_HOLD, P_G = PARAMS.offsets

OUTPUTS = Layout(
    "OUT_",
    u=1,  # m/s, forward speed (0 until the first fix)
    known=1,  # 1 once the filter has had its first fix
    gps_age=1,  # s since a GPS speed was last taken (refused and doubted fixes are not)
    gps_doubted=1,  # 1 while most recent fixes are refused: the receiver's speeds (and courses) are not believed
    gps_lost=1,  # 1 once gps_age exceeds gps_hold: the speed is dead reckoning
    # m/s^2: what the longitudinal accelerometer reads beyond the speed's rate, over the last OFFSET_TIME against
    # GPS: its bias and g sin(pitch) of an IMU pitched off the level (a slope, the suspension's sag, a mount)
    accel_offset=1,
    accel_offset_age=1,  # s its window has run since it (re)started (full, the last OFFSET_TIME's, from OFFSET_TIME)
)
OUT_U, OUT_KNOWN, OUT_GPS_AGE, OUT_GPS_DOUBTED, OUT_GPS_LOST, OUT_ACCEL_OFFSET, OUT_ACCEL_OFFSET_AGE = OUTPUTS.offsets


def new_speed_state(latency_samples: int) -> np.ndarray:
    return np.zeros(SPD_RING0 + max(1, latency_samples) + 1)


def build_params(settings, design) -> np.ndarray:
    sens = settings.sensors
    dt = float(design.sample_time)
    return PARAMS.vector(
        dt=dt,
        gain=sens.speed_filter_gain,
        bias_gain=sens.speed_bias_gain,
        latency_samples=round(sens.gps_latency / dt),
        gps_hold=settings.estimator.gps_hold_time,
        g=settings.vehicle.g,
    )


def _new_state(settings, design) -> np.ndarray:
    return new_speed_state(int(build_params(settings, design)[P_LATENCY_SAMPLES]))


@njit(cache=True)
def speed_step(
    state: np.ndarray,
    accel_x: float,
    gps_speed: float,
    gps_new: bool,
    gps_ok: bool,
    dt: float,
    gain: float,
    bias_gain: float,
    latency_samples: int,
    beyond_rate: float = 0.0,
) -> float:
    """One 10 ms step of the speed filter; returns the speed estimate [m/s] (never negative).

    `gps_new` marks a fix that arrived this cycle; `gps_ok` that it is usable (2D/3D fix).
    The fix describes the speed `latency_samples` cycles ago: the innovation is taken
    against the prediction stored then and applied to the present estimate. `beyond_rate`: what the
    accelerometer reads beyond the speed's rate (gravity's g sin of the IMU's pitch, a turn's part), taken out before
    the reading is integrated; the offset's running mean (OUTPUTS accel_offset) is of the reading as it is.
    """
    n_ring = state.shape[0] - SPD_RING0
    if state[SPD_INIT] == 0.0:
        if not (gps_new and gps_ok and math.isfinite(gps_speed)):
            return 0.0
        state[SPD_U] = gps_speed
        state[SPD_BIAS] = 0.0
        state[SPD_MEAN_SPEED] = gps_speed
        state[SPD_MEAN_ACCEL] = accel_x if math.isfinite(accel_x) else 0.0
        state[SPD_OFFSET] = state[SPD_MEAN_ACCEL]
        state[SPD_OFFSET_AGE] = 0.0
        for k in range(n_ring):
            state[SPD_RING0 + k] = gps_speed
        state[SPD_INIT] = 1.0
    a = accel_x if math.isfinite(accel_x) else 0.0
    u = state[SPD_U] + (a - beyond_rate - state[SPD_BIAS]) * dt
    state[SPD_MEAN_ACCEL] += dt / OFFSET_TIME * (a - state[SPD_MEAN_ACCEL])
    head = int(state[SPD_HEAD])
    state[SPD_SINCE] += dt
    interval = state[SPD_SINCE]  # s since the last fix taken, before this one
    if gps_new and gps_ok and math.isfinite(gps_speed):
        lag = min(latency_samples, n_ring - 1)
        past = state[SPD_RING0 + (head - lag) % n_ring]
        innovation = gps_speed - past
        share = gain
        gate = GATE_SPEED + GATE_DRIFT * min(state[SPD_SINCE], GATE_DRIFT_MAX_S)
        refused = abs(innovation) > gate
        state[SPD_REFUSED_SHARE] += ((1.0 if refused else 0.0) - state[SPD_REFUSED_SHARE]) / DOUBT_FIXES
        if refused:
            # refused fixes count towards re-taking the speed only while they agree with one another: a receiver
            # sending garbage never does (random 0-100 m/s at 10 Hz re-took the speed at 54.6 m/s for 27.8 true)
            if state[SPD_REFUSED] > 0.0 and abs(gps_speed - state[SPD_REFUSED_LAST]) > gate:
                state[SPD_REFUSED] = 0.0
            state[SPD_REFUSED] += 1.0
            state[SPD_REFUSED_LAST] = gps_speed
            share = 0.0  # refused: the prediction goes on
            if state[SPD_REFUSED] >= REACQUIRE_FIXES:  # re-taken from GPS whole, with the bias learned so far
                share = 1.0
                state[SPD_REFUSED_SHARE] = 0.0  # ten fixes that agree: a receiver that is right after all
        elif state[SPD_REFUSED_SHARE] > DOUBT_SHARE:
            share = 0.0  # inside the gate by chance: a doubted receiver's fixes are not taken
        if share != 0.0:
            state[SPD_REFUSED] = 0.0
            state[SPD_SINCE] = 0.0
        u += share * innovation
        if share == gain:  # an accelerometer bias shows up as a persistent innovation of one sign
            state[SPD_BIAS] -= bias_gain * innovation
            if interval <= OFFSET_MAX_GAP:
                rate = (gps_speed - state[SPD_MEAN_SPEED]) / OFFSET_TIME  # of the speed's running mean
                state[SPD_MEAN_SPEED] += interval / OFFSET_TIME * (gps_speed - state[SPD_MEAN_SPEED])
                state[SPD_OFFSET] = state[SPD_MEAN_ACCEL] - rate
            else:  # after an outage the mean is not the last OFFSET_TIME's: start it again, keep the offset
                state[SPD_MEAN_SPEED] = gps_speed
                state[SPD_OFFSET_AGE] = 0.0
        # shift the stored predictions too, so the next fix is compared like with like
        for k in range(n_ring):
            state[SPD_RING0 + k] += share * innovation
    if u < 0.0:
        u = 0.0
    state[SPD_OFFSET_AGE] += dt
    head = (head + 1) % n_ring
    state[SPD_RING0 + head] = u
    state[SPD_HEAD] = head
    state[SPD_U] = u
    return u


@njit(cache=True)
def speed_stage(
    st: np.ndarray, prm: np.ndarray, out: np.ndarray, inputs: np.ndarray, pitch: float = 0.0, turn_along: float = 0.0
) -> None:
    """One cycle from the inputs stage's outputs (accelerometer x, GPS speed and whether it is new), the IMU's
    pitch as the attitude stage last estimated it [rad] (0 while it has none): on a road whose grade changes, the
    accelerometer's g sin(pitch) changes faster than the speed's bias learns (a 5 deg swing every 400 m at 30 km/h:
    the speed 0.15 m/s off, which the tyres read as slip); and what a turn adds to that reading along x [m/s^2]
    (`attitude.turn_accel_along` at the attitude stage's last outputs, 0 while it has none): a slalom's leans make
    it swing faster than GPS corrects, and integrated as the speed's rate it read the speed 1 % low at every lean,
    which the tyre filters read as stiffer tyres (docs/estimator.md, "Speed"). Both are taken out of the reading
    before it is integrated; the offset's running mean (OUT_ACCEL_OFFSET) is of the reading as it is."""
    accel_x = inputs[inp.OUT_RAW + inp.RAW_AX] if inputs[inp.OUT_ACCEL_OK] != 0.0 else 0.0
    beyond_rate = prm[P_G] * math.sin(pitch) if math.isfinite(pitch) else 0.0
    if math.isfinite(turn_along):
        beyond_rate += turn_along
    gps_ok = inputs[inp.OUT_GPS_OK] != 0.0
    out[OUT_U] = speed_step(
        st,
        accel_x,
        inputs[inp.OUT_RAW + inp.RAW_GPS_SPEED],
        gps_ok,
        gps_ok,
        prm[P_DT],
        prm[P_GAIN],
        prm[P_BIAS_GAIN],
        int(prm[P_LATENCY_SAMPLES]),
        beyond_rate,
    )
    out[OUT_KNOWN] = 1.0 if st[SPD_INIT] != 0.0 else 0.0
    out[OUT_GPS_AGE] = st[SPD_SINCE]
    out[OUT_GPS_DOUBTED] = 1.0 if st[SPD_REFUSED_SHARE] > DOUBT_SHARE else 0.0
    out[OUT_GPS_LOST] = 1.0 if st[SPD_INIT] != 0.0 and st[SPD_SINCE] > prm[P_GPS_HOLD] else 0.0
    out[OUT_ACCEL_OFFSET] = st[SPD_OFFSET]
    out[OUT_ACCEL_OFFSET_AGE] = st[SPD_OFFSET_AGE]


STAGE = Stage(
    name="speed",
    state=STATE,
    params=PARAMS,
    outputs=OUTPUTS,
    build_params=build_params,
    new_state=_new_state,
    doc="GPS + longitudinal accelerometer, GPS latency compensated, held in dropouts",
)
