"""The twin's kernel: a batch of legs advanced tick by tick at the ODrive's 8 kHz.

Per tick and axis it does what firmware 0.5.x does: the board's checks, the encoder read
(quantized at the configured CPR, with noise) and its PLL, the cascade (position P ->
velocity PI with the velocity limit and the integrator's anti-windup, the input modes),
the current loop (first order at the current-control bandwidth, current limit, torque
constant) and its fault checks, then the DC bus with the brake resistor, then the leg's
mechanics (:mod:`leglib.twin.mechanics`). :func:`_run` shares the batch out in blocks over
the cores; a block the vectorized path allows goes to :mod:`leglib.twin.vector`, every
other one to :func:`_run_block`, the reference.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ..abort import (
    ABORT_NONE,
    ABORT_NONFINITE,
    ABORT_OSCILLATION,
    ABORT_POSITION_ERROR,
    _oscillation_step,
)
from .effects import _encoder_error
from .layout import (
    AXIS_ERROR_CONTROLLER_FAILED,
    AXIS_ERROR_DC_BUS_OVER_VOLTAGE,
    AXIS_ERROR_DC_BUS_UNDER_VOLTAGE,
    AXIS_ERROR_MOTOR_FAILED,
    AXIS_ERROR_WATCHDOG_TIMER_EXPIRED,
    C_ABORT_ERROR,
    C_BRAKE_ON,
    C_BRAKE_R,
    C_CAL_CURRENT,
    C_CAL_RAMP,
    C_CAL_VEL,
    C_COUNT_OFFSET,
    C_CURRENT_BW,
    C_CURRENT_LIM,
    C_DC_MAX_NEG,
    C_DC_MAX_POS,
    C_ENCODER_BW,
    C_FILTER_BW,
    C_INPUT_MODE,
    C_INPUT_POS,
    C_INPUT_TORQUE,
    C_INPUT_VEL,
    C_INT_RESET_TORQUE,
    C_KT,
    C_MAX_REGEN,
    C_OV_TRIP,
    C_POS_GAIN,
    C_REGEN_ERR_STYLE,
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
    C_UV_TRIP,
    C_VBUS,
    C_VBUS_CHECKS,
    C_VBUS_R,
    C_VEL_GAIN,
    C_VEL_INT_GAIN,
    C_VEL_INT_LIMIT,
    C_VEL_LIMIT,
    C_VEL_TOL,
    C_WD_ENABLE,
    CONTROLLER_ERROR_OVERSPEED,
    F_BELT_K,
    F_ENC_ON,
    I_AXIS_ERR,
    I_COUNTS,
    I_CTRL_ERR,
    I_MODE,
    I_MOTOR_ERR,
    I_SYS_ERR,
    I_TRAJ_DONE,
    INPUT_MODE_PASSTHROUGH,
    INPUT_MODE_POS_FILTER,
    INPUT_MODE_TRAP_TRAJ,
    LANES,
    MODE_CALIB,
    MODE_IDLE,
    MODE_POSITION,
    MODE_TORQUE,
    MOTOR_ERROR_CURRENT_LIMIT_VIOLATION,
    MOTOR_ERROR_DC_BUS_OVER_CURRENT,
    MOTOR_ERROR_DC_BUS_OVER_REGEN_CURRENT,
    MOTOR_ERROR_SYSTEM_LEVEL,
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
    S_IBUS,
    S_IBUS_MOTOR,
    S_INTEGRATOR,
    S_IQ,
    S_IQ_MEAS,
    S_OSC,
    S_POS_EST,
    S_POS_SP,
    S_TQ_SP,
    S_TT_T,
    S_VEL_EST,
    S_VEL_SP,
    S_WD_TIMER,
    X_PHI1,
)
from .mechanics import _at, _mechanics_leg, _mechanics_plain, _param_row, _plain_block
from .rng import _normal
from .stages import (
    TWO_PI,
    brake_current,
    bus_fault,
    current_loop,
    current_violation,
    encoder_counts,
    encoder_pll,
    integrator_step,
    motor_bus_current,
    overspeed,
    torque_command,
    torque_limit,
    velocity_command,
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


@njit(cache=True, parallel=True)
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
    pairs, phase resistance [ohm]); TT[b, i, axis] a torque table applied
    to axes in torque mode, row i = tick // tt_period (ignored when it has no rows);
    REC[b, k] = (t, counts0, counts1, Iq0, Iq1) every ``rec_every`` ticks from row
    ``rec_offset``. The legs go in blocks of ``block``, a thread's unit of work (see
    :func:`_run_block`). Returns nothing; everything is updated in place.
    """
    B = X.shape[0]
    block = min(block, LANES)
    for blk in prange((B + block - 1) // block):
        _run_block_any(blk * block, min(B, (blk + 1) * block), n_ticks, dt, X, AS, AI, C, P, FR, MECH, DRV,
                       RNG, ABORT, TT, tt_period, REC, rec_every, rec_offset)


@njit(cache=True)
def _run_serial(n_ticks, dt, X, AS, AI, C, P, FR, MECH, DRV, RNG, ABORT, TT, tt_period, REC, rec_every,
                rec_offset, block):
    """:func:`_run` without the thread pool: cheaper per call for a batch of one (a host loop
    advancing the virtual device a few ticks per USB transaction). Same numbers."""
    B = X.shape[0]
    block = min(block, LANES)
    for b0 in range(0, B, block):
        _run_block_any(b0, min(B, b0 + block), n_ticks, dt, X, AS, AI, C, P, FR, MECH, DRV, RNG, ABORT, TT,
                       tt_period, REC, rec_every, rec_offset)


@njit(cache=True)
def _run_block_any(b0, b1, n_ticks, dt, X, AS, AI, C, P, FR, MECH, DRV, RNG, ABORT, TT, tt_period, REC,
                   rec_every, rec_offset):
    """Legs b0..b1-1: vectorized (:func:`_run_block_vector`) when they allow, else
    :func:`_run_block`; the same numbers either way."""
    # ``plain`` goes to _run_block as a variable, never as the constant True or False: numba
    # would compile _run_block once for each literal (about 25 s more on a first run)
    plain = _plain_block(b0, b1, P, FR, MECH)
    if plain and _vector_block(b0, b1, FR, C, AI):
        _run_block_vector(b0, b1, n_ticks, dt, X, AS, AI, C, P, FR, DRV, RNG, ABORT, REC, rec_every,
                          rec_offset)
    elif plain:
        _run_block(b0, b1, n_ticks, dt, X, AS, AI, C, P, FR, MECH, DRV, RNG, ABORT, TT, tt_period, REC,
                   rec_every, rec_offset, plain)
    else:   # one leg at a time: its state stays in the cache over the ticks
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
    """encoder.cpp: the reading of joint angle ``q`` (noise, the plant's reading error,
    quantization) and the PLL; (rng, the rotor's turns from rest, pos_estimate,
    vel_estimate)."""
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


@njit(cache=True, inline="always")
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
    AS[b, a, S_INTEGRATOR] = 0.0
    FB[_at(R_TAU + _joint_of(a, DRV), i)] = DRV[2] * DRV[0] * DRV[8] * iq
    w = AS[b, a, S_VEL_EST] * TWO_PI
    ib = (1.5 * DRV[11] * i_now ** 2 + DRV[8] * iq * w) * inv_vbus
    AS[b, a, S_IBUS_MOTOR] = ib
    return rng, ib


@njit(cache=True, inline="always")
def _disarmed(b, a, i, AS, AI, FB, DRV):
    """An IDLE axis: no current, the integrator cleared, no torque on its joint."""
    AI[b, a, I_MODE] = MODE_IDLE
    AS[b, a, S_IQ] = 0.0
    AS[b, a, S_INTEGRATOR] = 0.0
    AS[b, a, S_IQ_MEAS] = 0.0
    AS[b, a, S_IBUS_MOTOR] = 0.0
    FB[_at(R_TAU + _joint_of(a, DRV), i)] = 0.0


@njit(cache=True, inline="always")
def _input_setpoints(b, a, mode, dt, C, AS, AI):
    """controller.cpp:183-283: the setpoints from the inputs by input_mode (PASSTHROUGH,
    POS_FILTER, TRAP_TRAJ; INACTIVE keeps them); the end of a trajectory drops the axis
    into position control (controller.cpp:255-262). Returns the control mode."""
    imode = int(C[b, a, C_INPUT_MODE])
    if imode == INPUT_MODE_PASSTHROUGH:
        AS[b, a, S_POS_SP] = C[b, a, C_INPUT_POS]
        AS[b, a, S_VEL_SP] = C[b, a, C_INPUT_VEL]
        AS[b, a, S_TQ_SP] = C[b, a, C_INPUT_TORQUE]
    elif imode == INPUT_MODE_POS_FILTER:
        fki = 2.0 * min(C[b, a, C_FILTER_BW], 0.25 / dt)
        fkp = 0.25 * fki * fki
        acc = fkp * (C[b, a, C_INPUT_POS] - AS[b, a, S_POS_SP]) + fki * (C[b, a, C_INPUT_VEL] - AS[b, a, S_VEL_SP])
        AS[b, a, S_TQ_SP] = 0.0  # acceleration times config.inertia (0 by default)
        AS[b, a, S_VEL_SP] += dt * acc
        AS[b, a, S_POS_SP] += dt * AS[b, a, S_VEL_SP]
    elif imode == INPUT_MODE_TRAP_TRAJ and AI[b, a, I_TRAJ_DONE] == 0:
        tt = AS[b, a, S_TT_T]
        ta, tv, td = C[b, a, C_TT_TA], C[b, a, C_TT_TV], C[b, a, C_TT_TD]
        if tt > ta + tv + td:
            AI[b, a, I_TRAJ_DONE] = 1
            AS[b, a, S_POS_SP] = C[b, a, C_TT_XF]
            AS[b, a, S_VEL_SP] = 0.0
            AS[b, a, S_TQ_SP] = 0.0
            if mode != MODE_POSITION:
                mode = MODE_POSITION
                AI[b, a, I_MODE] = MODE_POSITION
        else:
            if tt < 0.0:
                y, yd = C[b, a, C_TT_XI], C[b, a, C_TT_VI]
            elif tt < ta:
                y = C[b, a, C_TT_XI] + C[b, a, C_TT_VI] * tt + 0.5 * C[b, a, C_TT_AR] * tt * tt
                yd = C[b, a, C_TT_VI] + C[b, a, C_TT_AR] * tt
            elif tt < ta + tv:
                y = C[b, a, C_TT_YACC] + C[b, a, C_TT_VR] * (tt - ta)
                yd = C[b, a, C_TT_VR]
            else:
                tdd = tt - (ta + tv + td)
                y = C[b, a, C_TT_XF] + 0.5 * C[b, a, C_TT_DR] * tdd * tdd
                yd = C[b, a, C_TT_DR] * tdd
            AS[b, a, S_POS_SP] = y
            AS[b, a, S_VEL_SP] = yd
            AS[b, a, S_TQ_SP] = 0.0
            AS[b, a, S_TT_T] = tt + dt
    return mode


@njit(cache=True, inline="always")
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


@njit(cache=True, inline="always")
def _controller_tick(k, b, a, mode, pe, ve, dt, C, AS, TT, tt_period):
    """controller.cpp:286-420: the torque the controller asks for [N*m]: from the torque
    table or setpoint in torque control (with the firmware's torque-mode velocity limiter),
    else the cascade; limited to the current limit, and the velocity integrator's update."""
    vel_limit = C[b, a, C_VEL_LIMIT]
    vel_gain = C[b, a, C_VEL_GAIN]
    t_lim = C[b, a, C_CURRENT_LIM] * C[b, a, C_KT]
    if mode == MODE_TORQUE:
        n_tab = TT.shape[1]
        torque = TT[b, min(k // tt_period, n_tab - 1), a] if n_tab > 0 else AS[b, a, S_TQ_SP]
        # enable_torque_mode_vel_limit (controller.cpp:137-141,388-394)
        torque = min(max(torque, (-vel_limit - ve) * vel_gain), (vel_limit - ve) * vel_gain)
        torque, limited = torque_limit(torque, t_lim)
        if C[b, a, C_INT_RESET_TORQUE] > 0.0:   # the integrator is reset in torque control
            AS[b, a, S_INTEGRATOR] = 0.0
        return torque
    vel_des = velocity_command(AS[b, a, S_POS_SP], pe, AS[b, a, S_VEL_SP], C[b, a, C_POS_GAIN], vel_limit,
                               mode == MODE_POSITION)
    verr = vel_des - ve
    torque, limited = torque_limit(torque_command(vel_gain, verr, AS[b, a, S_INTEGRATOR], AS[b, a, S_TQ_SP]),
                                   t_lim)
    AS[b, a, S_INTEGRATOR] = integrator_step(AS[b, a, S_INTEGRATOR], limited, C[b, a, C_VEL_INT_GAIN], dt, verr,
                                             C[b, a, C_VEL_INT_LIMIT])
    return torque


@njit(cache=True, inline="always")
def _motor_tick(b, a, i, torque, ve, rng, C, AS, AI, FB, DRV, alpha, inv_kt, inv_vbus):
    """motor.cpp: the current loop reaching the commanded torque's current, its measurement
    (with noise) and the current-limit trip, the torque on the joint (the motor's true torque
    constant) and the motor's bus current. (rng, bus current)."""
    iq = current_loop(AS[b, a, S_IQ], alpha, torque, inv_kt)
    AS[b, a, S_IQ] = iq
    rng, nz = _normal(rng)
    iq_meas = iq + DRV[7] * nz
    AS[b, a, S_IQ_MEAS] = iq_meas
    if current_violation(iq_meas, C[b, a, C_CURRENT_LIM]):
        AI[b, a, I_MOTOR_ERR] |= MOTOR_ERROR_CURRENT_LIMIT_VIOLATION
        AI[b, a, I_AXIS_ERR] |= AXIS_ERROR_MOTOR_FAILED
        AI[b, a, I_MODE] = MODE_IDLE
        AS[b, a, S_IQ] = 0.0
        iq = 0.0
    # the motor's own torque constant makes the torque; the configured one only converts
    # the torque command to a current
    FB[_at(R_TAU + _joint_of(a, DRV), i)] = DRV[2] * DRV[0] * DRV[8] * iq
    ib = motor_bus_current(DRV[11], iq, DRV[8], ve, inv_vbus)
    AS[b, a, S_IBUS_MOTOR] = ib
    return rng, ib


@njit(cache=True, inline="always")
def _axis_tick(k, b, a, i, q, rng, dt, C, AS, AI, FR, FB, DRV, TT, tt_period, turns_per_rad, inv_cpr, alpha,
               inv_kt, inv_vbus):
    """One control tick of axis ``a`` of leg ``b`` (Axis::run_control_loop): the encoder, then
    calibration, IDLE, or the controller and the motor. (rng, bus current, abort code)."""
    rng, turns, pe, ve = _encoder_tick(b, a, q, rng, dt, C, AS, AI, FR, DRV, turns_per_rad, inv_cpr)
    mode = AI[b, a, I_MODE]
    if mode == MODE_CALIB:
        rng, ib = _calibration_tick(b, a, i, turns, rng, dt, C, AS, FB, DRV, inv_vbus)
        return rng, ib, ABORT_NONE
    if overspeed(mode != MODE_IDLE, ve, C[b, a, C_VEL_LIMIT], C[b, a, C_VEL_TOL]):
        AI[b, a, I_CTRL_ERR] |= CONTROLLER_ERROR_OVERSPEED
        AI[b, a, I_AXIS_ERR] |= AXIS_ERROR_CONTROLLER_FAILED
        mode = MODE_IDLE
    if mode == MODE_IDLE:
        _disarmed(b, a, i, AS, AI, FB, DRV)
        return rng, 0.0, ABORT_NONE
    mode = _input_setpoints(b, a, mode, dt, C, AS, AI)
    code = _step_abort(b, a, mode, pe, C, AS)
    torque = _controller_tick(k, b, a, mode, pe, ve, dt, C, AS, TT, tt_period)
    rng, ib = _motor_tick(b, a, i, torque, ve, rng, C, AS, AI, FB, DRV, alpha, inv_kt, inv_vbus)
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
        AS[b, a, S_INTEGRATOR] = 0.0
    if not old_style:
        AI[b, 0, I_SYS_ERR] |= (ODRIVE_ERROR_DC_BUS_OVER_REGEN_CURRENT if over_neg
                                else ODRIVE_ERROR_DC_BUS_OVER_CURRENT)
    FB[_at(R_TAU + 0, i)] = 0.0
    FB[_at(R_TAU + 1, i)] = 0.0


@njit(cache=True, inline="always")
def _abort_step(k, b, i, code, AS, AI, FB, ABORT):
    """leglib's abort: both axes IDLE, no current, the integrators cleared; the first abort's
    tick and reason recorded."""
    for a in range(2):
        AI[b, a, I_MODE] = MODE_IDLE
        AS[b, a, S_IQ] = 0.0
        AS[b, a, S_INTEGRATOR] = 0.0
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
    n_rec = REC.shape[1]
    turns_per_rad = DRV[0] / TWO_PI
    inv_cpr = 1.0 / DRV[1]
    # per-call invariants by leg (the host changes C only between calls): the current
    # loop's discrete pole, and reciprocals (a division in the tick loop is costly)
    ALPHA, INV_KT = np.empty((nb, 2)), np.empty((nb, 2))
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
            ALPHA[i, a] = 1.0 - math.exp(-C[b, a, C_CURRENT_BW] * dt)
            INV_KT[i, a] = 1.0 / C[b, a, C_KT]
        INV_VBUS[i], INV_BRAKE_R[i] = 1.0 / C[b, 0, C_VBUS], 1.0 / C[b, 0, C_BRAKE_R]
        INV_VS[i], INV_VSM[i] = 1.0 / FR[b, 6], 1.0 / FR[b, 7]
        for n in range(5):
            FB[_at(R_Q + n, i)] = X[b, n]
        IB[_at(R_DEAD, i)] = 1 if ABORT[b, 1] == ABORT_NONFINITE else 0
        RNGL[i] = RNG[b]
    Pb_first = _param_row(P, b0)   # the first leg's parameters, loaded once
    P_plain = P[b0:b0 + 1]
    FR_plain = FR[b0:b0 + 1]
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
            abort_code = ABORT_NONE
            for a in range(2):
                j = _joint_of(a, DRV)
                q = FB[_at(R_Q + 2 * j, i)] if plain else X[b, 2 * j]
                if FR[b, F_BELT_K] > 0.0:       # compliant belt: the encoder is on the rotor
                    q = X[b, X_PHI1 + 2 * j]
                rng, ib, code = _axis_tick(k, b, a, i, q, rng, dt, C, AS, AI, FR, FB, DRV, TT, tt_period,
                                           turns_per_rad, inv_cpr, ALPHA[i, a], INV_KT[i, a], INV_VBUS[i])
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
                if _mechanics_leg(b, k, dt, X, AI, FR, MECH, DRV, ABORT, Pb, tau2, TM[i], INV_VS[i],
                                  INV_VSM[i]):
                    IB[_at(R_DEAD, i)] = 1
    for i in range(nb):
        b = b0 + i
        if plain:
            for n in range(5):
                X[b, n] = FB[_at(R_Q + n, i)]
        RNG[b] = RNGL[i]
