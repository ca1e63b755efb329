"""The one classifier: is a measured response a second-order step, and what are its numbers?

Every consumer (the gain map, the thesis's readings, the robustness table, the panels,
:func:`leglib.design.tuning.tune`) classifies a step response here: ``ok`` with its
(zeta, fn), ``unstable`` (the experiment aborted it) or ``failed`` with the reason.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from ..errors import IdentificationError
from ..identify.fastfit import shape_numbers
from ..identify.step import identify_batch, second_order

STATUS_OK, STATUS_UNSTABLE, STATUS_FAILED, STATUS_MISSING = "ok", "unstable", "failed", "missing"
MIN_R2_MAP = 0.90  # a step the second-order fit explains less of is "failed", not a map point
MAX_OVERSHOOT = 1.0  # a second-order step overshoots less than 100 % of its step
MIN_POS_GAIN = 0.1  # (turn/s)/turn: below it there is no position control to identify
MIN_VEL_GAIN = 1e-4  # N*m/(turn/s): below it the cascade commands (almost) no torque


@dataclass
class PointResult:
    """One identified grid point."""

    gains: tuple
    status: str
    zeta: float = math.nan
    wn: float = math.nan
    r2: float = math.nan
    reason: str = ""
    fit: object = field(default=None, repr=False, compare=False)  # the SecondOrderFit, when one was made

    @property
    def fn(self) -> float:
        return self.wn / (2 * math.pi)


def step_shape_problem(t, y, fit, shape=None) -> str | None:
    """Why a fitted step response is not a second-order step, or None when it is one.

    Parameters
    ----------
    t : (N,) time [s]
    y : (N,) response (e.g. foot height [m])
    fit : :class:`leglib.identify.step.SecondOrderFit` of (t, y)
    shape : the response's :func:`leglib.identify.fastfit.shape_numbers` row when already computed
        (for many responses at once); computed here otherwise

    The tests: the fit explains at least :data:`MIN_R2_MAP` of the response (R^2); the
    response overshoots its final value by less than :data:`MAX_OVERSHOOT` of the step (no
    second-order step overshoots 100 %); an overdamped fit's fast pole
    wn (zeta + sqrt(zeta^2 - 1)) is slower than the sampling's Nyquist rate pi/dt (a faster
    pole cannot be seen in the data, so its zeta would be a number the data does not hold).
    """
    if not fit.r2 >= MIN_R2_MAP:
        return (f"not a second-order step: the fit explains R^2 = {fit.r2:.2f} of it "
                f"(the map needs {MIN_R2_MAP})")
    if shape is None:
        shape = shape_numbers([t], [y])[0]
    start, final, peak, spacing = (float(v) for v in shape)
    step = final - start
    if step != 0 and peak / abs(step) >= MAX_OVERSHOOT:
        return f"not a second-order step: it overshoots by {peak / abs(step):.0%} of its step"
    if fit.zeta > 1:
        fast = fit.wn * (fit.zeta + math.sqrt(fit.zeta ** 2 - 1))
        nyquist = math.pi / spacing
        if fast > nyquist:
            return (f"not a second-order step: the fit's fast pole ({fast:.3g} rad/s, zeta {fit.zeta:.3g}) "
                    f"lies beyond the sampling's Nyquist rate ({nyquist:.3g} rad/s)")
    return None


def identify_response(resp, method: str = "fit", fit=None, shape=None) -> PointResult:
    """Identify one :class:`leglib.experiments.step.StepResponse` (foot height ``y``).

    Returns a :class:`PointResult` with status "unstable" (the step was aborted), "failed"
    (no position control because pos_gain < :data:`MIN_POS_GAIN` or vel_gain <
    :data:`MIN_VEL_GAIN`; the data cannot be identified; or the response is not a
    second-order step, :func:`step_shape_problem`) or "ok" with zeta, wn [rad/s] and r2.
    A "failed" point never carries numbers; ``reason`` says why. ``fit``: the response's
    ``second_order`` result (or its IdentificationError) when already computed, e.g. by
    :func:`identify_many`'s batch; ``shape`` likewise its :func:`step_shape_problem` numbers.
    """
    g = tuple(float(x) for x in resp.gains)
    if not resp.completed:
        return PointResult(g, STATUS_UNSTABLE, reason=resp.abort_reason or "aborted")
    if not (g[0] >= MIN_POS_GAIN and g[1] >= MIN_VEL_GAIN):
        return PointResult(g, STATUS_FAILED, reason=(
            f"no position control to identify: pos_gain {g[0]:g} (needs >= {MIN_POS_GAIN:g}) or "
            f"vel_gain {g[1]:g} (needs >= {MIN_VEL_GAIN:g}) is (nearly) zero"))
    try:
        if isinstance(fit, IdentificationError):
            raise fit
        f = second_order(resp.t, resp.y, method=method) if fit is None else fit
    except IdentificationError as exc:
        return PointResult(g, STATUS_FAILED, reason=str(exc))
    problem = step_shape_problem(resp.t, resp.y, f, shape)
    if problem:
        return PointResult(g, STATUS_FAILED, r2=f.r2, reason=problem, fit=f)
    return PointResult(g, STATUS_OK, f.zeta, f.wn, f.r2, fit=f)


def identify_many(responses, method: str = "fit", workers: int | None = None) -> list[PointResult]:
    """Identify many :class:`leglib.experiments.step.StepResponse` objects.

    Parameters
    ----------
    responses : iterable of StepResponse (foot height ``y`` [m] against ``t`` [s])
    method : "fit" identifies every completed response in one compiled call
        (:func:`leglib.identify.step.identify_batch`, the same numbers as
        :func:`identify_response` one by one); other methods go one by one
    workers : accepted for compatibility and ignored: the compiled batch needs no
        process pool (400 responses take well under a second on one core)

    Returns
    -------
    list of PointResult, in the order of ``responses``
    """

    responses = list(responses)
    if method != "fit":
        return [identify_response(r, method) for r in responses]
    done = [r for r in responses if r.completed]
    fits, shapes = identify_batch([r.t for r in done], [r.y for r in done], shapes=True)
    fits, shapes = iter(fits), iter(shapes)
    # the same checks as one by one (gains, shape, fit quality), on the batch's numbers
    return [identify_response(r, method, fit=next(fits), shape=next(shapes)) if r.completed
            else identify_response(r, method) for r in responses]
