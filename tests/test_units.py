"""Numbers with their unit and the digits their interval supports (leglib.units)."""

import math

import pytest

from leglib import units as U


@pytest.mark.parametrize("half, places", [
    (0.0065, 3),    # one significant digit of the half-width: 0.007 -> three decimals
    (0.03, 3),      # leading digits 300 < 355: two significant digits -> 0.030
    (0.07, 2),
    (0.35, 2),      # leading digits 350 < 355: two digits
    (0.355, 1),     # 355: one digit
    (0.0996, 2),    # 996 rounds up into the next decade: 0.10, two digits
    (35.0, 0),
    (40.0, -1),     # tens
    (1e-6, 7),
])
def test_decimals_follow_the_half_width(half, places):
    assert U.decimals(half) == places


@pytest.mark.parametrize("bad", [0.0, -1.0, math.inf, math.nan])
def test_no_decimals_without_a_half_width(bad):
    assert U.decimals(bad) is None


def test_a_value_is_written_to_its_intervals_decimal_and_never_past_it():
    assert U.interval_text(0.37093, (0.36472, 0.37801)) == "0.371 [0.365, 0.378]"
    assert U.interval_text(0.2424, (0.162, 0.323)) == "0.24 [0.16, 0.32]"
    assert U.interval_text(5.021, (4.47, 5.57), "Hz") == "5.0 [4.5, 5.6] Hz"
    assert U.interval_text(1234.5, (1194.5, 1274.5)) == "1230 [1190, 1270]"
    # a wider interval never gets more digits than a narrower one
    widths = [1e-4, 1e-3, 1e-2, 1e-1]
    shown = [U.interval_text(0.123456, (0.123456 - w, 0.123456 + w)).split(" ")[0] for w in widths]
    assert [len(s) for s in shown] == sorted((len(s) for s in shown), reverse=True)
    # the printed value is the value rounded to that decimal (what a reader computes with)
    assert U.shown(0.2424, (0.162, 0.323)) == 0.24


def test_intervals_without_a_width_say_so():
    assert U.interval_text(0.239, (0.0, math.inf)) == "0.239 [0, ∞]"
    assert U.interval_text(0.239, (math.nan, math.nan)) == "0.239 (no interval)"
    assert U.interval_text(0.239, None, "Hz") == "0.239 (no interval) Hz"
    assert U.interval_text(0.0981, (0.0981, 0.0981)) == "0.0981"
    assert U.interval_text(-0.0, (-0.001, 0.001)) == "0.0000 [-0.0010, 0.0010]"   # no "-0.0000"


def test_relative_errors_in_percent_with_their_interval():
    assert U.percent_interval_text(0.0123, (-0.003, 0.027)) == "+1.2 % [−0.3, +2.7] %"
    assert U.percent_interval_text(0.01, (-0.324, 0.344)) == "+1 % [−32, +34] %"


def test_significant_digits_without_an_interval():
    assert U.quantity_text(0.098014, "N*m*s/rad") == "0.0980 N·m·s/rad"
    assert U.significant(8.1e-5, 2) == "8.1e-05"          # never "0.000"
    assert U.significant(0.0002, 2) == "0.00020"
    assert U.significant(273.456) == "273"
    assert U.significant(0.0) == "0"


@pytest.mark.parametrize("num, dens, expected", [
    ("N*m", ("rad",), "N·m/rad"),                 # a state-feedback gain on an angle
    ("N*m", ("rad/s",), "N·m·s/rad"),             # ... on an angular velocity
    ("rad/s", ("rad",), "1/s"),                   # an observer gain on an angle's rate
    ("rad/s^2", ("rad",), "1/s²"),                # ... on an angular velocity's rate
    ("N*m", ("rad*s",), "N·m/(rad·s)"),           # an integral gain
    ("rad/s", ("rad", "s"), "1/s²"),
    ("kg*m^2", ("kg",), "m²"),
    ("m", ("m",), "-"),                           # dimensionless
])
def test_derived_units(num, dens, expected):
    assert U.derived(num, *dens) == expected


def test_pretty_units_and_what_it_cannot_read():
    assert U.pretty("kg*m^2") == "kg·m²" and U.pretty("m/s^2") == "m/s²" and U.pretty("count/turn") == "count/turn"
    assert U.pretty("-") == "-" and U.pretty("") == ""
    assert U.pretty("(turn/s)/turn") == "(turn/s)/turn"      # not parsed: left as written
    with pytest.raises(ValueError, match="cannot read"):
        U.Unit.parse("N*m!")


def test_dynamics_text():
    assert U.dynamics_text(0.2424, 5.021, (0.162, 0.323), (4.47, 5.57)) == "zeta 0.24 [0.16, 0.32], fn 5.0 [4.5, 5.6] Hz"
    assert U.dynamics_text(0.2424, 5.021, (0.162, 0.323), (4.47, 5.57), zeta_name="ζ", sep="=") == \
        "ζ = 0.24 [0.16, 0.32], fn = 5.0 [4.5, 5.6] Hz"
    assert U.dynamics_text(0.2424, 5.021) == "zeta 0.242, fn 5.02 Hz"


def test_units_read_back_as_written_and_compare_in_any_order():
    for text in ("N·m·s/rad", "1/s²", "N·m/(rad·s)", "rad/(N·m·s²)", "kg·m²"):
        assert str(U.Unit.parse(text)) == text
    assert U.Unit.parse("m*N") == U.Unit.parse("N*m") and U.Unit.parse("N*m") != U.Unit.parse("N")
    assert U.Unit.parse("rad/s/s") == U.Unit.parse("rad/s^2")
