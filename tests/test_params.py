"""Parameter files: shipped sets load in SI; malformed files are rejected by name."""

import math
import re
from pathlib import Path

import pytest

from leglib.params import (
    PARAMS_DIR,
    ParameterError,
    load_leg,
    load_motor,
    load_odrive_config,
)


def test_shipped_sets_load_in_si(leg):
    assert leg.m1 == pytest.approx(0.055)          # 55 g -> kg
    assert leg.q1 == pytest.approx(math.radians(267))
    assert leg.gear_ratio == 3.0 and leg.encoder_cpr == 4000
    motor = load_motor("mn5212")
    assert motor.phase_resistance == pytest.approx(0.069)  # 69 mOhm, not 69 Ohm
    assert motor.La == pytest.approx(0.56e-3)
    assert motor.kv == pytest.approx(340 * 2 * math.pi / 60)
    cfg = load_odrive_config("thesis")
    assert cfg.cpr == 4000 and cfg.current_lim == 10.0
    assert cfg.torque_constant == pytest.approx(8.27 / 340)


def test_every_value_has_a_source(leg):
    for name in ("l1", "m1", "lc3", "Jd1", "c11", "q1", "encoder_cpr"):
        assert leg.source(name), name


def _write_variant(tmp_path: Path, old: str, new: str) -> Path:
    text = (PARAMS_DIR / "leg_thesis.toml").read_text()
    assert old in text
    p = tmp_path / "leg_bad.toml"
    p.write_text(text.replace(old, new, 1))
    return p


@pytest.mark.parametrize("old,new,message", [
    ('m3 = { value = 100.0, unit = "g", source = "lower link with pins, bearings, foot (estimate)" }\n', "",
     "missing field 'mass.m3'"),
    ('value = 0.09,  unit = "m", source = "Stanford Doggo upper link L1 (Doggo firmware leg kinematics; '
     'README, How the shipped parameters were obtained)" }',
     'value = "0.09", unit = "m" }', "field 'geometry.l1': value must be a number"),
    ('value = 55.0,  unit = "g"', 'value = -55.0, unit = "g"', "field 'mass.m1': value must be positive"),
    ('value = 0.162, unit = "m"', 'value = 0.162, unit = "kg"', "field 'geometry.l3': unit 'kg' is kg"),
    ('value = 0.045,   unit = "m"', 'value = 0.045,   unit = "furlong"', "unknown unit 'furlong'"),
    ('value = 4000, unit = "count/turn"', 'value = 4000.5, unit = "count/turn"', "must be an integer"),
    ('value = 9.81,', 'value = nan,', "must be finite"),
    ('l2 = { value = 0.09,', 'l2 = 0.09 #', "must be an inline table"),
])
def test_malformed_files_are_rejected_by_file_and_field(tmp_path, old, new, message):
    bad = _write_variant(tmp_path, old, new)
    with pytest.raises(ParameterError) as err:
        load_leg(bad)
    assert message in str(err.value)
    assert str(bad) in str(err.value)


def test_not_toml_and_missing_file(tmp_path):
    p = tmp_path / "broken.toml"
    p.write_text("[geometry\nl1 = ")
    with pytest.raises(ValueError, match="not valid TOML"):
        load_leg(p)
    with pytest.raises(ValueError, match="not found"):
        load_leg(tmp_path / "nope.toml")
    with pytest.raises(ValueError, match="no parameter set named 'nosuchleg'"):
        load_leg("nosuchleg")


def test_cross_damping_may_be_negative_but_diagonal_may_not(tmp_path, leg):
    assert leg.c12 < 0
    bad = _write_variant(tmp_path, 'c11 = { value = 0.098014', 'c11 = { value = -0.098014')
    with pytest.raises(ParameterError, match="'damping.c11': value must be non-negative"):
        load_leg(bad)


def test_overrides(leg):
    assert load_leg("thesis", g=0.0).g == 0.0
    with pytest.raises(ParameterError, match="unknown field 'gg'"):
        load_leg("thesis", gg=1.0)


def _variant_of(tmp_path: Path, stem: str, old: str, new: str) -> Path:
    text = (PARAMS_DIR / f"{stem}.toml").read_text()
    assert old in text, old
    p = tmp_path / f"{stem}_bad.toml"
    p.write_text(text.replace(old, new, 1))
    return p


@pytest.mark.parametrize("stem,old,new,message", [
    ("leg_thesis", "[geometry]\n", '[geometry]\nl5 = { value = 0.1, unit = "m", source = "x" }\n',
     ":{line}: unknown field 'geometry.l5'"),
    ("leg_thesis", "[geometry]\n", "[geometri]\nl1 = 1\n[geometry]\n", "unknown section [geometri]; did you mean 'geometry'?"),
    ("leg_thesis", "lc3 = { value", "lcc3 = { value", "unknown field 'com.lcc3'; did you mean 'lc3'?"),
    ("leg_thesis", "g = { value = 9.81,", "g = { vlaue = 1, value = 9.81,", "unknown key 'vlaue'"),
    ("leg_thesis", "lc3 = { value = 0.093017", "lc3 = { value = 0.2", "field 'com.lc3' = 0.2 m lies beyond its link"),
    ("leg_thesis", "l4 = { value = 0.162", "l4 = { value = 0.3", "the five-bar cannot close"),
    ("odrive_thesis", 'motor_type = { value = 0', 'motor_type = { value = 7', "field 'config.motor_type' must be one of (0, 2, 3), got 7"),
    ("plant_default", "usb_jitter = { value = 1.0", "usb_jitter = { value = 5", "'sensing.usb_jitter'"),
    ("plant_default", "gap_max = { value = 160.0", "gap_max = { value = 1.0", "gap_min must be below gap_max"),
    ("plant_default", 'leg_set = "thesis"', 'leg_set = "nosuchleg"', "field 'leg.leg_set' = 'nosuchleg': no parameter set"),
    ("plant_default", 'mechanism = "fivebar"', 'mechanism = "fivebars"', "field 'leg.mechanism' must be one of"),
])
def test_typos_and_impossible_values_are_refused_at_load(tmp_path, stem, old, new, message):
    from leglib.params import load_odrive_config, load_plant
    loader = {"leg_thesis": load_leg, "odrive_thesis": load_odrive_config, "plant_default": load_plant}[stem]
    bad = _variant_of(tmp_path, stem, old, new)
    # {line}: the line the inserted field landed on (the line after the section header)
    if "{line}" in message:
        message = message.replace("{line}", str(bad.read_text().splitlines().index(old.strip()) + 2))
    with pytest.raises(ParameterError) as err:
        loader(bad)
    assert message in str(err.value) and str(bad) in str(err.value)


@pytest.mark.parametrize("call,message", [
    (lambda: load_leg("thesis", m3="heavy"), "field 'mass.m3': value must be a number, got 'heavy'"),
    (lambda: load_leg("thesis", g=float("nan")), "field 'environment.g': value must be finite"),
    (lambda: load_leg("thesis", encoder_cpr=4000.5), "must be an integer"),
    (lambda: load_leg("thesis", lc1=0.5), "field 'com.lc1' = 0.5 m lies beyond its link"),
    (lambda: load_leg("thesis", gg=1.0), "unknown field 'gg'; did you mean 'g'?"),
])
def test_keyword_overrides_pass_the_same_checks(call, message):
    with pytest.raises(ParameterError) as err:
        call()
    assert message in str(err.value) and "leg_thesis.toml" in str(err.value)


def test_plant_overrides_and_relations():
    from leglib.params import load_plant
    with pytest.raises(ParameterError, match="'scale.payload_mass': value must be non-negative"):
        load_plant("default", payload_mass=-3)
    with pytest.raises(ParameterError, match="gap_min must be below gap_max"):
        load_plant("default", gap_min=3.0, gap_max=0.1)
    assert load_plant("default", payload_mass=0.5).payload_mass == 0.5


def test_parameter_file_that_is_not_a_utf8_regular_file(tmp_path):
    d = tmp_path / "dir.toml"
    d.mkdir()
    with pytest.raises(ParameterError, match="not a regular file"):
        load_leg(d)
    p = tmp_path / "latin.toml"
    p.write_bytes(b"# caf\xe9\n")
    with pytest.raises(ParameterError, match=r"latin.toml:1: not UTF-8 text \(byte 0xe9\)"):
        load_leg(p)


@pytest.mark.parametrize("call, message", [
    (lambda: load_odrive_config("thesis", current_lim=1e9),
     "field 'config.current_lim' = 1e+09 A is implausible: it must be at most 60 (the ODrive v3.6's current sense"),
    (lambda: load_odrive_config("thesis", max_pos_gain=1e12),
     "field 'experiment.max_pos_gain' = 1e+12 (turn/s)/turn is implausible: it must be at most 1000"),
    (lambda: load_odrive_config("thesis", step_vel_limit=1e9), "field 'experiment.step_vel_limit' = 1e+09 turn/s"),
    (lambda: load_odrive_config("thesis", cpr=1), "field 'config.cpr' = 1 count/turn is implausible"),
    (lambda: load_leg("thesis", gear_ratio=1e-300), "field 'drive.gear_ratio' = 1e-300 - is implausible: it must "
                                                     "be [0.1, 100]"),
    (lambda: load_leg("thesis", encoder_cpr=1), "field 'drive.encoder_cpr' = 1 count/turn is implausible: it must "
                                                 "be [12, 1.67772e+07]"),
])
def test_implausible_overrides_are_refused(call, message):
    with pytest.raises(ParameterError) as err:
        call()
    assert message in str(err.value) and "(keyword override)" in str(err.value)


def test_implausible_plant_overrides_are_refused():
    from leglib.params import load_plant
    with pytest.raises(ParameterError, match=r"plant_default.toml \(keyword override\): field 'scale.payload_mass' "
                                             r"= 1e\+09 kg is implausible: it must be at most 5"):
        load_plant("default", payload_mass=1e9)
    # each transaction advances the twin by the latency: 1e6 s would make connect never return
    with pytest.raises(ParameterError, match=r"field 'sensing.usb_latency' = 1e\+06 s is implausible: it must be "
                                             r"at most 0.1"):
        load_plant("default", usb_latency=1e6)
    assert load_plant("default", payload_mass=2.0, usb_latency=0.05).usb_latency == 0.05


def test_implausible_file_value_is_refused_at_its_line(tmp_path):
    bad = _variant_of(tmp_path, "odrive_thesis", "current_lim = { value = 10.0", "current_lim = { value = 1e9")
    with pytest.raises(ParameterError, match=r"odrive_thesis_bad.toml:4: field 'config.current_lim' = 1e\+09 A is "
                                             r"implausible"):
        load_odrive_config(bad)


@pytest.mark.parametrize("old, new, field, value", [
    ('m3 = { value = 100.0, unit = "g"', 'm3 = { value = 1e9, unit = "g"', "mass.m3", "1e+06 kg"),     # 10^6 kg
    ('m1 = { value = 55.0,  unit = "g"', 'm1 = { value = 0.05,  unit = "g"', "mass.m1", "5e-05 kg"),
    ('value = 0.162, unit = "m"', 'value = 1.62e3, unit = "mm"', "geometry.l3", "1.62 m"),   # l3 and l4
    ('I3 = { value = 2.187e-4,  unit = "kg*m^2"', 'I3 = { value = 2.187,  unit = "kg*m^2"', "inertia.I3",
     "2.187 kg*m^2"),
    ('Jd1 = { value = 1.035928e-3, unit = "kg*m^2"', 'Jd1 = { value = 1.035928, unit = "kg*m^2"', "inertia.Jd1",
     "1.03593 kg*m^2"),
])
def test_a_leg_outside_its_class_is_refused_by_file_line_and_field_unless_allowed(tmp_path, old, new, field, value):
    """Masses, inertias and lengths are checked against a leg of this class (a lower link of
    10^6 kg loads no more); the named flag allow_implausible loads such a leg on purpose."""
    bad = _write_variant(tmp_path, old, new)
    bad.write_text(bad.read_text().replace(old, new))
    with pytest.raises(ParameterError, match=rf"leg_bad.toml:\d+: field '{field}' = {re.escape(value)} is "
                                             r"implausible.*allow_implausible=True"):
        load_leg(bad)
    leg = load_leg(bad, allow_implausible=True)
    assert getattr(leg, field.split(".")[1]) == pytest.approx(float(value.split()[0]), rel=1e-5)
    # a keyword override passes the same check
    with pytest.raises(ParameterError, match=r"\(keyword override\): field 'mass.m3' = 1e\+06 kg is implausible"):
        load_leg("thesis", m3=1e6)


def test_a_link_inertia_beyond_m_l_squared_is_refused(tmp_path):
    bad = _write_variant(tmp_path, 'I4 = { value = 2.187e-4', 'I4 = { value = 4e-3')
    with pytest.raises(ParameterError, match=r"field 'inertia.I4' = 0.004 kg\*m\^2 is implausible: a link's inertia "
                                             r"about its centre of mass is at most m4 l4\^2"):
        load_leg(bad)
    assert load_leg(bad, allow_implausible=True).I4 == 4e-3


def test_every_shipped_leg_and_plant_is_plausible():
    from leglib.params import load_plant, plant_names
    for name in plant_names():
        load_plant(name).base_leg()
