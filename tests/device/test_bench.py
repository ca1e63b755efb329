"""A day at the bench: configure once, calibrate once per power-up, the zero kept; the
ledger's bench time at real speed, the cost model beforehand, the limit on the real leg.

"The USB code path" below is leglib's own (``connect("usb")`` -> ``odrive.find_any`` on a
worker thread, reconnection by serial number after a save, polled steps, a file per sweep
point) with the twin put behind ``odrive.find_any``, as the thesis listings' tests do it.
"""

import functools
import json
import math
import time
import warnings
from types import SimpleNamespace

import numpy as np
import pytest

import leglib as lg
from leglib.design.statefeedback import place_poles, run_live
from leglib.device import bench, setup
from leglib.device.virtual import find_any
from leglib.device.virtual import firmware as V
from leglib.errors import BenchLimitError
from leglib.experiments.step import return_to_rest
from leglib.files.sweepdir import list_measurements
from leglib.model.drive import AxisMap
from leglib.twin import layout as L

odrive = pytest.importorskip("odrive")

STABLE = (50.0, 0.046, 0.001)
CALIBRATION_STATES = (V.AXIS_STATE_FULL_CALIBRATION_SEQUENCE, V.AXIS_STATE_MOTOR_CALIBRATION,
                      V.AXIS_STATE_ENCODER_OFFSET_CALIBRATION)


@pytest.fixture
def requests(monkeypatch):
    """Every state request the virtual boards made from now on take up, as (axis, state)."""
    seen = []
    real = V.VirtualODrive._request_state

    def spy(self, a, value):
        seen.append((a, int(value)))
        return real(self, a, value)
    monkeypatch.setattr(V.VirtualODrive, "_request_state", spy)
    return seen


@pytest.fixture
def usb(monkeypatch, tmp_path):
    """``lg.connect("usb")`` reaches the virtual board of seed 26 through ``odrive.find_any``;
    zeros of real boards would be kept under tmp_path."""
    monkeypatch.setenv("LEGLIB_STATE_DIR", str(tmp_path / "state"))
    monkeypatch.setattr(odrive, "find_any", functools.partial(find_any, seed=26))
    return lambda: lg.connect("usb", timeout=5.0)


def _calibrations(requests):
    return [r for r in requests if r[1] in CALIBRATION_STATES]


# ---------------------------------------------------------------------------------------
# idempotent configuration and calibration
# ---------------------------------------------------------------------------------------

def test_configure_writes_and_saves_only_what_differs(capsys):
    d = lg.connect("virtual", seed=21)
    first = lg.configure(d, verbose=True)
    assert first.saved and first.rebooted and d.sim.boot_count == 1
    assert "axis0.encoder.config.cpr: 8192 -> 4000" in first.differences
    assert "config.enable_brake_resistor: False -> True" in first.differences
    again = lg.configure(d, verbose=True)
    assert again.differences == [] and not again.written and not again.saved and d.sim.boot_count == 1
    assert "nothing written" in capsys.readouterr().out.splitlines()[-1]
    # a step leaves its own velocity limit: written for the session, never a reason to reboot
    lg.calibrate(d)
    lg.step_response(d, *STABLE)
    runtime = lg.configure(d)
    assert runtime.written and not runtime.saved and d.sim.boot_count == 1
    assert runtime.differences == ["axis0.controller.config.vel_limit: 12 -> 2",
                                   "axis1.controller.config.vel_limit: 12 -> 2"]
    assert float(d.get(0, "vel_limit")) == 2.0
    # a stored value changed behind leglib's back: found, written, saved (one reboot)
    d.set(1, "pole_pairs", 7)
    stored = lg.configure(d)
    assert stored.differences == ["axis1.motor.config.pole_pairs: 7 -> 11"] and stored.rebooted
    assert d.sim.boot_count == 2 and int(d.get(1, "pole_pairs")) == 11
    # and force writes and saves what is already there
    assert lg.configure(d, force=True).rebooted and d.sim.boot_count == 3


def test_needs_reads_the_board_without_changing_it():
    d = lg.connect("virtual", seed=22)
    n = setup.needs(d)
    assert n.save and n.reboot and n.calibrate_axes == (0, 1) and d.sim.boot_count == 0
    lg.configure(d)
    lg.calibrate(d)
    n = setup.needs(d)
    assert not n.save and not n.reboot and n.calibrate_axes == () and n.differences == []


def _excursion(monkeypatch, dev):
    """The largest change of the twin's joint angles [rad] (its plant's state, not what the
    encoders say) from now on, seen after every wait of the host."""
    sim = dev.sim
    start = sim.st.X[0, [L.X_Q1, L.X_Q2]].copy()
    worst = [0.0]
    real = sim.sleep

    def sleep(seconds):
        real(seconds)
        worst[0] = max(worst[0], float(np.max(np.abs(sim.st.X[0, [L.X_Q1, L.X_Q2]] - start))))
    monkeypatch.setattr(sim, "sleep", sleep)
    return worst


def test_a_second_calibrate_on_a_ready_board_does_not_move_the_leg(requests, monkeypatch):
    d = lg.connect("virtual", seed=23)
    lg.configure(d)
    first = lg.calibrate(d)
    assert first.axes == (0, 1) and first.zeroing == "calibration"
    assert sorted(a for a, _ in _calibrations(requests)) == [0, 1]
    zero = d.axes.zero
    counts = (d.counts(0), d.counts(1))
    del requests[:]
    d.close()
    # the next session (another notebook): the same virtual board, its calibration kept for
    # its life as a powered board keeps it
    d = lg.connect("virtual", seed=23)
    moved = _excursion(monkeypatch, d)
    second = lg.calibrate(d)
    assert second.axes == () and second.zeroing == "kept" and "did not move" in second.text
    assert _calibrations(requests) == []                                # no calibration state, and
    assert {s for _, s in requests} == {V.AXIS_STATE_IDLE}               # nothing but IDLE requested
    # the encoders did not move beyond the creep: the leg only settled on (a leg resting within
    # its friction dead band creeps by hundredths of a degree, a count of the motor's 4000 is
    # 0.03 deg of joint: about a count a second here, as on a board left alone): no swing
    assert all(abs(now - then) <= 1 for now, then in zip((d.counts(0), d.counts(1)), counts))
    assert moved[0] < math.radians(0.05)
    assert d.axes.zero == zero
    # force calibrates anyway: each encoder offset scan swings its link about 87 deg
    moved = _excursion(monkeypatch, d)
    assert lg.calibrate(d, force=True).axes == (0, 1) and len(_calibrations(requests)) == 2
    assert moved[0] > math.radians(40)


def test_calibrate_calibrates_only_the_axis_that_needs_it(requests):
    d = lg.connect("virtual", seed=24)
    lg.configure(d)
    lg.calibrate(d)
    del requests[:]
    d.sim._axis[1]["encoder_ready"] = False        # as after an encoder fault on axis 1 alone
    c = lg.calibrate(d)
    assert c.axes == (1,) and [a for a, _ in _calibrations(requests)] == [1]
    # the motor kept its calibration: only the encoder offset calibration ran
    assert [s for _, s in _calibrations(requests)] == [V.AXIS_STATE_ENCODER_OFFSET_CALIBRATION]


def test_a_moved_rest_pose_is_detected_and_said():
    d = lg.connect("virtual", seed=25)
    lg.configure(d)
    lg.calibrate(d)
    # the zero noted for this power-up is now 0.05 motor turn (6 deg of joint) from where
    # the leg rests: as if the leg had been moved on its stop (or the belt slipped)
    z = setup._ZEROS[d.serial]
    setup._ZEROS[d.serial] = setup._Zero(z.serial, (z.turns[0] + 0.05, z.turns[1]), z.uptime_ms, z.clock, z.wall)
    with pytest.warns(UserWarning, match=r"the rest pose moved since this power-up's calibration \(by -6\.\d and"):
        c = lg.calibrate(d)
    assert c.zeroing == "moved" and c.axes == ()
    assert c.zero[0] == pytest.approx(z.turns[0], abs=setup.REST_TOLERANCE)
    # the new zero is kept: the next session finds the leg where it was zeroed
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert lg.calibrate(d).zeroing == "kept"


def test_a_reboot_voids_the_zero_and_the_calibration(requests):
    d = lg.connect("virtual", seed=27)
    lg.configure(d)
    lg.calibrate(d)
    d = lg.apply_gains(d, STABLE, save=True)            # saving reboots the board (0.5.6)
    assert d.serial not in setup._ZEROS
    del requests[:]
    c = lg.calibrate(d)
    assert c.axes == (0, 1) and c.zeroing == "calibration" and len(_calibrations(requests)) == 2


class _Board:
    """A real board as the zero's note sees it: a serial number, an uptime, the host's clock
    (no virtual board behind it), the leg's axes."""

    backend = "usb"

    def __init__(self, serial, uptime_s):
        self.serial = serial
        self.__dict__["_serial"] = serial
        self.axes = AxisMap.from_leg(lg.load_leg("thesis"))
        self.raw = SimpleNamespace(system_stats=SimpleNamespace(uptime=int(uptime_s * 1000)))

    def board_clock(self):
        return time.monotonic()


def test_the_zero_of_a_real_board_is_kept_across_processes(monkeypatch, tmp_path):
    """A notebook is a process: the zero a calibration noted on a real board is found by the
    next process while the board runs from the same power-up (its uptime grew by the time
    that passed), and refused once it rebooted."""
    monkeypatch.setenv("LEGLIB_STATE_DIR", str(tmp_path))
    now = [1000.0]
    monkeypatch.setattr(setup.time, "time", lambda: now[0])
    b = _Board(0x1234ABCD, uptime_s=60.0)
    setup._note_zero(b, (0.25, -0.5))
    assert b.axes.zero == (0.25, -0.5)
    saved = json.loads((tmp_path / "boards" / "00001234ABCD.json").read_text())
    assert saved["turns"] == [0.25, -0.5] and saved["serial"] == "00001234ABCD"
    setup._ZEROS.clear()                                  # the next process
    now[0] += 600.0                                       # ten minutes later, the board ran on
    b.raw.system_stats.uptime = int((60.0 + 600.0) * 1000) + 40   # (USB latency, drift)
    assert setup._known_zero(b).turns == (0.25, -0.5)
    b.raw.system_stats.uptime = int(300.0 * 1000)         # it rebooted 5 minutes ago
    assert setup._known_zero(b) is None
    b.raw.system_stats.uptime = int(30.0 * 1000)          # ... or just now
    assert setup._known_zero(b) is None
    # a note that cannot be read is no note
    (tmp_path / "boards" / "00001234ABCD.json").write_text("{not json")
    b.raw.system_stats.uptime = int((60.0 + 600.0) * 1000)
    assert setup._known_zero(b) is None


@pytest.mark.parametrize("noted_ms, uptime_ms, passed, same", [
    (60_000, 60_000 + 600_000, 600.0, True),             # the same power-up, ten minutes on
    (60_000, 60_000 + 600_000 + 1_500, 600.0, True),     # latency and drift within the slack
    (60_000, 300_000, 600.0, False),                     # rebooted meanwhile
    (60_000, 59_000, 0.5, False),                        # the uptime went back: a reboot
    ((1 << 32) - 1_000_000, 1_000_000, 2_000.0, True),   # the uint32 ms counter wrapped (49.7 days)
    ((1 << 32) - 1_000_000, 500_000, 2_000.0, False),    # ... and a reboot after the wrap
])
def test_same_boot_from_uptime_and_elapsed_time(noted_ms, uptime_ms, passed, same):
    z = setup._Zero(1, (0.0, 0.0), noted_ms, clock=10.0, wall=0.0)
    assert setup._same_boot(z, uptime_ms, 10.0 + passed, 0.0) is same


# ---------------------------------------------------------------------------------------
# the USB code path: a day of notebooks 02-05 on one powered board
# ---------------------------------------------------------------------------------------

@pytest.mark.slow
def test_notebooks_02_to_05_on_one_board_configure_once_and_calibrate_once(usb, requests, tmp_path):
    """The experiments of notebooks 02-05, each notebook's sessions as the notebook opens
    them, through leglib's USB code path: the board is configured (saved, one reboot) once
    and calibrated once (one request per axis); every later session reads the configuration
    back, finds the encoders ready and keeps the zero."""
    m = bench.mark()
    leg = lg.load_leg("thesis")
    sessions = []

    def session(run):
        with usb() as d:
            assert d.backend == "usb" and d.sim is None          # driven as a real board
            sessions.append((lg.configure(d), lg.calibrate(d)))
            run(d)
            return d

    # 02: the friction experiment, then a step
    first = session(lambda d: lg.friction_experiment(d, duration=1.0, ramp=0.2))
    session(lambda d: lg.step_response(d, *STABLE))
    # 03: a playback, back to rest, a live loop
    session(lambda d: (lg.play_torque_table(d, np.full((250, 2), 0.01)), return_to_rest(d, move_time=0.5),
                       run_live(d, place_poles(lg.linearize(leg)), leg, duration=0.5)))
    # 04: a (small) sweep, its file per point, then the target's step
    session(lambda d: lg.sweep(d, lg.thesis_grid(2, 2, 1), tmp_path / "sweep", progress=False, max_minutes=1))
    session(lambda d: lg.step_response(d, 30.0, 0.05, 0.01))
    # 05: a validation step and a design of two steps
    session(lambda d: lg.tune(d, 0.24, 5.0, max_experiments=2))

    board = first._board_sim
    assert board.boot_count == 1                                     # one save, one reboot
    assert sorted(a for a, _ in _calibrations(requests)) == [0, 1]   # one calibration per axis
    configured, calibrated = zip(*sessions)
    assert [c.saved for c in configured] == [True] + [False] * 5
    assert [c.axes for c in calibrated] == [(0, 1)] + [()] * 5
    # the zero kept, or set anew where the leg rests if it came to rest elsewhere (calibrate's
    # 3 deg; after session 03's live loop the twin's leg rests 6 deg off in the whole leg's
    # rotation, within its friction dead band, at the cited 0.36 ms per transaction): never
    # a calibration again
    assert calibrated[0].zeroing == "calibration"
    assert {c.zeroing for c in calibrated[1:]} <= {"kept", "moved"}
    assert len(list_measurements(tmp_path / "sweep")) == 4            # a real leg's sweep: a file per point
    r = bench.report(m, serial=first.serial, clock=board.time)
    assert r.backend == "usb" and r.counts["save"] == 1 and r.counts["reboot"] == 1
    assert r.counts["calibration"] == 2 and r.counts["step"] == 1 + 4 + 1 + 2 and r.counts["torque"] == 3


# ---------------------------------------------------------------------------------------
# the cost model and the ledger
# ---------------------------------------------------------------------------------------

def test_the_cost_model_agrees_with_the_twin_s_polled_runs():
    """Each cost beforehand (bench.*_seconds) against what the same operation takes on the
    virtual board's clock on the polling path, as on the leg: within 1 %. The cost model is
    the mean: the board's transactions cost exactly that here (usb_jitter 0; their spread
    and tail average out over a run, tests/device/test_firmware.py)."""
    d = lg.connect("virtual", seed=28, plant=lg.load_plant("default", usb_jitter=0.0))
    lat = d.sim.twin.plant.usb_latency

    def took(f):
        t0 = d.time()
        f()
        return d.time() - t0
    assert took(lambda: lg.configure(d)) == pytest.approx(bench.config_check_seconds(lat) + bench.reboot_seconds(lat),
                                                          rel=0.01)
    assert took(lambda: lg.calibrate(d)) == pytest.approx(bench.calibration_seconds(2, lat), rel=0.01)
    assert took(lambda: lg.configure(d)) == pytest.approx(bench.config_check_seconds(lat), rel=0.1)  # (ms)
    assert took(lambda: lg.calibrate(d)) == pytest.approx(bench.rest_seconds(lat), rel=0.01)
    for duration, settle in ((1.5, 2.0), (0.5, 0.3)):
        assert took(lambda: lg.step_response(d, *STABLE, duration=duration, settle=settle, path="polled")) \
            == pytest.approx(bench.step_seconds(duration, settle, latency=lat), rel=0.01)
    assert took(lambda: lg.play_torque_table(d, np.full((500, 2), 0.01))) \
        == pytest.approx(bench.torque_seconds(1.0, lat), rel=0.01)
    assert took(lambda: return_to_rest(d)) == pytest.approx(bench.hold_seconds(latency=lat), rel=0.01)


def test_a_batched_step_is_charged_what_the_polled_one_costs():
    """The twin runs a step whole in its kernel (and its settle as 2 s); the ledger charges
    it what the leg's polling path costs, so a rehearsal's steps add up as the leg's."""
    d = lg.connect("virtual", seed=29)
    lg.configure(d)
    lg.calibrate(d)
    m = bench.mark(d)
    lg.step_response(d, *STABLE, path="polled")
    polled = bench.report(m, d).seconds
    m = bench.mark(d)
    lg.step_response(d, *STABLE, path="batched")
    batched = bench.report(m, d)
    assert batched.counts == {"step": 1} and batched.charged != 0
    assert batched.seconds == pytest.approx(polled, rel=0.005)
    # an unstable step ends at its abort, on the leg as in the kernel
    m = bench.mark(d)
    r = lg.step_response(d, 50.0, 0.002, 0.08, path="batched")
    assert not r.completed and bench.report(m, d).seconds < polled - 0.5


def test_the_plan_agrees_with_the_rehearsal():
    d = lg.connect("virtual", seed=30)
    plan = bench.Plan(steps=2, torque=(1.0,), holds=1)
    run = setup.start_run(d, plan)
    assert run.planned == pytest.approx(plan.seconds(reboot=True, calibrate_axes=2))
    lg.configure(d)
    lg.calibrate(d)
    lg.step_response(d, *STABLE)
    lg.step_response(d, 30.0, 0.05, 0.01)
    lg.play_torque_table(d, np.full((500, 2), 0.01))
    return_to_rest(d)
    r = run.report()
    assert r.counts == {"configure": 1, "save": 1, "reboot": 1, "calibration": 2, "step": 2, "torque": 1,
                        "hold": 1}
    assert r.seconds == pytest.approx(run.planned, rel=0.01)
    assert str(r).startswith("Rehearsal on the twin: on the leg this run would do 1 configuration saved, 1 reboot, "
                             "2 axes calibrated, 2 steps, 1 torque run, 1 return to rest: about 41 s")
    assert r.to_dict()["planned_s"] == run.planned


@pytest.mark.slow
def test_the_estimate_agrees_with_a_real_time_run():
    """The rehearsal's bench time (a twin at full speed, its steps run in the kernel)
    against the wall-clock time of the same run on a twin in real time (polled, as on the
    leg): within 10 %. The run is a few seconds: the session's checks, two steps, a torque
    playback and a return to rest, on boards configured and calibrated beforehand."""
    def run(d):
        lg.configure(d)
        lg.calibrate(d)
        lg.step_response(d, *STABLE, duration=0.5, settle=0.5)
        lg.step_response(d, 30.0, 0.05, 0.01, duration=0.5, settle=0.5)
        lg.play_torque_table(d, np.full((250, 2), 0.01))
        return_to_rest(d, move_time=0.5, settle=0.2)

    for seed in (40, 41):
        d = lg.connect("virtual", seed=seed)
        lg.configure(d)
        lg.calibrate(d)
    rehearsal = lg.connect("virtual", seed=40)
    m = bench.mark(rehearsal)
    run(rehearsal)
    estimate = bench.report(m, rehearsal)
    assert estimate.counts["step"] == 2 and estimate.charged != 0    # the steps ran in the kernel
    real = lg.connect("virtual", seed=41, realtime=True)
    m = bench.mark(real)
    t0 = time.monotonic()
    run(real)
    wall = time.monotonic() - t0
    assert 3.0 < wall < 10.0
    assert estimate.seconds == pytest.approx(wall, rel=0.10)
    # the real-time run's own ledger says the same
    assert bench.report(m, real).seconds == pytest.approx(wall, rel=0.10)


# ---------------------------------------------------------------------------------------
# the limit on the real leg
# ---------------------------------------------------------------------------------------

def test_a_long_run_on_the_leg_is_refused_with_its_estimate(usb):
    with usb() as d:
        plan = bench.Plan(steps=100)
        with pytest.raises(BenchLimitError, match=r"this run \(the configuration saved \(1 reboot\), 2 axes calibrated, "
                                                  r"100 steps\) takes about 6\.\d min on the leg .* set "
                                                  r"max_bench_minutes to at least 7"):
            setup.start_run(d, plan, max_minutes=5)
        assert d._board_sim.boot_count == 0                    # nothing was done
        assert setup.start_run(d, plan, max_minutes=7).planned == pytest.approx(plan.seconds(True, 2))
    # on the twin the same run is only estimated
    v = lg.connect("virtual", seed=42)
    assert setup.start_run(v, plan, max_minutes=5).planned > 300


def test_a_sweep_on_the_leg_is_refused_before_it_writes(usb, tmp_path):
    with usb() as d:
        lg.configure(d)
        lg.calibrate(d)
        out = tmp_path / "sweep"
        with pytest.raises(BenchLimitError, match=r"the sweep of 400 point\(s\) into .* takes about 2\d\.\d min on the "
                                                  r"leg .* set max_minutes to at least 2\d to run it"):
            lg.sweep(d, lg.thesis_grid(), out, progress=False)
        assert not out.exists() or not any(out.iterdir())
        with pytest.raises(BenchLimitError, match="tune: up to 50 steps takes about 2.9 min"):
            lg.tune(d, 0.24, 5.0, max_experiments=50, max_minutes=2)
        r = lg.sweep(d, [STABLE], out, progress=False)
        assert r.measured == 1 and r.bench.counts == {"sweep": 1, "step": 1}
        assert r.bench.seconds == pytest.approx(bench.step_seconds(latency=d._board_sim.twin.plant.usb_latency),
                                                rel=0.01)


def test_a_bad_limit_is_named():
    d = lg.connect("virtual", seed=43)
    with pytest.raises(lg.LeglibError, match="max_bench_minutes must be above 0"):
        setup.start_run(d, bench.Plan(), max_minutes=0)
    with pytest.raises(lg.LeglibError, match="max_minutes must be a real number"):
        bench.require(d, 1.0, "five", "a run")
    assert math.isfinite(bench.limit_seconds(5, "x"))
