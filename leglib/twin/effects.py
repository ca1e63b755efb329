"""What the twin's plant has and the fitting models lack: the unmodeled effects.

Each is called from the kernel only when the plant's parameters switch it on
(``plant_*.toml`` sections ``[belt]``, ``[cogging]``, ``[encoder_error]``, ``[friction]``):
a compliant belt with backlash, cogging torque, an encoder reading error, and LuGre,
direction-dependent and drifting friction; plus the Stribeck term of the plain friction.

Their sines, exponentials and tanh are :mod:`leglib.kernelmath`'s (within a few ulp of the
library's), and a harmonic's sine of the angle plus its phase is taken by angle addition
from one sincos of the angle and the phase's cosine and sine (FR columns the host computes
once). The functions ending in ``_v`` are the same effects for the vectorized mechanics of
a block of legs that share one plant (:func:`leglib.twin.mechanics._mechanics_effects`):
the same operations in the same order, branches turned into selects, so that a loop over
the legs calling them vectorizes. So the two paths give the same numbers, bit for bit.
"""

from __future__ import annotations

import math

from numba import njit

from .. import _numba_gc, _numba_inline  # noqa: F401  (before any kernel compiles)
from ..kernelmath import exp as _exp
from ..kernelmath import select
from ..kernelmath import sincos as _sincos
from ..kernelmath import tanh as _tanh
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
    F_COG_PERIODS,
    F_COG_S1,
    F_COG_S2,
    F_COG_S3,
    F_DRIFT,
    F_DRIFT_TRAVEL,
    F_ENC_A1,
    F_ENC_A2,
    F_ENC_C1,
    F_ENC_C2,
    F_ENC_S1,
    F_ENC_S2,
    F_JM,
    F_LUGRE_S0,
    F_LUGRE_S1,
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
    X_Z1,
)


@njit(cache=True, inline="always")
def _stribeck(excess, u):
    """excess * exp(-u^2), the Stribeck term; 0 without the call when there is none or
    when exp underflows (u^2 > 750)."""
    u2 = u * u
    if excess == 0.0 or u2 > 750.0:
        return 0.0 * excess
    return excess * _exp(-u2)


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
    return _encoder_error_v(turns, FR[b, F_ENC_A1], FR[b, F_ENC_C1], FR[b, F_ENC_S1], FR[b, F_ENC_A2],
                            FR[b, F_ENC_C2], FR[b, F_ENC_S2])


@njit(cache=True, inline="always")
def _cogging_torque(FR, b, turns):
    """Cogging torque on the rotor [N*m, motor side] at rotor angle ``turns``: harmonics 1-3
    of the cogging period (FR[b, F_COG_PERIODS] periods per turn). A sum of sines: it has a
    potential, so it stores no energy over a period."""
    return _cogging_torque_v(2.0 * math.pi * FR[b, F_COG_PERIODS] * turns, FR[b, F_COG_A1], FR[b, F_COG_A2],
                             FR[b, F_COG_A3], FR[b, F_COG_C1], FR[b, F_COG_S1], FR[b, F_COG_C2], FR[b, F_COG_S2],
                             FR[b, F_COG_C3], FR[b, F_COG_S3])


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
    s = 1.0 - FR[b, F_DRIFT] * (1.0 - _exp(-travel / FR[b, F_DRIFT_TRAVEL]))
    X[b, X_TRAVEL1 + j] = travel + abs(v) * dt
    sgn = 1.0 if v > 0.0 else -1.0
    g = s * (1.0 + sgn * FR[b, F_ASYM]) * (FR[b, 2 + j] + FR[b, 4 + j] * _exp(-(v / FR[b, 6]) ** 2))
    visc = s * FR[b, j] * v
    s0 = FR[b, F_LUGRE_S0]
    if s0 <= 0.0:
        return visc + g * _tanh(v / FR[b, 7])
    z = X[b, X_Z1 + j]
    z_new = z
    if v != 0.0:
        z_ss = sgn * g / s0
        z_new = z_ss + (z - z_ss) * _exp(-s0 * abs(v) * dt / g)
    X[b, X_Z1 + j] = z_new
    return s0 * z_new + FR[b, F_LUGRE_S1] * (z_new - z) / dt + visc


@njit(cache=True, inline="always")
def _encoder_error_v(turns, a1, cp1, sp1, a2, cp2, sp2):
    """The encoder's reading error at ``turns``, the plant's amplitudes and the cosines and
    sines of its phases as arguments: one sincos, the second harmonic by the double-angle
    formulas and the phases by angle addition."""
    s, c = _sincos(2.0 * math.pi * turns)
    s2 = 2.0 * s * c
    c2 = 1.0 - 2.0 * (s * s)
    err = a1 * (s * cp1 + c * sp1) + a2 * (s2 * cp2 + c2 * sp2)
    return err / (2.0 * math.pi)


@njit(cache=True, inline="always")
def _cogging_torque_v(th, a1, a2, a3, cp1, sp1, cp2, sp2, cp3, sp3):
    """The cogging torque at ``th`` = 2 pi periods turns, the plant's amplitudes and the
    cosines and sines of its phases as arguments: one sincos of ``th``, the second and
    third harmonics by the double- and triple-angle formulas and the phases by angle
    addition (within a few ulp of the library's sines of ``k th`` plus each phase)."""
    s, c = _sincos(th)
    ss = s * s
    s2 = 2.0 * s * c
    c2 = 1.0 - 2.0 * ss
    s3 = s * (3.0 - 4.0 * ss)
    c3 = c * (1.0 - 4.0 * ss)
    return (a1 * (s * cp1 + c * sp1) + a2 * (s2 * cp2 + c2 * sp2)) + a3 * (s3 * cp3 + c3 * sp3)


@njit(cache=True, inline="always")
def _belt_torque_v(stretch, rate, k, c, h):
    """:func:`_belt_torque`, branch-free: stiffness ``k``, damping ``c``, half the backlash
    ``h``."""
    dead = select(stretch > h, stretch - h, select(stretch < -h, stretch + h, 0.0))
    return k * dead + c * rate


@njit(cache=True, inline="always")
def _joint_friction_v(dt, v, travel, z, visc, coul, strib, v_strib, v_smooth, asym, drift, drift_travel, s0, s1,
                      ext, lugre, inv_v_strib, inv_v_smooth):
    """The friction torque of :func:`leglib.twin.mechanics._mechanics_leg` on a joint at
    velocity ``v``, branch-free: with ``ext`` :func:`_joint_friction` (``lugre``: sigma0 >
    0), the joint's accumulated ``travel`` and bristle deflection ``z`` and the plant's
    parameters as arguments; else the plain friction with :func:`_stribeck` (``inv_v_strib``,
    ``inv_v_smooth`` the reciprocals it multiplies by). The Stribeck exp and the tanh take
    the argument of the case's own path (one of each for both). Returns (friction torque,
    the new z, the new travel)."""
    s = 1.0 - drift * (1.0 - _exp(-travel / drift_travel))
    travel_new = travel + abs(v) * dt
    sgn = select(v > 0.0, 1.0, -1.0)
    u = select(ext, v / v_strib, v * inv_v_strib)
    u2 = u * u
    e_strib = _exp(-u2)
    th = _tanh(select(ext, v / v_smooth, v * inv_v_smooth))
    # the plain friction, _stribeck's term 0 without a Stribeck excess or past exp's underflow
    strib_plain = select((strib == 0.0) | (u2 > 750.0), 0.0 * strib, strib * e_strib)
    f_plain = visc * v + (coul + strib_plain) * th
    # the extended one
    g = s * (1.0 + sgn * asym) * (coul + strib * e_strib)
    visc_f = s * visc * v
    z_ss = sgn * g / s0
    z_new = select(v != 0.0, z_ss + (z - z_ss) * _exp(-s0 * abs(v) * dt / g), z)
    f_lugre = s0 * z_new + s1 * (z_new - z) / dt + visc_f
    f_ext = select(lugre, f_lugre, visc_f + g * th)
    return select(ext, f_ext, f_plain), select(lugre, z_new, z), travel_new
