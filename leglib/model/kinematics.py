"""The leg's kinematics (thesis 5.1): the exact coaxial five-bar's lower-link angles, foot
position and its inverse, the leg length, the workspace, and the thesis's own height
measures (eq. 6.5 and Listing 7.7).

Joint angles ``q1``, ``q2`` are the absolute angles of the upper links [rad] (from +x,
counter-clockwise); positions are in metres.
"""

from __future__ import annotations

import numpy as np

from ..cores import cores, over_cores
from ..params import LegParams
from .terms import (
    PARALLEL_POINTS,
    _batch_foot,
    _batch_lower_angles,
    _flat,
    param_vector,
)


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
    leg : LegParams
        The leg's geometry (link lengths).
    q1, q2 : float or array_like [rad]
        Absolute angles of the upper links; broadcast together.

    Returns
    -------
    x, y : ndarray [m]
        The shape of ``q1`` and ``q2`` broadcast; NaN where the five-bar cannot close.
    """
    shape, (a, b) = _flat(q1, q2)
    out = np.empty((a.size, 2))
    P = param_vector(leg)
    # a part per core from PARALLEL_POINTS points on: each point alone, the same numbers
    over_cores(lambda i0, i1: _batch_foot(a[i0:i1], b[i0:i1], P, out[i0:i1]), a.size, -(-a.size // cores()),
               serial_below=PARALLEL_POINTS)
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
