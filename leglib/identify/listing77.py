"""The thesis's Listing 7.7 ("identifyParams") exactly, in its own measure.

MATLAB ``smooth`` (5-point moving average with shrinking end spans) of -y, ``findpeaks``,
delta = -ln(pks(1)/pks(2)) from the raw peak values (not from the final value),
zeta = delta / sqrt(4 pi^2 + delta^2), and the listing's "omega_n [Hz]" = 1/(t2 - t1), a
damped frequency (``.fd``). One peak gives zeta = 1, none zeta = 2, as the listing does,
flagged. This is the measure of the thesis's Fig. 6.12, its target (zeta 0.24, 5 Hz) and its
validation result (0.229, 5.06 Hz); it is strongly biased against the true zeta (see
:mod:`leglib.thesis`). Apply it to the listing's own signal,
:func:`leglib.model.kinematics.thesis_listing_height` of the zeroed angles in degrees.

A reading whose first two peaks are the oscillation's (:attr:`ThesisReading.usable`) carries
90 % intervals of its zeta and its 1/(t2 - t1) (:class:`ReadingIntervals`): the doubt of what
the listing reads of this response, from the doubt of the two peak values it divides (the
record's sample noise, the encoder's quantization at each crest, the sample grid) and of the
two peak times. They bound the listing's own reading, not the true zeta, from which it is
biased by far more (:mod:`leglib.thesis`). A reading the listing fails on has none, and says
why (:attr:`ThesisReading.interval_reason`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from statistics import NormalDist

import numpy as np

from .. import checks, plots
from ..errors import IdentificationError
from ..units import interval_text

#: a second peak whose prominence (its height above the lowest point between the first two
#: peaks) is below this part of the step of smooth(-y) is ripple on the settled tail, not the
#: oscillation's second peak (on the twin over the thesis grid: 0.2 to 0.45 of the step where
#: the true zeta is below 0.3, under 0.007 where it is above 0.6)
RIPPLE = 0.01

# the most samples a response may have: a step of seconds at the ODrive's 8 kHz is below
# 100 000, and the fit of 1 000 000 takes tens of seconds; longer records are refused with
# the advice to decimate them (y[::k], t[::k]), never cut or decimated silently
MAX_SAMPLES = 250_000

#: the confidence level of the intervals quoted for identified values (the fit's zeta, fn, fd
#: and Listing 7.7's readings)
LEVEL = 0.90
#: the local fit whose residual measures a record's sample noise: a cubic over 11 samples
#: (22 ms at Listing 7.4's 2 ms) follows an oscillation of up to about 25 Hz and leaves the
#: sample-to-sample noise
NOISE_WINDOW, NOISE_ORDER = 11, 3


def _series(t, y, min_samples: int, names=("t", "y")):
    """``t``, ``y`` as float arrays, checked: arrays of real numbers (no strings, no complex
    values, no masked samples: masks are not honoured), 1-D, equal length, at least
    ``min_samples`` and at most :data:`MAX_SAMPLES`, finite, time strictly increasing.
    IdentificationError naming the argument (``names``) otherwise."""
    t = checks.real_array(t, names[0], IdentificationError, finite=False, max_size=MAX_SAMPLES)
    y = checks.real_array(y, names[1], IdentificationError, finite=False, max_size=MAX_SAMPLES)
    if t.ndim != 1 or y.shape != t.shape:
        raise IdentificationError(f"t and y must be 1-D arrays of equal length, got {t.shape} and {y.shape}")
    if t.size < min_samples:
        raise IdentificationError(f"response too short: {t.size} samples (need at least {min_samples})")
    if not np.all(np.isfinite(t)):
        raise IdentificationError(f"time {names[0]} contains NaN or infinite values")
    if not np.all(np.isfinite(y)):
        raise IdentificationError("response contains NaN or infinite values")
    if np.any(np.diff(t) <= 0):
        raise IdentificationError("time must increase strictly")
    return t, y


@dataclass
class ThesisReading:
    """A step response read by the thesis's Listing 7.7 ("identifyParams").

    All numbers are in the thesis's measure, not the true second-order parameters.

    Attributes
    ----------
    zeta : float
        Listing 7.7's damping [-]: delta / sqrt(4 pi^2 + delta^2) with
        delta = -ln(pks(1)/pks(2)) from the raw peak values of smooth(-y); 1 for one peak,
        2 for none (the listing's constants, see ``flagged``).
    fd : float
        1/(t2 - t1) [Hz] between the first two peaks: the listing's "omega_n [Hz]" (eq. 6.8),
        a damped frequency. NaN with fewer than two peaks (the listing returns 0 there, see
        ``listing_output``).
    delta : float
        The decrement -ln(pks(1)/pks(2)) [-]; NaN with fewer than two peaks.
    peak_times : (P,) ndarray
        Times [s] of every peak ``findpeaks`` finds in smooth(-y) (``locs``).
    peak_values : (P,) ndarray
        The peaks' values of smooth(-y) (``pks``), in the unit of y.
    smoothed : (N,) ndarray
        smooth(-y), the signal the peaks are taken from.
    method : str
        "thesis".
    peak_index : (P,) ndarray of int
        The peaks' sample indices.
    record_end : float
        The record's last time [s].
    """

    zeta: float
    fd: float
    delta: float
    peak_times: np.ndarray
    peak_values: np.ndarray
    smoothed: np.ndarray
    method: str = "thesis"
    peak_index: np.ndarray = None
    record_end: float = float("nan")
    #: :class:`ReadingIntervals` of a usable reading (None otherwise: see ``interval_reason``)
    intervals: object = field(default=None, repr=False, compare=False)
    #: why the first two peaks are not told apart by their doubt (:func:`add_intervals`;
    #: a failure, see :attr:`failure`), or None
    interval_failure: str | None = field(default=None, repr=False, compare=False)

    @property
    def n_peaks(self) -> int:
        return int(self.peak_times.size)

    @property
    def flagged(self) -> bool:
        """True when zeta is the listing's constant (1 for one peak, 2 for none)."""
        return self.n_peaks < 2

    overdamped = flagged

    @property
    def second_peak_prominence(self) -> float:
        """The second peak's height above the lowest point of smooth(-y) between the first two
        peaks, as a part of the step of smooth(-y) (NaN with fewer than two peaks)."""
        if self.n_peaks < 2 or self.peak_index is None:
            return float("nan")
        sm = self.smoothed
        n = sm.size
        step = abs(float(np.mean(sm[n - max(5, n // 5):])) - float(np.mean(sm[:max(3, n // 50)])))
        i1, i2 = int(self.peak_index[0]), int(self.peak_index[1])
        return float((self.peak_values[1] - sm[i1:i2 + 1].min()) / step) if step > 0 else float("nan")

    @property
    def failure(self) -> str | None:
        """The kind of an outright failure of the listing on this response, or None:
        ``"flagged"`` (fewer than two peaks: its constants), ``"ripple"`` (the second peak is
        ripple of the settled tail), ``"unresolved"`` (the two peaks are not told apart by
        their doubt: within the record's noise and the encoder's resolution smooth(-y) does not
        fall between them, e.g. a noise bump on the rise taken for the first peak). A reading
        with more peaks than cycles is not one: its first two peaks are the oscillation's."""
        if self.flagged:
            return "flagged"
        if self.second_peak_prominence < RIPPLE:
            return "ripple"
        if self.interval_failure:
            return "unresolved"
        return None

    @property
    def usable(self) -> bool:
        """True when the listing's first two peaks are the oscillation's: at least two, the
        second not ripple of the settled tail (prominence at least :data:`RIPPLE` of the
        step), and the two told apart by more than their doubt (:attr:`failure`). Only such
        readings say what Listing 7.7 reads of a response, and only they have intervals."""
        return self.failure is None

    @property
    def problem(self) -> str | None:
        """Why Listing 7.7 fails on this response, or None: fewer than two peaks (its
        constants), a second peak that is ripple of the settled tail, two peaks not told
        apart by their doubt, or more peaks than an oscillation at the reading's own
        frequency has in the record (findpeaks counts the quantized tail's ripple; the first
        two may still be the oscillation's, see :attr:`usable`)."""
        if self.flagged:
            return (f"fewer than two peaks ({self.n_peaks}): the listing returns its constant zeta = "
                    f"{self.zeta:g}, no reading")
        prom = self.second_peak_prominence
        if prom < RIPPLE:
            return (f"its second 'peak' is ripple of the settled tail (prominence {prom:.2%} of the step, under "
                    f"{RIPPLE:.0%}): the reading measures the encoder's quantization, not the oscillation")
        if self.interval_failure:
            return self.interval_failure
        cycles = (self.record_end - self.peak_times[0]) * self.fd + 1
        if np.isfinite(cycles) and self.n_peaks > cycles + 1:
            return (f"findpeaks finds {self.n_peaks} peaks where an oscillation at the reading's own "
                    f"{self.fd:.2f} Hz has at most {int(cycles) + 1} in the record: it counts the quantized tail's "
                    f"ripple as peaks (its first two are the oscillation's here)")
        return None

    @property
    def interval_reason(self) -> str | None:
        """Why the reading has no interval (None when it has one): the listing fails on the
        response (:attr:`problem`, no reading to give an interval to)."""
        if self.intervals is not None:
            return None
        if not self.usable:
            return f"no reading: {self.problem}"
        return "no interval computed (add_intervals)"

    @property
    def zeta_interval(self) -> tuple:
        """90 % interval (low, high) of the listing's zeta; (NaN, NaN) without one."""
        return self.intervals.zeta if self.intervals is not None else (math.nan, math.nan)

    @property
    def fd_interval(self) -> tuple:
        """90 % interval (low, high) [Hz] of the listing's 1/(t2 - t1); (NaN, NaN) without one."""
        return self.intervals.fd if self.intervals is not None else (math.nan, math.nan)

    def text(self) -> str:
        """"zeta 0.0460 [0.0458, 0.0462], 1/(t2 - t1) 4.67 [4.6, 4.8] Hz (Listing 7.7, 90 %
        intervals)", or why the listing gives no reading (its constant, tail ripple) or no
        interval."""
        if self.intervals is None:
            if not self.usable:
                return f"Listing 7.7 fails: {self.problem}"
            return (f"zeta {self.zeta:.4g}, 1/(t2 - t1) {self.fd:.3g} Hz (Listing 7.7; no interval: "
                    f"{self.interval_reason})")
        return (f"zeta {interval_text(self.zeta, self.zeta_interval)}, 1/(t2 - t1) "
                f"{interval_text(self.fd, self.fd_interval)} Hz (Listing 7.7, {100 * self.intervals.level:.0f} % intervals)")

    def to_dict(self) -> dict:
        """Plain values for a metrics file: the reading, its intervals (or why none) and why
        the listing fails, if it does."""
        nan = [math.nan, math.nan]
        return {"zeta": self.zeta, "f_hz": self.fd if self.n_peaks >= 2 else math.nan, "n_peaks": self.n_peaks,
                "usable": self.usable, "problem": self.problem,
                "zeta_interval": list(self.zeta_interval) if self.intervals is not None else nan,
                "f_interval": list(self.fd_interval) if self.intervals is not None else nan,
                "interval_reason": self.interval_reason}

    def plot(self, t, ax=None):
        """Listing 7.7's view of the step at times ``t``: smooth(-y) with the peaks it found
        (:func:`leglib.plots.plot_thesis_peaks`)."""
        return plots.plot_thesis_peaks(np.asarray(t, float), self, ax=ax)

    def _repr_markdown_(self) -> str:
        how = "flagged: the listing's constant (fewer than two peaks)" if self.flagged else f"{self.n_peaks} peaks"
        if self.problem and not self.flagged:
            how += f"; **the listing fails here**: {self.problem}"
        if self.intervals is not None:
            zeta, fd = interval_text(self.zeta, self.zeta_interval), interval_text(self.fd, self.fd_interval)
        else:
            zeta, fd = f"{self.zeta:.4f}", (f"{self.fd:.3f}" if self.n_peaks >= 2 else "–")
            how += f"; no interval: {self.interval_reason}" if self.usable else ""
        return ("| ζ (Listing 7.7) [90 % interval] | 1/(t2 − t1) [Hz] | |\n|---|---|---|\n"
                f"| {zeta} | {fd} | thesis measure, {how} |")

    @property
    def listing_output(self) -> tuple[float, float]:
        """``[wn, xi]`` exactly as Listing 7.7 returns them (wn = 0 with fewer than two peaks)."""
        return (self.fd if self.n_peaks >= 2 else 0.0, self.zeta)


def matlab_smooth(y, span: int = 5) -> np.ndarray:
    """MATLAB's ``smooth(y)``: a moving average of ``span`` points (odd), whose span shrinks
    symmetrically near the ends (yy(1) = y(1), yy(2) = mean(y(1:3)), ...).

    Parameters
    ----------
    y : (N,) array_like
    span : int, odd, default 5 (MATLAB's default)

    Returns
    -------
    (N,) ndarray, in the unit of y
    """
    y = np.asarray(y, dtype=float)
    if span < 1 or span % 2 == 0:
        raise ValueError(f"span must be a positive odd integer, got {span}")
    n = y.size
    h = span // 2
    out = np.empty(n)
    # window sums added left to right, sample by sample (no running sums), so equal windows
    # of quantized data give exactly equal averages and findpeaks sees the same plateaus
    if n > 2 * h:
        acc = np.zeros(n - 2 * h)
        for j in range(span):
            acc = acc + y[j:n - 2 * h + j]
        out[h:n - h] = acc / span
    for k in list(range(min(h, n))) + list(range(max(n - h, 0), n)):
        w = min(k, n - 1 - k, h)
        out[k] = sum(y[k - w:k + w + 1].tolist()) / (2 * w + 1)
    return out


def matlab_findpeaks(x) -> np.ndarray:
    """Indices of MATLAB ``findpeaks(x)``'s peaks with its default options: samples larger
    than both neighbours, a flat peak reported at its first sample, never an end point."""
    x = np.asarray(x, dtype=float)
    if x.size < 3:
        return np.zeros(0, dtype=int)
    # collapse runs of equal values to their first sample, as findpeaks does
    keep = np.concatenate([[True], x[1:] != x[:-1]])
    idx = np.nonzero(keep)[0]
    s = np.sign(np.diff(x[idx]))
    # a rise followed by a fall; the run's first sample must not be an end point
    peak = np.nonzero((s[:-1] > 0) & (s[1:] < 0))[0] + 1
    return idx[peak]


def _thesis_reading(t, y) -> ThesisReading:
    """Listing 7.7 on (``t``, ``y``), with the intervals of a usable reading from the
    record's noise alone (:func:`add_intervals`; a quantized record's callers add the
    encoder's resolution, as :func:`leglib.thesis.read_angles` does)."""
    reading = _listing(t, y)
    return add_intervals(reading, t, y)


def _listing(t, y) -> ThesisReading:
    t, y = _series(t, y, 3)
    inv = matlab_smooth(-y)
    i = matlab_findpeaks(inv)
    pks, locs = inv[i], t[i]
    if pks.size == 0:
        zeta, fd, delta = 2.0, float("nan"), float("nan")
    elif pks.size == 1:
        zeta, fd, delta = 1.0, float("nan"), float("nan")
    else:
        ratio = pks[0] / pks[1]
        if not ratio > 0:
            raise IdentificationError(f"Listing 7.7 cannot read this response: its first two peaks "
                                      f"({pks[0]:.4g}, {pks[1]:.4g}) differ in sign, so ln(pks(1)/pks(2)) "
                                      "is not real (the listing expects y of one sign)")
        delta = -math.log(ratio)
        zeta = delta / math.sqrt((2 * math.pi) ** 2 + delta ** 2)
        fd = 1.0 / (locs[1] - locs[0])
    return ThesisReading(float(zeta), float(fd), float(delta), locs, pks, inv, peak_index=i,
                         record_end=float(t[-1]))


# ---------------------------------------------------------------------------------------
# the doubt of a reading
# ---------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ReadingIntervals:
    """Intervals of a Listing 7.7 reading at confidence ``level``, in the listing's measure.

    The listing reads one pair of peaks: zeta from delta = ln(pks(2)/pks(1)) of the first two
    peak values of smooth(-y), 1/(t2 - t1) from their times. There is no average over
    successive peak pairs whose scatter could give a standard error (the listing takes the
    first pair only, and the decrements of later pairs of raw peak values differ
    systematically, as the peaks close in on the final value), so the doubt is propagated
    from that of the two peaks:

    - **a peak value's standard deviation** ``peak_sd`` [unit of y] combines (in quadrature)
      the record's sample noise ``noise`` (:func:`sample_noise`), taken whole: at a crest the
      signal is flat over the listing's 5-point smoothing, so the encoder's quantization error
      is the same in all five samples and the smoothing does not reduce it, and findpeaks takes
      the largest of the near-crest samples, which undoes the averaging of white noise; the
      encoder's quantization at the crest, ``quantization`` (the standard deviation of a
      rounding to whole counts, one count / sqrt(12) per joint, given by the caller that knows
      the counts); and the sample grid, which may miss the crest by up to half a sample, i.e.
      up to c/4 below it for a crest of curvature c per sample^2 (uniform: c / (4 sqrt(12))).
    - **delta**: ``delta -+ z sd``, sd^2 = (sd1/p1)^2 + (sd2/p2)^2 (independent peaks, z the
      normal quantile of ``level``, 1.645); **zeta** = delta / sqrt(4 pi^2 + delta^2) is
      increasing in delta, so its interval is the image of delta's.
    - **the peak times** ``peak_spans`` [s]: under that doubt the listing could have put a
      peak at any sample of smooth(-y) within z sd of the crest's value (a broad or flat crest
      leaves it a span of samples, and findpeaks reports a plateau at its first), and at
      another phase of the sampling grid half a sample further; **1/(t2 - t1)** takes the
      extremes of both spans (a bound, at least ``level``).

    What they bound is the listing's reading of this record without its measurement error,
    not the reading of another run of the same experiment (one record does not show how
    much the leg's motion itself differs from run to run) nor the true zeta. Checked on
    synthetic steps with noise and quantization (tests/identify/test_intervals.py): they hold
    the listing's noise-free reading of the same step in at least 80 % of the repetitions
    (about all of them: taking the noise whole makes them conservative, the 90th percentile
    of the error is about half the half-width). Where the two peaks' spans touch, the
    reading is not defined by its data: a failure, no interval (:attr:`ThesisReading.failure`).
    """

    level: float
    zeta: tuple
    fd: tuple
    delta: tuple
    peak_sd: tuple
    peak_spans: tuple
    noise: float
    quantization: tuple

    def to_dict(self) -> dict:
        return {"level": self.level, "zeta": list(self.zeta), "fd": list(self.fd), "delta": list(self.delta),
                "peak_sd": list(self.peak_sd), "peak_spans": [list(x) for x in self.peak_spans],
                "noise": self.noise, "quantization": list(self.quantization)}


def sample_noise(y) -> float:
    """The standard deviation of ``y``'s sample-to-sample noise [unit of y]: the robust
    (median absolute deviation) spread of its residual from a local cubic
    (Savitzky-Golay, :data:`NOISE_WINDOW` samples), divided by sqrt(1 - h0), h0 the local
    fit's weight of the sample itself (white noise of standard deviation s leaves a residual
    of s sqrt(1 - h0)). The median keeps the step's onset, where the local cubic does not
    follow, from counting as noise. 0 for a record shorter than the window."""
    from scipy.signal import savgol_filter  # load time: scipy.signal, 0.6 s

    y = np.asarray(y, float)
    if y.size < NOISE_WINDOW:
        return 0.0
    r = y - savgol_filter(y, NOISE_WINDOW, NOISE_ORDER)
    h0 = float(savgol_filter(np.eye(NOISE_WINDOW)[NOISE_WINDOW // 2], NOISE_WINDOW, NOISE_ORDER,
                             mode="constant")[NOISE_WINDOW // 2])
    mad = float(np.median(np.abs(r - np.median(r))))
    return 1.4826 * mad / math.sqrt(1.0 - h0)


def _z(level: float) -> float:
    if not 0 < level < 1:
        raise ValueError(f"level must lie in (0, 1), got {level!r}")
    return NormalDist().inv_cdf(0.5 + level / 2)


def _crest_span(sm, i: int, floor: float, lo: int, hi: int) -> tuple[int, int]:
    """The samples around ``i`` (within ``lo`` .. ``hi``) where smooth(-y) stays at or above
    ``floor``: where the listing could put this crest under its doubt."""
    a = i
    while a - 1 >= lo and sm[a - 1] >= floor:
        a -= 1
    b = i
    while b + 1 <= hi and sm[b + 1] >= floor:
        b += 1
    return a, b


def add_intervals(reading: ThesisReading, t, y, quantization=(0.0, 0.0), level: float = LEVEL) -> ThesisReading:
    """Set the :class:`ReadingIntervals` of a usable ``reading`` of (``t`` [s], ``y``); a reading
    the listing fails on keeps none (:attr:`ThesisReading.interval_reason` says why).

    Parameters
    ----------
    reading : the :class:`ThesisReading` of (t, y)
    t, y : the record it was read from
    quantization : the standard deviation [unit of y] of the encoder's rounding at the first
        and the second peak: a count's change of y at each joint's angle there, / sqrt(12),
        summed in quadrature over the joints (:func:`leglib.thesis.read_angles`); 0 for a
        record that is not quantized or whose counts are unknown
    level : confidence level (default :data:`LEVEL`)

    Returns
    -------
    ``reading``, its ``intervals`` (and ``interval_failure``) set.
    """
    reading.intervals, reading.interval_failure = None, None
    if not reading.usable or reading.peak_index is None:   # the listing's own failures: no reading
        return reading
    t, y = _series(t, y, 3)
    z = _z(level)
    sm, idx, pk = reading.smoothed, reading.peak_index, reading.peak_values
    n = sm.size
    noise = sample_noise(y)
    quant = tuple(float(abs(q)) for q in quantization)
    if len(quant) != 2 or not all(math.isfinite(q) for q in quant):
        raise ValueError(f"quantization must be two finite standard deviations, got {quantization!r}")
    dt = float(np.median(np.diff(t)))
    sds, spans = [], []
    for k in (0, 1):
        i = int(idx[k])
        # the crest's curvature per sample^2 (smooth(-y) has a maximum there: second difference <= 0)
        c = max(-(sm[min(i + 1, n - 1)] - 2 * sm[i] + sm[max(i - 1, 0)]), 0.0)
        grid = c / 4 / math.sqrt(12)
        sds.append(math.sqrt(noise ** 2 + quant[k] ** 2 + grid ** 2))
    # each crest's span of samples within z sd of its value, kept apart from the other crest
    i1, i2 = int(idx[0]), int(idx[1])
    a1, b1 = _crest_span(sm, i1, pk[0] - z * sds[0], 0, i2)
    a2, b2 = _crest_span(sm, i2, pk[1] - z * sds[1], i1, n - 1)
    if b1 >= i2 or a2 <= i1 or b1 + 1 >= a2:
        reading.interval_failure = (f"its first two 'peaks' are not told apart by their doubt: between them "
                                    f"smooth(-y) stays within {z:.3g} standard deviations ({max(sds):.2g}) of a "
                                    f"crest (a noise bump taken for a peak), so the reading is not the oscillation's")
        return reading
    spans = ((float(t[a1] - dt / 2), float(t[b1] + dt / 2)), (float(t[a2] - dt / 2), float(t[b2] + dt / 2)))
    h = z * math.hypot(sds[0] / pk[0], sds[1] / pk[1])
    delta = (reading.delta - h, reading.delta + h)

    def zeta_of(d):
        return d / math.sqrt((2 * math.pi) ** 2 + d ** 2)

    fd = (1.0 / (spans[1][1] - spans[0][0]), 1.0 / (spans[1][0] - spans[0][1]))
    reading.intervals = ReadingIntervals(level, (zeta_of(delta[0]), zeta_of(delta[1])), fd, delta,
                                         tuple(sds), spans, noise, quant)
    return reading
