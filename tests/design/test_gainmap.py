"""The gain map: gap filling, interpolation, inverse design, on known answers and the twin."""

import math

import numpy as np
import pytest

import leglib as lg
from leglib.design.gainmap import (
    TOLERANCE,
    OutsideRegionError,
    _axis_matrix,
    _tensor_interp,
    harmonic_fill,
    spread_targets,
)
from leglib.design.plantfit import fit_leg_plant
from leglib.design.points import (
    STATUS_FAILED,
    STATUS_OK,
    STATUS_UNSTABLE,
    PointResult,
    identify_response,
)
from leglib.experiments.step import StepResponse, _responses_from_batch
from leglib.model.drive import AxisMap
from leglib.model.kinematics import foot_position


def test_harmonic_fill_reproduces_harmonic_fields():
    i, j, k = np.meshgrid(np.arange(5), np.arange(7), np.arange(6), indexing="ij")
    field = 2.0 * i - 0.5 * j + 3.0 * k + 1.0  # linear: harmonic, so the fill is exact
    # holes inside the grid (the edges carry the fill's Neumann condition)
    known = np.random.default_rng(0).random(field.shape) > 0.4
    known[0], known[-1], known[:, 0], known[:, -1], known[:, :, 0], known[:, :, -1] = (True,) * 6
    filled = harmonic_fill(np.where(known, field, np.nan), known)
    np.testing.assert_allclose(filled, field, atol=1e-9)
    with pytest.raises(ValueError):
        harmonic_fill(field, np.zeros(field.shape, bool))


def _analytic(kp, kv, ki, J=0.0011, b=0.002):
    """A PD-like second-order law: wn^2 = kv kp / J, 2 zeta wn = (kv + b) / J."""
    wn = math.sqrt(kv * kp / J) * (1 + 0.5 * ki)
    zeta = (kv + b) / (2 * wn * J)
    return zeta, wn


@pytest.fixture(scope="module")
def synthetic():
    points = []
    for kp in np.linspace(20, 50, 4):
        for kv in np.linspace(0.02, 0.18, 9):
            for ki in np.linspace(0.002, 0.08, 5):
                z, wn = _analytic(kp, kv, ki)
                status = STATUS_OK
                if kv < 0.03 and ki > 0.06:
                    status = STATUS_UNSTABLE
                elif (int(kp) + int(kv * 1000) + int(ki * 1000)) % 11 == 0:
                    status = STATUS_FAILED
                points.append(PointResult((kp, kv, ki), status, z if status == "ok" else math.nan,
                                             wn if status == "ok" else math.nan))
    return lg.GainMap(points)


def test_map_layout_and_counts(synthetic):
    assert synthetic.zeta.shape == (4, 9, 5)
    c = synthetic.counts()
    assert c["ok"] + c["unstable"] + c["failed"] == 180 and c["unstable"] > 0 and c["failed"] > 0
    assert np.all(np.isnan(synthetic.zeta[synthetic.status != "ok"]))  # nothing invented


def test_filled_cells_are_close_to_the_truth(synthetic):
    zeta, wn = synthetic.filled()
    failed = synthetic.status == "failed"
    for idx in zip(*np.nonzero(failed)):
        g = [synthetic.axes[a][idx[a]] for a in range(3)]
        z, w = _analytic(*g)
        assert zeta[idx] == pytest.approx(z, rel=0.1) and wn[idx] == pytest.approx(w, rel=0.1)


def test_interpolation_matches_the_truth_between_grid_points(synthetic):
    rng = np.random.default_rng(3)
    for _ in range(30):
        g = (rng.uniform(22, 48), rng.uniform(0.06, 0.17), rng.uniform(0.005, 0.05))
        z, fn = synthetic.predict(g)
        zt, wt = _analytic(*g)
        assert z == pytest.approx(zt, rel=0.05) and fn == pytest.approx(wt / (2 * math.pi), rel=0.05)


def test_inverse_recovers_gains_with_the_requested_dynamics(synthetic):
    a = synthetic.achievable()
    assert a.zeta.size > 100
    for z, fn in spread_targets(a, 8):
        gains = synthetic.gains_for(z, fn)
        zt, wt = _analytic(*gains)
        assert zt == pytest.approx(z, rel=0.10) and wt / (2 * math.pi) == pytest.approx(fn, rel=0.10)
        # never next to an unstable cell
        assert not (gains[1] < 0.04 and gains[2] > 0.06)


@pytest.mark.parametrize("fixed", [0, 1, 2])
def test_a_map_with_one_value_of_a_gain_is_a_plane_and_inverts(synthetic, fixed):
    """A sweep that holds one gain fixed (one value on that axis): the map is a plane of
    the other two, its region and inverse work on it and keep the fixed gain."""
    value = synthetic.axes[fixed][1]
    plane = lg.GainMap([p for p in synthetic.points if p.gains[fixed] == value])
    assert plane.zeta.shape[fixed] == 1 and plane.fine()["valid"].shape[fixed] == 1
    a = plane.achievable()
    assert a.zeta.size > 20 and np.all(a.gains[:, fixed] == value)
    for z, fn in spread_targets(a, 4):
        gains = plane.gains_for(z, fn)
        zt, wt = _analytic(*gains)
        assert gains[fixed] == value
        assert zt == pytest.approx(z, rel=0.10) and wt / (2 * math.pi) == pytest.approx(fn, rel=0.10)


def test_inverse_rejects_nonsense(synthetic):
    with pytest.raises(ValueError, match="positive"):
        synthetic.gains_for(-0.1, 5.0)


@pytest.fixture(scope="module")
def twin_sweep(tmp_path_factory):
    out = tmp_path_factory.mktemp("sweep")
    odrv = lg.connect("virtual", seed=11)
    lg.configure(odrv)
    lg.calibrate(odrv)
    grid = np.array([(p, v, i) for p in (30.0, 50.0) for v in (0.002, 0.03, 0.08, 0.15) for i in (0.002, 0.04, 0.08)])
    lg.sweep(odrv, grid, out, progress=False)
    return odrv, grid, out


def test_map_from_files_equals_map_from_responses(twin_sweep):
    odrv, grid, out = twin_sweep
    from_files = lg.GainMap.from_measurements(out)
    resp = _responses_from_batch(odrv, grid, odrv.sim.step_batch(
        grid, vel_limit=odrv.config.step_vel_limit, abort_error_turns=0.8), 0.4)
    from_mem = lg.GainMap.from_responses(resp, odrv.leg, workers=1)
    assert from_files.counts() == from_mem.counts()
    assert from_files.counts().get("unstable", 0) > 0  # the grid reaches instability
    ok = from_files.status == "ok"
    # the second run starts from the device's state a few transactions later (the idle leg,
    # the estimator's noise): the same map to a fraction of a percent
    np.testing.assert_allclose(from_files.zeta[ok], from_mem.zeta[ok], rtol=1e-2)


def test_model_based_inverse_on_the_twin(twin_sweep):
    odrv, _, _ = twin_sweep
    from leglib.identify.step import second_order
    fit_gains = [(25, 0.05, 0.01), (40, 0.03, 0.01), (50, 0.1, 0.01), (30, 0.15, 0.01)]
    model = fit_leg_plant([lg.step_response(odrv, *g) for g in fit_gains], odrv.config)
    assert model.experiments == 4 and model.rms_turns < 0.01
    gains, pred = model.gains_for(0.5, 6.0)
    assert pred[0] == pytest.approx(0.5, rel=0.01) and pred[1] == pytest.approx(6.0, rel=0.01)
    r = lg.step_response(odrv, *gains)
    m = second_order(r.t, r.y)
    assert m.zeta == pytest.approx(0.5, rel=0.05) and m.fn == pytest.approx(6.0, rel=0.05)


# -- an honest map: only what the leg does is offered ----------------------------------------

@pytest.fixture(scope="module")
def thesis_map():
    """The thesis grid measured on the default twin, and the device to re-measure on."""
    odrv = lg.connect("virtual", seed=11)
    lg.configure(odrv)
    lg.calibrate(odrv)
    grid = lg.thesis_grid()
    out = odrv.sim.step_batch(grid, vel_limit=odrv.config.step_vel_limit, abort_error_turns=0.8)
    gm = lg.GainMap.from_responses(_responses_from_batch(odrv, grid, out, 0.4), odrv.leg, workers=1)
    return odrv, gm


def test_offered_points_agree_when_remeasured(thesis_map):
    """Every offered point, measured again with its gains, identifies as the map said:
    spread over the region, at its edges, and for requests outside it."""
    odrv, gm = thesis_map
    a = gm.achievable()
    edges = [int(np.argmin(a.zeta)), int(np.argmax(a.zeta)), int(np.argmin(a.fn)), int(np.argmax(a.fn))]
    requests = [(2.0, 3.0), (1.5, 4.0), (0.3, 2.5), (0.24, 5.0)]
    requests += [(a.zeta[i], a.fn[i]) for i in edges]
    requests += [tuple(x) for x in spread_targets(a, 12, margin=0.0, seed=2)]
    errors, held = [], []
    for z, f in requests:
        c = gm.nearest(z, f)
        p = identify_response(lg.step_response(odrv, *c.gains), odrv.leg)
        assert p.status == "ok", (z, f, c, p.reason)
        errors.append(max(abs(p.zeta / c.zeta - 1), abs(p.fn / c.fn - 1)))
        held.append(c.zeta_interval[0] <= p.zeta <= c.zeta_interval[1] and c.fn_interval[0] <= p.fn <= c.fn_interval[1])
    errors = np.array(errors)
    assert np.median(errors) < 0.05 and errors.max() < 0.15, errors
    # the map's 90 % intervals (its neighbours' interpolated) hold what is measured again
    assert np.mean(held) >= 0.8, held


def test_a_target_outside_the_region_is_refused_with_the_nearest_point(thesis_map):
    _, gm = thesis_map
    with pytest.raises(OutsideRegionError, match="outside the achievable region") as err:
        gm.gains_for(0.05, 30.0)
    near = gm.nearest(0.05, 30.0)
    assert err.value.nearest == near and not near.within()
    msg = str(err.value)
    assert f"zeta {near.zeta:.3g}" in msg and f"fn {near.fn:.3g} Hz" in msg and f"{near.gains[0]:.4g}" in msg
    assert isinstance(err.value, ValueError)
    # inside the region gains_for answers, and the answer is within the tolerance
    a = gm.achievable()
    z, f = a.zeta[len(a.zeta) // 2] * 1.01, a.fn[len(a.fn) // 2] * 0.99
    gains = gm.gains_for(z, f)
    c = gm.nearest(z, f)
    assert gains == c.gains and abs(c.zeta / z - 1) <= TOLERANCE and abs(c.fn / f - 1) <= TOLERANCE


def test_region_holds_only_measured_cells(thesis_map):
    """No achievable point lies in a grid cell with a corner that is not identified."""
    _, gm = thesis_map
    a = gm.achievable()
    ok = gm.status == "ok"
    for g in a.gains[:: max(1, len(a.gains) // 500)]:
        idx = [np.clip(np.searchsorted(ax, v, side="right") - 1, 0, len(ax) - 2) for ax, v in zip(gm.axes, g)]
        assert ok[idx[0]:idx[0] + 2, idx[1]:idx[1] + 2, idx[2]:idx[2] + 2].all(), g
    # the twin's map: zeta of a foot step on this leg stays of order one (no extrapolated trail)
    assert a.zeta.max() < 3.0


def test_zero_gains_and_non_second_order_steps_are_failed(thesis_map):
    odrv, _ = thesis_map
    for gains in [(0.0, 0.0, 0.0), (20.0, 0.0, 0.0), (0.0, 0.05, 0.0)]:
        p = identify_response(lg.step_response(odrv, *gains), odrv.leg)
        assert p.status in ("failed", "unstable") and math.isnan(p.zeta), (gains, p)
    # a step that overshoots by 110 %: no second-order step does (the joints move along the
    # commanded step of 0.1 motor turn and back, the foot height follows the five-bar)
    leg = odrv.leg
    t = np.arange(750) * 0.002
    a = 1 - np.exp(-20 * t) + 5.0 * 20 * t * np.exp(-20 * t)
    dq1, dq2 = AxisMap.from_leg(leg).motor_step_to_joint_step(0.1)
    q1, q2 = leg.q1 + dq1 * a, leg.q2 + dq2 * a
    y = foot_position(leg, q1, q2)[1]
    assert (y.max() - y[-1]) / (y[-1] - y[0]) > 1.0
    resp = StepResponse(t=t, q1=q1, q2=q2, y=y, gains=(50.0, 0.05, 0.01), step=0.1)
    p = identify_response(resp, leg)
    assert p.status == "failed" and math.isnan(p.zeta) and "not a second-order step" in p.reason, p.reason


def test_counts_are_plain_python(synthetic):
    c = synthetic.counts()
    assert all(type(k) is str and type(v) is int for k, v in c.items())
    assert "np.str_" not in str(c)


@pytest.mark.parametrize("shape", [(4, 10, 10), (4, 3, 5), (1, 6, 4)])
def test_fine_grid_interpolants_equal_regular_grid_interpolator(shape):
    """GainMap.fine's per-axis matrices give RegularGridInterpolator's cubic (not-a-knot,
    solved exactly) and linear values on the fine product grid (cubic only where every axis has 4 points)."""
    from scipy.interpolate import RegularGridInterpolator
    from scipy.sparse.linalg import spsolve

    rng = np.random.default_rng(3)
    axes = [np.sort(rng.uniform(0.0, 2.0, n)) + np.arange(n) for n in shape]
    active = [a for a in axes if len(a) > 1]
    fine = [np.linspace(a[0], a[-1], 2 * len(a) + 7) for a in active]
    field = rng.normal(size=[len(a) for a in active])
    mesh = np.stack(np.meshgrid(*fine, indexing="ij"), axis=-1)
    for method in ("cubic", "linear"):
        if method == "cubic" and not all(len(a) >= 4 for a in active):
            continue
        mats = [_axis_matrix(a, x, method) for a, x in zip(active, fine)]
        ours = _tensor_interp(field, mats)
        # the reference solved exactly (its default is an iterative solver with a
        # tolerance: its values differ from the exact spline by ~1e-5 of the data)
        exact = {"solver": spsolve} if method == "cubic" else {}
        ref = RegularGridInterpolator(active, field, method=method, **exact)(mesh)
        np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-10 * np.abs(field).max())


def test_predict_is_the_fine_grids_interpolant_and_refuses_gains_off_the_grid(synthetic):
    f = synthetic.fine()
    for idx in [(0, 0, 0), (7, 13, 21), (30, 45, 39), (12, 30, 5)]:
        g = [f["axes"][k][idx[k]] for k in range(3)]
        z, fn = synthetic.predict(g)
        assert z == pytest.approx(f["zeta"][idx], rel=1e-12) and fn == pytest.approx(f["fn"][idx], rel=1e-12)
    lo = synthetic.axes[1][0]
    with pytest.raises(ValueError, match="vel_gain .* outside the map's grid"):
        synthetic.predict((30.0, lo / 2, 0.01))
