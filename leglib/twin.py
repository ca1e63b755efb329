"""The virtual leg: a compiled batch simulator of ODrive v3.6 + BLDC + belt + five-bar.

One numba kernel, :func:`_run`, advances a *batch* of legs by a number of 8 kHz ticks.
Per tick and axis it does what the firmware (0.5.x) does: encoder read (quantized at the
configured CPR, with noise), PLL position/velocity estimator, position P -> velocity PI
(velocity limit, integrator with the firmware's anti-windup) -> current loop (first-order
at the current-control bandwidth, current limit, torque constant), fault checks (overspeed,
current-limit violation, watchdog); then the leg's mechanics (exact five-bar with gravity,
the plant's viscous, Coulomb and Stribeck friction, the stop between the upper links) by
semi-implicit Euler. A plant may add what the fitting models do not have, each effect off
at zero (see :class:`leglib.params.PlantParams`): a compliant belt with backlash (the rotors
their own inertias, sub-stepped when stiff, the encoders on the rotors), cogging torque, an
encoder reading error, and LuGre, direction-dependent and drifting friction.

A single experiment is a batch of one and a sweep a batch of many; both go through the same
kernel, so they give identical numbers. Each thread advances a block of up to 16 legs tick
by tick. The common case of a sweep -- a plant without the unmodeled effects, every axis in
position control or IDLE with its inputs passed through, no watchdog -- runs vectorized
(:func:`_run_block_vector`): the block's state copied into rows by leg, then per tick one
loop over the legs for the controllers and one for the mechanics, branch-free, which the
compiler turns into SIMD code over 8 legs at a time. Every other block runs leg by leg
(:func:`_run_block`, the reference: calibration, torque and filtered modes, trajectories,
the watchdog, the unmodeled effects). Both paths do the same operations in the same order,
so a leg's numbers do not depend on its block or path (tests/test_twin.py checks it bit for
bit). :class:`Twin` holds the batch state and exposes ``advance`` and the whole-experiment
runners; :mod:`leglib.virtual_odrive` puts the ODrive object tree on top of a batch of one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import get_num_threads, njit, prange, set_parallel_chunksize

from .drive import AxisMap
from .kernelmath import py_max, py_min, select
from .kernelmath import sincos as _sincos
from .kernelmath import tanh as _tanh
from .model import _fivebar_reduced, param_vector
from .params import (LegParams, MotorParams, OdriveConfig, PlantParams, load_motor,
                     load_odrive_config, load_plant)

TICK_HZ_DEFAULT = 8000.0

# axis modes inside the kernel (control_mode values of the firmware; 0 = not in closed loop;
# MODE_CALIB: armed by a calibration, the rotor locked to an electrical angle that the axis
# state machine of leglib.virtual_odrive moves)
MODE_IDLE, MODE_TORQUE, MODE_VELOCITY, MODE_POSITION, MODE_CALIB = 0, 1, 2, 3, 4
# controller.config.input_mode values (firmware enums)
INPUT_MODE_INACTIVE, INPUT_MODE_PASSTHROUGH, INPUT_MODE_POS_FILTER, INPUT_MODE_TRAP_TRAJ = 0, 1, 3, 5

# float config per axis: C[b, axis, k]
(C_POS_GAIN, C_VEL_GAIN, C_VEL_INT_GAIN, C_VEL_LIMIT, C_VEL_TOL, C_CURRENT_LIM, C_KT,
 C_INPUT_POS, C_INPUT_VEL, C_INPUT_TORQUE, C_WD_TIMEOUT, C_CURRENT_BW, C_ENCODER_BW,
 C_ABORT_ERROR, C_WD_ENABLE, C_COUNT_OFFSET, C_VEL_INT_LIMIT, C_INPUT_MODE, C_FILTER_BW,
 C_TT_XI, C_TT_XF, C_TT_VI, C_TT_AR, C_TT_VR, C_TT_DR, C_TT_TA, C_TT_TV, C_TT_TD, C_TT_YACC,
 C_CAL_VEL, C_CAL_CURRENT, C_INT_RESET_TORQUE, C_CAL_RAMP) = range(33)
# system (board) configuration, kept in the slots of axis 0: C[b, 0, k]
(C_BRAKE_ON, C_BRAKE_R, C_MAX_REGEN, C_DC_MAX_POS, C_DC_MAX_NEG, C_VBUS, C_REGEN_ERR_STYLE) = range(33, 40)
N_CFG = 40
# float state per axis: AS[b, axis, k]
S_POS_EST, S_VEL_EST, S_INTEGRATOR, S_IQ, S_WD_TIMER, S_IQ_MEAS = range(6)
S_OSC = 6           # N_OSC slots of the oscillation monitor (see oscillation_update)
N_OSC = 6
S_COUNT_F = S_OSC + N_OSC  # the encoder reading as a float (equal to the counts when quantized)
(S_POS_SP, S_VEL_SP, S_TQ_SP, S_TT_T, S_CAL_POS, S_IBUS_MOTOR, S_CAL_I) = range(S_COUNT_F + 1, S_COUNT_F + 8)
# system state in the slots of axis 0: the reported bus current and the brake current [A]
S_IBUS, S_BRAKE_I = S_COUNT_F + 8, S_COUNT_F + 9
N_AXSTATE = S_COUNT_F + 10
# int state per axis: AI[b, axis, k]; I_SYS_ERR is the board's error (odrv.error), on axis 0
I_MODE, I_AXIS_ERR, I_CTRL_ERR, I_MOTOR_ERR, I_COUNTS, I_TRAJ_DONE, I_SYS_ERR = range(7)
N_AXINT = 7
# firmware error codes (odrive.enums values)
AXIS_ERROR_MOTOR_FAILED = 0x40
AXIS_ERROR_CONTROLLER_FAILED = 0x200
AXIS_ERROR_WATCHDOG_TIMER_EXPIRED = 0x800
CONTROLLER_ERROR_OVERSPEED = 0x1
MOTOR_ERROR_CURRENT_LIMIT_VIOLATION = 0x1000
MOTOR_ERROR_DC_BUS_OVER_REGEN_CURRENT = 0x4000      # 0.5.1: the bus faults land on the motors
MOTOR_ERROR_DC_BUS_OVER_CURRENT = 0x8000
MOTOR_ERROR_SYSTEM_LEVEL = 0x1000000                # 0.5.2+: motors disarmed by a board fault
ODRIVE_ERROR_DC_BUS_OVER_CURRENT = 0x4              # 0.5.2+: odrv.error
ODRIVE_ERROR_DC_BUS_OVER_REGEN_CURRENT = 0x8
CURRENT_LIM_MARGIN = 8.0  # A, firmware default motor.config.current_lim_margin
# the leg's state X[b, k]: joints, time, then the unmodeled effects' state (see _run)
X_Q1, X_DQ1, X_Q2, X_DQ2, X_T = range(5)
X_PHI1, X_DPHI1, X_PHI2, X_DPHI2 = range(5, 9)   # rotor angles on the joint side (compliant belt)
X_Z1, X_Z2 = 9, 10                               # LuGre bristle deflections [rad]
X_TRAVEL1, X_TRAVEL2 = 11, 12                    # accumulated joint travel [rad] (friction drift)
N_X = 13
# plant parameters FR[b, k] beyond the joints' friction (k < 14; see _run): the unmodeled
# effects, each off at zero
(F_BELT_K, F_BELT_C, F_BACKLASH_HALF, F_JM, F_BELT_SUB, F_COG_ON, F_COG_PERIODS, F_COG_A1, F_COG_A2,
 F_COG_A3, F_COG_P1, F_COG_P2, F_COG_P3, F_ENC_ON, F_ENC_A1, F_ENC_P1, F_ENC_A2, F_ENC_P2, F_FRIC_EXT,
 F_LUGRE_S0, F_LUGRE_S1, F_ASYM, F_DRIFT, F_DRIFT_TRAVEL) = range(14, 38)
N_FR = 38
# legs per vector of the plain mechanics (see _run_block): 8 doubles fill an AVX-512
# register, two AVX2 ones; a block of legs is one or two of these (a block that is not a
# multiple leaves legs to the slower scalar remainder of the loop; more legs than 16 leave
# the L1 cache)
VECTOR_LEGS = 8
# a compliant belt is sub-stepped so that its mode advances at most this many radians a step
BELT_PHASE_PER_STEP = 0.3
# leglib's own abort codes (ABORT[b, 1])
ABORT_NONE, ABORT_POSITION_ERROR, ABORT_NONFINITE, ABORT_OSCILLATION = 0, 1, 2, 3
OSC_HALF_CYCLES = 3  # consecutive non-decaying half-cycles that count as unstable
OSC_GROWTH = 1.1     # a half-cycle this much larger than the first overshoot: growing
OSC_DECAY = 0.95     # a half-cycle at least this fraction of the previous one is "not decaying"
                     # (a stable response decays by exp(-pi zeta / sqrt(1 - zeta^2)) per
                     # half-cycle: 0.95 flags zeta below about 0.016)


# ---------------------------------------------------------------------------------------
# random numbers: a per-leg xorshift64* stream, so results do not depend on threading
# ---------------------------------------------------------------------------------------

# The state is passed and returned (the kernel keeps it in a register over its tick loop).

@njit(cache=True, inline="always")
def _next_u64(x):
    """One xorshift64* step of state ``x``: (new state, 64 output bits)."""
    x ^= x >> np.uint64(12)
    x ^= x << np.uint64(25)
    x ^= x >> np.uint64(27)
    return x, x * np.uint64(2685821657736338717)


@njit(cache=True, inline="always")
def _normal(x):
    """(new state, a normal deviate) from one step: the Irwin-Hall sum of four uniforms, the
    output's top 52 bits as four 13-bit integers k_i, u_i = (k_i + 1/2) / 2^13 (mean 1/2 exactly),
    scaled to unit variance; bounded by +-2 sqrt(3), cheap and adequate for noise."""
    x, r = _next_u64(x)
    m = np.uint64(0x1FFF)
    k = (np.int64((r >> np.uint64(12)) & m) + np.int64((r >> np.uint64(25)) & m)
         + np.int64((r >> np.uint64(38)) & m) + np.int64(r >> np.uint64(51)))
    return x, (float(k) + 2.0 - 2.0 * 8192.0) * (1.7320508075688772 / 8192.0)


# ---------------------------------------------------------------------------------------
# the oscillation monitor (also used by odrive_io's polling loop on a real device)
# ---------------------------------------------------------------------------------------

@njit(cache=True, inline="always")
def _oscillation_step(amp, prev, sgn0, count, halves, first, err, min_amp):
    """One sample of :func:`oscillation_update` on its six slots, passed and returned as
    scalars: (amp, prev, sgn0, count, halves, first, unstable). Written with selects, not
    branches (the kernel's loop over legs calls it and vectorizes)."""
    sgn = select(err > 0, 1.0, -1.0)
    sgn0 = select(sgn0 == 0.0, sgn, sgn0)
    flip = sgn != sgn0                      # a half-cycle ends
    halves_f = halves + 1.0
    first_f = select(halves_f == 2.0, amp, first)
    flagged = flip & (halves_f >= 3.0) & (amp > min_amp) & (amp > OSC_GROWTH * first_f)
    steady = (amp > min_amp) & (halves_f >= 2.0) & (prev > 0.0) & (amp >= OSC_DECAY * prev)
    counted = count + 1.0
    count_f = select(steady, counted, 0.0)
    halves = select(flip, halves_f, halves)
    first = select(flip, first_f, first)
    count = select(flip, count_f, count)
    prev = select(flip, amp, prev)
    amp = select(flip, 0.0, amp)
    sgn0 = select(flip, sgn, sgn0)
    e = abs(err)
    amp = select(e > amp, e, amp)
    return amp, prev, sgn0, count, halves, first, flagged | (count >= OSC_HALF_CYCLES)


@njit(cache=True)
def oscillation_update(st, err, min_amp):
    """Feed one position-error sample; True when the oscillation is growing or not decaying.

    ``st`` (N_OSC,) starts at zeros and holds: the largest |err| of the current half-cycle,
    the previous half-cycle's amplitude, the current sign, the count of consecutive
    non-decaying half-cycles, the number of half-cycles, and the first overshoot. A
    half-cycle ends when the error changes sign (the first one is the approach to the
    target, the second the first overshoot). Unstable when, with amplitudes above
    ``min_amp``, a later half-cycle exceeds OSC_GROWTH times the first overshoot (a damped
    response never grows past it), or OSC_HALF_CYCLES half-cycles in a row keep at least
    OSC_DECAY of the previous amplitude.
    """
    st[0], st[1], st[2], st[3], st[4], st[5], unstable = _oscillation_step(
        st[0], st[1], st[2], st[3], st[4], st[5], err, min_amp)
    return unstable


@njit(cache=True, inline="always")
def _oscillation_update_at(AS, b, a, err, min_amp):
    """:func:`oscillation_update` on the monitor of axis ``a`` of leg ``b`` in place
    (AS[b, a, S_OSC:S_OSC + N_OSC], without a slice per tick)."""
    o = S_OSC
    (AS[b, a, o], AS[b, a, o + 1], AS[b, a, o + 2], AS[b, a, o + 3], AS[b, a, o + 4], AS[b, a, o + 5],
     unstable) = _oscillation_step(AS[b, a, o], AS[b, a, o + 1], AS[b, a, o + 2], AS[b, a, o + 3],
                                   AS[b, a, o + 4], AS[b, a, o + 5], err, min_amp)
    return unstable


# ---------------------------------------------------------------------------------------
# friction
# ---------------------------------------------------------------------------------------

@njit(cache=True, inline="always")
def _stribeck(excess, u):
    """excess * exp(-u^2), the Stribeck term; 0 without the call when there is none or
    when exp underflows (u^2 > 750)."""
    u2 = u * u
    if excess == 0.0 or u2 > 750.0:
        return 0.0 * excess
    return excess * math.exp(-u2)


# ---------------------------------------------------------------------------------------
# the plant's unmodeled effects (plant_*.toml [belt], [cogging], [encoder_error], [friction]);
# each is called from the kernel only when its plant parameters switch it on
# ---------------------------------------------------------------------------------------

@njit(cache=True, inline="always")
def _motor_angle(X, FR, b, j):
    """The angle the motor of joint ``j`` is at, on the joint side [rad]: the rotor's with a
    compliant belt, the joint's with a rigid one."""
    if FR[b, F_BELT_K] > 0.0:
        return X[b, X_PHI1 + 2 * j]
    return X[b, 2 * j]


@njit(cache=True, inline="always")
def _encoder_error(FR, b, turns):
    """Reading error [turn] of a magnetic encoder at rotor angle ``turns``: once per turn
    (magnet eccentricity, offsets) and twice per turn (amplitude mismatch of the sine and
    cosine channels)."""
    th = 2.0 * math.pi * turns
    err = FR[b, F_ENC_A1] * math.sin(th + FR[b, F_ENC_P1]) + FR[b, F_ENC_A2] * math.sin(2.0 * th + FR[b, F_ENC_P2])
    return err / (2.0 * math.pi)


@njit(cache=True, inline="always")
def _cogging_torque(FR, b, turns):
    """Cogging torque on the rotor [N*m, motor side] at rotor angle ``turns``: harmonics 1-3
    of the cogging period (FR[b, F_COG_PERIODS] periods per turn). A sum of sines: it has a
    potential, so it stores no energy over a period."""
    th = 2.0 * math.pi * FR[b, F_COG_PERIODS] * turns
    return (FR[b, F_COG_A1] * math.sin(th + FR[b, F_COG_P1]) + FR[b, F_COG_A2] * math.sin(2.0 * th + FR[b, F_COG_P2])
            + FR[b, F_COG_A3] * math.sin(3.0 * th + FR[b, F_COG_P3]))


@njit(cache=True, inline="always")
def _add_cogging(b, X, FR, DRV, tau):
    """Add each motor's cogging torque, reflected to the joint side, to ``tau`` (the motor
    torques): it acts in every axis state, IDLE included."""
    for j in range(2):
        turns = DRV[2] * (_motor_angle(X, FR, b, j) - DRV[3 + j]) * DRV[0] / (2.0 * math.pi)
        tau[j] += DRV[2] * DRV[0] * _cogging_torque(FR, b, turns)


@njit(cache=True, inline="always")
def _belt_torque(FR, b, stretch, rate):
    """Torque the belt puts on the joint [N*m]: stiffness times the stretch ``stretch`` =
    phi - q less the backlash dead zone, plus damping times ``rate`` = dphi - dq."""
    h = FR[b, F_BACKLASH_HALF]
    if stretch > h:
        stretch -= h
    elif stretch < -h:
        stretch += h
    else:
        stretch = 0.0
    return FR[b, F_BELT_K] * stretch + FR[b, F_BELT_C] * rate


@njit(cache=True, inline="always")
def _belt_split(b, X, FR, tau, tm):
    """Compliant belt: the motor torques ``tau`` (joint side) move to the rotors (``tm``);
    the joints get the belt's torques instead."""
    for j in range(2):
        tm[j] = tau[j]
        tau[j] = _belt_torque(FR, b, X[b, X_PHI1 + 2 * j] - X[b, 2 * j], X[b, X_DPHI1 + 2 * j] - X[b, 2 * j + 1])


@njit(cache=True, inline="always")
def _belt_advance(b, dt, X, FR, tm, tau, a1, a2, d11, d12, d22):
    """One tick of joints and rotors coupled by the belt, semi-implicit Euler in
    FR[b, F_BELT_SUB] sub-steps: ``a1``, ``a2`` are the joints' accelerations with the belt
    torques ``tau`` of the tick's start; the rest of them (gravity, friction, stops) is held
    over the tick while the belt coupling is re-evaluated every sub-step."""
    n = int(FR[b, F_BELT_SUB])
    h = dt / n
    jm = FR[b, F_JM]
    det = d11 * d22 - d12 * d12
    o1 = a1 - (d22 * tau[0] - d12 * tau[1]) / det
    o2 = a2 - (-d12 * tau[0] + d11 * tau[1]) / det
    q1, dq1, q2, dq2 = X[b, X_Q1], X[b, X_DQ1], X[b, X_Q2], X[b, X_DQ2]
    p1, dp1, p2, dp2 = X[b, X_PHI1], X[b, X_DPHI1], X[b, X_PHI2], X[b, X_DPHI2]
    for _ in range(n):
        t1 = _belt_torque(FR, b, p1 - q1, dp1 - dq1)
        t2 = _belt_torque(FR, b, p2 - q2, dp2 - dq2)
        dq1 += (o1 + (d22 * t1 - d12 * t2) / det) * h
        dq2 += (o2 + (-d12 * t1 + d11 * t2) / det) * h
        dp1 += (tm[0] - t1) / jm * h
        dp2 += (tm[1] - t2) / jm * h
        q1 += dq1 * h
        q2 += dq2 * h
        p1 += dp1 * h
        p2 += dp2 * h
    X[b, X_Q1], X[b, X_DQ1], X[b, X_Q2], X[b, X_DQ2] = q1, dq1, q2, dq2
    X[b, X_PHI1], X[b, X_DPHI1], X[b, X_PHI2], X[b, X_DPHI2] = p1, dp1, p2, dp2
    X[b, X_T] += dt


@njit(cache=True, inline="always")
def _joint_friction(b, dt, X, FR, j, v):
    """Friction torque [N*m] on joint ``j`` at velocity ``v`` beyond the tanh model: Coulomb
    levels coulomb * (1 +- asymmetry) by direction, all levels scaled by the drift factor
    1 - drift (1 - exp(-travel / drift_travel)), and with LuGre (sigma0 > 0) presliding
    bristles z: dz/dt = v - sigma0 |v| z / g(v), F = sigma0 z + sigma1 dz/dt + viscous v,
    integrated exactly for v constant over the tick (unconditionally stable). Updates the
    joint's z and travel in X."""
    travel = X[b, X_TRAVEL1 + j]
    s = 1.0 - FR[b, F_DRIFT] * (1.0 - math.exp(-travel / FR[b, F_DRIFT_TRAVEL]))
    X[b, X_TRAVEL1 + j] = travel + abs(v) * dt
    sgn = 1.0 if v > 0.0 else -1.0
    g = s * (1.0 + sgn * FR[b, F_ASYM]) * (FR[b, 2 + j] + FR[b, 4 + j] * math.exp(-(v / FR[b, 6]) ** 2))
    visc = s * FR[b, j] * v
    s0 = FR[b, F_LUGRE_S0]
    if s0 <= 0.0:
        return visc + g * math.tanh(v / FR[b, 7])
    z = X[b, X_Z1 + j]
    z_new = z
    if v != 0.0:
        z_ss = sgn * g / s0
        z_new = z_ss + (z - z_ss) * math.exp(-s0 * abs(v) * dt / g)
    X[b, X_Z1 + j] = z_new
    return s0 * z_new + FR[b, F_LUGRE_S1] * (z_new - z) / dt + visc


# ---------------------------------------------------------------------------------------
# the kernel
# ---------------------------------------------------------------------------------------

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
    plain = _plain_block(b0, b1, P, FR, MECH)
    if plain and _vector_block(b0, b1, FR, C, AI):
        _run_block_vector(b0, b1, n_ticks, dt, X, AS, AI, C, P, FR, DRV, RNG, ABORT, REC, rec_every,
                          rec_offset)
    elif plain:
        _run_block(b0, b1, n_ticks, dt, X, AS, AI, C, P, FR, MECH, DRV, RNG, ABORT, TT, tt_period, REC,
                   rec_every, rec_offset, True)
    else:   # one leg at a time: its state stays in the cache over the ticks
        for b in range(b0, b1):
            _run_block(b, b + 1, n_ticks, dt, X, AS, AI, C, P, FR, MECH, DRV, RNG, ABORT, TT, tt_period,
                       REC, rec_every, rec_offset, False)


@njit(cache=True, inline="always")
def _param_row(P, b):
    """Row ``b`` of P (the 19 entries of ``derivation.PARAM_NAMES``) as a tuple: loaded once
    per call, so the five-bar's constant terms leave the tick loop."""
    return (P[b, 0], P[b, 1], P[b, 2], P[b, 3], P[b, 4], P[b, 5], P[b, 6], P[b, 7], P[b, 8], P[b, 9],
            P[b, 10], P[b, 11], P[b, 12], P[b, 13], P[b, 14], P[b, 15], P[b, 16], P[b, 17], P[b, 18])


@njit(cache=True)
def _plain_block(b0, b1, P, FR, MECH):
    """Whether legs b0..b1-1 share one plain plant (see :func:`_mechanics_plain`)."""
    for b in range(b0, b1):
        if MECH[b] != 0 or FR[b, F_BELT_K] > 0.0 or FR[b, F_COG_ON] > 0.0 or FR[b, F_FRIC_EXT] > 0.0:
            return False
        if FR[b, 4] != 0.0 or FR[b, 5] != 0.0:
            return False
        for n in range(P.shape[1]):
            if P[b, n] != P[b0, n]:
                return False
        for n in range(FR.shape[1]):
            if FR[b, n] != FR[b0, n]:
                return False
    return True


@njit(cache=True, error_model="numpy")
def _mechanics_plain(dt, FB, IB, nb, P, FR):
    """One tick of the mechanics of a block of ``nb`` legs that share one plain plant (the
    exact five-bar, rigid belts, tanh friction without a Stribeck term, no cogging): the
    operations of :func:`_mechanics_leg` in the same order, written with selects instead of
    branches so that this loop over the legs vectorizes; the numbers are identical. The
    legs' joints, time and torques are rows of FB (see :data:`R_Q`, :data:`R_TAU`); a dead
    leg (IB row R_DEAD) keeps its state; IB row R_NF is set where the accelerations came
    out non-finite (the caller stops the leg)."""
    Pb = _param_row(P, 0)
    visc1, visc2, coul1, coul2 = FR[0, 0], FR[0, 1], FR[0, 2], FR[0, 3]
    strib1, strib2 = 0.0 * FR[0, 4], 0.0 * FR[0, 5]     # what _stribeck gives without one
    inv_v_smooth = 1.0 / FR[0, 7]
    gap_min, k_stop, c_stop, gap_max = FR[0, 8], FR[0, 9], FR[0, 10], FR[0, 13]
    for i in range(nb):
        q1, dq1 = FB[_at(R_Q, i)], FB[_at(R_Q + 1, i)]
        q2, dq2 = FB[_at(R_Q + 2, i)], FB[_at(R_Q + 3, i)]
        t = FB[_at(R_Q + 4, i)]
        s_q1, c_q1 = _sincos(q1)
        s_q2, c_q2 = _sincos(q2)
        r5 = _fivebar_reduced(c_q1, s_q1, c_q2, s_q2, dq1, dq2, Pb)
        d11, d12, d22, b1, b2 = r5[0], r5[1], r5[2], r5[3], r5[4]
        f1 = visc1 * dq1 + (coul1 + strib1) * _tanh(dq1 * inv_v_smooth)
        f2 = visc2 * dq2 + (coul2 + strib2) * _tanh(dq2 * inv_v_smooth)
        t1 = FB[_at(R_TAU, i)] - b1 - f1
        t2 = FB[_at(R_TAU + 1, i)] - b2 - f2
        gap = q2 - q1
        push = k_stop * (gap_min - gap) - c_stop * (dq2 - dq1)
        pull = k_stop * (gap - gap_max) + c_stop * (dq2 - dq1)
        pushing = (gap < gap_min) & (push > 0.0)
        pulling = (not (gap < gap_min)) & (gap > gap_max) & (pull > 0.0)
        t1 = (t1 - push) if pushing else ((t1 + pull) if pulling else t1)
        t2 = (t2 + push) if pushing else ((t2 - pull) if pulling else t2)
        det = d11 * d22 - d12 * d12
        inv_det = 1.0 / det
        a1 = (d22 * t1 - d12 * t2) * inv_det
        a2 = (-d12 * t1 + d11 * t2) * inv_det
        alive = IB[_at(R_DEAD, i)] == 0
        ok = math.isfinite(a1) & math.isfinite(a2)
        IB[_at(R_NF, i)] = 1 if (alive & (not ok)) else 0
        go = alive & ok
        dq1n = dq1 + a1 * dt
        dq2n = dq2 + a2 * dt
        FB[_at(R_Q, i)] = (q1 + dq1n * dt) if go else q1
        FB[_at(R_Q + 1, i)] = dq1n if go else dq1
        FB[_at(R_Q + 2, i)] = (q2 + dq2n * dt) if go else q2
        FB[_at(R_Q + 3, i)] = dq2n if go else dq2
        FB[_at(R_Q + 4, i)] = (t + dt) if go else t


@njit(cache=True, inline="always")
def _mechanics_leg(b, k, dt, X, AI, FR, MECH, DRV, ABORT, Pb, tau, tm, inv_v_stribeck, inv_v_smooth):
    """One tick of leg ``b``'s mechanics, any plant (the belt, cogging and friction effects,
    independent inertias), ``tau`` the motor torques on the joint side; X updated in place.
    True when the accelerations were not finite (the leg is stopped: ABORT, axes IDLE)."""
    if FR[b, F_COG_ON] > 0.0:           # cogging on the rotors (plant [cogging])
        _add_cogging(b, X, FR, DRV, tau)
    if FR[b, F_BELT_K] > 0.0:           # compliant belt: the joints get the belt's torques
        _belt_split(b, X, FR, tau, tm)
    q1, dq1, q2, dq2 = X[b, 0], X[b, 1], X[b, 2], X[b, 3]
    if MECH[b] == 0:
        s_q1, c_q1 = _sincos(q1)
        s_q2, c_q2 = _sincos(q2)
        r5 = _fivebar_reduced(c_q1, s_q1, c_q2, s_q2, dq1, dq2, Pb)
        d11, d12, d22, b1, b2 = r5[0], r5[1], r5[2], r5[3], r5[4]
    else:
        d11, d12, d22, b1, b2 = FR[b, 11], 0.0, FR[b, 12], 0.0, 0.0
    if FR[b, F_FRIC_EXT] > 0.0:         # asymmetric, LuGre, drifting friction (plant [friction])
        f1 = _joint_friction(b, dt, X, FR, 0, dq1)
        f2 = _joint_friction(b, dt, X, FR, 1, dq2)
    else:
        f1 = FR[b, 0] * dq1 + (FR[b, 2] + _stribeck(FR[b, 4], dq1 * inv_v_stribeck)) * _tanh(dq1 * inv_v_smooth)
        f2 = FR[b, 1] * dq2 + (FR[b, 3] + _stribeck(FR[b, 5], dq2 * inv_v_stribeck)) * _tanh(dq2 * inv_v_smooth)
    t1 = tau[0] - b1 - f1
    t2 = tau[1] - b2 - f2
    if MECH[b] == 0:
        gap = q2 - q1
        if gap < FR[b, 8]:
            push = FR[b, 9] * (FR[b, 8] - gap) - FR[b, 10] * (dq2 - dq1)
            if push > 0.0:
                t1 -= push
                t2 += push
        elif gap > FR[b, 13]:
            pull = FR[b, 9] * (gap - FR[b, 13]) + FR[b, 10] * (dq2 - dq1)
            if pull > 0.0:
                t1 += pull
                t2 -= pull
    det = d11 * d22 - d12 * d12
    inv_det = 1.0 / det
    a1 = (d22 * t1 - d12 * t2) * inv_det
    a2 = (-d12 * t1 + d11 * t2) * inv_det
    if not (math.isfinite(a1) and math.isfinite(a2)):
        ABORT[b, 0] = k
        ABORT[b, 1] = ABORT_NONFINITE
        for a in range(2):
            AI[b, a, I_MODE] = MODE_IDLE
        return True
    if FR[b, F_BELT_K] > 0.0:           # compliant belt: joints and rotors advance together
        _belt_advance(b, dt, X, FR, tm, tau, a1, a2, d11, d12, d22)
        return False
    dq1 += a1 * dt
    dq2 += a2 * dt
    X[b, 0] = q1 + dq1 * dt
    X[b, 1] = dq1
    X[b, 2] = q2 + dq2 * dt
    X[b, 3] = dq2
    X[b, 4] += dt
    return False


# ---------------------------------------------------------------------------------------
# a block's working copy of its legs' state, laid out by leg (structure of arrays): FB
# (float) and IB (int) hold rows of LANES entries, one per leg of the block, at rows fixed
# at compile time, so the compiler sees that the rows do not overlap and vectorizes the
# loops over the legs without run-time checks
# ---------------------------------------------------------------------------------------

LANES = 2 * VECTOR_LEGS   # the most legs in a block
# float rows: the joints and time, the motor torques, then (vectorized block only) per axis
# its state (V_) and configuration (K_), and the board's (G_)
R_Q = 0                   # q1, dq1, q2, dq2, t (the X_ order)
R_TAU = 5                 # joint 0, joint 1 [N*m] on the joint side
(V_PE, V_VE, V_INT, V_IQ, V_IQM, V_CNTF, V_PSP, V_VSP, V_TSP, V_IBM) = range(10)
V_OSC = 10
N_V = V_OSC + N_OSC
(K_OFF, K_KP, K_KI, K_VL, K_VTOL, K_IPOS, K_IVEL, K_ITQ, K_KT, K_VG, K_CLIM, K_AE, K_PG, K_VIG,
 K_VIL, K_ALPHA, K_INVKT) = range(17)
N_K = 17
# the configuration rows copied as they are: (K_ row, C_ slot)
K_FROM_C = ((K_OFF, C_COUNT_OFFSET), (K_VL, C_VEL_LIMIT), (K_VTOL, C_VEL_TOL), (K_IPOS, C_INPUT_POS),
            (K_IVEL, C_INPUT_VEL), (K_ITQ, C_INPUT_TORQUE), (K_KT, C_KT), (K_VG, C_VEL_GAIN),
            (K_CLIM, C_CURRENT_LIM), (K_AE, C_ABORT_ERROR), (K_PG, C_POS_GAIN), (K_VIG, C_VEL_INT_GAIN),
            (K_VIL, C_VEL_INT_LIMIT))
(G_BRAKE_ON, G_BRAKE_R, G_MAX_REGEN, G_DCP, G_DCN, G_VBUS, G_STYLE, G_INV_VBUS, G_INV_BRAKE_R, G_IBUS,
 G_BRAKE_I, G_IBUS_AXES) = range(12)
N_G = 12
R_V0, R_V1 = 7, 7 + N_V                       # axis 0, axis 1
R_K0, R_K1 = 7 + 2 * N_V, 7 + 2 * N_V + N_K
R_G = 7 + 2 * N_V + 2 * N_K
N_FROWS = R_G + N_G
# int rows: per axis (W_), then per leg
W_MODE, W_AXERR, W_CTRLERR, W_MOTERR, W_COUNTS = range(5)
N_W = 5
R_W0, R_W1 = 0, N_W
R_DEAD = 2 * N_W          # 1: stopped for good (non-finite mechanics)
R_NF = R_DEAD + 1         # set by the mechanics: non-finite this tick
R_SYS = R_DEAD + 2        # the board's error
R_AB = R_DEAD + 3         # abort tick, abort reason
R_RNG = R_DEAD + 5        # the noise stream's state (its bits)
R_CODE = R_DEAD + 6       # the abort code the axes raised this tick
N_IROWS = R_CODE + 1


@njit(cache=True, inline="always")
def _at(row, i):
    """Index of leg ``i`` in row ``row`` of a block's FB or IB; unsigned, so the compiler
    adds no wraparound of negative indices (which hides the rows' independence)."""
    return np.uint64(row * LANES + i)


@njit(cache=True)
def _vector_block(b0, b1, FR, C, AI):
    """Whether legs b0..b1-1 of a plain block (see :func:`_plain_block`) can take
    :func:`_run_block_vector`: no encoder reading error, and every axis in position control
    or IDLE with its inputs passed through and no watchdog."""
    for b in range(b0, b1):
        if FR[b, F_ENC_ON] > 0.0:
            return False
        for a in range(2):
            mode = AI[b, a, I_MODE]
            if mode != MODE_IDLE and mode != MODE_POSITION:
                return False
            if C[b, a, C_INPUT_MODE] != INPUT_MODE_PASSTHROUGH or C[b, a, C_WD_ENABLE] > 0.0:
                return False
    return True


@njit(cache=True, inline="always")
def _axis_vector(i, a, FB, IB, q, q_rest, rng, alive, dt, dirn, turns_per_rad, cpr, inv_cpr, enc_noise,
                 cur_noise, quantize, N, kt_true, r_phase, inv_vbus):
    """One tick of axis ``a`` (a constant) of leg ``i`` of a vectorized block, its joint at
    ``q``: what the per-leg controller of :func:`_run_block` does for an axis in position
    control or IDLE with passthrough inputs, the same operations in the same order,
    branches turned into selects. Returns (rng, joint torque, bus current, abort code)."""
    rv, rk, rw = R_V0 + a * N_V, R_K0 + a * N_K, R_W0 + a * N_W
    # encoder and PLL: every tick, IDLE included
    turns = dirn * (q - q_rest) * turns_per_rad
    rng1, nz = _normal(rng)
    raw = turns * cpr + enc_noise * nz
    off = FB[_at(rk + K_OFF, i)]
    rounded = math.floor(raw + 0.5)
    counts = select(quantize, rounded, raw) + off
    kp = FB[_at(rk + K_KP, i)]
    ki = FB[_at(rk + K_KI, i)]
    pe0 = FB[_at(rv + V_PE, i)]
    ve0 = FB[_at(rv + V_VE, i)]
    pe = pe0 + dt * ve0
    delta = counts * inv_cpr - pe
    pe += dt * kp * delta
    ve = ve0 + dt * ki * delta
    below = abs(ve) < 0.5 * dt * ki * inv_cpr
    ve = select(below, 0.0, ve)
    # the board's check, then overspeed
    mode0 = IB[_at(rw + W_MODE, i)]
    axis_err0 = IB[_at(rw + W_AXERR, i)]
    mode = select(axis_err0 != 0, MODE_IDLE, mode0)
    vel_limit = FB[_at(rk + K_VL, i)]
    over = (mode != MODE_IDLE) & (abs(ve) > vel_limit * FB[_at(rk + K_VTOL, i)])
    ctrl_err = IB[_at(rw + W_CTRLERR, i)] | select(over, CONTROLLER_ERROR_OVERSPEED, 0)
    axis_err = axis_err0 | select(over, AXIS_ERROR_CONTROLLER_FAILED, 0)
    active = (mode != MODE_IDLE) & (not over)
    # position control with passthrough inputs
    pos_sp = FB[_at(rk + K_IPOS, i)]
    vel_in = FB[_at(rk + K_IVEL, i)]
    tq_in = FB[_at(rk + K_ITQ, i)]
    kt = FB[_at(rk + K_KT, i)]
    vel_gain = FB[_at(rk + K_VG, i)]
    current_lim = FB[_at(rk + K_CLIM, i)]
    t_lim = current_lim * kt
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
    vel_sp = py_min(py_max(vel_in, -vel_limit), vel_limit)
    vel_des = FB[_at(rk + K_PG, i)] * (pos_sp - pe) + vel_sp
    vel_des = py_min(py_max(vel_des, -vel_limit), vel_limit)
    verr = vel_des - ve
    integ0 = FB[_at(rv + V_INT, i)]
    torque = vel_gain * verr + integ0 + tq_in
    limited = (torque > t_lim) | (torque < -t_lim)
    neg_t_lim = -t_lim
    torque = select(torque > t_lim, t_lim, select(torque < neg_t_lim, neg_t_lim, torque))
    decayed = integ0 * 0.99
    grown = integ0 + FB[_at(rk + K_VIG, i)] * dt * verr
    integ = select(limited, decayed, grown)
    lim = FB[_at(rk + K_VIL, i)]
    integ = py_min(py_max(integ, -lim), lim)
    iq0 = FB[_at(rv + V_IQ, i)]
    iq = iq0 + FB[_at(rk + K_ALPHA, i)] * (torque * FB[_at(rk + K_INVKT, i)] - iq0)
    rng2, nz = _normal(rng1)
    iq_meas = iq + cur_noise * nz
    violated = active & (abs(iq_meas) > current_lim + CURRENT_LIM_MARGIN)
    motor_err = IB[_at(rw + W_MOTERR, i)] | select(violated, MOTOR_ERROR_CURRENT_LIMIT_VIOLATION, 0)
    axis_err = axis_err | select(violated, AXIS_ERROR_MOTOR_FAILED, 0)
    iq = select(violated, 0.0, iq)
    tau = dirn * N * kt_true * iq
    w = ve * (2.0 * math.pi)
    ib = (1.5 * r_phase * iq * iq + kt_true * iq * w) * inv_vbus
    # write back: a dead leg keeps everything; an IDLE axis zeroes its outputs (the old
    # values loaded first: a select between two loaded values vectorizes, a load
    # under a condition does not)
    cntf0 = FB[_at(rv + V_CNTF, i)]
    counts_i0 = IB[_at(rw + W_COUNTS, i)]
    iqm0 = FB[_at(rv + V_IQM, i)]
    ibm0 = FB[_at(rv + V_IBM, i)]
    psp0, vsp0, tsp0 = FB[_at(rv + V_PSP, i)], FB[_at(rv + V_VSP, i)], FB[_at(rv + V_TSP, i)]
    ctrl_err0 = IB[_at(rw + W_CTRLERR, i)]
    motor_err0 = IB[_at(rw + W_MOTERR, i)]
    run = alive & active
    idle = alive & (not active)
    osc_new = run & osc_on
    FB[_at(rv + V_PE, i)] = select(alive, pe, pe0)
    FB[_at(rv + V_VE, i)] = select(alive, ve, ve0)
    FB[_at(rv + V_CNTF, i)] = select(alive, counts, cntf0)
    counts_i = np.int64(rounded + off)
    IB[_at(rw + W_COUNTS, i)] = select(alive, counts_i, counts_i0)
    FB[_at(rv + V_INT, i)] = select(run, integ, select(idle, 0.0, integ0))
    FB[_at(rv + V_IQ, i)] = select(run, iq, select(idle, 0.0, iq0))
    FB[_at(rv + V_IQM, i)] = select(run, iq_meas, select(idle, 0.0, iqm0))
    FB[_at(rv + V_IBM, i)] = select(run, ib, select(idle, 0.0, ibm0))
    FB[_at(rv + V_PSP, i)] = select(run, pos_sp, psp0)
    FB[_at(rv + V_VSP, i)] = select(run, vel_in, vsp0)
    FB[_at(rv + V_TSP, i)] = select(run, tq_in, tsp0)
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
    return rng_out, select(run, tau, 0.0), select(run, ib, 0.0), select(run, code_a, ABORT_NONE)


@njit(cache=True, inline="always")
def _stop_axis(i, a, FB, IB, fault, stop, motor_flag):
    """Axis ``a`` (a constant) of leg ``i`` of a vectorized block after the bus check: a
    bus fault's error flags, and for a fault or an abort (``stop``) IDLE, no current, the
    integrator cleared."""
    rv, rw = R_V0 + a * N_V, R_W0 + a * N_W
    motor_err0, axis_err0, mode0 = IB[_at(rw + W_MOTERR, i)], IB[_at(rw + W_AXERR, i)], IB[_at(rw + W_MODE, i)]
    iq0, integ0 = FB[_at(rv + V_IQ, i)], FB[_at(rv + V_INT, i)]
    IB[_at(rw + W_MOTERR, i)] = motor_err0 | select(fault, motor_flag, 0)
    IB[_at(rw + W_AXERR, i)] = axis_err0 | select(fault, AXIS_ERROR_MOTOR_FAILED, 0)
    IB[_at(rw + W_MODE, i)] = select(stop, MODE_IDLE, mode0)
    FB[_at(rv + V_IQ, i)] = select(stop, 0.0, iq0)
    FB[_at(rv + V_INT, i)] = select(stop, 0.0, integ0)


@njit(cache=True, error_model="numpy")
def _control_vector(k, dt, FB, IB, nb, DRV):
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
    inv_cpr = 1.0 / cpr
    for i in range(nb):
        alive = IB[_at(R_DEAD, i)] == 0
        inv_vbus = FB[_at(R_G + G_INV_VBUS, i)]
        rng = np.uint64(IB[_at(R_RNG, i)])
        ibus_sum = 0.0
        # the joints' angles, read from fixed rows (a row chosen at run time would keep
        # the compiler from proving the accesses independent)
        q_joint0, q_joint1 = FB[_at(R_Q, i)], FB[_at(R_Q + 2, i)]
        axis0_on_joint0 = j_of_a0 == 0
        rng, tau_axis0, ib0, code0 = _axis_vector(
            i, 0, FB, IB, select(axis0_on_joint0, q_joint0, q_joint1),
            select(axis0_on_joint0, q_rest_joint0, q_rest_joint1), rng, alive, dt, dirn, turns_per_rad, cpr,
            inv_cpr, enc_noise, cur_noise, quantize, N, kt_true, r_phase, inv_vbus)
        rng, tau_axis1, ib1, code1 = _axis_vector(
            i, 1, FB, IB, select(axis0_on_joint0, q_joint1, q_joint0),
            select(axis0_on_joint0, q_rest_joint1, q_rest_joint0), rng, alive, dt, dirn, turns_per_rad, cpr,
            inv_cpr, enc_noise, cur_noise, quantize, N, kt_true, r_phase, inv_vbus)
        ibus_sum += ib0
        ibus_sum += ib1
        code = select(code1 != ABORT_NONE, code1, code0)
        IB[_at(R_RNG, i)] = np.int64(rng)
        FB[_at(R_TAU, i)] = select(axis0_on_joint0, tau_axis0, tau_axis1)
        FB[_at(R_TAU + 1, i)] = select(axis0_on_joint0, tau_axis1, tau_axis0)
        FB[_at(R_G + G_IBUS_AXES, i)] = ibus_sum
        IB[_at(R_CODE, i)] = code
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
        brake_i = -ibus_sum - FB[_at(R_G + G_MAX_REGEN, i)]
        duty = brake_i * FB[_at(R_G + G_BRAKE_R, i)] * inv_vbus
        duty = py_min(py_max(duty, 0.0), 0.95)
        braking = duty * FB[_at(R_G + G_VBUS, i)] * FB[_at(R_G + G_INV_BRAKE_R, i)]
        brake_i = select(brake, braking, 0.0)
        with_brake = ibus_sum + brake_i
        ibus_sum = select(brake, with_brake, ibus_sum)
        brake_i0, ibus0 = FB[_at(R_G + G_BRAKE_I, i)], FB[_at(R_G + G_IBUS, i)]
        FB[_at(R_G + G_BRAKE_I, i)] = select(alive, brake_i, brake_i0)
        FB[_at(R_G + G_IBUS, i)] = select(alive, ibus_sum, ibus0)
        over_pos = ibus_sum > FB[_at(R_G + G_DCP, i)]
        over_neg = (not over_pos) & (ibus_sum < FB[_at(R_G + G_DCN, i)])
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


@njit(cache=True)
def _run_block_vector(b0, b1, n_ticks, dt, X, AS, AI, C, P, FR, DRV, RNG, ABORT, REC, rec_every,
                      rec_offset):
    """Legs b0..b1-1 of :func:`_run` when :func:`_vector_block` allows: the state copied
    into the block's rows, then per tick one loop over the legs for the controllers
    (:func:`_control_vector`) and one for the mechanics (:func:`_mechanics_plain`), both
    of which vectorize; the numbers are those of :func:`_run_block`."""
    nb = b1 - b0
    FB = np.zeros(N_FROWS * LANES)
    IB = np.zeros(N_IROWS * LANES, np.int64)
    f_slots = (S_POS_EST, S_VEL_EST, S_INTEGRATOR, S_IQ, S_IQ_MEAS, S_COUNT_F, S_POS_SP, S_VEL_SP, S_TQ_SP,
               S_IBUS_MOTOR, S_OSC, S_OSC + 1, S_OSC + 2, S_OSC + 3, S_OSC + 4, S_OSC + 5)
    w_slots = (I_MODE, I_AXIS_ERR, I_CTRL_ERR, I_MOTOR_ERR, I_COUNTS)
    for i in range(nb):
        b = b0 + i
        for n in range(5):
            FB[_at(R_Q + n, i)] = X[b, n]
        IB[_at(R_DEAD, i)] = 1 if ABORT[b, 1] == ABORT_NONFINITE else 0
        IB[_at(R_RNG, i)] = np.int64(RNG[b])
        for a in range(2):
            rv = R_V0 if a == 0 else R_V1
            rk = R_K0 if a == 0 else R_K1
            rw = R_W0 if a == 0 else R_W1
            for n in range(N_V):
                FB[_at(rv + n, i)] = AS[b, a, f_slots[n]]
            for n in range(N_W):
                IB[_at(rw + n, i)] = AI[b, a, w_slots[n]]
            for n in range(len(K_FROM_C)):
                FB[_at(rk + K_FROM_C[n][0], i)] = C[b, a, K_FROM_C[n][1]]
            kp = 2.0 * C[b, a, C_ENCODER_BW]
            FB[_at(rk + K_KP, i)] = kp
            FB[_at(rk + K_KI, i)] = 0.25 * kp * kp
            FB[_at(rk + K_ALPHA, i)] = 1.0 - math.exp(-C[b, a, C_CURRENT_BW] * dt)
            FB[_at(rk + K_INVKT, i)] = 1.0 / C[b, a, C_KT]
        FB[_at(R_G + G_BRAKE_ON, i)] = C[b, 0, C_BRAKE_ON]
        FB[_at(R_G + G_BRAKE_R, i)] = C[b, 0, C_BRAKE_R]
        FB[_at(R_G + G_MAX_REGEN, i)] = C[b, 0, C_MAX_REGEN]
        FB[_at(R_G + G_DCP, i)] = C[b, 0, C_DC_MAX_POS]
        FB[_at(R_G + G_DCN, i)] = C[b, 0, C_DC_MAX_NEG]
        FB[_at(R_G + G_VBUS, i)] = C[b, 0, C_VBUS]
        FB[_at(R_G + G_STYLE, i)] = C[b, 0, C_REGEN_ERR_STYLE]
        FB[_at(R_G + G_INV_VBUS, i)] = 1.0 / C[b, 0, C_VBUS]
        FB[_at(R_G + G_INV_BRAKE_R, i)] = 1.0 / C[b, 0, C_BRAKE_R]
        FB[_at(R_G + G_IBUS, i)] = AS[b, 0, S_IBUS]
        FB[_at(R_G + G_BRAKE_I, i)] = AS[b, 0, S_BRAKE_I]
        IB[_at(R_SYS, i)] = AI[b, 0, I_SYS_ERR]
        IB[_at(R_AB, i)] = ABORT[b, 0]
        IB[_at(R_AB + 1, i)] = ABORT[b, 1]
    P_plain = P[b0:b0 + 1]
    FR_plain = FR[b0:b0 + 1]
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
        _control_vector(k, dt, FB, IB, nb, DRV)
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
        for n in range(5):
            X[b, n] = FB[_at(R_Q + n, i)]
        RNG[b] = np.uint64(IB[_at(R_RNG, i)])
        for a in range(2):
            rv = R_V0 if a == 0 else R_V1
            rw = R_W0 if a == 0 else R_W1
            for n in range(N_V):
                AS[b, a, f_slots[n]] = FB[_at(rv + n, i)]
            for n in range(N_W):
                AI[b, a, w_slots[n]] = IB[_at(rw + n, i)]
        AS[b, 0, S_IBUS] = FB[_at(R_G + G_IBUS, i)]
        AS[b, 0, S_BRAKE_I] = FB[_at(R_G + G_BRAKE_I, i)]
        AI[b, 0, I_SYS_ERR] = IB[_at(R_SYS, i)]
        ABORT[b, 0] = IB[_at(R_AB, i)]
        ABORT[b, 1] = IB[_at(R_AB + 1, i)]


@njit(cache=True)
def _run_block(b0, b1, n_ticks, dt, X, AS, AI, C, P, FR, MECH, DRV, RNG, ABORT, TT, tt_period, REC,
               rec_every, rec_offset, plain):
    """Legs b0..b1-1 of :func:`_run`, tick by tick: each tick the controller of every leg
    (the firmware's loop), then the block's mechanics: one loop over the legs that
    vectorizes when ``plain`` (they share a plain plant, :func:`_plain_block`), else leg by
    leg. A leg's numbers do not depend on the block it is in."""
    nb = b1 - b0
    N = DRV[0]
    cpr = DRV[1]
    dirn = DRV[2]
    enc_noise = DRV[6]
    cur_noise = DRV[7]
    j_of_a0 = int(DRV[5])
    n_tab = TT.shape[1]
    n_rec = REC.shape[1]
    two_pi = 2.0 * math.pi
    turns_per_rad = N / two_pi
    inv_cpr = 1.0 / cpr
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
            # ---- record (before the tick, so row 0 is the initial state)
            if 0 <= rec_row < n_rec:
                REC[b, rec_row, 0] = FB[_at(R_Q + 4, i)] if plain else X[b, 4]
                REC[b, rec_row, 1] = AS[b, 0, S_COUNT_F]
                REC[b, rec_row, 2] = AS[b, 1, S_COUNT_F]
                REC[b, rec_row, 3] = AS[b, 0, S_IQ_MEAS]
                REC[b, rec_row, 4] = AS[b, 1, S_IQ_MEAS]
            rng = RNGL[i]
            abort_now = False
            abort_code = ABORT_NONE
            # ---- the board's checks first (main.cpp:413-420): axis checks and the watchdog,
            # in every state; a failed check disarms the motor
            for a in range(2):
                if C[b, a, C_WD_ENABLE] > 0.0:
                    # axis.cpp:171-182: counts down while enabled, IDLE included; at 0 the
                    # error is set (and stays set while the watchdog is not fed)
                    if AS[b, a, S_WD_TIMER] > 0.0:
                        AS[b, a, S_WD_TIMER] -= 1.0
                    else:
                        AI[b, a, I_AXIS_ERR] |= AXIS_ERROR_WATCHDOG_TIMER_EXPIRED
                if AI[b, a, I_AXIS_ERR] != 0:
                    AI[b, a, I_MODE] = MODE_IDLE
            ibus_sum = 0.0
            for a in range(2):
                j = j_of_a0 if a == 0 else 1 - j_of_a0
                q = FB[_at(R_Q + 2 * j, i)] if plain else X[b, 2 * j]
                if FR[b, F_BELT_K] > 0.0:       # compliant belt: the encoder is on the rotor
                    q = X[b, X_PHI1 + 2 * j]
                turns = dirn * (q - DRV[3 + j]) * turns_per_rad
                rng, nz = _normal(rng)
                raw = turns * cpr + enc_noise * nz
                if FR[b, F_ENC_ON] > 0.0:       # the encoder's reading error (plant [encoder_error])
                    raw += cpr * _encoder_error(FR, b, turns)
                off = C[b, a, C_COUNT_OFFSET]
                counts = (math.floor(raw + 0.5) if DRV[9] > 0.0 else raw) + off
                AI[b, a, I_COUNTS] = np.int64(math.floor(raw + 0.5) + off)
                AS[b, a, S_COUNT_F] = counts
                # PLL estimator (firmware: kp = 2 bw, ki = kp^2 / 4)
                kp = 2.0 * C[b, a, C_ENCODER_BW]
                ki = 0.25 * kp * kp
                pe = AS[b, a, S_POS_EST] + dt * AS[b, a, S_VEL_EST]
                delta = counts * inv_cpr - pe
                pe += dt * kp * delta
                ve = AS[b, a, S_VEL_EST] + dt * ki * delta
                if abs(ve) < 0.5 * dt * ki * inv_cpr:
                    ve = 0.0
                AS[b, a, S_POS_EST] = pe
                AS[b, a, S_VEL_EST] = ve
                mode = AI[b, a, I_MODE]
                if mode == MODE_CALIB:
                    # open-loop lock/scan at calibration_current (encoder.cpp:328-461): the
                    # rotor follows the electrical angle through a torque ~ sin(pole_pairs * error)
                    AS[b, a, S_CAL_POS] += C[b, a, C_CAL_VEL] * dt
                    # the current ramps towards calibration_current at C_CAL_RAMP [A/s]
                    i_tgt = C[b, a, C_CAL_CURRENT]
                    step_i = C[b, a, C_CAL_RAMP] * dt
                    i_now = AS[b, a, S_CAL_I]
                    i_now = min(i_now + step_i, i_tgt) if i_now < i_tgt else max(i_now - step_i, i_tgt)
                    AS[b, a, S_CAL_I] = i_now
                    pp = DRV[10]
                    iq = i_now * math.sin(two_pi * pp * (AS[b, a, S_CAL_POS] - turns))
                    AS[b, a, S_IQ] = iq
                    rng, nz = _normal(rng)
                    AS[b, a, S_IQ_MEAS] = iq + cur_noise * nz
                    AS[b, a, S_INTEGRATOR] = 0.0
                    FB[_at(R_TAU + j, i)] = dirn * N * DRV[8] * iq
                    w = AS[b, a, S_VEL_EST] * two_pi
                    ib = (1.5 * DRV[11] * i_now ** 2 + DRV[8] * iq * w) * INV_VBUS[i]
                    AS[b, a, S_IBUS_MOTOR] = ib
                    ibus_sum += ib
                    continue
                vel_limit = C[b, a, C_VEL_LIMIT]
                if mode != MODE_IDLE and abs(ve) > vel_limit * C[b, a, C_VEL_TOL]:
                    AI[b, a, I_CTRL_ERR] |= CONTROLLER_ERROR_OVERSPEED
                    AI[b, a, I_AXIS_ERR] |= AXIS_ERROR_CONTROLLER_FAILED
                    mode = MODE_IDLE
                if mode == MODE_IDLE:
                    AI[b, a, I_MODE] = MODE_IDLE
                    AS[b, a, S_IQ] = 0.0
                    AS[b, a, S_INTEGRATOR] = 0.0
                    AS[b, a, S_IQ_MEAS] = 0.0
                    AS[b, a, S_IBUS_MOTOR] = 0.0
                    FB[_at(R_TAU + j, i)] = 0.0
                    continue
                # ---- input modes (controller.cpp:183-283): setpoints from the inputs
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
                elif imode == INPUT_MODE_TRAP_TRAJ:
                    if AI[b, a, I_TRAJ_DONE] == 0:
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
                # INPUT_MODE_INACTIVE: the setpoints stay as they are
                kt = C[b, a, C_KT]
                vel_gain = C[b, a, C_VEL_GAIN]
                t_lim = C[b, a, C_CURRENT_LIM] * kt
                verr = 0.0
                if mode == MODE_POSITION and C[b, a, C_ABORT_ERROR] > 0.0:
                    err = AS[b, a, S_POS_SP] - pe
                    if abs(err) > C[b, a, C_ABORT_ERROR]:
                        abort_now = True
                        abort_code = ABORT_POSITION_ERROR
                    elif _oscillation_update_at(AS, b, a, err, 0.025 * C[b, a, C_ABORT_ERROR]):
                        abort_now = True
                        abort_code = ABORT_OSCILLATION
                if mode == MODE_TORQUE:
                    if n_tab > 0:
                        row = min(k // tt_period, n_tab - 1)
                        torque = TT[b, row, a]
                    else:
                        torque = AS[b, a, S_TQ_SP]
                    # firmware's enable_torque_mode_vel_limit
                    t_max = (vel_limit - ve) * vel_gain
                    t_min = (-vel_limit - ve) * vel_gain
                    torque = min(max(torque, t_min), t_max)
                else:
                    vel_sp = min(max(AS[b, a, S_VEL_SP], -vel_limit), vel_limit)
                    if mode == MODE_POSITION:
                        vel_des = C[b, a, C_POS_GAIN] * (AS[b, a, S_POS_SP] - pe) + vel_sp
                    else:
                        vel_des = vel_sp
                    vel_des = min(max(vel_des, -vel_limit), vel_limit)
                    verr = vel_des - ve
                    torque = vel_gain * verr + AS[b, a, S_INTEGRATOR] + AS[b, a, S_TQ_SP]
                limited = False
                if torque > t_lim:
                    torque = t_lim
                    limited = True
                elif torque < -t_lim:
                    torque = -t_lim
                    limited = True
                # controller.cpp:408-420: the integrator is reset in torque control (where the
                # firmware version does so), decays while limited, and is clamped
                if mode == MODE_TORQUE:
                    if C[b, a, C_INT_RESET_TORQUE] > 0.0:
                        AS[b, a, S_INTEGRATOR] = 0.0
                else:
                    if limited:
                        AS[b, a, S_INTEGRATOR] *= 0.99
                    else:
                        AS[b, a, S_INTEGRATOR] += C[b, a, C_VEL_INT_GAIN] * dt * verr
                    lim = C[b, a, C_VEL_INT_LIMIT]
                    AS[b, a, S_INTEGRATOR] = min(max(AS[b, a, S_INTEGRATOR], -lim), lim)
                alpha = ALPHA[i, a]
                iq = AS[b, a, S_IQ] + alpha * (torque * INV_KT[i, a] - AS[b, a, S_IQ])
                AS[b, a, S_IQ] = iq
                rng, nz = _normal(rng)
                iq_meas = iq + cur_noise * nz
                AS[b, a, S_IQ_MEAS] = iq_meas
                if abs(iq_meas) > C[b, a, C_CURRENT_LIM] + CURRENT_LIM_MARGIN:
                    AI[b, a, I_MOTOR_ERR] |= MOTOR_ERROR_CURRENT_LIMIT_VIOLATION
                    AI[b, a, I_AXIS_ERR] |= AXIS_ERROR_MOTOR_FAILED
                    AI[b, a, I_MODE] = MODE_IDLE
                    AS[b, a, S_IQ] = 0.0
                    iq = 0.0
                # the motor's own torque constant makes the torque; the configured one only
                # converts the torque command to a current
                FB[_at(R_TAU + j, i)] = dirn * N * DRV[8] * iq
                # this motor's bus current: copper loss plus mechanical power over vbus
                w = ve * two_pi
                ib = (1.5 * DRV[11] * iq * iq + DRV[8] * iq * w) * INV_VBUS[i]
                AS[b, a, S_IBUS_MOTOR] = ib
                ibus_sum += ib
            # ---- the DC bus (low_level.cpp:320-376): brake resistor, then the bus limits
            brake_i = 0.0
            if C[b, 0, C_BRAKE_ON] > 0.0:
                brake_i = -ibus_sum - C[b, 0, C_MAX_REGEN]
                duty = brake_i * C[b, 0, C_BRAKE_R] * INV_VBUS[i]
                duty = min(max(duty, 0.0), 0.95)
                brake_i = duty * C[b, 0, C_VBUS] * INV_BRAKE_R[i]
                ibus_sum += brake_i
            AS[b, 0, S_BRAKE_I] = brake_i
            AS[b, 0, S_IBUS] = ibus_sum
            bus_fault = 0
            if ibus_sum > C[b, 0, C_DC_MAX_POS]:
                bus_fault = 1
            elif ibus_sum < C[b, 0, C_DC_MAX_NEG]:
                bus_fault = 2
            if bus_fault:
                for a in range(2):
                    if C[b, 0, C_REGEN_ERR_STYLE] > 0.0:   # 0.5.1: low_level_fault on the motors
                        AI[b, a, I_MOTOR_ERR] |= (MOTOR_ERROR_DC_BUS_OVER_REGEN_CURRENT if bus_fault == 2
                                                   else MOTOR_ERROR_DC_BUS_OVER_CURRENT)
                    else:                                  # 0.5.2+: odrv.disarm_with_error
                        AI[b, a, I_MOTOR_ERR] |= MOTOR_ERROR_SYSTEM_LEVEL
                    AI[b, a, I_AXIS_ERR] |= AXIS_ERROR_MOTOR_FAILED
                    AI[b, a, I_MODE] = MODE_IDLE
                    AS[b, a, S_IQ] = 0.0
                    AS[b, a, S_INTEGRATOR] = 0.0
                if C[b, 0, C_REGEN_ERR_STYLE] <= 0.0:
                    AI[b, 0, I_SYS_ERR] |= (ODRIVE_ERROR_DC_BUS_OVER_REGEN_CURRENT if bus_fault == 2
                                            else ODRIVE_ERROR_DC_BUS_OVER_CURRENT)
                FB[_at(R_TAU + 0, i)] = 0.0
                FB[_at(R_TAU + 1, i)] = 0.0
            if abort_now:
                for a in range(2):
                    AI[b, a, I_MODE] = MODE_IDLE
                    AS[b, a, S_IQ] = 0.0
                    AS[b, a, S_INTEGRATOR] = 0.0
                FB[_at(R_TAU + 0, i)] = 0.0
                FB[_at(R_TAU + 1, i)] = 0.0
                if ABORT[b, 1] == ABORT_NONE:
                    ABORT[b, 0] = k
                    ABORT[b, 1] = abort_code
            RNGL[i] = rng
        # ---- mechanics
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


# ---------------------------------------------------------------------------------------
# the batch simulator
# ---------------------------------------------------------------------------------------

def true_leg(plant: PlantParams) -> LegParams:
    """The twin's hidden leg: the base set scaled (inertia, mass), the payload on the foot,
    and the plant's own viscous and Coulomb friction (Stribeck is added in the kernel).
    With a compliant belt the rotor (reflected through the belt, J_rotor N^2) is its own
    inertia in the kernel and is taken out of the drive inertias Jd1, Jd2: the total stays."""
    leg = plant.base_leg().scaled(plant.inertia_scale, plant.mass_scale, plant.payload_mass)
    leg = leg.replace(c11=plant.viscous1, c12=0.0, c21=0.0, c22=plant.viscous2,
                      coulomb1=plant.coulomb1, coulomb2=plant.coulomb2)
    if plant.belt_compliant:
        jm = reflected_rotor_inertia(plant, leg)
        leg = leg.replace(Jd1=leg.Jd1 - jm, Jd2=leg.Jd2 - jm)
    return leg


def reflected_rotor_inertia(plant: PlantParams, leg: LegParams | None = None) -> float:
    """The rotor and its pulley seen at the joint through the belt, J_rotor N^2 [kg*m^2]."""
    leg = plant.base_leg() if leg is None else leg
    return plant.rotor_inertia * leg.gear_ratio ** 2


def effect_parameters(plant: PlantParams, leg: LegParams, dt: float) -> np.ndarray:
    """The kernel's parameters of the plant's unmodeled effects (FR[b, 14:], the F_
    indices), all zero where an effect is off. A compliant belt gets the number of
    sub-steps that keeps its mode (rotor against the lightest joint inertia at rest) and
    its damping well inside semi-implicit Euler's stable range at ``dt``."""
    from .model import mass_matrix
    out = np.zeros(N_FR - 14)
    k = lambda i: i - 14   # noqa: E731 - FR index -> position in this vector
    if plant.belt_compliant:
        jm = reflected_rotor_inertia(plant, leg)
        if plant.mechanism == "fivebar":
            j_min = float(np.min(np.linalg.eigvalsh(mass_matrix(leg, *leg.q0))))
        else:
            j_min = min(leg.I1 + leg.Jd1 + leg.m1 * leg.lc1 ** 2, leg.I2 + leg.Jd2 + leg.m2 * leg.lc2 ** 2)
        inv = 1.0 / jm + 1.0 / j_min
        w = math.sqrt(plant.belt_stiffness * inv)
        sub = max(1, math.ceil(w * dt / BELT_PHASE_PER_STEP), math.ceil(plant.belt_damping * inv * dt / 0.5))
        out[k(F_BELT_K)], out[k(F_BELT_C)] = plant.belt_stiffness, plant.belt_damping
        out[k(F_BACKLASH_HALF)], out[k(F_JM)], out[k(F_BELT_SUB)] = 0.5 * plant.backlash, jm, sub
    amps = (plant.cogging1, plant.cogging2, plant.cogging3)
    if sum(amps) > 0.0:
        out[k(F_COG_ON)], out[k(F_COG_PERIODS)] = 1.0, plant.cogging_periods
        out[k(F_COG_A1):k(F_COG_A3) + 1] = amps
        out[k(F_COG_P1):k(F_COG_P3) + 1] = plant.cogging_phase1, plant.cogging_phase2, plant.cogging_phase3
    if plant.encoder_error1 + plant.encoder_error2 > 0.0:
        out[k(F_ENC_ON)] = 1.0
        out[k(F_ENC_A1)], out[k(F_ENC_P1)] = plant.encoder_error1, plant.encoder_phase1
        out[k(F_ENC_A2)], out[k(F_ENC_P2)] = plant.encoder_error2, plant.encoder_phase2
    if plant.lugre or plant.coulomb_asymmetry != 0.0 or plant.friction_drift > 0.0:
        out[k(F_FRIC_EXT)] = 1.0
        out[k(F_LUGRE_S0)], out[k(F_LUGRE_S1)] = plant.lugre_stiffness, plant.lugre_damping
        out[k(F_ASYM)], out[k(F_DRIFT)] = plant.coulomb_asymmetry, plant.friction_drift
        out[k(F_DRIFT_TRAVEL)] = plant.drift_travel
    return out


def _seed_words(seed: int, key) -> list:
    return [int(seed) & 0xFFFFFFFF] + [int(round(float(v) * 1e6)) & 0xFFFFFFFF for v in key]


def seeds_for(seed: int, keys) -> np.ndarray:
    """Per-leg RNG states derived from ``seed`` and each leg's key (content, not order), so
    a point simulated alone or inside a batch sees the same noise.

    Each state is ``np.random.SeedSequence(words).generate_state(1, np.uint64)[0] | 1``
    with ``words`` the seed and the key's values in millionths, each taken modulo 2^32.
    It is computed here for all legs at once: the same mixing as numpy's SeedSequence
    (bit_generator.pyx: four pool words, hashmix and mix over uint32, two output words),
    checked against it in tests/test_twin.py. Keys of unequal lengths or huge values go
    through SeedSequence leg by leg."""
    n = len(keys)
    lens = {len(k) for k in keys}
    vals = np.asarray(keys, dtype=float).reshape(n, -1) if len(lens) == 1 else None
    if vals is None or not np.all(np.abs(vals) < 2.0 ** 52 / 1e6):
        out = np.empty(n, dtype=np.uint64)
        for i, key in enumerate(keys):
            out[i] = np.random.SeedSequence(_seed_words(seed, key)).generate_state(1, np.uint64)[0] | np.uint64(1)
        return out
    # Python's round() is numpy's (half to even); |value| < 2^52: exact in int64
    words = [np.full(n, int(seed) & 0xFFFFFFFF, dtype=np.uint32)]
    words += [(np.round(vals[:, j] * 1e6).astype(np.int64) & 0xFFFFFFFF).astype(np.uint32)
              for j in range(vals.shape[1])]
    return _seed_sequence_state(words) | np.uint64(1)


_M32 = 0xFFFFFFFF


def _seed_sequence_state(entropy) -> np.ndarray:
    """``SeedSequence(words).generate_state(1, np.uint64)`` for ``entropy``, a list of
    uint32 arrays over the legs (word k of every leg's words), pool size 4. The hash
    constants do not depend on the data, so they run as Python integers; the data as
    uint32 arrays, which wrap as C does."""
    hc = [0x43B0D7E5]

    def hashmix(value):
        value = value ^ np.uint32(hc[0])
        hc[0] = (hc[0] * 0x931E8875) & _M32
        value = value * np.uint32(hc[0])
        return value ^ (value >> np.uint32(16))

    def mix(x, y):
        r = np.uint32(0xCA01F9DD) * x - np.uint32(0x4973F715) * y
        return r ^ (r >> np.uint32(16))

    with np.errstate(over="ignore"):
        zero = np.zeros_like(entropy[0])
        pool = [hashmix(entropy[i] if i < len(entropy) else zero) for i in range(4)]
        for src in range(4):
            for dst in range(4):
                if src != dst:
                    pool[dst] = mix(pool[dst], hashmix(pool[src]))
        for src in range(4, len(entropy)):
            for dst in range(4):
                pool[dst] = mix(pool[dst], hashmix(entropy[src]))
        hb = 0x8B51F9DD
        state = []
        for i in range(2):
            v = pool[i] ^ np.uint32(hb)
            hb = (hb * 0x58F38DED) & _M32
            v = v * np.uint32(hb)
            state.append(v ^ (v >> np.uint32(16)))
    return state[0].astype(np.uint64) | (state[1].astype(np.uint64) << np.uint64(32))


@dataclass
class TwinState:
    """Everything the kernel mutates, for a batch of B legs (arrays, see :func:`_run`)."""

    X: np.ndarray
    AS: np.ndarray
    AI: np.ndarray
    C: np.ndarray
    RNG: np.ndarray
    ABORT: np.ndarray

    def copy(self) -> "TwinState":
        return TwinState(*(a.copy() for a in (self.X, self.AS, self.AI, self.C, self.RNG, self.ABORT)))

    def take(self, idx) -> "TwinState":
        return TwinState(*(a[idx].copy() for a in (self.X, self.AS, self.AI, self.C, self.RNG, self.ABORT)))

    @property
    def batch(self) -> int:
        return self.X.shape[0]


class Twin:
    """Batch simulator of B virtual legs sharing one plant and ODrive configuration.

    Parameters
    ----------
    plant : PlantParams or name, the simulated physical leg (default ``"default"``)
    config : OdriveConfig or name, the ODrive configuration (default Listing 7.1)
    batch : number of legs
    seed : base seed of the noise streams
    noise : encoder and current noise on
    quantize : encoder readings quantized at the CPR (False: exact positions, for models
        fitted by finite differences)
    """

    def __init__(self, plant: PlantParams | str = "default", config: OdriveConfig | str = "thesis",
                 batch: int = 1, seed: int = 0, noise: bool = True, motor: MotorParams | str = "mn5212",
                 quantize: bool = True):
        self.plant = load_plant(plant) if isinstance(plant, str) else plant
        self.motor = load_motor(motor) if isinstance(motor, str) else motor
        self.config = load_odrive_config(config) if isinstance(config, str) else config
        self.nominal_leg = self.plant.base_leg()
        self.leg = true_leg(self.plant)
        self.axes = AxisMap.from_leg(self.nominal_leg)
        self.seed = int(seed)
        self.noise = bool(noise)
        self.dt = 1.0 / self.config.loop_frequency
        self.P = param_vector(self.leg)
        self.payload_mounted = True
        leg = self.leg
        J1 = leg.I1 + leg.Jd1 + leg.m1 * leg.lc1 ** 2
        J2 = leg.I2 + leg.Jd2 + leg.m2 * leg.lc2 ** 2
        p = self.plant
        self.FR = np.array([p.viscous1, p.viscous2, p.coulomb1, p.coulomb2, p.stribeck1, p.stribeck2,
                            p.stribeck_velocity, p.coulomb_smoothing, p.gap_min, p.stop_stiffness,
                            p.stop_damping, J1, J2, p.gap_max, *effect_parameters(p, leg, self.dt)])
        self.mech = 0 if p.mechanism == "fivebar" else 1
        ax = self.axes
        motor = self.motor
        self.DRV = np.array([ax.gear_ratio, ax.cpr, ax.direction, ax.q_rest[0], ax.q_rest[1],
                             ax.joint_of_axis(0), p.encoder_noise if noise else 0.0,
                             p.current_noise if noise else 0.0, motor.torque_constant, 1.0 if quantize else 0.0,
                             float(motor.pole_pairs), motor.phase_resistance])
        self.state = self._initial_state(batch)

    def mount_payload(self, mounted: bool) -> None:
        """Put the plant's foot payload on (True) or take it off (False) the simulated leg.
        The plant (its parameters, what the device reports) keeps the payload either way;
        only the mechanics simulated from now on change."""
        p = self.plant if mounted else self.plant.replace(payload_mass=0.0)
        self.leg = true_leg(p)
        self.P = param_vector(self.leg)
        self.payload_mounted = bool(mounted)
        self.__dict__.pop("_fixed", None)   # the kernel's cached copies of P

    # -- state -----------------------------------------------------------------------
    def _initial_state(self, batch: int) -> TwinState:
        X = np.zeros((batch, N_X))
        X[:, X_Q1], X[:, X_Q2] = self.axes.q_rest
        X[:, X_PHI1], X[:, X_PHI2] = self.axes.q_rest
        C = np.zeros((batch, 2, N_CFG))
        cfg = self.config
        C[:, :, C_POS_GAIN] = 20.0       # firmware defaults
        C[:, :, C_VEL_GAIN] = 1.0 / 6.0
        C[:, :, C_VEL_INT_GAIN] = 1.0 / 3.0
        C[:, :, C_VEL_LIMIT] = cfg.vel_limit
        C[:, :, C_VEL_TOL] = cfg.vel_limit_tolerance
        C[:, :, C_CURRENT_LIM] = cfg.current_lim
        C[:, :, C_KT] = cfg.torque_constant
        C[:, :, C_CURRENT_BW] = cfg.current_control_bandwidth
        C[:, :, C_ENCODER_BW] = cfg.encoder_bandwidth
        C[:, :, C_VEL_INT_LIMIT] = np.inf           # firmware default (0.5.4+)
        C[:, :, C_INPUT_MODE] = INPUT_MODE_PASSTHROUGH
        C[:, :, C_FILTER_BW] = 2.0                  # firmware default input_filter_bandwidth
        C[:, :, C_INT_RESET_TORQUE] = 1.0
        C[:, :, C_CAL_CURRENT] = 10.0               # firmware default calibration_current
        # the board as leglib configures it: brake resistor on, the firmware's bus limits
        C[:, 0, C_BRAKE_ON] = 1.0
        C[:, 0, C_BRAKE_R] = cfg.brake_resistance
        C[:, 0, C_MAX_REGEN] = 0.0
        C[:, 0, C_DC_MAX_POS] = np.inf
        C[:, 0, C_DC_MAX_NEG] = -0.01
        C[:, 0, C_VBUS] = 24.0
        st = TwinState(X=X, AS=np.zeros((batch, 2, N_AXSTATE)), AI=np.zeros((batch, 2, N_AXINT), np.int64),
                       C=C, RNG=seeds_for(self.seed, [(i,) for i in range(batch)]),
                       ABORT=np.zeros((batch, 2), np.int64))
        return st

    def rest_state(self) -> TwinState:
        """A copy of the state after the idle leg has settled on its stop (cached)."""
        if not hasattr(self, "_rest"):
            st = self._initial_state(1)
            self.run(st, seconds=2.0)
            st.X[:, [X_DQ1, X_DQ2, X_DPHI1, X_DPHI2]] = 0.0
            st.X[:, 4] = 0.0
            # encoder and estimator agree with the settled leg
            self.run(st, ticks=int(0.05 / self.dt))
            st.X[:, 4] = 0.0
            st.X[:, [X_TRAVEL1, X_TRAVEL2]] = 0.0   # a leg fresh from assembly: no use yet
            self._rest = st
        return self._rest.copy()

    def motor_angle(self, st: TwinState, joint: int) -> np.ndarray:
        """Where joint ``joint``'s motor is, on the joint side [rad] (B,): the rotor's angle
        with a compliant belt, the joint's with a rigid one."""
        col = (X_PHI1 if self.plant.belt_compliant else X_Q1) + 2 * joint
        return st.X[:, col].copy()

    def encoder_turns(self, st: TwinState, joint: int) -> np.ndarray:
        """What joint ``joint``'s encoder reads [motor turn from rest] (B,), without noise
        and quantization: the rotor's turns plus the plant's encoder error."""
        turns = self.axes.motor_turns(self.motor_angle(st, joint), joint)
        fr = self.FR[None, :]
        if fr[0, F_ENC_ON] > 0.0:
            turns = turns + np.array([_encoder_error(fr, 0, float(t)) for t in np.atleast_1d(turns)])
        return turns

    # -- running ---------------------------------------------------------------------
    def run(self, st: TwinState, seconds: float | None = None, ticks: int | None = None,
            torque_table: np.ndarray | None = None, table_period: float | None = None,
            record_every: int = 0, record: np.ndarray | None = None, record_offset: int = 0) -> None:
        """Advance ``st`` in place (compiled kernel; no Python per tick)."""
        n = int(ticks) if ticks is not None else int(round(seconds / self.dt))
        if n <= 0:
            return
        B = st.batch
        fixed = self.__dict__.setdefault("_fixed", {})
        if B not in fixed:  # per-batch-size constant arrays, built once (host loops call run often)
            fixed[B] = (np.ascontiguousarray(np.broadcast_to(self.P, (B, self.P.size))),
                        np.ascontiguousarray(np.broadcast_to(self.FR, (B, self.FR.size))),
                        np.full(B, self.mech, np.int64), np.zeros((B, 0, 2)), np.zeros((B, 0, 5)))
        P, FR, MECH, no_table, no_rec = fixed[B]
        tt = no_table if torque_table is None else np.ascontiguousarray(torque_table, float)
        tt_period = 1 if table_period is None else max(1, int(round(table_period / self.dt)))
        rec = no_rec if record is None else record
        if B == 1:
            _run_serial(n, self.dt, st.X, st.AS, st.AI, st.C, P, FR, MECH, self.DRV, st.RNG, st.ABORT, tt,
                        tt_period, rec, int(record_every), int(record_offset), 1)
            return
        # blocks of legs handed out one at a time (a dynamic schedule: a core busy with
        # something else takes fewer); whole vectors of legs, two when there are blocks
        # enough to share out evenly
        big = B >= 16 * VECTOR_LEGS * get_num_threads()
        block = 2 * VECTOR_LEGS if big else VECTOR_LEGS
        chunk = set_parallel_chunksize(1)
        try:
            _run(n, self.dt, st.X, st.AS, st.AI, st.C, P, FR, MECH, self.DRV, st.RNG, st.ABORT, tt, tt_period,
                 rec, int(record_every), int(record_offset), block)
        finally:
            set_parallel_chunksize(chunk)

    def step_batch(self, gains: np.ndarray, step_turns: float = 0.4, duration: float = 1.5,
                   sample_period: float = 0.002, vel_limit: float | None = None,
                   abort_error_turns: float | None = None, start: TwinState | None = None) -> dict:
        """Position step responses of Listing 7.4 for each row of ``gains``, all at once.

        Parameters
        ----------
        gains : (B, 3) pos_gain [(turn/s)/turn], vel_gain [N*m/(turn/s)],
            vel_integrator_gain [N*m/(turn/s)/s]
        step_turns : motor step; the axis driving q1 gets +step, the other -step [turn]
        duration : response length [s]; sample_period : recording period [s]
        vel_limit : velocity limit during the step [turn/s] (default: config.step_vel_limit)
        abort_error_turns : abort (both axes IDLE) when |input_pos - pos_estimate| exceeds it
            (default 2 * |step|)
        start : the state every leg starts from (default: at rest on its stop). Every
            point starts from this same state, its friction drift (accumulated joint travel,
            X[:, X_TRAVEL1:]) included: a batch's points do not wear the leg for each other,
            whereas a device (:class:`leglib.virtual_odrive.VirtualODrive`) carries its
            drift from experiment to experiment.

        Returns
        -------
        dict with ``t`` (n,), ``counts`` (B, n, 2) per axis, ``iq`` (B, n, 2) [A],
        ``abort_tick`` (B,) (-1: completed), ``abort_reason`` (B,), axis errors (B, 2).
        """
        gains = np.atleast_2d(np.asarray(gains, dtype=float))
        B = gains.shape[0]
        base = self.rest_state() if start is None else start
        st = base.take(np.zeros(B, dtype=int))
        st.RNG[:] = seeds_for(self.seed, [tuple(g) + (step_turns, duration) for g in gains])
        st.ABORT[:] = (-1, ABORT_NONE)
        st.X[:, 4] = 0.0
        vl = self.config.step_vel_limit if vel_limit is None else vel_limit
        abort = 2.0 * abs(step_turns) if abort_error_turns is None else abort_error_turns
        a_q1 = self.axes.axis_of_joint[0]
        for a in range(2):
            sign = 1.0 if a == a_q1 else -1.0
            st.C[:, a, C_POS_GAIN] = gains[:, 0]
            st.C[:, a, C_VEL_GAIN] = gains[:, 1]
            st.C[:, a, C_VEL_INT_GAIN] = gains[:, 2]
            st.C[:, a, C_VEL_LIMIT] = vl
            st.C[:, a, C_INPUT_VEL] = 0.0
            st.C[:, a, C_INPUT_TORQUE] = 0.0
            st.C[:, a, C_INPUT_POS] = st.AS[:, a, S_POS_EST] + sign * step_turns
            st.C[:, a, C_ABORT_ERROR] = abort
            st.C[:, a, C_INPUT_MODE] = INPUT_MODE_PASSTHROUGH
            st.AI[:, a, I_MODE] = MODE_POSITION
            st.AS[:, a, S_INTEGRATOR] = 0.0
            st.AS[:, a, S_OSC:S_OSC + N_OSC] = 0.0
        every = max(1, int(round(sample_period / self.dt)))
        n_ticks = int(round(duration / self.dt))
        n_rec = (n_ticks + every - 1) // every
        rec = np.zeros((B, n_rec, 5))
        self.run(st, ticks=n_ticks, record_every=every, record=rec)
        # views of the record (no copies of its megabytes): nothing else holds it
        return {"t": rec[0, :, 0], "counts": rec[:, :, 1:3], "iq": rec[:, :, 3:5],
                "abort_tick": np.where(st.ABORT[:, 1] != ABORT_NONE, st.ABORT[:, 0], -1),
                "abort_reason": st.ABORT[:, 1].copy(), "axis_error": st.AI[:, :, I_AXIS_ERR].copy(),
                "final": st}
