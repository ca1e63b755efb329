"""How wrong each method is on legs its models do not describe: the robustness table.

Every method of the workbench runs on every shipped twin plant (``leglib/params/plant_*.toml``:
the default plant, whose structure the models share, and plants with effects no model here
has: compliant belts, cogging and encoder nonlinearity, LuGre friction that is asymmetric and
drifts), and is scored against the plant's truth or the target:

====================  ==================================================================
friction (02)         ``identify.fit_leg_friction`` of the sine-torque run: worst relative
                      error of the joints' viscous and Coulomb friction against the plant's
                      (for an asymmetric plant, the mean of both directions; for a drifting
                      one, its value when the run starts)
second order (02)     ``identify.second_order`` of steps at five gain sets: relative error of
                      zeta and fn against the same plant measured by an ideal sensor (no
                      noise, no quantization, no encoder nonlinearity)
state feedback (03)   a design on the identified leg, its torque table played back and the
                      loop closed live: RMS deviation of segment 2 from the design's
                      nonlinear simulation, in % of the step
map (04/05)           the thesis grid swept (400 steps), the map's nearest point for each
                      target, measured
model (05)            ``gainmap.fit_leg_plant`` (the twin's own structure, 5 steps), its
                      gains for each target, measured
design (05)           ``tune`` for each target (at most 10 steps each)
====================  ==================================================================

Targets: the thesis's (zeta 0.24, fn 5 Hz) and the (zeta, fn) measured on the same leg at
other gains (so each is reachable on that leg). :func:`run` returns a :class:`Table`;
``python -m leglib robustness`` (``make robustness``) writes it to ``reports/robustness/``.

Every identified (zeta, fn) in the table carries its 90 % intervals from the one classifier
(:func:`leglib.design.points.identify_response`), stored as a saved design stores them
(``{"zeta", "fn_hz", "zeta_interval", "fn_interval_hz"}``); a step that is not a second-order
step is stored as its status and reason, without numbers. The relative errors of
:data:`INTERVAL_METHODS` carry intervals too: each item's (``error_interval``, the
measurement's intervals relative to its reference, as :mod:`leglib.design.validation`), and
each cell's median and worst (``median_interval``, ``worst_interval``:
:func:`leglib.design.validation.error_statistics`). A table written before they were stored
still loads and says "no interval recorded" wherever it shows such a number.
"""

from __future__ import annotations

import datetime
import json
import math
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import identify
from .. import model as M
from .._version import staleness as _staleness
from ..design import statefeedback as SF
from ..design.gainmap import GainMap
from ..design.plantfit import fit_leg_plant, fitting_gains, twin_step_responses
from ..design.points import STATUS_OK, identify_response
from ..design.saved import NO_INTERVAL
from ..design.tuning import tune
from ..design.validation import Validation, error_statistics, relative_intervals, validate
from ..device.session import connect
from ..device.setup import calibrate, configure
from ..errors import ExperimentError, ParameterError
from ..experiments.step import _responses_from_batch, return_to_rest, step_response
from ..experiments.sweep import thesis_grid
from ..experiments.torque import friction_experiment, play_torque_table
from ..params import load_plant, plant_names
from ..twin.host import Twin
from ..units import dynamics_text, percent_interval_text

THESIS_TARGET = (0.24, 5.0)
#: gains at which the further targets are measured on each leg (moderate, stable)
TARGET_GAINS = ((30.0, 0.05, 0.01), (45.0, 0.09, 0.01), (25.0, 0.12, 0.01), (60.0, 0.06, 0.01))
METHODS = ("friction", "second order", "state feedback: playback", "state feedback: live", "map", "model", "design")
#: evaluation budget of the friction fit (a plant it cannot describe can keep it searching for minutes)
FRICTION_NFEV = 200
#: a method "degrades" on a plant when its error there exceeds this and twice its default-plant error
DEGRADED = 0.05
#: the methods whose errors come from identified (zeta, fn): their errors carry 90 % intervals
#: (the others' are not identified values: friction's against the plant's truth, the state
#: feedback's RMS deviations of one run)
INTERVAL_METHODS = ("second order", "map", "model", "design")


@dataclass
class Score:
    """One method on one plant: ``median`` and ``worst`` relative errors (fractions),
    ``experiments`` the device experiments it took, ``detail`` per item, ``note`` anything
    the numbers do not say (outside the region, not identifiable). ``median_interval`` and
    ``worst_interval``: for :data:`INTERVAL_METHODS`, the ranges of the median and worst
    error that the items' 90 % intervals allow (:func:`leglib.design.validation.error_statistics`);
    None for the other methods, and in a table written before they were stored."""

    median: float
    worst: float
    experiments: int
    detail: dict = field(default_factory=dict)
    note: str = ""
    seconds: float = math.nan
    median_interval: tuple | None = None
    worst_interval: tuple | None = None

    def __post_init__(self):
        # a table read from JSON holds lists; None stays None (no interval recorded)
        for name in ("median_interval", "worst_interval"):
            v = getattr(self, name)
            if v is not None:
                setattr(self, name, tuple(math.inf if b is None else float(b) for b in v))


def _rel(a, b) -> float:
    return float(a / b - 1) if b else math.nan


def _stats(errors) -> tuple[float, float]:
    e = np.abs(np.asarray([x for x in errors if isinstance(x, float) and not math.isnan(x)], float))
    return (float(np.median(e)), float(np.max(e))) if e.size else (math.nan, math.nan)


def friction_truth(plant) -> dict:
    """The friction values a Coulomb + viscous fit should find on ``plant`` (joint side),
    before any drift: viscous and Coulomb per joint. An asymmetric plant's Coulomb levels
    are coulomb (1 +- coulomb_asymmetry), so their mean is its ``coulomb``; a LuGre plant's
    viscous term is its ``viscous``."""
    return {f"{k}{j}": float(getattr(plant, f"{k}{j}")) for j in (1, 2) for k in ("coulomb", "viscous")}


def ideal_sensor_plant(plant):
    """``plant`` read by an ideal encoder: no encoder nonlinearity (noise and quantization are
    switched off on the twin itself)."""
    zero = {k: 0.0 for k in vars(plant) if k.startswith("encoder_") and k != "encoder_noise"
            and isinstance(getattr(plant, k), float)}
    return plant.replace(**zero) if zero else plant


def _pairs(intervals) -> list:
    return [[float(b) for b in iv] for iv in intervals]


def dynamics(point) -> dict:
    """A :class:`leglib.design.points.PointResult` as the table stores it: ``{"zeta", "fn_hz",
    "zeta_interval", "fn_interval_hz"}`` (a saved design's keys) when it is a second-order
    step, else ``{"status", "reason"}`` and no numbers."""
    if point.status != STATUS_OK:
        return {"status": point.status, "reason": point.reason or point.status}
    return {"zeta": float(point.zeta), "fn_hz": float(point.fn), "zeta_interval": _pairs([point.zeta_interval])[0],
            "fn_interval_hz": _pairs([point.fn_interval])[0]}


def _gains_text(gains) -> str:
    return "(" + ", ".join(f"{float(g):g}" for g in gains) + ")"


def _measure(dev, gains) -> dict | None:
    """A target measured on the leg at ``gains``: :func:`dynamics` of the step, with where
    it was measured; None when the step is not a second-order step."""
    p = identify_response(step_response(dev, *gains), dev.leg)
    return {**dynamics(p), "source": f"measured at {_gains_text(gains)}"} if p.status == STATUS_OK else None


def _pair(target: dict) -> tuple:
    return (target["zeta"], target["fn_hz"])


def _scored(detail: dict, errors: list, intervals: list) -> dict:
    """``detail`` with the relative errors (zeta, fn) and their 90 % intervals."""
    return {**detail, "error": [float(e) for e in errors], "error_interval": _pairs(intervals)}


def _final_check(d):
    """The :class:`leglib.design.points.PointResult` of a tuning's final check (the experiment
    at its gains; the last one when none matches)."""
    final = next((e for e in reversed(d.experiments) if e.gains == d.gains), d.experiments[-1])
    return final.result


def _score(v: Validation, targets: list, seconds: float) -> Score:
    """A :class:`Validation` as a table cell: its median and worst error (infinite for a
    target that is not identifiable) with their intervals, experiments, each target's
    detail (``targets``: the stored targets, in ``v``'s order)."""
    s = v.summary()
    detail, notes = {}, []
    for k, (r, tgt) in enumerate(zip(v.rows, targets), 1):
        if r.outside:
            near = {"zeta": r.nearest[0], "fn_hz": r.nearest[1]}
            if r.nearest_intervals is not None:
                near.update(zeta_interval=_pairs(r.nearest_intervals)[0], fn_interval_hz=_pairs(r.nearest_intervals)[1])
            detail[f"target {k}"] = {"target": tgt, "outside": True, "nearest": near}
            notes.append(f"target {k} outside the region")
            continue
        item = {"target": tgt, "gains": list(r.gains), "status": r.measured.status, "measured": dynamics(r.measured),
                "experiments": r.experiments, **({"note": r.note} if r.note else {})}
        if r.identified:
            item = _scored(item, r.error, r.error_interval)
        else:
            item["reason"] = r.measured.reason or r.measured.status
            notes.append(f"target {k} not identifiable")
        detail[f"target {k}"] = item
    return Score(s["median"], s["worst"], experiments=s["experiments"], detail=detail, note="; ".join(notes),
                 seconds=seconds, median_interval=s["median_interval"], worst_interval=s["worst_interval"])


def _stats_score(errors, intervals, **kw) -> Score:
    st = error_statistics(errors, intervals)
    return Score(st["median"], st["worst"], median_interval=st["median_interval"],
                 worst_interval=st["worst_interval"], **kw)


def evaluate(plant_name: str, payload: float = 0.0, seed: int = 70, quick: bool = False,
             methods=METHODS, progress=None) -> dict:
    """Every method in ``methods`` on one plant (a fresh virtual device); returns
    {method: Score} and "targets"."""

    say = progress or (lambda msg: None)
    plant = load_plant(plant_name, payload_mass=payload)
    dev = connect("virtual", seed=seed, plant=plant)
    out: dict = {}
    try:
        configure(dev)
        calibrate(dev)
        leg = dev.leg
        tw = dev.sim.twin
        truth = friction_truth(tw.plant)
        n_targets = 2 if quick else len(TARGET_GAINS)
        stored = [{"zeta": THESIS_TARGET[0], "fn_hz": THESIS_TARGET[1], "source": "thesis"}]
        stored += [m for m in (_measure(dev, g) for g in TARGET_GAINS[:n_targets]) if m is not None]
        targets = [_pair(t) for t in stored]
        out["targets"] = stored
        fit = None
        if any(m in methods for m in ("friction", "state feedback: playback", "state feedback: live")):
            t0 = time.perf_counter()
            say(f"{plant_name}: friction")
            run = friction_experiment(dev, duration=5.0 if quick else 8.0)
            fit = identify.fit_leg_friction(run, leg, start=0.8, starts=1, max_nfev=FRICTION_NFEV)
            errs = {k: _rel(fit.params[k], v) for k, v in truth.items()}
            out["friction"] = Score(*_stats(errs.values()), experiments=1,
                                    detail={**errs, "rms_deg": fit.rms_deg, "converged": fit.converged},
                                    note="" if fit.converged else f"fit stopped at {FRICTION_NFEV} evaluations",
                                    seconds=time.perf_counter() - t0)
            return_to_rest(dev)
        if "second order" in methods:
            t0 = time.perf_counter()
            say(f"{plant_name}: second-order identification")
            gains = fitting_gains(5)
            ideal = twin_step_responses(Twin(ideal_sensor_plant(tw.plant), dev.config, noise=False,
                                                quantize=False), gains)
            errs, ivs, detail, flagged = [], [], {}, 0
            for g, ref in zip(gains, ideal):
                p = identify_response(step_response(dev, *g), leg)
                r = identify_response(ref, leg)
                item = {"gains": [float(x) for x in g], "status": p.status, "measured": dynamics(p),
                        "ideal": dynamics(r)}
                key = f"gains {_gains_text(g)}"
                if p.status != STATUS_OK or r.status != STATUS_OK:
                    flagged += 1
                    which = p if p.status != STATUS_OK else r
                    item.update(status=which.status, reason=("" if which is p else "the ideal sensor's step: ")
                                + (which.reason or which.status))
                    detail[key] = item
                    continue
                # the measurement's intervals relative to the ideal sensor's reading, taken as the
                # reference as a validation takes its target; the reference's own intervals are
                # stored beside it
                e = (_rel(p.zeta, r.zeta), _rel(p.fn, r.fn))
                iv = relative_intervals((p.zeta_interval, p.fn_interval), (r.zeta, r.fn))
                errs.extend(e)
                ivs.extend(iv)
                detail[key] = _scored({**item, "r2": p.r2,
                                       "ideal_inside": bool(p.zeta_interval[0] <= r.zeta <= p.zeta_interval[1]
                                                            and p.fn_interval[0] <= r.fn <= p.fn_interval[1])}, e, iv)
            out["second order"] = _stats_score(errs, ivs, experiments=len(gains), detail=detail,
                                               note=f"{flagged} flagged as not a second-order step" if flagged else "",
                                               seconds=time.perf_counter() - t0)
        if fit is not None and ("state feedback: playback" in methods or "state feedback: live" in methods):
            t0 = time.perf_counter()
            say(f"{plant_name}: state feedback")
            cfg = dev.config
            torque_limit = cfg.current_lim * cfg.torque_constant * leg.gear_ratio
            step = (0.0, math.radians(20.0))
            ident_leg, F = fit.leg, M.friction_vector(fit.leg, v_smooth=fit.params["v_smooth"])
            d = SF.place_poles(M.linearize(ident_leg, coupled=True, model="fivebar"), SF.spread_poles(-7.0, 4), 6.0,
                          integral_poles=SF.spread_poles(-4.0, 2))
            sim = SF.simulate_closed_loop(ident_leg, d, step=step, duration=4.5, period=0.002,
                                          torque_limit=torque_limit, friction=F)
            span = abs(step[1])
            played = play_torque_table(dev, sim.tau, period=0.002)
            n = min(len(played.q2), len(sim.x))
            rms_play = float(np.sqrt(np.mean((played.q2[:n] - sim.x[:n, 2]) ** 2)) / span)
            return_to_rest(dev)
            out["state feedback: playback"] = Score(rms_play, rms_play, experiments=1,
                                                    detail={"rms_deviation_of_step": rms_play},
                                                    seconds=time.perf_counter() - t0)
            t0 = time.perf_counter()
            try:
                live = SF.run_live(dev, d, ident_leg, step=step, duration=4.5, period=0.002)
                n = min(len(live.q2), len(sim.x))
                ti = np.interp(sim.t[:n], live.t, live.q2)
                rms_live = float(np.sqrt(np.mean((ti - sim.x[:n, 2]) ** 2)) / span)
                final = abs(live.q2[-1] - (leg.q2 + step[1])) / span
                out["state feedback: live"] = Score(rms_live, max(rms_live, final), experiments=1,
                                                    detail={"rms_deviation_of_step": rms_live, "final_error": final},
                                                    seconds=time.perf_counter() - t0)
            except ExperimentError as exc:
                out["state feedback: live"] = Score(math.inf, math.inf, experiments=1, note=f"aborted: {exc}",
                                                    seconds=time.perf_counter() - t0)
            return_to_rest(dev)
        if "map" in methods:
            t0 = time.perf_counter()
            say(f"{plant_name}: map (thesis grid)")
            grid = thesis_grid()
            batch = dev.sim.step_batch(grid, vel_limit=dev.config.step_vel_limit, abort_error_turns=0.8)
            gm = GainMap.from_responses(_responses_from_batch(dev, grid, batch, 0.4), leg)
            v = validate(dev, targets, lambda tg: (gm.gains_for(*tg), 0, None, ""), "map",
                         setup_experiments=len(grid))
            out["map"] = _score(v, stored, time.perf_counter() - t0)
        if "model" in methods:
            t0 = time.perf_counter()
            say(f"{plant_name}: model-based inverse (fit_leg_plant)")
            fg = fitting_gains(5)
            model = fit_leg_plant([step_response(dev, *g) for g in fg], dev.config, load_plant("default"))
            def model_gains(tg):
                gains, predicted = model.gains_for(*tg)
                return gains, 0, predicted, ""
            v = validate(dev, targets, model_gains, "model", setup_experiments=len(fg))
            out["model"] = _score(v, stored, time.perf_counter() - t0)
        if "design" in methods:
            t0 = time.perf_counter()
            say(f"{plant_name}: design")
            errs, ivs, detail, counts, failed = [], [], {}, [], 0
            for k, (tgt, stored_target) in enumerate(zip(targets, stored), 1):
                d = tune(dev, *tgt, max_experiments=10)
                counts.append(len(d.experiments))
                final = _final_check(d)
                item = {"target": stored_target, "gains": list(d.gains), "status": final.status,
                        "measured": dynamics(final), "experiments": len(d.experiments), "reached": bool(d.reached),
                        "verdict": d.verdict}
                if final.status == STATUS_OK:
                    errs.extend(d.error)
                    ivs.extend(d.error_interval)
                    item = _scored(item, d.error, d.error_interval)
                else:
                    # as a validation counts a check that is not a second-order step: an infinite
                    # error, never dropped
                    failed += 1
                    errs.extend((math.inf, math.inf))
                    ivs.extend(((math.inf, math.inf),) * 2)
                    item["reason"] = final.reason or final.status
                detail[f"target {k}"] = item
            note = f"experiments per target: median {np.median(counts):.0f}, max {max(counts)}"
            out["design"] = _stats_score(errs, ivs, experiments=int(sum(counts)), detail=detail,
                                         note=note + (f"; {failed} final check(s) not identifiable" if failed else ""),
                                         seconds=time.perf_counter() - t0)
    finally:
        dev.close()
    return out


# ---------------------------------------------------------------------------------------
# the table's numbers as text (also what findings.robustness quotes)
# ---------------------------------------------------------------------------------------

def error_text(value, interval, method: str | None = None) -> str:
    """A relative error [fraction] as the table writes it: for :data:`INTERVAL_METHODS` (and
    ``method`` None: a number that has one) with its 90 % interval, to the digits the
    interval supports ("2.9 % [2.1, 3.6] %", :func:`leglib.units.percent_interval_text`), or
    "2.9 % (no interval recorded)" when the table holds none (one written before they were
    stored); for the other methods "2.9 %"; "∞" when it is infinite (a step that is not a
    second-order step, an aborted run), "—" when there is none."""
    if value is None or math.isnan(value):
        return "—"
    if math.isinf(value):
        return "∞"
    if method is not None and method not in INTERVAL_METHODS:
        return f"{100 * value:.1f} %"
    if interval is None:
        return f"{100 * value:.1f} % ({NO_INTERVAL})"
    return percent_interval_text(value, interval, sign=False)


def worst_of(cells, method: str | None = None) -> tuple[float, tuple | None]:
    """The largest finite worst error of ``cells`` (:class:`Score` objects or their JSON
    dicts, of ``method``; None: of methods with intervals) and its range: (max of the
    worsts, (max of their lower bounds, max of their upper bounds)); the range is None when
    a cell has no interval recorded or ``method`` has none. (NaN, None) without finite cells."""
    get = (lambda c, k: c.get(k) if isinstance(c, dict) else getattr(c, k))
    cells = [c for c in cells if get(c, "worst") is not None and math.isfinite(get(c, "worst"))]
    if not cells:
        return math.nan, None
    worst = max(float(get(c, "worst")) for c in cells)
    ivs = [get(c, "worst_interval") for c in cells]
    if (method is not None and method not in INTERVAL_METHODS) or any(iv is None for iv in ivs):
        return worst, None
    return worst, (max(float(iv[0]) for iv in ivs), max(float(iv[1]) for iv in ivs))


def _interval_pair(v) -> tuple | None:
    if v is None:
        return None
    return tuple(math.inf if b is None else float(b) for b in v)


def read_dynamics(value, intervals=None) -> tuple[tuple | None, tuple | None, str | None]:
    """A stored (zeta, fn): (pair, intervals ((zeta low, high), (fn low, high)) or None,
    failure or None). Reads what :func:`dynamics` stores, and what tables written before
    the intervals were stored hold: a bare [zeta, fn] (``intervals`` given beside it, if any;
    [NaN, NaN] for a step that was not identified, whose reason those tables did not keep)."""
    if isinstance(value, dict):
        if "zeta" not in value:
            return None, None, f"{value.get('status', 'failed')}: {value.get('reason', 'no reason recorded')}"
        pair = (float(value["zeta"]), float(value.get("fn_hz", value.get("fn"))))
        zi, fi = value.get("zeta_interval"), value.get("fn_interval_hz", value.get("fn_interval"))
        return pair, None if zi is None or fi is None else (_interval_pair(zi), _interval_pair(fi)), None
    if value is None:
        return None, None, "none"
    pair = tuple(float(x) for x in value)
    if any(math.isnan(x) for x in pair):
        return None, None, "not identified (this table did not record why)"
    if intervals is not None and not any(x is None for x in intervals):
        intervals = tuple(_interval_pair(x) for x in intervals)
        if any(math.isnan(b) for x in intervals for b in x):
            intervals = None
    else:
        intervals = None
    return pair, intervals, None


def dynamics_cell(value, intervals=None) -> str:
    """A stored (zeta, fn) as a table cell: "ζ 0.243 [0.236, 0.250], fn 5.02 [4.98, 5.06] Hz"
    (the digits its intervals support), "ζ 0.243, fn 5.02 Hz (no interval recorded)" from a
    table without them, or the status and reason of a step that is not a second-order step."""
    pair, iv, failure = read_dynamics(value, intervals)
    if failure is not None:
        return failure.replace("|", "/")
    if iv is None:
        return f"ζ {pair[0]:.3f}, fn {pair[1]:.2f} Hz ({NO_INTERVAL})"
    return dynamics_text(pair[0], pair[1], *iv, zeta_name="ζ")


def target_cell(target) -> str:
    """A stored target: the thesis's (prescribed, exact), or measured on the leg with its
    intervals and where (:func:`dynamics_cell`)."""
    if isinstance(target, dict) and target.get("source") == "thesis":
        return f"ζ {target['zeta']:g}, fn {target['fn_hz']:g} Hz (the thesis's target, prescribed)"
    text = dynamics_cell(target)
    return text + (f", {target['source']}" if isinstance(target, dict) and target.get("source") else "")


def _errors_cell(item: dict) -> str:
    if "error" not in item:
        return "–"
    e = [float(x) for x in item["error"]]
    if not all(math.isfinite(x) for x in e):
        return "∞"
    ivs = item.get("error_interval")
    if ivs is None:
        return f"{e[0]:+.1%}, {e[1]:+.1%} ({NO_INTERVAL})"
    return ", ".join(percent_interval_text(x, _interval_pair(iv)) for x, iv in zip(e, ivs))


def _detail_row(method: str, item: dict) -> tuple[str, str, str, str]:
    """(reference, measured, error, steps) cells of one item of ``method``'s detail."""
    if method == "second order":
        ref = dynamics_cell(item.get("ideal"), None) + " (ideal sensor)"
        old_iv = (item.get("zeta_interval"), item.get("fn_interval")) if "zeta_interval" in item else None
        measured = dynamics_cell(item.get("measured"), old_iv)
        if "reason" in item and "error" not in item:
            measured = f"not scored: {item.get('status', 'failed')}: {item['reason']}".replace("|", "/")
        elif "error" not in item:
            measured = f"not scored: {item.get('status', 'failed')} (reference {item.get('reference', '?')})"
        return ref, measured, _errors_cell(item) if "error" in item else "not scored", "1"
    ref = target_cell(item.get("target"))
    steps = str(item.get("experiments", "–"))
    if item.get("outside"):
        near = item.get("nearest")
        return ref, f"outside the region (nearest {dynamics_cell(near)})", "–", "0"
    if "reason" in item or item.get("status", "ok") != "ok":
        return ref, f"not identifiable: {item.get('reason', item.get('status'))}".replace("|", "/"), "∞", steps
    measured = dynamics_cell(item.get("measured"), item.get("intervals"))
    return ref, measured, _errors_cell(item), steps


@dataclass
class Table:
    """The robustness table: ``scores[plant][method]`` (:class:`Score`), the targets per
    plant (the thesis's, prescribed, and those measured on the leg with their 90 %
    intervals) and the payload."""

    scores: dict
    targets: dict
    payload: float
    quick: bool

    def degraded(self) -> list[tuple[str, str, float, float]]:
        """(method, plant, worst error, worst error on the default plant) where a method
        degrades: worst error above :data:`DEGRADED` and above twice the default plant's."""
        ref = self.scores.get("default", {})
        out = []
        for plant, row in self.scores.items():
            if plant == "default":
                continue
            for method, s in row.items():
                base = ref.get(method)
                b = base.worst if base is not None else math.nan
                if s.worst > DEGRADED and not (s.worst <= 2 * b):
                    out.append((method, plant, s.worst, b))
        return out

    def _cell(self, method: str, s: Score) -> str:
        if not math.isfinite(s.worst):
            cell = "∞"
        elif method not in INTERVAL_METHODS:
            cell = f"{100 * s.median:.1f} / {100 * s.worst:.1f} %"
        elif s.median_interval is None and s.worst_interval is None:
            cell = f"{100 * s.median:.1f} / {100 * s.worst:.1f} % ({NO_INTERVAL})"
        else:
            cell = f"{error_text(s.median, s.median_interval, method)} / {error_text(s.worst, s.worst_interval, method)}"
        cell += f" ({s.experiments} exp.)"
        return cell + (f" — {s.note}" if s.note else "")

    def markdown(self) -> str:
        """Median / worst error per method (rows) and plant (columns), the errors of
        :data:`INTERVAL_METHODS` with their 90 % intervals, and the experiments used."""
        plants = list(self.scores)
        head = "| method | " + " | ".join(plants) + " |"
        lines = [head, "|---|" + "---|" * len(plants)]
        for method in METHODS:
            cells = [self._cell(method, self.scores[p][method]) if method in self.scores[p] else "—" for p in plants]
            lines.append(f"| {method} | " + " | ".join(cells) + " |")
        return "\n".join(lines)

    def detail_markdown(self) -> str:
        """Every item behind the cells of :data:`INTERVAL_METHODS`: its reference (the ideal
        sensor's reading, or the target), the measured (zeta, fn) with their 90 % intervals
        (or why the step is not a second-order step), the errors with their intervals and the
        steps it took."""
        lines = ["| method | plant | item | reference (ζ, fn [Hz]) | measured [90 % interval] | "
                 "error ζ, fn [90 % interval] | steps |", "|---|---|---|---|---|---|---|"]
        for method in INTERVAL_METHODS:
            for plant, row in self.scores.items():
                s = row.get(method)
                for key, item in (s.detail.items() if s is not None else ()):
                    if isinstance(item, dict):
                        cells = _detail_row(method, item)
                        lines.append(f"| {method} | {plant} | {key} | " + " | ".join(cells) + " |")
        return "\n".join(lines)

    def degraded_markdown(self) -> str:
        """Where a method degrades (:meth:`degraded`), its worst error there and on the
        default plant, each with its interval where it has one; "- none" when nowhere."""
        ref = self.scores.get("default", {})
        out = []
        for m, p, w, b in self.degraded():
            here, base = self.scores[p][m], ref.get(m)
            out.append(f"- {m} on {p}: worst {error_text(w, here.worst_interval, m)} (default plant "
                       f"{error_text(b, base.worst_interval if base is not None else None, m)})")
        return "\n".join(out) or "- none"

    def to_json(self) -> dict:
        try:
            commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                    cwd=Path(__file__).parent, timeout=10).stdout.strip() or None
        except (OSError, subprocess.SubprocessError):
            commit = None
        return {"payload": self.payload, "quick": self.quick, "targets": self.targets, "commit": commit,
                "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                "scores": {p: {m: vars(s) for m, s in row.items()} for p, row in self.scores.items()},
                "degraded": self.degraded()}


def run(plants=None, payload: float = 0.0, seed: int = 70, quick: bool = False, methods=METHODS,
        progress: bool = True) -> Table:
    """The robustness table over ``plants`` (default: every shipped plant)."""
    if plants is None:
        plants = plant_names()
    plants = list(plants)
    say = (lambda msg: print(f"  {msg}", flush=True)) if progress else None
    scores, targets = {}, {}
    for i, name in enumerate(plants):
        res = evaluate(name, payload=payload, seed=seed + i, quick=quick, methods=methods, progress=say)
        targets[name] = res.pop("targets")
        scores[name] = res
    return Table(scores, targets, payload, quick)


def write(table: Table, out_dir="reports/robustness") -> Path:
    """Write ``robustness.md`` and ``robustness.json`` to ``out_dir``; returns the .md path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    md = out / "robustness.md"
    text = [f"# Robustness table (payload {table.payload} kg{', quick' if table.quick else ''})", "",
            "Median / worst relative error (friction: against the plant's values; second order: against an "
            "ideal sensor; state feedback: RMS deviation from the design's simulation, % of the step; map, "
            "model, design: against the target) and the experiments used. Second order, map, model and design "
            "with the ranges their items' 90 % intervals allow.", "", table.markdown(), "",
            "Degrades (worst error above 5 % and above twice the default plant's):", "", table.degraded_markdown(),
            "", "## Every identified step behind the cells", "",
            "Measured (ζ, fn) with their 90 % intervals (the one classifier's; a step that is not a second-order "
            "step with its reason, no numbers), and the errors against the reference with theirs (the "
            "measurement's intervals relative to the reference).", "", table.detail_markdown()]
    md.write_text("\n".join(text) + "\n")
    (out / "robustness.json").write_text(json.dumps(table.to_json(), indent=1, default=float))
    return md


# ---------------------------------------------------------------------------------------
# tune on every plant and payload (notebook 05)
# ---------------------------------------------------------------------------------------

@dataclass
class DesignRow:
    """One :func:`leglib.design.tuning.tune` call of :func:`design_study`."""

    plant: str
    payload: float
    target: tuple
    source: str            # "thesis" or the gains the target was measured at
    design: object = field(repr=False)   # None when the leg could not be prepared
    failure: str | None = None           # why there is no design (e.g. the calibration failed)
    #: the 90 % intervals ((zeta low, high), (fn low, high) [Hz]) of a target measured on the
    #: leg; None for the thesis's (prescribed, exact)
    target_intervals: tuple | None = None

    @property
    def error(self) -> tuple:
        return self.design.error

    @property
    def final(self):
        """The :class:`leglib.design.points.PointResult` of the design's final check."""
        return _final_check(self.design)

    @property
    def error_interval(self) -> tuple:
        """90 % intervals of :attr:`error` (the final check's relative to the target)."""
        return self.design.error_interval

    def scored(self) -> tuple[tuple, tuple]:
        """(errors, their intervals) as a validation counts them: the final check's relative
        errors and intervals, infinite when it is not a second-order step (never dropped)."""
        if self.final.status != STATUS_OK:
            return (math.inf, math.inf), ((math.inf, math.inf),) * 2
        return self.error, self.error_interval

    def target_text(self) -> str:
        """The target: the thesis's (prescribed) or measured, with its intervals and where."""
        if self.target_intervals is None:
            return f"({self.target[0]:.3f}, {self.target[1]:.2f}), {self.source}"
        return f"{dynamics_text(*self.target, *self.target_intervals, zeta_name='ζ')}, {self.source}"

    @property
    def experiments(self) -> int:
        return len(self.design.experiments)


def design_study(plants=None, payloads=(0.0, 0.3), n_targets: int = 4, seed: int = 90,
                 max_experiments: int = 10, progress: bool = True) -> list[DesignRow]:
    """:func:`leglib.design.tuning.tune` for the thesis's target and ``n_targets`` targets
    measured at :data:`TARGET_GAINS` on each leg, on every plant (default: every shipped
    one) and payload [kg]; one fresh virtual device per (plant, payload)."""

    if plants is None:
        plants = plant_names()
    plants = list(plants)
    rows = []
    k = 0
    for name in plants:
        for payload in payloads:
            dev = connect("virtual", seed=seed + k, plant=load_plant(name, payload_mass=float(payload)))
            k += 1
            try:
                configure(dev)
                try:
                    calibrate(dev)
                except ExperimentError as exc:
                    # a leg that does not calibrate (e.g. stick-slip under a payload moves the
                    # scan more than calib_range from cpr / pole_pairs) is a row with its reason
                    rows.append(DesignRow(name, float(payload), tuple(map(float, THESIS_TARGET)), "thesis",
                                          None, f"calibration failed: {exc}"))
                    if progress:
                        print(f"  {name:8s} payload {payload:.2f} kg: calibration failed", flush=True)
                    continue
                targets = [(THESIS_TARGET, "thesis", None)]
                for g in TARGET_GAINS[:n_targets]:
                    m = _measure(dev, g)
                    if m is not None:
                        targets.append((_pair(m), m["source"], (tuple(m["zeta_interval"]), tuple(m["fn_interval_hz"]))))
                for tgt, src, iv in targets:
                    d = tune(dev, *tgt, max_experiments=max_experiments)
                    row = DesignRow(name, float(payload), tuple(map(float, tgt)), src, d, target_intervals=iv)
                    rows.append(row)
                    if progress:
                        print(f"  {name:8s} payload {payload:.2f} kg, target {row.target_text()}: "
                              f"{len(d.experiments)} experiments, error {_design_errors_text(row)}"
                              + ("" if d.reached else " (not reached)"), flush=True)
            finally:
                dev.close()
    return rows


def _design_errors_text(row: DesignRow) -> str:
    """A design's errors (zeta, fn) with their 90 % intervals, or why its final check has none."""
    final = row.final
    if final.status != STATUS_OK:
        return f"none: the final check is {final.status}: {final.reason or final.status}".replace("|", "/")
    return ", ".join(percent_interval_text(e, iv) for e, iv in zip(row.error, row.error_interval))


def design_summary(rows) -> dict:
    """Per (plant, payload): median and worst |error| (zeta and fn together; infinite for a
    final check that is not a second-order step) with the ranges their 90 % intervals allow
    (``median_interval``, ``worst_interval``: :func:`leglib.design.validation.error_statistics`),
    the largest number of experiments, targets reached (the final check's 90 % intervals within
    the tolerance), targets whose intervals are wider than the tolerance (``undecided``: the
    model error is larger than it); and "all" over every row."""
    groups: dict = {}
    for r in rows:
        if r.design is not None:
            groups.setdefault(f"{r.plant}, {r.payload:g} kg", []).append(r)
    designed = [r for r in rows if r.design is not None]
    if designed:
        groups["all"] = designed
    out = {}
    for key, rs in groups.items():
        scored = [r.scored() for r in rs]
        st = error_statistics([e for es, _ in scored for e in es], [iv for _, ivs in scored for iv in ivs])
        out[key] = {"median": st["median"], "worst": st["worst"], "median_interval": st["median_interval"],
                    "worst_interval": st["worst_interval"],
                    "max_experiments": int(max(r.experiments for r in rs)),
                    "reached": int(sum(r.design.reached for r in rs)),
                    "undecided": int(sum("cannot be told" in r.design.verdict for r in rs)), "targets": len(rs)}
    failed = [f"{r.plant}, {r.payload:g} kg" for r in rows if r.design is None]
    if failed:
        out["not prepared"] = {"legs": failed, "reasons": [r.failure for r in rows if r.design is None]}
    return out


def design_study_markdown(rows) -> str:
    """The rows of :func:`design_study` and their :func:`design_summary` as two Markdown
    tables; a leg that could not be prepared is a row with its reason."""
    lines = ["| plant | payload [kg] | target (ζ, fn [Hz]) [90 % interval] | from | measured [90 % interval] | "
             "error ζ, fn [90 % interval] | experiments |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        tgt = (f"({r.target[0]:.3f}, {r.target[1]:.2f}), prescribed" if r.target_intervals is None else
               dynamics_text(*r.target, *r.target_intervals, zeta_name="ζ"))
        head = f"| {r.plant} | {r.payload:g} | {tgt} | {r.source} | "
        if r.design is None:
            lines.append(head + f"— | {r.failure.replace('|', '/')} | 0 |")
            continue
        final = r.final
        meas = (dynamics_text(final.zeta, final.fn, final.zeta_interval, final.fn_interval, zeta_name="ζ")
                if final.status == STATUS_OK else f"{final.status}: {final.reason or final.status}".replace("|", "/"))
        err = _design_errors_text(r) if final.status == STATUS_OK else "∞"
        lines.append(head + f"{meas} | {err} | {r.experiments}{'' if r.design.reached else ' (not reached)'} |")
    summary = design_summary(rows)
    lines += ["", "| plant, payload | median error [90 % interval] | worst error [90 % interval] | most experiments | "
                  "reached |", "|---|---|---|---|---|"]
    for k, v in summary.items():
        if k != "not prepared":
            lines.append(f"| {k} | {error_text(v['median'], v['median_interval'], 'design')} | "
                         f"{error_text(v['worst'], v['worst_interval'], 'design')} | {v['max_experiments']} | "
                         f"{v['reached']}/{v['targets']} |")
    return "\n".join(lines)


def parse_plants(text: str, name: str = "design_plants") -> list[str]:
    """"all" (every shipped plant) or comma-separated plant names; an unknown name is an
    error naming ``name`` and the known plants."""
    known = plant_names()
    if not isinstance(text, str) or not text.strip():
        raise ParameterError(f"{name} must be 'all' or comma-separated plant names ({', '.join(known)}), got {text!r}")
    if text.strip() == "all":
        return list(known)
    out = [p.strip() for p in text.split(",") if p.strip()]
    bad = [p for p in out if p not in known]
    if bad:
        raise ParameterError(f"{name}: unknown plant(s) {bad}; shipped plants: {', '.join(known)}")
    return out


def parse_payloads(text: str, name: str = "design_payloads", high: float = 5.0) -> list[float]:
    """Comma-separated foot payloads [kg] in [0, ``high``]; errors name ``name``."""
    try:
        vals = [float(x) for x in str(text).split(",") if x.strip()]
    except ValueError:
        raise ParameterError(f"{name} must be comma-separated payloads in kg, e.g. '0, 0.3', got {text!r}") from None
    if not vals or not all(math.isfinite(v) and 0.0 <= v <= high for v in vals):
        raise ParameterError(f"{name}: payloads must be finite, in [0, {high:g}] kg, at least one; got {text!r}")
    return vals


def load_table(path) -> dict:
    """A robustness table written by :func:`write` (``robustness.json``), with a clear error
    when it is missing or not one."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no robustness table; write one with `make robustness`")
    try:
        doc = json.loads(p.read_text())
        doc["scores"], doc["payload"]
    except (json.JSONDecodeError, KeyError, TypeError) as exc:
        raise ValueError(f"{p}: not a robustness table ({exc})") from None
    return doc


# the code a robustness table's numbers depend on (the methods, the twin they run on, the
# parameters), relative to the repository; a commit touching any of them makes a table older
TABLE_DEPENDS_ON = ("leglib/identify", "leglib/design", "leglib/twin", "leglib/device", "leglib/experiments",
                    "leglib/model", "leglib/evaluation", "leglib/params", "leglib/thesis.py")


def staleness(doc: dict, repo=None) -> str | None:
    """Whether a table written by :func:`write` (its ``commit``) is older than the code it
    depends on (:data:`TABLE_DEPENDS_ON`) in the git checkout ``repo`` (default: the one
    leglib runs from): :func:`leglib._version.staleness`, the one check every result read
    from a file goes through. None when no commit since changed that code; else a sentence
    to show beside the table."""
    return _staleness(doc.get("commit"), TABLE_DEPENDS_ON, what="This table", code="the code it scores",
                      rerun="Rerun `make robustness` for a current table.", repo=repo)


def table_from_json(doc: dict) -> Table:
    """The :class:`Table` of a document :func:`load_table` read. A table written before the
    intervals were stored loads too: its cells and items then say "no interval recorded"
    wherever they show a number of :data:`INTERVAL_METHODS` (:func:`error_text`,
    :func:`dynamics_cell`), never a bare number as if it had none."""
    scores = {p: {m: Score(**v) for m, v in row.items()} for p, row in doc["scores"].items()}
    return Table(scores, doc.get("targets", {}), doc["payload"], doc.get("quick", False))
