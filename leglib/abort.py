"""The step experiment's safety abort: leglib's own rule, one definition for both paths.

A position step is aborted (both axes IDLE, the response recorded as not completed:
unstable, never given a damping value) when the position error passes a bound or when the
oscillation about the target stops decaying. The rule runs in two places with the same
numbers: compiled into the twin's batch kernel (:mod:`leglib.twin`), which runs whole
steps on the virtual device, and in the polling loop that drives a real leg
(:mod:`leglib.experiments.step`). It lives below both.
"""

from __future__ import annotations

from numba import njit

from . import _numba_gc, _numba_inline  # noqa: F401  (before any kernel compiles)
from .kernelmath import select

# leglib's own abort codes (the twin's ABORT[b, 1]) and what a step's record says of each
ABORT_NONE, ABORT_POSITION_ERROR, ABORT_NONFINITE, ABORT_OSCILLATION = 0, 1, 2, 3
REASONS = {ABORT_NONE: None, ABORT_POSITION_ERROR: "position error past bound",
           ABORT_NONFINITE: "simulation left the valid configuration",
           ABORT_OSCILLATION: "oscillation not decaying (growing or sustained)"}
# the oscillation monitor's slots (see oscillation_update)
N_OSC = 6
OSC_HALF_CYCLES = 3  # consecutive non-decaying half-cycles that count as unstable
OSC_GROWTH = 1.1     # a half-cycle this much larger than the first overshoot: growing
OSC_DECAY = 0.95     # a half-cycle at least this fraction of the previous one is "not decaying"
                     # (a stable response decays by exp(-pi zeta / sqrt(1 - zeta^2)) per
                     # half-cycle: 0.95 flags zeta below about 0.016)


@njit(cache=True, inline="always")
def _oscillation_step(amp, prev, sgn0, count, halves, first, err, min_amp):
    """One sample of :func:`oscillation_update` on its six slots, passed and returned as
    scalars: (amp, prev, sgn0, count, halves, first, unstable). Written with selects, not
    branches (the kernel's loop over legs calls it and vectorizes)."""
    sgn = select(err > 0, 1.0, -1.0)
    sgn0 = select(sgn0 == 0.0, sgn, sgn0)
    flip = sgn != sgn0                      # a half-cycle ends
    halves_f = halves + 1.0
    first_f = select(halves_f == 2.0, amp, first)
    flagged = flip & (halves_f >= 3.0) & (amp > min_amp) & (amp > OSC_GROWTH * first_f)
    steady = (amp > min_amp) & (halves_f >= 2.0) & (prev > 0.0) & (amp >= OSC_DECAY * prev)
    counted = count + 1.0
    count_f = select(steady, counted, 0.0)
    halves = select(flip, halves_f, halves)
    first = select(flip, first_f, first)
    count = select(flip, count_f, count)
    prev = select(flip, amp, prev)
    amp = select(flip, 0.0, amp)
    sgn0 = select(flip, sgn, sgn0)
    e = abs(err)
    amp = select(e > amp, e, amp)
    return amp, prev, sgn0, count, halves, first, flagged | (count >= OSC_HALF_CYCLES)


@njit(cache=True)
def oscillation_update(st, err, min_amp):
    """Feed one position-error sample; True when the oscillation is growing or not decaying.

    ``st`` (N_OSC,) starts at zeros and holds: the largest |err| of the current half-cycle,
    the previous half-cycle's amplitude, the current sign, the count of consecutive
    non-decaying half-cycles, the number of half-cycles, and the first overshoot. A
    half-cycle ends when the error changes sign (the first one is the approach to the
    target, the second the first overshoot). Unstable when, with amplitudes above
    ``min_amp``, a later half-cycle exceeds OSC_GROWTH times the first overshoot (a damped
    response never grows past it), or OSC_HALF_CYCLES half-cycles in a row keep at least
    OSC_DECAY of the previous amplitude.
    """
    st[0], st[1], st[2], st[3], st[4], st[5], unstable = _oscillation_step(
        st[0], st[1], st[2], st[3], st[4], st[5], err, min_amp)
    return unstable
