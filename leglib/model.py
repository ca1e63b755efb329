"""Numeric five-bar model: kinematics, forward dynamics, energy, linearization, simulation.

Two models (see :mod:`leglib.derivation`):

- ``"parallelogram"``: the thesis's model (a), eqs. 5.1-5.7;
- ``"fivebar"``: the exact coaxial five-bar (b), reduced from maximal coordinates onto
  q = (q1, q2) through the loop-closure constraint.

Units: SI throughout (rad, rad/s, N*m, m). Joint angles are absolute, from +x,
counter-clockwise; at the operating point (267 deg, 273 deg) the leg hangs down.

The per-point functions are numba-compiled scalars (``_fivebar_dynamics`` etc.) shared with
the twin's batch kernel (:mod:`leglib.twin`); the public functions accept scalars or arrays.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from . import _generated as gen
from .derivation import PARAM_NAMES
from .params import LegParams

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


# ---------------------------------------------------------------------------------------
# compiled per-point kernels
# ---------------------------------------------------------------------------------------

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
    unit vectors, :func:`leglib._generated.fivebar_terms_cs` the maximal-coordinate terms).

    Returns (D11, D12, D22, b1, b2, c3, s3, c4, s4, dphi3, dphi4): D the 2x2 inertia matrix
    on q and b = S^T (M a0 + h + G) the velocity-product plus gravity torque, so that
    D ddq + b = tau (before friction); (c3, s3), (c4, s4) the unit vectors of phi3, phi4.
    P may be the parameter vector or a tuple of its entries (hoisted by a caller's loop).
    """
    l1, l2, l3, l4 = P[0], P[1], P[2], P[3]
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


@njit(cache=True)
def _batch_foot(q1, q2, P, out):
    for i in range(q1.size):
        r = _foot_cs(math.cos(q1[i]), math.sin(q1[i]), math.cos(q2[i]), math.sin(q2[i]), P)
        out[i, 0], out[i, 1] = r[0], r[1]


@njit(cache=True, parallel=True)
def _batch_foot_parallel(q1, q2, P, out):
    """:func:`_batch_foot` on the cores present (elementwise: the same numbers)."""
    for i in prange(q1.size):
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


def friction_vector(leg: LegParams, scale: float = 1.0, v_smooth: float = COULOMB_VELOCITY,
                    stribeck=None) -> np.ndarray:
    """F as the kernels take it (see ``_friction``): the leg's viscous matrix and Coulomb
    terms times ``scale``, the Coulomb smoothing velocity, and optionally
    ``stribeck = (stribeck1, stribeck2, v_stribeck)``."""
    F = [scale * v for v in (leg.c11, leg.c12, leg.c21, leg.c22, leg.coulomb1, leg.coulomb2)]
    F.append(v_smooth)
    if stribeck is not None:
        F.extend(stribeck)
    return np.array(F, dtype=float)


def simulate_torque_table(leg: LegParams, x0, tau, table_dt: float, substeps: int = 4,
                          model: str = "fivebar", friction=None) -> np.ndarray:
    """Simulate the leg under a torque table (compiled; fast enough for fitting loops).

    Parameters
    ----------
    x0 : (4,) initial state (q1, dq1, q2, dq2)
    tau : (N, 2) joint torques [N*m], row i held over [i, i+1) * table_dt
    friction : None (the leg's own) or a friction vector (see :func:`friction_vector`;
        9 entries add Stribeck terms)
    Returns (N, 4) states at the start of each row; rows after a singularity are NaN.
    """
    mid = MODELS.index(_check_model(model))
    tau = np.ascontiguousarray(tau, dtype=float)
    F = friction_vector(leg) if friction is None else np.asarray(friction, dtype=float)
    out = np.full((tau.shape[0], 4), np.nan)
    _simulate_table(mid, param_vector(leg), F, np.asarray(x0, dtype=float), tau, float(table_dt),
                    int(substeps), out)
    return out


# ---------------------------------------------------------------------------------------
# kinematics
# ---------------------------------------------------------------------------------------

def lower_link_angles(leg: LegParams, q1, q2):
    """Absolute angles (phi3, phi4) [rad] of the lower links; NaN where the loop can't close."""
    shape, (a, b) = _flat(q1, q2)
    out = np.empty((a.size, 2))
    _batch_lower_angles(a, b, param_vector(leg), out)
    return out[:, 0].reshape(shape), out[:, 1].reshape(shape)


def foot_position(leg: LegParams, q1, q2):
    """Foot position (x, y) [m] of the exact five-bar, hip at the origin.

    Parameters
    ----------
    q1, q2 : float or array_like [rad]
        Absolute angles of the upper links; broadcast together.
    """
    shape, (a, b) = _flat(q1, q2)
    out = np.empty((a.size, 2))
    (_batch_foot_parallel if a.size >= PARALLEL_POINTS else _batch_foot)(a, b, param_vector(leg), out)
    return out[:, 0].reshape(shape), out[:, 1].reshape(shape)


def inverse_kinematics(leg: LegParams, x, y):
    """Joint angles (q1, q2) [rad] that put the foot at (x, y) [m] (knee-out branch).

    Raises ValueError for a point outside the reachable annulus.
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    r = np.hypot(x, y)
    psi = np.arctan2(y, x)
    c1 = (leg.l1 ** 2 + r ** 2 - leg.l4 ** 2) / (2 * leg.l1 * np.where(r > 0, r, np.nan))
    c2 = (leg.l2 ** 2 + r ** 2 - leg.l3 ** 2) / (2 * leg.l2 * np.where(r > 0, r, np.nan))
    bad = ~(np.isfinite(c1) & np.isfinite(c2) & (np.abs(c1) <= 1) & (np.abs(c2) <= 1))
    if np.any(bad):
        raise ValueError(f"inverse_kinematics: {int(np.sum(bad))} point(s) outside the workspace "
                         f"(foot distance from hip must lie in the reachable annulus)")
    q1 = np.mod(psi - np.arccos(c1), 2 * np.pi)
    q2 = np.mod(psi + np.arccos(c2), 2 * np.pi)
    return q1, q2


def thesis_foot_height(leg: LegParams, q1, q2):
    """The thesis's foot height, eq. 6.5: y = l1 sin q1 + l2 sin q2 [m] (upper links only)."""
    return leg.l1 * np.sin(q1) + leg.l2 * np.sin(q2)


LISTING_LENGTH = 0.16  # m, the constant of Listing 7.7, line 29


def thesis_listing_height(q1_deg, q2_deg, length: float = LISTING_LENGTH):
    """The signal Listing 7.7 identifies: y = 0.16 cos(angle1) + 0.16 cos(angle2) [m].

    Unlike eq. 6.5 (l sin q of absolute angles), the listing takes the cosine of the angles
    *zeroed at the start of the step* (Listing 7.4 subtracts the first sample), in degrees.
    At rest y = 0.32 m; a step of +-48 deg on the two joints lowers it to 0.32 cos 48 deg.

    Parameters
    ----------
    q1_deg, q2_deg : array_like
        Joint-angle changes from the first sample [deg] (the thesis's CSV columns).
    length : float
        The listing's 0.16 [m].

    Returns
    -------
    ndarray, the listing's y [m]
    """
    return (length * np.cos(np.radians(np.asarray(q1_deg, dtype=float)))
            + length * np.cos(np.radians(np.asarray(q2_deg, dtype=float))))


def zeroed_degrees(q):
    """Joint angles [rad] as Listing 7.4 records them: change from the first sample [deg]."""
    q = np.asarray(q, dtype=float)
    return np.degrees(q - q[..., :1])


def leg_length(leg: LegParams, q1, q2):
    """Hip-to-foot distance [m] (Doggo's L = L1 cos(gamma) + sqrt(L2^2 - L1^2 sin^2(gamma)))."""
    x, y = foot_position(leg, q1, q2)
    return np.hypot(x, y)


def workspace_grid(leg: LegParams, n: int = 60, gap_deg=(6.0, 150.0), theta_deg=(230.0, 310.0)):
    """Joint-angle grid over the working range: q2 - q1 in gap_deg, (q1+q2)/2 in theta_deg.

    Returns (q1, q2) arrays of shape (n, n) [rad].
    """
    gap = np.radians(np.linspace(*gap_deg, n))
    theta = np.radians(np.linspace(*theta_deg, n))
    G, T = np.meshgrid(gap, theta, indexing="ij")
    return T - G / 2, T + G / 2


# ---------------------------------------------------------------------------------------
# dynamics
# ---------------------------------------------------------------------------------------

def _terms(leg, q1, q2, dq1=0.0, dq2=0.0, model="fivebar"):
    mid = MODELS.index(_check_model(model))
    shape, (a, b, c, d) = _flat(q1, q2, dq1, dq2)
    out = np.empty((a.size, 5))
    _batch_terms(mid, a, b, c, d, param_vector(leg), out)
    return shape, out


def mass_matrix(leg: LegParams, q1, q2, model: str = "fivebar") -> np.ndarray:
    """Inertia matrix D(q) on the joint angles, shape ``broadcast(q1, q2).shape + (2, 2)``."""
    shape, t = _terms(leg, q1, q2, model=model)
    D = np.stack([t[:, 0], t[:, 1], t[:, 1], t[:, 2]], axis=-1).reshape(shape + (2, 2))
    return D


def gravity_torque(leg: LegParams, q1, q2, model: str = "fivebar") -> np.ndarray:
    """Gravity torque g(q) [N*m] on the joints, shape ``shape + (2,)``."""
    shape, t = _terms(leg, q1, q2, model=model)
    return t[:, 3:5].reshape(shape + (2,))


def bias_torque(leg: LegParams, q1, q2, dq1, dq2, model: str = "fivebar") -> np.ndarray:
    """Velocity-product plus gravity torque b(q, dq) [N*m], so that D ddq + b = tau."""
    shape, t = _terms(leg, q1, q2, dq1, dq2, model=model)
    return t[:, 3:5].reshape(shape + (2,))


def energy(leg: LegParams, q1, q2, dq1, dq2, model: str = "fivebar"):
    """Kinetic and potential energy (T, V) [J]."""
    mid = MODELS.index(_check_model(model))
    shape, (a, b, c, d) = _flat(q1, q2, dq1, dq2)
    out = np.empty((a.size, 2))
    _batch_energy(mid, a, b, c, d, param_vector(leg), out)
    return out[:, 0].reshape(shape), out[:, 1].reshape(shape)


def forward_dynamics(leg: LegParams, q, dq, tau, model: str = "fivebar", friction: bool = True):
    """Joint accelerations ddq [rad/s^2] for one state.

    Parameters
    ----------
    q, dq : (2,) joint angles [rad] and velocities [rad/s]
    tau : (2,) joint torques [N*m]
    friction : include the leg's damping matrix and Coulomb terms
    """
    mid = MODELS.index(_check_model(model))
    F = friction_vector(leg, 1.0 if friction else 0.0)
    return np.array(_accel(mid, float(q[0]), float(q[1]), float(dq[0]), float(dq[1]),
                           float(tau[0]), float(tau[1]), param_vector(leg), F))


def equilibrium_torque(leg: LegParams, q0=None, model: str = "parallelogram") -> np.ndarray:
    """Torques [N*m] holding the leg at rest at ``q0`` (default: the operating point)."""
    q0 = leg.q0 if q0 is None else q0
    return gravity_torque(leg, q0[0], q0[1], model=model)


def simulate(leg: LegParams, t, x0, tau=None, model: str = "fivebar", friction: bool = True,
             rtol: float = 1e-9, atol: float = 1e-11):
    """Integrate the nonlinear model with scipy's DOP853.

    Parameters
    ----------
    t : (N,) output times [s], increasing
    x0 : (4,) initial state (q1, dq1, q2, dq2)
    tau : None (zero), a (2,) constant, an (N, 2) table (zero-order hold on ``t``), or a
        callable ``tau(t, x) -> (2,)`` [N*m]
    Returns
    -------
    x : (N, 4) states at ``t``
    """
    from scipy.integrate import solve_ivp

    t = np.asarray(t, dtype=float)
    mid = MODELS.index(_check_model(model))
    P = param_vector(leg)
    F = friction_vector(leg, 1.0 if friction else 0.0)
    if tau is None:
        torque = lambda tt, x: (0.0, 0.0)  # noqa: E731
    elif callable(tau):
        torque = tau
    else:
        table = np.asarray(tau, dtype=float)
        if table.shape == (2,):
            torque = lambda tt, x: table  # noqa: E731
        elif table.shape == (t.size, 2):
            torque = lambda tt, x: table[min(max(np.searchsorted(t, tt, "right") - 1, 0),  # noqa: E731
                                             t.size - 1)]
        else:
            raise ValueError(f"tau must be (2,) or ({t.size}, 2), got shape {table.shape}")

    def rhs(tt, x):
        u = torque(tt, x)
        a1, a2 = _accel(mid, x[0], x[2], x[1], x[3], float(u[0]), float(u[1]), P, F)
        if not (math.isfinite(a1) and math.isfinite(a2)):
            raise ValueError(
                f"simulate: the {model} model is singular at t = {tt:.6g} s, q = "
                f"({math.degrees(x[0]):.3f}, {math.degrees(x[2]):.3f}) deg (the loop cannot "
                f"close, or upper links coincide); keep q2 - q1 inside (0, 180) deg")
        return (x[1], a1, x[3], a2)

    sol = solve_ivp(rhs, (t[0], t[-1]), np.asarray(x0, dtype=float), t_eval=t, method="DOP853",
                    rtol=rtol, atol=atol, max_step=(t[1] - t[0]) if t.size > 1 else np.inf)
    if not sol.success:
        raise RuntimeError(f"simulate: integration failed: {sol.message}")
    return sol.y.T


# ---------------------------------------------------------------------------------------
# linearization
# ---------------------------------------------------------------------------------------

def _thesis_decoupled_AB(leg: LegParams, q0):
    """Listing 7.5's linearization: d12 dropped, D constant, g2 with +m4 lc4."""
    d11 = leg.m1 * leg.lc1 ** 2 + leg.m3 * leg.lc3 ** 2 + leg.m4 * leg.l1 ** 2 + leg.I1 + leg.I3 + leg.Jd1
    d22 = leg.m2 * leg.lc2 ** 2 + leg.m3 * leg.l2 ** 2 + leg.m4 * leg.lc4 ** 2 + leg.I2 + leg.I4 + leg.Jd2
    k1 = leg.m1 * leg.lc1 + leg.m3 * leg.lc3 + leg.m4 * leg.l1
    # Listing 7.5's +m4 lc4: the sign this coaxial leg's exact five-bar supports (eq. 5.4's
    # minus is Spong's parallelogram; leglib.thesis.g2_sign_check)
    k2 = leg.m2 * leg.lc2 + leg.m3 * leg.l2 + leg.m4 * leg.lc4
    A = np.array([
        [0.0, 1.0, 0.0, 0.0],
        [leg.g * k1 * math.sin(q0[0]) / d11, -leg.c11 / d11, 0.0, -leg.c12 / d11],
        [0.0, 0.0, 0.0, 1.0],
        [0.0, -leg.c21 / d22, leg.g * k2 * math.sin(q0[1]) / d22, -leg.c22 / d22],
    ])
    B = np.array([[0.0, 0.0], [1.0 / d11, 0.0], [0.0, 0.0], [0.0, 1.0 / d22]])
    return A, B


def _numeric_AB(leg: LegParams, q0, model: str, eps: float = 1e-6):
    """Central-difference Jacobians of the nonlinear model at rest at q0 with u0 = g(q0)."""
    u0 = equilibrium_torque(leg, q0, model=model)
    x0 = np.array([q0[0], 0.0, q0[1], 0.0])

    def f(x, u):
        a1, a2 = forward_dynamics(leg, (x[0], x[2]), (x[1], x[3]), u, model=model)
        return np.array([x[1], a1, x[3], a2])

    A = np.empty((4, 4))
    B = np.empty((4, 2))
    for j in range(4):
        dx = np.zeros(4)
        dx[j] = eps
        A[:, j] = (f(x0 + dx, u0) - f(x0 - dx, u0)) / (2 * eps)
    for j in range(2):
        du = np.zeros(2)
        du[j] = eps
        B[:, j] = (f(x0, u0 + du) - f(x0, u0 - du)) / (2 * eps)
    # Coulomb friction is not differentiable at rest: linearize its viscous part only
    return A, B


def linearize(leg: LegParams, q0=None, coupled: bool = False, model: str = "parallelogram"):
    """Linearize the leg at rest at ``q0`` with the equilibrium torques.

    Parameters
    ----------
    leg : LegParams
    q0 : (q1, q2) [rad], default the leg's operating point (267 deg, 273 deg)
    coupled : False gives the thesis's decoupled form (Listing 7.5: d12 dropped, D constant,
        g2 with Listing 7.5's +m4 lc4, which eq. 5.11 was computed with); True gives the full
        coupled linearization of ``model``.
    model : "parallelogram" (the thesis's model a) or "fivebar" (exact model b); used when
        ``coupled`` is True.

    Returns
    -------
    control.StateSpace
        states (q1, dq1, q2, dq2) [rad, rad/s], inputs (tau1, tau2) [N*m], outputs (q1, q2).
    """
    import control

    q0 = leg.q0 if q0 is None else (float(q0[0]), float(q0[1]))
    if coupled:
        leg_viscous = leg.replace(coulomb1=0.0, coulomb2=0.0)
        A, B = _numeric_AB(leg_viscous, q0, _check_model(model))
    else:
        A, B = _thesis_decoupled_AB(leg, q0)
    C = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    D = np.zeros((2, 2))
    return control.ss(A, B, C, D, states=list(STATE_NAMES), inputs=["tau1", "tau2"],
                      outputs=["q1", "q2"], name=f"leg_{'coupled_' + model if coupled else 'thesis'}")


# eq. 5.11 as printed in the thesis (A[3,3] printed +30.22).
THESIS_A_PRINTED = np.array([[0, 1, 0, 0], [-66.12, -31.84, 0, 0.65],
                             [0, 0, 0, 1], [0, 0.62, -65.78, 30.22]], dtype=float)
THESIS_B = np.array([[0, 0], [324.85, 0], [0, 0], [0, 308.35]], dtype=float)
# ... and as it must read for positive damping.
THESIS_A = THESIS_A_PRINTED.copy()
THESIS_A[3, 3] = -30.22


def compare_models(leg: LegParams, n: int = 60, **grid) -> dict:
    """How far the thesis's model (a) is from the exact five-bar (b) over the working range.

    Returns a dict of (n, n) arrays on :func:`workspace_grid`: ``q1``, ``q2`` [rad],
    ``gap`` = q2 - q1 and ``theta`` = (q1 + q2)/2 [rad]; ``D_rel`` = ||D_a - D_b|| / ||D_b||
    (Frobenius); ``G_diff`` = ||G_a - G_b|| [N*m]; ``y_exact`` [m] the foot height and
    ``y_eq65`` [m] the thesis's eq. 6.5.
    """
    q1, q2 = workspace_grid(leg, n=n, **grid)
    Da = mass_matrix(leg, q1, q2, model="parallelogram")
    Db = mass_matrix(leg, q1, q2, model="fivebar")
    Ga = gravity_torque(leg, q1, q2, model="parallelogram")
    Gb = gravity_torque(leg, q1, q2, model="fivebar")
    _, y = foot_position(leg, q1, q2)
    return {
        "q1": q1, "q2": q2, "gap": q2 - q1, "theta": (q1 + q2) / 2,
        "D_rel": np.linalg.norm(Da - Db, axis=(-2, -1)) / np.linalg.norm(Db, axis=(-2, -1)),
        "G_diff": np.linalg.norm(Ga - Gb, axis=-1),
        "y_exact": y, "y_eq65": thesis_foot_height(leg, q1, q2),
    }
