"""Designs as files: exact round trips, provenance, and errors that name the field."""

import json
import math
import re

import numpy as np
import pytest

import leglib as lg
from leglib import model as M
from leglib.design import saved as designs
from leglib.design import statefeedback as SF
from leglib.design.saved import DesignFileError, GainDesign


@pytest.fixture(scope="module")
def sf_designs(leg):
    thesis = SF.place_poles(M.linearize(leg), SF.THESIS_POLES, 6.0)
    # complex poles and integral action on the coupled five-bar: every optional field set
    coupled = SF.place_poles(M.linearize(leg, coupled=True, model="fivebar"), (-6 + 3j, -6 - 3j, -15, -15.5), 4.5,
                        integral_poles=SF.spread_poles(-4.0, 2))
    return thesis, coupled


def test_state_feedback_round_trip_is_exact(tmp_path, sf_designs):
    for i, d in enumerate(sf_designs):
        path = designs.save(tmp_path / f"d{i}.json", d, linearization={"leg": "thesis", "q0_rad": [4.66, 4.76]})
        back = designs.load(path)
        assert isinstance(back, SF.StateFeedback)
        assert designs.same(back, d)
        for name in ("K", "L", "Nbar", "poles", "observer_poles"):
            assert np.array_equal(getattr(back, name), getattr(d, name)), name
            assert getattr(back, name).dtype.kind == np.asarray(getattr(d, name)).dtype.kind, name
        assert np.array_equal(back.sys.A, d.sys.A) and np.array_equal(back.sys.B, d.sys.B)
        # the loaded design behaves as the saved one: same closed-loop eigenvalues
        assert np.array_equal(np.linalg.eigvals(back.sys.A - back.sys.B @ back.K),
                              np.linalg.eigvals(d.sys.A - d.sys.B @ d.K))
        data = designs.read(path)
        assert data["kind"] == "state_feedback"
        assert data["observer_factor"] == pytest.approx([6.0, 4.5][i])
        assert data["linearization"]["about"]["leg"] == "thesis"
    assert sf_designs[1].Ki is not None and designs.load(tmp_path / "d1.json").Ki is not None


def test_gain_design_round_trip_is_exact(tmp_path):
    g = GainDesign(target=(0.24, 5.0), gains=(47.123456789, 0.0461234567891, 0.001), method="map",
                   predicted=(0.2391, 4.987), measured=(0.229, 5.06),
                   source={"sweep_dir": "data/raw/sweep_thesis_grid", "counts": {"ok": 398, "unstable": 2},
                           "values": np.array([1.0, 1 / 3])})
    back = designs.load(designs.save(tmp_path / "g.json", g, backend="virtual", serial="3A7F1E2D4B0B"))
    assert back == g and designs.same(back, g)
    assert back.gains == (47.123456789, 0.0461234567891, 0.001)
    assert back.source["values"] == [1.0, 1 / 3]
    # optional parts may be absent
    bare = GainDesign(target=(0.5, 3), gains=(20, 0.1, 0.0), method="model")
    assert designs.load(designs.save(tmp_path / "bare.json", bare)) == bare


def test_file_is_readable_with_provenance(tmp_path, sf_designs):
    from leglib import __version__
    with lg.connect("virtual", seed=3) as dev:
        path = designs.save(tmp_path / "d.json", sf_designs[0], device=dev, note="thesis poles")
        serial = f"{int(dev.serial_number):012X}"
    text = path.read_text()
    assert '"K": [' in text and text.count("\n") > 40      # one value per line, not one long line
    prov = json.loads(text)["provenance"]
    assert prov["leglib_version"] == __version__
    assert prov["backend"] == "virtual" and prov["device_serial"] == serial
    assert prov["git_commit"] and prov["date"].endswith("+00:00")


def _edit(path, fn):
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))
    return path


@pytest.mark.parametrize("edit, field", [
    (lambda d: d.pop("K"), "'K' is missing"),
    (lambda d: d.__setitem__("K", [[1.0, 2.0]]), "'K' must be a 2 x 4 array"),
    (lambda d: d.__setitem__("L", "many"), "'L' must be a 4 x 2 array"),
    (lambda d: d["linearization"].__setitem__("A", [[1.0, 2.0]]), "'linearization.A' must be square"),
    (lambda d: d.__setitem__("poles", {"re": [1, 2, 3, 4]}), "'poles' as a complex array"),
    (lambda d: d.__setitem__("Nbar", [[1.0, None], [0.0, 1.0]]), "'Nbar' must hold finite numbers"),
    (lambda d: d.__setitem__("observer_factor", "six"), "'observer_factor' must be a finite number"),
    (lambda d: d.__setitem__("kind", "pid"), "'kind' must be one of"),
    (lambda d: d.__setitem__("format", 99), "'format' is 99"),
    (lambda d: d["provenance"].pop("git_commit"), "'provenance.git_commit' must be a string"),
    (lambda d: d.__setitem__("controllability_rank", 7), "'controllability_rank' must be an integer in [0, 4]"),
    (lambda d: d.__setitem__("Ki", [[1.0, 0.0], [0.0, 1.0]]), "'Ki' and 'integral_poles'"),
])
def test_malformed_state_feedback_file_names_the_field(tmp_path, sf_designs, edit, field):
    path = _edit(designs.save(tmp_path / "d.json", sf_designs[0]), edit)
    with pytest.raises(DesignFileError) as err:
        designs.load(path)
    assert field in str(err.value) and str(path) in str(err.value)


@pytest.mark.parametrize("edit, field", [
    (lambda d: d["gains"].pop("vel_gain"), "'gains.vel_gain' is missing"),
    (lambda d: d["gains"].__setitem__("pos_gain", True), "'gains.pos_gain' must be a finite number"),
    (lambda d: d["target"].__setitem__("fn_hz", "5 Hz"), "'target.fn_hz' must be a finite number"),
    (lambda d: d.__setitem__("measured", [0.2, 5.0]), "'measured' must be an object"),
    (lambda d: d.__setitem__("source", None), "'source' must be a JSON object"),
])
def test_malformed_gain_file_names_the_field(tmp_path, edit, field):
    g = GainDesign(target=(0.24, 5.0), gains=(50, 0.046, 0.001), method="map", measured=(0.23, 5.1))
    path = _edit(designs.save(tmp_path / "g.json", g), edit)
    with pytest.raises(DesignFileError, match=field.replace("(", r"\(").replace("[", r"\[")):
        designs.load(path)


def test_kind_asked_for(tmp_path, sf_designs):
    path = designs.save(tmp_path / "d.json", sf_designs[0])
    assert designs.same(designs.load(path, kind="state_feedback"), sf_designs[0])
    with pytest.raises(DesignFileError, match="'kind' is 'state_feedback', but a 'cascade_gains' design is needed"):
        designs.load(path, kind="cascade_gains")


def test_not_json_or_absent(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text('{"kind": "state_feedback",\n "K": [1, 2,]}')
    with pytest.raises(DesignFileError, match="not valid JSON \\(line 2"):
        designs.load(bad)
    with pytest.raises(DesignFileError, match="no such design file"):
        designs.load(tmp_path / "absent.json")
    with pytest.raises(TypeError, match="StateFeedback .place_poles. or a GainDesign"):
        designs.save(tmp_path / "x.json", {"K": 1})


def test_gain_design_from_model_and_map_record_their_source():
    class FakeModel:
        params = {"inertia_scale": 1.1, "payload_mass": 0.05}
        experiments, rms_turns, step, duration, sample_period = 5, 1e-4, 0.4, 1.5, 0.002

        def gains_for(self, zeta, fn, vel_integrator_gain=0.01):
            return (40.0, 0.05, vel_integrator_gain), (zeta * 1.01, fn * 0.99)

    g = designs.gain_design_from_model(FakeModel(), 0.24, 5.0)
    assert g.gains == (40.0, 0.05, 0.01) and g.predicted == pytest.approx((0.2424, 4.95))
    assert g.source["plant_params"]["payload_mass"] == 0.05 and g.method == "model"
    assert math.isfinite(g.source["rms_turns"])


def _bump_k(d):
    d["K"][0][0] += 1.0


@pytest.mark.parametrize("edit, field", [
    (lambda d: d.__setitem__("poles", [1.0, -7.007, -7.014, -7.021]), "'poles' holds [1.], not in the open left"),
    (lambda d: d.__setitem__("observer_poles", [6.0, -42.042, -42.084, -42.126]), "'observer_poles' holds"),
    (_bump_k, "'K' does not place the file's 'poles'"),
    (lambda d: d["L"][0].__setitem__(0, d["L"][0][0] * 2), "'L' does not place the file's 'observer_poles'"),
    (lambda d: d["K"][0].__setitem__(0, 1e308), "'K' holds 1e+308: no entry of a design exceeds 1e+09"),
    (lambda d: d["K"][0].__setitem__(0, "0.05"), "'K' must be a 2 x 4 array of numbers, got '0.05' in it"),
    (lambda d: d["K"].__setitem__(0, ["1", "2", "3", "4"]), "'K' must be a 2 x 4 array of numbers, got '1'"),
    (lambda d: d.__setitem__("observer_factor", -6), "'observer_factor' must be above 0, got -6"),
    (lambda d: d.__setitem__("observer_factor", 0), "'observer_factor' must be above 0"),
])
def test_state_feedback_file_that_is_not_a_sound_design_is_refused(tmp_path, sf_designs, edit, field):
    path = _edit(designs.save(tmp_path / "d.json", sf_designs[0]), edit)
    with pytest.raises(DesignFileError, match=re.escape(str(path)) + ".*" + re.escape(field)):
        designs.load(path)


def test_integral_design_checks_k_and_ki_together(tmp_path, sf_designs):
    path = designs.save(tmp_path / "d.json", sf_designs[1])
    assert designs.same(designs.load(path), sf_designs[1])
    _edit(path, lambda d: d["Ki"][0].__setitem__(0, d["Ki"][0][0] + 5.0))
    with pytest.raises(DesignFileError, match="'K' does not place the file's 'poles' and 'integral_poles'"):
        designs.load(path)


@pytest.mark.parametrize("edit, field", [
    (lambda d: d["gains"].__setitem__("pos_gain", 1e300), r"'gains.pos_gain' = 1e\+300 is beyond the configured "
                                                          r"maximum 200 \(.*odrive_thesis.toml, \[experiment\] max_pos_gain\)"),
    (lambda d: d["gains"].__setitem__("vel_gain", 5.0), "'gains.vel_gain' = 5 is beyond the configured maximum 1"),
    (lambda d: d["gains"].__setitem__("vel_integrator_gain", 21), "'gains.vel_integrator_gain' = 21 is beyond"),
    (lambda d: d["target"].__setitem__("zeta", -5), "'target.zeta' must be above 0, got -5"),
    (lambda d: d["target"].__setitem__("fn_hz", 0), "'target.fn_hz' must be above 0, got 0"),
    (lambda d: d["measured"].__setitem__("fn_hz", 1e300), "'measured.fn_hz' must be at most 1000"),
])
def test_gain_file_beyond_the_configured_bounds_is_refused(tmp_path, edit, field):
    g = GainDesign(target=(0.24, 5.0), gains=(50, 0.046, 0.001), method="map", measured=(0.23, 5.1))
    path = _edit(designs.save(tmp_path / "g.json", g), edit)
    with pytest.raises(DesignFileError, match=field):
        designs.load(path)


def test_gain_bounds_come_from_the_configuration_given(tmp_path):
    from leglib.params import load_odrive_config
    g = GainDesign(target=(0.24, 5.0), gains=(150, 0.046, 0.001), method="map")
    path = designs.save(tmp_path / "g.json", g)
    assert designs.load(path) == g
    with pytest.raises(DesignFileError, match="'gains.pos_gain' = 150 is beyond the configured maximum 100"):
        designs.load(path, config=load_odrive_config("thesis", max_pos_gain=100.0))


def test_files_that_cannot_be_design_files_are_refused_by_name(tmp_path):
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100000 + "]" * 100000)
    with pytest.raises(DesignFileError, match="deep.json: not a design file: its JSON is nested too deeply"):
        designs.load(deep)
    digits = tmp_path / "digits.json"
    digits.write_text('{"kind": ' + "9" * 5000 + "}")
    with pytest.raises(DesignFileError, match="digits.json: not a design file: Exceeds the limit"):
        designs.load(digits)
    latin = tmp_path / "latin.json"
    latin.write_bytes(b'{"note": "caf\xe9"}')
    with pytest.raises(DesignFileError, match=r"latin.json:1: not UTF-8 text \(byte 0xe9\)"):
        designs.load(latin)
    with pytest.raises(DesignFileError, match=f"{tmp_path}: a directory, not a regular file; a design file is a regular JSON file"):
        designs.load(tmp_path)
    with pytest.raises(DesignFileError, match="/dev/zero: not a regular file"):
        designs.load("/dev/zero")
    big = tmp_path / "big.json"
    big.write_bytes(b" " * (designs.MAX_BYTES + 1))
    with pytest.raises(DesignFileError, match=f"big.json: {designs.MAX_BYTES + 1} bytes; a design file is at most"):
        designs.load(big)


def test_fifo_is_refused_without_blocking(tmp_path):
    import os
    fifo = tmp_path / "design.json"
    os.mkfifo(fifo)
    with pytest.raises(DesignFileError, match="design.json: not a regular file"):
        designs.load(fifo)


def test_dynamics_text_keeps_the_digits_identification_supports():
    from leglib.design import saved
    # without an interval it says so, never a bare number
    assert (saved.dynamics_text((0.23933203135364942, 5.004081632653061))
            == "zeta 0.239, fn 5.00 Hz (no interval recorded)")
    # with one, to the digits the interval supports (leglib.units.interval_text)
    assert (saved.dynamics_text((0.23933203135364942, 5.004081632653061), ((0.161, 0.318), (4.47, 5.54)))
            == "zeta 0.24 [0.16, 0.32], fn 5.0 [4.5, 5.5] Hz")
    assert saved.dynamics_text(None) == "none (not a second-order step)"


def _with_intervals():
    return GainDesign(target=(0.24, 5.0), gains=(50, 0.046, 0.001), method="map", predicted=(0.2391, 4.987),
                      measured=(0.2424, 5.021), measured_intervals=((0.162, 0.323), (4.47, 5.57)),
                      predicted_intervals=((0.2, 0.28), (4.6, math.inf)))


def test_gain_design_keeps_the_measured_intervals_and_shows_them(tmp_path):
    """The measured (zeta, fn) is stored with the 90 % intervals of the step that measured
    it, read back exactly (an unbounded end as null in the file) and shown with them."""
    g = _with_intervals()
    path = designs.save(tmp_path / "g.json", g)
    doc = json.loads(path.read_text())
    assert doc["measured"]["zeta_interval"] == [0.162, 0.323] and doc["measured"]["fn_interval_hz"] == [4.47, 5.57]
    assert doc["predicted"]["fn_interval_hz"] == [4.6, None]          # unbounded above: no inf in JSON
    back = designs.load(path)
    assert back == g and designs.same(back, g)
    assert back.measured_intervals == ((0.162, 0.323), (4.47, 5.57)) and back.predicted_intervals[1][1] == math.inf
    assert back.measured_text() == "zeta 0.24 [0.16, 0.32], fn 5.0 [4.5, 5.6] Hz"
    assert "zeta 0.24 [0.16, 0.32], fn 5.0 [4.5, 5.6] Hz" in str(back) and "90 % intervals" in str(back)
    assert "zeta 0.24 [0.16, 0.32]" in back._repr_markdown_()


def test_an_old_design_file_without_intervals_loads_and_says_so(tmp_path):
    """A file written before intervals were stored (its measured and predicted hold zeta and
    fn only) still loads, and the design states "no interval recorded" rather than printing
    a bare number as if it had none to give."""
    g = _with_intervals()
    path = designs.save(tmp_path / "old.json", g)
    doc = json.loads(path.read_text())
    for part in ("measured", "predicted"):
        for k in ("zeta_interval", "fn_interval_hz"):
            doc[part].pop(k)
    path.write_text(json.dumps(doc))
    old = designs.load(path, kind="cascade_gains")
    assert old.measured == g.measured and old.predicted == g.predicted
    assert old.measured_intervals is None and old.predicted_intervals is None
    assert old.measured_text() == "zeta 0.242, fn 5.02 Hz (no interval recorded)"
    assert "no interval recorded" in old.predicted_text() and "no interval recorded" in str(old)
    assert "no interval recorded" in old._repr_markdown_()
    # and a design without any measurement stays as it was
    bare = GainDesign(target=(0.5, 3), gains=(20, 0.1, 0.0), method="model")
    assert designs.load(designs.save(tmp_path / "bare.json", bare)).measured_intervals is None


@pytest.mark.parametrize("edit, field", [
    (lambda d: d["measured"].pop("fn_interval_hz"), "'measured.fn_interval_hz' is missing"),
    (lambda d: d["measured"].__setitem__("zeta_interval", [0.3, 0.4]),
     "'measured.zeta_interval' \\[0.3, 0.4\\] does not hold the value 0.2424"),
    (lambda d: d["measured"].__setitem__("zeta_interval", 0.2), "'measured.zeta_interval' must be \\[low, high\\]"),
    (lambda d: d["measured"].__setitem__("fn_interval_hz", ["4", 5.6]), "'measured.fn_interval_hz\\[0\\]' must be"),
])
def test_malformed_intervals_name_the_field(tmp_path, edit, field):
    path = _edit(designs.save(tmp_path / "g.json", _with_intervals()), edit)
    with pytest.raises(DesignFileError, match=field):
        designs.load(path)


def test_intervals_must_hold_their_values():
    with pytest.raises(ValueError, match="does not hold its value"):
        GainDesign(target=(0.24, 5.0), gains=(50, 0.046, 0.001), method="map", measured=(0.24, 5.0),
                   measured_intervals=((0.3, 0.4), (4.5, 5.5)))
    # an identification without an interval (NaN bounds) records none
    g = GainDesign(target=(0.24, 5.0), gains=(50, 0.046, 0.001), method="map", measured=(0.24, 5.0),
                   measured_intervals=((math.nan, math.nan), (4.5, 5.5)))
    assert g.measured_intervals is None and "no interval recorded" in g.measured_text()
