"""leglib.robustness: the table's logic, its files, and the methods scored on the twin."""

import json
import math

import pytest

from leglib.design.points import PointResult
from leglib.evaluation import robustness as R
from leglib.notebook import findings
from leglib.params import plant_names
from leglib.units import dynamics_text, percent_interval_text


def _table():
    S = R.Score
    scores = {"default": {"map": S(0.01, 0.03, 401), "design": S(0.01, 0.02, 12)},
              "belt": {"map": S(0.04, 0.08, 401), "design": S(0.01, 0.03, 14)},
              "bench": {"map": S(0.02, 0.055, 401), "design": S(0.02, math.inf, 9, note="aborted")}}
    return R.Table(scores, {"default": [(0.24, 5.0)]}, 0.0, True)


def test_degraded_names_methods_above_five_percent_and_twice_the_default():
    deg = {(m, p) for m, p, _, _ in _table().degraded()}
    # map on belt: 8 % > 5 % and > 2 x 3 %; map on bench: 5.5 % but not above 2 x 3 %;
    # design on bench: not finite (an abort) counts as degraded
    assert deg == {("map", "belt"), ("design", "bench")}


def test_table_round_trips_through_its_files(tmp_path):
    t = _table()
    md = R.write(t, tmp_path)
    doc = R.load_table(md.with_suffix(".json"))
    back = R.table_from_json(doc)
    assert back.markdown() == t.markdown()
    assert back.degraded() == t.degraded()
    assert "map on belt" in md.read_text() and "| design |" in md.read_text()


def test_load_table_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="make robustness"):
        R.load_table(tmp_path / "none.json")
    bad = tmp_path / "bad.json"
    bad.write_text("[1, 2]")
    with pytest.raises(ValueError, match="bad.json: not a robustness table"):
        R.load_table(bad)


def test_parse_plants_and_payloads():
    assert R.parse_plants("all") == plant_names()
    assert R.parse_plants(" default ,default") == ["default", "default"]
    with pytest.raises(ValueError, match="design_plants: unknown plant"):
        R.parse_plants("default, belts")
    assert R.parse_payloads("0, 0.3") == [0.0, 0.3]
    for bad in ("", "x", "-1", "nan", "0, 9"):
        with pytest.raises(ValueError, match="design_payloads"):
            R.parse_payloads(bad)


def _inside(value, interval):
    return interval[0] <= value <= interval[1]


def _check_dynamics(d):
    """A stored (zeta, fn): its values inside their 90 % intervals, or a failure with its
    reason and no numbers."""
    if "zeta" not in d:
        assert d["status"] != "ok" and d["reason"] and "fn_hz" not in d
        return False
    assert _inside(d["zeta"], d["zeta_interval"]) and _inside(d["fn_hz"], d["fn_interval_hz"])
    assert d["zeta_interval"][1] > d["zeta_interval"][0] and d["fn_interval_hz"][1] > d["fn_interval_hz"][0]
    return True


@pytest.mark.slow
def test_methods_on_the_default_plant_score_as_measured():
    res = R.evaluate("default", quick=True, methods=("second order", "model", "design"), seed=171)
    so, de, mo = res["second order"], res["design"], res["model"]
    assert so.experiments == 5 and so.worst < 0.05           # the sensor costs little on the default leg
    assert de.worst < 0.05 and len(res["targets"]) == 3      # the thesis's target and two measured ones
    # the search stops within 2 % of each target; "reached" is the intervals' verdict on that
    assert all(max(map(abs, v["error"])) <= 0.02 and v["experiments"] <= 10 for v in de.detail.values())
    assert all(v["reached"] == v["verdict"].startswith("reached") for v in de.detail.values())
    # the targets: the thesis's prescribed, the measured ones with their intervals
    thesis, *measured = res["targets"]
    assert thesis == {"zeta": 0.24, "fn_hz": 5.0, "source": "thesis"}
    assert measured and all(_check_dynamics(t) and t["source"].startswith("measured at") for t in measured)
    # every (zeta, fn) of every item holds its value in its interval, and so do the errors
    scored = 0
    for score in (so, mo, de):
        for item in score.detail.values():
            ok = _check_dynamics(item["measured"])
            if "ideal" in item:
                _check_dynamics(item["ideal"])
            assert ok == ("error" in item) == (item["status"] == "ok")
            if ok:
                scored += 1
                assert all(_inside(e, iv) for e, iv in zip(item["error"], item["error_interval"]))
        # the cell's median and worst inside the ranges its items' intervals allow
        assert _inside(score.median, score.median_interval) and _inside(score.worst, score.worst_interval)
        assert score.worst_interval[1] >= max(abs(b) for it in score.detail.values() if "error" in it
                                              for iv in it["error_interval"] for b in iv) - 1e-15
    assert scored == 5 + 3 + 3
    so_detail = [d for d in so.detail.values() if "error" in d]
    assert so_detail and all(d["ideal_inside"] == (_inside(d["ideal"]["zeta"], d["measured"]["zeta_interval"])
                                                   and _inside(d["ideal"]["fn_hz"], d["measured"]["fn_interval_hz"]))
                             for d in so_detail)
    # through the file and back: the same numbers, the markdown shows the intervals
    res_scores = {k: v for k, v in res.items() if k != "targets"}
    table = R.Table({"default": res_scores}, {"default": res["targets"]}, 0.0, True)
    doc = json.loads(json.dumps(table.to_json(), default=float))
    back = R.table_from_json(doc)
    assert back.markdown() == table.markdown()
    md = back.detail_markdown()
    item = so_detail[0]
    assert dynamics_text(item["measured"]["zeta"], item["measured"]["fn_hz"], item["measured"]["zeta_interval"],
                         item["measured"]["fn_interval_hz"], zeta_name="ζ") in md
    assert percent_interval_text(item["error"][0], item["error_interval"][0]) in md
    assert "(the thesis's target, prescribed)" in md and R.NO_INTERVAL not in md + back.markdown()
    assert percent_interval_text(mo.worst, mo.worst_interval, sign=False) in back.markdown()
    assert set(res_scores) == {"second order", "model", "design"}


def _new_doc():
    """A table in the current format, two plants: map with intervals, one target failed (its
    reason, no numbers), one outside the region; friction without intervals (it has none)."""
    def dyn(z, f, hz=0.02, hf=0.1):
        return {"zeta": z, "fn_hz": f, "zeta_interval": [z - hz, z + hz], "fn_interval_hz": [f - hf, f + hf]}
    thesis = {"zeta": 0.24, "fn_hz": 5.0, "source": "thesis"}
    ok = {"target": thesis, "gains": [44.2, 0.024, 0.08], "status": "ok", "measured": dyn(0.2426, 5.022),
          "experiments": 1, "error": [0.0108, 0.0044], "error_interval": [[-0.073, 0.094], [-0.016, 0.024]]}
    failed = {"target": {**dyn(0.55, 6.0), "source": "measured at (30, 0.05, 0.01)"}, "gains": [30.0, 0.05, 0.01],
              "status": "failed", "reason": "does not reach its commanded final value",
              "measured": {"status": "failed", "reason": "does not reach its commanded final value"},
              "experiments": 1}
    outside = {"target": {**dyn(0.37, 8.1), "source": "measured at (60, 0.06, 0.01)"}, "outside": True,
               "nearest": dyn(0.40, 7.5)}

    def cell(median, worst, mi=None, wi=None, detail=None, note=""):
        return {"median": median, "worst": worst, "experiments": 404 if detail else 1, "detail": detail or {},
                "note": note,
                "seconds": 1.0, "median_interval": mi, "worst_interval": wi}
    scores = {"default": {"map": cell(0.0108, 0.0108, [0.0, 0.073], [0.0, 0.094], {"target 1": ok}),
                          "friction": cell(0.001, 0.007)},
              "belt": {"map": cell(0.0108, math.inf, [0.0, 0.094], [math.inf, math.inf],
                                   {"target 1": ok, "target 2": failed, "target 3": outside},
                                   "target 2 not identifiable; target 3 outside the region"),
                       "friction": cell(0.068, 0.203)}}
    return {"payload": 0.0, "quick": True, "targets": {"default": [thesis]}, "commit": None, "date": "2026-12-01",
            "scores": scores, "degraded": [["map", "belt", math.inf, 0.0108], ["friction", "belt", 0.203, 0.007]]}


def test_the_markdown_shows_the_intervals_and_a_failure_without_numbers(tmp_path):
    doc = _new_doc()
    (tmp_path / "t.json").write_text(json.dumps(doc))
    t = R.table_from_json(R.load_table(tmp_path / "t.json"))
    assert t.scores["default"]["map"].worst_interval == (0.0, 0.094)
    md = t.markdown()
    # the map's cell with its ranges, to the digits they support (half-widths 3.7 and 4.7 %: one
    # digit); friction's without (it has none)
    assert "| map | 1 % [0, 7] % / 1 % [0, 9] % (404 exp.) | ∞ (404 exp.) — target 2 not identifiable" in md
    assert "| friction | 0.1 / 0.7 % (1 exp.) |" in md and R.NO_INTERVAL not in md
    detail = t.detail_markdown()
    rows = {ln.split(" | ")[2]: ln for ln in detail.splitlines() if ln.startswith("| map | belt")}
    assert "ζ 0.243 [0.223, 0.263], fn 5.02 [4.92, 5.12] Hz" in rows["target 1"]
    assert "+1 % [−7, +9] %, +0.4 % [−1.6, +2.4] %" in rows["target 1"]
    assert "(the thesis's target, prescribed)" in rows["target 1"]
    # the failed target: its status and reason, no measured numbers, an infinite error
    assert "not identifiable: does not reach its commanded final value | ∞ |" in rows["target 2"]
    assert "ζ 0.550 [0.530, 0.570], fn 6.00 [5.90, 6.10] Hz, measured at (30, 0.05, 0.01)" in rows["target 2"]
    assert "outside the region (nearest ζ 0.400 [0.380, 0.420], fn 7.50 [7.40, 7.60] Hz)" in rows["target 3"]
    deg = t.degraded_markdown()
    assert "- map on belt: worst ∞ (default plant 1 % [0, 9] %)" in deg
    assert "- friction on belt: worst 20.3 % (default plant 0.7 %)" in deg


def test_an_old_table_without_intervals_loads_and_says_so(tmp_path):
    """A robustness.json written before the intervals were stored (bare [zeta, fn] pairs, no
    interval fields; a failed check as [NaN, NaN] with no reason) loads; wherever it shows a
    number of a method that has intervals it says "no interval recorded"."""
    old_item = {"target": [0.24, 5.0], "gains": [44.2, 0.024, 0.08], "measured": [0.2426, 5.022],
                "error": [0.0108, 0.0044], "experiments": 1}
    failed = {"target": [0.55, 6.0], "gains": [30.0, 0.05, 0.01], "measured": [math.nan, math.nan],
              "error": [math.inf, math.inf], "experiments": 1}
    so_item = {"measured": [0.4243, 4.339], "ideal": [0.4250, 4.3775], "error": [-0.0017, -0.0087], "r2": 0.99}

    def cell(median, worst, detail=None):
        return {"median": median, "worst": worst, "experiments": 5, "detail": detail or {}, "note": "",
                "seconds": 1.0}
    doc = {"payload": 0.0, "quick": False, "targets": {"default": [[0.24, 5.0], [0.55, 6.0]]}, "commit": "0697ee6",
           "date": "2026-12-01T10:50:36+00:00",
           "scores": {"default": {"map": cell(0.0108, 0.0286, {"target 1": old_item}),
                                  "second order": cell(0.003, 0.0087, {"(np.float64(25.0), 0.03, 0.01)": so_item}),
                                  "friction": cell(0.001, 0.007)},
                      "belt": {"map": cell(0.007, math.inf, {"target 1": old_item, "target 2": failed}),
                               "second order": cell(0.003, 0.021), "friction": cell(0.068, 0.203)}},
           "degraded": [["friction", "belt", 0.203, 0.007]]}
    path = tmp_path / "robustness.json"
    path.write_text(json.dumps(doc))
    t = R.table_from_json(R.load_table(path))
    assert t.scores["default"]["map"].worst_interval is None
    md = t.markdown()
    assert "| map | 1.1 / 2.9 % (no interval recorded) (5 exp.) | ∞ (5 exp.) |" in md
    assert "| friction | 0.1 / 0.7 % (5 exp.) |" in md    # friction has no interval in any table: nothing to say
    detail = t.detail_markdown()
    assert "ζ 0.243, fn 5.02 Hz (no interval recorded)" in detail and "+1.1%, +0.4% (no interval recorded)" in detail
    # the failed check of an old table: no numbers, and it says its reason was not kept
    assert "| target 2 | ζ 0.550, fn 6.00 Hz (no interval recorded) | not identified (this table did not record " \
           "why) | ∞ | 1 |" in detail
    assert "ζ 0.424, fn 4.34 Hz (no interval recorded)" in detail
    text = findings.robustness(doc)
    so = next(ln for ln in text.splitlines() if "second-order identification" in ln)
    assert "worst error 0.9 % (no interval recorded) on the default plant" in so
    assert "stays within 2.1 % (no interval recorded) on belt" in so
    assert findings.unquoted(text, doc) == []


def test_reading_a_table_quotes_its_intervals():
    """findings.robustness quotes every error of a method with intervals with the range its
    items' intervals allow, and nothing the table does not hold."""
    doc = _new_doc()
    text = findings.robustness(doc)
    assert findings.unquoted(text, doc) == [], findings.unquoted(text, doc)
    mp = next(ln for ln in text.splitlines() if ln.startswith("- **The map**"))
    assert "worst error 1 % [0, 9] % on the default plant" in mp and "degrades on belt (no number)" in mp
    fr = next(ln for ln in text.splitlines() if ln.startswith("- **Friction"))
    assert "worst error 0.7 % on the default plant" in fr and R.NO_INTERVAL not in fr


def test_a_failed_step_is_stored_with_its_reason_and_no_numbers():
    p = PointResult((50.0, 0.002, 0.001), "failed", zeta=math.nan, reason="does not reach its commanded final value")
    assert R.dynamics(p) == {"status": "failed", "reason": "does not reach its commanded final value"}
    assert R.dynamics_cell(R.dynamics(p)) == "failed: does not reach its commanded final value"


def test_a_table_older_than_the_code_it_scores_says_so(tmp_path):
    """staleness: None while no commit since the table's touched the code it depends on; a
    notice naming the count and the latest commit once one did (a change elsewhere does not
    count); and it says when it cannot tell."""
    import subprocess

    def git(*args):
        return subprocess.run(["git", "-C", str(tmp_path), *args], check=True, capture_output=True,
                              text=True).stdout.strip()

    git("init", "-q")
    git("config", "user.email", "t@example.org")
    git("config", "user.name", "t")
    (tmp_path / "leglib" / "design").mkdir(parents=True)
    (tmp_path / "leglib" / "design" / "gainmap.py").write_text("a = 1\n")
    (tmp_path / "README.md").write_text("x\n")
    git("add", ".")
    git("commit", "-q", "-m", "first")
    doc = {"commit": git("rev-parse", "--short", "HEAD")}
    assert R.staleness(doc, repo=tmp_path) is None
    (tmp_path / "README.md").write_text("y\n")
    git("commit", "-q", "-am", "docs only")
    assert R.staleness(doc, repo=tmp_path) is None
    (tmp_path / "leglib" / "design" / "gainmap.py").write_text("a = 2\n")
    git("commit", "-q", "-am", "the map changes")
    notice = R.staleness(doc, repo=tmp_path)
    assert notice.startswith("Made by an older version: 1 commit(s) since " + doc["commit"])
    assert "the map changes" in notice and "make robustness" in notice
    assert "does not have" in R.staleness({"commit": "0123abc"}, repo=tmp_path)
    assert "does not say which commit" in R.staleness({"commit": None}, repo=tmp_path)


def test_the_repositorys_table_holds_every_identified_value_with_its_interval():
    """reports/robustness/robustness.json (what notebook 05 shows): every stored (zeta, fn)
    of the methods that identify them holds its value inside its 90 % interval (or is a
    failure with its reason and no numbers), every error likewise, every cell's median and
    worst inside their ranges; its markdown and its reading quote them."""
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "reports" / "robustness" / "robustness.json"
    doc = R.load_table(path)
    stored = 0
    for plant, row in doc["scores"].items():
        for t in doc["targets"][plant]:
            assert t["source"] == "thesis" or _check_dynamics(t)
        for method in R.INTERVAL_METHODS:
            cell = row[method]
            for name in ("median", "worst"):
                v, iv = cell[name], cell[f"{name}_interval"]
                assert math.isinf(v) or _inside(v, iv), (plant, method, name)
            for item in cell["detail"].values():
                for part in ("measured", "ideal", "nearest"):
                    if part in item:
                        stored += _check_dynamics(item[part])
                if "error" in item:
                    assert all(_inside(e, iv) for e, iv in zip(item["error"], item["error_interval"]))
    assert stored >= len(doc["scores"]) * 15     # 5 second-order steps (and their ideal readings), 4+ per method
    table = R.table_from_json(doc)
    assert R.NO_INTERVAL not in table.markdown() + table.detail_markdown()
    text = findings.robustness(doc)
    assert findings.unquoted(text, doc) == [] and R.NO_INTERVAL not in text
    so = doc["scores"]["default"]["second order"]
    assert f"worst error {percent_interval_text(so['worst'], so['worst_interval'], sign=False)} on the default" in text
