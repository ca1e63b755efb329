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
from ..design.points import identify_response
from ..design.tuning import tune
from ..design.validation import Validation, validate
from ..device.session import connect
from ..device.setup import calibrate, configure
from ..errors import ExperimentError, ParameterError
from ..experiments.step import _responses_from_batch, return_to_rest, step_response
from ..experiments.sweep import thesis_grid
from ..experiments.torque import friction_experiment, play_torque_table
from ..params import load_plant, plant_names
from ..twin.host import Twin
from ..units import dynamics_text

THESIS_TARGET = (0.24, 5.0)
#: gains at which the further targets are measured on each leg (moderate, stable)
TARGET_GAINS = ((30.0, 0.05, 0.01), (45.0, 0.09, 0.01), (25.0, 0.12, 0.01), (60.0, 0.06, 0.01))
METHODS = ("friction", "second order", "state feedback: playback", "state feedback: live", "map", "model", "design")
#: evaluation budget of the friction fit (a plant it cannot describe can keep it searching for minutes)
FRICTION_NFEV = 200
#: a method "degrades" on a plant when its error there exceeds this and twice its default-plant error
DEGRADED = 0.05


@dataclass
class Score:
    """One method on one plant: ``median`` and ``worst`` relative errors (fractions),
    ``experiments`` the device experiments it took, ``detail`` per item, ``note`` anything
    the numbers do not say (outside the region, not identifiable)."""

    median: float
    worst: float
    experiments: int
    detail: dict = field(default_factory=dict)
    note: str = ""
    seconds: float = math.nan


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


def _measure(dev, gains):
    p = identify_response(step_response(dev, *gains), dev.leg)
    return (p.zeta, p.fn) if p.status == "ok" else (math.nan, math.nan)


def _score(v: Validation, seconds: float) -> Score:
    """A :class:`Validation` as a table cell: its median and worst error (infinite for a
    target that is not identifiable), experiments, each target's detail."""
    s = v.summary()
    detail, notes = {}, []
    for k, r in enumerate(v.rows, 1):
        if r.outside:
            detail[f"target {k}"] = {"target": r.target, "outside": True, "nearest": r.nearest}
            notes.append(f"target {k} outside the region")
            continue
        m = (r.measured.zeta, r.measured.fn) if r.identified else (math.nan, math.nan)
        detail[f"target {k}"] = {"target": r.target, "gains": r.gains, "measured": m, "error": r.error,
                                 "error_interval": r.error_interval, "experiments": r.experiments,
                                 **({"note": r.note} if r.note else {})}
        if not r.identified:
            notes.append(f"target {k} not identifiable")
    return Score(s["median"], s["worst"], experiments=s["experiments"], detail=detail, note="; ".join(notes),
                 seconds=seconds)


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
        targets = [THESIS_TARGET] + [m for m in (_measure(dev, g) for g in TARGET_GAINS[:n_targets])
                                     if np.all(np.isfinite(m))]
        out["targets"] = targets
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
            errs, detail, flagged = [], {}, 0
            for g, ref in zip(gains, ideal):
                p = identify_response(step_response(dev, *g), leg)
                r = identify_response(ref, leg)
                if p.status != "ok" or r.status != "ok":
                    flagged += 1
                    detail[str(tuple(g))] = {"status": p.status, "reference": r.status, "reason": p.reason}
                    continue
                e = (_rel(p.zeta, r.zeta), _rel(p.fn, r.fn))
                errs.extend(e)
                detail[str(tuple(g))] = {"measured": (p.zeta, p.fn), "ideal": (r.zeta, r.fn), "error": e,
                                         "zeta_interval": p.zeta_interval, "fn_interval": p.fn_interval,
                                         "ideal_inside": bool(p.zeta_interval[0] <= r.zeta <= p.zeta_interval[1]
                                                              and p.fn_interval[0] <= r.fn <= p.fn_interval[1]),
                                         "r2": p.r2}
            out["second order"] = Score(*_stats(errs), experiments=len(gains), detail=detail,
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
            out["map"] = _score(v, time.perf_counter() - t0)
        if "model" in methods:
            t0 = time.perf_counter()
            say(f"{plant_name}: model-based inverse (fit_leg_plant)")
            fg = fitting_gains(5)
            model = fit_leg_plant([step_response(dev, *g) for g in fg], dev.config, load_plant("default"))
            def model_gains(tg):
                gains, predicted = model.gains_for(*tg)
                return gains, 0, predicted, ""
            v = validate(dev, targets, model_gains, "model", setup_experiments=len(fg))
            out["model"] = _score(v, time.perf_counter() - t0)
        if "design" in methods:
            t0 = time.perf_counter()
            say(f"{plant_name}: design")
            errs, detail, counts = [], {}, []
            for k, tgt in enumerate(targets, 1):
                d = tune(dev, *tgt, max_experiments=10)
                errs.extend(d.error)
                counts.append(len(d.experiments))
                detail[f"target {k}"] = {"target": tgt, "gains": d.gains, "measured": d.measured,
                                         "intervals": d.intervals, "error": d.error,
                                         "experiments": len(d.experiments), "reached": d.reached,
                                         "verdict": d.verdict}
            out["design"] = Score(*_stats(errs), experiments=int(sum(counts)), detail=detail,
                                  note=f"experiments per target: median {np.median(counts):.0f}, max {max(counts)}",
                                  seconds=time.perf_counter() - t0)
    finally:
        dev.close()
    return out


@dataclass
class Table:
    """The robustness table: ``scores[plant][method]`` (:class:`Score`), the targets per
    plant and the payload."""

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

    def markdown(self) -> str:
        plants = list(self.scores)
        head = "| method | " + " | ".join(plants) + " |"
        lines = [head, "|---|" + "---|" * len(plants)]
        for method in METHODS:
            cells = []
            for p in plants:
                s = self.scores[p].get(method)
                if s is None:
                    cells.append("—")
                    continue
                cell = ("∞" if not math.isfinite(s.worst) else f"{100 * s.median:.1f} / {100 * s.worst:.1f} %")
                cell += f" ({s.experiments} exp.)"
                if s.note:
                    cell += f" — {s.note}"
                cells.append(cell)
            lines.append(f"| {method} | " + " | ".join(cells) + " |")
        return "\n".join(lines)

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
    deg = table.degraded()
    text = [f"# Robustness table (payload {table.payload} kg{', quick' if table.quick else ''})", "",
            "Median / worst relative error (friction: against the plant's values; second order: against an "
            "ideal sensor; state feedback: RMS deviation from the design's simulation, % of the step; map, "
            "model, design: against the target) and the experiments used.", "", table.markdown(), "",
            "Degrades (worst error above 5 % and above twice the default plant's):", ""]
    text += [f"- {m} on {p}: worst {100 * w:.1f} % (default plant {100 * b:.1f} %)" for m, p, w, b in deg] or ["- none"]
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

    @property
    def error(self) -> tuple:
        return self.design.error

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
                targets = [(THESIS_TARGET, "thesis")]
                for g in TARGET_GAINS[:n_targets]:
                    m = _measure(dev, g)
                    if np.all(np.isfinite(m)):
                        targets.append((m, f"measured at {g[0]:g}, {g[1]:g}, {g[2]:g}"))
                for tgt, src in targets:
                    d = tune(dev, *tgt, max_experiments=max_experiments)
                    rows.append(DesignRow(name, float(payload), tuple(map(float, tgt)), src, d))
                    if progress:
                        print(f"  {name:8s} payload {payload:.2f} kg, target ({tgt[0]:.3f}, {tgt[1]:.2f} Hz): "
                              f"{len(d.experiments)} experiments, error {d.error[0]:+.1%} / {d.error[1]:+.1%}"
                              + ("" if d.reached else " (not reached)"), flush=True)
            finally:
                dev.close()
    return rows


def design_summary(rows) -> dict:
    """Per (plant, payload): median and worst |error| (zeta and fn together), the largest
    number of experiments, targets reached (the final check's 90 % intervals within the
    tolerance), targets whose intervals are wider than the tolerance (``undecided``: the
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
        e = np.abs(np.array([r.error for r in rs], float))
        out[key] = {"median": float(np.median(e)), "worst": float(np.max(e)),
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
    lines = ["| plant | payload [kg] | target (ζ, fn [Hz]) | from | measured [90 % interval] | error ζ, fn | "
             "experiments |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        head = f"| {r.plant} | {r.payload:g} | ({r.target[0]:.3f}, {r.target[1]:.2f}) | {r.source} | "
        if r.design is None:
            lines.append(head + f"— | {r.failure.replace('|', '/')} | 0 |")
            continue
        d = r.design
        lines.append(head + dynamics_text(*d.measured, *d.intervals, zeta_name="ζ") + " | "
                     f"{d.error[0]:+.1%}, {d.error[1]:+.1%} | {r.experiments}{'' if d.reached else ' (not reached)'} |")
    summary = design_summary(rows)
    lines += ["", "| plant, payload | median error | worst error | most experiments | reached |", "|---|---|---|---|---|"]
    for k, v in summary.items():
        if k != "not prepared":
            lines.append(f"| {k} | {v['median']:.1%} | {v['worst']:.1%} | {v['max_experiments']} | "
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
    scores = {p: {m: Score(**v) for m, v in row.items()} for p, row in doc["scores"].items()}
    return Table(scores, doc.get("targets", {}), doc["payload"], doc.get("quick", False))
