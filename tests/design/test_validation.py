"""One validation routine (notebook 05, the robustness table, the CLI): a target a method
has no answer for is outside, without an error; a check that is not a second-order step is
an infinite error, counted, never dropped."""

import math

import numpy as np
import pytest

import leglib as lg
from leglib.design.gainmap import Choice
from leglib.design.points import identify_response
from leglib.design.validation import Validation
from leglib.errors import OutsideRegionError

STABLE = (50.0, 0.046, 0.001)
UNSTABLE = (50.0, 0.002, 0.08)


@pytest.fixture(scope="module")
def dev():
    d = lg.connect("virtual", seed=21)
    lg.configure(d)
    lg.calibrate(d)
    return d


def test_a_known_answer_outside_and_unidentifiable_targets(dev):
    p = identify_response(lg.step_response(dev, *STABLE), dev.leg)
    reachable = (p.zeta, p.fn)
    far = (3.0, 40.0)
    fails = (0.1, 2.0)

    def gains_of(target):
        if target == far:
            raise OutsideRegionError(target, Choice(STABLE, p.zeta, p.fn, 1.0), 0.05)
        return (UNSTABLE if target == fails else STABLE), 2, target, "a note"

    v = lg.validate(dev, [reachable, far, fails], gains_of, "test", setup_experiments=7)
    assert isinstance(v, Validation) and [r.outside for r in v.rows] == [False, True, False]
    ok, outside, failed = v.rows
    assert ok.identified and max(abs(e) for e in ok.error) < 0.02   # the same gains measure again alike
    assert math.isnan(outside.error[0]) and outside.nearest == (p.zeta, p.fn) and outside.experiments == 0
    assert not failed.identified and failed.error == (math.inf, math.inf)
    s = v.summary()
    assert s["targets"] == 2 and s["outside_region"] == 1 and s["unidentified"] == 1
    assert s["worst"] == math.inf and s["median_zeta"] == np.median([abs(ok.error[0]), math.inf])
    assert s["experiments"] == 7 + 3 + 3
    md = v._repr_markdown_()
    assert "outside the region" in md and "not identifiable" in md and "∞" in md and "a note" not in md


def test_a_validation_plots_itself(dev):
    import matplotlib
    matplotlib.use("Agg")
    v = lg.validate(dev, [(0.2, 3.0)], lambda t: (STABLE, 0, None, ""), "one")
    ax = v.plot()
    assert ax.get_title() == "one: error per target"
    # zeta and fn, each a marker at its error with its 90 % interval as a bar
    bars = ax.containers
    assert len(bars) == 2
    r = v.rows[0]
    for bar, e, (lo, hi) in zip(bars, r.error, r.error_interval):
        (x,), (y,) = bar.lines[0].get_data()
        assert y == pytest.approx(100 * e)
        seg = bar.lines[2][0].get_segments()[0]
        assert sorted(p[1] for p in seg) == pytest.approx([100 * lo, 100 * hi])


def test_errors_are_intervals_and_reached_needs_them_inside_the_tolerance(dev):
    """A target the check measures closely: its error interval holds its error, and it is
    reached within a tolerance only when both intervals lie inside it."""
    p = identify_response(lg.step_response(dev, *STABLE), dev.leg)
    target = (p.zeta, p.fn)
    v = lg.validate(dev, [target], lambda tg: (STABLE, 0, None, ""), "fixed", tolerance=0.05)
    r = v.rows[0]
    (zl, zh), (fl, fh) = r.error_interval
    assert zl <= r.error[0] <= zh and fl <= r.error[1] <= fh
    ok, why = r.reached(0.05)
    inside = max(abs(zl), abs(zh), abs(fl), abs(fh)) <= 0.05
    assert ok == inside and (why.startswith("reached") == inside)
    s = v.summary()
    assert s["worst_bound"] >= s["worst"] and s["reached"] == int(ok) and s["error_intervals"][0] == [[zl, zh],
                                                                                                    [fl, fh]]
    assert "90 % interval" in v.markdown() and "within ±5%?" in v.markdown()
    # a tolerance below the intervals' half-width: the verdict says it cannot be told
    ok, why = r.reached(1e-4)
    assert not ok and "larger than the tolerance" in why


def test_error_statistics_are_the_statistics_of_the_intervals_bounds():
    """The median and worst |error| of items with 90 % intervals, and the ranges those allow:
    |x| of an interval holding 0 starts at 0; an infinite error (not identifiable) counts,
    a NaN one (outside) does not; an item without an interval leaves no range."""
    from leglib.design.validation import abs_interval, error_statistics

    assert abs_interval((-0.02, 0.05)) == (0.0, 0.05) and abs_interval((-0.05, -0.01)) == (0.01, 0.05)
    errors = [0.01, -0.03, 0.002, math.nan]
    ivs = [(-0.01, 0.03), (-0.05, -0.02), (0.001, 0.004), (math.nan, math.nan)]
    s = error_statistics(errors, ivs)
    assert s["median"] == 0.01 and s["worst"] == 0.03
    assert s["median_interval"] == (0.001, 0.03) and s["worst_interval"] == (0.02, 0.05)
    assert s["median_interval"][0] <= s["median"] <= s["median_interval"][1]
    s = error_statistics(errors + [math.inf], ivs + [(math.nan, math.nan)])
    assert s["worst"] == math.inf and s["worst_interval"] == (math.inf, math.inf)
    assert s["median"] == 0.02 and s["median_interval"] == (0.0105, 0.04)   # between items 2 and 3
    assert error_statistics([0.01], [(math.nan, math.nan)])["worst_interval"] is None
    assert error_statistics([math.nan], [(math.nan, math.nan)])["worst"] != 0.0   # NaN: no items


def test_a_target_outside_keeps_the_nearest_points_intervals(dev):
    p = identify_response(lg.step_response(dev, *STABLE), dev.leg)
    near = Choice(STABLE, p.zeta, p.fn, 1.0, p.zeta_interval, p.fn_interval)

    def gains_of(target):
        raise OutsideRegionError(target, near, 0.05)

    v = lg.validate(dev, [(3.0, 40.0)], gains_of, "test")
    r = v.rows[0]
    assert r.outside and r.nearest_intervals == (p.zeta_interval, p.fn_interval)
    assert f"nearest {p.text().replace('zeta', 'ζ')}" in v.markdown()
    s = v.summary()
    assert s["median_interval"] is None and math.isnan(s["worst"])
