"""The leg's dynamics (thesis 5.1-5.2): mass matrix, gravity and bias torques, energy, forward
dynamics and simulation, for the exact five-bar (``model="fivebar"``) and the thesis's
parallelogram model (``"parallelogram"``, eq. 5.4).

SI units throughout: rad, rad/s, N*m, kg*m^2.
"""

from __future__ import annotations

import math

import numpy as np

from ..params import LegParams
from .terms import (
    COULOMB_VELOCITY,
    MODELS,
    _accel,
    _batch_energy,
    _batch_terms,
    _check_model,
    _flat,
    _simulate_table,
    param_vector,
)


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


def held_torque_stepper(leg: LegParams, period: float, substeps: int, model: str = "fivebar", friction=None):
    """A function ``step(x, tau) -> x_next``: the state (4,) one ``period`` later under the
    joint torques ``tau`` (2,) held over it, in ``substeps`` steps -- what
    :func:`simulate_torque_table` gives for a table of one torque, with the leg's
    parameters, the friction vector and the buffers prepared once (a sampled closed loop
    calls it every period). The next state is NaN where the model left its valid
    configuration."""
    mid = MODELS.index(_check_model(model))
    P = param_vector(leg)
    F = friction_vector(leg) if friction is None else np.asarray(friction, dtype=float)
    h = period / substeps
    tau_rows = np.empty((substeps + 1, 2))
    out = np.empty((substeps + 1, 4))

    def step(x, tau):
        tau_rows[:] = tau
        if _simulate_table(mid, P, F, np.asarray(x, dtype=float), tau_rows, h, 1, out) < substeps + 1:
            return np.full(4, np.nan)
        return out[-1].copy()

    return step


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
    leg : LegParams
    t : (N,) output times [s], increasing
    x0 : (4,) initial state (q1, dq1, q2, dq2) [rad, rad/s]
    tau : None (zero), a (2,) constant, an (N, 2) table (zero-order hold on ``t``), or a
        callable ``tau(t, x) -> (2,)`` [N*m]
    model : {"fivebar", "parallelogram"}
        The exact five-bar or the thesis's model (a).
    friction : bool
        Include the leg's viscous and Coulomb friction.
    rtol, atol : float
        The integrator's tolerances.
    Returns
    -------
    x : (N, 4) states at ``t``
    """

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

    from scipy.integrate import solve_ivp  # load time: scipy.integrate (0.7 s), only for this reference simulation

    sol = solve_ivp(rhs, (t[0], t[-1]), np.asarray(x0, dtype=float), t_eval=t, method="DOP853",
                    rtol=rtol, atol=atol, max_step=(t[1] - t[0]) if t.size > 1 else np.inf)
    if not sol.success:
        raise RuntimeError(f"simulate: integration failed: {sol.message}")
    return sol.y.T
