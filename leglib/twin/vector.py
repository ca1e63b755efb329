"""The vectorized path of the twin's kernel: a block of legs, structure of arrays.

The common case of a sweep -- every axis in position control or IDLE with its inputs passed
through, no watchdog -- runs here: the block's state copied into rows by leg, then per tick
one loop over the legs for the controllers and, for a plain plant (no unmodeled effects),
one for the mechanics, branch-free, which the compiler turns into SIMD code over 8 legs at
a time. It does what the reference tick of :mod:`leglib.twin.kernel` does for such a block,
the same operations in the same order, so a leg's numbers do not depend on its path
(tests/twin checks it bit for bit).

A block whose legs share one plant with unmodeled effects (the thesis grid on one plant)
keeps the vectorized controllers and steps its mechanics in loops over the legs that
vectorize as well (:func:`leglib.twin.mechanics._mechanics_effects`; the encoder's reading
error beforehand, :func:`_encoder_errors_shared`): the same operations in the same order
with the same functions (:mod:`leglib.kernelmath`'s sin, exp and tanh, on both paths), so
bit for bit the reference's numbers. A block of legs of different plants with effects
steps its mechanics leg by leg (:func:`leglib.twin.mechanics._mechanics_leg`, the
reference's; its encoder errors leg by leg): bit for bit the reference's numbers too.
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
from ..kernelmath import py_min, select
from .effects import _encoder_error, _encoder_error_v
from .layout import (
    AXIS_ERROR_CONTROLLER_FAILED,
    AXIS_ERROR_MOTOR_FAILED,
    C_BEMF_FF,
    C_BRAKE_ON,
    C_BRAKE_R,
    C_CIRCULAR,
    C_CONTROL_MODE,
    C_CPR,
    C_CURRENT_BW,
    C_DC_MAX_NEG,
    C_DC_MAX_POS,
    C_EN_GAIN_SCHED,
    C_EN_OVERSPEED,
    C_EN_VEL_LIMIT,
    C_ENCODER_BW,
    C_FW_056,
    C_IBUS_MAX,
    C_IBUS_MIN,
    C_INPUT_MODE,
    C_KT,
    C_MAX_REGEN,
    C_PHASE_L,
    C_PHASE_R,
    C_REGEN_ERR_STYLE,
    C_RWL_FF,
    C_VBUS,
    C_VBUS_CHECKS,
    C_WD_ENABLE,
    CONTROL_MODE_POSITION,
    CONTROLLER_ERROR_OVERSPEED,
    CONTROLLER_ERROR_SPINOUT_DETECTED,
    F_BELT_K,
    F_ENC_A1,
    F_ENC_A2,
    F_ENC_C1,
    F_ENC_C2,
    F_ENC_ON,
    F_ENC_S1,
    F_ENC_S2,
    G_BRAKE_I,
    G_BRAKE_ON,
    G_BRAKE_R,
    G_DCN,
    G_DCP,
    G_FW056,
    G_IBUS,
    G_IBUS_AXES,
    G_INV_BRAKE_R,
    G_INV_VBUS,
    G_MAX_REGEN,
    G_STYLE,
    G_TAU_AXIS0,
    G_VBUS,
    I_AXIS_ERR,
    I_CONNECTED,
    I_COUNTS,
    I_CTRL_ERR,
    I_MODE,
    I_MOTOR_ERR,
    I_SYS_ERR,
    I_TQ_PRESENT,
    INPUT_MODE_PASSTHROUGH,
    K_AE,
    K_CCKI,
    K_CCKP,
    K_CLIM,
    K_ELECBW,
    K_FROM_C,
    K_INVCPR,
    K_INVKT,
    K_IPOS,
    K_ITQ,
    K_IVEL,
    K_KI,
    K_KP,
    K_KT,
    K_MARGIN,
    K_MAXI,
    K_MECHBW,
    K_OFF,
    K_PG,
    K_PHR,
    K_SPINE,
    K_SPINM,
    K_TLIM,
    K_VG,
    K_VIG,
    K_VIL,
    K_VL,
    K_VMAX,
    K_VTOL,
    LANES,
    MODE_IDLE,
    MODE_POSITION,
    MOTOR_ERROR_CURRENT_LIMIT_VIOLATION,
    MOTOR_ERROR_DC_BUS_OVER_CURRENT,
    MOTOR_ERROR_DC_BUS_OVER_REGEN_CURRENT,
    MOTOR_ERROR_SYSTEM_LEVEL,
    MOTOR_ERROR_UNKNOWN_TORQUE,
    MOTOR_ERROR_UNKNOWN_VOLTAGE_COMMAND,
    N_IROWS,
    N_K,
    N_V,
    N_VS,
    N_W,
    N_X,
    ODRIVE_ERROR_DC_BUS_OVER_CURRENT,
    ODRIVE_ERROR_DC_BUS_OVER_REGEN_CURRENT,
    R_AB,
    R_CODE,
    R_DEAD,
    R_ENC_ERR,
    R_G,
    R_K0,
    R_K1,
    R_NF,
    R_Q,
    R_RNG,
    R_SYS,
    R_TAU,
    R_V0,
    R_V1,
    R_W0,
    R_W1,
    S_BRAKE_I,
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
    S_POS_EST,
    S_POS_SP,
    S_TQ_OUT,
    S_TQ_SP,
    S_V_INT,
    S_V_PREV,
    S_VEL_EST,
    S_VEL_SP,
    V_CNTF,
    V_CONN,
    V_ELECP,
    V_FOCP,
    V_IBM,
    V_INT,
    V_IQ,
    V_IQM,
    V_IQSP,
    V_MAX_PER_VBUS,
    V_MECHP,
    V_OSC,
    V_PE,
    V_PSP,
    V_TQOUT,
    V_TQP,
    V_TSP,
    V_VE,
    V_VINT,
    V_VPREV,
    V_VSP,
    W_AXERR,
    W_COUNTS,
    W_CTRLERR,
    W_MODE,
    W_MOTERR,
    X_PHI1,
)
from .mechanics import (
    N_FROWS_EFFECTS,
    R_X,
    _at,
    _mechanics_effects,
    _mechanics_leg,
    _mechanics_plain,
    _param_row,
    _shared_block,
)
from .rng import _normal
from .stages import (
    brake_current,
    bus_fault,
    clamp,
    current_gains,
    current_setpoint,
    current_violation,
    encoder_counts,
    encoder_pll,
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
)


@njit(cache=True)
def _vector_block(b0, b1, FR, C, AI):
    """Whether legs b0..b1-1 can take :func:`_run_block_vector`: every axis in position control
    (configured, and armed or IDLE) with its inputs passed through, no watchdog, and the
    controller's optional features at their defaults (velocity limit and overspeed check
    on, no gain scheduling, no circular setpoints), a calibrated current controller without
    feed-forwards or bus-current limits; and no bus-voltage trips to check (a bare Twin's,
    or a virtual ODrive's step batch, which checks beforehand that they are out of reach:
    kernel._board_checks is not on this path)."""
    for b in range(b0, b1):
        if C[b, 0, C_VBUS_CHECKS] > 0.0:
            return False
        for a in range(2):
            mode = AI[b, a, I_MODE]
            if mode != MODE_IDLE and mode != MODE_POSITION:
                return False
            if C[b, a, C_INPUT_MODE] != INPUT_MODE_PASSTHROUGH or C[b, a, C_WD_ENABLE] > 0.0:
                return False
            if C[b, a, C_CONTROL_MODE] != CONTROL_MODE_POSITION or C[b, a, C_CIRCULAR] > 0.0:
                return False
            if not (C[b, a, C_EN_VEL_LIMIT] > 0.0 and C[b, a, C_EN_OVERSPEED] > 0.0) or C[b, a, C_EN_GAIN_SCHED] > 0.0:
                return False
            # a calibrated current controller without feed-forwards or bus-current trips
            if not C[b, a, C_PHASE_L] > 0.0 or C[b, a, C_BEMF_FF] > 0.0 or C[b, a, C_RWL_FF] > 0.0:
                return False
            if C[b, a, C_IBUS_MIN] != -np.inf or C[b, a, C_IBUS_MAX] != np.inf:
                return False
    return True


@njit(cache=True, inline="always")
def _axis_vector(i, a, FB, IB, q, w_joint, q_rest, rng, alive, dt, dirn, turns_per_rad, cpr, enc_noise,
                 cur_noise, quantize, N, kt_true, r_phase, inv_vbus, fw056, a_half, inv_r, m_half, enc):
    """One tick of axis ``a`` (a constant) of leg ``i`` of a vectorized block, its joint at
    ``q``: what the per-leg tick of :func:`_run_block` does for an axis in position
    control, armed or IDLE, with passthrough inputs, the same operations in the same order,
    branches turned into selects. Returns (rng, joint torque, bus current, abort code)."""
    rv, rk, rw = R_V0 + a * N_V, R_K0 + a * N_K, R_W0 + a * N_W
    # encoder and PLL: every tick, IDLE included
    turns = dirn * (q - q_rest) * turns_per_rad
    rng1, nz = _normal(rng)
    raw = turns * cpr + enc_noise * nz
    # the plant's reading error (row R_ENC_ERR, from :func:`_encoder_errors`), added as
    # kernel._encoder_tick adds it; ``enc`` False: a block without one
    raw = select(enc, raw + cpr * FB[_at(R_ENC_ERR + a, i)], raw)
    counts, counts_i = encoder_counts(raw, FB[_at(rk + K_OFF, i)], quantize)
    pe0 = FB[_at(rv + V_PE, i)]
    ve0 = FB[_at(rv + V_VE, i)]
    pe, ve = encoder_pll(pe0, ve0, counts, dt, FB[_at(rk + K_KP, i)], FB[_at(rk + K_KI, i)],
                         FB[_at(rk + K_INVCPR, i)])
    # the board's check
    mode0 = IB[_at(rw + W_MODE, i)]
    axis_err0 = IB[_at(rw + W_AXERR, i)]
    mode = select(axis_err0 != 0, MODE_IDLE, mode0)
    armed = mode != MODE_IDLE
    # the controller: every tick on 0.5.6, in closed loop on 0.5.1; its estimates the
    # encoder's once connected, else 0
    connected = FB[_at(rv + V_CONN, i)] != 0.0
    ctrl = fw056 | armed
    pe_c = select(connected, pe, 0.0)
    ve_c = select(connected, ve, 0.0)
    vel_limit = FB[_at(rk + K_VL, i)]
    kt = FB[_at(rk + K_KT, i)]
    vel_gain = FB[_at(rk + K_VG, i)]
    current_lim = FB[_at(rk + K_CLIM, i)]
    max_i = FB[_at(rk + K_MAXI, i)]
    t_lim = max_torque(current_lim, max_i, kt, FB[_at(rk + K_TLIM, i)])
    pos_sp = FB[_at(rk + K_IPOS, i)]
    vel_in = FB[_at(rk + K_IVEL, i)]
    tq_in = FB[_at(rk + K_ITQ, i)]
    vel_sp = select(fw056, clamp(vel_in, -vel_limit, vel_limit), vel_in)
    tq_sp = select(fw056, clamp(tq_in, -t_lim, t_lim), tq_in)
    over = ctrl & overspeed(True, ve_c, vel_limit, FB[_at(rk + K_VTOL, i)])
    vel_des = clamp(vel_sp + FB[_at(rk + K_PG, i)] * (pos_sp - pe_c), -vel_limit, vel_limit)
    verr = vel_des - ve_c
    integ0 = FB[_at(rv + V_INT, i)]
    torque, limited = torque_limit(torque_command(vel_gain, verr, integ0, tq_sp), t_lim)
    integ = integrator_step(integ0, limited, FB[_at(rk + K_VIG, i)], dt, verr, FB[_at(rk + K_VIL, i)])
    # the spinout check (0.5.6), on the current controller's last power and current
    iqm0 = FB[_at(rv + V_IQM, i)]
    mechp0, elecp0, focp0 = FB[_at(rv + V_MECHP, i)], FB[_at(rv + V_ELECP, i)], FB[_at(rv + V_FOCP, i)]
    mechp, elecp, spun = spinout(mechp0, elecp0, torque, ve_c, focp0, iqm0, FB[_at(rk + K_PHR, i)],
                                 FB[_at(rk + K_MECHBW, i)], FB[_at(rk + K_ELECBW, i)], dt, FB[_at(rk + K_SPINM, i)],
                                 FB[_at(rk + K_SPINE, i)])
    powers = ctrl & (not over) & fw056
    spin = powers & spun
    fail = over | spin
    ok = ctrl & (not fail)
    unknown_torque = fail & fw056 & connected
    ctrl_err = IB[_at(rw + W_CTRLERR, i)] | select(over, CONTROLLER_ERROR_OVERSPEED, 0) \
        | select(spin, CONTROLLER_ERROR_SPINOUT_DETECTED, 0)
    axis_err = axis_err0 | select(fail, AXIS_ERROR_CONTROLLER_FAILED, 0) \
        | select(unknown_torque & armed, AXIS_ERROR_MOTOR_FAILED, 0)
    motor_err = IB[_at(rw + W_MOTERR, i)] | select(unknown_torque, MOTOR_ERROR_UNKNOWN_TORQUE, 0) \
        | select(unknown_torque & armed, MOTOR_ERROR_UNKNOWN_VOLTAGE_COMMAND, 0)
    active = armed & (not fail)
    # leglib's abort rule on an armed axis
    abort_error = FB[_at(rk + K_AE, i)]
    err = pos_sp - pe
    checked = active & (abort_error > 0.0)
    too_far = checked & (abs(err) > abort_error)
    osc_on = checked & (not too_far)
    o0, o1, o2 = FB[_at(rv + V_OSC, i)], FB[_at(rv + V_OSC + 1, i)], FB[_at(rv + V_OSC + 2, i)]
    o3, o4, o5 = FB[_at(rv + V_OSC + 3, i)], FB[_at(rv + V_OSC + 4, i)], FB[_at(rv + V_OSC + 5, i)]
    n0, n1, n2, n3, n4, n5, unstable = _oscillation_step(o0, o1, o2, o3, o4, o5, err, 0.025 * abort_error)
    growing = osc_on & unstable
    code_a = select(too_far, ABORT_POSITION_ERROR, select(growing, ABORT_OSCILLATION, ABORT_NONE))
    # the motor: current setpoint, the sampled current and its trip, the current PI and the
    # phase current it drives (kernel._motor_tick)
    ilim = py_min(current_lim, max_i)
    iq_sp = current_setpoint(torque, FB[_at(rk + K_INVKT, i)], ilim)
    iq0 = FB[_at(rv + V_IQ, i)]
    rng2, nz = _normal(rng1)
    iq_meas = iq0 + cur_noise * nz
    violated = active & current_violation(iq_meas, current_lim, max_i, FB[_at(rk + K_MARGIN, i)])
    motor_err = motor_err | select(violated, MOTOR_ERROR_CURRENT_LIMIT_VIOLATION, 0)
    axis_err = axis_err | select(violated, AXIS_ERROR_MOTOR_FAILED, 0)
    vint0 = FB[_at(rv + V_VINT, i)]
    v, vint = foc_voltage(iq_sp, iq_meas, vint0, FB[_at(rk + K_CCKP, i)], FB[_at(rk + K_CCKI, i)], 0.0,
                          FB[_at(rk + K_VMAX, i)])
    e_bemf = (2.0 / 3.0) * kt_true * (dirn * N * w_joint)
    vprev0 = FB[_at(rv + V_VPREV, i)]
    i_next, i_mean = motor_current(iq0, vprev0, v, e_bemf, a_half, inv_r, m_half)
    flows = active & (not violated)
    tau = dirn * N * kt_true * i_mean
    ib = motor_bus_current(r_phase, i_mean, kt_true, ve, inv_vbus)
    # write back: a dead leg keeps everything; an IDLE axis zeroes its outputs (the old
    # values loaded first: a select between two loaded values vectorizes, a load
    # under a condition does not)
    cntf0 = FB[_at(rv + V_CNTF, i)]
    counts_i0 = IB[_at(rw + W_COUNTS, i)]
    ibm0 = FB[_at(rv + V_IBM, i)]
    iqsp0 = FB[_at(rv + V_IQSP, i)]
    psp0, vsp0, tsp0 = FB[_at(rv + V_PSP, i)], FB[_at(rv + V_VSP, i)], FB[_at(rv + V_TSP, i)]
    tqo0 = FB[_at(rv + V_TQOUT, i)]
    ctrl_err0 = IB[_at(rw + W_CTRLERR, i)]
    motor_err0 = IB[_at(rw + W_MOTERR, i)]
    tqp0 = FB[_at(rv + V_TQP, i)]
    run = alive & active
    idle = alive & (not active)
    flowing = alive & flows
    updated = alive & ctrl
    done = alive & ok
    osc_new = run & osc_on
    FB[_at(rv + V_PE, i)] = select(alive, pe, pe0)
    FB[_at(rv + V_VE, i)] = select(alive, ve, ve0)
    FB[_at(rv + V_CNTF, i)] = select(alive, counts, cntf0)
    IB[_at(rw + W_COUNTS, i)] = select(alive, counts_i, counts_i0)
    integrated = alive & ctrl & (not over)
    FB[_at(rv + V_INT, i)] = select(integrated, integ, integ0)
    FB[_at(rv + V_MECHP, i)] = select(alive & powers, mechp, mechp0)
    FB[_at(rv + V_ELECP, i)] = select(alive & powers, elecp, elecp0)
    FB[_at(rv + V_FOCP, i)] = select(flowing, 1.5 * v * iq_meas, focp0)
    FB[_at(rv + V_TQOUT, i)] = select(done, torque, tqo0)
    FB[_at(rv + V_TQP, i)] = select(done, 1.0, select(alive, 0.0, tqp0))
    iqsp_idle = select(done & connected, iq_sp, 0.0)
    FB[_at(rv + V_IQ, i)] = select(flowing, i_next, select(run | idle, 0.0, iq0))
    FB[_at(rv + V_VPREV, i)] = select(flowing, v, select(run | idle, 0.0, vprev0))
    FB[_at(rv + V_VINT, i)] = select(flowing, vint, vint0)
    FB[_at(rv + V_IQSP, i)] = select(run, iq_sp, select(idle & fw056, iqsp_idle, iqsp0))
    FB[_at(rv + V_IQM, i)] = select(run, iq_meas, iqm0)
    FB[_at(rv + V_IBM, i)] = select(flowing, ib, select(run | idle, 0.0, ibm0))
    FB[_at(rv + V_PSP, i)] = select(updated, pos_sp, psp0)
    FB[_at(rv + V_VSP, i)] = select(updated, vel_sp, vsp0)
    FB[_at(rv + V_TSP, i)] = select(updated, tq_sp, tsp0)
    FB[_at(rv + V_OSC, i)] = select(osc_new, n0, o0)
    FB[_at(rv + V_OSC + 1, i)] = select(osc_new, n1, o1)
    FB[_at(rv + V_OSC + 2, i)] = select(osc_new, n2, o2)
    FB[_at(rv + V_OSC + 3, i)] = select(osc_new, n3, o3)
    FB[_at(rv + V_OSC + 4, i)] = select(osc_new, n4, o4)
    FB[_at(rv + V_OSC + 5, i)] = select(osc_new, n5, o5)
    stopped = violated | (not active)
    mode_new = select(stopped, MODE_IDLE, mode)
    IB[_at(rw + W_MODE, i)] = select(alive, mode_new, mode0)
    IB[_at(rw + W_AXERR, i)] = select(alive, axis_err, axis_err0)
    IB[_at(rw + W_CTRLERR, i)] = select(alive, ctrl_err, ctrl_err0)
    IB[_at(rw + W_MOTERR, i)] = select(alive, motor_err, motor_err0)
    rng_out = select(run, rng2, select(alive, rng1, rng))
    return rng_out, select(flowing, tau, 0.0), select(flowing, ib, 0.0), select(run, code_a, ABORT_NONE)


@njit(cache=True, inline="always")
def _stop_axis(i, a, FB, IB, fault, stop, motor_flag):
    """Axis ``a`` (a constant) of leg ``i`` of a vectorized block after the bus check: a
    bus fault's error flags, and for a fault or an abort (``stop``) IDLE, no current."""
    rv, rw = R_V0 + a * N_V, R_W0 + a * N_W
    motor_err0, axis_err0, mode0 = IB[_at(rw + W_MOTERR, i)], IB[_at(rw + W_AXERR, i)], IB[_at(rw + W_MODE, i)]
    iq0, vprev0 = FB[_at(rv + V_IQ, i)], FB[_at(rv + V_VPREV, i)]
    IB[_at(rw + W_MOTERR, i)] = motor_err0 | select(fault, motor_flag, 0)
    IB[_at(rw + W_AXERR, i)] = axis_err0 | select(fault, AXIS_ERROR_MOTOR_FAILED, 0)
    IB[_at(rw + W_MODE, i)] = select(stop, MODE_IDLE, mode0)
    FB[_at(rv + V_IQ, i)] = select(stop, 0.0, iq0)
    FB[_at(rv + V_VPREV, i)] = select(stop, 0.0, vprev0)


@njit(cache=True, error_model="numpy")
def _control_vector(k, dt, FB, IB, nb, DRV, enc):
    """The controllers of a vectorized block for tick ``k``: one loop over its ``nb`` legs
    doing what the per-leg controller of :func:`_run_block` does for axes in position
    control or IDLE with passthrough inputs (the same operations in the same order,
    branches turned into selects), then the DC bus and the safety abort. The state and
    configuration of axis ``a`` are at rows R_V0/R_K0/R_W0 + a * N_V/N_K/N_W."""
    N, cpr, dirn = DRV[0], DRV[1], DRV[2]
    enc_noise, cur_noise, kt_true, r_phase = DRV[6], DRV[7], DRV[8], DRV[11]
    quantize = DRV[9] > 0.0
    j_of_a0 = int(DRV[5])
    q_rest_joint0, q_rest_joint1 = DRV[3], DRV[4]
    turns_per_rad = N / (2.0 * math.pi)
    a_half, inv_r, m_half = motor_plant(DRV, dt)
    axis0_on_joint0 = j_of_a0 == 0
    # one loop per axis: both axes in one loop would need more run-time overlap checks
    # between the block's arrays than the compiler makes, and it would not vectorize. Per
    # leg the axes still run in order (the noise stream, the mirrored torque)
    for i in range(nb):
        alive = IB[_at(R_DEAD, i)] == 0
        # the joints' angles, read from fixed rows (a row chosen at run time would keep
        # the compiler from proving the accesses independent)
        q_joint0, q_joint1 = FB[_at(R_Q, i)], FB[_at(R_Q + 2, i)]
        w_joint0, w_joint1 = FB[_at(R_Q + 1, i)], FB[_at(R_Q + 3, i)]
        rng, tau_axis0, ib0, code0 = _axis_vector(
            i, 0, FB, IB, select(axis0_on_joint0, q_joint0, q_joint1), select(axis0_on_joint0, w_joint0, w_joint1),
            select(axis0_on_joint0, q_rest_joint0, q_rest_joint1), np.uint64(IB[_at(R_RNG, i)]), alive, dt, dirn,
            turns_per_rad, cpr, enc_noise, cur_noise, quantize, N, kt_true, r_phase,
            FB[_at(R_G + G_INV_VBUS, i)], FB[_at(R_G + G_FW056, i)] > 0.0, a_half, inv_r, m_half, enc)
        IB[_at(R_RNG, i)] = np.int64(rng)
        FB[_at(R_G + G_TAU_AXIS0, i)] = tau_axis0
        FB[_at(R_G + G_IBUS_AXES, i)] = ib0
        IB[_at(R_CODE, i)] = code0
    for i in range(nb):
        alive = IB[_at(R_DEAD, i)] == 0
        q_joint0, q_joint1 = FB[_at(R_Q, i)], FB[_at(R_Q + 2, i)]
        w_joint0, w_joint1 = FB[_at(R_Q + 1, i)], FB[_at(R_Q + 3, i)]
        rng, tau_axis1, ib1, code1 = _axis_vector(
            i, 1, FB, IB, select(axis0_on_joint0, q_joint1, q_joint0), select(axis0_on_joint0, w_joint1, w_joint0),
            select(axis0_on_joint0, q_rest_joint1, q_rest_joint0), np.uint64(IB[_at(R_RNG, i)]), alive, dt, dirn,
            turns_per_rad, cpr, enc_noise, cur_noise, quantize, N, kt_true, r_phase,
            FB[_at(R_G + G_INV_VBUS, i)], FB[_at(R_G + G_FW056, i)] > 0.0, a_half, inv_r, m_half, enc)
        tau_axis0, code0 = FB[_at(R_G + G_TAU_AXIS0, i)], IB[_at(R_CODE, i)]
        ibus_sum = 0.0
        ibus_sum += FB[_at(R_G + G_IBUS_AXES, i)]
        ibus_sum += ib1
        IB[_at(R_RNG, i)] = np.int64(rng)
        FB[_at(R_TAU, i)] = select(axis0_on_joint0, tau_axis0, tau_axis1)
        FB[_at(R_TAU + 1, i)] = select(axis0_on_joint0, tau_axis1, tau_axis0)
        FB[_at(R_G + G_IBUS_AXES, i)] = ibus_sum
        IB[_at(R_CODE, i)] = select(code1 != ABORT_NONE, code1, code0)
    # a second loop for the board: one loop for everything would hold more memory accesses
    # than the compiler groups for its run-time overlap checks, and it would not vectorize
    for i in range(nb):
        alive = IB[_at(R_DEAD, i)] == 0
        inv_vbus = FB[_at(R_G + G_INV_VBUS, i)]
        ibus_sum = FB[_at(R_G + G_IBUS_AXES, i)]
        code = IB[_at(R_CODE, i)]
        tau_joint0, tau_joint1 = FB[_at(R_TAU, i)], FB[_at(R_TAU + 1, i)]
        # the DC bus: brake resistor, then the bus limits
        brake = FB[_at(R_G + G_BRAKE_ON, i)] > 0.0
        braking = brake_current(ibus_sum, FB[_at(R_G + G_MAX_REGEN, i)], FB[_at(R_G + G_BRAKE_R, i)], inv_vbus,
                                FB[_at(R_G + G_VBUS, i)], FB[_at(R_G + G_INV_BRAKE_R, i)])
        brake_i = select(brake, braking, 0.0)
        with_brake = ibus_sum + brake_i
        ibus_sum = select(brake, with_brake, ibus_sum)
        brake_i0, ibus0 = FB[_at(R_G + G_BRAKE_I, i)], FB[_at(R_G + G_IBUS, i)]
        FB[_at(R_G + G_BRAKE_I, i)] = select(alive, brake_i, brake_i0)
        FB[_at(R_G + G_IBUS, i)] = select(alive, ibus_sum, ibus0)
        over_pos, over_neg = bus_fault(ibus_sum, FB[_at(R_G + G_DCP, i)], FB[_at(R_G + G_DCN, i)])
        fault = alive & (over_pos | over_neg)
        old_style = FB[_at(R_G + G_STYLE, i)] > 0.0
        bus_flag = select(over_neg, MOTOR_ERROR_DC_BUS_OVER_REGEN_CURRENT, MOTOR_ERROR_DC_BUS_OVER_CURRENT)
        motor_flag = select(old_style, bus_flag, MOTOR_ERROR_SYSTEM_LEVEL)
        sys_flag = select(over_neg, ODRIVE_ERROR_DC_BUS_OVER_REGEN_CURRENT, ODRIVE_ERROR_DC_BUS_OVER_CURRENT)
        IB[_at(R_SYS, i)] = IB[_at(R_SYS, i)] | select(fault & (not old_style), sys_flag, 0)
        # a bus fault or an abort: both axes IDLE, no current, integrators cleared
        stop = fault | (alive & (code != ABORT_NONE))
        _stop_axis(i, 0, FB, IB, fault, stop, motor_flag)
        _stop_axis(i, 1, FB, IB, fault, stop, motor_flag)
        FB[_at(R_TAU, i)] = select(stop, 0.0, tau_joint0)
        FB[_at(R_TAU + 1, i)] = select(stop, 0.0, tau_joint1)
        ab_tick, ab_reason = IB[_at(R_AB, i)], IB[_at(R_AB + 1, i)]
        first = alive & (code != ABORT_NONE) & (ab_reason == ABORT_NONE)
        IB[_at(R_AB, i)] = select(first, k, ab_tick)
        IB[_at(R_AB + 1, i)] = select(first, code, ab_reason)


@njit(cache=True, inline="always")
def _sensed_rows(b, i, X, FR, FB):
    """Rows R_Q.. of leg ``i`` (leg ``b``) of a block whose mechanics go leg by leg: the
    angles and speeds the motors' encoders see (the rotors' with a compliant belt, else the
    joints', as kernel._run_block reads them) and the time, from X (which holds the joints)."""
    belt = FR[b, F_BELT_K] > 0.0
    for j in range(2):
        FB[_at(R_Q + 2 * j, i)] = X[b, X_PHI1 + 2 * j] if belt else X[b, 2 * j]
        FB[_at(R_Q + 2 * j + 1, i)] = X[b, X_PHI1 + 2 * j + 1] if belt else X[b, 2 * j + 1]
    FB[_at(R_Q + 4, i)] = X[b, 4]


@njit(cache=True)
def _encoder_errors(b0, nb, FB, IB, FR, DRV):
    """Rows R_ENC_ERR of a block for this tick: each axis's encoder reading error
    (effects._encoder_error) at the turns its encoder is at, computed as
    kernel._encoder_tick computes them; 0 for a leg without one. A loop of its own: the
    legs' branches would keep the axes' loops from vectorizing."""
    turns_per_rad = DRV[0] / (2.0 * math.pi)
    dirn = DRV[2]
    j0 = int(DRV[5])
    for i in range(nb):
        b = b0 + i
        for a in range(2):
            j = j0 if a == 0 else 1 - j0
            e = 0.0
            if FR[b, F_ENC_ON] > 0.0 and IB[_at(R_DEAD, i)] == 0:
                turns = dirn * (FB[_at(R_Q + 2 * j, i)] - DRV[3 + j]) * turns_per_rad
                e = _encoder_error(FR, b, turns)
            FB[_at(R_ENC_ERR + a, i)] = e


@njit(cache=True, error_model="numpy")
def _encoder_errors_shared(nb, FB, IB, FR, DRV):
    """:func:`_encoder_errors` for a block of legs that share one plant (FR its one row), in
    a loop over the legs that vectorizes (the same numbers)."""
    turns_per_rad = DRV[0] / (2.0 * math.pi)
    dirn = DRV[2]
    swap = int(DRV[5]) != 0          # axis 0 on joint 1
    on = FR[0, F_ENC_ON] > 0.0
    a1, cp1, sp1 = FR[0, F_ENC_A1], FR[0, F_ENC_C1], FR[0, F_ENC_S1]
    a2, cp2, sp2 = FR[0, F_ENC_A2], FR[0, F_ENC_C2], FR[0, F_ENC_S2]
    rest_a0 = select(swap, DRV[4], DRV[3])
    rest_a1 = select(swap, DRV[3], DRV[4])
    for i in range(nb):
        err_on = on & (IB[_at(R_DEAD, i)] == 0)
        q_joint0, q_joint1 = FB[_at(R_Q, i)], FB[_at(R_Q + 2, i)]
        turns0 = dirn * (select(swap, q_joint1, q_joint0) - rest_a0) * turns_per_rad
        turns1 = dirn * (select(swap, q_joint0, q_joint1) - rest_a1) * turns_per_rad
        FB[_at(R_ENC_ERR, i)] = select(err_on, _encoder_error_v(turns0, a1, cp1, sp1, a2, cp2, sp2), 0.0)
        FB[_at(R_ENC_ERR + 1, i)] = select(err_on, _encoder_error_v(turns1, a1, cp1, sp1, a2, cp2, sp2), 0.0)


@njit(cache=True)
def _mechanics_legs(k, dt, b0, nb, FB, IB, X, AI, P, FR, MECH, DRV, ABORT, TM, INV_VS, INV_VSM, tau2):
    """The mechanics of a vectorized block whose plant has unmodeled effects: leg by leg,
    the reference's :func:`_mechanics_leg` on X with the torques of rows R_TAU; a leg whose
    accelerations came out non-finite is stopped as :func:`_run_block_vector` stops one of
    a plain block. Then the rows R_Q.. read what the encoders will see next tick."""
    for i in range(nb):
        if IB[_at(R_DEAD, i)] != 0:
            continue
        b = b0 + i
        tau2[0], tau2[1] = FB[_at(R_TAU, i)], FB[_at(R_TAU + 1, i)]
        if _mechanics_leg(b, k, dt, X, AI, FR, MECH, DRV, ABORT, _param_row(P, b), tau2, TM[i], INV_VS[i],
                          INV_VSM[i]):
            IB[_at(R_AB, i)] = k
            IB[_at(R_AB + 1, i)] = ABORT_NONFINITE
            IB[_at(R_W0 + W_MODE, i)] = MODE_IDLE
            IB[_at(R_W1 + W_MODE, i)] = MODE_IDLE
            IB[_at(R_DEAD, i)] = 1
        _sensed_rows(b, i, X, FR, FB)


@njit(cache=True, nogil=True)
def _run_block_vector(b0, b1, n_ticks, dt, X, AS, AI, C, P, FR, MECH, DRV, RNG, ABORT, REC, rec_every,
                      rec_offset, plain):
    """Legs b0..b1-1 of :func:`_run` when :func:`_vector_block` allows: the state copied
    into the block's rows, then per tick one loop over the legs for the controllers
    (:func:`_control_vector`) and, when ``plain`` (they share a plain plant,
    :func:`_plain_block`), one for the mechanics (:func:`_mechanics_plain`), both of which
    vectorize: the numbers of :func:`_run_block`. When they share a plant with unmodeled
    effects (:func:`_shared_block`), the mechanics' loops of :func:`_mechanics_effects`,
    which vectorize too: the numbers of :func:`_run_block`. Else
    the mechanics leg by leg (:func:`_mechanics_legs`): the numbers of :func:`_run_block`."""
    nb = b1 - b0
    shared = (not plain) and _shared_block(b0, b1, P, FR, MECH)
    FB = np.zeros(N_FROWS_EFFECTS * LANES)
    IB = np.zeros(N_IROWS * LANES, np.int64)
    # any leg's encoder with a reading error; computed, not grown from the constant False (numba
    # would type the call below for Literal[bool](False) too, and compile _control_vector twice)
    enc = (FR[b0:b1, F_ENC_ON] > 0.0).any()
    # the leg-by-leg mechanics' per-leg invariants and scratch, as kernel._run_block's
    INV_VS, INV_VSM = np.empty(nb), np.empty(nb)
    TM = np.zeros((nb, 2))
    tau2 = np.empty(2)
    f_slots = (S_POS_EST, S_VEL_EST, S_INTEGRATOR, S_IQ, S_IQ_MEAS, S_COUNT_F, S_POS_SP, S_VEL_SP, S_TQ_SP,
               S_IBUS_MOTOR, S_TQ_OUT, S_IQ_SP, S_V_PREV, S_V_INT, S_MECH_P, S_ELEC_P, S_FOC_POWER, S_OSC,
               S_OSC + 1, S_OSC + 2, S_OSC + 3, S_OSC + 4, S_OSC + 5)
    w_slots = (I_MODE, I_AXIS_ERR, I_CTRL_ERR, I_MOTOR_ERR, I_COUNTS)
    for i in range(nb):
        b = b0 + i
        if plain:
            for n in range(5):
                FB[_at(R_Q + n, i)] = X[b, n]
        else:
            _sensed_rows(b, i, X, FR, FB)
        if shared:
            for n in range(N_X):
                FB[_at(R_X + n, i)] = X[b, n]
        INV_VS[i], INV_VSM[i] = 1.0 / FR[b, 6], 1.0 / FR[b, 7]
        IB[_at(R_DEAD, i)] = 1 if ABORT[b, 1] == ABORT_NONFINITE else 0
        IB[_at(R_RNG, i)] = np.int64(RNG[b])
        for a in range(2):
            rv = R_V0 if a == 0 else R_V1
            rk = R_K0 if a == 0 else R_K1
            rw = R_W0 if a == 0 else R_W1
            for n in range(N_VS):
                FB[_at(rv + n, i)] = AS[b, a, f_slots[n]]
            for n in range(N_W):
                IB[_at(rw + n, i)] = AI[b, a, w_slots[n]]
            FB[_at(rv + V_CONN, i)] = float(AI[b, a, I_CONNECTED])
            FB[_at(rv + V_TQP, i)] = float(AI[b, a, I_TQ_PRESENT])
            for n in range(len(K_FROM_C)):
                FB[_at(rk + K_FROM_C[n][0], i)] = C[b, a, K_FROM_C[n][1]]
            kp = 2.0 * C[b, a, C_ENCODER_BW]
            FB[_at(rk + K_KP, i)] = kp
            FB[_at(rk + K_KI, i)] = 0.25 * kp * kp
            kp_cc, ki_cc = current_gains(C[b, a, C_CURRENT_BW], C[b, a, C_PHASE_R], C[b, a, C_PHASE_L], dt)
            FB[_at(rk + K_CCKP, i)] = kp_cc
            FB[_at(rk + K_CCKI, i)] = ki_cc
            FB[_at(rk + K_VMAX, i)] = V_MAX_PER_VBUS * C[b, 0, C_VBUS]
            FB[_at(rk + K_INVKT, i)] = 1.0 / C[b, a, C_KT]
            FB[_at(rk + K_INVCPR, i)] = 1.0 / C[b, a, C_CPR]
        FB[_at(R_G + G_BRAKE_ON, i)] = C[b, 0, C_BRAKE_ON]
        FB[_at(R_G + G_BRAKE_R, i)] = C[b, 0, C_BRAKE_R]
        FB[_at(R_G + G_MAX_REGEN, i)] = C[b, 0, C_MAX_REGEN]
        FB[_at(R_G + G_DCP, i)] = C[b, 0, C_DC_MAX_POS]
        FB[_at(R_G + G_DCN, i)] = C[b, 0, C_DC_MAX_NEG]
        FB[_at(R_G + G_VBUS, i)] = C[b, 0, C_VBUS]
        FB[_at(R_G + G_STYLE, i)] = C[b, 0, C_REGEN_ERR_STYLE]
        FB[_at(R_G + G_FW056, i)] = C[b, 0, C_FW_056]
        FB[_at(R_G + G_INV_VBUS, i)] = 1.0 / C[b, 0, C_VBUS]
        FB[_at(R_G + G_INV_BRAKE_R, i)] = 1.0 / C[b, 0, C_BRAKE_R]
        FB[_at(R_G + G_IBUS, i)] = AS[b, 0, S_IBUS]
        FB[_at(R_G + G_BRAKE_I, i)] = AS[b, 0, S_BRAKE_I]
        IB[_at(R_SYS, i)] = AI[b, 0, I_SYS_ERR]
        IB[_at(R_AB, i)] = ABORT[b, 0]
        IB[_at(R_AB + 1, i)] = ABORT[b, 1]
    P_plain = P[b0:b0 + 1]
    FR_plain = FR[b0:b0 + 1]
    MECH_plain = MECH[b0:b0 + 1]
    n_rec = REC.shape[1]
    next_rec = 0 if rec_every > 0 else -1
    for k in range(n_ticks):
        if k == next_rec:
            next_rec += rec_every
            r = rec_offset + k // rec_every
            if 0 <= r < n_rec:
                for i in range(nb):
                    if IB[_at(R_DEAD, i)] == 0:
                        b = b0 + i
                        REC[b, r, 0] = FB[_at(R_Q + 4, i)]
                        REC[b, r, 1] = FB[_at(R_V0 + V_CNTF, i)]
                        REC[b, r, 2] = FB[_at(R_V1 + V_CNTF, i)]
                        REC[b, r, 3] = FB[_at(R_V0 + V_IQM, i)]
                        REC[b, r, 4] = FB[_at(R_V1 + V_IQM, i)]
        if enc:
            if plain or shared:
                _encoder_errors_shared(nb, FB, IB, FR_plain, DRV)
            else:
                _encoder_errors(b0, nb, FB, IB, FR, DRV)
        _control_vector(k, dt, FB, IB, nb, DRV, enc)
        if shared:
            _mechanics_effects(dt, FB, IB, nb, P_plain, FR_plain, MECH_plain, DRV)
        elif not plain:
            _mechanics_legs(k, dt, b0, nb, FB, IB, X, AI, P, FR, MECH, DRV, ABORT, TM, INV_VS, INV_VSM, tau2)
            continue
        else:
            _mechanics_plain(dt, FB, IB, nb, P_plain, FR_plain)
        for i in range(nb):
            if IB[_at(R_NF, i)] != 0:
                IB[_at(R_AB, i)] = k
                IB[_at(R_AB + 1, i)] = ABORT_NONFINITE
                IB[_at(R_W0 + W_MODE, i)] = MODE_IDLE
                IB[_at(R_W1 + W_MODE, i)] = MODE_IDLE
                IB[_at(R_DEAD, i)] = 1
    for i in range(nb):
        b = b0 + i
        if plain:
            for n in range(5):
                X[b, n] = FB[_at(R_Q + n, i)]
        if shared:
            for n in range(N_X):
                X[b, n] = FB[_at(R_X + n, i)]
        RNG[b] = np.uint64(IB[_at(R_RNG, i)])
        for a in range(2):
            rv = R_V0 if a == 0 else R_V1
            rw = R_W0 if a == 0 else R_W1
            for n in range(N_VS):
                AS[b, a, f_slots[n]] = FB[_at(rv + n, i)]
            for n in range(N_W):
                AI[b, a, w_slots[n]] = IB[_at(rw + n, i)]
            AI[b, a, I_CONNECTED] = int(FB[_at(rv + V_CONN, i)])
            AI[b, a, I_TQ_PRESENT] = int(FB[_at(rv + V_TQP, i)])
        AS[b, 0, S_IBUS] = FB[_at(R_G + G_IBUS, i)]
        AS[b, 0, S_BRAKE_I] = FB[_at(R_G + G_BRAKE_I, i)]
        AI[b, 0, I_SYS_ERR] = IB[_at(R_SYS, i)]
        ABORT[b, 0] = IB[_at(R_AB, i)]
        ABORT[b, 1] = IB[_at(R_AB + 1, i)]
