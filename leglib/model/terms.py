"""The compiled terms of the leg's dynamics: the sympy derivation's generated code
(:mod:`leglib.model._generated`) evaluated for one pose or for many at once.

Everything here is a numba function over the parameter vector of
:func:`param_vector` (the order of :data:`leglib.model.derivation.PARAM_NAMES`); the
readable functions of :mod:`leglib.model.kinematics` and :mod:`leglib.model.dynamics` call
them, and the twin's kernel inlines :func:`_fivebar_reduced`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .. import _numba_gc, _numba_inline  # noqa: F401  (before any kernel compiles)
from ..params import LegParams
from . import _generated as gen
from .param_names import PARAM_NAMES

MODELS = ("fivebar", "parallelogram")
STATE_NAMES = ("q1", "dq1", "q2", "dq2")
COULOMB_VELOCITY = 1e-3  # rad/s: default width of the smooth (tanh) Coulomb term


def param_vector(leg: LegParams) -> np.ndarray:
    """The parameter vector P (order of ``derivation.PARAM_NAMES``) the kernels take."""
    return np.array([float(getattr(leg, n)) for n in PARAM_NAMES])


def _check_model(model: str) -> str:
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    return model


@njit(cache=True, inline="always")
def _foot_cs(c1, s1, c2, s2, P):
    """The foot and the knees of the exact five-bar, from the unit vectors (c, s) = (cos,
    sin) of the joint angles q1, q2: (fx, fy, p1x, p1y, p2x, p2y) [m], hip at the origin.

    The foot is the intersection of the circles (P1, l4) and (P2, l3) on the far side of the
    line P1-P2 from the hip (knee-out branch). Valid for 0 < q2 - q1 < pi (mod 2 pi), the
    leg's assembly mode; the foot is NaN outside it and where the loop cannot close.
    """
    l1, l2, l3, l4 = P[0], P[1], P[2], P[3]
    p1x, p1y = l1 * c1, l1 * s1
    p2x, p2y = l2 * c2, l2 * s2
    if s2 * c1 - c2 * s1 <= 1e-9:  # sin(q2 - q1)
        return math.nan, math.nan, p1x, p1y, p2x, p2y
    dx, dy = p2x - p1x, p2y - p1y
    dd = dx * dx + dy * dy    # |P2 - P1|^2
    if dd < 1e-24 or dd > (l3 + l4) * (l3 + l4) or dd < (l4 - l3) * (l4 - l3):
        return math.nan, math.nan, p1x, p1y, p2x, p2y
    # along P1-P2 and along its normal (-dy, dx), in units of |P2 - P1|: one division and
    # one square root
    inv = 1.0 / dd
    ka = 0.5 * (l4 * l4 - l3 * l3 + dd) * inv
    kh = math.sqrt(max(l4 * l4 * inv - ka * ka, 0.0))
    side = dy * p1x - dx * p1y  # where the hip lies relative to the line P1-P2
    if side > 0:
        kh = -kh
    fx = p1x + ka * dx - kh * dy
    fy = p1y + ka * dy + kh * dx
    return fx, fy, p1x, p1y, p2x, p2y


@njit(cache=True)
def _lower_angles(q1, q2, P):
    """Absolute angles (phi3, phi4) of the lower links for joint angles q1, q2 [rad] (see
    :func:`_foot_cs`); NaNs outside the assembly mode and where the loop cannot close."""
    fx, fy, p1x, p1y, p2x, p2y = _foot_cs(math.cos(q1), math.sin(q1), math.cos(q2), math.sin(q2), P)
    return math.atan2(fy - p2y, fx - p2x), math.atan2(fy - p1y, fx - p1x)


@njit(cache=True, inline="always")
def _fivebar_reduced(c1, s1, c2, s2, dq1, dq2, P):
    """Reduced dynamics of the exact five-bar at one point, from the unit vectors (c, s) =
    (cos, sin) of q1, q2: no trigonometric call (the loop closure gives the lower links'
    unit vectors, :func:`leglib.model._generated.fivebar_terms_cs` the maximal-coordinate terms).

    Returns (D11, D12, D22, b1, b2, c3, s3, c4, s4, dphi3, dphi4): D the 2x2 inertia matrix
    on q and b = S^T (M a0 + h + G) the velocity-product plus gravity torque, so that
    D ddq + b = tau (before friction); (c3, s3), (c4, s4) the unit vectors of phi3, phi4.
    P may be the parameter vector or a tuple of its entries (hoisted by a caller's loop).
    """
    l3, l4 = P[2], P[3]
    fx, fy, p1x, p1y, p2x, p2y = _foot_cs(c1, s1, c2, s2, P)
    # lower links: u3 = (F - P2) / l3, u4 = (F - P1) / l4
    e3x, e3y = fx - p2x, fy - p2y
    e4x, e4y = fx - p1x, fy - p1y
    inv_l3, inv_l4 = 1.0 / l3, 1.0 / l4
    c3, s3 = e3x * inv_l3, e3y * inv_l3
    c4, s4 = e4x * inv_l4, e4y * inv_l4
    # Phi_phi = [-l3 u'(phi3), l4 u'(phi4)], Phi_q = [l1 u'(q1), -l2 u'(q2)], u' = (-sin, cos)
    a11, a21 = e3y, -e3x
    a12, a22 = -e4y, e4x
    inv_det = 1.0 / (a11 * a22 - a12 * a21)
    b11, b21 = -p1y, p1x
    b12, b22 = p2y, -p2x
    # J = -Phi_phi^{-1} Phi_q  (dphi = J dq)
    j11 = -(a22 * b11 - a12 * b21) * inv_det
    j12 = -(a22 * b12 - a12 * b22) * inv_det
    j21 = -(-a21 * b11 + a11 * b21) * inv_det
    j22 = -(-a21 * b12 + a11 * b22) * inv_det
    dphi3 = j11 * dq1 + j12 * dq2
    dphi4 = j21 * dq1 + j22 * dq2
    # acceleration of (phi3, phi4) at ddq = 0: Phi_phi a0 = w
    w1, w2, w3, w4 = dq1 * dq1, dq2 * dq2, dphi3 * dphi3, dphi4 * dphi4
    wx = p1x * w1 + e4x * w4 - p2x * w2 - e3x * w3
    wy = p1y * w1 + e4y * w4 - p2y * w2 - e3y * w3
    a03 = (a22 * wx - a12 * wy) * inv_det
    a04 = (-a21 * wx + a11 * wy) * inv_det
    t = gen.fivebar_terms_cs(c1, s1, c2, s2, c3, s3, c4, s4, dq1, dq2, dphi3, dphi4, P)
    # M row-major 4x4 in t[0:16], h in t[16:20], G in t[20:24]. M is diagonal but for the
    # coupling of each upper link with the lower link it carries, M03 = M30 (links 1, 4)
    # and M12 = M21 (links 2, 3) (tests/test_model.py checks the generated form)
    m00, m03, m11, m12, m22, m33 = t[0], t[3], t[5], t[6], t[10], t[15]
    # S = [[1, 0], [0, 1], [j11, j12], [j21, j22]]: D = S^T M S, b = S^T (M a0 + h + G)
    f0 = m03 * a04 + (t[16] + t[20])
    f1 = m12 * a03 + (t[17] + t[21])
    f2 = m22 * a03 + (t[18] + t[22])
    f3 = m33 * a04 + (t[19] + t[23])
    d11 = m00 + j21 * (2.0 * m03 + m33 * j21) + m22 * j11 * j11
    d12 = (m03 * j22 + m12 * j11) + (m22 * j11 * j12 + m33 * j21 * j22)
    d22 = m11 + j12 * (2.0 * m12 + m22 * j12) + m33 * j22 * j22
    bb1 = f0 + (j11 * f2 + j21 * f3)
    bb2 = f1 + (j12 * f2 + j22 * f3)
    return d11, d12, d22, bb1, bb2, c3, s3, c4, s4, dphi3, dphi4


@njit(cache=True)
def _fivebar_dynamics(q1, q2, dq1, dq2, P):
    """Reduced dynamics of the exact five-bar at one point.

    Returns (D11, D12, D22, b1, b2, phi3, phi4, dphi3, dphi4) with D the 2x2 inertia
    matrix on q and b = S^T (M a0 + h + G) the velocity-product plus gravity torque, so
    that D ddq + b = tau (before friction). See :func:`_fivebar_reduced`.
    """
    r = _fivebar_reduced(math.cos(q1), math.sin(q1), math.cos(q2), math.sin(q2), dq1, dq2, P)
    return r[0], r[1], r[2], r[3], r[4], math.atan2(r[6], r[5]), math.atan2(r[8], r[7]), r[9], r[10]


@njit(cache=True)
def _parallelogram_dynamics(q1, q2, dq1, dq2, P):
    """Model (a) at one point: (D11, D12, D22, b1, b2) with D ddq + b = tau."""
    t = gen.parallelogram_terms(q1, q2, dq1, dq2, P)
    return t[0], t[1], t[3], t[4] + t[6], t[5] + t[7]


@njit(cache=True)
def _friction(dq1, dq2, F):
    """Joint friction torques. F = (c11, c12, c21, c22, coulomb1, coulomb2, v_smooth[,
    stribeck1, stribeck2, v_stribeck]): viscous matrix, Coulomb smoothed as
    tanh(v / v_smooth), optional Stribeck excess times exp(-(v / v_stribeck)^2)."""
    f1 = F[0] * dq1 + F[1] * dq2
    f2 = F[2] * dq1 + F[3] * dq2
    c1, c2 = F[4], F[5]
    if F.size > 7:
        c1 += F[7] * math.exp(-(dq1 / F[9]) ** 2)
        c2 += F[8] * math.exp(-(dq2 / F[9]) ** 2)
    return f1 + c1 * math.tanh(dq1 / F[6]), f2 + c2 * math.tanh(dq2 / F[6])


@njit(cache=True)
def _simulate_table(model_id, P, F, x0, tau, table_dt, substeps, out):
    """Semi-implicit Euler under a zero-order-held torque table.

    x0 = (q1, dq1, q2, dq2); tau (N, 2) joint torques, one row per ``table_dt``; out (N, 4)
    receives the state at the start of each row. Returns the number of rows simulated
    (less than N when the model left its valid configuration).
    """
    q1, dq1, q2, dq2 = x0[0], x0[1], x0[2], x0[3]
    h = table_dt / substeps
    for i in range(tau.shape[0]):
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = q1, dq1, q2, dq2
        for _ in range(substeps):
            a1, a2 = _accel(model_id, q1, q2, dq1, dq2, tau[i, 0], tau[i, 1], P, F)
            if not (math.isfinite(a1) and math.isfinite(a2)):
                return i
            dq1 += a1 * h
            dq2 += a2 * h
            q1 += dq1 * h
            q2 += dq2 * h
    return tau.shape[0]


@njit(cache=True)
def _accel(model_id, q1, q2, dq1, dq2, tau1, tau2, P, F):
    """Joint accelerations. model_id 0: five-bar, 1: parallelogram."""
    if model_id == 0:
        r = _fivebar_dynamics(q1, q2, dq1, dq2, P)
        d11, d12, d22, b1, b2 = r[0], r[1], r[2], r[3], r[4]
    else:
        d11, d12, d22, b1, b2 = _parallelogram_dynamics(q1, q2, dq1, dq2, P)
    f1, f2 = _friction(dq1, dq2, F)
    r1 = tau1 - b1 - f1
    r2 = tau2 - b2 - f2
    det = d11 * d22 - d12 * d12
    return (d22 * r1 - d12 * r2) / det, (-d12 * r1 + d11 * r2) / det


@njit(cache=True)
def _batch_terms(model_id, q1, q2, dq1, dq2, P, out):
    for i in range(q1.size):
        if model_id == 0:
            r = _fivebar_dynamics(q1[i], q2[i], dq1[i], dq2[i], P)
            for k in range(5):
                out[i, k] = r[k]
        else:
            r2 = _parallelogram_dynamics(q1[i], q2[i], dq1[i], dq2[i], P)
            for k in range(5):
                out[i, k] = r2[k]


@njit(cache=True)
def _batch_lower_angles(q1, q2, P, out):
    for i in range(q1.size):
        out[i, 0], out[i, 1] = _lower_angles(q1[i], q2[i], P)


@njit(cache=True, nogil=True)
def _batch_foot(q1, q2, P, out):
    """Foot positions of the points (rows of ``out``); called on parts of a batch from
    threads (elementwise: the same numbers)."""
    for i in range(q1.size):
        r = _foot_cs(math.cos(q1[i]), math.sin(q1[i]), math.cos(q2[i]), math.sin(q2[i]), P)
        out[i, 0], out[i, 1] = r[0], r[1]


PARALLEL_POINTS = 50_000   # from about this many points a thread pool pays (a sweep: 300 000)


@njit(cache=True)
def _batch_energy(model_id, q1, q2, dq1, dq2, P, out):
    for i in range(q1.size):
        if model_id == 0:
            r = _fivebar_dynamics(q1[i], q2[i], dq1[i], dq2[i], P)
            e = gen.fivebar_energy(q1[i], q2[i], r[5], r[6], dq1[i], dq2[i], r[7], r[8], P)
        else:
            e = gen.parallelogram_energy(q1[i], q2[i], dq1[i], dq2[i], P)
        out[i, 0], out[i, 1] = e[0], e[1]


def _flat(*arrays):
    b = np.broadcast_arrays(*[np.asarray(a, dtype=float) for a in arrays])
    return b[0].shape, [np.ascontiguousarray(x).ravel() for x in b]
