"""The I/O layer on the twin: the flows of Listings 7.1-7.4, safety, fault injection."""

import hashlib

import numpy as np
import pytest

from leglib import dataio
from leglib import odrive_io as io
from leglib import twin as T
from leglib import virtual_odrive as V

STABLE = (50.0, 0.046, 0.001)
UNSTABLE = (50.0, 0.002, 0.08)


@pytest.fixture
def dev():
    d = io.connect("virtual", seed=11)
    io.apply_configuration(d)
    io.calibrate(d)
    return d


def _idle(dev):
    return all(int(dev.get(a, "current_state")) == V.AXIS_STATE_IDLE for a in (0, 1))


def test_listing_71_configuration_reads_back_and_is_saved():
    d = io.connect("virtual")
    written = io.apply_configuration(d)
    for a in (0, 1):
        assert d.get(a, "current_lim") == 10.0 and d.get(a, "cpr") == 4000
        assert d.get(a, "torque_constant") == pytest.approx(8.27 / 340)
    assert written["brake_resistance"] == 2.05
    assert d.sim.saved_configuration["axes"][0]["cpr"] == 4000


def test_listing_72_calibration_then_closed_loop(dev):
    for a in (0, 1):
        dev.set(a, "requested_state", io.AXIS_STATE_CLOSED_LOOP_CONTROL)
        assert int(dev.get(a, "current_state")) == io.AXIS_STATE_CLOSED_LOOP_CONTROL
    dev.idle_all()
    assert _idle(dev)


def test_calibration_failure_is_reported_by_axis():
    d = io.connect("virtual")
    with pytest.raises(io.ExperimentError, match="axis0 calibration failed"):
        io.calibrate(d)  # cpr/pole_pairs never configured: mismatch


def test_listing_73_torque_playback(dev):
    n = 750
    tau = np.zeros((n, 2))
    tau[:, 1] = 0.08 * np.sin(np.linspace(0, 4 * np.pi, n))
    run = io.play_torque_table(dev, tau, period=0.002)
    assert np.all(np.diff(run.t) > 0)
    assert 250 < run.rate_hz < 600
    assert run.t[-1] == pytest.approx(1.5, abs=0.01)
    assert np.ptp(run.q2) > np.radians(1.0)       # the driven joint moved
    assert _idle(dev)


def test_listing_74_step_response(dev):
    r = io.step_response(dev, *STABLE)
    assert r.completed and r.abort_reason is None
    assert len(r.t) == 750 and r.t[1] - r.t[0] == pytest.approx(0.002)
    dq1, dq2 = dev.axes.motor_step_to_joint_step(0.4)
    assert r.q1[-1] - r.q1[0] == pytest.approx(dq1, rel=0.1)
    assert r.q2[-1] - r.q2[0] == pytest.approx(dq2, rel=0.1)
    assert r.y[-1] > r.y[0] + 0.02                 # the leg shortened: foot rose
    assert _idle(dev)


def test_gains_outside_bounds_are_refused(dev):
    with pytest.raises(ValueError, match="pos_gain = 500"):
        io.step_response(dev, 500, 0.05, 0.01)
    with pytest.raises(ValueError, match="vel_gain"):
        io.step_response(dev, 50, -0.1, 0.01)


def test_unstable_gains_are_detected_and_aborted(dev, tmp_path):
    r = io.step_response(dev, *UNSTABLE)
    assert not r.completed and r.abort_reason
    assert len(r.t) < 750
    assert _idle(dev)
    m = dataio.read_measurement(r.write(tmp_path))
    assert m.meta["completed"] is False and not m.stable


def _hashes(paths):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in paths}


GRID = io.thesis_grid()[::37][:8]


def test_sweep_writes_every_point_and_resume_skips(dev, tmp_path):
    res = io.sweep(dev, GRID, tmp_path, progress=False)
    assert len(res.written) == len(GRID) and res.skipped == 0
    before = _hashes(res.paths)
    again = io.sweep(dev, GRID, tmp_path, progress=False)
    assert again.skipped == len(GRID) and not again.written
    assert _hashes(again.paths) == before
    with pytest.raises(FileExistsError):
        io.sweep(dev, GRID, tmp_path, resume=False, progress=False)


def test_exception_mid_sweep_keeps_files_and_resume_completes(dev, tmp_path, monkeypatch):
    real_write = io.StepResponse.write
    calls = {"n": 0}

    def flaky(self, out_dir, when=None):
        calls["n"] += 1
        if calls["n"] == 4:
            raise RuntimeError("disk full (injected)")
        return real_write(self, out_dir, when)

    monkeypatch.setattr(io.StepResponse, "write", flaky)
    with pytest.raises(RuntimeError, match="injected"):
        io.sweep(dev, GRID, tmp_path, progress=False)
    assert _idle(dev)
    kept = dataio.list_measurements(tmp_path)
    assert len(kept) == 3
    before = _hashes(kept)
    for p in kept:
        dataio.read_measurement(p)  # intact
    monkeypatch.setattr(io.StepResponse, "write", real_write)
    res = io.sweep(dev, GRID, tmp_path, progress=False)
    assert res.skipped == 3 and len(res.paths) == len(GRID)
    assert {k: v for k, v in _hashes(res.paths).items() if k in before} == before


def test_keyboard_interrupt_mid_sweep(dev, tmp_path, monkeypatch):
    real_write = io.StepResponse.write
    calls = {"n": 0}

    def interrupted(self, out_dir, when=None):
        calls["n"] += 1
        if calls["n"] == 6:
            raise KeyboardInterrupt
        return real_write(self, out_dir, when)

    monkeypatch.setattr(io.StepResponse, "write", interrupted)
    with pytest.raises(KeyboardInterrupt):
        io.sweep(dev, GRID, tmp_path, progress=False)
    assert _idle(dev)
    assert len(dataio.list_measurements(tmp_path)) == 5
    monkeypatch.setattr(io.StepResponse, "write", real_write)
    assert len(io.sweep(dev, GRID, tmp_path, progress=False).paths) == len(GRID)


def test_injected_disconnect_mid_sweep_then_resume(tmp_path):
    d = io.connect("virtual", seed=5)
    io.apply_configuration(d)
    io.calibrate(d)
    d.sim.disconnect_after = d.sim.transactions + 2  # two batches, then the link dies
    with pytest.warns(UserWarning, match="could not set IDLE"):
        with pytest.raises(V.DeviceLostError):
            io.sweep(d, GRID, tmp_path, chunk=2, progress=False)
    assert len(dataio.list_measurements(tmp_path)) == 4
    assert np.all(d.sim.st.AI[0, :, T.I_MODE] == T.MODE_IDLE)
    d2 = io.connect("virtual", seed=5)
    io.apply_configuration(d2)
    io.calibrate(d2)
    res = io.sweep(d2, GRID, tmp_path, progress=False)
    assert res.skipped == 4 and len(res.paths) == len(GRID)


def test_disconnect_in_closed_loop_watchdog_idles_the_motors(dev):
    dev.sim.disconnect_after = dev.sim.transactions + 40
    tau = np.full((500, 2), 0.01)
    with pytest.warns(UserWarning):
        with pytest.raises(V.DeviceLostError):
            io.play_torque_table(dev, tau)
    assert np.any(dev.sim.st.AI[0, :, T.I_MODE] != T.MODE_IDLE)  # still energized ...
    dev.sim.twin.run(dev.sim.st, seconds=0.5)                     # ... until the watchdog acts
    assert np.all(dev.sim.st.AI[0, :, T.I_MODE] == T.MODE_IDLE)
    assert np.all(dev.sim.st.AI[0, :, T.I_AXIS_ERR] & T.AXIS_ERROR_WATCHDOG_TIMER_EXPIRED)


def test_per_point_and_sweep_paths_agree(dev, tmp_path):
    res = io.sweep(dev, GRID[:3], tmp_path, progress=False)
    for p in res.written:
        m = dataio.read_measurement(p)
        r = io.step_response(dev, *m.gains)
        np.testing.assert_allclose(np.radians(m.angle1), r.q1, atol=1e-6)  # file: 6 decimals in deg
        np.testing.assert_allclose(np.radians(m.angle2), r.q2, atol=1e-6)


def test_virtual_device_is_the_odrive_client_object():
    """connect("virtual") wraps the odrive client's tree built over the firmware table; the
    model (virtual clock, twin) is dev.sim. A v3.6 has no 0.6 firmware (odrive 0.6.11
    utils.py:87-89 treats < 0.6.0 as legacy 0.5.x)."""
    from odrive.sync_tree import SyncObject
    d = io.connect("virtual", seed=5)
    assert isinstance(d.raw, SyncObject) and isinstance(d.sim, V.VirtualODrive)
    assert d.firmware == "0.5" and d.firmware_version == (0, 5, 6)
    assert io.as_device(d.raw).sim is d.sim and io.as_device(d.raw).backend == "virtual"
    assert io.connect("virtual", seed=5).sim is d.sim            # same seed, same device
    assert io.connect("virtual", seed=7, firmware="0.5.1").firmware_version == (0, 5, 1)
    with pytest.raises(ValueError, match="firmware='0.5.1'"):
        io.connect("virtual", seed=5, firmware="0.5.1")          # seed 5 runs 0.5.6
    with pytest.raises(ValueError, match="no 0.6 firmware"):
        io.connect("virtual", seed=6, firmware="0.6")


def test_connect_errors():
    with pytest.raises(ValueError, match="backend must be"):
        io.connect("bluetooth")
    with pytest.raises(TypeError, match="unknown option"):
        io.connect("virtual", sed=1)


def test_usb_without_device_fails_clearly():
    with pytest.raises(io.DeviceNotFoundError, match="no ODrive answered|cannot import"):
        io.connect("usb", timeout=1.0)


def test_context_manager_idles_on_exception(dev):
    with pytest.raises(ZeroDivisionError):
        with dev:
            dev.set(1, "requested_state", io.AXIS_STATE_CLOSED_LOOP_CONTROL)
            1 / 0
    assert _idle(dev)
