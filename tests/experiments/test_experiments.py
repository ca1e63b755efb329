"""The I/O layer on the twin: the flows of Listings 7.1-7.4, safety, fault injection."""

import hashlib
import time

import numpy as np
import pytest

import leglib as lg
from leglib.device.session import (
    AXIS_STATE_CLOSED_LOOP_CONTROL,
    ExperimentError,
    as_device,
    clear_errors,
    describe_errors,
    enter_closed_loop,
)
from leglib.device.usb import DeviceNotFoundError
from leglib.device.virtual import firmware as V
from leglib.experiments import sweep as sweep_module
from leglib.files.measurements import read_file, read_measurement, write_batch
from leglib.files.sweepdir import list_measurements
from leglib.twin import layout as L

STABLE = (50.0, 0.046, 0.001)
UNSTABLE = (50.0, 0.002, 0.08)


@pytest.fixture
def dev():
    d = lg.connect("virtual", seed=11)
    lg.configure(d)
    lg.calibrate(d)
    return d


def _idle(dev):
    return all(int(dev.get(a, "current_state")) == V.AXIS_STATE_IDLE for a in (0, 1))


def test_listing_71_configuration_reads_back_and_is_saved():
    d = lg.connect("virtual")
    written = lg.configure(d)
    for a in (0, 1):
        assert d.get(a, "current_lim") == 10.0 and d.get(a, "cpr") == 4000
        assert d.get(a, "torque_constant") == pytest.approx(8.27 / 340)
    assert written["brake_resistance"] == 2.05 and written["enable_brake_resistor"] is True
    assert d.sim.saved_configuration["axes"][0]["cpr"] == 4000
    assert d.sim.boot_count == 1                      # saving rebooted the board (0.5.6)
    assert d.raw.config.enable_brake_resistor and d.raw.brake_resistor_armed


def test_listing_72_calibration_zeroing_then_closed_loop(dev):
    # the zeroing step put the rest pose at the thesis's operating point
    q1 = np.degrees(dev.axes.counts_to_joint(dev.counts(dev.axes.axis_of_joint[0]), 0))
    q2 = np.degrees(dev.axes.counts_to_joint(dev.counts(dev.axes.axis_of_joint[1]), 1))
    assert q1 == pytest.approx(267.0, abs=2.0) and q2 == pytest.approx(273.0, abs=2.0)
    enter_closed_loop(dev)
    for a in (0, 1):
        assert int(dev.get(a, "current_state")) == AXIS_STATE_CLOSED_LOOP_CONTROL
        # closed-loop entry set input_pos := pos_estimate: the leg holds where it is
        assert float(dev.get(a, "input_pos")) == pytest.approx(float(dev.get(a, "pos_estimate")), abs=0.002)
    dev.idle_all()
    assert _idle(dev)


def test_step_starts_at_the_rest_pose_on_0_5_6(dev):
    """apply_configuration, calibrate, step_response on 0.5.6 give
    q1 = 267 +- 2 deg at rest."""
    assert dev.firmware_version == (0, 5, 6)
    r = lg.step_response(dev, *STABLE)
    assert r.completed
    assert np.degrees(r.q1[0]) == pytest.approx(267.0, abs=2.0)
    assert np.degrees(r.q2[0]) == pytest.approx(273.0, abs=2.0)


def test_calibration_failure_is_reported_by_axis():
    d = lg.connect("virtual")
    with pytest.raises(ExperimentError, match="axis0 calibration failed"):
        lg.calibrate(d)  # cpr/pole_pairs never configured: mismatch


def test_listing_73_torque_playback(dev):
    n = 750
    tau = np.zeros((n, 2))
    tau[:, 1] = 0.08 * np.sin(np.linspace(0, 4 * np.pi, n))
    run = lg.play_torque_table(dev, tau, period=0.002)
    assert np.all(np.diff(run.t) > 0)
    # about eight USB transactions a cycle (two angles, two torques, two Iq, two states; a
    # watchdog feed every fifth cycle)
    lat = dev.sim.twin.plant.usb_latency
    assert run.rate_hz == pytest.approx(1.0 / (8.2 * lat), rel=0.2)
    assert run.t[-1] == pytest.approx(1.5, abs=0.01)
    assert np.ptp(run.q2) > np.radians(1.0)       # the driven joint moved
    assert _idle(dev)


def test_listing_74_step_response(dev):
    r = lg.step_response(dev, *STABLE)
    assert r.completed and r.abort_reason is None
    assert len(r.t) == 750 and r.t[1] - r.t[0] == pytest.approx(0.002)
    dq1, dq2 = dev.axes.motor_step_to_joint_step(0.4)
    assert r.q1[-1] - r.q1[0] == pytest.approx(dq1, rel=0.1)
    assert r.q2[-1] - r.q2[0] == pytest.approx(dq2, rel=0.1)
    assert r.y[-1] > r.y[0] + 0.02                 # the leg shortened: foot rose
    assert _idle(dev)


def test_gains_outside_bounds_are_refused(dev):
    with pytest.raises(ValueError, match="pos_gain = 500"):
        lg.step_response(dev, 500, 0.05, 0.01)
    with pytest.raises(ValueError, match="vel_gain"):
        lg.step_response(dev, 50, -0.1, 0.01)


def test_unstable_gains_are_detected_and_aborted(dev, tmp_path):
    r = lg.step_response(dev, *UNSTABLE)
    assert not r.completed and r.abort_reason
    assert len(r.t) < 750
    assert _idle(dev)
    m = read_measurement(r.write(tmp_path))
    assert m.meta["completed"] is False and not m.stable


def _hashes(paths):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in paths}


GRID = lg.thesis_grid()[::37][:8]


def _points(directory):
    """The measurements in a directory, all read (raises for anything damaged)."""
    return [m for p in list_measurements(directory) for m in read_file(p)]


def test_sweep_writes_every_point_and_resume_skips(dev, tmp_path):
    res = lg.sweep(dev, GRID, tmp_path, progress=False)
    assert res.measured == len(GRID) and len(res.written) == 1 and res.skipped == 0   # one batch
    assert sorted(m.gains for m in _points(tmp_path)) == sorted(tuple(g) for g in GRID)
    before = _hashes(res.paths)
    again = lg.sweep(dev, GRID, tmp_path, progress=False)
    assert again.skipped == len(GRID) and not again.written and again.measured == 0
    assert _hashes(again.paths) == before
    with pytest.raises(FileExistsError):
        lg.sweep(dev, GRID, tmp_path, resume=False, progress=False)


def _failing_batch_write(monkeypatch, nth, exc):
    real_write = write_batch
    calls = {"n": 0}

    def failing(*a, **kw):
        calls["n"] += 1
        if calls["n"] == nth:
            raise exc
        return real_write(*a, **kw)
    monkeypatch.setattr(sweep_module, "write_batch", failing)


def test_exception_mid_sweep_keeps_files_and_resume_completes(dev, tmp_path, monkeypatch):
    _failing_batch_write(monkeypatch, 3, RuntimeError("disk full (injected)"))
    with pytest.raises(RuntimeError, match="injected"):
        lg.sweep(dev, GRID, tmp_path, chunk=2, progress=False)
    assert _idle(dev)
    kept = list_measurements(tmp_path)
    assert len(kept) == 2 and len(_points(tmp_path)) == 4   # two batches of two, intact
    before = _hashes(kept)
    monkeypatch.undo()
    res = lg.sweep(dev, GRID, tmp_path, chunk=2, progress=False)
    assert res.skipped == 4 and res.measured == 4 and len(_points(tmp_path)) == len(GRID)
    assert {k: v for k, v in _hashes(res.paths).items() if k in before} == before


def test_keyboard_interrupt_mid_sweep(dev, tmp_path, monkeypatch):
    _failing_batch_write(monkeypatch, 3, KeyboardInterrupt())
    with pytest.raises(KeyboardInterrupt):
        lg.sweep(dev, GRID, tmp_path, chunk=2, progress=False)
    assert _idle(dev)
    assert len(_points(tmp_path)) == 4
    monkeypatch.undo()
    lg.sweep(dev, GRID, tmp_path, progress=False)
    assert len(_points(tmp_path)) == len(GRID)


def test_injected_disconnect_mid_sweep_then_resume(tmp_path):
    d = lg.connect("virtual", seed=5)
    lg.configure(d)
    lg.calibrate(d)
    real_batch = d.sim.step_batch
    calls = {"n": 0}

    def dies_after_two_batches(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:
            d.sim.lost = True          # the link dies
        return real_batch(*args, **kwargs)
    d.sim.step_batch = dies_after_two_batches
    with pytest.warns(UserWarning, match="could not set IDLE"):
        with pytest.raises(V.DeviceLostError):
            lg.sweep(d, GRID, tmp_path, chunk=2, progress=False)
    assert len(list_measurements(tmp_path)) == 2 and len(_points(tmp_path)) == 4
    assert np.all(d.sim.st.AI[0, :, L.I_MODE] == L.MODE_IDLE)
    d2 = lg.connect("virtual", seed=5)
    lg.configure(d2)
    lg.calibrate(d2)
    res = lg.sweep(d2, GRID, tmp_path, progress=False)
    assert res.skipped == 4 and len(_points(tmp_path)) == len(GRID)


def test_disconnect_in_closed_loop_watchdog_idles_the_motors(dev):
    def cut_the_link(sample):
        if dev.sim.disconnect_after is None:
            dev.sim.disconnect_after = dev.sim.transactions + 20
    with pytest.warns(UserWarning):
        with pytest.raises(V.DeviceLostError):
            lg.torque_loop(dev, lambda t, q1, q2: (0.01, 0.01), 1.0, on_sample=cut_the_link)
    assert np.any(dev.sim.st.AI[0, :, L.I_MODE] != L.MODE_IDLE)  # still energized ...
    dev.sim.twin.run(dev.sim.st, seconds=0.5)                     # ... until the watchdog acts
    assert np.all(dev.sim.st.AI[0, :, L.I_MODE] == L.MODE_IDLE)
    assert np.all(dev.sim.st.AI[0, :, L.I_AXIS_ERR] & L.AXIS_ERROR_WATCHDOG_TIMER_EXPIRED)


def test_per_point_and_sweep_paths_agree(dev, tmp_path):
    """Same kernel, same numbers: the steps start from the device's state at the time, which
    moves on by a few transactions between the sweep and the single steps (the idle leg on
    its stop, encoder noise), so they agree to the encoder's resolution (exact equality of
    batch and single runs from one state: tests/test_twin.py)."""
    lg.sweep(dev, GRID[:3], tmp_path, progress=False)
    one_count = 2 * np.pi / (dev.axes.cpr * dev.axes.gear_ratio)
    for m in _points(tmp_path):
        r = lg.step_response(dev, *m.gains)
        assert m.meta["completed"] == r.completed
        n = min(len(r.t), len(m.t))
        np.testing.assert_allclose(np.radians(m.angle1[:n]), r.q1[:n], atol=4 * one_count)
        np.testing.assert_allclose(np.radians(m.angle2[:n]), r.q2[:n], atol=4 * one_count)


def test_no_06_firmware_on_a_v36():
    """odrive 0.6.11 utils.py:87-89 sends firmware below 0.6 to the legacy error model; the
    0.6.x firmware line is for ODrive Pro, S1 and Micro, not the v3.6."""
    with pytest.raises(ValueError, match="no 0.6 firmware"):
        lg.connect("virtual", firmware="0.6")


def test_firmware_051_differences():
    """fw-v0.5.1: no vel_integrator_limit (0.5.4+), no odrv.error, axis.clear_errors
    (fw-v0.5.1 axis.hpp:108), brake resistor always used (no enable flag), and
    save_configuration neither refuses nor reboots (fw-v0.5.1 main.cpp:43-61)."""
    d = lg.connect("virtual", firmware="0.5.1")
    assert d.firmware_version == (0, 5, 1)
    with pytest.raises(ExperimentError, match="0.5.4"):
        d.get(0, "vel_integrator_limit")
    with pytest.raises(AttributeError):
        d.raw.error
    with pytest.raises(AttributeError):
        d.raw.config.enable_brake_resistor
    assert d.raw.brake_resistor_armed
    lg.configure(d)
    assert d.sim.boot_count == 0 and d.sim.saved_configuration is not None
    d.axis(0).error = 0x800
    clear_errors(d)
    assert int(d.get(0, "error")) == 0
def test_virtual_device_is_the_odrive_client_object():
    """connect("virtual") wraps the odrive client's tree built over the firmware table; the
    model (virtual clock, twin) is dev.sim. A v3.6 has no 0.6 firmware (odrive 0.6.11
    utils.py:87-89 treats < 0.6.0 as legacy 0.5.x)."""
    from odrive.sync_tree import SyncObject
    d = lg.connect("virtual", seed=5)
    assert isinstance(d.raw, SyncObject) and isinstance(d.sim, V.VirtualODrive)
    assert d.firmware == "0.5" and d.firmware_version == (0, 5, 6)
    assert as_device(d.raw).sim is d.sim and as_device(d.raw).backend == "virtual"
    assert lg.connect("virtual", seed=5).sim is d.sim            # same seed, same device
    assert lg.connect("virtual", seed=7, firmware="0.5.1").firmware_version == (0, 5, 1)
    with pytest.raises(ValueError, match="firmware='0.5.1'"):
        lg.connect("virtual", seed=5, firmware="0.5.1")          # seed 5 runs 0.5.6
    with pytest.raises(ValueError, match="no 0.6 firmware"):
        lg.connect("virtual", seed=6, firmware="0.6")


def test_connect_errors():
    with pytest.raises(ValueError, match="backend must be"):
        lg.connect("bluetooth")
    with pytest.raises(TypeError, match="unknown option"):
        lg.connect("virtual", sed=1)


def test_usb_without_device_fails_clearly():
    with pytest.raises(DeviceNotFoundError, match="no ODrive answered|cannot import"):
        lg.connect("usb", timeout=1.0)


def test_context_manager_idles_on_exception(dev):
    with pytest.raises(ZeroDivisionError):
        with dev:
            dev.set(1, "requested_state", AXIS_STATE_CLOSED_LOOP_CONTROL)
            1 / 0
    assert _idle(dev)


def test_apply_gains_saved_survive_the_reboot(dev):
    """Issue 15: apply_gains writes, reads back, saves (main.cpp:159-184 reboots on 0.5.6)
    and reconnects by serial number; a new connection reads the gains on both axes."""
    g = (31.0, 0.052, 0.021)
    boots = dev.sim.boot_count
    out = lg.apply_gains(dev, g, save=True)
    assert out is dev and dev.sim.boot_count == boots + 1
    fresh = dev.sim.handle()          # what another connection to the board sees
    for a in (0, 1):
        ax = getattr(fresh, f"axis{a}")
        assert (ax.controller.config.pos_gain, ax.controller.config.vel_gain,
                ax.controller.config.vel_integrator_gain) == pytest.approx(g)
    assert not bool(dev.get(0, "is_calibrated"))   # the reboot lost the calibration
    with pytest.raises(ValueError, match="vel_gain"):
        lg.apply_gains(dev, (30.0, True, 0.01))
    with pytest.raises(ExperimentError, match="not calibrated"):
        lg.step_response(dev, *g)


def test_experiments_refuse_what_cannot_work(dev):
    """Issue 17: sample_period <= 0, >= duration or NaN; booleans as gains; NaN limits; a
    step below the encoder's resolution."""
    for bad in (0.0, -0.001, float("nan"), 1.5, 2.0):
        with pytest.raises(ValueError, match="sample_period"):
            lg.step_response(dev, *STABLE, sample_period=bad)
    with pytest.raises(ValueError, match="pos_gain"):
        lg.step_response(dev, True, 0.046, 0.001)
    with pytest.raises(ValueError, match="vel_limit"):
        lg.step_response(dev, *STABLE, vel_limit=float("nan"))
    with pytest.raises(ValueError, match="resolution"):
        lg.step_response(dev, *STABLE, step=1e-4)
    with pytest.raises(ValueError, match="period"):
        lg.torque_loop(dev, lambda t, q1, q2: (0.0, 0.0), 0.1, period=0.5)
    assert _idle(dev)


@pytest.mark.parametrize("realtime", [False, True])
def test_a_step_with_a_firmware_error_is_not_completed(dev, realtime):
    """low_level.cpp:374-376: with the brake resistor disabled the braking leg trips
    ODRIVE_ERROR_DC_BUS_OVER_REGEN_CURRENT; the step is then not completed, on the kernel
    path and on the polling path alike."""
    dev.raw.config.enable_brake_resistor = False
    dev.sim.set_realtime(realtime)
    r = lg.step_response(dev, *STABLE, duration=0.5, settle=0.2)
    assert not r.completed and r.abort_reason
    assert int(dev.raw.error) & V.ODRIVE_ERROR_DC_BUS_OVER_REGEN_CURRENT
    assert _idle(dev)


def test_a_host_stall_longer_than_the_watchdog_disarms_the_realtime_step(dev):
    """axis.cpp:171-182: the device runs on while the host stalls; a stall longer than the
    step's 0.5 s watchdog trips WATCHDOG_TIMER_EXPIRED, the axes drop to IDLE, and the
    response is not completed, with a reason naming the flag. The step lasts 0.8 s past the
    stall's end, so that the loop reads an axis's state (every fourth sample) before the
    step's end even when the host resumes late: at 0.1 s past it, on a loaded machine, the
    step once ended first and said only "firmware error during the step"."""
    dev.sim.set_realtime(True)
    stalled = []

    def stall_once(sample):
        if sample["t"] > 0.2 and not stalled:
            stalled.append(sample["t"])
            time.sleep(0.7)
    r = lg.step_response(dev, *STABLE, duration=1.7, settle=0.1, on_sample=stall_once)
    dev.sim.set_realtime(False)
    assert stalled and not r.completed
    assert "WATCHDOG_TIMER_EXPIRED" in r.abort_reason and "dropped out of closed loop" in r.abort_reason
    assert np.max(np.diff(r.t)) >= 0.7
    assert _idle(dev)


def test_describe_errors_names_the_firmware_flags():
    errs = {"odrv": V.ODRIVE_ERROR_DC_BUS_OVER_REGEN_CURRENT,
            "axis0": {"error": V.AXIS_ERROR_WATCHDOG_TIMER_EXPIRED | V.AXIS_ERROR_MOTOR_FAILED,
                      "motor_error": L.MOTOR_ERROR_SYSTEM_LEVEL, "encoder_error": 0, "controller_error": 0},
            "axis1": {"error": 0, "motor_error": 0, "encoder_error": 0, "controller_error": 0}}
    text = describe_errors(errs)
    assert text == ("odrv.error = DC_BUS_OVER_REGEN_CURRENT (0x8), "
                    "axis0.error = MOTOR_FAILED|WATCHDOG_TIMER_EXPIRED (0x840), "
                    "axis0.motor.error = SYSTEM_LEVEL (0x1000000)")
    assert describe_errors({"odrv": None, "axis0": {"error": 0}, "axis1": {"error": 0}}) == "no errors"


def test_live_view_hook_keeps_the_requested_rate_on_the_realtime_twin(dev):
    """Issue 15: on_sample is called from the paced polling loop of a real-time twin, and a
    cheap callback does not slow the sampling: the achieved period is within 10 % of the
    requested one."""
    dev.sim.set_realtime(True)
    seen = []
    r = lg.step_response(dev, *STABLE, duration=0.6, sample_period=0.002, settle=0.1,
                         on_sample=seen.append)
    assert r.completed
    assert len(seen) == len(r.t) and set(seen[0]) == {"t", "q1", "q2", "iq", "setpoint"}
    assert seen[-1]["q1"] == pytest.approx(r.q1[-1]) and seen[0]["setpoint"] is not None
    # the achieved period: the median interval (a loaded host that loses the CPU for a few
    # ms skips sample slots; those gaps show in the mean, not in the rate the loop keeps)
    period = np.median(np.diff(r.t))
    assert period == pytest.approx(0.002, rel=0.1)
    dev.sim.set_realtime(False)
    dev.sleep(2.0)                    # the leg falls back onto its stop
    dev.sim.set_realtime(True)
    samples = []
    run = lg.torque_loop(dev, lambda t, q1, q2: (0.0, 0.0), 0.2, period=0.005, on_sample=samples.append)
    assert len(samples) == len(run.t) and samples[0]["iq"] is not None
    assert np.median(np.diff(run.t)) == pytest.approx(0.005, rel=0.1)


def test_a_loaded_leg_is_calibrated_with_its_payload_off():
    """A payload on the foot: the encoder offset scan at calibration_current (encoder.cpp:
    329-461, checked to 2 % of cpr) cannot carry the loaded leg and fails the CPR check, as
    it would on the device; the bench's procedure (payload off while calibrating, the
    twin's default) calibrates, and the steps afterwards carry the payload."""
    from leglib.params import load_plant
    loaded = load_plant("default", payload_mass=0.5)
    d = lg.connect("virtual", seed=31, plant=loaded, payload_off_for_calibration=False)
    lg.configure(d)
    with pytest.raises(ExperimentError, match="calibration failed"):
        lg.calibrate(d)
    d = lg.connect("virtual", seed=32, plant=loaded)
    lg.configure(d)
    lg.calibrate(d)
    assert d.sim.twin.payload_mounted and d.describe()["twin_plant_values"]["payload_mass"] == 0.5
    light = lg.connect("virtual", seed=34)
    lg.configure(light)
    lg.calibrate(light)
    g = (40.0, 0.05, 0.02)
    y_loaded, y_light = lg.step_response(d, *g).y, lg.step_response(light, *g).y
    assert np.max(np.abs(y_loaded - y_light)) > 1e-3   # the payload changes the response (m)


def test_the_step_path_is_a_named_choice(dev):
    """path="batched" is only for a twin not paced to the wall clock, and calls no on_sample;
    "auto" polls when a live view is given (it would otherwise see nothing)."""
    seen = []
    r = lg.step_response(dev, *STABLE, duration=0.3, settle=0.1, on_sample=seen.append)
    assert r.completed and len(seen) == len(r.t)
    with pytest.raises(ValueError, match="calls no on_sample"):
        lg.step_response(dev, *STABLE, on_sample=seen.append, path="batched")
    with pytest.raises(ValueError, match="path must be one of"):
        lg.step_response(dev, *STABLE, path="kernel")
    dev.sim.set_realtime(True)
    try:
        with pytest.raises(ValueError, match="not paced to the wall clock"):
            lg.step_response(dev, *STABLE, path="batched")
    finally:
        dev.sim.set_realtime(False)


def test_a_torque_run_is_one_committed_unit(dev, tmp_path, monkeypatch):
    """TorqueRun.write commits the positions file last: a full disk at the torque table leaves
    no measurement in the directory (only leftovers a resumed sweep sets aside), and a table
    that is not the one the sidecar committed is refused."""
    import errno

    from leglib.errors import MeasurementError
    from leglib.experiments.torque import TorqueRun
    from leglib.files import measurements
    from leglib.files.sweepdir import find_uncommitted
    run = lg.play_torque_table(dev, np.full((30, 2), 0.01))
    real = measurements.write_bytes_atomic

    def full(path, data, **kw):
        if str(path).endswith("_torque.csv"):
            raise OSError(errno.ENOSPC, f"{path}: No space left on device")
        return real(path, data, **kw)
    monkeypatch.setattr(measurements, "write_bytes_atomic", full)
    with pytest.raises(OSError, match="No space left"):
        run.write(tmp_path / "full")
    assert list_measurements(tmp_path / "full") == [] and find_uncommitted(tmp_path / "full")
    monkeypatch.undo()
    path = run.write(tmp_path / "ok")
    back = TorqueRun.read(path)
    assert np.array_equal(back.table, np.round(run.table, 6)) and np.allclose(back.t, run.t, atol=1e-6)
    table = path.with_name(path.name.replace("_positions.csv", "_torque.csv"))
    table.chmod(0o644)
    table.write_text(table.read_text().replace("0.010000", "0.020000", 1))
    with pytest.raises(MeasurementError, match="not this measurement's file"):
        TorqueRun.read(path)
