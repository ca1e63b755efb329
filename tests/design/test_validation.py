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
    assert ax.get_title() == "one: error per target" and len(ax.lines) == 2
