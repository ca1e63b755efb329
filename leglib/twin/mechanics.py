"""The leg's mechanics in the twin's tick: one semi-implicit Euler step of the exact
five-bar with gravity, friction and the stop between the upper links.

:func:`_mechanics_leg` steps one leg of any plant (the unmodeled effects included);
:func:`_mechanics_plain` steps a block of legs that share a plain plant, branch-free so
that its loop over the legs vectorizes, with the same operations in the same order (the
same numbers).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..abort import ABORT_NONFINITE
from ..kernelmath import sincos as _sincos
from ..kernelmath import tanh as _tanh
from ..model.terms import _fivebar_reduced
from .effects import (
    _add_cogging,
    _belt_advance,
    _belt_split,
    _joint_friction,
    _stribeck,
)
from .layout import (
    F_BELT_K,
    F_COG_ON,
    F_FRIC_EXT,
    I_MODE,
    LANES,
    MODE_IDLE,
    R_DEAD,
    R_NF,
    R_Q,
    R_TAU,
)


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
