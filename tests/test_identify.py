"""Second-order identification: known answers, noise and quantization, clear failures."""

import math

import numpy as np
import pytest

from leglib.identify import IdentificationError, _model, second_order

T = np.arange(750) * 0.002  # the thesis's 1.5 s at 500 Hz
ZETAS = [0.05, 0.1, 0.24, 0.5, 0.7, 0.9]
WNS = [5.0, 12.0, 31.4, 60.0, 100.0]


@pytest.mark.parametrize("zeta", ZETAS)
@pytest.mark.parametrize("wn", WNS)
def test_fit_recovers_noiseless_within_1_percent(zeta, wn):
    y = _model(T, zeta, wn, -0.046, -0.252, 0.0)
    f = second_order(T, y)
    assert f.zeta == pytest.approx(zeta, rel=0.01)
    assert f.wn == pytest.approx(wn, rel=0.01)
    assert f.fn == pytest.approx(wn / (2 * math.pi), rel=0.01)
    assert f.r2 > 0.999


def _quantized_noisy(zeta, wn, seed):
    # a 0.4-turn step at 4000 counts/turn: the response in counts, quantized, noisy
    rng = np.random.default_rng(seed)
    counts = _model(T, zeta, wn, 1600.0, 0.0, 0.01)
    return np.floor(counts + rng.normal(0, 0.35, T.size) + 0.5)


@pytest.mark.parametrize("zeta", ZETAS)
@pytest.mark.parametrize("wn", WNS)
def test_fit_with_quantization_and_noise_within_3_percent(zeta, wn):
    f = second_order(T, _quantized_noisy(zeta, wn, seed=int(zeta * 100 + wn)))
    assert f.zeta == pytest.approx(zeta, rel=0.03)
    assert f.wn == pytest.approx(wn, rel=0.03)


@pytest.mark.parametrize("zeta,wn", [(0.1, 31.4), (0.24, 31.4), (0.2, 60.0), (0.15, 12.0)])
def test_thesis_log_decrement_where_two_periods_exist(zeta, wn):
    f = second_order(T, _quantized_noisy(zeta, wn, seed=3), method="logdec")
    assert f.method == "logdec" and f.n_peaks >= 2
    assert f.zeta == pytest.approx(zeta, rel=0.05)
    assert f.wn == pytest.approx(wn, rel=0.03)
    assert f.fd == pytest.approx(wn * math.sqrt(1 - zeta ** 2) / (2 * math.pi), rel=0.03)


@pytest.mark.parametrize("zeta", [0.95, 1.0, 1.5, 3.0])
def test_no_oscillation_reports_fit_zeta_and_flag_not_a_constant(zeta):
    y = _model(T, zeta, 40.0, 1.0, 0.0, 0.0)
    for method in ("fit", "logdec"):
        f = second_order(T, y, method=method)
        assert f.overdamped and f.n_peaks < 2
        assert f.zeta == pytest.approx(zeta, rel=0.02)   # not the thesis's 1 or 2
        assert math.isnan(f.fd) or zeta < 1


@pytest.mark.parametrize("t,y,message", [
    (T, np.full(T.size, 0.3), "flat"),
    (T, np.where(T > 0.5, np.nan, 0.0), "NaN"),
    (T[:10], T[:10], "too short"),
    (T, np.sin(2 * np.pi * 4 * T), "not a (second-order )?step"),
    (T, T[:-1], "equal length"),
    (T[::-1], T, "increase"),
])
def test_unusable_responses_raise(t, y, message):
    with pytest.raises(IdentificationError, match=message):
        second_order(t, y)


def test_unknown_method():
    with pytest.raises(ValueError, match="method"):
        second_order(T, _model(T, 0.3, 30, 1, 0, 0), method="magic")
