"""Identification from measurements: second-order dynamics of step responses (thesis 6.4).

:func:`second_order` fits a step response ``y(t)`` with two methods:

- ``"logdec"``: the thesis's method done properly: smoothing, peaks of the deviation from
  the final value (scipy.signal.find_peaks), logarithmic decrement
  zeta = delta / sqrt(4 pi^2 + delta^2), damped frequency fd = 1/(t2 - t1) [Hz]; then
  wn = 2 pi fd / sqrt(1 - zeta^2). The thesis's "omega_n [Hz] = 1/(t2 - t1)" is fd.
- ``"fit"`` (default): least squares of the second-order step response
  y = y0 + K (1 - h(t - delay; zeta, wn)) over (zeta, wn, K, y0, delay), started from the
  log-decrement estimate; valid for any zeta, including >= 1.

No invented numbers: a response with fewer than two peaks is reported with the fit's zeta
(which may be >= 1) and ``overdamped=True``; an unusable response raises
:class:`IdentificationError`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import find_peaks, savgol_filter


MIN_R2 = 0.5  # below this the data is not a second-order step response


class IdentificationError(ValueError):
    """The data cannot be identified (flat, NaN, too short, not a step)."""


@dataclass
class SecondOrderFit:
    """Second-order model of a step response.

    zeta [-], wn [rad/s], fn = wn / 2 pi [Hz], fd = damped frequency [Hz] (NaN when
    zeta >= 1), gain K and offset y0 in the units of y, delay [s], method, r2, n_peaks,
    overdamped (fewer than two peaks: no oscillation to measure).
    """

    zeta: float
    wn: float
    gain: float
    offset: float
    delay: float
    method: str
    r2: float
    n_peaks: int
    overdamped: bool

    @property
    def fn(self) -> float:
        return self.wn / (2 * math.pi)

    @property
    def fd(self) -> float:
        return self.fn * math.sqrt(1 - self.zeta ** 2) if self.zeta < 1 else float("nan")

    def response(self, t) -> np.ndarray:
        """The model's step response at times ``t`` [s]."""
        return _model(np.asarray(t, dtype=float), self.zeta, self.wn, self.gain, self.offset, self.delay)


def _unit_step(tau, zeta, wn):
    """Unit step response of wn^2/(s^2 + 2 zeta wn s + wn^2) at tau >= 0 (0 before)."""
    tau = np.maximum(tau, 0.0)
    if zeta < 1.0 - 1e-6:
        wd = wn * math.sqrt(1 - zeta ** 2)
        e = np.exp(-zeta * wn * tau)
        return 1 - e * (np.cos(wd * tau) + zeta / math.sqrt(1 - zeta ** 2) * np.sin(wd * tau))
    if zeta <= 1.0 + 1e-6:
        return 1 - np.exp(-wn * tau) * (1 + wn * tau)
    r = math.sqrt(zeta ** 2 - 1)
    s1, s2 = -wn * (zeta - r), -wn * (zeta + r)
    return 1 - (s2 * np.exp(s1 * tau) - s1 * np.exp(s2 * tau)) / (s2 - s1)


def _model(t, zeta, wn, gain, offset, delay):
    return offset + gain * _unit_step(t - delay, zeta, wn)


def _validate(t, y):
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    if t.ndim != 1 or y.shape != t.shape:
        raise IdentificationError(f"t and y must be 1-D arrays of equal length, got {t.shape} and {y.shape}")
    if t.size < 20:
        raise IdentificationError(f"response too short: {t.size} samples (need at least 20)")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(y))):
        raise IdentificationError("response contains NaN or infinite values")
    if np.any(np.diff(t) <= 0):
        raise IdentificationError("time must increase strictly")
    n = t.size
    head = y[: max(3, n // 50)]
    tail = y[-max(5, n // 5):]
    step = float(np.mean(tail) - np.mean(head))
    span = float(np.ptp(y))
    if span <= 1e-12 * max(1.0, float(np.max(np.abs(y)))):
        raise IdentificationError("response is flat")
    resid = y - _smooth(y)
    noise = 1.4826 * float(np.median(np.abs(resid - np.median(resid))))
    if abs(step) < 8 * noise or abs(step) < 0.05 * span:
        raise IdentificationError(f"response is not a step: its end differs from its start by "
                                  f"{step:.3g}, against a range of {span:.3g} and noise {noise:.3g}")
    return t, y, float(np.mean(head)), float(np.mean(tail)), step


def _smooth(y):
    n = y.size
    win = max(5, (n // 60) | 1)
    return savgol_filter(y, win, 2) if n > win else y


def _logdec(t, y, y0, yf, step):
    """Thesis method, corrected: the decrement of peak-to-valley amplitudes one period
    apart (independent of the final value, so an unsettled response is fine)."""
    dev = (_smooth(y) - yf) / step          # overshoots are positive
    prom = max(0.005, 4 * float(np.std(np.diff(y))) / abs(step))
    peaks, _ = find_peaks(dev, prominence=prom)
    valleys, _ = find_peaks(-dev, prominence=prom)
    pairs = []
    for p in peaks:
        later = valleys[valleys > p]
        if later.size:
            pairs.append((p, later[0]))
    if len(pairs) < 2:
        return None, len(peaks)
    (p1, v1), (p2, v2) = pairs[0], pairs[1]
    a1, a2 = dev[p1] - dev[v1], dev[p2] - dev[v2]
    if a2 <= 0 or a1 <= a2:
        return None, len(peaks)
    delta = math.log(a1 / a2)
    zeta = delta / math.sqrt(4 * math.pi ** 2 + delta ** 2)
    fd = 1.0 / (t[p2] - t[p1])
    wn = 2 * math.pi * fd / math.sqrt(1 - zeta ** 2)
    return (zeta, wn), len(peaks)


def _r2(y, yhat):
    ss = float(np.sum((y - np.mean(y)) ** 2))
    return 1.0 - float(np.sum((y - yhat) ** 2)) / ss if ss > 0 else float("nan")


def second_order(t, y, method: str = "fit") -> SecondOrderFit:
    """Identify (zeta, wn) of a step response.

    Parameters
    ----------
    t : (N,) time [s], strictly increasing; the step is applied at or after t[0]
    y : (N,) response (any unit, e.g. foot height [m])
    method : "fit" (least squares, default) or "logdec" (the thesis's method)

    Returns
    -------
    SecondOrderFit (.zeta, .wn [rad/s], .fn [Hz], .fd [Hz], .r2, .n_peaks, .overdamped)
    """
    if method not in ("fit", "logdec"):
        raise ValueError(f"method must be 'fit' or 'logdec', got {method!r}")
    t, y, y0, yf, step = _validate(t, y)
    t = t - t[0]
    est, n_peaks = _logdec(t, y, y0, yf, step)
    if method == "logdec":
        if est is None:
            # no oscillation to measure: report the fit's zeta, flagged, never a constant
            fit = second_order(t, y, method="fit")
            fit.method = "logdec->fit"
            return fit
        zeta, wn = est
        yhat = _model(t, zeta, wn, step, y0, 0.0)
        return SecondOrderFit(zeta, wn, step, y0, 0.0, "logdec", _r2(y, yhat), n_peaks, False)
    starts = []
    if est is not None:
        starts.append(est)
    # rise time of the response gives a scale for wn when there is no oscillation
    cross = np.nonzero((y - y0) / step > 0.5)[0]
    t50 = t[cross[0]] if cross.size else t[-1] / 4
    for z in (0.2, 0.7, 1.5):
        starts.append((z, 1.8 / max(t50, 1e-3) * (1 + 0.6 * z)))
    best = None
    lo = [1e-3, 1e-2, -np.inf, -np.inf, 0.0]
    hi = [20.0, 1e4, np.inf, np.inf, 0.5 * t[-1]]
    for z0, w0 in starts:
        x0 = [min(max(z0, 2e-3), 19.0), min(max(w0, 2e-2), 9e3), step, y0, 0.0]
        res = least_squares(lambda p: _model(t, *p) - y, x0, bounds=(lo, hi), method="trf",
                            x_scale=[0.1, max(w0, 1.0) * 0.1, abs(step), abs(step), 0.005])
        if best is None or res.cost < best.cost:
            best = res
        if est is not None and res.cost < 1e-3 * float(np.sum((y - np.mean(y)) ** 2)):
            break  # started from the log decrement and fits well: done
    zeta, wn, gain, offset, delay = best.x
    r2 = _r2(y, _model(t, *best.x))
    if not r2 >= MIN_R2:
        raise IdentificationError(f"response is not a second-order step: the best fit explains "
                                  f"R^2 = {r2:.2f} of it (need {MIN_R2})")
    return SecondOrderFit(float(zeta), float(wn), float(gain), float(offset), float(delay), "fit",
                          r2, n_peaks, n_peaks < 2)
