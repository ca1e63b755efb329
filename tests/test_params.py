"""Parameter files: shipped sets load in SI; malformed files are rejected by name."""

import math
from pathlib import Path

import pytest

from leglib.params import (PARAMS_DIR, ParameterError, load_leg, load_motor,
                           load_odrive_config)


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
