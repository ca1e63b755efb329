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
    return {"thesis_measure": {"reached": False, "error_zeta": -0.89, "target": {"zeta": 0.24, "f_hz": 5.0},
                               "listing_reach": {"points": 95, "max_thesis_zeta": max_zeta, "min_true_zeta": 0.206,
                                                 "thesis_result_zeta": 0.229, "max_first_peak_deg": 60.9}},
            "thesis_reading": {"zeta": 0.027, "f_hz": 4.9},
            "thesis_target": {"target": [0.24, 5.0], "inside_region": True, "zeta": 0.2424, "fn": 5.021, "zeta_interval": [0.162, 0.323],
                              "fn_interval": [4.47, 5.57], "error_zeta": 0.01, "error_fn": 0.004,
                              "verdict": "the 90 % intervals hold zeta to +-33.1% of the target, more than the "
                                         "tolerance (+-5.0%)", "tolerance": 0.05},
            "summary": {"map": {"median": 0.012, "worst": 0.2, "worst_bound": 0.4, "targets": 5, "unidentified": 0,
                                "experiments": 405, "outside_region": 1}},
            "design_study": {"all": {"median": 0.01, "worst": 0.02, "max_experiments": 4, "reached": 3,
                                     "undecided": 5, "targets": 8}}, "design_plants": 5}


def test_05_leads_with_the_thesis_measure_result_and_quotes_intervals():
    m = _m05()
    text = findings.render("05_validation", m)
    first = text.splitlines()[0]
    assert "does not reproduce the thesis" in first and "0.046" in first and "0.229" in first
    # zeta to the digits its interval supports (half-width 0.08: two decimals), not 0.242 [0.162, 0.323]
    assert "zeta 0.24 [0.16, 0.32], fn 5.0 [4.5, 5.6] Hz" in text and "interval" in text
    assert findings.unquoted(text, m) == []
    m["thesis_measure"]["reached"] = True
    assert "reaches the thesis's target" in findings.render("05_validation", m).splitlines()[0]


def test_render_reads_a_metrics_file_and_refuses_unknown_notebooks(tmp_path):
    p = tmp_path / "m.json"
    p.write_text(json.dumps(_m01()))
    assert findings.render("01_derivation", p) == findings.render("01_derivation", _m01())
    with pytest.raises(ValueError, match="no findings for notebook"):
        findings.render("03_pole_placement", {})
    with pytest.raises(FileNotFoundError, match="no metrics file"):
        findings.read_metrics(tmp_path / "none.json")
    assert not math.isnan(findings.read_metrics(p)["eq511_max_rel_error"])
