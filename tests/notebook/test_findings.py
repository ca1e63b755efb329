"""The notebooks' "What we found" (leglib.notebook.findings): made of their metrics, never
saying more than them."""

import json
import math

import pytest

from leglib.notebook import findings


def _m01(leg_is_thesis=True, err=1.2e-5):
    return {"leg_file_name": "leg_thesis.toml" if leg_is_thesis else "leg_mine.toml", "leg_is_thesis": leg_is_thesis,
            "eq511_max_rel_error": err, "printed_A33": 30.22, "printed_A_max_real_eig": 27.9,
            "corrected_A_max_real_eig": -2.21, "linear_vs_nonlinear_rms_deg": 0.004,
            "linear_vs_nonlinear_travel_deg": 0.61, "inertia_rel_difference_median": 0.37,
            "inertia_rel_difference_max": 0.517, "twin_plant_name": "default",
            "mismatch": {"gains": [50.0, 0.046, 0.001], "viscous": 0.098, "step_deg": 48.0,
                         "model": {"zeta": 1.0665, "fn": 5.83},
                         "thesis_result": {"zeta": 0.229, "f_hz": 5.06},
                         "thesis_result_as_true": {"zeta": 0.0732, "fd": 5.06, "fn": 5.07}},
            "twin_plant_model": {"viscous": 0.001, "model": {"zeta": 0.4017, "fn": 8.76}}}


def test_every_quoted_number_must_be_a_metric():
    m = {"a": 0.3712, "b": [6.977, 0.05], "c": {"d": 360}, "why": "ends 28.8 mm short"}
    ok = "zeta 0.371, fn 6.98 Hz, +5.0 % and 360 points; ends 28.8 mm short (eq. 5.11, Listing 7.7, `run_04`)"
    assert findings.unquoted(ok, m) == []
    assert findings.unquoted("zeta 0.372", m) == ["0.372"]       # not what the metric rounds to
    assert findings.unquoted("361 points", m) == ["361"]
    assert findings.unquoted("an error of 9.0 %", m) == ["9.0%"]
    assert findings.unquoted("tiny 0.05 and 5e-02", m) == []
    # an interval of percents: its bounds are percents of the metrics (units.percent_interval_text)
    pm = {"e": 0.0123, "e_interval": [-0.0031, 0.0272]}
    assert findings.unquoted("+1.23 % [−0.31, +2.72] %", pm) == []
    assert findings.unquoted("+1.23 % [−0.35, +2.72] %", pm) == ["-0.35%"]


def test_01_claims_eq_5_11_only_for_the_thesis_leg():
    text = findings.render("01_derivation", _m01())
    assert "reproduces eq. 5.11" in text and findings.unquoted(text, _m01()) == []
    other = findings.render("01_derivation", _m01(leg_is_thesis=False, err=0.31))
    assert "reproduces eq. 5.11 to" not in other and "is not the thesis's" in other
    assert "only with the shipped `leg_thesis.toml`" in other
    assert findings.unquoted(other, _m01(False, 0.31)) == []
    # the thesis's leg that does not reproduce it says so
    assert "does **not** reproduce eq. 5.11" in findings.render("01_derivation", _m01(err=0.05))
    # what the twin reproduces and what it cannot
    assert "What the virtual leg reproduces, and what it cannot" in text and "does not reproduce" in text


def _m05(max_zeta=0.0459):
    return {"thesis_measure": {"reached": False, "error_zeta": -0.8875, "error_zeta_interval": [-0.8880, -0.8870],
                               "error_f": -0.02, "error_f_interval": [-0.05, 0.01], "tolerance": 0.1,
                               "verdict": "not reached: the errors' 90 % intervals of zeta [-88.8%, -88.7%] reach "
                                          "beyond +-10%",
                               "target": {"zeta": 0.24, "f_hz": 5.0},
                               "listing_reach": {"points": 95, "max_thesis_zeta": max_zeta,
                                                 "max_thesis_zeta_interval": [max_zeta - 1e-4, max_zeta + 1e-4],
                                                 "max_thesis_zeta_upper": max_zeta + 1.2e-4, "min_true_zeta": 0.206,
                                                 "thesis_result_zeta": 0.229, "max_first_peak_deg": 60.9}},
            "thesis_reading": {"zeta": 0.0270, "f_hz": 4.9, "usable": True, "problem": None,
                               "zeta_interval": [0.0269, 0.0271], "f_interval": [4.8, 5.0]},
            "thesis_target": {"target": [0.24, 5.0], "inside_region": True, "zeta": 0.2424, "fn": 5.021, "zeta_interval": [0.162, 0.323],
                              "fn_interval": [4.47, 5.57], "error_zeta": 0.01, "error_fn": 0.004,
                              "verdict": "the 90 % intervals hold zeta to +-33.1% of the target, more than the "
                                         "tolerance (+-5.0%)", "tolerance": 0.05},
            "summary": {"map": {"median": 0.012, "worst": 0.2, "worst_bound": 0.4, "targets": 5, "unidentified": 0,
                                "experiments": 405, "outside_region": 1}},
            "design_study": {"all": {"median": 0.01, "worst": 0.02, "median_interval": [0.0, 0.061],
                                     "worst_interval": [0.0, 0.13], "max_experiments": 4, "reached": 3,
                                     "undecided": 5, "targets": 8}}, "design_plants": 5}


def test_05_leads_with_the_thesis_measure_result_and_quotes_intervals():
    m = _m05()
    text = findings.render("05_validation", m)
    first = text.splitlines()[0]
    assert "does not reproduce the thesis" in first and "0.229" in first
    # Listing 7.7's largest reading and the step's reading with their 90 % intervals
    assert ("zeta 0.04590 [0.04580, 0.04600] (90 % interval; no usable reading's interval reaches above 0.0460)"
            in first)
    assert "reads zeta 0.02700 [0.02690, 0.02710] at 4.90 [4.80, 5.00] Hz" in first
    assert "−88.75 % [−88.80, −88.70] %" in first
    # zeta to the digits its interval supports (half-width 0.08: two decimals), not 0.242 [0.162, 0.323]
    assert "zeta 0.24 [0.16, 0.32], fn 5.0 [4.5, 5.6] Hz" in text and "interval" in text
    assert findings.unquoted(text, m) == []
    # tune's errors over every plant with the ranges their intervals allow; a metrics file
    # written before they were stored says so
    assert "median error 1.0 % [0.0, 6.1] %, worst 2 % [0, 13] % (the ranges their intervals allow)" in text
    old = json.loads(json.dumps(m))
    for k in ("median_interval", "worst_interval"):
        old["design_study"]["all"].pop(k)
    assert ("median error 1.0 % (no interval recorded), worst 2.0 % (no interval recorded), at most"
            in findings.render("05_validation", old))
    m["thesis_measure"]["reached"] = True
    assert "reaches the thesis's target" in findings.render("05_validation", m).splitlines()[0]
    # a step the listing fails on: no number quoted for it, its reason instead
    m["thesis_reading"].update(usable=False, problem="its second 'peak' is ripple of the settled tail")
    m["thesis_measure"]["reached"] = False
    first = findings.render("05_validation", m).splitlines()[0]
    assert "gives no reading of the step at the gains nearest the target: its second 'peak' is ripple" in first
    assert "0.0270" not in first and findings.unquoted(first, m) == []


def test_render_reads_a_metrics_file_and_refuses_unknown_notebooks(tmp_path):
    p = tmp_path / "m.json"
    p.write_text(json.dumps(_m01()))
    assert findings.render("01_derivation", p) == findings.render("01_derivation", _m01())
    with pytest.raises(ValueError, match="no findings for notebook"):
        findings.render("03_pole_placement", {})
    with pytest.raises(FileNotFoundError, match="no metrics file"):
        findings.read_metrics(tmp_path / "none.json")
    assert not math.isnan(findings.read_metrics(p)["eq511_max_rel_error"])


def _m02_reading(**kw):
    base = {"zeta": 0.02522, "f_hz": 6.41, "n_peaks": 99, "usable": True,
            "problem": "findpeaks finds 99 peaks where an oscillation at the reading's own 6.41 Hz has at most 10",
            "zeta_interval": [0.02514, 0.02530], "f_interval": [6.10, 6.67], "interval_reason": None}
    return {**base, **kw}


@pytest.mark.parametrize("reading, says, quotes", [
    (_m02_reading(), "**the listing fails here**: findpeaks finds 99 peaks", "zeta 0.02522 [0.02514, 0.02530] at 6.41 [6.10, 6.67] Hz"),
    (_m02_reading(problem=None), "its own, biased measure", "zeta 0.02522 [0.02514, 0.02530]"),
    (_m02_reading(usable=False, problem="fewer than two peaks (1): the listing returns its constant zeta = 1, no reading",
                  zeta=1.0, zeta_interval=[math.nan, math.nan], f_interval=[math.nan, math.nan]),
     "Listing 7.7 gives no reading of the same step: **the listing fails here**: fewer than two peaks", None),
])
def test_02_quotes_listing_7_7_with_its_intervals_or_no_reading(reading, says, quotes):
    """The Listing 7.7 line of notebook 02: a reading with its 90 % intervals (and, where
    findpeaks counts the tail, that the listing fails there), or no number at all when it
    fails outright."""
    line = findings.friction({"rms_deg": [0.016], "rms_before_deg": [8.3], "preferred_model": "coulomb_viscous",
                              "friction": {"not_identifiable": {"viscous1": "on its bound", "viscous2": "on its bound",
                                                                "coulomb1": "on its bound", "coulomb2": "on its bound"},
                                           "params": {}, "intervals": {}},
                              "recovery_rel_error": {}, "single_joint": None,
                              "step_fit": {"zeta": 0.371, "fn": 6.98, "zeta_interval": [0.364, 0.378],
                                           "fn_interval": [6.90, 7.05], "r2": 0.999},
                              "step_thesis_reading": reading}).splitlines()[-1]
    assert says in line
    if quotes:
        assert quotes in line and "90 % intervals" in line
    else:
        assert "1.000" not in line and "zeta 1" not in line


def _robustness_doc(intervals=True):
    """A robustness table's JSON; ``intervals``: the second-order and design cells carry the
    ranges of their median and worst errors (a table written before they were stored: not)."""
    def cell(median, worst, experiments=1, detail=None, note="", mi=None, wi=None):
        out = {"median": median, "worst": worst, "experiments": experiments, "detail": detail or {}, "note": note,
               "seconds": 1.0}
        return {**out, "median_interval": mi, "worst_interval": wi} if intervals and wi is not None else out
    fr = {"default": cell(0.001, 0.007, detail={"viscous1": -0.007, "rms_deg": [0.017, 0.016]}),
          "belt": cell(0.068, 0.203, detail={"viscous1": -0.203, "rms_deg": [0.094, 0.086]}),
          "lugre": cell(0.058, 0.996, detail={"viscous1": -0.996, "rms_deg": [0.48, 0.2]},
                        note="fit stopped at 200 evaluations")}
    scores = {p: {"friction": fr[p],
                  "state feedback: playback": cell(0.11, {"default": 0.113, "belt": 0.109, "lugre": 0.143}[p]),
                  "second order": cell(0.003, {"default": 0.009, "belt": 0.021, "lugre": 0.012}[p], 5,
                                       mi=[0.0, 0.02], wi={"default": [0.0, 0.18], "belt": [0.004, 0.061],
                                                           "lugre": [0.0, 0.07]}[p]),
                  "design": cell(0.008, 0.02, 16, {"target 1": {"experiments": 2}, "target 2": {"experiments": 4}},
                                 mi=[0.0, 0.06], wi=[0.0, 0.13])}
              for p in ("belt", "default", "lugre")}
    degraded = [["friction", "belt", 0.203, 0.007], ["friction", "lugre", 0.996, 0.007]]
    return {"commit": "abc1234", "date": "2026-12-01T10:50:36+00:00", "payload": 0.0, "scores": scores,
            "degraded": degraded}


def test_reading_the_robustness_table_is_written_from_its_numbers():
    """Notebook 05's "Reading the table": which methods degrade and by how much, from the
    table's numbers and its own rule (its ``degraded`` list); a claim the numbers do not
    carry is not made."""
    doc = _robustness_doc()
    text = findings.robustness(doc)
    assert findings.unquoted(text, doc) == [], findings.unquoted(text, doc)
    assert "The methods that identify a *structure* degrade where the leg has one they lack" in text
    fr = next(ln for ln in text.splitlines() if ln.startswith("- **Friction"))
    assert "degrades on belt (20.3 %), lugre (99.6 %)" in fr and "zero on lugre" in fr
    assert "On lugre: fit stopped at 200 evaluations." in fr
    # the methods with intervals are quoted with the ranges their items' intervals allow
    so = next(ln for ln in text.splitlines() if "second-order identification" in ln)
    assert "worst error 1 % [0, 18] % on the default plant" in so
    assert "stays within 2.1 % [0.4, 7.0] % on belt, lugre" in so   # the largest worst, its range over both
    assert "worst error 2 % [0, 13] % on the default plant" in text
    pb = next(ln for ln in text.splitlines() if "played-back" in ln)
    # more than any measuring method's worst error on any plant, but not more than the upper end
    # of their ranges (18 %): said so, without the conclusion
    assert ("departs by 10.9 % to 14.3 % on every plant, the default included: more than the methods that measure "
            "the leg do on any plant (at most 2 % [0, 18] %), though their intervals allow more" in pb)
    assert "no way to reach a target" not in pb
    assert "at most 4 steps per target" in text
    # a measuring method that degrades is said to, and the structure/measure claim is not made
    doc["degraded"].append(["second order", "belt", 0.21, 0.009])
    other = findings.robustness(doc)
    assert "Methods that measure the leg degrade too here (second order)" in other
    assert "the methods that measure the leg do not" not in other


def test_reading_an_old_robustness_table_says_no_interval_was_recorded():
    """A table written before the intervals were stored: every error of a method that has
    intervals is quoted with "no interval recorded", friction's (which has none in any
    table) as it is; the claims are the point values'."""
    doc = _robustness_doc(intervals=False)
    text = findings.robustness(doc)
    assert findings.unquoted(text, doc) == []
    so = next(ln for ln in text.splitlines() if "second-order identification" in ln)
    assert "worst error 0.9 % (no interval recorded) on the default plant" in so
    assert "stays within 2.1 % (no interval recorded) on belt, lugre" in so
    fr = next(ln for ln in text.splitlines() if ln.startswith("- **Friction"))
    assert "no interval" not in fr and "degrades on belt (20.3 %)" in fr
    pb = next(ln for ln in text.splitlines() if "played-back" in ln)
    assert "departs by 10.9 % to 14.3 % on every plant" in pb and "at most 2.1 % (no interval recorded)" in pb


def test_03_playback_says_what_its_runs_show():
    m = {"model": {"rise_time": 0.21, "overshoot_pct": 2.5, "final_error_pct": 1.25},
         "playback": {"rise_time": 0.15, "overshoot_pct": 9.75, "final_error_pct": 7.5},
         "viscous": 0.098, "k22_listing": 0.2133, "k22_exact": 0.1780, "step_deg": 20.0}
    text = findings.thesis_playback(m)
    assert text.startswith("As in the thesis, the leg played back rises in 0.150 s against the model's 0.210 s")
    assert "20 % above the exact five-bar's 0.178" in text and findings.unquoted(text, m) == []
    m["playback"]["rise_time"] = 0.3
    assert findings.thesis_playback(m).startswith("Unlike the thesis")
