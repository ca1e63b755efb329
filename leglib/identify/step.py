"""Identification from measurements: second-order dynamics of step responses (thesis 6.4).

:func:`second_order` reads a step response ``y(t)`` with three methods, in two measures:

- ``"fit"`` (default): least squares of the second-order step response
  y = y0 + K (1 - h(t - delay; zeta, wn)) over (zeta, wn, K, y0, delay), started from the
  corrected log-decrement estimate; valid for any zeta, including >= 1. This gives the true
  (textbook) zeta, wn, fn = wn / 2 pi and fd = fn sqrt(1 - zeta^2).
- ``"corrected_logdec"`` (alias ``"logdec"``): a corrected logarithmic decrement, *not* the
  thesis's method: smoothing, peaks of the deviation from the final value
  (scipy.signal.find_peaks), the decrement of peak-to-valley amplitudes one period apart,
  zeta = delta / sqrt(4 pi^2 + delta^2), fd = 1/(t2 - t1) [Hz], wn = 2 pi fd / sqrt(1 - zeta^2).
  Same measure as ``"fit"``.
- ``"thesis"``: Listing 7.7 ("identifyParams") exactly, returning a :class:`ThesisReading`:
  MATLAB ``smooth`` (5-point moving average with shrinking end spans) of -y, ``findpeaks``,
  delta = -ln(pks(1)/pks(2)) from the raw peak values (not from the final value),
  zeta = delta / sqrt(4 pi^2 + delta^2), and the listing's "omega_n [Hz]" = 1/(t2 - t1),
  which is a damped frequency (``.fd``). One peak gives zeta = 1, none zeta = 2, as the
  listing does, flagged. This is the measure of the thesis's Fig. 6.12, its target
  (zeta 0.24, 5 Hz) and its validation result (0.229, 5.06 Hz); it is strongly biased
  against the true zeta (see :mod:`leglib.thesis`). Apply it to the listing's own signal,
  :func:`leglib.model.kinematics.thesis_listing_height` of the zeroed angles in degrees.

No invented numbers in the true measure: a response with fewer than two peaks is reported
with the fit's zeta (which may be >= 1) and ``overdamped=True``; an unusable response raises
:class:`IdentificationError`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from statistics import NormalDist

import numpy as np

from .. import checks, plots
from ..errors import IdentificationError
from ..units import interval_text
from .fastfit import (
    C_DELAY,
    C_GAIN,
    C_N,
    C_NOISE,
    C_NPEAKS,
    C_OFFSET,
    C_R2,
    C_SPAN,
    C_STEP,
    C_WN,
    C_ZETA,
    FLAT,
    LOW_R2,
    MIN_R2,
    NO_DECAY,
    NONFINITE,
    NOT_INCREASING,
    NOT_STEP,
    OK,
    SHORT,
    ZETA_BOUND,
    ZETA_MAX,
    ZETA_MIN,
    _fit,
    _jacobian_normal_equations,
    _pack,
    _shapes,
    model,
    refit_from,
)
from .listing77 import LEVEL, MAX_SAMPLES, _crest_span, _series, _thesis_reading, sample_noise


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
    #: :class:`FitIntervals` of zeta, fn, fd when computed (``second_order(..., intervals=True)``,
    #: :func:`identify_batch` with ``intervals=True``, :func:`fit_intervals`); None otherwise
    intervals: object = field(default=None, repr=False, compare=False)

    @property
    def fn(self) -> float:
        return self.wn / (2 * math.pi)

    @property
    def fd(self) -> float:
        return self.fn * math.sqrt(1 - self.zeta ** 2) if self.zeta < 1 else float("nan")

    def _repr_markdown_(self) -> str:
        kind = "overdamped (fewer than two peaks)" if self.overdamped else f"{self.n_peaks} peaks"
        fd = f"{self.fd:.3f}" if self.zeta < 1 else "–"
        iv = self.intervals
        if iv is None:
            return ("| ζ | ωn [rad/s] | fn [Hz] | fd [Hz] | R² | |\n|---|---|---|---|---|---|\n"
                    f"| {self.zeta:.4f} | {self.wn:.3f} | {self.fn:.3f} | {fd} | {self.r2:.4f} | {self.method}, {kind} |")
        return (f"| ζ [{iv.level:.0%} interval] | fn [Hz] | fd [Hz] | R² | |\n|---|---|---|---|---|\n"
                f"| {iv.text('zeta', self.zeta)} | {iv.text('fn', self.fn)} | "
                f"{iv.text('fd', self.fd) if self.zeta < 1 else '–'} | {self.r2:.4f} | {self.method}, {kind} |")

    def plot(self, t, y, ax=None):
        """The measured response ``y(t)`` with this fit (:func:`leglib.plots.plot_step_identification`)."""
        return plots.plot_step_identification(np.asarray(t, float), np.asarray(y, float), self, ax=ax)

    def response(self, t) -> np.ndarray:
        """The model's step response at times ``t`` [s]."""
        t = np.asarray(t, dtype=float)
        return model(np.ascontiguousarray(t.ravel()), self.zeta, self.wn, self.gain, self.offset,
                     self.delay).reshape(t.shape)


def _validate(t, y):
    t, y = _series(t, y, 20)
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
    from scipy.signal import savgol_filter  # load time: scipy.signal, 0.6 s

    n = y.size
    win = max(5, (n // 60) | 1)
    return savgol_filter(y, win, 2) if n > win else y


def _logdec(t, y, y0, yf, step):
    """Corrected logarithmic decrement (not the thesis's Listing 7.7): the decrement of
    peak-to-valley amplitudes one period apart (independent of the final value, so an
    unsettled response is fine)."""
    from scipy.signal import find_peaks  # load time: scipy.signal, 0.6 s

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
        return None, len(peaks), None
    (p1, v1), (p2, v2) = pairs[0], pairs[1]
    a1, a2 = dev[p1] - dev[v1], dev[p2] - dev[v2]
    if a2 <= 0 or a1 <= a2:
        return None, len(peaks), None
    delta = math.log(a1 / a2)
    zeta = delta / math.sqrt(4 * math.pi ** 2 + delta ** 2)
    fd = 1.0 / (t[p2] - t[p1])
    wn = 2 * math.pi * fd / math.sqrt(1 - zeta ** 2)
    return (zeta, wn), len(peaks), (dev, (p1, v1, p2, v2))


def _logdec_intervals(t, y, step, dev, extrema, level: float) -> FitIntervals | None:
    """90 % intervals of the corrected log decrement's zeta, fn and fd, propagated from the
    doubt of the four extremes it reads (two peaks, two valleys of the smoothed deviation
    ``dev``), as Listing 7.7's reading is (:class:`leglib.identify.listing77.ReadingIntervals`:
    the record's sample noise taken whole at each extreme, the sample grid's miss of the
    crest; no average over further periods to take a scatter from, since only the first two
    are read): delta = ln(a1/a2) -+ z sd with sd^2 = var(a1)/a1^2 + var(a2)/a2^2, zeta its
    image; fd from the spans of samples within z sd of the two peaks (their extremes, a
    bound) and fn = fd / sqrt(1 - zeta^2) from both. ``se`` holds each half-width / z and
    ``model_error`` nothing (0): the interval is the propagation's alone. None when the two
    peaks are not told apart by their doubt."""
    z = _normal_quantile(level)
    noise = sample_noise(y) / abs(step)
    n = dev.size
    sds = {}
    for i in extrema:
        c = abs(dev[min(i + 1, n - 1)] - 2 * dev[i] + dev[max(i - 1, 0)])
        sds[i] = math.hypot(noise, c / 4 / math.sqrt(12))
    p1, v1, p2, v2 = extrema
    a1, a2 = dev[p1] - dev[v1], dev[p2] - dev[v2]
    h = z * math.sqrt((sds[p1] ** 2 + sds[v1] ** 2) / a1 ** 2 + (sds[p2] ** 2 + sds[v2] ** 2) / a2 ** 2)
    delta = math.log(a1 / a2)
    b1 = _crest_span(dev, p1, dev[p1] - z * sds[p1], 0, p2)
    b2 = _crest_span(dev, p2, dev[p2] - z * sds[p2], p1, n - 1)
    if b1[1] + 1 >= b2[0]:
        return None
    dt = float(np.median(np.diff(t)))
    fd = (1.0 / (t[b2[1]] - t[b1[0]] + dt), 1.0 / (t[b2[0]] - t[b1[1]] - dt))

    def zeta_of(d):
        return d / math.sqrt(4 * math.pi ** 2 + d ** 2)

    zi = (max(zeta_of(delta - h), 0.0), zeta_of(delta + h))
    fn = (fd[0] / math.sqrt(1 - zi[0] ** 2), fd[1] / math.sqrt(1 - zi[1] ** 2))
    se = {k: (hi - lo) / 2 / z for k, (lo, hi) in (("zeta", zi), ("fn", fn), ("fd", fd))}
    return FitIntervals(level, zi, fn, fd, se, {"zeta": 0.0, "fn": 0.0, "fd": 0.0})


def _r2(y, yhat):
    ss = float(np.sum((y - np.mean(y)) ** 2))
    return 1.0 - float(np.sum((y - yhat) ** 2)) / ss if ss > 0 else float("nan")
METHODS = ("fit", "corrected_logdec", "logdec", "thesis")


def second_order(t, y, method: str = "fit", intervals: bool = False):
    """Identify the second-order dynamics of a step response.

    Parameters
    ----------
    t : (N,) time [s], strictly increasing, finite; the step is applied at or after t[0]
    y : (N,) response (any unit, e.g. foot height [m]; for ``"thesis"`` the listing's
        signal, :func:`leglib.model.kinematics.thesis_listing_height`); real numbers: a
        masked array with masked samples is refused (masks are not honoured: drop those
        samples), so are complex values and strings. 20 <= N <= :data:`MAX_SAMPLES`
        (250 000): a longer record is refused with the advice to decimate it (``t[::k]``,
        ``y[::k]``), never decimated silently
    method : {"fit", "corrected_logdec", "logdec", "thesis"}
        "fit" (least squares, default) and "corrected_logdec" (a corrected logarithmic
        decrement; "logdec" is the same) give the true zeta, wn; "thesis" is Listing 7.7
        exactly, in the thesis's measure.
    intervals : also compute :class:`FitIntervals` (90 % intervals of zeta, fn, fd),
        ``.intervals``: with "fit", residual-corrected standard errors widened by the model
        error; with "corrected_logdec", the doubt of the extremes it reads propagated
        (:func:`_logdec_intervals`; None where its two peaks are not told apart by it).
        Listing 7.7's readings ("thesis") always carry theirs
        (:class:`leglib.identify.listing77.ReadingIntervals`)

    Returns
    -------
    SecondOrderFit (.zeta, .wn [rad/s], .fn [Hz], .fd [Hz], .r2, .n_peaks, .overdamped) for
    "fit" and "corrected_logdec"; :class:`ThesisReading` (.zeta, .fd [Hz] = 1/(t2 - t1),
    .peak_times, .peak_values, .flagged) for "thesis".
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(map(repr, METHODS))}, got {method!r}")
    if method == "thesis":
        return _thesis_reading(t, y)
    if method == "fit":
        # the arguments checked by name first (types, masks, size); then validation, starts
        # and fit in one compiled call (leglib.identify.fastfit), a batch of one
        _series(t, y, 20)
        fit = identify_batch([t], [y], intervals=intervals)[0]
        if isinstance(fit, IdentificationError):
            raise fit
        return fit
    t, y, y0, yf, step = _validate(t, y)
    t = t - t[0]
    est, n_peaks, read = _logdec(t, y, y0, yf, step)
    if method in ("corrected_logdec", "logdec"):
        if est is None:
            # no oscillation to measure: report the fit's zeta, flagged, never a constant
            fit = second_order(t, y, method="fit", intervals=intervals)
            fit.method = "corrected_logdec->fit"
            return fit
        zeta, wn = est
        yhat = model(t, zeta, wn, step, y0, 0.0)
        fit = SecondOrderFit(zeta, wn, step, y0, 0.0, "corrected_logdec", _r2(y, yhat), n_peaks, False)
        if intervals:
            fit.intervals = _logdec_intervals(t, y, step, *read, LEVEL)
        return fit


def standard_errors(fit: "SecondOrderFit", t, y) -> dict:
    """Standard errors of a second-order fit of (``t``, ``y``): zeta, wn [rad/s], fn [Hz] and
    fd [Hz] (NaN when zeta >= 1).

    From the model's Jacobian at the fit (central differences) and the residual variance,
    s^2 (J^T J)^-1, inflated by n / n_eff with n_eff = n / tau, tau the integrated
    autocorrelation time of the residuals (1 + 2 sum of their autocorrelation up to its
    first negative value): the residuals of a step response are correlated in time, and
    treating them as independent would make the numbers look more certain than the data
    allow. A response the model does not describe (large, structured residuals) therefore
    gets wide errors, not confident ones: on the leg, whose steps are second order only
    approximately (gravity, friction, the five-bar), zeta's standard error is typically
    several percent although repeated steps agree to about 0.5 %: zeta of such a response
    is defined only that well. fd's error is propagated from zeta's and wn's with their
    covariance (fd = wn sqrt(1 - zeta^2) / 2 pi).
    """
    t, y = _series(t, y, 8)
    t = t - t[0]   # the fit's delay counts from the record's first sample
    p = np.array([fit.zeta, fit.wn, fit.gain, fit.offset, fit.delay], float)
    r = y - model(t, *p)
    # J^T J with the kernel's exact Jacobian, in one pass (recurrence on a uniform grid)
    n = t.size
    dt = t[-1] / (n - 1)
    if np.any(np.abs(t - dt * np.arange(n)) > 1e-9 * dt):
        dt = 0.0
    JtJ = np.empty((5, 5))
    _jacobian_normal_equations(t, y, p, JtJ, np.empty(5), dt)
    s2 = float(np.dot(r, r)) / max(n - p.size, 1) * max(_autocorrelation_time(r), 1.0)
    try:
        cov = s2 * np.linalg.inv(JtJ)
    except np.linalg.LinAlgError:
        return {"zeta": math.inf, "wn": math.inf, "fn": math.inf, "fd": math.inf}
    se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    out = {"zeta": float(se[0]), "wn": float(se[1]), "fn": float(se[1] / (2 * math.pi)), "fd": math.nan}
    if fit.zeta < 1:
        # d fd / d (zeta, wn) with fd = wn sqrt(1 - zeta^2) / 2 pi
        q = math.sqrt(1 - fit.zeta ** 2)
        g = np.array([-fit.wn * fit.zeta / q, q]) / (2 * math.pi)
        out["fd"] = float(math.sqrt(max(float(g @ cov[:2, :2] @ g), 0.0)))
    return out


def _autocorrelation_time(r: np.ndarray) -> float:
    """Integrated autocorrelation time [samples] of residuals ``r``: 1 + 2 sum of their
    autocorrelation up to its first negative value."""
    c = r - r.mean()
    m = c.size
    spec = np.fft.rfft(c, 2 * m)
    acf = np.fft.irfft(spec * np.conj(spec))[:m]
    acf = acf / acf[0] if acf[0] > 0 else np.zeros(m)
    neg = np.flatnonzero(acf[1:] <= 0)
    return 1.0 + 2.0 * float(np.sum(acf[1:1 + (neg[0] if neg.size else m - 1)]))


# LEVEL (0.90), the confidence level of the intervals quoted for zeta, fn and fd, is
# leglib.identify.listing77's, shared with Listing 7.7's readings
#: the leading parts of a record the model-error term refits (fractions of its samples)
WINDOWS = (0.5, 2.0 / 3.0, 5.0 / 6.0)


@dataclass(frozen=True)
class FitIntervals:
    """Intervals of a second-order fit's zeta [-], fn [Hz] and fd [Hz] at confidence ``level``.

    Each interval is (low, high) = value -+ h, h = sqrt((z se)^2 + m^2), clipped at 0:
    ``se`` the residual-corrected standard error (:func:`standard_errors`), z the normal
    quantile of ``level`` (1.645 for 90 %), and ``model_error`` m the largest change of the
    value when the same model is fitted to the leading 1/2, 2/3 and 5/6 of the record
    (:data:`WINDOWS`), each fit started from the whole record's (the same minimum, moved by
    what the window leaves out: :func:`leglib.identify.fastfit.refit_from`). A response the second-order model describes exactly gives the same
    numbers from every window, so m measures how much the numbers depend on which part of
    an approximate response is fitted (the slow integrator mode, friction's stick near
    rest), a model error the noise term does not hold. m is infinite when no window
    could be fitted (the numbers then rest on the whole record alone).

    Measured on the twin (tests/identify/test_intervals.py): at three gain points, 50 steps
    each with fresh noise seeds, these intervals hold the seeds' mean value in every case;
    where the fit explains R^2 > 0.999 of the response zeta's interval is about +-1 %, at
    R^2 0.97 (the thesis's target) about +-30 %: zeta of such a response is defined that
    loosely (the corrected log decrement of the same response differs from the fit by 36 %).
    """

    level: float
    zeta: tuple
    fn: tuple
    fd: tuple
    se: dict
    model_error: dict

    def half_width(self, name: str) -> float:
        """h of ``name`` ("zeta", "fn", "fd"), before clipping at 0."""
        z = _normal_quantile(self.level)
        return float(math.hypot(z * self.se[name], self.model_error[name]))

    def relative(self, name: str, value: float) -> float:
        """h / |value|: the interval's relative half-width."""
        return self.half_width(name) / abs(value) if value else math.inf

    def text(self, name: str, value: float, unit: str = "") -> str:
        """"value [low, high]" to the digits the interval supports (:func:`leglib.units.interval_text`)."""
        return interval_text(value, getattr(self, name), unit)

    def to_dict(self) -> dict:
        """Plain numbers for a metrics file: the intervals, standard errors and model errors."""
        return {"level": self.level, "zeta": list(self.zeta), "fn": list(self.fn), "fd": list(self.fd),
                "se": dict(self.se), "model_error": dict(self.model_error)}


def _normal_quantile(level: float) -> float:
    """z with P(|N(0, 1)| <= z) = level."""
    if not 0 < level < 1:
        raise ValueError(f"level must lie in (0, 1), got {level!r}")
    return NormalDist().inv_cdf(0.5 + level / 2)


def _interval(value: float, se: float, m: float, z: float) -> tuple:
    if not math.isfinite(value):
        return (math.nan, math.nan)
    h = math.hypot(z * se, m)
    return (max(value - h, 0.0), value + h)


def _window_parts(t, y):
    """(t, y) of the leading :data:`WINDOWS` of a record (each at least 20 samples)."""
    n = len(t)
    return [(t[:int(f * n)], y[:int(f * n)]) for f in WINDOWS if int(f * n) >= 20]


def _window_values(params) -> dict:
    """{"zeta", "fn", "fd"} of a refit's parameter row (NaN row: no values)."""
    zeta, wn = float(params[0]), float(params[1])
    fn = wn / (2 * math.pi)
    return {"zeta": zeta, "fn": fn, "fd": fn * math.sqrt(1 - zeta ** 2) if zeta < 1 else math.nan}


def _make_intervals(fit: "SecondOrderFit", se: dict, windows, level: float) -> FitIntervals:
    """:class:`FitIntervals` of ``fit`` from its standard errors ``se`` and its window refits
    (parameter rows of :func:`leglib.identify.fastfit.refit_from`, NaN for a failed one)."""
    z = _normal_quantile(level)
    good = [_window_values(w) for w in windows if np.isfinite(w[0])]
    m = {}
    for name in ("zeta", "fn", "fd"):
        v = getattr(fit, name)
        if not math.isfinite(v):
            m[name] = math.nan
            continue
        d = [abs(w[name] - v) for w in good]
        # a window whose fit has no fd (zeta >= 1 there) says fd is not defined that well
        m[name] = max((x if math.isfinite(x) else v for x in d), default=math.inf)
    return FitIntervals(level, _interval(fit.zeta, se["zeta"], m["zeta"], z),
                        _interval(fit.fn, se["fn"], m["fn"], z), _interval(fit.fd, se["fd"], m["fd"], z),
                        {k: se[k] for k in ("zeta", "fn", "fd")}, m)


def fit_intervals(fit: "SecondOrderFit", t, y, level: float = LEVEL) -> FitIntervals:
    """The :class:`FitIntervals` (zeta, fn [Hz], fd [Hz]) of a second-order ``fit`` of
    (``t`` [s], ``y``); also stored as ``fit.intervals``."""
    t, y = _series(t, y, 20)
    parts = _window_parts(t, y)
    windows = refit_from([w[0] for w in parts], [w[1] for w in parts], [_params(fit)] * len(parts))
    fit.intervals = _make_intervals(fit, standard_errors(fit, t, y), windows, level)
    return fit.intervals


def _params(fit: "SecondOrderFit") -> list:
    return [fit.zeta, fit.wn, fit.gain, fit.offset, fit.delay]


def _error(code, row):
    """The message of a failed identification (the same words as identify's checks)."""
    if code == SHORT:
        return f"response too short: {int(row[C_N])} samples (need at least 20)"
    if code == NONFINITE:
        return "response contains NaN or infinite values"
    if code == NOT_INCREASING:
        return "time must increase strictly"
    if code == FLAT:
        return "response is flat"
    if code == NOT_STEP:
        return (f"response is not a step: its end differs from its start by "
                f"{row[C_STEP]:.3g}, against a range of {row[C_SPAN]:.3g} and noise {row[C_NOISE]:.3g}")
    if code == ZETA_BOUND:
        return f"response too overdamped to identify (zeta reached the fit's bound {ZETA_MAX})"
    if code == LOW_R2:
        return (f"response is not a second-order step: the best fit explains "
                f"R^2 = {row[C_R2]:.2f} of it (need {MIN_R2})")
    if code == NO_DECAY:
        return (f"response is not a second-order step: its oscillation does not decay (zeta reached "
                f"the fit's lower bound {ZETA_MIN})")
    raise AssertionError(code)

def identify_batch(ts, ys, shapes: bool = False, intervals: bool = False, level: float = LEVEL):
    """Second-order identification of many step responses in one compiled call.

    Parameters
    ----------
    ts, ys : sequences of array-likes, times [s] (strictly increasing) and responses, of real
        numbers (masked arrays with masked samples, complex values and strings are refused),
        at most :data:`MAX_SAMPLES` samples each (decimate longer records first)
    shapes : also return each response's :func:`shape_numbers` row (NaN for a response
        refused before fitting), from the same packed copy of the data
    intervals : also give every fit its :class:`FitIntervals` at ``level`` (``.intervals``;
        the window refits of all responses in one more compiled call)

    Returns
    -------
    list, per response, of a :class:`leglib.identify.step.SecondOrderFit` (method "fit") or
    the :class:`leglib.errors.IdentificationError` that
    :func:`leglib.identify.step.second_order` raises for it; with ``shapes``, the pair
    (that list, the (K, 4) shape numbers)
    """

    ts, ys = list(ts), list(ys)
    if len(ts) != len(ys):
        raise ValueError(f"{len(ts)} time arrays for {len(ys)} responses")
    bad = {}
    for k, (t, y) in enumerate(zip(ts, ys)):
        try:
            ts[k] = checks.real_array(t, f"ts[{k}]", IdentificationError, finite=False, max_size=MAX_SAMPLES)
            ys[k] = checks.real_array(y, f"ys[{k}]", IdentificationError, finite=False, max_size=MAX_SAMPLES)
        except IdentificationError as exc:
            bad[k] = exc
            continue
        t, y = ts[k], ys[k]
        if t.ndim != 1 or y.shape != t.shape:
            bad[k] = IdentificationError(f"t and y must be 1-D arrays of equal length, got {t.shape} and {y.shape}")
    keep = [k for k in range(len(ts)) if k not in bad]
    packed = _pack([ts[k] for k in keep], [ys[k] for k in keep])
    status, out = _fit(*packed)
    results = [None] * len(ts)
    for k, e in bad.items():
        results[k] = e
    for k, code, row in zip(keep, status, out):
        if code != OK:
            results[k] = IdentificationError(_error(int(code), row))
            continue
        n_peaks = int(row[C_NPEAKS])
        results[k] = SecondOrderFit(float(row[C_ZETA]), float(row[C_WN]), float(row[C_GAIN]),
                                    float(row[C_OFFSET]), float(row[C_DELAY]), "fit", float(row[C_R2]),
                                    n_peaks, n_peaks < 2)
    if intervals:
        add_intervals(results, ts, ys, level)
    if not shapes:
        return results
    numbers = np.full((len(ts), 4), np.nan)
    numbers[keep] = _shapes(*packed)
    return results, numbers


def add_intervals(results, ts, ys, level: float = LEVEL) -> None:
    """Set ``.intervals`` (:class:`FitIntervals` at ``level``) of every SecondOrderFit in
    ``results`` (fits of ``ts`` [s], ``ys``; other entries, e.g. errors, are skipped): the
    window refits of all of them in one compiled call, then each one's standard errors."""
    done = [k for k, f in enumerate(results) if isinstance(f, SecondOrderFit)]
    parts = {k: _window_parts(np.asarray(ts[k], float), np.asarray(ys[k], float)) for k in done}
    flat = [w for k in done for w in parts[k]]
    starts = [_params(results[k]) for k in done for _ in parts[k]]
    refits = iter(refit_from([w[0] for w in flat], [w[1] for w in flat], starts) if flat else [])
    for k in done:
        windows = [next(refits) for _ in parts[k]]
        results[k].intervals = _make_intervals(results[k], standard_errors(results[k], ts[k], ys[k]), windows,
                                               level)
