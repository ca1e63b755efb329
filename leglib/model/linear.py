"""Linearization at the operating point (thesis 5.4, eq. 5.11) and the model comparison.

:func:`linearize` gives the thesis's form (Listing 7.5: decoupled, d12 dropped) or the
coupled one; :data:`THESIS_A` is eq. 5.11 with its sign error fixed.
"""

from __future__ import annotations

import math

import numpy as np

from ..params import LegParams
from .dynamics import equilibrium_torque, forward_dynamics, gravity_torque, mass_matrix
from .kinematics import foot_position, thesis_foot_height, workspace_grid
from .terms import STATE_NAMES, _check_model


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
    import control  # load time: python-control (about 2 s), only for a design's linear system

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
