"""The thesis's own numbers, read the way the thesis computed them, and its errata checked.

Two measures of a step response appear in this project; every number says which it is in:

- **the thesis's reading** (Listing 7.7, ``identify.second_order(..., method="thesis")``):
  zeta from delta = -ln(pks(1)/pks(2)) of the raw peak values of smooth(-y), with
  y = 0.16 cos(angle1) + 0.16 cos(angle2) of the zeroed angles in degrees, and
  "omega_n [Hz]" = 1/(t2 - t1), which is the damped frequency fd. The thesis's Fig. 6.12,
  its target (zeta 0.24, 5 Hz), Listing 7.8's ``desiredPoint = [0.23, 5]`` and its
  validation result (0.229, 5.06 Hz) are all in this measure.
- **the true second-order parameters** (``identify.second_order``'s least-squares fit):
  zeta, wn [rad/s], fn = wn / 2 pi [Hz], fd = fn sqrt(1 - zeta^2) [Hz].

This module holds the thesis's published constants (Table 6.1, Listings 7.1, 7.4, 7.8,
eq. 5.11), the conversions between the two measures, and the errata computations that
notebooks 01, 04 and 05 show.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from . import model as M
from .design.points import identify_many
from .design.tuning import AxisModel
from .errors import IdentificationError
from .experiments.step import StepResponse
from .files.sweepdir import read_measurements
from .identify.fastfit import model
from .identify.listing77 import ThesisReading, add_intervals
from .identify.step import second_order
from .model.cascade import motor_side_inertia
from .params import SHIPPED_DIR, LegParams, load_leg, load_odrive_config

# ---------------------------------------------------------------------------------------
# the thesis's targets and results, in the thesis's measure (Listing 7.7)
# ---------------------------------------------------------------------------------------

#: Thesis 6.5: "zeta = 0.24 and omega_n = 5" -- Listing 7.7's zeta and 1/(t2 - t1) [Hz].
TEXT_TARGET = (0.24, 5.0)
#: Listing 7.8, line 57: ``desiredPoint = [0.23, 5]`` (the text says 0.24).
LISTING_7_8_TARGET = (0.23, 5.0)
#: Thesis 6.5: the validated response, "zeta = 0.229, omega_n = 5.06", in Listing 7.7's measure.
THESIS_RESULT = (0.229, 5.06)
#: Fig. 6.9's gains (pos_gain, vel_gain, vel_integrator_gain), thesis 6.4.
FIG_6_9_GAINS = (50.0, 0.046, 0.001)
#: Listing 7.4's step: 0.4 motor turns through the 1:3 belt = 48 deg on each joint.
STEP_DEG = 0.4 * 360.0 / 3.0


def listing_7_4_axes() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Listing 7.4's gain axes: pos_gain linspace(20, 50, 4), vel_gain linspace(0.002, 0.18, 10),
    vel_integrator_gain linspace(0.002, 0.08, 10)."""
    return np.linspace(20, 50, 4), np.linspace(0.002, 0.18, 10), np.linspace(0.002, 0.08, 10)


def gains_on_listing_grid(gains, rel: float = 1e-6) -> dict:
    """Whether each gain of ``gains`` lies on Listing 7.4's grid.

    Returns
    -------
    dict with, per name ("pos_gain", "vel_gain", "vel_integrator_gain"): ``on_grid`` (bool),
    ``nearest`` (the grid value nearest to it) and ``inside`` (within the axis's range).
    """
    out = {}
    for name, g, axis in zip(("pos_gain", "vel_gain", "vel_integrator_gain"), gains, listing_7_4_axes()):
        k = int(np.argmin(np.abs(axis - g)))
        out[name] = {"value": float(g), "on_grid": bool(abs(axis[k] - g) <= rel * abs(axis[k])),
                     "nearest": float(axis[k]), "inside": bool(axis[0] <= g <= axis[-1])}
    return out


# ---------------------------------------------------------------------------------------
# Listing 7.7 on measured and on ideal responses
# ---------------------------------------------------------------------------------------

def listing_signal(q1, q2) -> np.ndarray:
    """Listing 7.7's y [m] of absolute joint angles q1, q2 [rad] (zeroed at the first sample,
    in degrees, as Listing 7.4 records them)."""
    return M.thesis_listing_height(M.zeroed_degrees(q1), M.zeroed_degrees(q2))


def equivalent_angle_deg(peak_value: float, length: float = M.LISTING_LENGTH) -> float:
    """The joint angle change [deg] that, on both joints alike, gives Listing 7.7's
    smooth(-y) the value ``peak_value`` [m]: arccos(-peak / (2 * 0.16))."""
    return float(np.degrees(np.arccos(np.clip(-peak_value / (2 * length), -1.0, 1.0))))


def first_peak_needed(thesis_zeta: float, second_peak_deg: float = STEP_DEG) -> dict:
    """What Listing 7.7's zeta demands of a response: pks(1)/pks(2) = exp(-delta), with
    delta = 2 pi zeta / sqrt(1 - zeta^2) (eq. 6.7 inverted).

    Returns
    -------
    dict: ``delta``, ``peak_ratio`` = pks(1)/pks(2), ``first_peak_deg``: the joint swing
    at the first peak [deg] when the second peak sits at ``second_peak_deg`` (default the
    step's 48 deg, i.e. settled), and ``overshoot`` of that first peak relative to 48 deg
    """
    if not 0 < thesis_zeta < 1:
        raise ValueError(f"thesis_zeta must lie in (0, 1), got {thesis_zeta}")
    delta = 2 * math.pi * thesis_zeta / math.sqrt(1 - thesis_zeta ** 2)
    ratio = math.exp(-delta)
    a1 = math.degrees(math.acos(ratio * math.cos(math.radians(second_peak_deg))))
    return {"delta": delta, "peak_ratio": ratio, "first_peak_deg": a1, "overshoot": a1 / STEP_DEG - 1}


def angle_count(a_deg) -> float:
    """The encoder count [deg] of a recorded angle: the largest step of which every change
    between its samples is a whole multiple (the record is quantized: the twin's counts, the
    thesis's CSV of a 4000-count encoder through the 1:3 belt, 0.03 deg), tried as the
    smallest change over 1 ... 5; 0 when the changes share no such step (a record without
    quantization)."""
    d = np.abs(np.diff(np.asarray(a_deg, float)))
    d = d[d > 1e-9]
    if d.size == 0:
        return 0.0
    for k in range(1, 6):
        q = float(d.min()) / k
        ratio = d / q
        if bool(np.all(np.abs(ratio - np.round(ratio)) < 0.01)):
            return q
    return 0.0


def read_angles(t, angle1_deg, angle2_deg, length: float = M.LISTING_LENGTH) -> ThesisReading:
    """Listing 7.7 on the thesis's own columns: joint-angle changes from the first sample
    [deg] (Listing 7.4's CSV), with the intervals of a usable reading.

    The intervals (:class:`leglib.identify.listing77.ReadingIntervals`) take the record's
    noise and, for a quantized record, the encoder's rounding at each crest: one count
    (:func:`angle_count`) of joint j changes y by length |sin(angle_j)| count [rad] there,
    whose rounding error has a standard deviation of that / sqrt(12); both joints in
    quadrature.
    """
    a1, a2 = np.asarray(angle1_deg, float), np.asarray(angle2_deg, float)
    y = M.thesis_listing_height(a1, a2, length)
    reading = second_order(t, y, method="thesis")
    if reading.usable:
        counts = (math.radians(angle_count(a1)), math.radians(angle_count(a2)))
        quant = tuple(math.hypot(*(length * abs(math.sin(math.radians(a[i]))) * c for a, c in zip((a1, a2), counts)))
                      / math.sqrt(12) for i in reading.peak_index[:2])
        add_intervals(reading, t, y, quantization=quant)
    return reading


def read_step(resp) -> ThesisReading:
    """Listing 7.7's reading of a :class:`leglib.experiments.step.StepResponse` (thesis
    measure), with its intervals (:func:`read_angles`)."""
    return read_angles(resp.t, M.zeroed_degrees(resp.q1), M.zeroed_degrees(resp.q2))


def ideal_step(zeta: float, fd: float, step_deg: float = STEP_DEG, duration: float = 1.5,
               dt: float = 0.002) -> tuple[np.ndarray, np.ndarray]:
    """An ideal second-order step of both joints by +-``step_deg`` [deg] with true damping
    ``zeta`` and damped frequency ``fd`` [Hz], as Listing 7.7 would see it.

    Returns
    -------
    t : (N,) [s]; y : (N,) Listing 7.7's signal [m]
    """
    if not (0 < zeta < 1 and fd > 0):
        raise ValueError(f"need 0 < zeta < 1 and fd > 0, got zeta={zeta}, fd={fd}")
    t = np.arange(int(round(duration / dt))) * dt
    wn = 2 * math.pi * fd / math.sqrt(1 - zeta ** 2)
    a = model(t, zeta, wn, step_deg, 0.0, 0.0)   # the fit's own second-order step
    return t, M.thesis_listing_height(a, -a)


def ideal_reading(zeta: float, fd: float, **kw) -> ThesisReading:
    """Listing 7.7's reading of :func:`ideal_step` (true ``zeta``, ``fd`` [Hz])."""
    return second_order(*ideal_step(zeta, fd, **kw), method="thesis")


def bias_table(zetas=(0.05, 0.1, 0.15, 0.229, 0.3, 0.4, 0.5, 0.6, 0.7), fd: float = 5.0, **kw) -> list[dict]:
    """Listing 7.7's zeta against the true zeta on ideal 48-degree steps.

    Returns
    -------
    list of dict: ``true_zeta``, ``thesis_zeta``, ``thesis_f_hz`` (1/(t2 - t1)), ``true_fd``,
    ``true_fn`` [Hz], ``n_peaks``
    """
    rows = []
    for z in zetas:
        r = ideal_reading(z, fd, **kw)
        rows.append({"true_zeta": float(z), "thesis_zeta": r.zeta, "thesis_f_hz": r.fd, "true_fd": fd,
                     "true_fn": fd / math.sqrt(1 - z ** 2), "n_peaks": r.n_peaks})
    return rows


def true_from_reading(thesis_zeta: float, thesis_f_hz: float, step_deg: float = STEP_DEG,
                      bracket=(0.05, 0.7)) -> dict:
    """The ideal second-order step whose Listing 7.7 reading is (``thesis_zeta``,
    ``thesis_f_hz``): what a thesis-measure number means in true zeta, fd, fn.

    Listing 7.7's zeta falls with the true zeta over ``bracket`` on ideal steps of ``step_deg``
    (tests/test_thesis.py checks it; here the bracket's ends must straddle the reading);
    1/(t2 - t1) is fd. Sampled as Listing 7.4 records (2 ms).

    Returns
    -------
    dict: ``zeta`` (true), ``fd`` [Hz], ``fn`` [Hz], ``wn`` [rad/s]
    """
    fd = float(thesis_f_hz)

    def gap(z):
        # sampled as Listing 7.4 records (2 ms), over 1.5 s or long enough for two peaks
        return ideal_reading(z, fd, step_deg=step_deg, duration=max(1.5, 3.0 / fd)).zeta - thesis_zeta

    lo, hi = bracket
    g_lo, g_hi = gap(lo), gap(hi)
    if not g_lo > 0 > g_hi:
        raise ValueError(f"Listing 7.7's zeta {thesis_zeta} is not reached by ideal steps with true zeta in "
                         f"{bracket} (readings {g_lo + thesis_zeta:.3f} .. {g_hi + thesis_zeta:.3f})")
    z = brentq(gap, lo, hi, xtol=1e-5)
    fn = fd / math.sqrt(1 - z ** 2)
    return {"zeta": float(z), "fd": fd, "fn": float(fn), "wn": float(2 * math.pi * fn)}


def compare_readings(responses, leg) -> list[dict]:
    """Both measures for every step response: Listing 7.7's reading and the true fit, the
    latter classified by the one classifier (:func:`leglib.design.points.identify_many`), so
    a point is "ok" here exactly when the gain map counts it "ok".

    Parameters
    ----------
    responses : iterable of :class:`leglib.experiments.step.StepResponse`
    leg : the leg's LegParams (the commanded foot heights)

    Returns
    -------
    list of dict: ``gains``, ``status`` ("ok", "unstable", "failed"), ``reason``;
    Listing 7.7's ``thesis_zeta``, ``thesis_f_hz`` (1/(t2 - t1)) with their 90 % intervals
    ``thesis_zeta_interval``, ``thesis_f_interval`` ((NaN, NaN) for a reading the listing
    fails on), ``thesis_flagged`` (fewer than two peaks: the listing's constants),
    ``thesis_usable`` (its first two peaks are the oscillation's, :attr:`ThesisReading.usable`),
    ``thesis_failure`` (the kind of an outright failure, :attr:`ThesisReading.failure`, or
    None), ``thesis_problem`` (why the listing fails on the response, or None),
    ``thesis_peaks``, ``first_peak_deg``
    (:func:`equivalent_angle_deg` of the first peak); and for an "ok" point the true
    ``zeta``, ``fn``, ``fd`` [Hz] (least squares on the foot height) with their 90 %
    intervals ``zeta_interval``, ``fn_interval``, ``fd_interval`` (NaN otherwise). A failed
    or unstable point keeps its Listing 7.7 reading (what the thesis's method would have
    read) but no true numbers.
    """
    responses = list(responses)
    points = identify_many(responses, leg)
    out = []
    nan = float("nan")
    for r, p in zip(responses, points):
        row = {"gains": tuple(float(g) for g in r.gains), "status": p.status, "reason": p.reason,
               "thesis_zeta": nan, "thesis_f_hz": nan, "thesis_zeta_interval": (nan, nan),
               "thesis_f_interval": (nan, nan), "thesis_flagged": True, "thesis_usable": False,
               "thesis_failure": "not read" if not r.completed else None,
               "thesis_problem": "not read: the step was aborted" if not r.completed else None,
               "thesis_peaks": 0, "first_peak_deg": nan, "zeta": nan, "fn": nan, "fd": nan,
               "zeta_interval": (nan, nan), "fn_interval": (nan, nan), "fd_interval": (nan, nan)}
        if r.completed:
            try:
                th = read_step(r)
            except IdentificationError as exc:
                row.update(thesis_problem=f"Listing 7.7 cannot read it: {exc}", thesis_failure="not read")
            else:
                row.update(thesis_zeta=th.zeta, thesis_f_hz=th.fd, thesis_zeta_interval=th.zeta_interval,
                           thesis_f_interval=th.fd_interval, thesis_flagged=th.flagged,
                           thesis_usable=th.usable, thesis_failure=th.failure, thesis_problem=th.problem,
                           thesis_peaks=th.n_peaks,
                           first_peak_deg=equivalent_angle_deg(th.peak_values[0]) if th.n_peaks else nan)
        if p.status == "ok":
            row.update(zeta=p.zeta, fn=p.fn, fd=p.fd, zeta_interval=p.zeta_interval, fn_interval=p.fn_interval,
                       fd_interval=p.interval("fd"))
        out.append(row)
    return out


def read_sweep(sweep_dir, leg) -> list[dict]:
    """:func:`compare_readings` of every measurement file in ``sweep_dir`` (``leg``:
    LegParams or a parameter-set name, for the files' kinematics)."""

    leg = load_leg(leg) if isinstance(leg, str) else leg
    measurements = read_measurements(sweep_dir).measurements
    if not measurements:
        raise ValueError(f"no measurement files in {sweep_dir}")
    return compare_readings(StepResponse.from_measurements(measurements, leg), leg)


def nearest_reading(rows: list[dict], zeta: float, f_hz: float) -> dict:
    """The measured point whose Listing 7.7 reading is nearest to (``zeta``, ``f_hz``), in
    distances relative to the request (as Listing 7.8's ``dsearchn``, on the measured points
    rather than an interpolated map). Only "ok" points whose reading is usable (its first two
    peaks are the oscillation's) are candidates.

    Returns
    -------
    the row of :func:`compare_readings`, with ``distance`` (relative, Euclidean) added
    """
    best, best_d = None, math.inf
    for r in rows:
        if r["status"] != "ok" or not r["thesis_usable"] or not np.isfinite(r["thesis_zeta"]):
            continue
        d = math.hypot(r["thesis_zeta"] / zeta - 1, r["thesis_f_hz"] / f_hz - 1)
        if d < best_d:
            best, best_d = r, d
    if best is None:
        raise ValueError("no point with a usable Listing 7.7 reading (two peaks of the oscillation) to choose from")
    return {**best, "distance": best_d}


#: how close Listing 7.7's reading must come to a thesis-measure target to count as reached
#: (relative, each of zeta and 1/(t2 - t1))
THESIS_TOLERANCE = 0.10


def reading_against(reading: ThesisReading, target, tolerance: float = THESIS_TOLERANCE) -> dict:
    """Listing 7.7's ``reading`` against a target in its own measure (``target`` = (zeta,
    1/(t2 - t1) [Hz]), e.g. :data:`TEXT_TARGET`): the relative errors with their 90 %
    intervals (the reading's, :class:`leglib.identify.listing77.ReadingIntervals`), and
    reached only when both intervals lie within ``tolerance`` of the target.

    Returns
    -------
    dict: ``error_zeta``, ``error_f`` (fractions), ``error_zeta_interval``,
    ``error_f_interval`` ((NaN, NaN) without a reading), ``reached`` (bool), ``verdict``
    (a sentence: reached, what reaches beyond the tolerance, or why there is no reading)
    """
    nan = float("nan")
    tz, tf = float(target[0]), float(target[1])
    if not reading.usable:
        return {"error_zeta": nan, "error_f": nan, "error_zeta_interval": [nan, nan], "error_f_interval": [nan, nan],
                "reached": False, "verdict": f"not reached: Listing 7.7 gives no reading ({reading.problem})"}
    ez, ef = reading.zeta / tz - 1, reading.fd / tf - 1
    zi = [b / tz - 1 for b in reading.zeta_interval]
    fi = [b / tf - 1 for b in reading.fd_interval]
    beyond = [f"{name} [{lo:+.1%}, {hi:+.1%}]" for name, (lo, hi) in (("zeta", zi), ("1/(t2 - t1)", fi))
              if not (-tolerance <= lo and hi <= tolerance)]
    verdict = (f"reached: both 90 % intervals lie within +-{tolerance:.0%} of the target" if not beyond else
               f"not reached: the errors' 90 % intervals of {' and '.join(beyond)} reach beyond +-{tolerance:.0%}")
    return {"error_zeta": float(ez), "error_f": float(ef), "error_zeta_interval": zi, "error_f_interval": fi,
            "reached": not beyond, "verdict": verdict}


def bias_summary(rows: list[dict]) -> dict:
    """Median and range of Listing 7.7's error against the true values over ``rows``
    (from :func:`compare_readings`), on the points both measures identify: "ok" for the
    classifier, a usable reading for the listing, a true zeta below 1 (an fd to compare).

    Returns
    -------
    dict: ``points``, the three (min, median, max) relative errors, and the "ok" points the
    listing fails on, by kind: ``flagged`` (fewer than two peaks), ``ripple`` (its second peak
    is the tail's ripple), ``unresolved`` (its first two peaks not told apart by their doubt),
    ``many_peaks`` (more peaks than cycles; usable, counted above)
    """
    okr = [r for r in rows if r["status"] == "ok"]

    def kind(r):   # rows without the kind (older callers): every other failure is the tail's ripple
        return r.get("thesis_failure", "flagged" if r["thesis_flagged"] else None if r["thesis_usable"] else "ripple")

    fails = {"flagged": sum(1 for r in okr if kind(r) == "flagged"),
             "ripple": sum(1 for r in okr if kind(r) == "ripple"),
             "unresolved": sum(1 for r in okr if kind(r) == "unresolved"),
             "many_peaks": sum(1 for r in okr if r["thesis_usable"] and r["thesis_problem"])}
    ok = [r for r in okr if r["thesis_usable"] and np.isfinite(r["zeta"]) and np.isfinite(r["fd"])]
    if not ok:
        return {"points": 0, **fails}
    tz = np.array([r["thesis_zeta"] for r in ok])
    z = np.array([r["zeta"] for r in ok])
    tf = np.array([r["thesis_f_hz"] for r in ok])
    fd = np.array([r["fd"] for r in ok])
    fn = np.array([r["fn"] for r in ok])
    ez, efd, efn = tz / z - 1, tf / fd - 1, tf / fn - 1
    q = lambda e: [float(np.min(e)), float(np.median(e)), float(np.max(e))]  # noqa: E731
    return {"points": len(ok), "zeta_rel_error_min_median_max": q(ez),
            "f_vs_fd_rel_error_min_median_max": q(efd), "f_vs_fn_rel_error_min_median_max": q(efn), **fails}


def listing_reach(rows: list[dict]) -> dict:
    """What Listing 7.7 reads at most over a sweep's "ok" points with a usable reading: the
    largest ``thesis_zeta`` with its 90 % interval ``max_thesis_zeta_interval`` and the
    highest upper end of any such reading's interval ``max_thesis_zeta_upper`` (what the
    listing could have read at most, by the readings' doubt), the first peak's largest joint
    swing [deg] there, the true zeta of the least-damped such point, and how many points there
    are. The thesis's validated reading (:data:`THESIS_RESULT`) is the number to hold them
    against."""
    nan = float("nan")
    ok = [r for r in rows if r["status"] == "ok" and r["thesis_usable"]]
    if not ok:
        return {"points": 0, "max_thesis_zeta": nan, "max_thesis_zeta_interval": [nan, nan],
                "max_thesis_zeta_upper": nan, "max_first_peak_deg": nan, "min_true_zeta": nan,
                "thesis_result_zeta": THESIS_RESULT[0]}
    best = max(ok, key=lambda r: r["thesis_zeta"])
    upper = [r.get("thesis_zeta_interval", (nan, nan))[1] for r in ok]
    return {"points": len(ok), "max_thesis_zeta": float(best["thesis_zeta"]),
            "max_thesis_zeta_interval": [float(x) for x in best.get("thesis_zeta_interval", (nan, nan))],
            "max_thesis_zeta_upper": float(np.nanmax(upper)) if np.any(np.isfinite(upper)) else nan,
            "max_thesis_zeta_gains": list(best["gains"]),
            "max_first_peak_deg": float(max(r["first_peak_deg"] for r in ok)),
            "min_true_zeta": float(min(r["zeta"] for r in ok)),
            "thesis_result_zeta": THESIS_RESULT[0]}


def is_thesis_leg(leg: LegParams) -> bool:
    """True when ``leg`` holds the values of the shipped ``leg_thesis.toml`` (the parameter set
    built to reproduce eq. 5.11), wherever it was loaded from: eq. 5.11 is that leg's
    linearization and no other's."""
    ref = load_leg(SHIPPED_DIR / "leg_thesis.toml")
    return all(getattr(leg, f) == getattr(ref, f) for f in vars(ref) if not f.startswith("_") and f != "source_file")


def chapter5_mismatch(leg: LegParams, gains=FIG_6_9_GAINS, viscous: float | None = None) -> dict:
    """The chapter-5/6 mismatch in numbers: the damping chapter 5 identified against the
    damping chapter 6's response shows.

    The model: one cascade axis (:class:`leglib.design.tuning.AxisModel`: position P,
    velocity PI, current loop and encoder PLL of Listing 7.1's ODrive) on ``leg``'s
    opening-mode inertia at rest, with the joint's viscous damping ``viscous``
    [N*m*s/rad] (default ``leg.c11``, chapter 5's 0.098 on the thesis's leg) seen at the
    motor (viscous 2 pi / gear^2 per turn/s), stepped with ``gains`` (Fig. 6.9's by default)
    and identified on the foot height. The measurement: the thesis's validated reading
    (:data:`THESIS_RESULT`, Listing 7.7's measure) as the ideal step that reads so
    (:func:`true_from_reading`).

    Returns
    -------
    dict: ``gains``, ``viscous`` [N*m*s/rad], ``step_deg`` (the step's joint swing [deg]), ``model`` {``zeta``, ``fn`` [Hz]} (NaN when the
    model's step is no second-order step), ``thesis_result`` {``zeta``, ``f_hz``} (Listing
    7.7), ``thesis_result_as_true`` {``zeta``, ``fd``, ``fn``} (true measure)
    """
    cfg = load_odrive_config("thesis")
    c = leg.c11 if viscous is None else float(viscous)
    D = M.mass_matrix(leg, *leg.q0)
    model = AxisModel(J=motor_side_inertia(float(D[0, 0] - D[0, 1]), leg.gear_ratio),
                      b=c * 2 * math.pi / leg.gear_ratio ** 2, torque_constant=cfg.torque_constant,
                      current_bandwidth=cfg.current_control_bandwidth, encoder_bandwidth=cfg.encoder_bandwidth,
                      leg=leg)
    zeta, fn = model.predict(tuple(gains))
    true = true_from_reading(*THESIS_RESULT)
    return {"gains": [float(g) for g in gains], "viscous": c, "step_deg": STEP_DEG,
            "model": {"zeta": float(zeta), "fn": float(fn)},
            "thesis_result": {"zeta": THESIS_RESULT[0], "f_hz": THESIS_RESULT[1]},
            "thesis_result_as_true": {"zeta": true["zeta"], "fd": true["fd"], "fn": true["fn"]}}


# ---------------------------------------------------------------------------------------
# eqs. 6.1 / 6.3: the virtual leg's m, b, k
# ---------------------------------------------------------------------------------------

@dataclass
class VirtualLeg:
    """The spring-damper-mass of eq. 6.1 equivalent to a second-order response (eq. 6.3).

    m [kg], b [N*s/m], k [N/m], k_dc = 1/k [m/N]; zeta [-], fn [Hz] the true parameters it
    was built from.
    """

    m: float
    b: float
    k: float
    zeta: float
    fn: float

    @property
    def k_dc(self) -> float:
        return 1.0 / self.k


def step_end_pose(leg: LegParams, step_deg: float = STEP_DEG) -> tuple[float, float]:
    """Joint angles [rad] at the end of Listing 7.4's step: the leg opened by ``step_deg``
    on each joint from the operating point (q1 down, q2 up)."""
    s = math.radians(step_deg)
    return leg.q0[0] - s, leg.q0[1] + s


def foot_mass(leg: LegParams, q=None, model: str = "fivebar", eps: float = 1e-6) -> float:
    """The leg's effective mass [kg] at the foot along y (vertical), at rest at ``q``.

    m_y = 1 / (J D^-1 J^T)_yy with D(q) the joint-space inertia (drive inertias included)
    and J the foot's Jacobian: the mass a vertical force at the foot accelerates, which is
    eq. 6.1's m for the virtual leg. ``q`` defaults to :func:`step_end_pose`, where a step
    response oscillates (at the operating point, 6 deg from straight, the leg is nearly
    singular vertically and m_y is tens of kg).
    """
    q1, q2 = step_end_pose(leg) if q is None else (float(q[0]), float(q[1]))
    J = np.empty((2, 2))
    for j, dq in enumerate(((eps, 0.0), (0.0, eps))):
        p = np.array(M.foot_position(leg, q1 + dq[0], q2 + dq[1]))
        m_ = np.array(M.foot_position(leg, q1 - dq[0], q2 - dq[1]))
        J[:, j] = (p - m_) / (2 * eps)
    D = M.mass_matrix(leg, q1, q2, model=model)
    lam_inv = J @ np.linalg.solve(D, J.T)
    return float(1.0 / lam_inv[1, 1])


def virtual_leg(zeta: float, fn: float, mass: float) -> VirtualLeg:
    """Eqs. 6.1/6.3: the m, b, k at the foot equivalent to a response with true damping
    ``zeta`` [-] and natural frequency ``fn`` [Hz], for the foot's effective ``mass`` [kg].

    From 1/(m s^2 + b s + k) = k_dc wn^2 / (s^2 + 2 zeta wn s + wn^2): k = m wn^2,
    b = 2 zeta wn m, k_dc = 1/k, with wn = 2 pi fn. A thesis-measure target (Listing 7.7)
    must first be converted with :func:`true_from_reading`.

    Parameters
    ----------
    zeta : float, true damping ratio (> 0)
    fn : float, true natural frequency [Hz] (> 0)
    mass : float, effective mass at the foot [kg] (e.g. :func:`foot_mass`)

    Returns
    -------
    VirtualLeg
    """
    for name, v in (("zeta", zeta), ("fn", fn), ("mass", mass)):
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"virtual_leg: {name} must be positive and finite, got {v}")
    wn = 2 * math.pi * fn
    return VirtualLeg(m=float(mass), b=float(2 * zeta * wn * mass), k=float(mass * wn ** 2), zeta=float(zeta),
                      fn=float(fn))


# ---------------------------------------------------------------------------------------
# Table 6.1 and Listing 7.1
# ---------------------------------------------------------------------------------------

#: Table 6.1 as printed (SI).
TABLE_6_1 = {"Ra": 1.2, "La": 0.56e-3, "Kt": 25.5e-3, "tm": 17.1e-3, "J": 92.5e-7, "p": 3, "Kb": 0.0764,
             "B1": 0.1, "Hc": 1.0}
#: Listing 7.1: torque_constant = 8.27/340 [N*m/A]; Table 4.3: KV 340 rpm/V, 69 (milli)ohm.
LISTING_7_1_KT = 8.27 / 340
TABLE_4_3_RESISTANCE = 69e-3


def table_6_1_checks() -> list[dict]:
    """Table 6.1's constants against each other and against Listing 7.1 / Table 4.3.

    Returns
    -------
    list of dict: ``claim``, ``printed``, ``derived``, ``ratio`` (printed / derived), ``how``
    """
    T = TABLE_6_1
    kv_si = 340 * 2 * math.pi / 60  # rad/s per V
    rows = [
        ("R_a (twice the phase resistance, Krishnan)", T["Ra"], 2 * TABLE_4_3_RESISTANCE, "2 x 69 mOhm (Table 4.3)"),
        ("K_t [N m/A]", T["Kt"], LISTING_7_1_KT, "Listing 7.1: 8.27/340"),
        ("K_b [V s/rad] (= K_t in SI)", T["Kb"], T["Kt"], "K_b = K_t (SI, same winding)"),
        ("K_b [V s/rad] against KV", T["Kb"], 1 / kv_si, "1/KV = 60/(2 pi 340)"),
        ("t_m [s] = J R_a / (K_t K_b)", T["tm"], T["J"] * T["Ra"] / (T["Kt"] * T["Kb"]), "with the printed K_b"),
        ("t_m [s] = J R_a / K_t^2", T["tm"], T["J"] * T["Ra"] / T["Kt"] ** 2, "with K_b = K_t"),
        ("J / B_1 [s] (mechanical friction time)", T["J"] / T["B1"], T["tm"], "against t_m"),
    ]
    return [{"claim": c, "printed": float(p), "derived": float(d), "ratio": float(p / d), "how": h}
            for c, p, d, h in rows]


# ---------------------------------------------------------------------------------------
# eq. 5.11: inputs, outputs, sensitivity; the sign of m4 lc4 in g2
# ---------------------------------------------------------------------------------------

def eq511_lumped(q0=(math.radians(267.0), math.radians(273.0)), g: float = 9.81) -> dict:
    """The four lumped quantities eq. 5.11 (Listing 7.5's decoupled form) pins down.

    Returns
    -------
    dict: ``d11``, ``d22`` [kg m^2] = 1/B; ``K1`` = m1 lc1 + m3 lc3 + m4 l1 and ``K2`` =
    m2 lc2 + m3 l2 + m4 lc4 [kg m] (Listing 7.5's sign) from A[1,0] and A[3,2]; the damping
    ``c11, c12, c21, c22`` [N m s/rad] (A[3,3] read as -30.22).
    """
    A, B = M.THESIS_A, M.THESIS_B
    d11, d22 = 1 / B[1, 0], 1 / B[3, 1]
    return {"d11": d11, "d22": d22,
            "K1": A[1, 0] * d11 / (g * math.sin(q0[0])), "K2": A[3, 2] * d22 / (g * math.sin(q0[1])),
            "c11": -A[1, 1] * d11, "c12": -A[1, 3] * d11, "c21": -A[3, 1] * d22, "c22": -A[3, 3] * d22}


def leg_for_lower_masses(leg: LegParams, m3: float, m4: float) -> tuple[LegParams, dict]:
    """Re-solve the shipped parameter set for other lower-link masses ``m3``, ``m4`` [kg].

    Follows leg_thesis.toml's recipe: lc3, lc4 from K1, K2, uniform-rod I3, I4,
    and Jd1, Jd2 from d11, d22, so that the thesis form reproduces eq. 5.11 whatever the
    masses. Returns the leg and a dict of flags (``lc3_on_link``, ``lc4_on_link``,
    ``Jd_positive``): a guess is physical only if the COMs lie on the links and the drive
    inertias are positive.
    """
    L = eq511_lumped(leg.q0, leg.g)
    lc3 = (L["K1"] - leg.m1 * leg.lc1 - m4 * leg.l1) / m3
    lc4 = (L["K2"] - leg.m2 * leg.lc2 - m3 * leg.l2) / m4
    I3, I4 = m3 * leg.l3 ** 2 / 12, m4 * leg.l4 ** 2 / 12
    Jd1 = L["d11"] - (leg.m1 * leg.lc1 ** 2 + m3 * lc3 ** 2 + m4 * leg.l1 ** 2 + leg.I1 + I3)
    Jd2 = L["d22"] - (leg.m2 * leg.lc2 ** 2 + m3 * leg.l2 ** 2 + m4 * lc4 ** 2 + leg.I2 + I4)
    new = leg.replace(m3=m3, m4=m4, lc3=lc3, lc4=lc4, I3=I3, I4=I4, Jd1=Jd1, Jd2=Jd2)
    flags = {"lc3_on_link": bool(0 <= lc3 <= leg.l3), "lc4_on_link": bool(0 <= lc4 <= leg.l4),
             "Jd_positive": bool(Jd1 > 0 and Jd2 > 0)}
    return new, flags


def eq511_sensitivity(leg: LegParams, masses=(0.07, 0.085, 0.1, 0.115, 0.13)) -> list[dict]:
    """How the exact five-bar's linearization depends on the guessed lower-link masses.

    For each m3 = m4 in ``masses`` [kg] the parameter set is re-solved from eq. 5.11
    (:func:`leg_for_lower_masses`): the thesis form then reproduces eq. 5.11 by construction
    (its inputs), while the exact five-bar's coupled A (an output) moves.

    Returns
    -------
    list of dict: ``m_lower`` [kg], ``lc3``, ``lc4`` [m], ``Jd1``, ``Jd2`` [kg m^2], the
    physical flags, ``thesis_A`` and ``exact_A`` (4x4 lists) and the exact model's
    ``A10``, ``A12``, ``A30``, ``A32`` [1/s^2], ``B10``, ``B31`` [1/(kg m^2)], ``eig`` (open loop)
    """
    rows = []
    for m in masses:
        lg, flags = leg_for_lower_masses(leg, m, m)
        th = M.linearize(lg)
        ex = M.linearize(lg, coupled=True, model="fivebar")
        A, B = np.asarray(ex.A), np.asarray(ex.B)
        rows.append({"m_lower": float(m), "lc3": lg.lc3, "lc4": lg.lc4, "Jd1": lg.Jd1, "Jd2": lg.Jd2, **flags,
                     "thesis_A": np.asarray(th.A).tolist(), "exact_A": A.tolist(),
                     "A10": float(A[1, 0]), "A12": float(A[1, 2]), "A30": float(A[3, 0]), "A32": float(A[3, 2]),
                     "B10": float(B[1, 0]), "B31": float(B[3, 1]),
                     "eig": [complex(e) for e in np.linalg.eigvals(A)]})
    return rows


def gravity_stiffness(leg: LegParams, q=None, model: str = "fivebar", eps: float = 1e-6) -> np.ndarray:
    """dg/dq [N m/rad] (2x2) of the gravity torques of ``model`` at ``q`` (default q0)."""
    q1, q2 = leg.q0 if q is None else (float(q[0]), float(q[1]))
    K = np.empty((2, 2))
    for j, d in enumerate(((eps, 0.0), (0.0, eps))):
        K[:, j] = (np.asarray(M.gravity_torque(leg, q1 + d[0], q2 + d[1], model=model))
                   - np.asarray(M.gravity_torque(leg, q1 - d[0], q2 - d[1], model=model))) / (2 * eps)
    return K


def g2_sign_check(leg: LegParams) -> dict:
    """Joint 2's gravity stiffness with eq. 5.4's sign (-m4 lc4), Listing 7.5's (+m4 lc4) and
    the exact coaxial five-bar, at the operating point.

    Returns
    -------
    dict: ``k22_eq54``, ``k22_listing``, ``k22_exact`` = dg2/dq2 [N m/rad]; ``A32_eq54``,
    ``A32_listing`` = -k22 / d22 of the decoupled form and ``A32_exact`` (coupled exact
    five-bar) [1/s^2]; ``A32_thesis`` = eq. 5.11's -65.78; ``supported`` ("+" or "-"): the
    sign whose stiffness is nearer the exact model's.
    """
    q2 = leg.q0[1]
    d22 = 1 / np.asarray(M.linearize(leg).B)[3, 1]
    base = leg.m2 * leg.lc2 + leg.m3 * leg.l2
    k_minus = -leg.g * math.sin(q2) * (base - leg.m4 * leg.lc4)
    k_plus = -leg.g * math.sin(q2) * (base + leg.m4 * leg.lc4)
    k_exact = float(gravity_stiffness(leg, model="fivebar")[1, 1])
    ex = np.asarray(M.linearize(leg, coupled=True, model="fivebar").A)
    return {"k22_eq54": k_minus, "k22_listing": k_plus, "k22_exact": k_exact,
            "A32_eq54": -k_minus / d22, "A32_listing": -k_plus / d22, "A32_exact": float(ex[3, 2]),
            "A32_thesis": float(M.THESIS_A[3, 2]),
            "supported": "+" if abs(k_plus - k_exact) < abs(k_minus - k_exact) else "-"}
