"""Validation (thesis 6.5): a method chooses gains for target (zeta, fn); a step at those
gains on the leg, identified; the relative errors. One routine for every consumer (notebook
05, :mod:`leglib.evaluation.robustness`, ``python -m leglib robustness``), with one convention:

- a target the method has no answer for (outside a gain map's achievable region) is
  *outside*: it has no error and is counted apart, its nearest achievable point noted;
- a step that is not a second-order step (the one classifier,
  :func:`leglib.design.points.identify_response`, says ``failed`` or ``unstable``) is *not
  identifiable*: its error is infinite, so a method's worst error says so, and it is
  counted; it is never dropped, never given numbers;
- an identified check's error is an interval: its 90 % intervals of zeta and fn relative to
  the target (:attr:`TargetResult.error_interval`). A target counts as reached within a
  tolerance only when both intervals lie inside it (:func:`verdict`), and when an interval
  is wider than the tolerance itself (the response's model error is larger than the
  tolerance) the verdict says so instead of calling it reached or missed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .. import plots
from ..device.session import as_device
from ..errors import OutsideRegionError
from ..experiments.step import step_response
from ..units import dynamics_text, percent_interval_text
from .points import STATUS_OK, identify_response


def relative_intervals(intervals, reference) -> tuple[tuple, tuple]:
    """90 % intervals ((zeta low, high), (fn low, high) [Hz]) of a measurement relative to
    ``reference`` (zeta, fn [Hz]): each bound b as b / r - 1, the interval of the relative
    error measured / reference - 1 when the reference is taken as exact (a target, or the
    same response read by an ideal sensor). NaN bounds stay NaN."""
    return tuple(tuple(float(b) / float(r) - 1.0 for b in iv) for iv, r in zip(intervals, reference))


def abs_interval(interval) -> tuple[float, float]:
    """The interval of |x| for x in ``interval`` (low, high): 0 at the bottom when it holds
    0. NaN bounds give (NaN, NaN)."""
    lo, hi = (float(b) for b in interval)
    if math.isnan(lo) or math.isnan(hi):
        return (math.nan, math.nan)
    return (0.0 if lo <= 0.0 <= hi else min(abs(lo), abs(hi)), max(abs(lo), abs(hi)))


def error_statistics(errors, intervals) -> dict:
    """Median and worst |relative error| of items with their intervals.

    Parameters
    ----------
    errors : sequence of relative errors [-] (NaN: no error, e.g. a target outside a
        method's answers, left out; inf: not identifiable, counted as infinite)
    intervals : sequence of (low, high), each error's 90 % interval ((NaN, NaN) where it has
        none; an infinite error's is (inf, inf))

    Returns
    -------
    dict: ``median``, ``worst`` (NaN without items) and ``median_interval``,
    ``worst_interval``: the range of each statistic that the items' intervals allow (the
    median and the maximum are monotone in every item, so they are the statistic of the
    intervals' lower and upper bounds of |error|). Each item's interval is a 90 % one; the
    statistic's holds its true value whenever every item's does. None when an item with a
    finite error has no interval.
    """
    pairs = [(abs(float(e)), abs_interval((math.inf, math.inf) if math.isinf(float(e)) else iv))
             for e, iv in zip(errors, intervals) if not math.isnan(float(e))]
    if not pairs:
        return {"median": math.nan, "worst": math.nan, "median_interval": None, "worst_interval": None}
    e = np.array([x for x, _ in pairs])
    b = np.array([iv for _, iv in pairs], float)
    bounded = bool(np.all(np.isfinite(b) | np.isinf(b)))   # no NaN bound
    stat = (lambda f: (float(f(b[:, 0])), float(f(b[:, 1]))) if bounded else None)
    return {"median": float(np.median(e)), "worst": float(np.max(e)), "median_interval": stat(np.median),
            "worst_interval": stat(np.max)}


def verdict(zeta_interval, fn_interval, target, tolerance: float) -> tuple[bool, str]:
    """Whether measured 90 % intervals of (zeta, fn [Hz]) put ``target`` (zeta, fn) reached
    within ``tolerance`` (relative): True only when both intervals lie inside
    target x (1 +- tolerance). Returns (reached, why) with why a sentence: reached; the
    interval that reaches beyond the tolerance; or, when an interval's half-width is larger
    than the tolerance itself, that the response's uncertainty (its model error included)
    is larger than the tolerance, so reaching it cannot be told."""
    wide, beyond = [], []
    for name, (lo, hi), t in (("zeta", zeta_interval, target[0]), ("fn", fn_interval, target[1])):
        if not (math.isfinite(lo) and math.isfinite(hi)):
            return False, f"{name} has no interval (the check is not a second-order step)"
        if (hi - lo) / 2 > tolerance * t:
            wide.append(f"{name} to +-{(hi - lo) / 2 / t:.1%} of the target")
        elif lo < t * (1 - tolerance) or hi > t * (1 + tolerance):
            beyond.append(f"{name} [{lo:.3g}, {hi:.3g}] reaches beyond +-{tolerance:.1%} of {t:.3g}")
    if wide:
        return False, (f"the 90 % intervals hold {' and '.join(wide)}, more than the tolerance "
                       f"(+-{tolerance:.1%}): the model error of this response is larger than the tolerance, so "
                       f"whether the target is reached cannot be told")
    if beyond:
        return False, f"not reached: {'; '.join(beyond)} (90 % interval)"
    return True, f"reached: both 90 % intervals lie within +-{tolerance:.1%} of the target"


def nearest_text(pair, intervals) -> str:
    """A method's nearest achievable (zeta, fn [Hz]) with its 90 % intervals, or saying it
    has none."""
    if intervals is None:
        return f"ζ {pair[0]:.3f}, fn {pair[1]:.2f} Hz, no interval"
    return dynamics_text(pair[0], pair[1], *intervals, zeta_name="ζ")


@dataclass
class TargetResult:
    """One target of a :class:`Validation`.

    Attributes
    ----------
    target : (zeta, fn [Hz])
    gains : (pos_gain, vel_gain, vel_integrator_gain) the method chose; None when outside
    predicted : the method's own (zeta, fn [Hz]) for its gains, or None
    measured : :class:`leglib.design.points.PointResult` of the check step, or None
    experiments : steps this target cost (the method's own plus the check)
    outside : the method had no answer (``nearest``: the nearest achievable (zeta, fn),
        ``nearest_intervals`` its 90 % intervals ((zeta low, high), (fn low, high)) where the
        method gives them)
    note : what the method said
    """

    target: tuple
    gains: tuple | None = None
    predicted: tuple | None = None
    measured: object = None
    experiments: int = 0
    outside: bool = False
    nearest: tuple | None = None
    note: str = ""
    nearest_intervals: tuple | None = None

    @property
    def identified(self) -> bool:
        return self.measured is not None and self.measured.status == STATUS_OK

    @property
    def error(self) -> tuple[float, float]:
        """Relative errors (zeta, fn) of the check against the target: NaN outside the
        method's answers, infinite when the check is not a second-order step."""
        if self.outside or self.measured is None:
            return (math.nan, math.nan)
        if not self.identified:
            return (math.inf, math.inf)
        return (self.measured.zeta / self.target[0] - 1.0, self.measured.fn / self.target[1] - 1.0)

    @property
    def error_interval(self) -> tuple[tuple, tuple]:
        """The 90 % intervals of the relative errors ((zeta low, high), (fn low, high)): the
        check's intervals relative to the target (NaN where :attr:`error` is not finite)."""
        if not self.identified:
            nan = (math.nan, math.nan)
            return (nan, nan)
        return relative_intervals((self.measured.zeta_interval, self.measured.fn_interval), self.target)

    @property
    def worst_bound(self) -> float:
        """The largest |relative error| the intervals allow (inf when not identifiable, NaN
        outside)."""
        if self.outside or self.measured is None:
            return math.nan
        if not self.identified:
            return math.inf
        return float(max(abs(b) for iv in self.error_interval for b in iv))

    def reached(self, tolerance: float) -> tuple[bool, str]:
        """:func:`verdict` of the check against the target within ``tolerance``."""
        if not self.identified:
            return False, "the check is not a second-order step" if self.measured is not None else "no check"
        return verdict(self.measured.zeta_interval, self.measured.fn_interval, self.target, tolerance)


@dataclass
class Validation:
    """A method's validation over targets: :func:`validate`'s result.

    Attributes
    ----------
    method : str
    rows : list of :class:`TargetResult`, one per target
    setup_experiments : steps spent before any target (a sweep for the map, the fitting steps
        of a model)
    tolerance : the relative tolerance a target counts as reached within (:func:`verdict`,
        the check's 90 % intervals inside it), or None: no verdicts
    """

    method: str
    rows: list = field(default_factory=list)
    setup_experiments: int = 0
    tolerance: float | None = None

    @property
    def errors(self) -> np.ndarray:
        """(K, 2) relative errors (zeta, fn) of the targets the method answered (inf for a
        check that is not a second-order step)."""
        e = [r.error for r in self.rows if not r.outside]
        return np.array(e, dtype=float).reshape(-1, 2)

    @property
    def experiments(self) -> int:
        return self.setup_experiments + sum(r.experiments for r in self.rows)

    def summary(self) -> dict:
        """Median and worst absolute relative errors (of zeta, of fn, of both), the largest
        error any check's 90 % interval allows (``worst_bound``), the ranges of the median and
        worst error of both that the checks' intervals allow (``median_interval``,
        ``worst_interval``: :func:`error_statistics`), each answered target's error intervals
        (``error_intervals``, in the rows' order), the targets answered, outside and not
        identifiable, the experiments."""
        e = np.abs(self.errors)
        stat = (lambda f, x: float(f(x)) if x.size else math.nan)
        answered = [r for r in self.rows if not r.outside]
        bounds = np.array([r.worst_bound for r in answered], float)
        both = error_statistics([x for r in answered for x in r.error],
                                [iv for r in answered for iv in r.error_interval])
        out = {"median_zeta": stat(np.median, e[:, 0]), "median_fn": stat(np.median, e[:, 1]),
               "worst_zeta": stat(np.max, e[:, 0]), "worst_fn": stat(np.max, e[:, 1]),
               "median": stat(np.median, e), "worst": stat(np.max, e), "worst_bound": stat(np.max, bounds),
               "median_interval": both["median_interval"], "worst_interval": both["worst_interval"],
               "error_intervals": [[list(iv) for iv in r.error_interval] for r in answered],
               "targets": len(e), "outside_region": sum(r.outside for r in self.rows),
               "unidentified": sum((not r.outside) and not r.identified for r in self.rows),
               "experiments": self.experiments}
        if self.tolerance is not None:
            verdicts = [r.reached(self.tolerance) for r in answered]
            out.update(tolerance=self.tolerance, reached=sum(ok for ok, _ in verdicts),
                       undecided=sum("cannot be told" in why for _, why in verdicts))
        return out

    def markdown(self) -> str:
        """The table of targets and the summary, as Markdown."""
        tol = self.tolerance
        lines = [f"**{self.method}**", "", "| # | target (ζ, fn [Hz]) | predicted | measured [90 % interval] | "
                 "error ζ, fn [90 % interval] | steps |" + (f" within ±{tol:.0%}? |" if tol is not None else ""),
                 "|---|---|---|---|---|---|" + ("---|" if tol is not None else "")]
        for k, r in enumerate(self.rows, 1):
            tgt = f"({r.target[0]:.3f}, {r.target[1]:.2f})"
            pred = f"({r.predicted[0]:.3f}, {r.predicted[1]:.2f})" if r.predicted else "–"
            if r.outside:
                near = f" (nearest {nearest_text(r.nearest, r.nearest_intervals)})" if r.nearest else ""
                lines.append(f"| {k} | {tgt} | outside the region{near} | – | – | {r.experiments} |"
                             + (" – |" if tol is not None else ""))
                continue
            if r.identified:
                ez, ef = r.error_interval
                meas = dynamics_text(r.measured.zeta, r.measured.fn, r.measured.zeta_interval,
                                     r.measured.fn_interval, zeta_name="ζ")
                err = f"{percent_interval_text(r.error[0], ez)}, {percent_interval_text(r.error[1], ef)}"
            else:
                meas = f"not identifiable: {r.measured.reason or r.measured.status}"
                err = "∞"
            cell = ""
            if tol is not None:
                ok, why = r.reached(tol)
                cell = " yes |" if ok else (" cannot be told (intervals wider) |" if "cannot be told" in why else " no |")
            lines.append(f"| {k} | {tgt} | {pred} | {meas} | {err} | {r.experiments} |{cell}")
        s = self.summary()
        lines += ["", f"Median error {s['median']:.1%}, worst {s['worst']:.1%} (their 90 % intervals allow up to "
                      f"{s['worst_bound']:.1%}) over {s['targets']} targets "
                      f"({s['unidentified']} not identifiable, {s['outside_region']} outside the region); "
                      f"{s['experiments']} experiments."
                      + (f" {s['reached']} reached within ±{tol:.0%} by their 90 % intervals, {s['undecided']} with "
                         f"intervals wider than that." if tol is not None else "")]
        return "\n".join(lines)

    def _repr_markdown_(self) -> str:
        return self.markdown()

    def plot(self, ax=None):
        """The errors per target (zeta and fn), a failed check marked (:func:`leglib.plots.plot_validation`)."""
        return plots.plot_validation(self, ax=ax)


def validate(odrv, targets, gains_of, method: str, setup_experiments: int = 0, step_kwargs=None,
             tolerance: float | None = None) -> Validation:
    """Validate a method on the leg: for each target the method's gains, one step, its
    classification.

    Parameters
    ----------
    odrv : Device or an ODrive object (calibrated)
    targets : sequence of (zeta, fn [Hz])
    gains_of : callable
        ``gains_of((zeta, fn)) -> (gains, experiments, predicted, note)``: the method's gains
        for a target, the steps it spent on them (0 for a lookup), its own prediction
        ((zeta, fn) or None) and a note; it raises :class:`leglib.errors.OutsideRegionError`
        when it has no answer.
    method : str
        The method's name, for the table.
    setup_experiments : int
        Steps the method spent before any target.
    step_kwargs : dict, optional
        Passed to :func:`leglib.experiments.step.step_response` for the check steps.
    tolerance : float, optional
        Relative tolerance within which a target counts as reached (only when its check's
        90 % intervals lie inside it, :func:`verdict`); None gives errors without verdicts.

    Returns
    -------
    Validation
    """
    result = Validation(method, setup_experiments=int(setup_experiments), tolerance=tolerance)
    dev = as_device(odrv)
    for tgt in targets:
        tgt = (float(tgt[0]), float(tgt[1]))
        try:
            gains, spent, predicted, note = gains_of(tgt)
        except OutsideRegionError as exc:
            near = exc.nearest
            iv = (tuple(getattr(near, "zeta_interval", (math.nan, math.nan))),
                  tuple(getattr(near, "fn_interval", (math.nan, math.nan))))
            result.rows.append(TargetResult(tgt, outside=True, nearest=(near.zeta, near.fn), note="outside the region",
                                            nearest_intervals=None if any(math.isnan(b) for x in iv for b in x)
                                            else iv))
            continue
        point = identify_response(step_response(dev, *gains, **(step_kwargs or {})), dev.leg)
        result.rows.append(TargetResult(tgt, tuple(float(g) for g in gains),
                                        None if predicted is None else tuple(map(float, predicted)), point,
                                        int(spent) + 1, note=note))
    return result
