"""Every notebook: committed clean, typed parameters cell, and runs in smoke mode with
metrics that say it computed the right things."""

import ast
import json
import math
import os

import nbformat
import pytest

from leglib import model as M
from leglib.design import saved as designs
from leglib.design import statefeedback as SF
from leglib.notebook import findings, offline, widgets
from leglib.notebook import run as notebooks
from leglib.notebook.run import count_figures, execute, notebook_paths
from leglib.units import interval_text

NOTEBOOKS = notebook_paths()


def test_there_are_notebooks():
    assert [p.name[:2] for p in NOTEBOOKS] == sorted(p.name[:2] for p in NOTEBOOKS)
    assert len(NOTEBOOKS) >= 1


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_committed_without_outputs(path):
    nb = nbformat.read(str(path), as_version=4)
    for cell in nb.cells:
        if cell.cell_type == "code":
            assert not cell.outputs, f"{path.name}: cell {cell.get('id')} has outputs"
            assert cell.execution_count is None, f"{path.name}: cell {cell.get('id')} has a count"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_parameters_cell_is_plain_typed_values(path):
    nb = nbformat.read(str(path), as_version=4)
    cells = [c for c in nb.cells if "parameters" in c.metadata.get("tags", [])]
    assert len(cells) == 1, f"{path.name}: needs exactly one cell tagged 'parameters'"
    tree = ast.parse(cells[0].source)
    names = []
    for node in tree.body:
        assert isinstance(node, ast.AnnAssign), f"{path.name}: parameter without annotation"
        try:
            value = ast.literal_eval(node.value)
        except ValueError:
            raise AssertionError(f"{path.name}: {ast.unparse(node)} is not a plain value") from None
        assert isinstance(value, (bool, int, float, str)), f"{path.name}: {ast.unparse(node)} not plain"
        names.append(node.target.id)
    for line in cells[0].source.splitlines():
        assert "#" in line, f"{path.name}: parameter line without a unit/explanation: {line}"
    assert {"smoke", "figures_dir", "metrics_path"} <= set(names)
    # papermill's own parser documents every parameter (papermill --help-notebook)
    import papermill as pm
    inspected = pm.inspect_notebook(str(path))
    assert set(inspected) == set(names)
    assert all(v["help"] and v["inferred_type_name"] != "None" for v in inspected.values()), inspected


def assert_report_has_figures(out_dir, stem, html=True):
    """The executed notebook (and its HTML) carry its figures inline; widget panels leave a
    static picture."""
    nb = nbformat.read(str(out_dir / f"{stem}.ipynb"), as_version=4)
    n = count_figures(nb)
    assert n >= 1, f"{stem}: the executed notebook holds no figure"
    # a panel (a widget holding an output area, not e.g. a progress bar) leaves a picture
    state = nb.metadata.get("widgets", {}).get("application/vnd.jupyter.widget-state+json", {}).get("state", {})

    def holds_output_area(model_id, seen=()):
        m = state.get(model_id, {})
        if m.get("model_name") == "OutputModel":
            return True
        kids = [c[len("IPY_MODEL_"):] for c in m.get("state", {}).get("children", []) if isinstance(c, str)]
        return any(holds_output_area(k, seen + (model_id,)) for k in kids if k not in seen)

    for c in nb.cells:
        views = [o["data"]["application/vnd.jupyter.widget-view+json"]["model_id"] for o in c.get("outputs", [])
                 if "application/vnd.jupyter.widget-view+json" in o.get("data", {})]
        if any(holds_output_area(v) for v in views):
            assert any("image/png" in o.get("data", {}) for o in c.outputs), f"{stem}: a panel left no picture"
    if html:
        page = (out_dir / f"{stem}.html").read_text()
        assert page.count("data:image/png;base64") >= n, f"{stem}: the HTML lacks figures"
        # every table rendered: none left as a paragraph of pipes (offline.unrendered_tables)
        assert offline.unrendered_tables(page) == [], offline.unrendered_tables(page)


def _check_animations(executed, count: int, max_bytes: int = 3_000_000):
    """The executed notebook shows ``count`` leg animations (matplotlib's JS players, PNG
    frames embedded) and stays small enough to read and to keep."""
    players = [o for c in nbformat.read(str(executed), as_version=4).cells if c.cell_type == "code"
               for o in c.get("outputs", []) if 'class="animation"' in str(o.get("data", {}).get("text/html", ""))]
    assert len(players) == count, len(players)
    assert all("frames[1]" in o["data"]["text/html"] for o in players)
    assert executed.stat().st_size < max_bytes, executed.stat().st_size


def _run(path, tmp_path, **params):
    execute(path, tmp_path, {"smoke": True, **params}, html=True)
    assert_report_has_figures(tmp_path, path.stem)
    metrics = json.loads((tmp_path / "metrics" / f"{path.stem}.json").read_text())
    # every figure the notebook saved reads: no text over another, no legend on data
    # (leglib.plots.text_overlaps, legends_on_data)
    assert metrics["figure_text_overlaps"] == {}, metrics["figure_text_overlaps"]
    return metrics


def _check_rehearsal(m, exact: bool = False):
    """The notebook's bench report: on a fresh twin it configures (one reboot) and calibrates
    both axes once, however many sessions it opens; the estimate made before anything moved
    is an upper bound of the rehearsed bench time (``exact``: the same within 2 %)."""
    b = m["bench"]
    assert b["backend"] == "virtual" and b["summary"].startswith("Rehearsal on the twin: on the leg this run would do")
    assert b["counts"]["save"] == b["counts"]["reboot"] == 1 and b["counts"]["calibration"] == 2
    assert b["planned_s"] >= 0.99 * b["bench_s"] > 0
    if exact:
        assert b["bench_s"] == pytest.approx(b["planned_s"], rel=0.02)
    assert b["limit_s"] == 300.0


def _check_findings(executed, stem, m):
    """The notebook's "What we found" is findings.render of its metrics, shown as such, and
    every number it quotes is one of them."""
    text = findings.render(stem, m)
    assert findings.unquoted(text, m) == [], findings.unquoted(text, m)
    shown = [o["data"]["text/markdown"] for c in nbformat.read(str(executed), as_version=4).cells
             if c.cell_type == "code" for o in c.get("outputs", []) if "text/markdown" in o.get("data", {})]
    assert any(text in md and "What we found" in md for md in shown), "the findings shown are not the metrics'"
    return text


def _inside(value, interval):
    return interval[0] <= value <= interval[1]


@pytest.mark.notebook
def test_01_derivation(tmp_path):
    m = _run(NOTEBOOKS[0], tmp_path)
    _check_animations(tmp_path / NOTEBOOKS[0].name, 1)
    assert (tmp_path / "figures" / "01_leg_motion.gif").exists()
    assert m["eq511_max_rel_error"] < 0.01
    assert m["printed_A_max_real_eig"] > 0 > m["corrected_A_max_real_eig"]
    assert m["linear_vs_nonlinear_rms_deg"] < 0.02 * m["linear_vs_nonlinear_travel_deg"]
    assert 0 < m["inertia_rel_difference_median"] < 10
    assert (tmp_path / "figures" / "01_model_difference.png").stat().st_size > 10_000
    # the g2 sign the exact five-bar supports, and eq. 5.11's guessed masses
    g2 = m["g2_sign"]
    assert g2["supported"] == "+" and abs(g2["A32_exact"]) > 10 * abs(g2["A32_eq54"])
    assert len({round(r["A10"], 3) for r in m["eq511_sensitivity"]}) == len(m["eq511_sensitivity"]) > 1
    text = _check_findings(tmp_path / NOTEBOOKS[0].name, NOTEBOOKS[0].stem, m)
    # eq. 5.11 is claimed for the thesis's leg; the chapter-5/6 mismatch in numbers
    assert m["leg_is_thesis"] and "reproduces eq. 5.11" in text and "what it cannot" in text
    mm = m["mismatch"]
    assert mm["model"]["zeta"] > 3 * mm["thesis_result_as_true"]["zeta"]   # chapter 5 damps far more


@pytest.mark.notebook
@pytest.mark.parametrize("index, params, message", [
    (0, {"grid_n": "many"}, "parameter 'grid_n' must be int"),                      # wrong type
    (2, {"step_deg": 90.0}, "parameter 'step_deg' must be <= 40.0"),                 # out of range
    (3, {"backend": "serial"}, "parameter 'backend' must be one of ('virtual', 'usb')"),  # unknown backend
], ids=["type", "range", "backend"])


def test_bad_parameter_stops_notebook_early(tmp_path, index, params, message):
    import papermill as pm
    with pytest.raises(pm.PapermillExecutionError) as err:
        execute(NOTEBOOKS[index], tmp_path, {"smoke": True, **params}, html=False)
    assert message in str(err.value)
    # stopped in its first code cells: the parameters, the injected ones, the checks
    nb = nbformat.read(str(tmp_path / NOTEBOOKS[index].name), as_version=4)
    code = [c for c in nb.cells if c.cell_type == "code"]
    failed = [i for i, c in enumerate(code) if any(o.get("output_type") == "error" for o in c.outputs)]
    assert failed and failed[0] <= 2, failed
    assert all(c.execution_count is None for c in code[failed[0] + 1:])


@pytest.mark.notebook
def test_02_friction_fitting(processed):
    tmp_path, m = processed
    assert_report_has_figures(tmp_path, "02_friction_fitting", html=False)
    assert m["backend"] == "virtual"
    for name, rel in m["recovery_rel_error"].items():
        # v_smooth: the model's smoothing width, not a friction coefficient. Viscous: the
        # current sensor's noise dithers the firmware's current loop (tests/identify), 12 %;
        # inertia: the back-EMF rejected at the current loop's bandwidth adds about 4 %
        limit = {"v_smooth": math.inf, "viscous1": 0.12, "viscous2": 0.12, "inertia_scale": 0.06}.get(name, 0.05)
        assert abs(rel) < limit, (name, rel)
    assert max(m["rms_deg"]) < 0.1 < min(m["rms_before_deg"])
    assert m["preferred_model"] == "coulomb_viscous"  # the twin has no Stribeck friction
    sj = m["single_joint"]
    assert sj["inertia"] == pytest.approx(sj["inertia_true"], rel=0.05) and sj["r2"] > 0.99
    assert 0 < m["step_fit"]["zeta"] < 1 and m["step_fit"]["fd"] < m["step_fit"]["fn"]
    assert m["step_thesis_reading"]["n_peaks"] >= 2 and m["step_thesis_reading"]["zeta"] < m["step_fit"]["zeta"]
    assert (tmp_path / "figures" / "02_listing77_peaks.png").exists()
    assert (tmp_path / "processed" / "friction_identified.json").exists()
    assert len(list((tmp_path / "raw").glob("*_torque.csv"))) == 1
    _check_rehearsal(m, exact=True)
    assert m["bench"]["counts"]["torque"] == 1 and m["bench"]["counts"]["step"] == 1   # the rig is not the leg
    # every number with its interval: the step's (zeta, fn), the friction values
    s = m["step_fit"]
    assert _inside(s["zeta"], s["zeta_interval"]) and _inside(s["fn"], s["fn_interval"])
    assert s["classifier"]["status"] == "ok"
    f = m["friction"]
    assert all(_inside(f["params"][k], f["intervals"][k]) for k in ("viscous1", "viscous2", "coulomb1", "coulomb2")
               if k not in f["not_identifiable"])
    # Listing 7.7 on this step counts the quantized tail's ripple: a failure, and said so
    th = m["step_thesis_reading"]
    text = _check_findings(tmp_path / "02_friction_fitting.ipynb", "02_friction_fitting", m)
    if th["problem"]:
        assert "the listing fails here" in text
    # the corrected log decrement with its intervals (or the fit's, where it falls back to it)
    ld = m["step_logdec"]
    assert "note" in ld or (_inside(ld["zeta"], ld["zeta_interval"]) and _inside(ld["fn"], ld["fn_interval"]))
    # its reading with its 90 % intervals, or none (no reading, its reason)
    if th["usable"]:
        assert _inside(th["zeta"], th["zeta_interval"]) and _inside(th["f_hz"], th["f_interval"])
        assert th["interval_reason"] is None
    else:
        assert all(math.isnan(x) for x in th["zeta_interval"]) and th["interval_reason"].startswith("no reading")


def _shown_markdown(executed) -> str:
    return "".join(o.get("data", {}).get("text/markdown", "") + "".join(o.get("text", ""))
                   for c in nbformat.read(str(executed), as_version=4).cells if c.cell_type == "code"
                   for o in c.get("outputs", []))


@pytest.mark.notebook
def test_03_pole_placement(processed, tmp_path):
    out02, _ = processed
    m = _run(NOTEBOOKS[2], tmp_path, identified_path=str(out02 / "processed" / "friction_identified.json"),
             processed_dir=str(tmp_path / "processed"))
    _check_animations(tmp_path / NOTEBOOKS[2].name, 1)
    d = designs.load(tmp_path / "processed" / "design_03_thesis.json")
    assert isinstance(d, SF.StateFeedback) and designs.read(tmp_path / "processed" / "design_03_identified.json")["Ki"]
    assert designs.read(tmp_path / "processed" / "design_03_identified.json")["provenance"]["backend"] == "virtual"
    assert m["eig_K_max_rel_error"] < 1e-6 and m["eig_L_max_rel_error"] < 1e-6
    assert m["controllability_rank"] == 4 == m["observability_rank"]
    runs = m["runs"]
    # the identified design, closed live on the twin, ends within 2 % of the step
    assert runs["identified: live closed loop"]["final_error_pct"] < 2.0
    # and agrees with its simulation; the thesis design's playback overshoots far more
    assert abs(runs["identified: live closed loop"]["rise_time"] - runs["identified: nonlinear model"]["rise_time"]) < 0.05
    assert runs["thesis design: playback"]["overshoot_pct"] > 3 * runs["identified: playback"]["overshoot_pct"]
    assert 400 < m["live_rate_hz"] < 600
    assert m["readout"].startswith("K = [")
    _check_rehearsal(m)
    assert m["bench"]["counts"]["torque"] == 4 and m["bench"]["counts"]["hold"] == 2
    # the playback against the model is written from the runs' numbers, not by hand
    text = findings.thesis_playback(m["thesis_playback"])
    assert findings.unquoted(text, m) == [] and text in _shown_markdown(tmp_path / NOTEBOOKS[2].name)
    assert m["thesis_playback"]["playback"] == runs["thesis design: playback"]


def _run_notebook_04(out):
    _run(NOTEBOOKS[3], out, sweep_dir=str(out / "sweep"), processed_dir=str(out / "processed"))


@pytest.fixture(scope="module")
def sweep04(shared):
    """Notebook 04 run once for the session (tests 04 and 05 may run on two workers)."""
    out = shared("nb04", _run_notebook_04)
    return out, json.loads((out / "metrics" / f"{NOTEBOOKS[3].stem}.json").read_text())


@pytest.mark.notebook
def test_04_pid_sweeps(sweep04):
    out, m = sweep04
    _check_animations(out / NOTEBOOKS[3].name, 1)
    g = designs.load(out / "processed" / "design_04_thesis_target.json", kind="cascade_gains")
    assert g.method == "map" and g.target == (0.24, 5.0) and g.measured is not None
    # saved with the measuring step's 90 % intervals and the map's for its prediction
    assert g.measured_intervals == (tuple(m["thesis_target_measured"]["zeta_interval"]),
                                    tuple(m["thesis_target_measured"]["fn_interval"]))
    assert g.predicted_intervals is not None and g.measured_text() in _shown_markdown(out / NOTEBOOKS[3].name)
    assert g.source["sweep_dir"] == str(out / "sweep") and sum(g.source["counts"].values()) == 32
    assert m["points"] == 32 and sum(m["counts"].values()) == 32
    under, over = m["bldc"]["(100.0, 0.1, 10.0)"], m["bldc"]["(8.0, 5.0, 0.3)"]
    assert under["overshoot_pct"] > 10 and under["zeta"] < 1       # thesis Fig. 6.8a
    assert over["overshoot_pct"] < 0.5                              # thesis Fig. 6.8b
    assert m["achievable"] > 0 and m["zeta_range"][0] > 0 and m["fn_range"][0] > 0
    # Listing 7.7 reads the ideal steps far below their true damping above zeta 0.2, fd exactly
    bias = m["thesis_reading_bias"]
    for row in bias["ideal_fd5"]:
        assert row["thesis_f_hz"] == pytest.approx(5.0, rel=0.01)
        if row["true_zeta"] >= 0.2:
            assert row["thesis_zeta"] < 0.5 * row["true_zeta"]
    assert bias["target_as_true"]["zeta"] < 0.24 and bias["grid"]["points"] > 0
    _check_rehearsal(m)
    assert m["bench"]["counts"]["sweep"] == 1 and m["bench"]["counts"]["step"] == 32 + 2
    t = m["thesis_target_nearest"]
    assert _inside(t["zeta"], t["zeta_interval"]) and _inside(t["fn"], t["fn_interval"])
    reach = m["listing_reach"]
    assert reach["max_thesis_zeta"] < reach["thesis_result_zeta"]
    # Listing 7.7's largest reading with its 90 % interval, in the text too
    if reach["points"]:
        assert _inside(reach["max_thesis_zeta"], reach["max_thesis_zeta_interval"])
        assert reach["max_thesis_zeta_upper"] >= reach["max_thesis_zeta_interval"][1]
    text = _check_findings(out / NOTEBOOKS[3].name, NOTEBOOKS[3].stem, m)
    if reach["points"]:
        assert "(90 % interval; no usable reading's interval reaches above" in text


def _without_intervals(obj):
    """``obj`` (a robustness table's JSON) as a table written before the intervals were stored."""
    drop = {"zeta_interval", "fn_interval_hz", "error_interval", "median_interval", "worst_interval"}
    if isinstance(obj, dict):
        return {k: _without_intervals(v) for k, v in obj.items() if k not in drop}
    if isinstance(obj, list):
        return [_without_intervals(v) for v in obj]
    return obj


@pytest.mark.notebook
def test_05_validation(sweep04, tmp_path):
    """Notebook 05 started from 04's saved design and the repository's robustness table, both
    written as files of before intervals were stored (their values only): they load, say "no
    interval recorded", and 05 saves its own design with the intervals of the step it measured."""
    from leglib.evaluation import robustness

    out04, _ = sweep04
    old = json.loads((out04 / "processed" / "design_04_thesis_target.json").read_text())
    for part in ("measured", "predicted"):
        for k in ("zeta_interval", "fn_interval_hz"):
            old[part].pop(k, None)
    (tmp_path / "old_design.json").write_text(json.dumps(old))
    table = json.loads((NOTEBOOKS[4].parent.parent / "reports" / "robustness" / "robustness.json").read_text())
    old_table = _without_intervals(table)
    (tmp_path / "old_robustness.json").write_text(json.dumps(old_table))
    m = _run(NOTEBOOKS[4], tmp_path, sweep_dir=str(out04 / "sweep"), processed_dir=str(tmp_path / "processed"),
             design_file=str(tmp_path / "old_design.json"), robustness_path=str(tmp_path / "old_robustness.json"))
    shown = _shown_markdown(tmp_path / NOTEBOOKS[4].name)
    assert "no interval recorded" in shown
    # the old table's cells and reading: the values it holds, each saying it has no interval
    assert robustness.table_from_json(old_table).markdown() in shown
    assert m["robustness"] is not None and "(no interval recorded)" in findings.robustness(m["robustness"])
    g = designs.load(tmp_path / "processed" / "design_05_thesis_target.json")
    assert g.gains == tuple(m["thesis_target"]["gains"]) and g.measured == (m["thesis_target"]["zeta"],
                                                                            m["thesis_target"]["fn"])
    assert g.measured_intervals == (tuple(m["thesis_target"]["zeta_interval"]), tuple(m["thesis_target"]["fn_interval"]))
    assert g.predicted_intervals is None and "no interval recorded" in g.predicted_text()   # none in the file it read
    assert len(m["targets"]) == 5
    # the smoke map is a 2 x 4 x 4 grid: coarse; the model needs no grid
    assert m["summary"]["map"]["worst"] < 0.5
    assert m["summary"]["model"]["worst"] < 0.1
    assert set(m["thesis_target"]) >= {"gains", "zeta", "fn", "error_zeta", "error_fn"}
    # the validated response in the thesis's measure next to its true zeta, fd, fn
    th, tr = m["thesis_reading"], m["true_reading"]
    assert set(th) >= {"zeta", "f_hz"} and set(tr) >= {"zeta", "fd", "fn"}
    assert 0 < tr["zeta"] < 1 and tr["fd"] < tr["fn"]
    tm = m["thesis_measure"]
    errors_small = abs(tm["error_zeta"]) <= 0.1 and abs(tm["error_f"]) <= 0.1
    assert not tm["reached"] or errors_small           # reached only when the intervals lie within it
    # Listing 7.7's readings with their 90 % intervals, or why none
    if th["usable"]:
        assert _inside(th["zeta"], th["zeta_interval"]) and _inside(th["f_hz"], th["f_interval"])
        assert _inside(tm["error_zeta"], tm["error_zeta_interval"])
    else:
        assert th["interval_reason"].startswith("no reading")
    if not tm["reached"]:
        # the notebook shows where the target lies: the twin's best Listing 7.7 reading
        assert 0 <= tm["max_thesis_zeta"] < 1
        if tm["max_thesis_zeta"] < 0.8 * tm["target"]["zeta"]:   # out of reach: the step reads low too
            assert tm["error_zeta"] < -0.1
    assert m["virtual_leg"]["achieved"]["k"] > 0
    assert m["summary"]["model"]["experiments"] < m["summary"]["map"]["experiments"]
    _check_rehearsal(m)
    assert "sweep" not in m["bench"]["counts"]             # 04's sweep was there
    # the thesis's target with its interval and what the interval allows; the errors' bounds
    t = m["thesis_target"]
    assert _inside(t["zeta"], t["zeta_interval"]) and _inside(t["fn"], t["fn_interval"]) and t["verdict"]
    assert all(v["worst_bound"] >= v["worst"] for v in m["summary"].values())
    text = _check_findings(tmp_path / NOTEBOOKS[4].name, NOTEBOOKS[4].stem, m)
    # it leads with the thesis-measure result, the measured maximum against the thesis's 0.229
    reach = m["thesis_measure"]["listing_reach"]
    first = text.splitlines()[0]
    assert "thesis's own measure" in first and f"{reach['thesis_result_zeta']:.3f}" in first
    if not tm["reached"] and reach["points"]:
        assert interval_text(reach["max_thesis_zeta"], reach["max_thesis_zeta_interval"]) in first
    # "Reading the table": written from the robustness table's numbers, when there is one
    if m["robustness"] is not None:
        reading = findings.robustness(m["robustness"])
        assert findings.unquoted(reading, m["robustness"]) == [] and reading in shown
    else:
        assert "No robustness table" in shown


@pytest.mark.notebook
def test_03_starts_from_a_saved_design(processed, tmp_path):
    """With design_file the notebook uses the saved design, not its poles parameter."""
    import subprocess

    from leglib.params import load_leg
    saved = SF.place_poles(M.linearize(load_leg("thesis")), (-9.0, -9.007, -9.014, -9.021), 5.0)
    path = designs.save(tmp_path / "start.json", saved, linearization={"leg": "thesis"})
    # made, as it says, by the repository's first commit: older than the code it depends on
    first = subprocess.run(["git", "rev-list", "--max-parents=0", "HEAD"], capture_output=True, text=True,
                           cwd=NOTEBOOKS[0].parent).stdout.split()
    doc = json.loads(path.read_text())
    doc["provenance"]["git_commit"] = first[0] if first else "unknown"
    path.write_text(json.dumps(doc))
    out02, _ = processed
    # the design's source is what this test is about, not its runs: 1 s experiments, not 4.5 s
    m = _run(NOTEBOOKS[2], tmp_path, identified_path=str(out02 / "processed" / "friction_identified.json"),
             processed_dir=str(tmp_path / "processed"), design_file=str(path), duration=1.0)
    assert m["readout"] == widgets.design_readout(saved)
    # the inputs read from files say where they came from; the old design shows its notice
    ident, design = m["inputs"]["identified_path"], m["inputs"]["design_file"]
    assert ident["notice"] is None and ident["commits"]            # 02 ran on this very code
    assert design["notice"] and (design["stale"] or not first)     # "Made by an older version: ..."
    shown = "".join(o.get("data", {}).get("text/markdown", "") for c in
                    nbformat.read(str(tmp_path / NOTEBOOKS[2].name), as_version=4).cells for o in c.get("outputs", []))
    assert design["notice"] in shown
    assert m["eig_K_max_rel_error"] < 1e-6
    # and saved again as it was loaded
    assert designs.same(designs.load(tmp_path / "processed" / "design_03_thesis.json"), saved)


def _notebook_with_cells(path, cells):
    nb = nbformat.v4.new_notebook(cells=[nbformat.v4.new_code_cell(c) for c in cells])
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    nbformat.write(nb, str(path))
    return path


def _fake_execute(notebook, out_dir, parameters, progress=False):
    """Stands in for notebooks.execute in run_all's pool: records when it ran."""
    import time as _time
    from pathlib import Path as _Path
    t0 = _time.monotonic()
    _time.sleep(0.3)
    if _Path(notebook).name.startswith("03"):
        raise ValueError("cell 2 failed")
    (_Path(out_dir) / f"{_Path(notebook).stem}.times").write_text(f"{t0} {_time.monotonic()}")
    return _Path(out_dir) / _Path(notebook).name


def test_run_all_runs_two_at_a_time_along_the_dependencies(tmp_path, monkeypatch):
    """make run: notebooks in two processes, 03 only after 02, 05 only after 04; a failing
    notebook is raised naming it, after every notebook not reading from it ran."""
    names = ["01_a.ipynb", "02_b.ipynb", "03_c.ipynb", "04_d.ipynb", "05_e.ipynb"]
    monkeypatch.setattr(notebooks, "notebook_paths", lambda: [tmp_path / n for n in names])
    monkeypatch.setattr(notebooks, "execute", _fake_execute)
    with pytest.raises(ValueError, match="cell 2 failed") as err:
        notebooks.run_all(tmp_path, workers=2)
    assert any("03_c.ipynb" in n for n in getattr(err.value, "__notes__", []))
    assert not any("not run" in n for n in err.value.__notes__)   # nothing reads from 03
    times = {p.stem[:2]: tuple(map(float, p.read_text().split())) for p in tmp_path.glob("*.times")}
    assert set(times) == {"01", "02", "04", "05"}          # all but the failing one ran
    assert times["05"][0] >= times["04"][1]                 # 05 waited for 04
    overlap = min(times["02"][1], times["04"][1]) - max(times["02"][0], times["04"][0])
    assert overlap > 0.1                                    # two at a time
    with pytest.raises(ValueError, match="workers"):
        notebooks.run_all(tmp_path, workers=0)


def _fake_execute_on_cores(notebook, out_dir, parameters, progress=False):
    """Stands in for notebooks.execute: records when it ran and on which cores it may run."""
    import os as _os
    import time as _time
    from pathlib import Path as _Path
    t0 = _time.monotonic()
    _time.sleep(0.3)
    cores = " ".join(map(str, sorted(_os.sched_getaffinity(0))))
    (_Path(out_dir) / f"{_Path(notebook).stem}.cores").write_text(f"{t0} {_time.monotonic()} {cores}")
    return _Path(out_dir) / _Path(notebook).name


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity") or (os.cpu_count() or 1) < 2,
                    reason="one core, or no CPU affinity on this system")
def test_run_all_keeps_each_notebook_to_a_free_core(tmp_path, monkeypatch):
    """make run with a process per core: each notebook (and the kernel it starts) keeps to one
    core, two running at once to two cores; with fewer processes than cores, it is left
    where it was."""
    names = ["01_a.ipynb", "02_b.ipynb", "03_c.ipynb", "04_d.ipynb", "05_e.ipynb"]
    monkeypatch.setattr(notebooks, "notebook_paths", lambda: [tmp_path / n for n in names])
    monkeypatch.setattr(notebooks, "execute", _fake_execute_on_cores)
    # cores 0 and 1 (this test's own process may keep to one core: tests/conftest.py)
    monkeypatch.setattr(notebooks, "usable_cores", lambda: [0, 1])

    def ran():
        out = {}
        for p in tmp_path.glob("*.cores"):
            t0, t1, *on = p.read_text().split()
            out[p.stem[:2]] = (float(t0), float(t1), {int(c) for c in on})
            p.unlink()
        return out

    notebooks.run_all(tmp_path, workers=2)
    runs = ran()
    assert len(runs) == 5 and all(len(on) == 1 and on <= {0, 1} for *_, on in runs.values())
    together = [(a, b) for a in runs for b in runs
                if a < b and min(runs[a][1], runs[b][1]) > max(runs[a][0], runs[b][0])]
    assert together and all(runs[a][2] != runs[b][2] for a, b in together), together
    notebooks.run_all(tmp_path, workers=1)
    assert all(on == os.sched_getaffinity(0) for *_, on in ran().values())


def _fake_execute_02_fails(notebook, out_dir, parameters, progress=False):
    from pathlib import Path as _Path
    if _Path(notebook).name.startswith("02"):
        raise ValueError("02 failed")
    (_Path(out_dir) / f"{_Path(notebook).stem}.ran").write_text("")
    return _Path(out_dir) / _Path(notebook).name


def test_run_all_skips_what_reads_from_a_failed_notebook(tmp_path, monkeypatch):
    names = ["01_a.ipynb", "02_b.ipynb", "03_c.ipynb", "04_d.ipynb", "05_e.ipynb"]
    monkeypatch.setattr(notebooks, "notebook_paths", lambda: [tmp_path / n for n in names])
    monkeypatch.setattr(notebooks, "execute", _fake_execute_02_fails)
    with pytest.raises(ValueError, match="02 failed") as err:
        notebooks.run_all(tmp_path, workers=2)
    assert sorted(p.stem[:2] for p in tmp_path.glob("*.ran")) == ["01", "04", "05"]
    assert any("not run" in n and "03_c.ipynb" in n for n in err.value.__notes__)


def _fake_execute_writes_data(notebook, out_dir, parameters, progress=False):
    from pathlib import Path as _Path
    if _Path(notebook).name.startswith("02"):
        raise ValueError("02 failed")
    data = _Path(out_dir) / "data" / "raw"
    data.mkdir(parents=True, exist_ok=True)
    (data / f"{_Path(notebook).stem}.csv").write_text("")
    return _Path(out_dir) / _Path(notebook).name


def test_run_all_says_each_notebook_as_it_ends(tmp_path, monkeypatch, capfd):
    names = ["01_a.ipynb", "02_b.ipynb", "03_c.ipynb", "04_d.ipynb", "05_e.ipynb"]
    monkeypatch.setattr(notebooks, "notebook_paths", lambda: [tmp_path / n for n in names])
    monkeypatch.setattr(notebooks, "execute", _fake_execute_writes_data)
    monkeypatch.setattr(notebooks, "REPO", tmp_path)   # its data/ is where the notebooks write
    with pytest.raises(ValueError, match="02 failed"):
        notebooks.run_all(tmp_path, workers=2)
    lines = [ln for ln in capfd.readouterr().err.splitlines() if ln.startswith("[run]")]
    assert lines[0].startswith("[run] 5 notebooks, 2 at a time")
    assert lines[-1] == "[run] the notebooks also wrote 3 file(s) under data/raw"
    ends = lines[1:-1]
    assert len(ends) == 5 and [ln.split(": ")[1].split()[0] for ln in ends] == ["1/5", "2/5", "3/5", "4/5", "5/5"]
    assert any("02_b.ipynb failed" in ln for ln in ends)
    assert any("03_c.ipynb skipped" in ln for ln in ends)
    assert sum(" done: " in ln for ln in ends) == 3


@pytest.mark.slow
def test_a_run_says_its_sections_and_a_long_cell_while_it_runs(tmp_path, monkeypatch, capfd):
    """Progress lines from the first second: the start, each markdown heading as the run
    reaches it, a heartbeat naming a cell that runs long, the end with its time."""
    from leglib.notebook import progress
    monkeypatch.setattr(progress, "HEARTBEAT_S", 0.5)
    nb = nbformat.v4.new_notebook(cells=[
        nbformat.v4.new_markdown_cell("# 1. Set-up\nsome text"), nbformat.v4.new_code_cell("x = 1"),
        nbformat.v4.new_markdown_cell("## 2. The long part"),
        nbformat.v4.new_code_cell("import time\ntime.sleep(2.0)  # a sweep")])
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    path = tmp_path / "07_progress.ipynb"
    nbformat.write(nb, str(path))
    execute(path, tmp_path / "out", html=False, progress=True)
    lines = [ln for ln in capfd.readouterr().err.splitlines() if ln.startswith("[07]")]
    assert lines[0] == "[07] 07_progress.ipynb: started"
    assert lines[1].startswith("[07] 1. Set-up (cell 2/5, ")  # after papermill's injected parameters
    assert lines[2].startswith("[07] 2. The long part (cell 4/5, ")
    beats = [ln for ln in lines if "running for" in ln]
    assert beats and all("cell 5/5" in ln and "import time" in ln for ln in beats)
    assert lines[-1].startswith("[07] 07_progress.ipynb: done in ")
    # a failing run says so
    bad = _notebook_with_cells(tmp_path / "08_bad.ipynb", ["raise ValueError('no')"])
    with pytest.raises(Exception, match="no"):
        execute(bad, tmp_path / "out", html=False, progress=True)
    assert "[08] 08_bad.ipynb: FAILED after" in capfd.readouterr().err


def test_a_kernel_that_did_not_start_is_started_again_even_for_the_leg(tmp_path, monkeypatch):
    """A kernel given a port another process took first dies before it answers (nbclient
    raises jupyter_client's RuntimeError, client.py wait_for_ready): no cell ran, nothing
    moved, so the run is tried again, on backend "usb" too. Another RuntimeError is not."""
    import papermill

    real, calls = papermill.execute_notebook, []

    def first_start_fails(*args, **kwargs):
        calls.append(kwargs["parameters"])
        if len(calls) == 1:
            raise RuntimeError("Kernel died before replying to kernel_info")
        return real(*args, **kwargs)
    monkeypatch.setattr(papermill, "execute_notebook", first_start_fails)
    path = _notebook_with_cells(tmp_path / "nb.ipynb", ["answer = 6 * 7\nprint(answer)"])
    with pytest.warns(RuntimeWarning, match="Kernel died before replying.*running it once more"):
        out = execute(path, tmp_path / "out", {"backend": "usb"}, html=False)
    assert len(calls) == 2
    assert "42" in json.dumps(nbformat.read(str(out), as_version=4).cells[-1].outputs)

    def other_error(*args, **kwargs):
        calls.append(kwargs["parameters"])
        raise RuntimeError("something else")
    monkeypatch.setattr(papermill, "execute_notebook", other_error)
    calls.clear()
    with pytest.raises(RuntimeError, match="something else"):
        execute(path, tmp_path / "out2", html=False)
    assert len(calls) == 1


@pytest.mark.slow
def test_a_cell_past_the_timeout_names_the_cell_and_is_tried_once_more(tmp_path):
    """A cell that runs longer than execute's timeout stops the run with nbclient's
    CellTimeoutError, which shows the cell; on the twin the run is tried once more."""
    from nbclient.exceptions import CellTimeoutError
    path = _notebook_with_cells(tmp_path / "slow.ipynb", ["import time\ntime.sleep(30)  # the slow cell"])
    with pytest.warns(RuntimeWarning, match="running it once more"), pytest.raises(CellTimeoutError) as err:
        execute(path, tmp_path / "out", timeout=2, html=False)
    assert "the slow cell" in str(err.value)


@pytest.mark.parametrize("backend, exits", [("usb", True), ("virtual", False)])
def test_the_kernel_exits_on_its_own_on_the_leg_and_is_stopped_on_the_twin(tmp_path, backend, exits):
    """After the last cell, a run on the leg asks its kernel to exit and waits for it: the
    kernel's exit handlers run (whatever a library registered to release the board). On the
    twin nothing waits on them, and the kernel is stopped at once."""
    marker = tmp_path / "exited"
    path = _notebook_with_cells(tmp_path / "nb.ipynb", [
        "backend = 'virtual'", f"import atexit, pathlib\natexit.register(pathlib.Path({str(marker)!r}).touch)"])
    nb = nbformat.read(str(path), as_version=4)
    nb.cells[0].metadata["tags"] = ["parameters"]
    nbformat.write(nb, str(path))
    execute(path, tmp_path / "out", {"backend": backend}, html=False)
    assert marker.exists() == exits
