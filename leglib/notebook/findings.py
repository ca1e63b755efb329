"""Each notebook's "What we found", written from its metrics JSON.

A notebook writes its metrics (:func:`leglib.notebook.setup.write_metrics`) and then shows
:func:`render` of them, so its conclusions are made of the numbers its cells computed and
cannot contradict them. :func:`unquoted` is the check: every number a text quotes must be
one of the metrics' values as printed (references such as "eq. 5.11" or "Listing 7.7" are
not quotes).
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

from ..evaluation.robustness import error_text, worst_of
from ..identify.friction import FrictionFit, LegFrictionFit
from ..units import dynamics_text, interval_text, percent_interval_text, significant


def read_metrics(path) -> dict:
    """A notebook's metrics JSON (the file :func:`leglib.notebook.setup.write_metrics` wrote)."""
    p = Path(path)
    try:
        return json.loads(p.read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"{p}: no metrics file; the notebook's metrics cell writes it") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{p}: not a metrics file ({exc})") from None


def _dyn(d: dict, zeta: str = "zeta", fn: str = "fn") -> str:
    """ "zeta 0.24 [0.17, 0.31], fn 5.0 [4.5, 5.6] Hz" of a metrics dict's values and intervals."""
    return dynamics_text(d[zeta], d[fn], d[f"{zeta}_interval"], d[f"{fn}_interval"])


def _pct(x: float, digits: int = 1, sign: bool = True) -> str:
    return f"{100 * x:{'+' if sign else ''}.{digits}f} %"


def _listing(th: dict, zeta: str = "zeta", f: str = "f_hz") -> str:
    """ "zeta 0.0460 [0.0458, 0.0462] at 4.67 [4.6, 4.8] Hz" of a Listing 7.7 reading's metrics
    (its 90 % intervals, :class:`leglib.identify.listing77.ReadingIntervals`)."""
    return (f"zeta {interval_text(th[zeta], th[f'{zeta}_interval'])} at "
            f"{interval_text(th[f], th[f.replace('_hz', '') + '_interval'])} Hz")


def _reach(reach: dict) -> str:
    """ "0.0460 [0.0458, 0.0462] (90 % interval; no usable reading's interval reaches above
    0.0463)": Listing 7.7's largest reading over a sweep with its doubt."""
    text = interval_text(reach["max_thesis_zeta"], reach.get("max_thesis_zeta_interval"))
    upper = reach.get("max_thesis_zeta_upper", math.nan)
    if math.isfinite(upper):
        text += f" (90 % interval; no usable reading's interval reaches above {significant(upper, 3)})"
    return text


# ---------------------------------------------------------------------------------------
# 01: the derivation
# ---------------------------------------------------------------------------------------

def derivation(m: dict) -> str:
    """Notebook 01: what the derivation reproduces (eq. 5.11 only for the thesis's leg), the
    thesis's inconsistencies, and which of the thesis's numbers the virtual leg reproduces
    and which it cannot."""
    out = []
    err = m["eq511_max_rel_error"]
    if m["leg_is_thesis"] and err < 0.01:
        out.append(f"- With the thesis's leg (`{m['leg_file_name']}`) the derivation reproduces eq. 5.11 to a largest "
                   f"relative error of {err:.1e}.")
    elif m["leg_is_thesis"]:
        out.append(f"- With the thesis's leg the derivation does **not** reproduce eq. 5.11: largest relative error "
                   f"{err:.1e}.")
    else:
        out.append(f"- This leg (`{m['leg_file_name']}`) is not the thesis's: its linearization differs from eq. 5.11 "
                   f"by up to {err:.1e} (relative). Eq. 5.11 is the thesis's leg's; it is reproduced only with the "
                   f"shipped `leg_thesis.toml`.")
    a33 = m["printed_A33"]
    out.append(f"- A as printed (`A[3,3]` = {a33:+.2f}) has an eigenvalue with real part "
               f"{m['printed_A_max_real_eig']:+.1f} 1/s: unstable; with {-a33:+.2f} the largest real part is "
               f"{m['corrected_A_max_real_eig']:+.2f} 1/s.")
    out.append(f"- Near the operating point the linear model follows the nonlinear one to "
               f"{significant(m['linear_vs_nonlinear_rms_deg'], 2)} deg RMS over "
               f"{m['linear_vs_nonlinear_travel_deg']:.2f} deg of travel.")
    out.append(f"- The thesis's parallelogram model (a) and the exact five-bar (b) differ in inertia by "
               f"{_pct(m['inertia_rel_difference_median'], sign=False)} (median) up to "
               f"{_pct(m['inertia_rel_difference_max'], sign=False)} over the working range.")
    mm = m["mismatch"]
    model, true = mm["model"], mm["thesis_result_as_true"]
    twin = m["twin_plant_model"]
    damped = (f"zeta {model['zeta']:.2f} at fn {model['fn']:.2f} Hz" if math.isfinite(model["zeta"])
              else "no second-order step")
    out.append(f"- **The chapter-5/6 mismatch.** With chapter 5's damping ({mm['viscous']:.3f} N m s/rad at the "
               f"joint) one cascade axis on this leg steps with {damped} at Fig. 6.9's gains; the thesis's "
               f"validated reading (zeta {mm['thesis_result']['zeta']:.3f} at {mm['thesis_result']['f_hz']:.2f} Hz by "
               f"Listing 7.7) is, as an ideal {mm['step_deg']:.0f} deg step, a true zeta of {true['zeta']:.3f}: the leg it measured was "
               f"damped far less than chapter 5's model.")
    out.append(f"- **What the virtual leg reproduces, and what it cannot.** The twin's plant is built with little "
               f"damping ({twin['viscous']:.4f} N m s/rad, {m['twin_plant_name']} plant) and Coulomb friction: "
               f"the same model gives zeta {twin['model']['zeta']:.2f} at Fig. 6.9's gains, so it reproduces the "
               f"direction of the mismatch (far below chapter 5's damping) in the true measure. It does not reproduce "
               f"the thesis's measured response itself: that true zeta of {true['zeta']:.3f} is far below the twin's, "
               f"and Listing 7.7 reads the twin's steps far below the thesis's {mm['thesis_result']['zeta']:.3f} "
               f"(notebook 05 measures by how much).")
    return "\n".join(out)


# ---------------------------------------------------------------------------------------
# 02: friction and the second-order identification
# ---------------------------------------------------------------------------------------

def friction(m: dict) -> str:
    """Notebook 02: the friction fit (values with intervals, or not identifiable), the single
    joint's, and the Fig. 6.9 step in both measures."""
    out = [f"- The identified five-bar reproduces the measured angles to {significant(max(m['rms_deg']), 2)} deg RMS "
           f"(nominal model before: {significant(max(m['rms_before_deg']), 2)} deg); preferred friction model: "
           f"{m['preferred_model']}."]
    f = m["friction"]
    for name in ("viscous1", "viscous2", "coulomb1", "coulomb2"):
        if name in f["not_identifiable"]:
            out.append(f"- {name}: not identifiable: {f['not_identifiable'][name]}")
    shown = [f"{k} {interval_text(f['params'][k], f['intervals'][k], LegFrictionFit.UNITS[k])}"
             for k in ("viscous1", "viscous2", "coulomb1", "coulomb2") if k not in f["not_identifiable"]]
    if shown:
        out.append("- Friction per joint (90 % intervals): " + ", ".join(shown) + ".")
    if m["recovery_rel_error"]:
        worst = max(m["recovery_rel_error"], key=lambda k: abs(m["recovery_rel_error"][k]))
        out.append(f"- Against the twin's hidden truth the largest relative error is "
                   f"{_pct(m['recovery_rel_error'][worst])} ({worst}).")
    sj = m["single_joint"]
    if sj:
        parts = []
        for name in ("coulomb", "viscous", "inertia"):
            why = sj["not_identifiable"].get(name)
            parts.append(f"{name}: not identifiable ({why})" if why else
                         f"{name} {interval_text(sj[name], sj['intervals'][name], FrictionFit.UNITS[name])}")
        out.append(f"- The single-joint fit, from {sj['directions']} direction(s): " + "; ".join(parts) + ".")
    s = m["step_fit"]
    out.append(f"- The Fig. 6.9 step identifies as {_dyn(s)} (90 % intervals; R² {s['r2']:.3f}).")
    th = m["step_thesis_reading"]
    if not th["usable"]:
        out.append(f"- Listing 7.7 gives no reading of the same step: **the listing fails here**: {th['problem']}.")
    elif th["problem"]:
        out.append(f"- Listing 7.7 on the same step reads {_listing(th)} (90 % intervals) from its first two peaks, "
                   f"which are the oscillation's, but **the listing fails here**: {th['problem']}.")
    else:
        out.append(f"- Listing 7.7 on the same step reads {_listing(th)} (90 % intervals; its own, biased measure).")
    return "\n".join(out)


# ---------------------------------------------------------------------------------------
# 03: the thesis's design played back
# ---------------------------------------------------------------------------------------

def thesis_playback(m: dict) -> str:
    """Notebook 03, section 2: the thesis design's torque table played back on the leg
    against its nonlinear model (Figs. 5.6, 5.7), and what in the design model explains the
    difference, from ``m``: ``model`` and ``playback``
    (:func:`leglib.design.statefeedback.response_metrics` of the two runs), ``viscous``
    (the design model's joint damping [N*m*s/rad]), ``k22_listing`` and ``k22_exact``
    (joint 2's gravity stiffness [N*m/rad] in Listing 7.5's decoupled form and the exact
    five-bar, :func:`leglib.thesis.g2_sign_check`) and ``step_deg``. The thesis saw the leg
    run up faster than its model and both end beyond the setpoint; whether this leg does
    is read off the runs."""
    sim, play = m["model"], m["playback"]
    faster = math.isfinite(play["rise_time"]) and math.isfinite(sim["rise_time"]) and play["rise_time"] < sim["rise_time"]
    rise = (f"rises in {play['rise_time']:.3f} s against the model's {sim['rise_time']:.3f} s"
            if math.isfinite(play["rise_time"]) and math.isfinite(sim["rise_time"]) else
            "does not reach 90 % of the step" if not math.isfinite(play["rise_time"]) else
            f"rises in {play['rise_time']:.3f} s; the model never reaches 90 % of the step")
    both_over = play["overshoot_pct"] > 0 and sim["overshoot_pct"] > 0
    same = faster and both_over
    out = [f"{'As in the thesis' if same else 'Unlike the thesis (Figs. 5.6, 5.7: faster than the model, both beyond the setpoint)'}"
           f", the leg played back {rise} and overshoots by {play['overshoot_pct']:.1f} % (the model "
           f"{sim['overshoot_pct']:.1f} %); it ends {play['final_error_pct']:.2f} % of the step from the setpoint (the "
           f"model {sim['final_error_pct']:.2f} %)."]
    rel = m["k22_listing"] / m["k22_exact"] - 1
    out.append(f"The design model holds chapter 5's joint damping ({m['viscous']:.3f} N·m·s/rad) and is Listing 7.5's "
               f"decoupled form: its gravity stiffness on joint 2 (the listing's +m4·lc4, the sign this geometry "
               f"supports) is {m['k22_listing']:.3f} N·m/rad, {_pct(abs(rel), 0, False)} "
               f"{'above' if rel > 0 else 'below'} the exact five-bar's {m['k22_exact']:.3f}, and it drops the "
               f"joints' coupling, so Nbar misjudges the torque a {m['step_deg']:g}° step needs.")
    return " ".join(out)


# ---------------------------------------------------------------------------------------
# 04: the sweep and the map
# ---------------------------------------------------------------------------------------

def sweeps(m: dict) -> str:
    """Notebook 04: what the sweep identified, the achievable region, the thesis's target in
    both measures and what Listing 7.7 reads of the sweep."""
    c = m["counts"]
    out = [f"- {m['points']} steps: {c.get('ok', 0)} second-order steps, {c.get('unstable', 0)} unstable, "
           f"{c.get('failed', 0)} failed (not second-order steps, each with its reason; "
           f"{m['failed_not_reaching']} of them end more than half the step short of their commanded final value)."]
    if m["achievable"]:
        out.append(f"- Achievable: zeta {m['zeta_range'][0]:.2f} to {m['zeta_range'][1]:.2f}, fn "
                   f"{m['fn_range'][0]:.2f} to {m['fn_range'][1]:.2f} Hz ({m['achievable']} fine-grid points).")
    else:
        out.append("- The map has no achievable region: no grid cell has all its corners identified.")
    t = m["thesis_target_nearest"]
    if t:
        out.append(f"- The thesis's numbers ({t['target'][0]:.2f}, {t['target'][1]:g} Hz) taken as true zeta and fn are "
                   f"{'inside' if t['inside'] else 'outside'} this region; the map's nearest point: "
                   f"{_dyn(t)} (90 % intervals).")
    reach = m["listing_reach"]
    if reach["points"]:
        out.append(f"- In the thesis's measure Listing 7.7 reads at most zeta {_reach(reach)} over the "
                   f"{reach['points']} points with a usable reading; the thesis read {reach['thesis_result_zeta']:.3f} "
                   f"on its leg.")
    b = m["thesis_reading_bias"]["grid"]
    fails = b["ripple"] + b["flagged"] + b.get("unresolved", 0)
    if fails:
        out.append(f"- Listing 7.7 fails outright on {fails} of the second-order steps (its second peak is the "
                   f"settled tail's ripple, fewer than two peaks, or two peaks its noise does not tell apart: no "
                   f"reading, no interval) and counts more peaks than cycles on {b['many_peaks']} more.")
    if b["points"]:
        z = b["zeta_rel_error_min_median_max"]
        out.append(f"- Where both measures read a step, Listing 7.7's zeta lies {_pct(z[1])} (median) from the true "
                   f"zeta ({_pct(z[0])} to {_pct(z[2])}).")
    return "\n".join(out)


# ---------------------------------------------------------------------------------------
# 05: validation
# ---------------------------------------------------------------------------------------

def validation(m: dict) -> str:
    """Notebook 05: first the thesis-measure result (what Listing 7.7 reads on the twin at
    most, against the thesis's 0.229), then the thesis's target in the true measure with
    its interval and verdict, the methods' errors with their intervals, and the design study."""
    out = []
    tm = m["thesis_measure"]
    reach = tm["listing_reach"]
    target = tm["target"]
    th = m["thesis_reading"]
    if th["usable"]:
        step = (f"The step at the gains nearest the target reads {_listing(th)} (90 % intervals), "
                f"{percent_interval_text(tm['error_zeta'], tm['error_zeta_interval'])} from the target's zeta.")
    else:
        step = f"Listing 7.7 gives no reading of the step at the gains nearest the target: {th['problem']}."
    if tm["reached"]:
        out.append(f"- **In the thesis's own measure** the twin reaches the thesis's target (zeta {target['zeta']:.2f} "
                   f"at {target['f_hz']:.2f} Hz by Listing 7.7): {tm['verdict']} (tolerance "
                   f"{_pct(tm['tolerance'], 0, False)}). {step}")
    elif reach["points"]:
        out.append(f"- **In the thesis's own measure the twin does not reproduce the thesis.** Listing 7.7 reads at "
                   f"most zeta {_reach(reach)} on any of the {reach['points']} swept points with a "
                   f"usable reading, where the thesis measured {reach['thesis_result_zeta']:.3f} on its leg and "
                   f"targeted {target['zeta']:.2f}: the twin's least-damped second-order steps (true zeta "
                   f"{reach['min_true_zeta']:.2f}) decay too fast between the first two peaks. {step}")
    else:
        out.append("- **In the thesis's own measure** Listing 7.7 reads no swept point of the twin: it fails on "
                   "every one.")
    t = m["thesis_target"]
    out.append(f"- Taken as true zeta and fn, the thesis's target ({t['target'][0]:.2f}, {t['target'][1]:g} Hz) is "
               f"{'inside' if t['inside_region'] else 'outside'} the map's achievable region; the map's gains give "
               f"{_dyn(t)} (90 % intervals), {_pct(t['error_zeta'])} and {_pct(t['error_fn'])} from the target; "
               f"{t['verdict']} (tolerance {_pct(t['tolerance'], 0, False)}).")
    for method, v in m["summary"].items():
        reached = (f"; {v['reached']} reached within {_pct(v['tolerance'], 0, False)} by their intervals, "
                   f"{v['undecided']} with intervals wider than that" if "reached" in v else "")
        out.append(f"- {method}: median error {_pct(v['median'], sign=False)}, worst {_pct(v['worst'], sign=False)} "
                   f"(the 90 % intervals allow up to {_pct(v['worst_bound'], sign=False)}) over {v['targets']} "
                   f"targets, {v['unidentified']} not identifiable, {v['experiments']} experiments{reached}.")
    outside = m["summary"]["map"]["outside_region"] if "map" in m["summary"] else 0
    if outside:
        out.append(f"- {outside} target(s) outside the map's region: the map has no answer there.")
    d = m["design_study"]
    if d and "all" in d:
        a = d["all"]
        out.append(f"- tune on {m['design_plants']} plant(s): median error "
                   f"{error_text(a['median'], a.get('median_interval'), 'design')}, worst "
                   f"{error_text(a['worst'], a.get('worst_interval'), 'design')}"
                   f"{' (the ranges their intervals allow)' if a.get('worst_interval') is not None else ''}, "
                   f"at most {a['max_experiments']} experiments per target; "
                   f"{a['reached']} of {a['targets']} targets confirmed within the tolerance by their intervals, "
                   f"{a['undecided']} with intervals wider than the tolerance (the response's model error is larger "
                   f"than it).")
    return "\n".join(out)


# ---------------------------------------------------------------------------------------
# the robustness table (notebook 05, section 4)
# ---------------------------------------------------------------------------------------

#: the methods of the robustness table that rest on a structure they identify (and a leg can
#: lack), with what that structure is; the others measure the leg
STRUCTURE = {
    "friction": "**Friction identification** (notebook 02) fits tanh Coulomb + viscous friction on a rigid "
                "five-bar",
    "state feedback: live": "**State feedback run live** (notebook 03) closes the loop with the identified leg's "
                            "linear model",
    "state feedback: playback": "**The played-back torque table** (notebook 03) is the identified leg's model run "
                                "open loop",
    "model": "**The fitted leg model** (`fit_leg_plant`) assumes the twin's own structure",
}
MEASURES = {
    "second order": "**The second-order identification** fits each measured step",
    "map": "**The map** measures a full sweep of steps",
    "design": "**`lg.tune`** measures a few steps per target",
}


def _cells(doc: dict, method: str) -> dict:
    """{plant: score} of ``method`` in a robustness table's JSON."""
    return {p: row[method] for p, row in doc["scores"].items() if method in row}


def _worst(score: dict, method: str) -> str:
    """A cell's worst error as the table writes it (with its 90 % interval for the methods
    that have one, "no interval recorded" from a table without them), "no number" when it is
    not finite."""
    w = score["worst"]
    if w is None or not math.isfinite(w):
        return "no number"
    return error_text(w, score.get("worst_interval"), method)


def _largest(cells, method: str) -> tuple[float, str]:
    """The largest finite worst error of ``cells`` and its text with the range the cells'
    intervals allow (:func:`leglib.evaluation.robustness.worst_of`)."""
    w, iv = worst_of(cells, method)
    return w, error_text(w, iv, method)


def robustness(doc: dict) -> str:
    """"Reading the table": what the robustness table (``doc``, the JSON
    :func:`leglib.evaluation.robustness.write` wrote, or its copy in notebook 05's metrics)
    says, method by method, written from its numbers: where each method degrades (the
    table's own rule, its ``degraded`` list: worst error above 5 % and above twice the
    default plant's), and how far it stays elsewhere. The errors of the methods that
    identify (zeta, fn) are quoted with the ranges their 90 % intervals allow (a table
    written before they were stored says "no interval recorded"). Which methods rest on a
    structure they identify and which measure the leg is what the methods are, not a result."""
    degraded = {}
    for method, plant, worst, _ in doc.get("degraded", []):
        degraded.setdefault(method, []).append((plant, worst))
    s_deg = [m for m in STRUCTURE if m in degraded]
    m_deg = [m for m in MEASURES if m in degraded]
    if s_deg and not m_deg:
        head = ("The methods that identify a *structure* degrade where the leg has one they lack; the methods that "
                "measure the leg do not:")
    elif m_deg:
        head = f"Methods that measure the leg degrade too here ({', '.join(m_deg)}):"
    else:
        head = "No method degrades on any plant of this table:"
    out = [f"**Reading the table** (written from its numbers, payload {doc.get('payload', 0):g} kg). {head}", ""]
    for method, intro in {**STRUCTURE, **MEASURES}.items():
        cells = _cells(doc, method)
        if not cells:
            continue
        base = cells.get("default")
        parts = [f"{intro}: worst error {_worst(base, method)} on the default plant" if base else intro]
        deg = degraded.get(method, [])
        if deg:
            parts.append("degrades on " + ", ".join(f"{p} ({_worst(cells[p], method)})" for p, _ in deg))
        rest = [(p, c) for p, c in cells.items() if p != "default" and p not in dict(deg)]
        largest, text = _largest([c for _, c in rest], method)
        if rest and math.isfinite(largest):
            parts.append(f"{'and stays' if deg else 'stays'} within {text} on " + ", ".join(p for p, _ in rest))
        line = "- " + "; ".join(parts) + "."
        if method == "friction":
            zero = [p for p, c in cells.items()
                    if any(isinstance(v, (int, float)) and not isinstance(v, bool) and v <= -0.99
                           for k, v in c.get("detail", {}).items() if k != "rms_deg")]
            stopped = [f"on {p}: {c['note']}" for p, c in cells.items() if c.get("note")]
            rms = {p: max(c.get("detail", {}).get("rms_deg") or [math.nan]) for p, c in cells.items()}
            if zero:
                line += f" A coefficient is fitted to (nearly) zero on {', '.join(zero)}."
            if stopped:
                line += " " + "; ".join(stopped).capitalize() + "."
            if deg and all(math.isfinite(v) for v in rms.values()):
                line += (" Its residual (largest joint, deg RMS): "
                         + ", ".join(f"{p} {significant(v, 2)}" for p, v in rms.items())
                         + ". Where it degrades, use its values as an effective description of that run, not as the "
                           "bearings' physics.")
        if method == "state feedback: playback" and base:
            worst = [c["worst"] for c in cells.values() if c["worst"] is not None and math.isfinite(c["worst"])]
            # the measuring methods' largest worst error on any plant, with the range their
            # intervals allow: the playback is said to depart by more only beyond its upper end
            top, iv = worst_of([c for m in MEASURES for c in _cells(doc, m).values()])
            departs = (f" Open loop, it departs by {_pct(min(worst), sign=False)} to {_pct(max(worst), sign=False)} "
                       f"on every plant, the default included") if worst else ""
            if worst and math.isfinite(top) and min(worst) > (top if iv is None else iv[1]):
                line += (f"{departs}: more than any method that measures the leg does on any plant (at most "
                         f"{error_text(top, iv)}); it is no way to reach a target.")
            elif worst and math.isfinite(top) and min(worst) > top:
                line += (f"{departs}: more than the methods that measure the leg do on any plant (at most "
                         f"{error_text(top, iv)}), though their intervals allow more than it departs.")
        if method == "design":
            steps = [d["experiments"] for c in cells.values() for d in c.get("detail", {}).values()
                     if isinstance(d, dict) and "experiments" in d]
            if steps:
                line += f" It takes at most {max(steps)} steps per target."
        out.append(line)
    return "\n".join(out)


RENDERERS = {"01_derivation": derivation, "02_friction_fitting": friction, "04_pid_sweeps": sweeps,
             "05_validation": validation}


def render(notebook: str, metrics: dict) -> str:
    """The "What we found" of ``notebook`` (its stem, e.g. "04_pid_sweeps") from its
    ``metrics`` (a dict, or the path of its metrics JSON)."""
    if notebook not in RENDERERS:
        raise ValueError(f"no findings for notebook {notebook!r}; known: {sorted(RENDERERS)}")
    if not isinstance(metrics, dict):
        metrics = read_metrics(metrics)
    return RENDERERS[notebook](metrics)


# ---------------------------------------------------------------------------------------
# the check: every quoted number is a metric
# ---------------------------------------------------------------------------------------

# a number, optionally signed and followed by a percent sign
_NUMBER = re.compile(r"(?<![\w.\[])([-+−]?\d+(?:\.\d+)?(?:e[-+]?\d+)?)(\s*%)?")
# words after which a number names a thing (eq. 5.11, Listing 7.7, Fig. 6.9, notebook 05, A[3,3])
_REFERENCE = re.compile(r"(eqs?\.|Listings?|Figs?\.|Tables?|notebooks?|sections?|chapters?|§|chapter-)\s*$",
                        re.IGNORECASE)


def _leaves(obj):
    if isinstance(obj, dict):
        for v in obj.values():
            yield from _leaves(v)
    elif isinstance(obj, (list, tuple)):
        for v in obj:
            yield from _leaves(v)
    elif isinstance(obj, bool):
        return
    elif isinstance(obj, (int, float)) and math.isfinite(obj):
        yield float(obj)
    elif isinstance(obj, str):
        # a metric's text (a reason) may be quoted: its numbers are the metrics' too
        for tok, _ in quoted_numbers(obj):
            yield float(tok)


def quoted_numbers(text: str) -> list[tuple[str, bool]]:
    """The numbers ``text`` quotes, as (token, is_percent): not inside back-quotes (names),
    not references (eq. 5.11, Listing 7.7, Fig. 6.9, notebook 05, A[3,3]); the bounds of an
    interval followed by "%" ("[-0.3, +2.7] %") are percents."""
    plain = re.sub(r"`[^`]*`", " ", text)
    # an interval of percents, "+1.2 % [-0.3, +2.7] %" (units.percent_interval_text): its bounds are percents too
    plain = re.sub(r"\[([^\[\]]*)\]\s*%", lambda m: "[ " + ", ".join(f"{b.strip()} %" for b in m.group(1).split(","))
                   + "]", plain)
    out = []
    for match in _NUMBER.finditer(plain):
        before = plain[max(0, match.start() - 20):match.start()]
        if _REFERENCE.search(before):
            continue
        out.append((match.group(1).replace("−", "-"), bool(match.group(2))))
    return out


def _same(token: str, value: float, percent: bool) -> bool:
    """Whether ``token`` is ``value`` as printed: to the token's decimals (".3f", also in
    percent for a token followed by %), or to its significant digits (".4g", ".1e")."""
    x = float(token)
    candidates = [value, 100 * value] if percent else [value, 100 * value] if "e" in token.lower() else [value]
    mant = token.lower().split("e")[0].lstrip("+-")
    if "e" not in token.lower():
        digits = len(mant.split(".")[1]) if "." in mant else 0
        if any(round(abs(v), digits) == round(abs(x), digits) for v in candidates):
            return True
    # significant digits; an integer's trailing zeros are places, not digits ("1230" for 1234.5
    # written to the tens its interval supports)
    sig = len(mant.replace(".", "").lstrip("0")) if "." in mant else len(mant.lstrip("0").rstrip("0"))
    return sig > 0 and any(float(f"{abs(v):.{sig - 1}e}") == float(f"{abs(x):.{sig - 1}e}") for v in candidates)


def unquoted(text: str, metrics: dict, constants=()) -> list[str]:
    """The numbers ``text`` quotes that are none of ``metrics``' values (nor of
    ``constants``) as printed: empty when the text says only what its metrics hold."""
    values = list(_leaves(metrics)) + [float(c) for c in constants]
    return [tok + ("%" if pct else "") for tok, pct in quoted_numbers(text)
            if not any(_same(tok, v, pct) for v in values)]
