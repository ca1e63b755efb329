"""The leg's mechanics in the twin's tick: one semi-implicit Euler step of the exact
five-bar with gravity, friction and the stop between the upper links.

:func:`_mechanics_leg` steps one leg of any plant (the unmodeled effects included);
:func:`_mechanics_plain` steps a block of legs that share a plain plant, branch-free so
that its loop over the legs vectorizes, with the same operations in the same order (the
same numbers); :func:`_mechanics_effects` steps a block of legs that share a plant with
unmodeled effects, branch-free likewise, with the same operations in the same order and
the same functions (:mod:`leglib.kernelmath`'s sin, exp and tanh on both paths): the same
numbers, bit for bit (tests/twin).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .. import _numba_gc, _numba_inline  # noqa: F401  (before any kernel compiles)
from ..abort import ABORT_NONFINITE
from ..kernelmath import select
from ..kernelmath import sincos as _sincos
from ..kernelmath import tanh as _tanh
from ..model.terms import _fivebar_reduced
from .effects import (
    _add_cogging,
    _belt_advance,
    _belt_split,
    _belt_torque_v,
    _cogging_torque_v,
    _joint_friction,
    _joint_friction_v,
    _stribeck,
)
from .layout import (
    F_ASYM,
    F_BACKLASH_HALF,
    F_BELT_C,
    F_BELT_K,
    F_BELT_SUB,
    F_COG_A1,
    F_COG_A2,
    F_COG_A3,
    F_COG_C1,
    F_COG_C2,
    F_COG_C3,
    F_COG_ON,
    F_COG_PERIODS,
    F_COG_S1,
    F_COG_S2,
    F_COG_S3,
    F_DRIFT,
    F_DRIFT_TRAVEL,
    F_FRIC_EXT,
    F_JM,
    F_LUGRE_S0,
    F_LUGRE_S1,
    I_MODE,
    LANES,
    MODE_IDLE,
    N_FROWS,
    N_X,
    R_DEAD,
    R_NF,
    R_Q,
    R_TAU,
    X_DPHI1,
    X_DPHI2,
    X_DQ1,
    X_DQ2,
    X_PHI1,
    X_PHI2,
    X_Q1,
    X_Q2,
    X_T,
    X_TRAVEL1,
    X_TRAVEL2,
    X_Z1,
    X_Z2,
)

# further rows of a block's FB (after layout's N_FROWS) for :func:`_mechanics_effects`: the
# legs' whole mechanical state (R_X + the X_ index; rows R_Q.. keep what the encoders see),
# and what its loops pass on: the friction torques, then for the compliant belt the rotors'
# torques, the accelerations other than the belt's, the mass matrix and whether the leg
# advances (1.0) this tick
R_X = N_FROWS
(R_F1, R_F2, R_TM1, R_TM2, R_O1, R_O2, R_D11, R_D12, R_D22, R_DET, R_GO) = range(R_X + N_X, R_X + N_X + 11)
N_FROWS_EFFECTS = R_GO + 1


@njit(cache=True, inline="always")
def _at(row, i):
    """Index of leg ``i`` in row ``row`` of a block's FB or IB; unsigned, so the compiler
    adds no wraparound of negative indices (which hides the rows' independence)."""
    return np.uint64(row * LANES + i)


@njit(cache=True, inline="always")
def _param_row(P, b):
    """Row ``b`` of P (the 19 entries of ``derivation.PARAM_NAMES``) as a tuple: loaded once
    per call, so the five-bar's constant terms leave the tick loop."""
    return (P[b, 0], P[b, 1], P[b, 2], P[b, 3], P[b, 4], P[b, 5], P[b, 6], P[b, 7], P[b, 8], P[b, 9],
            P[b, 10], P[b, 11], P[b, 12], P[b, 13], P[b, 14], P[b, 15], P[b, 16], P[b, 17], P[b, 18])


@njit(cache=True)
def _plain_block(b0, b1, P, FR, MECH):
    """Whether legs b0..b1-1 share one plain plant (see :func:`_mechanics_plain`): one plant
    (:func:`_shared_block`) with the exact five-bar and no unmodeled effect."""
    for b in range(b0, b1):
        if MECH[b] != 0 or FR[b, F_BELT_K] > 0.0 or FR[b, F_COG_ON] > 0.0 or FR[b, F_FRIC_EXT] > 0.0:
            return False
        if FR[b, 4] != 0.0 or FR[b, 5] != 0.0:
            return False
    return _shared_block(b0, b1, P, FR, MECH)


@njit(cache=True, inline="always")
def _stops_and_accelerations(q1, dq1, q2, dq2, t1, t2, d11, d12, d22, stops, gap_min, k_stop, c_stop, gap_max):
    """The joint accelerations of a leg of a block (:func:`_mechanics_plain`,
    :func:`_mechanics_effects`), branch-free: the stop between the upper links (when
    ``stops``, a five-bar's) added to the joint torques ``t1``, ``t2`` as
    :func:`_mechanics_leg` adds it, then the 2x2 solve with the mass matrix (d11, d12, d22).
    Returns (a1, a2, det, both finite)."""
    gap = q2 - q1
    push = k_stop * (gap_min - gap) - c_stop * (dq2 - dq1)
    pull = k_stop * (gap - gap_max) + c_stop * (dq2 - dq1)
    pushing = stops & (gap < gap_min) & (push > 0.0)
    pulling = stops & (not (gap < gap_min)) & (gap > gap_max) & (pull > 0.0)
    t1 = select(pushing, t1 - push, select(pulling, t1 + pull, t1))
    t2 = select(pushing, t2 + push, select(pulling, t2 - pull, t2))
    det = d11 * d22 - d12 * d12
    inv_det = 1.0 / det
    a1 = (d22 * t1 - d12 * t2) * inv_det
    a2 = (-d12 * t1 + d11 * t2) * inv_det
    return a1, a2, det, math.isfinite(a1) & math.isfinite(a2)


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
        a1, a2, _, ok = _stops_and_accelerations(q1, dq1, q2, dq2, t1, t2, d11, d12, d22, True, gap_min, k_stop,
                                                 c_stop, gap_max)
        alive = IB[_at(R_DEAD, i)] == 0
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


@njit(cache=True, _nrt=False)
def _mechanics_leg_apart(b, k, dt, X, AI, FR, MECH, DRV, ABORT, Pb, tau, tm, inv_v_stribeck, inv_v_smooth):
    """:func:`_mechanics_leg` compiled as a function of its own, for the reference tick loop
    (kernel._run_block_ticks, whose compile it would otherwise lengthen by about a third; see
    there). The vectorized path's leg-by-leg mechanics inline it: called apart there, a mixed
    batch ran a fifth slower. Allocates nothing, so, as that loop, without numba's runtime."""
    return _mechanics_leg(b, k, dt, X, AI, FR, MECH, DRV, ABORT, Pb, tau, tm, inv_v_stribeck, inv_v_smooth)


@njit(cache=True)
def _shared_block(b0, b1, P, FR, MECH):
    """Whether legs b0..b1-1 share one plant, any (see :func:`_mechanics_effects`)."""
    for b in range(b0, b1):
        if MECH[b] != MECH[b0]:
            return False
        for n in range(P.shape[1]):
            if P[b, n] != P[b0, n]:
                return False
        for n in range(FR.shape[1]):
            if FR[b, n] != FR[b0, n]:
                return False
    return True


@njit(cache=True, error_model="numpy")
def _cogging_effects(FB, nb, FR, DRV):
    """Rows R_TAU of a block that shares a plant with cogging: each motor's cogging torque
    added, reflected to the joint side, as :func:`leglib.twin.effects._add_cogging` adds
    it, at the angle of the rotor (compliant belt) or of the joint."""
    belt = FR[0, F_BELT_K] > 0.0
    two_pi_periods = 2.0 * math.pi * FR[0, F_COG_PERIODS]
    a1, a2, a3 = FR[0, F_COG_A1], FR[0, F_COG_A2], FR[0, F_COG_A3]
    cp1, sp1 = FR[0, F_COG_C1], FR[0, F_COG_S1]
    cp2, sp2 = FR[0, F_COG_C2], FR[0, F_COG_S2]
    cp3, sp3 = FR[0, F_COG_C3], FR[0, F_COG_S3]
    dirn, gear, rest1, rest2 = DRV[2], DRV[0], DRV[3], DRV[4]
    reflect = DRV[2] * DRV[0]
    for i in range(nb):
        m1 = select(belt, FB[_at(R_X + X_PHI1, i)], FB[_at(R_X + X_Q1, i)])
        m2 = select(belt, FB[_at(R_X + X_PHI2, i)], FB[_at(R_X + X_Q2, i)])
        turns1 = dirn * (m1 - rest1) * gear / (2.0 * math.pi)
        turns2 = dirn * (m2 - rest2) * gear / (2.0 * math.pi)
        cog1 = _cogging_torque_v(two_pi_periods * turns1, a1, a2, a3, cp1, sp1, cp2, sp2, cp3, sp3)
        cog2 = _cogging_torque_v(two_pi_periods * turns2, a1, a2, a3, cp1, sp1, cp2, sp2, cp3, sp3)
        FB[_at(R_TAU, i)] = FB[_at(R_TAU, i)] + reflect * cog1
        FB[_at(R_TAU + 1, i)] = FB[_at(R_TAU + 1, i)] + reflect * cog2


@njit(cache=True, error_model="numpy")
def _friction_effects(dt, FB, IB, nb, FR):
    """Rows R_F1, R_F2 of a block that shares a plant with unmodeled effects: the joints'
    friction torques as :func:`_mechanics_leg` computes them, the plain friction with its
    Stribeck term or the extended one (effects._joint_friction, its bristles and travel
    updated in rows R_X..; a dead leg's stay). One loop for every case, the cases chosen by
    selects: each case's Stribeck exp and tanh take the argument its own path computes, so
    the loop inlines one exp and one tanh for both (the loop's code, compiled into every
    kernel that calls it, stays small)."""
    ext = FR[0, F_FRIC_EXT] > 0.0
    lugre = FR[0, F_LUGRE_S0] > 0.0
    visc1, visc2, coul1, coul2, strib1, strib2 = FR[0, 0], FR[0, 1], FR[0, 2], FR[0, 3], FR[0, 4], FR[0, 5]
    v_strib, v_smooth = FR[0, 6], FR[0, 7]
    inv_v_stribeck, inv_v_smooth = 1.0 / FR[0, 6], 1.0 / FR[0, 7]
    asym, drift, drift_travel = FR[0, F_ASYM], FR[0, F_DRIFT], FR[0, F_DRIFT_TRAVEL]
    s0, s1 = FR[0, F_LUGRE_S0], FR[0, F_LUGRE_S1]
    for i in range(nb):
        alive = IB[_at(R_DEAD, i)] == 0
        dq1, dq2 = FB[_at(R_X + X_DQ1, i)], FB[_at(R_X + X_DQ2, i)]
        z1, z2 = FB[_at(R_X + X_Z1, i)], FB[_at(R_X + X_Z2, i)]
        tr1, tr2 = FB[_at(R_X + X_TRAVEL1, i)], FB[_at(R_X + X_TRAVEL2, i)]
        f1, z1n, tr1n = _joint_friction_v(dt, dq1, tr1, z1, visc1, coul1, strib1, v_strib, v_smooth, asym, drift,
                                          drift_travel, s0, s1, ext, lugre, inv_v_stribeck, inv_v_smooth)
        f2, z2n, tr2n = _joint_friction_v(dt, dq2, tr2, z2, visc2, coul2, strib2, v_strib, v_smooth, asym, drift,
                                          drift_travel, s0, s1, ext, lugre, inv_v_stribeck, inv_v_smooth)
        FB[_at(R_F1, i)] = f1
        FB[_at(R_F2, i)] = f2
        FB[_at(R_X + X_Z1, i)] = select(alive & ext, z1n, z1)
        FB[_at(R_X + X_Z2, i)] = select(alive & ext, z2n, z2)
        FB[_at(R_X + X_TRAVEL1, i)] = select(alive & ext, tr1n, tr1)
        FB[_at(R_X + X_TRAVEL2, i)] = select(alive & ext, tr2n, tr2)


@njit(cache=True, error_model="numpy")
def _belt_effects(dt, FB, nb, FR):
    """Rows R_X.. of a block that shares a plant with a compliant belt: the joints and
    rotors advanced together over the tick as :func:`leglib.twin.effects._belt_advance`
    advances them (its sub-steps the outer loop, so that the loop over the legs is the
    inner one and vectorizes), for the legs whose row R_GO says so."""
    n = int(FR[0, F_BELT_SUB])
    h = dt / n
    jm = FR[0, F_JM]
    k, c, half = FR[0, F_BELT_K], FR[0, F_BELT_C], FR[0, F_BACKLASH_HALF]
    for _ in range(n):
        for i in range(nb):
            go = FB[_at(R_GO, i)] != 0.0
            q1, dq1, q2, dq2 = (FB[_at(R_X + X_Q1, i)], FB[_at(R_X + X_DQ1, i)], FB[_at(R_X + X_Q2, i)],
                                FB[_at(R_X + X_DQ2, i)])
            p1, dp1, p2, dp2 = (FB[_at(R_X + X_PHI1, i)], FB[_at(R_X + X_DPHI1, i)], FB[_at(R_X + X_PHI2, i)],
                                FB[_at(R_X + X_DPHI2, i)])
            d11, d12, d22, det = FB[_at(R_D11, i)], FB[_at(R_D12, i)], FB[_at(R_D22, i)], FB[_at(R_DET, i)]
            t1 = _belt_torque_v(p1 - q1, dp1 - dq1, k, c, half)
            t2 = _belt_torque_v(p2 - q2, dp2 - dq2, k, c, half)
            dq1n = dq1 + (FB[_at(R_O1, i)] + (d22 * t1 - d12 * t2) / det) * h
            dq2n = dq2 + (FB[_at(R_O2, i)] + (-d12 * t1 + d11 * t2) / det) * h
            dp1n = dp1 + (FB[_at(R_TM1, i)] - t1) / jm * h
            dp2n = dp2 + (FB[_at(R_TM2, i)] - t2) / jm * h
            FB[_at(R_X + X_Q1, i)] = select(go, q1 + dq1n * h, q1)
            FB[_at(R_X + X_Q2, i)] = select(go, q2 + dq2n * h, q2)
            FB[_at(R_X + X_PHI1, i)] = select(go, p1 + dp1n * h, p1)
            FB[_at(R_X + X_PHI2, i)] = select(go, p2 + dp2n * h, p2)
            FB[_at(R_X + X_DQ1, i)] = select(go, dq1n, dq1)
            FB[_at(R_X + X_DQ2, i)] = select(go, dq2n, dq2)
            FB[_at(R_X + X_DPHI1, i)] = select(go, dp1n, dp1)
            FB[_at(R_X + X_DPHI2, i)] = select(go, dp2n, dp2)
    for i in range(nb):
        t = FB[_at(R_X + X_T, i)]
        FB[_at(R_X + X_T, i)] = select(FB[_at(R_GO, i)] != 0.0, t + dt, t)


@njit(cache=True, error_model="numpy")
def _mechanics_effects(dt, FB, IB, nb, P, FR, MECH, DRV):
    """One tick of the mechanics of a block of ``nb`` legs that share one plant with
    unmodeled effects (P, FR, MECH: its one row): the operations of :func:`_mechanics_leg`
    in the same order, in loops over the legs that vectorize -- the cogging
    (:func:`_cogging_effects`), the friction (:func:`_friction_effects`), the five-bar
    and the stops, the compliant belt (:func:`_belt_effects`); the same numbers. The legs' state is in rows R_X.. of FB, the motor torques in
    rows R_TAU (the cogging added there); rows R_Q.. get what the encoders see next (the
    rotors with a compliant belt); a dead leg (IB row R_DEAD) keeps its state; IB row R_NF
    is set where the accelerations came out non-finite (the caller stops the leg; its
    friction state has advanced, as on the leg-by-leg path)."""
    Pb = _param_row(P, 0)
    belt = FR[0, F_BELT_K] > 0.0
    fivebar = MECH[0] == 0
    j1, j2 = FR[0, 11], FR[0, 12]
    gap_min, k_stop, c_stop, gap_max = FR[0, 8], FR[0, 9], FR[0, 10], FR[0, 13]
    k_belt, c_belt, half = FR[0, F_BELT_K], FR[0, F_BELT_C], FR[0, F_BACKLASH_HALF]
    if FR[0, F_COG_ON] > 0.0:
        _cogging_effects(FB, nb, FR, DRV)
    _friction_effects(dt, FB, IB, nb, FR)
    for i in range(nb):
        q1, dq1 = FB[_at(R_X + X_Q1, i)], FB[_at(R_X + X_DQ1, i)]
        q2, dq2 = FB[_at(R_X + X_Q2, i)], FB[_at(R_X + X_DQ2, i)]
        t = FB[_at(R_X + X_T, i)]
        tau1, tau2 = FB[_at(R_TAU, i)], FB[_at(R_TAU + 1, i)]
        # the compliant belt: the motor torques go to the rotors, the joints get the belt's
        bt1 = _belt_torque_v(FB[_at(R_X + X_PHI1, i)] - q1, FB[_at(R_X + X_DPHI1, i)] - dq1, k_belt, c_belt, half)
        bt2 = _belt_torque_v(FB[_at(R_X + X_PHI2, i)] - q2, FB[_at(R_X + X_DPHI2, i)] - dq2, k_belt, c_belt, half)
        tj1 = select(belt, bt1, tau1)
        tj2 = select(belt, bt2, tau2)
        s_q1, c_q1 = _sincos(q1)
        s_q2, c_q2 = _sincos(q2)
        r5 = _fivebar_reduced(c_q1, s_q1, c_q2, s_q2, dq1, dq2, Pb)
        d11 = select(fivebar, r5[0], j1)
        d12 = select(fivebar, r5[1], 0.0)
        d22 = select(fivebar, r5[2], j2)
        b1 = select(fivebar, r5[3], 0.0)
        b2 = select(fivebar, r5[4], 0.0)
        t1 = tj1 - b1 - FB[_at(R_F1, i)]
        t2 = tj2 - b2 - FB[_at(R_F2, i)]
        a1, a2, det, ok = _stops_and_accelerations(q1, dq1, q2, dq2, t1, t2, d11, d12, d22, fivebar, gap_min, k_stop,
                                                   c_stop, gap_max)
        alive = IB[_at(R_DEAD, i)] == 0
        IB[_at(R_NF, i)] = select(alive & (not ok), 1, 0)
        go = alive & ok
        # a rigid belt: the joints advance here; a compliant one: in _belt_effects
        rigid = go & (not belt)
        dq1n = dq1 + a1 * dt
        dq2n = dq2 + a2 * dt
        FB[_at(R_X + X_Q1, i)] = select(rigid, q1 + dq1n * dt, q1)
        FB[_at(R_X + X_DQ1, i)] = select(rigid, dq1n, dq1)
        FB[_at(R_X + X_Q2, i)] = select(rigid, q2 + dq2n * dt, q2)
        FB[_at(R_X + X_DQ2, i)] = select(rigid, dq2n, dq2)
        FB[_at(R_X + X_T, i)] = select(rigid, t + dt, t)
        FB[_at(R_GO, i)] = select(go, 1.0, 0.0)
        FB[_at(R_TM1, i)] = tau1
        FB[_at(R_TM2, i)] = tau2
        FB[_at(R_O1, i)] = a1 - (d22 * tj1 - d12 * tj2) / det
        FB[_at(R_O2, i)] = a2 - (-d12 * tj1 + d11 * tj2) / det
        FB[_at(R_D11, i)] = d11
        FB[_at(R_D12, i)] = d12
        FB[_at(R_D22, i)] = d22
        FB[_at(R_DET, i)] = det
    if belt:
        _belt_effects(dt, FB, nb, FR)
    for i in range(nb):     # what the encoders see: the rotors with a compliant belt
        FB[_at(R_Q, i)] = select(belt, FB[_at(R_X + X_PHI1, i)], FB[_at(R_X + X_Q1, i)])
        FB[_at(R_Q + 1, i)] = select(belt, FB[_at(R_X + X_DPHI1, i)], FB[_at(R_X + X_DQ1, i)])
        FB[_at(R_Q + 2, i)] = select(belt, FB[_at(R_X + X_PHI2, i)], FB[_at(R_X + X_Q2, i)])
        FB[_at(R_Q + 3, i)] = select(belt, FB[_at(R_X + X_DPHI2, i)], FB[_at(R_X + X_DQ2, i)])
        FB[_at(R_Q + 4, i)] = FB[_at(R_X + X_T, i)]
