"""Compiled second-order identification: its parts against scipy, batch against single,
known answers on non-uniform time, the sweep's batch against one by one."""

import math

import numpy as np
import pytest
from scipy.signal import find_peaks, savgol_filter

import leglib as lg
from leglib.design.points import STATUS_OK, identify_many, identify_response
from leglib.experiments.step import _responses_from_batch
from leglib.identify import fastfit as F
from leglib.identify.step import (
    MIN_R2,
    IdentificationError,
    _validate,
    identify_batch,
    second_order,
)
from leglib.identify.step import model as _model

T = np.arange(750) * 0.002


@pytest.mark.parametrize("zeta", [0.001, 0.05, 0.24, 0.7, 0.99, 1.01, 1.5, 3.0, 40.0])
@pytest.mark.parametrize("wn", [0.5, 31.4, 400.0, 5e4])
def test_model_equals_identify_model(zeta, wn):
    # step.model switches to the critical formula within 1e-6 of zeta = 1: not tested there
    np.testing.assert_allclose(F.model(T, zeta, wn, -0.046, -0.252, 0.013),
                               _model(T, zeta, wn, -0.046, -0.252, 0.013), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("zeta", [0.1, 0.7, 0.9999, 1.0, 1.00001, 1.3, 5.0])
def test_analytic_gradient_and_recurrence(zeta):
    rng = np.random.default_rng(0)
    p = np.array([zeta, 31.4, 1.3, 0.2, 0.013])
    y = F.model(T, *p) + rng.normal(0, 0.01, T.size)
    A, g = np.empty((5, 5)), np.empty(5)
    A2, g2 = np.empty((5, 5)), np.empty(5)
    cost = F._normal_equations(T, y, p, A, g, True, 0.002)       # recurrence on the uniform grid
    cost2 = F._normal_equations(T, y, p, A2, g2, True, 0.0)      # every sample direct
    assert cost == pytest.approx(cost2, rel=1e-10)
    np.testing.assert_allclose(A, A2, rtol=1e-8, atol=1e-10 * np.abs(A2).max())
    np.testing.assert_allclose(g, g2, rtol=1e-8, atol=1e-10 * np.abs(g2).max())
    for k in range(5):
        h = 1e-6 * max(abs(p[k]), 1e-2)
        up, down = p.copy(), p.copy()
        up[k] += h
        down[k] -= h
        fd = (F._normal_equations(T, y, up, A2, g2, False, 0.0)
              - F._normal_equations(T, y, down, A2, g2, False, 0.0)) / (2 * h)
        assert g[k] == pytest.approx(fd, rel=1e-5, abs=1e-9 * np.abs(g).max())


@pytest.mark.parametrize("n", [20, 61, 750, 1201])
def test_smoothing_equals_scipy_savgol(n):
    y = np.random.default_rng(n).normal(size=n).cumsum()
    win = max(5, (n // 60) | 1)
    np.testing.assert_allclose(F._savgol2(y, win), savgol_filter(y, win, 2), rtol=1e-10, atol=1e-10)


def test_peaks_equal_scipy_find_peaks():
    rng = np.random.default_rng(2)
    for k in range(40):
        x = np.round(rng.normal(size=200).cumsum(), 0)  # rounded: plateaus on peaks
        for prom in (0.0, 0.5, 2.0, 5.0):
            np.testing.assert_array_equal(F._peaks(x, prom), find_peaks(x, prominence=prom)[0])


def _cases():
    rng = np.random.default_rng(5)
    ts, ys = [], []
    for zeta, wn, n in [(0.24, 31.4, 750), (0.05, 12.0, 500), (1.5, 40.0, 300), (0.7, 100.0, 1200)]:
        t = np.arange(n) * 0.002
        ts.append(t)
        ys.append(np.floor(_model(t, zeta, wn, 1600.0, 3.0, 0.01) + rng.normal(0, 0.35, n) + 0.5))
    ts += [T, T, T[:10], T, T, T[::-1]]
    ys += [np.full(T.size, 0.3), np.where(T > 0.5, np.nan, 0.0), T[:10], np.sin(2 * np.pi * 4 * T), T[:-1], T]
    return ts, ys


@pytest.mark.parametrize("parallel_from", [10 ** 9, 1])
def test_batch_equals_single_fits_and_errors(parallel_from, monkeypatch):
    """One thread or the thread pool (a batch of PARALLEL_FROM or more): each response's
    fit is that of the response alone, bit for bit."""
    monkeypatch.setattr(F, "PARALLEL_FROM", parallel_from)
    ts, ys = _cases()
    ts, ys = ts * 3, ys * 3
    batch = identify_batch(ts, ys)
    assert len(batch) == len(ts)
    for t, y, b in zip(ts, ys, batch):
        try:
            s = second_order(t, y)
        except IdentificationError as exc:
            assert isinstance(b, IdentificationError) and str(b) == str(exc)
            continue
        assert not isinstance(b, IdentificationError)
        assert b == s  # every field, bit for bit


def test_not_a_step_message_equals_the_reference_checks():
    # the validation's words and numbers are those of _validate
    y = 0.3 + 1e-3 * np.sin(2 * np.pi * 3 * T) + np.random.default_rng(1).normal(0, 0.01, T.size)
    with pytest.raises(IdentificationError) as ref:
        _validate(T, y)
    with pytest.raises(IdentificationError) as new:
        second_order(T, y)
    assert str(new.value) == str(ref.value)


@pytest.mark.parametrize("zeta,wn", [(0.1, 31.4), (0.24, 31.4), (0.7, 60.0), (1.5, 40.0)])
def test_non_uniform_time_recovers_the_truth(zeta, wn):
    # jittered sample times take the direct (non-recurrent) path
    rng = np.random.default_rng(3)
    t = np.sort(T + rng.uniform(-4e-4, 4e-4, T.size))
    t -= t[0]
    y = np.floor(_model(t, zeta, wn, 1600.0, 0.0, 0.01) + rng.normal(0, 0.35, t.size) + 0.5)
    f = second_order(t, y)
    assert f.zeta == pytest.approx(zeta, rel=0.03) and f.wn == pytest.approx(wn, rel=0.03)


def test_sweep_batch_equals_one_by_one_on_the_twin():

    odrv = lg.connect("virtual", seed=11)
    lg.configure(odrv)
    lg.calibrate(odrv)
    grid = np.array([(p, v, i) for p in (20.0, 50.0) for v in (0.002, 0.03, 0.15) for i in (0.002, 0.08)])
    out = odrv.sim.step_batch(grid, vel_limit=odrv.config.step_vel_limit, abort_error_turns=0.8)
    responses = _responses_from_batch(odrv, grid, out, 0.4)
    many = identify_many(responses, odrv.leg)
    one = [identify_response(r, odrv.leg) for r in responses]
    assert [repr(p) for p in many] == [repr(p) for p in one]  # NaN where unstable: compare text
    assert {p.status for p in many} >= {STATUS_OK}
    assert all(math.isfinite(p.zeta) and p.r2 >= F.MIN_R2 for p in many if p.status == STATUS_OK)


def test_thresholds_are_identifys():
    assert F.MIN_R2 == MIN_R2


@pytest.mark.parametrize("zeta", [1.0 - 5e-7, 1.0, 1.0 + 5e-7])
def test_critical_band_is_critical_damping(zeta):
    # step.model takes |zeta - 1| <= 1e-6 as critical damping: so does the fit
    f = second_order(T, _model(T, zeta, 40.0, 1.0, 0.0, 0.0))
    assert f.zeta == 1.0 and math.isnan(f.fd) and f.overdamped


def test_shape_numbers_are_the_responses_start_final_peak_and_spacing():
    rng = np.random.default_rng(4)
    ts, ys = [], []
    for n in (2, 3, 20, 301, 750):
        t = np.cumsum(rng.uniform(0.001, 0.003, n))
        ts.append(t)
        ys.append(np.tanh(t * 5) * rng.choice([-1, 1]) + rng.normal(0, 0.01, n))
    got = F.shape_numbers(ts, ys)
    for (t, y), row in zip(zip(ts, ys), got):
        n = y.size
        start, final = np.mean(y[:max(3, n // 50)]), np.mean(y[-max(5, n // 5):])
        peak = np.max(y - final) if final > start else np.max(final - y)
        # the means summed in order (numpy sums pairwise): equal to rounding
        np.testing.assert_allclose(row[:3], [start, final, peak], rtol=1e-13, atol=1e-15)
        assert row[3] == np.median(np.diff(t))
