"""The one classifier: is a measured response a second-order step, and what are its numbers?

Every consumer (the gain map, the thesis's readings, the robustness table, the panels,
:func:`leglib.design.tuning.tune`, :func:`leglib.design.validation.validate`) classifies a
step response here: ``ok`` with its (zeta, fn) and their 90 % intervals, ``unstable`` (the
experiment aborted it) or ``failed`` with the reason, never with numbers.

A response is a second-order step when

1. it **reaches its commanded final value** (:func:`reach_problem`): the foot ends within
   half the commanded step of the height the step commands;
2. the **second-order model explains it**: the least-squares fit succeeds
   (:func:`leglib.identify.step.second_order`) and explains at least :data:`MIN_R2_MAP` of it
   (R^2), and its residuals have no structure the model cannot have: the fit does not keep
   ringing where the response has come to rest (:func:`step_shape_problem`);
3. it has a step's **shape**: it overshoots by less than 100 % of its step, and an
   overdamped fit's fast pole lies within the sampling's Nyquist rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import ArgumentError, IdentificationError
from ..identify.fastfit import shape_numbers
from ..identify.step import add_intervals, fit_intervals, identify_batch, second_order
from ..model.drive import AxisMap
from ..model.dynamics import gravity_torque
from ..model.kinematics import foot_position
from ..units import dynamics_text

STATUS_OK, STATUS_UNSTABLE, STATUS_FAILED, STATUS_MISSING = "ok", "unstable", "failed", "missing"
MIN_R2_MAP = 0.90  # a step the second-order fit explains less of is "failed", not a map point
MAX_OVERSHOOT = 1.0  # a second-order step overshoots less than 100 % of its step
MIN_POS_GAIN = 0.1  # (turn/s)/turn: below it there is no position control to identify
MIN_VEL_GAIN = 1e-4  # N*m/(turn/s): below it the cascade commands (almost) no torque
#: a response that ends further from its commanded foot height than this part of the
#: commanded step does not reach it (see :func:`reach_problem` for why half)
REACH_FRACTION = 0.5
#: the part of the record (its end) where the fit must not ring while the response rests
TAIL = 0.4
#: the fit "rings" in the tail when it moves there more than this many times the response
#: itself, and by more than :data:`RING_FLOOR` of the step
RING_RATIO = 1.5
RING_FLOOR = 0.01


@dataclass
class PointResult:
    """One identified step response (a grid point of a map, a check of a design).

    ``gains``; ``status`` ("ok", "unstable", "failed"); ``zeta`` [-], ``wn`` [rad/s] and
    ``r2`` of the fit (NaN unless "ok"); ``intervals``: the fit's
    :class:`leglib.identify.step.FitIntervals` (90 % intervals of zeta, fn, fd) when "ok";
    ``reason``: why it is not "ok"; ``commanded`` and ``final``: the foot height [m] the
    step commands and the one it ends at (mean of its last fifth); ``fit``: the
    SecondOrderFit, when one was made (also for a failed point, for plotting it as rejected).
    """

    gains: tuple
    status: str
    zeta: float = math.nan
    wn: float = math.nan
    r2: float = math.nan
    reason: str = ""
    fit: object = field(default=None, repr=False, compare=False)
    intervals: object = field(default=None, repr=False, compare=False)
    commanded: float = math.nan
    final: float = math.nan

    @property
    def fn(self) -> float:
        return self.wn / (2 * math.pi)

    @property
    def fd(self) -> float:
        """Damped frequency [Hz] (NaN when zeta >= 1 or not "ok")."""
        return self.fn * math.sqrt(1 - self.zeta ** 2) if self.zeta < 1 else math.nan

    def interval(self, name: str) -> tuple:
        """The 90 % interval (low, high) of ``name`` ("zeta", "fn" [Hz], "fd" [Hz]); (NaN, NaN)
        when the point is not "ok"."""
        if self.intervals is None:
            return (math.nan, math.nan)
        return tuple(getattr(self.intervals, name))

    @property
    def zeta_interval(self) -> tuple:
        return self.interval("zeta")

    @property
    def fn_interval(self) -> tuple:
        return self.interval("fn")

    def text(self) -> str:
        """"zeta 0.371 [0.365, 0.378], fn 6.98 [6.90, 7.05] Hz" for an "ok" point (each to the
        digits its interval supports: :func:`leglib.units.interval_text`), else its status and
        reason."""
        if self.status != STATUS_OK:
            return f"{self.status}: {self.reason}"
        return dynamics_text(self.zeta, self.fn, self.zeta_interval, self.fn_interval)

    def to_dict(self) -> dict:
        """Plain numbers for a metrics file: gains, status, reason, and for an "ok" point
        zeta, fn, fd with their 90 % intervals and R^2."""
        out = {"gains": [float(g) for g in self.gains], "status": self.status}
        if self.status != STATUS_OK:
            return {**out, "reason": self.reason}
        return {**out, "zeta": self.zeta, "fn": self.fn, "fd": self.fd, "r2": self.r2,
                "zeta_interval": list(self.zeta_interval), "fn_interval": list(self.fn_interval),
                "fd_interval": list(self.interval("fd")), "level": self.intervals.level}


def commanded_height(resp, leg) -> float:
    """Foot height [m] the commanded step of ``resp`` asks for: the joints' start plus the
    joint step of its motor step ``resp.step`` [turn] (exact five-bar of ``leg``)."""
    dq1, dq2 = AxisMap.from_leg(leg).motor_step_to_joint_step(resp.step)
    _, y = foot_position(leg, resp.q1[0] + dq1, resp.q2[0] + dq2)
    return float(y)


def _count_height(leg, q1, q2) -> float:
    """Foot height change [m] of one encoder count on each joint at (q1, q2), bounded by twice
    the larger of the two joints' (each joint reads to within one count)."""
    dq = 2 * math.pi / (leg.encoder_cpr * leg.gear_ratio)
    _, y0 = foot_position(leg, q1, q2)
    one = max(abs(foot_position(leg, q1 + dq, q2)[1] - y0), abs(foot_position(leg, q1, q2 + dq)[1] - y0))
    return float(2 * one)


def _gravity_share(resp, leg) -> tuple[float, float]:
    """(gravity torque [N*m] at the commanded pose, the larger of the two joints; its share of
    what a proportional loop with ``resp``'s gains exerts over the whole joint step, with
    static stiffness k = gear^2 pos_gain vel_gain / 2 pi [N*m/rad] at each joint): what the
    reason of a failed reach quotes, not what decides it."""
    dq1, dq2 = AxisMap.from_leg(leg).motor_step_to_joint_step(resp.step)
    g = np.abs(np.asarray(gravity_torque(leg, resp.q1[0] + dq1, resp.q2[0] + dq2), float))
    k = leg.gear_ratio ** 2 * resp.gains[0] * resp.gains[1] / (2 * math.pi)
    full = k * abs(dq1)
    return float(g.max()), float(g.max() / full) if full > 0 else math.inf


def reach_problem(resp, leg, final: float | None = None) -> str | None:
    """Why a step response does not reach its commanded final value, or None when it does.

    The response's final value (the mean of its last fifth, as
    :func:`leglib.identify.fastfit.shape_numbers`) must lie within

        band = :data:`REACH_FRACTION` x |commanded step| + one encoder count on each joint, at the foot

    of the foot height the step commands (:func:`commanded_height`).

    Why this band. The cascade's position loop is proportional: at rest it holds a load
    torque tau with a static error tau / k, k = gear^2 pos_gain vel_gain / 2 pi [N*m/rad] at
    each joint (the velocity integrator removes it only over seconds at the gains swept).
    The load is gravity at the commanded pose (about 0.10 N*m per joint on the thesis's
    leg after Listing 7.4's 48-degree step, more with a payload on the foot) and, around the
    loop's equilibrium, Coulomb friction, whose dead band +-C / k is where the leg may stop;
    the encoder adds its resolution (one count, 2 pi / (cpr gear) of joint angle: 0.03 mm
    of foot height). On the twin over the thesis grid the final values of the second-order
    steps lie 0.1 to 28 % of the step short of the command, and the gravity term alone
    predicts each to within 1 mm where the integrator is small; the friction dead band adds
    at most 3 % there (C = 0.01 N*m). A payload of 0.3 kg doubles the gravity term: a soft
    loop for a 4 Hz target on such a leg ends 36 to 50 % short and is still a second-order
    step of a smaller amplitude. Where the loop is so soft (vel_gain 0.002) that gravity and
    the dead band take most of the step, the leg stops where static friction catches it,
    and the fit of such a response describes a partial, stuck motion rather than the
    commanded step (notebook 04's panel at (50, 0.002, 0.001): 28.8 mm, 59 % short; the
    thesis grid's vel_gain 0.002 points 45 to 75 %). Half the step is the line: a response
    that covers less than half of its commanded step is governed by the loads on the leg
    more than by the gains, and its (zeta, fn) would describe the loads.

    ``final`` [m]: the final value when already computed (e.g. by :func:`shape_numbers`).
    """
    commanded = commanded_height(resp, leg)
    y = np.asarray(resp.y, float)
    if final is None:
        final = float(np.mean(y[-max(5, y.size // 5):]))
    start = float(np.mean(y[:max(3, y.size // 50)]))
    step = commanded - start
    band = REACH_FRACTION * abs(step) + _count_height(leg, resp.q1[0], resp.q2[0])
    if not (math.isfinite(commanded) and math.isfinite(band)):
        return ("its commanded final value cannot be computed: the leg's five-bar does not close at the "
                "commanded joint angles (is the response from this leg?)")
    miss = commanded - final
    if abs(miss) <= band:
        return None
    short = "short of" if miss * step > 0 else "past"
    tau, share = _gravity_share(resp, leg)
    return (f"does not reach its commanded final value: it ends {abs(miss) * 1e3:.1f} mm "
            f"({abs(miss / step):.0%} of the step) {short} the commanded {commanded * 1e3:.1f} mm (band: "
            f"{band * 1e3:.1f} mm, half the step); gravity on the nominal leg there needs {tau:.2f} N m per joint, "
            f"{share:.0%} of what the position loop exerts over the whole step at these gains, and friction "
            f"holds the leg where it stops")


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
    pole cannot be seen in the data, so its zeta would be a number the data does not hold);
    and the residuals' structure: over the last :data:`TAIL` of the record the fit may not
    move more than :data:`RING_RATIO` times the response itself (and more than
    :data:`RING_FLOOR` of the step). A second-order step decays on one time scale, so a fit
    that still rings where the response has come to rest describes a response that stopped
    early -- static friction caught the leg -- not a second-order one (on the twin over the
    thesis grid the fit moves at most half as much as the response there; at notebook 04's
    stalled step (50, 0.002, 0.001) 2.8 times as much).
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
    t = np.asarray(t, float)
    y = np.asarray(y, float)
    tail = slice(int((1 - TAIL) * y.size), y.size)
    moved_fit = float(np.ptp(fit.response(t - t[0])[tail]))
    moved = float(np.ptp(y[tail]))
    if step != 0 and moved_fit > RING_RATIO * moved and moved_fit > RING_FLOOR * abs(step):
        return (f"not a second-order step: the fit still rings over the last {TAIL:.0%} of the record "
                f"({moved_fit * 1e3:.1f} mm peak to peak) where the response has come to rest "
                f"({moved * 1e3:.1f} mm): it stopped early, held by friction")
    return None


def _check_leg(leg, who: str):
    if leg is None or not hasattr(leg, "gear_ratio"):
        raise ArgumentError(f"{who}: leg must be the leg's LegParams (its kinematics give the foot height the "
                            f"step commands), got {leg!r}")


def identify_response(resp, leg, method: str = "fit", fit=None, shape=None) -> PointResult:
    """Identify one :class:`leglib.experiments.step.StepResponse` (foot height ``y``) of the
    leg ``leg`` (:class:`leglib.params.LegParams`, whose kinematics give the commanded foot
    height).

    Returns a :class:`PointResult` with status "unstable" (the step was aborted), "failed"
    (no position control because pos_gain < :data:`MIN_POS_GAIN` or vel_gain <
    :data:`MIN_VEL_GAIN`; the response does not reach its commanded final value,
    :func:`reach_problem`; the data cannot be identified; or the response is not a
    second-order step, :func:`step_shape_problem`) or "ok" with zeta, wn [rad/s], r2 and
    the 90 % intervals. A "failed" point never carries numbers; ``reason`` says why.
    ``fit``: the response's ``second_order`` result (or its IdentificationError) when
    already computed, e.g. by :func:`identify_many`'s batch; ``shape`` likewise its
    :func:`step_shape_problem` numbers.
    """
    _check_leg(leg, "identify_response")
    point = _classify(resp, leg, method, fit, shape)
    if point.status == STATUS_OK and point.fit.intervals is None:
        fit_intervals(point.fit, resp.t, resp.y)
    if point.status == STATUS_OK:
        point.intervals = point.fit.intervals
    return point


def _classify(resp, leg, method, fit, shape) -> PointResult:
    """:func:`identify_response` without the intervals (which :func:`identify_many` computes
    for all "ok" points at once)."""
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
        f, error = None, exc
    else:
        error = None
    y = np.asarray(resp.y, float)
    usable = y.ndim == 1 and y.size >= 2 and np.shape(resp.t) == y.shape and bool(np.all(np.isfinite(y)))
    if shape is None and usable:
        shape = shape_numbers([np.asarray(resp.t, float)], [y])[0]   # the batch's numbers, one by one
    commanded = commanded_height(resp, leg)
    final = float(shape[1]) if usable else math.nan
    common = {"fit": f, "commanded": commanded, "final": final}
    if usable:
        miss = reach_problem(resp, leg, final)
        if miss:
            return PointResult(g, STATUS_FAILED, r2=f.r2 if f is not None else math.nan, reason=miss, **common)
    if error is not None:
        return PointResult(g, STATUS_FAILED, reason=str(error), **common)
    problem = step_shape_problem(resp.t, resp.y, f, shape)
    if problem:
        return PointResult(g, STATUS_FAILED, r2=f.r2, reason=problem, **common)
    return PointResult(g, STATUS_OK, f.zeta, f.wn, f.r2, **common)


def identify_many(responses, leg, method: str = "fit", workers: int | None = None) -> list[PointResult]:
    """Identify many :class:`leglib.experiments.step.StepResponse` objects of the leg ``leg``.

    Parameters
    ----------
    responses : iterable of StepResponse (foot height ``y`` [m] against ``t`` [s])
    leg : the leg's :class:`leglib.params.LegParams` (the commanded foot height)
    method : "fit" identifies every completed response in one compiled call
        (:func:`leglib.identify.step.identify_batch`, the same numbers as
        :func:`identify_response` one by one), and the intervals of every "ok" one in one
        more; other methods go one by one
    workers : accepted for compatibility and ignored: the compiled batch needs no
        process pool (400 responses take well under a second on one core)

    Returns
    -------
    list of PointResult, in the order of ``responses``
    """
    _check_leg(leg, "identify_many")
    responses = list(responses)
    if method != "fit":
        return [identify_response(r, leg, method) for r in responses]
    done = [r for r in responses if r.completed]
    fits, shapes = identify_batch([r.t for r in done], [r.y for r in done], shapes=True)
    fits, shapes = iter(fits), iter(shapes)
    # the same checks as one by one (gains, reach, shape, fit quality), on the batch's numbers
    points = [_classify(r, leg, method, next(fits), next(shapes)) if r.completed
              else _classify(r, leg, method, None, None) for r in responses]
    ok = [(p, r) for p, r in zip(points, responses) if p.status == STATUS_OK]
    add_intervals([p.fit for p, _ in ok], [r.t for _, r in ok], [r.y for _, r in ok])
    for p, _ in ok:
        p.intervals = p.fit.intervals
    return points
