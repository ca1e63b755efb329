"""The one classifier (leglib.design.points): a step that does not reach its commanded value
or that the fit only rings through is "failed" everywhere, the map and the thesis's readings
agree point for point, and an "ok" point carries its intervals."""

import math

import numpy as np
import pytest

import leglib as lg
from leglib import thesis
from leglib.design.points import (
    REACH_FRACTION,
    commanded_height,
    identify_many,
    identify_response,
    reach_problem,
    step_shape_problem,
)
from leglib.errors import ArgumentError
from leglib.experiments.step import StepResponse
from leglib.identify.fastfit import model
from leglib.model.drive import AxisMap
from leglib.model.kinematics import foot_position
from leglib.notebook import widgets

STALLED = (50.0, 0.002, 0.001)   # notebook 04's panel: the foot stops 28 mm short and stays


@pytest.fixture(scope="module")
def dev():
    d = lg.connect("virtual", seed=11)
    lg.configure(d)
    lg.calibrate(d)
    yield d
    d.close()


@pytest.fixture(scope="module")
def thesis_sweep(dev, tmp_path_factory):
    """The thesis grid and the stalled panel point, swept on the twin into files."""
    out = tmp_path_factory.mktemp("thesis_grid")
    grid = np.vstack([lg.thesis_grid(), [STALLED]])
    lg.sweep(dev, grid, out, progress=False)
    return out, grid


def test_the_map_and_the_thesis_readings_classify_alike(dev, thesis_sweep):
    """The map's classifier and thesis.read_sweep over the thesis grid on the twin: the same
    points "ok", "failed", "unstable" (they once counted 360/7 against 365/2)."""
    out, grid = thesis_sweep
    gm = lg.GainMap.from_measurements(out, leg=dev.leg)
    rows = thesis.read_sweep(out, dev.leg)
    by_gains = {tuple(np.round(p.gains, 6)): (p.status, p.reason) for p in gm.points}
    assert len(rows) == len(by_gains) == len(grid)
    for r in rows:
        assert (r["status"], r["reason"]) == by_gains[tuple(np.round(r["gains"], 6))], r["gains"]
    counts = gm.counts()
    assert counts["ok"] > 300 and counts["failed"] >= 5 and counts["unstable"] > 0
    # only "ok" rows carry true numbers, each with its interval around it
    for r in rows:
        if r["status"] == "ok":
            assert r["zeta_interval"][0] <= r["zeta"] <= r["zeta_interval"][1]
            assert r["fn_interval"][0] <= r["fn"] <= r["fn_interval"][1]
        else:
            assert math.isnan(r["zeta"]) and math.isnan(r["fn"])


def test_the_stalled_step_is_failed_in_the_map_the_panel_and_the_readings(dev, thesis_sweep):
    out, _ = thesis_sweep
    key = tuple(np.round(STALLED, 6))
    point = next(p for p in lg.GainMap.from_measurements(out, leg=dev.leg).points
                 if tuple(np.round(p.gains, 6)) == key)
    row = next(r for r in thesis.read_sweep(out, dev.leg) if tuple(np.round(r["gains"], 6)) == key)
    assert point.status == row["status"] == "failed"
    assert "does not reach its commanded final value" in point.reason
    assert math.isnan(point.zeta) and math.isnan(row["zeta"])
    # the panel: the same step, run alone
    resp = lg.step_response(dev, *STALLED)
    p = identify_response(resp, dev.leg)
    assert p.status == "failed" and "does not reach" in p.reason
    text = widgets.step_readout(resp, p, leg=dev.leg)
    assert text.startswith("not a second-order step: does not reach") and "zeta =" not in text
    # it ends far short of the setpoint, as measured
    assert (p.commanded - p.final) / (p.commanded - np.mean(resp.y[:10])) > REACH_FRACTION
    # and its residuals say so on their own: the fit still rings where the foot has stopped
    assert "still rings" in step_shape_problem(resp.t, resp.y, p.fit)


def test_every_grid_point_that_does_not_reach_its_step_is_failed(dev, thesis_sweep):
    """A property over the grid: a completed step whose final value lies beyond the band is
    failed with that reason; an "ok" one lies inside it."""
    out, _ = thesis_sweep
    gm = lg.GainMap.from_measurements(out, leg=dev.leg)
    responses = StepResponse.from_measurements(lg.files.sweepdir.read_measurements(out).measurements, dev.leg)
    by_gains = {tuple(np.round(p.gains, 6)): p for p in gm.points}
    for r in responses:
        if not r.completed:
            continue
        p = by_gains[tuple(np.round(r.gains, 6))]
        final = np.mean(r.y[-(r.y.size // 5):])
        start = np.mean(r.y[:max(3, r.y.size // 50)])
        short = abs(p.commanded - final) / abs(p.commanded - start)
        if short > REACH_FRACTION + 0.01:
            assert p.status == "failed" and "does not reach" in p.reason, (r.gains, short)
        if p.status == "ok":
            assert short <= REACH_FRACTION + 0.01


def _joint_step(leg, a, step=0.4, gains=(40.0, 0.08, 0.01)):
    """A StepResponse whose joints move along the commanded step by the profile ``a`` (0 ->
    the fraction reached), the foot height by the exact five-bar."""
    t = np.arange(a.size) * 0.002
    dq1, dq2 = AxisMap.from_leg(leg).motor_step_to_joint_step(step)
    q1, q2 = leg.q1 + dq1 * a, leg.q2 + dq2 * a
    return StepResponse(t=t, q1=q1, q2=q2, y=foot_position(leg, q1, q2)[1], gains=gains, step=step)


@pytest.mark.parametrize("reached, ok", [(1.0, True), (0.8, True), (0.45, False), (0.2, False)])
def test_reach_is_judged_against_the_commanded_foot_height(leg, reached, ok):
    t = np.arange(750) * 0.002
    a = reached * model(t, 0.4, 40.0, 1.0, 0.0, 0.0)
    resp = _joint_step(leg, a)
    assert commanded_height(resp, leg) == pytest.approx(foot_position(leg, *(
        np.array(leg.q0) + AxisMap.from_leg(leg).motor_step_to_joint_step(0.4)))[1])
    problem = reach_problem(resp, leg)
    assert (problem is None) == ok, problem
    p = identify_response(resp, leg)
    assert (p.status == "ok") == ok, p.reason
    if ok:
        lo, hi = p.zeta_interval
        # (the joints' zeta is 0.4; the foot height, a nonlinear function of them, is another
        # response with its own zeta)
        assert lo <= p.zeta <= hi and 0.2 < p.zeta < 0.5
        assert p.to_dict()["zeta_interval"] == [lo, hi]
    else:
        assert "short of the commanded" in p.reason and math.isnan(p.zeta) and p.to_dict()["status"] == "failed"


def test_the_classifier_needs_the_leg(leg):
    resp = _joint_step(leg, np.linspace(0, 1, 100))
    with pytest.raises(ArgumentError, match="leg"):
        identify_response(resp, None)
    with pytest.raises(ArgumentError, match="leg"):
        identify_many([resp], "fit")
    with pytest.raises(ArgumentError, match="leg"):
        widgets.step_readout(resp)
