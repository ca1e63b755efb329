"""The twin's kernel: a batch of legs advanced tick by tick at the ODrive's 8 kHz.

Per tick and axis it does what firmware 0.5.x does: the board's checks, the encoder read
(quantized at the encoder's resolution, with noise) and its PLL (in turns of the
configured cpr), the controller (controller.cpp:143-450: the input modes, the setpoint
clamps, position P -> velocity PI with the velocity limit, the overspeed check and the
integrator's anti-windup; every tick in every state on 0.5.6, in closed loop on 0.5.1),
the current loop (the firmware's PI with its voltage limit on the motor's R, L and
back-EMF, half a period late) and its fault checks, then the DC bus with the brake
resistor, then the leg's mechanics (:mod:`leglib.twin.mechanics`). :func:`_run` shares the batch out in blocks over
the cores; a block the vectorized path allows goes to :mod:`leglib.twin.vector`, every
other one to :func:`_run_block`, the reference, and so does a batch of one (a device):
both paths give the same numbers, bit for bit.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .. import _numba_gc, _numba_inline  # noqa: F401  (before any kernel compiles)
from ..abort import (
    ABORT_NONE,
    ABORT_NONFINITE,
    ABORT_OSCILLATION,
    ABORT_POSITION_ERROR,
    _oscillation_step,
)
from ..cores import over_cores
from ..kernelmath import py_min
from .effects import _encoder_error
from .layout import (
    AXIS_ERROR_CONTROLLER_FAILED,
    AXIS_ERROR_DC_BUS_OVER_VOLTAGE,
    AXIS_ERROR_DC_BUS_UNDER_VOLTAGE,
    AXIS_ERROR_MOTOR_FAILED,
    AXIS_ERROR_WATCHDOG_TIMER_EXPIRED,
    C_ABORT_ERROR,
    C_BEMF_FF,
    C_BRAKE_ON,
    C_BRAKE_R,
    C_CAL_CURRENT,
    C_CAL_RAMP,
    C_CAL_VEL,
    C_CIRC_RANGE,
    C_CIRCULAR,
    C_CONTROL_MODE,
    C_COUNT_OFFSET,
    C_CPR,
    C_CURRENT_BW,
    C_CURRENT_LIM,
    C_CURRENT_LIM_MARGIN,
    C_DC_MAX_NEG,
    C_DC_MAX_POS,
    C_ELEC_BW,
    C_EN_GAIN_SCHED,
    C_EN_OVERSPEED,
    C_EN_TQ_VEL_LIMIT,
    C_EN_VEL_LIMIT,
    C_ENCODER_BW,
    C_FILTER_BW,
    C_FW_056,
    C_GAIN_SCHED_WIDTH,
    C_IBUS_MAX,
    C_IBUS_MIN,
    C_INERTIA,
    C_INPUT_MODE,
    C_INPUT_POS,
    C_INPUT_TORQUE,
    C_INPUT_VEL,
    C_KT,
    C_MAX_CURRENT,
    C_MAX_REGEN,
    C_MECH_BW,
    C_MIRROR_AXIS,
    C_MIRROR_RATIO,
    C_OV_TRIP,
    C_PHASE_L,
    C_PHASE_R,
    C_POS_GAIN,
    C_REGEN_ERR_STYLE,
    C_RWL_FF,
    C_SPIN_ELEC,
    C_SPIN_MECH,
    C_TORQUE_LIM,
    C_TORQUE_MIRROR_RATIO,
    C_TORQUE_RAMP_RATE,
    C_TT_AR,
    C_TT_DR,
    C_TT_TA,
    C_TT_TD,
    C_TT_TV,
    C_TT_VI,
    C_TT_VR,
    C_TT_XF,
    C_TT_XI,
    C_TT_YACC,
    C_TUNE_FREQ,
    C_TUNE_POS_AMP,
    C_TUNE_TQ_AMP,
    C_TUNE_VEL_AMP,
    C_UV_TRIP,
    C_VBUS,
    C_VBUS_CHECKS,
    C_VBUS_R,
    C_VEL_GAIN,
    C_VEL_INT_GAIN,
    C_VEL_INT_LIMIT,
    C_VEL_LIMIT,
    C_VEL_RAMP_RATE,
    C_VEL_TOL,
    C_WD_ENABLE,
    CONTROL_MODE_POSITION,
    CONTROL_MODE_VELOCITY,
    CONTROLLER_ERROR_INVALID_ESTIMATE,
    CONTROLLER_ERROR_INVALID_INPUT_MODE,
    CONTROLLER_ERROR_INVALID_MIRROR_AXIS,
    CONTROLLER_ERROR_OVERSPEED,
    CONTROLLER_ERROR_SPINOUT_DETECTED,
    F_BELT_K,
    F_ENC_ON,
    I_AXIS_ERR,
    I_CONNECTED,
    I_COUNTS,
    I_CTRL_ERR,
    I_MODE,
    I_MOTOR_ERR,
    I_SYS_ERR,
    I_TQ_PRESENT,
    I_TRAJ_DONE,
    INPUT_MODE_INACTIVE,
    INPUT_MODE_MIRROR,
    INPUT_MODE_PASSTHROUGH,
    INPUT_MODE_POS_FILTER,
    INPUT_MODE_TORQUE_RAMP,
    INPUT_MODE_TRAP_TRAJ,
    INPUT_MODE_TUNING,
    INPUT_MODE_VEL_RAMP,
    LANES,
    MODE_CALIB,
    MODE_IDLE,
    MODE_POSITION,
    MOTOR_ERROR_CURRENT_LIMIT_VIOLATION,
    MOTOR_ERROR_DC_BUS_OVER_CURRENT,
    MOTOR_ERROR_DC_BUS_OVER_REGEN_CURRENT,
    MOTOR_ERROR_I_BUS_OUT_OF_RANGE,
    MOTOR_ERROR_MODULATION_IS_NAN,
    MOTOR_ERROR_SYSTEM_LEVEL,
    MOTOR_ERROR_UNKNOWN_TORQUE,
    MOTOR_ERROR_UNKNOWN_VOLTAGE_COMMAND,
    N_FROWS,
    N_IROWS,
    ODRIVE_ERROR_DC_BUS_OVER_CURRENT,
    ODRIVE_ERROR_DC_BUS_OVER_REGEN_CURRENT,
    ODRIVE_ERROR_DC_BUS_OVER_VOLTAGE,
    ODRIVE_ERROR_DC_BUS_UNDER_VOLTAGE,
    R_DEAD,
    R_NF,
    R_Q,
    R_TAU,
    S_BRAKE_I,
    S_CAL_I,
    S_CAL_POS,
    S_COUNT_F,
    S_ELEC_P,
    S_FOC_POWER,
    S_IBUS,
    S_IBUS_MOTOR,
    S_INTEGRATOR,
    S_IQ,
    S_IQ_MEAS,
    S_IQ_SP,
    S_MECH_P,
    S_OSC,
    S_POS_CIRC,
    S_POS_EST,
    S_POS_SP,
    S_TQ_OUT,
    S_TQ_SP,
    S_TT_T,
    S_TUNE_PHASE,
    S_V_INT,
    S_V_PREV,
    S_VEL_EST,
    S_VEL_SP,
    S_WD_TIMER,
    V_MAX_PER_VBUS,
    X_PHI1,
)
from .mechanics import _at, _mechanics_leg_apart, _mechanics_plain, _param_row, _plain_block
from .rng import _normal
from .stages import (
    TWO_PI,
    brake_current,
    bus_fault,
    clamp,
    current_gains,
    current_setpoint,
    current_violation,
    encoder_counts,
    encoder_pll,
    fmodf_pos,
    foc_voltage,
    integrator_step,
    max_torque,
    motor_bus_current,
    motor_current,
    motor_plant,
    overspeed,
    spinout,
    torque_command,
    torque_limit,
    wrap_pm,
)
from .vector import _run_block_vector, _vector_block


@njit(cache=True, inline="always")
def _oscillation_update_at(AS, b, a, err, min_amp):
    """:func:`oscillation_update` on the monitor of axis ``a`` of leg ``b`` in place
    (AS[b, a, S_OSC:S_OSC + N_OSC], without a slice per tick)."""
    o = S_OSC
    (AS[b, a, o], AS[b, a, o + 1], AS[b, a, o + 2], AS[b, a, o + 3], AS[b, a, o + 4], AS[b, a, o + 5],
     unstable) = _oscillation_step(AS[b, a, o], AS[b, a, o + 1], AS[b, a, o + 2], AS[b, a, o + 3],
                                   AS[b, a, o + 4], AS[b, a, o + 5], err, min_amp)
    return unstable


# The batch goes to the two paths from Python, and each path is its own compiled function:
# numba compiles a function with everything it can reach, so one entry point that chose
# between the paths inside (as this kernel once did) compiled both for every use. A device
# (a batch of one) takes the reference path only, and no longer compiles the vectorized one
# (about half of a cold start's compile); a sweep compiles the reference path only when one
# of its blocks needs it.

def _run(n_ticks, dt, X, AS, AI, C, P, FR, MECH, DRV, RNG, ABORT, TT, tt_period, REC, rec_every,
         rec_offset, block):
    """Advance every leg of the batch by ``n_ticks`` ticks of ``dt`` seconds.

    X[b] = (q1, dq1, q2, dq2, t, phi1, dphi1, phi2, dphi2, z1, z2, travel1, travel2) (the
    X_ indices: rotor angles on the joint side with a compliant belt, LuGre bristles,
    accumulated joint travel); AS, AI, C per axis (see the S_, I_, C_ indices);
    P[b] the true leg's parameter vector; FR[b] = (visc1, visc2, coul1, coul2, strib1,
    strib2, v_stribeck, v_smooth, gap_min, k_stop, c_stop, J1, J2, gap_max, then the
    unmodeled effects' parameters, the F_ indices, each off at zero); MECH[b] 0 five-bar,
    1 independent inertias; DRV = (gear_ratio, cpr, direction, q_rest1, q_rest2,
    joint_of_axis0, encoder_noise, current_noise, true torque constant, quantize, true pole
    pairs, phase resistance [ohm], phase inductance [H]); TT[b, i, axis] a torque table applied
    to axes in torque mode, row i = tick // tt_period (ignored when it has no rows);
    REC[b, k] = (t, counts0, counts1, Iq0, Iq1) every ``rec_every`` ticks from row
    ``rec_offset``. The legs go in blocks of ``block``, a thread's unit of work, over the
    cores (:func:`leglib.cores.over_cores`, a block to each thread that is free): a block
    that :func:`_vector_block` allows goes vectorized, every other one through
    :func:`_run_block`, the reference (:func:`_one_block`). A block changes only its own
    legs' rows, so the blocks may run in any order and at once.
    Returns nothing; everything is updated in place.
    """
    B = X.shape[0]
    block = min(block, LANES)
    vec = _vector_blocks(B, block, FR, C, AI).tolist()

    def blocks(k0, k1):
        for k in range(k0, k1):
            _one_block(k * block, min(B, (k + 1) * block), vec[k], n_ticks, dt, X, AS, AI, C, P, FR, MECH, DRV,
                       RNG, ABORT, TT, tt_period, REC, rec_every, rec_offset)

    over_cores(blocks, len(vec))


def _run_serial(n_ticks, dt, X, AS, AI, C, P, FR, MECH, DRV, RNG, ABORT, TT, tt_period, REC, rec_every,
                rec_offset, block):
    """:func:`_run` without the thread pool: cheaper per call for a batch of one (a host loop
    advancing the virtual device a few ticks per USB transaction). Same numbers. A batch of
    one always goes through the reference (:func:`_run_block`): the vectorized path pays
    only over a block of legs, and gives the reference's numbers bit for bit; so a device
    never compiles it."""
    B = X.shape[0]
    block = min(block, LANES)
    for b0 in range(0, B, block):
        b1 = min(B, b0 + block)
        _one_block(b0, b1, B > 1 and _vector_block(b0, b1, FR, C, AI), n_ticks, dt, X, AS, AI, C, P, FR, MECH,
                   DRV, RNG, ABORT, TT, tt_period, REC, rec_every, rec_offset)


def _one_block(b0, b1, vectorized, n_ticks, dt, X, AS, AI, C, P, FR, MECH, DRV, RNG, ABORT, TT, tt_period, REC,
               rec_every, rec_offset):
    """Legs b0..b1-1 vectorized (:func:`leglib.twin.vector._run_block_vector`) or through
    the reference (:func:`_run_block_reference`). Each compiled call releases the GIL
    (``nogil``): the blocks of :func:`_run` run on the cores at once."""
    if vectorized:
        _run_block_vector(b0, b1, n_ticks, dt, X, AS, AI, C, P, FR, MECH, DRV, RNG, ABORT, REC, rec_every,
                          rec_offset, _plain_block(b0, b1, P, FR, MECH))
    else:
        _run_block_reference(b0, b1, n_ticks, dt, X, AS, AI, C, P, FR, MECH, DRV, RNG, ABORT, TT, tt_period,
                             REC, rec_every, rec_offset)


@njit(cache=True)
def _vector_blocks(B, block, FR, C, AI):
    """Per block of ``block`` legs of a batch of ``B``: whether :func:`_vector_block` allows it."""
    out = np.zeros((B + block - 1) // block, np.bool_)
    for blk in range(out.size):
        out[blk] = _vector_block(blk * block, min(B, (blk + 1) * block), FR, C, AI)
    return out


@njit(cache=True, nogil=True)
def _run_block_reference(b0, b1, n_ticks, dt, X, AS, AI, C, P, FR, MECH, DRV, RNG, ABORT, TT, tt_period, REC,
                         rec_every, rec_offset):
    """Legs b0..b1-1 through :func:`_run_block`: all at once when they share a plain plant
    (its mechanics then vectorize), else one leg at a time (its state stays in the cache
    over the ticks)."""
    # ``plain`` goes to _run_block as a variable, never as the constant True or False: numba
    # would compile _run_block once for each literal (about 25 s more on a first run)
    plain = _plain_block(b0, b1, P, FR, MECH)
    if plain:
        _run_block(b0, b1, n_ticks, dt, X, AS, AI, C, P, FR, MECH, DRV, RNG, ABORT, TT, tt_period, REC,
                   rec_every, rec_offset, plain)
    else:
        for b in range(b0, b1):
            _run_block(b, b + 1, n_ticks, dt, X, AS, AI, C, P, FR, MECH, DRV, RNG, ABORT, TT, tt_period,
                       REC, rec_every, rec_offset, plain)


# ---------------------------------------------------------------------------------------
# the reference tick's stages, per axis and per leg, in the firmware's order; the shared
# arithmetic is in leglib.twin.stages (the vectorized path calls the same)
# ---------------------------------------------------------------------------------------

@njit(cache=True, inline="always")
def _board_checks(b, C, AS, AI):
    """main.cpp:413-420, axis.cpp:165-182: the axis checks and the watchdog, in every state.
    An enabled watchdog counts down every tick, IDLE included, and at 0 sets its error
    (kept while it is not fed); any axis error disarms the motor.

    main.cpp:300-305 (called every current measurement, armed or not): the bus voltage --
    the supply's voltage less its source resistance times the last tick's bus current --
    outside the trip levels disarms both motors and the brake resistor with the board's
    error (0.5.2+), or sets the axes' errors (fw-v0.5.1 axis.cpp:173-176)."""
    if C[b, 0, C_VBUS_CHECKS] > 0.0:
        vbus = C[b, 0, C_VBUS] - C[b, 0, C_VBUS_R] * AS[b, 0, S_IBUS]
        under = not (vbus >= C[b, 0, C_UV_TRIP])
        over = not (vbus <= C[b, 0, C_OV_TRIP])
        if under or over:
            if C[b, 0, C_REGEN_ERR_STYLE] > 0.0:     # 0.5.1
                for a in range(2):
                    AI[b, a, I_AXIS_ERR] |= ((AXIS_ERROR_DC_BUS_UNDER_VOLTAGE if under else 0)
                                             | (AXIS_ERROR_DC_BUS_OVER_VOLTAGE if over else 0))
            else:                                     # main.cpp:313-321 disarm_with_error
                for a in range(2):
                    AI[b, a, I_MOTOR_ERR] |= MOTOR_ERROR_SYSTEM_LEVEL
                    AI[b, a, I_AXIS_ERR] |= AXIS_ERROR_MOTOR_FAILED
                C[b, 0, C_BRAKE_ON] = 0.0
                AI[b, 0, I_SYS_ERR] |= ((ODRIVE_ERROR_DC_BUS_UNDER_VOLTAGE if under else 0)
                                        | (ODRIVE_ERROR_DC_BUS_OVER_VOLTAGE if over else 0))
    for a in range(2):
        if C[b, a, C_WD_ENABLE] > 0.0:
            if AS[b, a, S_WD_TIMER] > 0.0:
                AS[b, a, S_WD_TIMER] -= 1.0
            else:
                AI[b, a, I_AXIS_ERR] |= AXIS_ERROR_WATCHDOG_TIMER_EXPIRED
        if AI[b, a, I_AXIS_ERR] != 0:
            AI[b, a, I_MODE] = MODE_IDLE


@njit(cache=True, inline="always")
def _encoder_tick(b, a, q, rng, dt, C, AS, AI, FR, DRV, turns_per_rad, inv_cpr):
    """encoder.cpp:651-809: the reading of joint angle ``q`` (noise, the plant's reading
    error, quantization at the encoder's own resolution) and the PLL, whose counts are
    turned into turns by the *configured* cpr (``inv_cpr`` = 1 / encoder.config.cpr,
    encoder.cpp:800-801); (rng, the rotor's turns from rest, pos_estimate, vel_estimate)."""
    j = _joint_of(a, DRV)
    cpr = DRV[1]
    turns = DRV[2] * (q - DRV[3 + j]) * turns_per_rad
    rng, nz = _normal(rng)
    raw = turns * cpr + DRV[6] * nz
    if FR[b, F_ENC_ON] > 0.0:       # the encoder's reading error (plant [encoder_error])
        raw += cpr * _encoder_error(FR, b, turns)
    counts, counts_i = encoder_counts(raw, C[b, a, C_COUNT_OFFSET], DRV[9] > 0.0)
    AI[b, a, I_COUNTS] = counts_i
    AS[b, a, S_COUNT_F] = counts
    kp = 2.0 * C[b, a, C_ENCODER_BW]
    pe, ve = encoder_pll(AS[b, a, S_POS_EST], AS[b, a, S_VEL_EST], counts, dt, kp, 0.25 * kp * kp, inv_cpr)
    AS[b, a, S_POS_EST] = pe
    AS[b, a, S_VEL_EST] = ve
    return rng, turns, pe, ve


@njit(cache=True, inline="always")
def _joint_of(a, DRV):
    """The joint axis ``a`` drives (DRV[5]: the joint of axis 0)."""
    j0 = int(DRV[5])
    return j0 if a == 0 else 1 - j0


@njit(cache=True)   # a rare tick's work: compiled apart (see _run_block_ticks)
def _calibration_tick(b, a, i, turns, rng, dt, C, AS, FB, DRV, inv_vbus):
    """encoder.cpp:328-461, motor.cpp:416-463: an open-loop lock or scan at
    calibration_current (the axis state machine of leglib.device.virtual.firmware moves
    the electrical angle): the rotor follows it through a torque ~ sin(pole_pairs * error),
    the current ramping to calibration_current at C_CAL_RAMP [A/s]. (rng, bus current)."""
    AS[b, a, S_CAL_POS] += C[b, a, C_CAL_VEL] * dt
    i_tgt = C[b, a, C_CAL_CURRENT]
    step_i = C[b, a, C_CAL_RAMP] * dt
    i_now = AS[b, a, S_CAL_I]
    i_now = min(i_now + step_i, i_tgt) if i_now < i_tgt else max(i_now - step_i, i_tgt)
    AS[b, a, S_CAL_I] = i_now
    iq = i_now * math.sin(TWO_PI * DRV[10] * (AS[b, a, S_CAL_POS] - turns))
    AS[b, a, S_IQ] = iq
    rng, nz = _normal(rng)
    AS[b, a, S_IQ_MEAS] = iq + DRV[7] * nz
    FB[_at(R_TAU + _joint_of(a, DRV), i)] = DRV[2] * DRV[0] * DRV[8] * iq
    w = AS[b, a, S_VEL_EST] * TWO_PI
    ib = (1.5 * DRV[11] * i_now ** 2 + DRV[8] * iq * w) * inv_vbus
    AS[b, a, S_IBUS_MOTOR] = ib
    return rng, ib


@njit(cache=True, inline="always")
def _disarmed(b, a, i, AS, AI, FB, DRV, iq_sp_idle, fw056):
    """An IDLE axis: no current, no torque on its joint. The controller's state is the
    controller's: on 0.5.6 it runs on while IDLE, on 0.5.1 it keeps its last values; both
    reset it when the axis is armed again (motor.cpp:202, axis.cpp:290-294). On 0.5.6 the
    motor's update still turns the controller's torque into Iq's setpoint (``iq_sp_idle``:
    0 when there is none, motor.cpp:513-552; fw-v0.5.1 keeps the last armed one). Iq_measured
    keeps its last value: the current controller, detached at disarm (motor.cpp:279), no
    longer updates it."""
    AI[b, a, I_MODE] = MODE_IDLE
    AS[b, a, S_IQ] = 0.0
    AS[b, a, S_V_PREV] = 0.0
    if fw056:
        AS[b, a, S_IQ_SP] = iq_sp_idle
    AS[b, a, S_IBUS_MOTOR] = 0.0
    FB[_at(R_TAU + _joint_of(a, DRV), i)] = 0.0


@njit(cache=True)   # a rare tick's work: compiled apart (see _run_block_ticks)
def _trap_traj(b, a, dt, C, AS, AI, fw056):
    """controller.cpp:245-269 (the planned trajectory of trapTraj.cpp evaluated at its time;
    its end drops the configured mode into position control and holds the goal: Xf on 0.5.6,
    input_pos on 0.5.1, fw-v0.5.1 controller.cpp:197-203)."""
    if AI[b, a, I_TRAJ_DONE] != 0:
        return
    tt = AS[b, a, S_TT_T]
    ta, tv, td = C[b, a, C_TT_TA], C[b, a, C_TT_TV], C[b, a, C_TT_TD]
    if tt > ta + tv + td:
        C[b, a, C_CONTROL_MODE] = CONTROL_MODE_POSITION
        if AI[b, a, I_MODE] != MODE_IDLE and AI[b, a, I_MODE] != MODE_CALIB:
            AI[b, a, I_MODE] = MODE_POSITION
        AS[b, a, S_POS_SP] = C[b, a, C_TT_XF] if fw056 else C[b, a, C_INPUT_POS]
        AS[b, a, S_VEL_SP] = 0.0
        AS[b, a, S_TQ_SP] = 0.0
        AI[b, a, I_TRAJ_DONE] = 1
        return
    if tt < 0.0:
        y, yd, ydd = C[b, a, C_TT_XI], C[b, a, C_TT_VI], 0.0
    elif tt < ta:
        y = C[b, a, C_TT_XI] + C[b, a, C_TT_VI] * tt + 0.5 * C[b, a, C_TT_AR] * tt * tt
        yd = C[b, a, C_TT_VI] + C[b, a, C_TT_AR] * tt
        ydd = C[b, a, C_TT_AR]
    elif tt < ta + tv:
        y = C[b, a, C_TT_YACC] + C[b, a, C_TT_VR] * (tt - ta)
        yd = C[b, a, C_TT_VR]
        ydd = 0.0
    else:
        tdd = tt - (ta + tv + td)
        y = C[b, a, C_TT_XF] + 0.5 * C[b, a, C_TT_DR] * tdd * tdd
        yd = C[b, a, C_TT_DR] * tdd
        ydd = C[b, a, C_TT_DR]
    AS[b, a, S_POS_SP] = y
    AS[b, a, S_VEL_SP] = yd
    AS[b, a, S_TQ_SP] = ydd * C[b, a, C_INERTIA]
    AS[b, a, S_TT_T] = tt + dt


@njit(cache=True, inline="always")
def _input_setpoints(b, a, dt, C, AS, AI, wrap, fw056):
    """controller.cpp:183-283: the setpoints from the inputs by input_mode. Returns the
    controller error of an input mode that cannot run (0: none)."""
    imode = int(C[b, a, C_INPUT_MODE])
    if imode == INPUT_MODE_INACTIVE:
        return 0
    if imode == INPUT_MODE_PASSTHROUGH:
        AS[b, a, S_POS_SP] = C[b, a, C_INPUT_POS]
        AS[b, a, S_VEL_SP] = C[b, a, C_INPUT_VEL]
        AS[b, a, S_TQ_SP] = C[b, a, C_INPUT_TORQUE]
    elif imode == INPUT_MODE_VEL_RAMP:           # controller.cpp:192-199
        max_step = abs(dt * C[b, a, C_VEL_RAMP_RATE])
        step = clamp(C[b, a, C_INPUT_VEL] - AS[b, a, S_VEL_SP], -max_step, max_step)
        AS[b, a, S_VEL_SP] += step
        AS[b, a, S_TQ_SP] = (step / dt) * C[b, a, C_INERTIA]
    elif imode == INPUT_MODE_TORQUE_RAMP:        # controller.cpp:200-206
        max_step = abs(dt * C[b, a, C_TORQUE_RAMP_RATE])
        AS[b, a, S_TQ_SP] += clamp(C[b, a, C_INPUT_TORQUE] - AS[b, a, S_TQ_SP], -max_step, max_step)
    elif imode == INPUT_MODE_POS_FILTER:         # controller.cpp:207-222
        fki = 2.0 * min(C[b, a, C_FILTER_BW], 0.25 / dt)
        fkp = 0.25 * fki * fki
        delta_pos = C[b, a, C_INPUT_POS] - AS[b, a, S_POS_SP]
        if fw056 and C[b, a, C_CIRCULAR] > 0.0:
            delta_pos = wrap_pm(delta_pos, wrap)
        acc = fkp * delta_pos + fki * (C[b, a, C_INPUT_VEL] - AS[b, a, S_VEL_SP])
        AS[b, a, S_TQ_SP] = acc * C[b, a, C_INERTIA]
        AS[b, a, S_VEL_SP] += dt * acc
        AS[b, a, S_POS_SP] += dt * AS[b, a, S_VEL_SP]
    elif imode == INPUT_MODE_MIRROR:             # controller.cpp:223-241; fw-v0.5.1 :176-184
        m = int(C[b, a, C_MIRROR_AXIS])
        if m < 0 or m > 1:
            return CONTROLLER_ERROR_INVALID_MIRROR_AXIS
        ratio = C[b, a, C_MIRROR_RATIO]
        if fw056:
            # the other controller's torque output of this tick must be there: axis 1 can
            # mirror axis 0, whose controller ran first; anything else reads an output not
            # produced yet (torque_output_ is reset each tick, main.cpp:381)
            if m >= a or AI[b, m, I_TQ_PRESENT] == 0:
                return CONTROLLER_ERROR_INVALID_ESTIMATE
            AS[b, a, S_TQ_SP] = AS[b, m, S_TQ_OUT] * C[b, a, C_TORQUE_MIRROR_RATIO]
        AS[b, a, S_POS_SP] = AS[b, m, S_POS_EST] * ratio
        AS[b, a, S_VEL_SP] = AS[b, m, S_VEL_EST] * ratio
    elif imode == INPUT_MODE_TRAP_TRAJ:
        _trap_traj(b, a, dt, C, AS, AI, fw056)
    elif imode == INPUT_MODE_TUNING and fw056:   # controller.cpp:270-277
        ph = wrap_pm(AS[b, a, S_TUNE_PHASE] + TWO_PI * C[b, a, C_TUNE_FREQ] * dt, TWO_PI)
        AS[b, a, S_TUNE_PHASE] = ph
        c, s = math.cos(ph), math.sin(ph)
        AS[b, a, S_POS_SP] = C[b, a, C_INPUT_POS] + C[b, a, C_TUNE_POS_AMP] * s
        AS[b, a, S_VEL_SP] = C[b, a, C_INPUT_VEL] + C[b, a, C_TUNE_VEL_AMP] * c
        AS[b, a, S_TQ_SP] = C[b, a, C_INPUT_TORQUE] - C[b, a, C_TUNE_TQ_AMP] * s
    else:                                        # controller.cpp:278-281 (MIX_CHANNELS too)
        return CONTROLLER_ERROR_INVALID_INPUT_MODE
    return 0


@njit(cache=True, inline="always")
def _controller_update(k, b, a, dt, C, AS, AI, TT, tt_period, fw056):
    """controller.cpp:143-450 (fw-v0.5.1 controller.cpp:117-346): one update of the
    controller. Its estimates are the encoder's once connected (the first closed loop of a
    boot), else 0 (unconnected inputs). Returns (controller error, 0 if none; the torque
    [N*m])."""
    connected = AI[b, a, I_CONNECTED] != 0
    pe = AS[b, a, S_POS_EST] if connected else 0.0
    ve = AS[b, a, S_VEL_EST] if connected else 0.0
    circular = C[b, a, C_CIRCULAR] > 0.0
    wrap = C[b, a, C_CIRC_RANGE] if connected or not fw056 else 0.0
    if circular:                                   # controller.cpp:173-180
        C[b, a, C_INPUT_POS] = fmodf_pos(C[b, a, C_INPUT_POS], wrap)
    err = _input_setpoints(b, a, dt, C, AS, AI, wrap, fw056)
    if err != 0:
        return err, 0.0
    cmode = int(C[b, a, C_CONTROL_MODE])
    armed = AI[b, a, I_MODE] != MODE_IDLE and AI[b, a, I_MODE] != MODE_CALIB
    if armed and cmode < CONTROL_MODE_VELOCITY and TT.shape[1] > 0:
        # leglib's torque table (Twin.run) stands in for input_torque
        AS[b, a, S_TQ_SP] = TT[b, min(k // tt_period, TT.shape[1] - 1), a]
    vel_limit = C[b, a, C_VEL_LIMIT]
    en_vel_limit = C[b, a, C_EN_VEL_LIMIT] > 0.0
    t_lim = max_torque(C[b, a, C_CURRENT_LIM], C[b, a, C_MAX_CURRENT], C[b, a, C_KT], C[b, a, C_TORQUE_LIM])
    if fw056:                                      # controller.cpp:285-290 (not in 0.5.1)
        if en_vel_limit:
            AS[b, a, S_VEL_SP] = clamp(AS[b, a, S_VEL_SP], -vel_limit, vel_limit)
        AS[b, a, S_TQ_SP] = clamp(AS[b, a, S_TQ_SP], -t_lim, t_lim)
    # position control (controller.cpp:292-323)
    gs = 1.0
    vel_des = AS[b, a, S_VEL_SP]
    if cmode >= CONTROL_MODE_POSITION:
        if circular:
            pos_sp = fmodf_pos(AS[b, a, S_POS_SP], wrap)
            AS[b, a, S_POS_SP] = pos_sp
            pcirc = fmodf_pos(pe + AS[b, a, S_POS_CIRC], wrap) if connected or not fw056 else 0.0
            pos_err = wrap_pm(pos_sp - pcirc, wrap)
        else:
            pos_err = AS[b, a, S_POS_SP] - pe
        vel_des += C[b, a, C_POS_GAIN] * pos_err
        width = C[b, a, C_GAIN_SCHED_WIDTH]
        if C[b, a, C_EN_GAIN_SCHED] > 0.0 and abs(pos_err) <= width:
            # width 0 reaches here only with pos_err 0: 0 / 0, NaN on the board (a float
            # division; numba's would raise)
            gs = abs(pos_err) / width if width != 0.0 else math.nan
    if en_vel_limit:                               # controller.cpp:325-329
        vel_des = clamp(vel_des, -vel_limit, vel_limit)
    if overspeed(C[b, a, C_EN_OVERSPEED] > 0.0, ve, vel_limit, C[b, a, C_VEL_TOL]):
        return CONTROLLER_ERROR_OVERSPEED, 0.0    # controller.cpp:331-341
    vel_gain = C[b, a, C_VEL_GAIN]
    torque = AS[b, a, S_TQ_SP]
    v_err = 0.0
    if cmode >= CONTROL_MODE_VELOCITY:             # controller.cpp:373-385
        v_err = vel_des - ve
        torque = torque_command(vel_gain * gs, v_err, AS[b, a, S_INTEGRATOR], torque)
    elif C[b, a, C_EN_TQ_VEL_LIMIT] > 0.0:         # controller.cpp:387-394
        torque = clamp(torque, (-vel_limit - ve) * vel_gain, (vel_limit - ve) * vel_gain)
    torque, limited = torque_limit(torque, t_lim)  # controller.cpp:396-405
    if cmode < CONTROL_MODE_VELOCITY:              # controller.cpp:407-420
        AS[b, a, S_INTEGRATOR] = 0.0
    else:
        AS[b, a, S_INTEGRATOR] = integrator_step(AS[b, a, S_INTEGRATOR], limited, C[b, a, C_VEL_INT_GAIN] * gs,
                                                 dt, v_err, C[b, a, C_VEL_INT_LIMIT])
    if fw056:                                      # controller.cpp:422-441 (0.5.2+)
        mech, elec, spun = spinout(AS[b, a, S_MECH_P], AS[b, a, S_ELEC_P], torque, ve, AS[b, a, S_FOC_POWER],
                                   AS[b, a, S_IQ_MEAS], C[b, a, C_PHASE_R], C[b, a, C_MECH_BW], C[b, a, C_ELEC_BW],
                                   dt, C[b, a, C_SPIN_MECH], C[b, a, C_SPIN_ELEC])
        AS[b, a, S_MECH_P] = mech
        AS[b, a, S_ELEC_P] = elec
        if spun:
            return CONTROLLER_ERROR_SPINOUT_DETECTED, 0.0
    return 0, torque


@njit(cache=True)   # a rare tick's work: compiled apart (see _run_block_ticks)
def _step_abort(b, a, mode, pe, C, AS):
    """leglib's abort rule (:mod:`leglib.abort`) on an axis in position control during a
    step (C_ABORT_ERROR > 0): the position error past the bound, or an oscillation that does
    not decay. Returns the abort code (ABORT_NONE: go on)."""
    if mode != MODE_POSITION or not C[b, a, C_ABORT_ERROR] > 0.0:
        return ABORT_NONE
    err = AS[b, a, S_POS_SP] - pe
    if abs(err) > C[b, a, C_ABORT_ERROR]:
        return ABORT_POSITION_ERROR
    if _oscillation_update_at(AS, b, a, err, 0.025 * C[b, a, C_ABORT_ERROR]):
        return ABORT_OSCILLATION
    return ABORT_NONE


@njit(cache=True)   # a rare tick's work: compiled apart (see _run_block_ticks)
def _motor_failed(b, a, i, motor_error, AS, AI, FB, DRV):
    """A fault in the motor's update (the current trip, motor.cpp:631-644; a NaN modulation,
    foc.cpp:31-32): its error and the axis's MOTOR_FAILED set, the axis disarmed at once --
    no current, no torque on its joint, no bus current."""
    AI[b, a, I_MOTOR_ERR] |= motor_error
    AI[b, a, I_AXIS_ERR] |= AXIS_ERROR_MOTOR_FAILED
    AI[b, a, I_MODE] = MODE_IDLE
    AS[b, a, S_IQ] = 0.0
    AS[b, a, S_V_PREV] = 0.0
    FB[_at(R_TAU + _joint_of(a, DRV), i)] = 0.0
    AS[b, a, S_IBUS_MOTOR] = 0.0


@njit(cache=True, inline="always")
def _motor_tick(b, a, i, torque, ve, w_joint, rng, C, AS, AI, FB, DRV, inv_kt, inv_vbus, cc_kp, cc_ki_dt, vmax,
                a_half, inv_r, m_half):
    """motor.cpp:513-594 and foc.cpp:120-160 with the motor: the torque's current setpoint,
    the current sampled (with noise) and checked against the trip (motor.cpp:631-644), the
    current PI's voltage, and the phase current it drives through the motor's R and L
    against its back-EMF (the rotor's true speed ``w_joint`` [rad/s of the joint]); the
    torque on the joint from the period's mean current (the motor's true torque constant)
    and the motor's bus current. (rng, bus current)."""
    ilim = py_min(C[b, a, C_CURRENT_LIM], C[b, a, C_MAX_CURRENT])
    iq_sp = current_setpoint(torque, inv_kt, ilim)
    AS[b, a, S_IQ_SP] = iq_sp
    i0 = AS[b, a, S_IQ]
    rng, nz = _normal(rng)
    iq_meas = i0 + DRV[7] * nz
    AS[b, a, S_IQ_MEAS] = iq_meas
    if current_violation(iq_meas, C[b, a, C_CURRENT_LIM], C[b, a, C_MAX_CURRENT], C[b, a, C_CURRENT_LIM_MARGIN]):
        _motor_failed(b, a, i, MOTOR_ERROR_CURRENT_LIMIT_VIOLATION, AS, AI, FB, DRV)
        return rng, 0.0
    # feed-forwards (motor.cpp:567-586): the back-EMF from the estimated speed, R * Iq
    v_ff = 0.0
    if C[b, a, C_BEMF_FF] > 0.0:
        v_ff += (2.0 / 3.0) * C[b, a, C_KT] * (TWO_PI * ve)
    if C[b, a, C_RWL_FF] > 0.0:
        v_ff += C[b, a, C_PHASE_R] * iq_sp
    v, integ = foc_voltage(iq_sp, iq_meas, AS[b, a, S_V_INT], cc_kp, cc_ki_dt, v_ff, vmax)
    AS[b, a, S_V_INT] = integ
    AS[b, a, S_FOC_POWER] = 1.5 * v * iq_meas     # foc.cpp:175-179: vbus x (mod . Idq)
    if not v == v:        # foc.cpp:31-32 (gains from an uncalibrated R and L): disarmed
        _motor_failed(b, a, i, MOTOR_ERROR_MODULATION_IS_NAN, AS, AI, FB, DRV)
        return rng, 0.0
    # the motor's back-EMF: its flux linkage (2/3) kt / pole_pairs times the electrical speed
    e_bemf = (2.0 / 3.0) * DRV[8] * (DRV[2] * DRV[0] * w_joint)
    i_next, i_mean = motor_current(i0, AS[b, a, S_V_PREV], v, e_bemf, a_half, inv_r, m_half)
    AS[b, a, S_V_PREV] = v
    AS[b, a, S_IQ] = i_next
    # the motor's own torque constant makes the torque; the configured one only converts
    # the torque command to a current
    FB[_at(R_TAU + _joint_of(a, DRV), i)] = DRV[2] * DRV[0] * DRV[8] * i_mean
    ib = motor_bus_current(DRV[11], i_mean, DRV[8], ve, inv_vbus)
    AS[b, a, S_IBUS_MOTOR] = ib
    return rng, ib


@njit(cache=True)   # a rare tick's work: compiled apart (see _run_block_ticks)
def _controller_failed(b, a, err, mode, fw056, C, AI):
    """What a failed controller update leaves (0.5.6: main.cpp:443-445 the axis error,
    motor.cpp:515-518 the motor without a torque once connected to the controller, and for
    an armed closed loop foc.cpp:82-83 with motor.cpp:707-714: disarmed without a voltage
    command; 0.5.1: the closed loop ends, fw-v0.5.1 axis.cpp:347-348). Returns the mode."""
    AI[b, a, I_CTRL_ERR] |= err
    AI[b, a, I_AXIS_ERR] |= AXIS_ERROR_CONTROLLER_FAILED
    if fw056 and AI[b, a, I_CONNECTED] != 0:
        AI[b, a, I_MOTOR_ERR] |= MOTOR_ERROR_UNKNOWN_TORQUE
        if mode != MODE_IDLE and mode != MODE_CALIB:
            AI[b, a, I_MOTOR_ERR] |= MOTOR_ERROR_UNKNOWN_VOLTAGE_COMMAND
            AI[b, a, I_AXIS_ERR] |= AXIS_ERROR_MOTOR_FAILED
    if mode == MODE_CALIB:
        return mode        # the calibration drives the motor; the axis error ends it next tick
    return MODE_IDLE


@njit(cache=True, inline="always")
def _axis_tick(k, b, a, i, q, w_joint, rng, dt, C, AS, AI, FR, FB, DRV, TT, tt_period, turns_per_rad, inv_cpr,
               inv_kt, inv_vbus, cc_kp, cc_ki_dt, vmax, a_half, inv_r, m_half):
    """One control tick of axis ``a`` of leg ``b`` (main.cpp:429-461): the encoder, the
    controller (every tick in every state on 0.5.6; in closed loop on 0.5.1), then the
    motor: armed by the controller, by a calibration, or IDLE. (rng, bus current, abort
    code)."""
    rng, turns, pe, ve = _encoder_tick(b, a, q, rng, dt, C, AS, AI, FR, DRV, turns_per_rad, inv_cpr)
    mode = AI[b, a, I_MODE]
    fw056 = C[b, 0, C_FW_056] > 0.0
    AI[b, a, I_TQ_PRESENT] = 0
    torque = 0.0
    iq_sp_idle = 0.0
    if fw056 or (mode != MODE_IDLE and mode != MODE_CALIB):
        err, torque = _controller_update(k, b, a, dt, C, AS, AI, TT, tt_period, fw056)
        if err != 0:
            mode = _controller_failed(b, a, err, mode, fw056, C, AI)
        else:
            AS[b, a, S_TQ_OUT] = torque
            AI[b, a, I_TQ_PRESENT] = 1
            mode = AI[b, a, I_MODE]      # a trajectory's end may have switched it
            if AI[b, a, I_CONNECTED] != 0:
                iq_sp_idle = current_setpoint(torque, inv_kt, py_min(C[b, a, C_CURRENT_LIM], C[b, a, C_MAX_CURRENT]))
    code = ABORT_NONE
    ib = 0.0
    if mode == MODE_CALIB:
        rng, ib = _calibration_tick(b, a, i, turns, rng, dt, C, AS, FB, DRV, inv_vbus)
    elif mode == MODE_IDLE:
        _disarmed(b, a, i, AS, AI, FB, DRV, iq_sp_idle, fw056)
    else:
        code = _step_abort(b, a, mode, pe, C, AS)
        rng, ib = _motor_tick(b, a, i, torque, ve, w_joint, rng, C, AS, AI, FB, DRV, inv_kt, inv_vbus, cc_kp,
                              cc_ki_dt, vmax, a_half, inv_r, m_half)
    # motor.cpp:726-730 (0.5.2+): the motor's bus current outside its hard limits, in every state
    if not (C[b, a, C_IBUS_MIN] <= ib <= C[b, a, C_IBUS_MAX]):
        AI[b, a, I_MOTOR_ERR] |= MOTOR_ERROR_I_BUS_OUT_OF_RANGE
        AI[b, a, I_AXIS_ERR] |= AXIS_ERROR_MOTOR_FAILED
        if AI[b, a, I_MODE] != MODE_IDLE:
            _disarmed(b, a, i, AS, AI, FB, DRV, AS[b, a, S_IQ_SP], False)
            ib = 0.0
    return rng, ib, code


@njit(cache=True, inline="always")
def _bus_tick(b, i, ibus_axes, C, AS, AI, FB, inv_vbus, inv_brake_r):
    """low_level.cpp:322-376 and odrive_main's disarm: the brake resistor takes the
    regenerated current; a bus current beyond the DC limits disarms both motors, with the
    board's error (0.5.2+) or as a motor error (0.5.1, C_REGEN_ERR_STYLE)."""
    ibus = ibus_axes
    brake_i = 0.0
    if C[b, 0, C_BRAKE_ON] > 0.0:
        brake_i = brake_current(ibus, C[b, 0, C_MAX_REGEN], C[b, 0, C_BRAKE_R], inv_vbus, C[b, 0, C_VBUS],
                                inv_brake_r)
        ibus += brake_i
    AS[b, 0, S_BRAKE_I] = brake_i
    AS[b, 0, S_IBUS] = ibus
    over_pos, over_neg = bus_fault(ibus, C[b, 0, C_DC_MAX_POS], C[b, 0, C_DC_MAX_NEG])
    if not (over_pos or over_neg):
        return
    old_style = C[b, 0, C_REGEN_ERR_STYLE] > 0.0
    for a in range(2):
        if old_style:    # 0.5.1: low_level_fault on the motors
            AI[b, a, I_MOTOR_ERR] |= (MOTOR_ERROR_DC_BUS_OVER_REGEN_CURRENT if over_neg
                                       else MOTOR_ERROR_DC_BUS_OVER_CURRENT)
        else:            # 0.5.2+: odrv.disarm_with_error
            AI[b, a, I_MOTOR_ERR] |= MOTOR_ERROR_SYSTEM_LEVEL
        AI[b, a, I_AXIS_ERR] |= AXIS_ERROR_MOTOR_FAILED
        AI[b, a, I_MODE] = MODE_IDLE
        AS[b, a, S_IQ] = 0.0
        AS[b, a, S_V_PREV] = 0.0
    if not old_style:
        AI[b, 0, I_SYS_ERR] |= (ODRIVE_ERROR_DC_BUS_OVER_REGEN_CURRENT if over_neg
                                else ODRIVE_ERROR_DC_BUS_OVER_CURRENT)
    FB[_at(R_TAU + 0, i)] = 0.0
    FB[_at(R_TAU + 1, i)] = 0.0


@njit(cache=True)   # a rare tick's work: compiled apart (see _run_block_ticks)
def _abort_step(k, b, i, code, AS, AI, FB, ABORT):
    """leglib's abort: both axes IDLE (as a request of IDLE does: the controller keeps its
    state, motor.cpp:218-228), no current; the first abort's tick and reason recorded."""
    for a in range(2):
        AI[b, a, I_MODE] = MODE_IDLE
        AS[b, a, S_IQ] = 0.0
        AS[b, a, S_V_PREV] = 0.0
    FB[_at(R_TAU + 0, i)] = 0.0
    FB[_at(R_TAU + 1, i)] = 0.0
    if ABORT[b, 1] == ABORT_NONE:
        ABORT[b, 0] = k
        ABORT[b, 1] = code


@njit(cache=True)
def _run_block(b0, b1, n_ticks, dt, X, AS, AI, C, P, FR, MECH, DRV, RNG, ABORT, TT, tt_period, REC,
               rec_every, rec_offset, plain):
    """Legs b0..b1-1 of :func:`_run`, tick by tick: each tick the firmware's loop for every
    leg -- the board's checks, each axis's tick (:func:`_axis_tick`: encoder, controller,
    motor), the DC bus, leglib's abort -- then the block's mechanics: one loop over the legs
    that vectorizes when ``plain`` (they share a plain plant, :func:`_plain_block`), else
    leg by leg. A leg's numbers do not depend on the block it is in."""
    nb = b1 - b0
    turns_per_rad = DRV[0] / TWO_PI
    # per-call invariants by leg (the host changes C only between calls): the current
    # loop's discrete pole, and reciprocals (a division in the tick loop is costly)
    CC_KP, CC_KI_DT, INV_KT, INV_CPR = np.empty((nb, 2)), np.empty((nb, 2)), np.empty((nb, 2)), np.empty((nb, 2))
    VMAX = np.empty(nb)
    a_half, inv_r, m_half = motor_plant(DRV, dt)
    INV_VBUS, INV_BRAKE_R = np.empty(nb), np.empty(nb)
    INV_VS, INV_VSM = np.empty(nb), np.empty(nb)
    # the legs' joints, time, torques, dead and non-finite flags in the block's rows
    FB = np.zeros(N_FROWS * LANES)
    IB = np.zeros(N_IROWS * LANES, np.int64)
    tau2 = np.empty(2)         # one leg's motor torques (the belt and cogging modify them)
    RNGL = np.empty(nb, np.uint64)
    TM = np.zeros((nb, 2))     # the motor torques on the rotors (compliant belt)
    for i in range(nb):
        b = b0 + i
        for a in range(2):
            CC_KP[i, a], CC_KI_DT[i, a] = current_gains(C[b, a, C_CURRENT_BW], C[b, a, C_PHASE_R],
                                                        C[b, a, C_PHASE_L], dt)
            INV_KT[i, a] = 1.0 / C[b, a, C_KT]
            INV_CPR[i, a] = 1.0 / C[b, a, C_CPR]
        INV_VBUS[i], INV_BRAKE_R[i] = 1.0 / C[b, 0, C_VBUS], 1.0 / C[b, 0, C_BRAKE_R]
        VMAX[i] = V_MAX_PER_VBUS * C[b, 0, C_VBUS]
        INV_VS[i], INV_VSM[i] = 1.0 / FR[b, 6], 1.0 / FR[b, 7]
        for n in range(5):
            FB[_at(R_Q + n, i)] = X[b, n]
        IB[_at(R_DEAD, i)] = 1 if ABORT[b, 1] == ABORT_NONFINITE else 0
        RNGL[i] = RNG[b]
    _run_block_ticks(b0, b1, n_ticks, dt, X, AS, AI, C, P, FR, MECH, DRV, ABORT, TT, tt_period, REC, rec_every,
                     rec_offset, plain, CC_KP, CC_KI_DT, INV_KT, INV_CPR, VMAX, INV_VBUS, INV_BRAKE_R, INV_VS,
                     INV_VSM, FB, IB, tau2, RNGL, TM, a_half, inv_r, m_half, turns_per_rad, P[b0:b0 + 1],
                     FR[b0:b0 + 1])
    for i in range(nb):
        RNG[b0 + i] = RNGL[i]


# The stages a tick runs every time are inlined into this loop (numba's inline="always"); the
# ones only a rare tick runs (a calibration, a trapezoidal move, a fault, an abort) and the
# mechanics of a plant with unmodeled effects (mechanics._mechanics_leg_apart) are functions
# of their own. numba's passes over one function take time that grows faster than its size:
# this loop with all of them inlined took 27 s of the device group's 33 s to compile, apart
# about a third less, with the same ticks per second (benchmarks device_tick and a mixed
# batch leg by leg) and the same numbers (tests/twin: the vectorized path bit for bit).
#
# numba's runtime (NRT) counts references to every array a function holds: each array
# argument of each inlined stage is a new reference, taken and dropped with an atomic
# operation, and in this loop's branching body most of those pairs survive numba's
# pruning. They took over half of a tick's time (0.57 us a tick for one leg, 0.14 us
# without). The tick loop allocates nothing, so it is compiled without the runtime
# (numba's ``_nrt`` option, numba.core.options): its arrays are all borrowed from
# _run_block, which allocates them and outlives the call. Same operations, same numbers.
@njit(cache=True, _nrt=False)
def _run_block_ticks(b0, b1, n_ticks, dt, X, AS, AI, C, P, FR, MECH, DRV, ABORT, TT, tt_period, REC, rec_every,
                     rec_offset, plain, CC_KP, CC_KI_DT, INV_KT, INV_CPR, VMAX, INV_VBUS, INV_BRAKE_R, INV_VS,
                     INV_VSM, FB, IB, tau2, RNGL, TM, a_half, inv_r, m_half, turns_per_rad, P_plain, FR_plain):
    """The tick loop of :func:`_run_block` over its per-call invariants and scratch (the
    block's rows FB and IB, the legs' RNG states RNGL): X, AS, AI, ABORT, REC updated in
    place; RNGL holds the legs' RNG states at the end."""
    nb = b1 - b0
    n_rec = REC.shape[1]
    Pb_first = _param_row(P, b0)   # the first leg's parameters, loaded once
    next_rec = 0 if rec_every > 0 else -1   # the next tick recorded (no modulo per tick)
    for k in range(n_ticks):
        rec_row = -1
        if k == next_rec:
            next_rec += rec_every
            rec_row = rec_offset + k // rec_every
        for i in range(nb):
            if IB[_at(R_DEAD, i)] != 0:
                continue
            b = b0 + i
            if 0 <= rec_row < n_rec:   # recorded before the tick: row 0 is the initial state
                REC[b, rec_row, 0] = FB[_at(R_Q + 4, i)] if plain else X[b, 4]
                REC[b, rec_row, 1] = AS[b, 0, S_COUNT_F]
                REC[b, rec_row, 2] = AS[b, 1, S_COUNT_F]
                REC[b, rec_row, 3] = AS[b, 0, S_IQ_MEAS]
                REC[b, rec_row, 4] = AS[b, 1, S_IQ_MEAS]
            rng = RNGL[i]
            _board_checks(b, C, AS, AI)
            ibus_axes = 0.0
            # an int64 from the start: grown from the constant, _abort_step would also be compiled
            # for its literal 0 (tests/notebook/test_warmup.py)
            abort_code = np.int64(ABORT_NONE)
            for a in range(2):
                j = _joint_of(a, DRV)
                q = FB[_at(R_Q + 2 * j, i)] if plain else X[b, 2 * j]
                w = FB[_at(R_Q + 2 * j + 1, i)] if plain else X[b, 2 * j + 1]
                if FR[b, F_BELT_K] > 0.0:       # compliant belt: the encoder is on the rotor
                    q = X[b, X_PHI1 + 2 * j]
                    w = X[b, X_PHI1 + 2 * j + 1]
                rng, ib, code = _axis_tick(k, b, a, i, q, w, rng, dt, C, AS, AI, FR, FB, DRV, TT, tt_period,
                                           turns_per_rad, INV_CPR[i, a], INV_KT[i, a], INV_VBUS[i], CC_KP[i, a],
                                           CC_KI_DT[i, a], VMAX[i], a_half, inv_r, m_half)
                ibus_axes += ib
                if code != ABORT_NONE:
                    abort_code = code
            _bus_tick(b, i, ibus_axes, C, AS, AI, FB, INV_VBUS[i], INV_BRAKE_R[i])
            if abort_code != ABORT_NONE:
                _abort_step(k, b, i, abort_code, AS, AI, FB, ABORT)
            RNGL[i] = rng
        # ---- mechanics (leglib.twin.mechanics)
        if plain:
            _mechanics_plain(dt, FB, IB, nb, P_plain, FR_plain)
            for i in range(nb):
                if IB[_at(R_NF, i)] != 0:
                    b = b0 + i
                    ABORT[b, 0] = k
                    ABORT[b, 1] = ABORT_NONFINITE
                    for a in range(2):
                        AI[b, a, I_MODE] = MODE_IDLE
                    IB[_at(R_DEAD, i)] = 1
        else:
            for i in range(nb):
                if IB[_at(R_DEAD, i)] != 0:
                    continue
                b = b0 + i
                tau2[0], tau2[1] = FB[_at(R_TAU, i)], FB[_at(R_TAU + 1, i)]
                Pb = Pb_first if i == 0 else _param_row(P, b)
                if _mechanics_leg_apart(b, k, dt, X, AI, FR, MECH, DRV, ABORT, Pb, tau2, TM[i], INV_VS[i],
                                        INV_VSM[i]):
                    IB[_at(R_DEAD, i)] = 1
    if plain:
        for i in range(nb):
            for n in range(5):
                X[b0 + i, n] = FB[_at(R_Q + n, i)]
