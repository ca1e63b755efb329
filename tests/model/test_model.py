"""The five-bar model: eq. 5.11, kinematics, inertia matrix, energy, linearization."""

import math

import numpy as np
import pytest

from leglib import model as M
from leglib.model import _generated as gen
from leglib.model import kinematics, terms


def test_eq_5_11_reproduced_within_1_percent(leg):
    sys = M.linearize(leg)  # the thesis's decoupled form
    for ours, theirs in ((sys.A, M.THESIS_A), (sys.B, M.THESIS_B)):
        nz = theirs != 0
        np.testing.assert_array_equal(ours[~nz], 0.0)
        rel = np.abs(ours[nz] - theirs[nz]) / np.abs(theirs[nz])
        assert rel.max() < 0.01, rel


def test_printed_A33_is_unstable_and_corrected_is_stable():
    assert np.max(np.linalg.eigvals(M.THESIS_A_PRINTED).real) > 0
    assert np.max(np.linalg.eigvals(M.THESIS_A).real) < 0


def test_linearize_interface(leg):
    sys = M.linearize(leg, coupled=True)
    assert sys.nstates == 4 and sys.ninputs == 2 and sys.noutputs == 2
    assert list(sys.state_labels) == ["q1", "dq1", "q2", "dq2"]
    np.testing.assert_array_equal(sys.C, [[1, 0, 0, 0], [0, 0, 1, 0]])


def test_coupled_parallelogram_linearization_matches_symbolic_form(leg):
    # at rest: A_lower = -D^-1 dG/dq, damping -D^-1 Cd, B = D^-1, with D, G of model (a)
    q1, q2 = leg.q0
    D = M.mass_matrix(leg, q1, q2, model="parallelogram")
    k1 = leg.m1 * leg.lc1 + leg.m3 * leg.lc3 + leg.m4 * leg.l1
    k2 = leg.m2 * leg.lc2 + leg.m3 * leg.l2 - leg.m4 * leg.lc4  # eq. 5.4's sign (Spong's parallelogram)
    dG = np.diag([-leg.g * k1 * math.sin(q1), -leg.g * k2 * math.sin(q2)])
    Dinv = np.linalg.inv(D)
    sys = M.linearize(leg, coupled=True, model="parallelogram")
    np.testing.assert_allclose(sys.B[[1, 3]], Dinv, rtol=1e-6)
    np.testing.assert_allclose(sys.A[[1, 3]][:, [0, 2]], -Dinv @ dG, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(sys.A[[1, 3]][:, [1, 3]], -Dinv @ leg.damping_matrix, rtol=1e-5)


@pytest.mark.parametrize("model", M.MODELS)
def test_inertia_matrix_symmetric_positive_definite_over_workspace(leg, model):
    q1, q2 = M.workspace_grid(leg, n=40)
    D = M.mass_matrix(leg, q1, q2, model=model)
    np.testing.assert_array_equal(D, np.swapaxes(D, -1, -2))
    assert np.linalg.eigvalsh(D).min() > 0


def test_forward_inverse_kinematics_round_trip(leg):
    q1, q2 = M.workspace_grid(leg, n=50)
    x, y = M.foot_position(leg, q1, q2)
    r1, r2 = M.inverse_kinematics(leg, x, y)
    x2, y2 = M.foot_position(leg, r1, r2)
    assert np.max(np.hypot(x2 - x, y2 - y)) < 1e-9
    wrapped = np.angle(np.exp(1j * (r1 - q1)))
    np.testing.assert_allclose(wrapped, 0, atol=1e-9)


def test_kinematics_known_answers(leg):
    # symmetric pose: Doggo's closed form L = l1 cos(gamma) + sqrt(l3^2 - l1^2 sin^2(gamma))
    gamma = math.radians(-30)
    x, y = M.foot_position(leg, math.radians(270) + gamma, math.radians(270) - gamma)
    L = leg.l1 * math.cos(gamma) + math.sqrt(leg.l3 ** 2 - leg.l1 ** 2 * math.sin(gamma) ** 2)
    assert x == pytest.approx(0, abs=1e-12) and y == pytest.approx(-L, rel=1e-12)
    # lower links have their lengths
    q1, q2 = math.radians(250), math.radians(300)
    phi3, phi4 = M.lower_link_angles(leg, q1, q2)
    fx, fy = M.foot_position(leg, q1, q2)
    assert math.hypot(fx - leg.l2 * math.cos(q2), fy - leg.l2 * math.sin(q2)) == pytest.approx(leg.l3)
    with pytest.raises(ValueError, match="outside the workspace"):
        M.inverse_kinematics(leg, 0.0, -0.5)


def _energy_drift(leg, x0, model, duration=2.0):
    t = np.linspace(0, duration, 801)
    x = M.simulate(leg, t, x0, model=model, friction=False, rtol=1e-11, atol=1e-13)
    T, V = M.energy(leg, x[:, 0], x[:, 2], x[:, 1], x[:, 3], model=model)
    E = T + V
    return np.max(np.abs(E - E[0])) / np.max(T), x


def test_energy_conserved_parallelogram_with_gravity(leg):
    drift, x = _energy_drift(leg, [math.radians(230), 0.5, math.radians(300), -1.0], "parallelogram")
    assert np.ptp(x[:, 0]) > 1.0  # it really swung
    assert drift < 1e-6


def test_energy_conserved_fivebar_rotating_and_breathing(leg):
    # Under gravity the five-bar falls into its full-extension singularity within a few
    # tenths of a second (the real leg rests on a stop there), so 2 s of free motion are
    # run without gravity: the leg spins and breathes (q2 - q1 varies) under its own
    # Coriolis and centrifugal terms.
    drift, x = _energy_drift(leg.replace(g=0.0), [math.radians(240), 0.5, math.radians(330), 0.8],
                             "fivebar")
    gap = x[:, 2] - x[:, 0]
    assert np.ptp(gap) > math.radians(20)
    assert drift < 1e-6


def test_energy_conserved_fivebar_with_gravity_short(leg):
    drift, x = _energy_drift(leg, [math.radians(240), 0.0, math.radians(320), 0.0], "fivebar",
                             duration=0.12)
    assert drift < 1e-6


def test_gravity_is_gradient_of_potential(leg):
    q1, q2, h = 4.5, 4.9, 1e-6
    for model in M.MODELS:
        G = M.gravity_torque(leg, q1, q2, model=model)
        V = lambda a, b: M.energy(leg, a, b, 0.0, 0.0, model=model)[1]  # noqa: E731
        num = [(V(q1 + h, q2) - V(q1 - h, q2)) / (2 * h), (V(q1, q2 + h) - V(q1, q2 - h)) / (2 * h)]
        np.testing.assert_allclose(G, num, rtol=1e-6, atol=1e-9)


def test_fivebar_reduced_dynamics_match_the_maximal_coordinate_form(leg):
    """The twin's kernel takes M, h, G of model (b) from the links' unit vectors and uses
    M's sparsity: the two generated forms agree, and D, b equal S^T M S, S^T (M a0 + h + G)
    computed with numpy from the closure's angles."""
    P = M.param_vector(leg)
    rng = np.random.default_rng(3)
    for _ in range(200):
        q1, q2 = leg.q1 + rng.uniform(-0.6, 0.6), leg.q2 + rng.uniform(-0.6, 0.6)
        phi3, phi4 = terms._lower_angles(q1, q2, P)
        v = rng.normal(0.0, 10.0, 4)
        if math.isnan(phi3):   # outside the assembly mode
            assert math.isnan(terms._fivebar_dynamics(q1, q2, v[0], v[1], P)[0])
            continue
        ref = gen.fivebar_terms(q1, q2, phi3, phi4, *v, P)
        cs = gen.fivebar_terms_cs(*(f(a) for a in (q1, q2, phi3, phi4) for f in (math.cos, math.sin)), *v, P)
        np.testing.assert_allclose(cs, ref, rtol=1e-12, atol=1e-12)
        r = terms._fivebar_dynamics(q1, q2, v[0], v[1], P)
        assert r[5] == pytest.approx(phi3, abs=1e-13) and r[6] == pytest.approx(phi4, abs=1e-13)
        # the reduction onto q: D = S^T M S, b = S^T (M a0 + h + G) with the full 4x4 M
        # (the kernel uses M's sparsity), S = [I; J], J and a0 from the loop closure
        Mm = np.reshape(ref[:16], (4, 4))
        assert np.array_equal(Mm, Mm.T) and np.count_nonzero(Mm - np.diag(np.diag(Mm))) == 4
        assert Mm[0, 3] != 0.0 and Mm[1, 2] != 0.0
        A = np.array([[leg.l3 * math.sin(phi3), -leg.l4 * math.sin(phi4)],
                      [-leg.l3 * math.cos(phi3), leg.l4 * math.cos(phi4)]])       # Phi_phi
        Bq = np.array([[-leg.l1 * math.sin(q1), leg.l2 * math.sin(q2)],
                       [leg.l1 * math.cos(q1), -leg.l2 * math.cos(q2)]])           # Phi_q
        J = -np.linalg.solve(A, Bq)
        dq = v[:2]
        dphi = J @ dq
        assert np.allclose((r[7], r[8]), dphi, rtol=1e-9, atol=1e-12)
        w = (leg.l1 * np.array([math.cos(q1), math.sin(q1)]) * dq[0] ** 2
             + leg.l4 * np.array([math.cos(phi4), math.sin(phi4)]) * dphi[1] ** 2
             - leg.l2 * np.array([math.cos(q2), math.sin(q2)]) * dq[1] ** 2
             - leg.l3 * np.array([math.cos(phi3), math.sin(phi3)]) * dphi[0] ** 2)
        a0 = np.concatenate([[0.0, 0.0], np.linalg.solve(A, w)])
        S = np.vstack([np.eye(2), J])
        full = np.array(gen.fivebar_terms(q1, q2, phi3, phi4, dq[0], dq[1], *dphi, P))
        Mm, h, G = np.reshape(full[:16], (4, 4)), full[16:20], full[20:24]
        D = S.T @ Mm @ S
        bvec = S.T @ (Mm @ a0 + h + G)
        np.testing.assert_allclose([r[0], r[1], r[2]], [D[0, 0], D[0, 1], D[1, 1]], rtol=1e-10)
        np.testing.assert_allclose([r[3], r[4]], bvec, rtol=1e-9, atol=1e-12)


def test_simulate_reports_singularity(leg):
    with pytest.raises(ValueError, match="singular"):
        M.simulate(leg, np.linspace(0, 2, 201), [math.radians(250), 0, math.radians(320), 0],
                   model="fivebar", friction=False)


def test_linear_and_nonlinear_agree_near_operating_point(leg):
    import control
    q1, q2 = leg.q0
    u0 = M.equilibrium_torque(leg, model="parallelogram")
    sys = M.linearize(leg, coupled=True, model="parallelogram")
    t = np.linspace(0, 0.5, 501)
    du = np.array([0.002, -0.002])
    x = M.simulate(leg.replace(coulomb1=0.0, coulomb2=0.0), t, [q1, 0, q2, 0], tau=u0 + du,
                   model="parallelogram")
    lin = control.forced_response(sys, t, np.tile(du, (t.size, 1)).T).states.T
    dev = x - np.array([q1, 0, q2, 0])
    assert np.max(np.abs(dev[:, [0, 2]] - lin[:, [0, 2]])) < 0.02 * np.max(np.abs(lin[:, [0, 2]]))


def test_foot_positions_of_many_points_are_those_of_one_thread(leg, monkeypatch):
    """A sweep's 300 000 foot positions are computed on the cores present: the same numbers."""
    rng = np.random.default_rng(5)
    q1 = leg.q1 + rng.normal(0, 0.3, 2 * kinematics.PARALLEL_POINTS)
    q2 = leg.q2 + rng.normal(0, 0.3, q1.size)
    many = M.foot_position(leg, q1, q2)
    monkeypatch.setattr(kinematics, "PARALLEL_POINTS", 10 ** 12)
    one = M.foot_position(leg, q1, q2)
    for a, b in zip(many, one):
        assert np.array_equal(a, b, equal_nan=True)


@pytest.mark.parametrize("model", ["fivebar", "parallelogram"])
def test_a_held_torque_step_is_the_torque_tables_last_row(leg, model):
    """held_torque_stepper (the sampled closed loop's plant) gives what simulate_torque_table
    gives for the same held torque, bit for bit, period after period; NaN once the five-bar
    leaves its valid configuration (the parallelogram model has no singular one)."""
    period, substeps = 0.002, 16
    step = M.held_torque_stepper(leg, period, substeps, model=model)
    x = np.array([leg.q1, 0.3, leg.q2, -0.2])
    for tau in ([0.05, -0.02], [-0.1, 0.08], [0.0, 0.0]):
        table = M.simulate_torque_table(leg, x, np.tile(tau, (substeps + 1, 1)), period / substeps, substeps=1,
                                        model=model)
        nxt = step(x, np.array(tau))
        assert np.array_equal(nxt, table[-1]) and not np.array_equal(nxt, x)
        x = nxt
    if model == "fivebar":   # driven through the five-bar's singular configuration: NaN, as the table's rows
        wild = np.array([leg.q1, -2000.0, leg.q2, 2000.0])
        table = M.simulate_torque_table(leg, wild, np.zeros((substeps + 1, 2)), period / substeps, substeps=1,
                                        model=model)
        assert np.isnan(table[-1]).all() and np.isnan(step(wild, np.zeros(2))).all()
