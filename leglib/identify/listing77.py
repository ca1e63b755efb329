"""The thesis's Listing 7.7 ("identifyParams") exactly, in its own measure.

MATLAB ``smooth`` (5-point moving average with shrinking end spans) of -y, ``findpeaks``,
delta = -ln(pks(1)/pks(2)) from the raw peak values (not from the final value),
zeta = delta / sqrt(4 pi^2 + delta^2), and the listing's "omega_n [Hz]" = 1/(t2 - t1), a
damped frequency (``.fd``). One peak gives zeta = 1, none zeta = 2, as the listing does,
flagged. This is the measure of the thesis's Fig. 6.12, its target (zeta 0.24, 5 Hz) and its
validation result (0.229, 5.06 Hz); it is strongly biased against the true zeta (see
:mod:`leglib.thesis`). Apply it to the listing's own signal,
:func:`leglib.model.kinematics.thesis_listing_height` of the zeroed angles in degrees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .. import checks, plots
from ..errors import IdentificationError

#: a second peak whose prominence (its height above the lowest point between the first two
#: peaks) is below this part of the step of smooth(-y) is ripple on the settled tail, not the
#: oscillation's second peak (on the twin over the thesis grid: 0.2 to 0.45 of the step where
#: the true zeta is below 0.3, under 0.007 where it is above 0.6)
RIPPLE = 0.01

# the most samples a response may have: a step of seconds at the ODrive's 8 kHz is below
# 100 000, and the fit of 1 000 000 takes tens of seconds; longer records are refused with
# the advice to decimate them (y[::k], t[::k]), never cut or decimated silently
MAX_SAMPLES = 250_000


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
    def usable(self) -> bool:
        """True when the listing's first two peaks are the oscillation's: at least two, and the
        second not ripple of the settled tail (prominence at least :data:`RIPPLE` of the
        step). Only such readings say what Listing 7.7 reads of a response."""
        return not self.flagged and not self.second_peak_prominence < RIPPLE

    @property
    def problem(self) -> str | None:
        """Why Listing 7.7 fails on this response, or None: fewer than two peaks (its
        constants), a second peak that is ripple of the settled tail, or more peaks than an
        oscillation at the reading's own frequency has in the record (findpeaks counts the
        quantized tail's ripple; the first two may still be the oscillation's, see
        :attr:`usable`)."""
        if self.flagged:
            return (f"fewer than two peaks ({self.n_peaks}): the listing returns its constant zeta = "
                    f"{self.zeta:g}, no reading")
        prom = self.second_peak_prominence
        if prom < RIPPLE:
            return (f"its second 'peak' is ripple of the settled tail (prominence {prom:.2%} of the step, under "
                    f"{RIPPLE:.0%}): the reading measures the encoder's quantization, not the oscillation")
        cycles = (self.record_end - self.peak_times[0]) * self.fd + 1
        if np.isfinite(cycles) and self.n_peaks > cycles + 1:
            return (f"findpeaks finds {self.n_peaks} peaks where an oscillation at the reading's own "
                    f"{self.fd:.2f} Hz has at most {int(cycles) + 1} in the record: it counts the quantized tail's "
                    f"ripple as peaks (its first two are the oscillation's here)")
        return None

    def plot(self, t, ax=None):
        """Listing 7.7's view of the step at times ``t``: smooth(-y) with the peaks it found
        (:func:`leglib.plots.plot_thesis_peaks`)."""
        return plots.plot_thesis_peaks(np.asarray(t, float), self, ax=ax)

    def _repr_markdown_(self) -> str:
        how = "flagged: the listing's constant (fewer than two peaks)" if self.flagged else f"{self.n_peaks} peaks"
        if self.problem and not self.flagged:
            how += f"; **the listing fails here**: {self.problem}"
        fd = f"{self.fd:.3f}" if self.n_peaks >= 2 else "–"
        return ("| ζ (Listing 7.7) | 1/(t2 − t1) [Hz] | |\n|---|---|---|\n"
                f"| {self.zeta:.4f} | {fd} | thesis measure, {how} |")

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
