"""The gain map: gap filling, interpolation, inverse design, on known answers and the twin."""

import math

import numpy as np
import pytest

from leglib import gainmap as GM
from leglib import odrive_io as io


def test_harmonic_fill_reproduces_harmonic_fields():
    i, j, k = np.meshgrid(np.arange(5), np.arange(7), np.arange(6), indexing="ij")
    field = 2.0 * i - 0.5 * j + 3.0 * k + 1.0  # linear: harmonic, so the fill is exact
    # holes inside the grid (the edges carry the fill's Neumann condition)
    known = np.random.default_rng(0).random(field.shape) > 0.4
    known[0], known[-1], known[:, 0], known[:, -1], known[:, :, 0], known[:, :, -1] = (True,) * 6
    filled = GM.harmonic_fill(np.where(known, field, np.nan), known)
    np.testing.assert_allclose(filled, field, atol=1e-9)
    with pytest.raises(ValueError):
        GM.harmonic_fill(field, np.zeros(field.shape, bool))


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
                status = GM.STATUS_OK
                if kv < 0.03 and ki > 0.06:
                    status = GM.STATUS_UNSTABLE
                elif (int(kp) + int(kv * 1000) + int(ki * 1000)) % 11 == 0:
                    status = GM.STATUS_FAILED
                points.append(GM.PointResult((kp, kv, ki), status, z if status == "ok" else math.nan,
                                             wn if status == "ok" else math.nan))
    return GM.GainMap(points)


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
    for z, fn in GM.spread_targets(a, 8):
        gains = synthetic.gains_for(z, fn)
        zt, wt = _analytic(*gains)
        assert zt == pytest.approx(z, rel=0.10) and wt / (2 * math.pi) == pytest.approx(fn, rel=0.10)
        # never next to an unstable cell
        assert not (gains[1] < 0.04 and gains[2] > 0.06)


def test_inverse_rejects_nonsense(synthetic):
    with pytest.raises(ValueError, match="positive"):
        synthetic.gains_for(-0.1, 5.0)


@pytest.fixture(scope="module")
def twin_sweep(tmp_path_factory):
    out = tmp_path_factory.mktemp("sweep")
    odrv = io.connect("virtual", seed=11)
    io.apply_configuration(odrv)
    io.calibrate(odrv)
    grid = np.array([(p, v, i) for p in (30.0, 50.0) for v in (0.002, 0.03, 0.08, 0.15) for i in (0.002, 0.04, 0.08)])
    io.sweep(odrv, grid, out, progress=False)
    return odrv, grid, out


def test_map_from_files_equals_map_from_responses(twin_sweep):
    odrv, grid, out = twin_sweep
    from_files = GM.GainMap.from_measurements(out)
    resp = io._responses_from_batch(odrv, grid, odrv.sim.step_batch(
        grid, vel_limit=odrv.config.step_vel_limit, abort_error_turns=0.8), 0.4)
    from_mem = GM.GainMap.from_responses(resp, workers=1)
    assert from_files.counts() == from_mem.counts()
    assert from_files.counts().get("unstable", 0) > 0  # the grid reaches instability
    ok = from_files.status == "ok"
    np.testing.assert_allclose(from_files.zeta[ok], from_mem.zeta[ok], rtol=1e-3)


def test_model_based_inverse_on_the_twin(twin_sweep):
    odrv, _, _ = twin_sweep
    from leglib.identify import second_order
    fit_gains = [(25, 0.05, 0.01), (40, 0.03, 0.01), (50, 0.1, 0.01), (30, 0.15, 0.01)]
    model = GM.fit_leg_plant([io.step_response(odrv, *g) for g in fit_gains], odrv.config)
    assert model.experiments == 4 and model.rms_turns < 0.01
    gains, pred = model.gains_for(0.5, 6.0)
    assert pred[0] == pytest.approx(0.5, rel=0.01) and pred[1] == pytest.approx(6.0, rel=0.01)
    r = io.step_response(odrv, *gains)
    m = second_order(r.t, r.y)
    assert m.zeta == pytest.approx(0.5, rel=0.05) and m.fn == pytest.approx(6.0, rel=0.05)
