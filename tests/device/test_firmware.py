"""Conformance of the virtual ODrive with firmware 0.5.x (odriverobotics/ODrive, tags
fw-v0.5.6 and fw-v0.5.1; file:line of Firmware/MotorControl/ at fw-v0.5.6 unless marked).
The checklist is /work/shared/odrive/README.md, rows 1-12."""

import math

import numpy as np
import pytest

import leglib as lg
from leglib.device.session import ExperimentError, as_device, clear_errors
from leglib.device.virtual import firmware as V
from leglib.params import load_plant
from leglib.twin import layout as L


def _device(firmware="0.5.6", brake=True, seed=0, **kw):
    odrv = V.VirtualODrive(seed=seed, firmware=firmware, **kw)
    for a in (odrv.axis0, odrv.axis1):
        a.encoder.config.cpr = 4000
        a.motor.config.pole_pairs = 11
    if brake and firmware != "0.5.1":
        odrv.config.enable_brake_resistor = True
        odrv.clear_errors()   # arms the resistor (main.cpp:246-248)
    return odrv


def _calibrate(odrv, axes=(0, 1)):
    for a in axes:
        getattr(odrv, f"axis{a}").requested_state = V.AXIS_STATE_FULL_CALIBRATION_SEQUENCE
    odrv.sleep(V.CALIBRATION_DURATION + 0.1)


def _closed_loop(odrv, ax):
    ax.requested_state = V.AXIS_STATE_CLOSED_LOOP_CONTROL
    odrv.sleep(0.002)


@pytest.fixture
def odrv():
    o = _device()
    _calibrate(o)
    assert o.axis0.encoder.is_ready and o.axis1.encoder.is_ready
    return o


# -- row 1: the watchdog ---------------------------------------------------------------

def test_watchdog_enabled_without_feed_trips_at_once(odrv):
    """axis.cpp:171-182 (counts down while enabled, in every state), axis.hpp:210 (starts
    at 0), axis.cpp:165-168 (only a feed reloads it), main.cpp:413-420 (checked every tick,
    an expired watchdog disarms)."""
    ax = odrv.axis0
    ax.config.watchdog_timeout = 0.5
    ax.config.enable_watchdog = True          # no feed first
    odrv.sleep(0.001)
    assert ax.error & V.AXIS_ERROR_WATCHDOG_TIMER_EXPIRED
    assert ax.current_state == V.AXIS_STATE_IDLE
    _closed_loop(odrv, ax)                    # an axis with the error does not stay armed
    assert ax.current_state == V.AXIS_STATE_IDLE
    # the other axis, fed before enabling, counts down in IDLE too
    b = odrv.axis1
    b.config.watchdog_timeout = 0.2
    b.watchdog_feed()
    b.config.enable_watchdog = True
    odrv.sleep(0.15)
    assert not b.error
    odrv.sleep(0.1)
    assert b.error & V.AXIS_ERROR_WATCHDOG_TIMER_EXPIRED


def test_watchdog_feed_and_closed_loop_entry_reload_it(odrv):
    """axis.cpp:165-168 watchdog_feed; axis.cpp:577 closed-loop entry feeds it."""
    ax = odrv.axis1
    ax.config.watchdog_timeout = 0.1
    ax.watchdog_feed()
    ax.config.enable_watchdog = True
    odrv.sleep(0.08)
    _closed_loop(odrv, ax)                    # entry reloads the timer
    odrv.sleep(0.08)
    assert ax.current_state == V.AXIS_STATE_CLOSED_LOOP_CONTROL and not ax.error
    for _ in range(5):
        ax.watchdog_feed()
        odrv.sleep(0.05)
    assert ax.current_state == V.AXIS_STATE_CLOSED_LOOP_CONTROL
    odrv.sleep(0.15)
    assert ax.current_state == V.AXIS_STATE_IDLE and ax.error & V.AXIS_ERROR_WATCHDOG_TIMER_EXPIRED


def test_leglib_feeds_the_watchdog_before_enabling_it():
    """axis.cpp:165-182: leglib's step on the polling path enables the watchdog fed and
    leaves no watchdog error behind."""
    dev = lg.connect("virtual", seed=3, realtime=False)
    lg.configure(dev)
    lg.calibrate(dev)
    r = lg.step_response(dev, 50.0, 0.046, 0.001, duration=0.5, vel_limit=12.0, settle=0.0, path="polled")
    assert r.completed
    dev.sleep(1.0)
    assert not any(int(dev.get(a, "error")) for a in (0, 1))
    assert not any(bool(dev.get(a, "enable_watchdog")) for a in (0, 1))


# -- row 2: save_configuration and the reboot -------------------------------------------

def test_save_configuration_refuses_while_armed_then_reboots(odrv):
    """main.cpp:159-184: returns False while a motor is armed; otherwise stores and calls
    NVIC_SystemReset (the USB object is lost). motor.cpp:306: is_calibrated comes back only
    with pre_calibrated; encoder.cpp:19-30,130-138: an incremental encoder without index is
    not ready after a boot and cannot be pre-calibrated. main.cpp:146-154 and
    axis.cpp:77-81: the saved configuration is applied at boot."""
    handle = odrv.handle()
    odrv.axis0.controller.config.pos_gain = 42.0
    odrv.axis1.motor.config.pre_calibrated = True
    odrv.axis1.encoder.config.pre_calibrated = True
    assert odrv.axis1.encoder.config.pre_calibrated is False
    _closed_loop(odrv, odrv.axis0)
    assert odrv.save_configuration() is False
    odrv.axis0.requested_state = V.AXIS_STATE_IDLE
    odrv.sleep(0.002)
    before = [odrv.axis0.encoder.shadow_count, odrv.axis1.encoder.shadow_count]
    with pytest.raises(V.DeviceLostError):
        odrv.save_configuration()
    assert odrv.boot_count == 1
    with pytest.raises(V.DeviceLostError):
        handle.axis0.error                     # the old handle is gone
    with pytest.raises(V.DeviceLostError):
        odrv.axis0.error                       # and so is the connection, until reconnected
    odrv.reconnect()
    assert odrv.axis0.controller.config.pos_gain == 42.0            # config kept
    assert odrv.axis0.encoder.config.cpr == 4000
    assert not odrv.axis0.motor.is_calibrated                        # calibration lost ...
    assert odrv.axis1.motor.is_calibrated                            # ... unless pre_calibrated
    assert not odrv.axis0.encoder.is_ready and not odrv.axis1.encoder.is_ready
    after = [odrv.axis0.encoder.shadow_count, odrv.axis1.encoder.shadow_count]
    assert max(map(abs, after)) < 50 and max(map(abs, before)) > 1000  # counts restart at 0
    assert odrv.axis0.current_state == V.AXIS_STATE_IDLE and odrv.axis0.error == 0
    # a pre-calibrated motor with an encoder that is not ready: 0.5.6 closes the loop without
    # checking the encoder (axis.cpp:575), the encoder gives no phase (encoder.cpp:836-839)
    # and the first FOC update disarms the motor (foc.cpp:84-85, motor.cpp:337-341)
    _closed_loop(odrv, odrv.axis1)
    assert odrv.axis1.current_state == V.AXIS_STATE_IDLE
    assert odrv.axis1.error == V.AXIS_ERROR_MOTOR_FAILED
    assert odrv.axis1.motor.error == 0x4000000                         # UNKNOWN_PHASE_ESTIMATE


def test_save_then_reconnect_by_serial_number():
    """main.cpp:159-184 reboot; leglib reconnects by serial number and keeps the config."""
    dev = lg.connect("virtual", seed=4)
    lg.configure(dev)
    assert dev.sim.boot_count == 1
    with pytest.raises(V.DeviceLostError, match="serial"):
        dev.sim.reconnect(12345)
    assert int(dev.get(0, "cpr")) == 4000 and not bool(dev.get(0, "is_calibrated"))


def test_save_on_051_neither_refuses_nor_reboots():
    """fw-v0.5.1 main.cpp:43-61: save_configuration stores and returns; no reboot."""
    odrv = _device("0.5.1")
    _calibrate(odrv)
    _closed_loop(odrv, odrv.axis0)
    assert odrv.save_configuration() is None
    assert odrv.boot_count == 0 and odrv.axis0.current_state == V.AXIS_STATE_CLOSED_LOOP_CONTROL


# -- row 3: asynchronous requested_state ------------------------------------------------

def _just_after_a_millisecond(odrv):
    while not 0 < odrv.time % 1e-3 < 0.2e-3:
        odrv.sleep(odrv.twin.dt)


def test_requested_state_is_consumed_by_the_axis_thread():
    """axis.cpp:447-451 (the axis thread iterates every 1 ms), axis.cpp:455-488 (the request
    is taken up and reset to AXIS_STATE_UNDEFINED), axis.cpp:290-291 with
    controller.cpp:115-128 (closed-loop entry sets input_pos := pos_estimate, so a target
    written before the entry is overwritten)."""
    # a fast link (0.1 ms per transaction), so that two transactions fit in one iteration
    odrv = _device(plant=load_plant("default", usb_latency=0.1e-3))
    _calibrate(odrv)
    ax = odrv.axis0
    _just_after_a_millisecond(odrv)
    ax.requested_state = V.AXIS_STATE_CLOSED_LOOP_CONTROL
    assert ax.requested_state == V.AXIS_STATE_CLOSED_LOOP_CONTROL   # not taken up yet
    odrv.sleep(0.002)
    assert ax.requested_state == V.AXIS_STATE_UNDEFINED
    assert ax.current_state == V.AXIS_STATE_CLOSED_LOOP_CONTROL
    ax = odrv.axis1
    _just_after_a_millisecond(odrv)
    ax.requested_state = V.AXIS_STATE_CLOSED_LOOP_CONTROL
    ax.controller.input_pos = ax.encoder.pos_estimate + 0.3        # too early
    odrv.sleep(0.002)
    assert ax.requested_state == V.AXIS_STATE_UNDEFINED
    assert ax.current_state == V.AXIS_STATE_CLOSED_LOOP_CONTROL
    assert ax.controller.input_pos == pytest.approx(ax.encoder.pos_estimate, abs=2e-3)


def test_invalid_state_is_cleared_by_a_new_request():
    """axis.cpp:586-589 sets AXIS_ERROR_INVALID_STATE; axis.cpp:487 clears it on the next
    request."""
    odrv = _device()
    _closed_loop(odrv, odrv.axis0)           # not calibrated
    assert odrv.axis0.error & V.AXIS_ERROR_INVALID_STATE
    odrv.axis0.requested_state = V.AXIS_STATE_IDLE
    odrv.sleep(0.002)
    assert odrv.axis0.error == 0


# -- rows 4, 5: calibration as motion, the count re-reference ---------------------------

def test_calibration_swings_the_leg_and_re_references_the_counts():
    """encoder.hpp:22-23 (16 pi rad at 4 pi rad/s: 8/11 motor turn, 87 deg of joint),
    encoder.cpp:329,378-447 (1 s lock, forward and back), encoder.cpp:344 (shadow_count :=
    count_in_cpr), axis.cpp:472-479 (states 4 -> 7 -> 1)."""
    odrv = _device(seed=5)
    start = np.degrees(odrv.st.X[0, [0, 2]]).copy()
    assert abs(odrv.axis0.encoder.shadow_count) <= 2 and abs(odrv.axis1.encoder.shadow_count) <= 2
    for a in (odrv.axis0, odrv.axis1):
        a.requested_state = V.AXIS_STATE_FULL_CALIBRATION_SEQUENCE
    swing, states, gaps = 0.0, set(), []
    for _ in range(int(V.CALIBRATION_DURATION / 0.05) + 4):
        odrv.sleep(0.05)
        q = np.degrees(odrv.st.X[0, [0, 2]])
        swing = max(swing, float(np.max(np.abs(q - start))))
        gaps.append(q[1] - q[0])
        states.add(odrv.axis0.current_state)
    assert {V.AXIS_STATE_MOTOR_CALIBRATION, V.AXIS_STATE_ENCODER_OFFSET_CALIBRATION, V.AXIS_STATE_IDLE} <= states
    expected = 360.0 * (16 * math.pi / (2 * math.pi * 11)) / 3.0     # 87.3 deg of joint
    assert swing == pytest.approx(expected, abs=6.0)
    assert max(gaps) - min(gaps) < 15.0          # both links swung together: the stop stays closed
    assert odrv.axis0.encoder.is_ready and odrv.axis0.error == 0
    # the count was wrapped into [0, cpr) at the start of the offset calibration
    counts = [odrv.axis0.encoder.shadow_count, odrv.axis1.encoder.shadow_count]
    assert any(c > 4000 // 2 for c in counts)   # a count just below 0 became one just below cpr


def test_a_blocked_scan_fails_the_cpr_check(odrv):
    """encoder.cpp:412-433: the forward scan must move the encoder by the expected counts to
    2 %. With the other upper link held in closed loop, the scanned link runs into the stop
    between the links and the check fails."""
    scanned = None
    for a, other in ((0, 1), (1, 0)):
        o = _device(seed=5)
        _calibrate(o)
        _closed_loop(o, getattr(o, f"axis{other}"))
        ax = getattr(o, f"axis{a}")
        ax.requested_state = V.AXIS_STATE_ENCODER_OFFSET_CALIBRATION
        o.sleep(V.OFFSET_LOCK_TIME + 2 * V.CALIB_SCAN_DISTANCE / V.CALIB_SCAN_OMEGA + 0.1)
        if ax.encoder.error:
            scanned = (a, ax.encoder.error, ax.encoder.is_ready, ax.current_state)
    assert scanned is not None
    _, err, ready, state = scanned
    assert err & V.ENCODER_ERROR_CPR_POLEPAIRS_MISMATCH and not ready and state == V.AXIS_STATE_IDLE


def test_calibration_that_never_finishes_fails_with_a_message(monkeypatch):
    """Issue 17: a plant whose calibration never ends fails by the wall clock too."""
    dev = lg.connect("virtual", seed=6)
    lg.configure(dev)
    monkeypatch.setattr(dev.sim, "sleep", lambda s: None)     # a frozen virtual clock
    with pytest.raises(ExperimentError, match="calibration of axis0 did not finish"):
        lg.calibrate(dev, timeout=0.5)


# -- row 6: the DC bus ------------------------------------------------------------------

def _brake_step(odrv):
    ax = odrv.axis1
    ax.controller.config.vel_limit = 12.0
    ax.controller.config.pos_gain = 50.0
    ax.controller.config.vel_gain = 0.046
    ax.controller.config.vel_integrator_gain = 0.0
    _closed_loop(odrv, ax)
    target = ax.encoder.pos_estimate + 0.4
    ax.controller.input_pos = target
    ibus = []
    for _ in range(200):
        odrv.sleep(0.002)
        ibus.append(odrv.ibus)
    return np.array(ibus)


def test_brake_resistor_off_by_default_and_regen_trips_the_board():
    """odrive_main.h:82 (enable_brake_resistor = false), odrive_main.h:111
    (dc_max_negative_current = -0.01 A), low_level.cpp:320-376 (bus current of the armed
    motors; below the limit: disarm_with_error), main.cpp:313-320 (both motors disarmed,
    ODRIVE_ERROR_DC_BUS_OVER_REGEN_CURRENT on odrv.error)."""
    odrv = _device(brake=False)
    assert odrv.config.enable_brake_resistor is False and odrv.config.dc_max_negative_current == pytest.approx(-0.01)
    _calibrate(odrv)
    _brake_step(odrv)
    assert odrv.error & V.ODRIVE_ERROR_DC_BUS_OVER_REGEN_CURRENT
    assert odrv.axis1.motor.error & L.MOTOR_ERROR_SYSTEM_LEVEL
    assert odrv.axis1.current_state == V.AXIS_STATE_IDLE


def test_brake_resistor_takes_the_regenerated_current():
    """low_level.cpp:337-361: with the resistor armed the bus current stays above the
    limit; motor.cpp:208-213: enabling it without arming (boot or clear_errors) refuses to
    arm the motors."""
    odrv = _device(brake=False)
    _calibrate(odrv)
    odrv.config.enable_brake_resistor = True     # enabled, not armed yet
    _closed_loop(odrv, odrv.axis1)
    assert odrv.axis1.current_state == V.AXIS_STATE_IDLE
    assert odrv.axis1.motor.error & V.MOTOR_ERROR_BRAKE_RESISTOR_DISARMED
    odrv.clear_errors()
    assert odrv.brake_resistor_armed
    ibus = _brake_step(odrv)
    assert odrv.error == 0 and odrv.axis1.error == 0
    assert ibus.max() > 0.0 and ibus.min() >= -0.01


def test_firmware_051_always_brakes_and_reports_bus_faults_on_the_motors():
    """fw-v0.5.1 low_level.cpp:620-668: the resistor is always used; a bus fault lands on
    the motors (low_level_fault), there is no odrv.error."""
    odrv = _device("0.5.1")
    _calibrate(odrv)
    _brake_step(odrv)
    assert odrv.axis1.error == 0
    odrv.config.dc_max_positive_current = 0.01
    _closed_loop(odrv, odrv.axis0)
    odrv.axis0.controller.input_pos = odrv.axis0.encoder.pos_estimate + 0.2
    odrv.sleep(0.05)
    assert odrv.axis0.motor.error & L.MOTOR_ERROR_DC_BUS_OVER_CURRENT


# -- row 7: errors ------------------------------------------------------------------------

def test_any_axis_error_disarms_and_idles(odrv):
    """main.cpp:413-420 with axis.hpp:151-153 (check_for_errors: any axis error disarms),
    axis.cpp:343-350 (the closed-loop state ends when disarmed)."""
    _closed_loop(odrv, odrv.axis0)
    odrv.axis0.error = 0x800
    odrv.sleep(0.001)
    assert odrv.axis0.current_state == V.AXIS_STATE_IDLE and not odrv.axis0.motor.is_armed


def test_firmware_051_has_no_motor_is_armed():
    """motor.is_armed came with 0.5.2 (fw-v0.5.2 odrive-interface.yaml:708); fw-v0.5.1 has
    motor.armed_state instead (its odrive-interface.yaml:517), not modeled: the twin refuses
    the name as the board would."""
    with pytest.raises(AttributeError, match="no attribute 'is_armed'"):
        V.VirtualODrive(firmware="0.5.1").axis0.motor.is_armed
    assert V.VirtualODrive().axis0.motor.is_armed is False


def test_clear_errors_the_firmware_way():
    """main.cpp:236-249 odrv.clear_errors (0.5.2+); fw-v0.5.1 axis.hpp:108-116."""
    new, old = _device("0.5.6"), _device("0.5.1")
    assert not hasattr(new.axis0, "clear_errors") or "clear_errors" not in dir(new.axis0)
    assert "clear_errors" not in dir(old)
    for o in (new, old):
        o.axis0.error = 0x800
        clear_errors(as_device(o))
        assert o.axis0.error == 0


# -- row 8: input modes -------------------------------------------------------------------

def test_input_modes(odrv):
    """controller.cpp:183-283: PASSTHROUGH copies the inputs, POS_FILTER is a critically
    damped 2nd-order filter at input_filter_bandwidth (controller.cpp:130-134), TRAP_TRAJ
    follows trapTraj.cpp planTrapezoidal and drops into position control when done."""
    ax = odrv.axis0
    ax.controller.config.vel_limit = 5.0
    _closed_loop(odrv, ax)
    p0 = ax.encoder.pos_estimate
    ax.controller.input_pos = p0 + 0.1
    odrv.sleep(0.001)
    assert ax.controller.pos_setpoint == pytest.approx(p0 + 0.1)
    ax.controller.config.input_filter_bandwidth = 5.0
    ax.controller.config.input_mode = V.INPUT_MODE_POS_FILTER
    p1 = ax.controller.pos_setpoint
    ax.controller.input_pos = p1 + 0.2
    t0 = odrv.time
    odrv.sleep(0.5 - (odrv.time - t0))
    w = 5.0 * (odrv.time - t0)
    assert ax.controller.pos_setpoint - p1 == pytest.approx(0.2 * (1 - (1 + w) * math.exp(-w)), rel=0.03)
    ax.controller.input_pos = ax.controller.pos_setpoint   # let it settle
    odrv.sleep(3.0)
    ax.trap_traj.config.vel_limit = 1.0
    ax.trap_traj.config.accel_limit = 2.0
    ax.trap_traj.config.decel_limit = 2.0
    ax.controller.config.input_mode = V.INPUT_MODE_TRAP_TRAJ
    p2 = ax.controller.pos_setpoint
    ax.controller.input_pos = p2 + 1.0
    t0 = odrv.time
    odrv.sleep(0.75 - (odrv.time - t0))
    t = odrv.time - t0       # Ta = Td = 0.5 s, Tv = 0.5 s: cruising at 1 turn/s
    assert ax.controller.vel_setpoint == pytest.approx(1.0)
    assert ax.controller.pos_setpoint - p2 == pytest.approx(0.25 + (t - 0.5), abs=0.01)
    assert not ax.controller.trajectory_done
    odrv.sleep(1.0)
    assert ax.controller.trajectory_done and ax.controller.pos_setpoint == pytest.approx(p2 + 1.0)


# -- row 9: the integrator --------------------------------------------------------------

def test_integrator_limit_and_reset_in_torque_mode(odrv):
    """controller.cpp:408-420: clamped to vel_integrator_limit (0.5.4+, default inf), zeroed
    in torque control."""
    ax = odrv.axis0
    assert ax.controller.config.vel_integrator_limit == math.inf
    ax.controller.config.control_mode = 2
    ax.controller.config.vel_integrator_gain = 5.0
    ax.controller.config.vel_integrator_limit = 0.01
    ax.controller.config.vel_limit = 5.0
    _closed_loop(odrv, ax)
    ax.controller.input_vel = 2.0       # the leg's stop and gravity hold it back
    odrv.sleep(0.3)
    assert 0 < abs(ax.controller.vel_integrator_torque) <= 0.01 + 1e-12
    ax.controller.config.control_mode = 1
    ax.controller.input_torque = 0.0
    odrv.sleep(0.01)
    assert ax.controller.vel_integrator_torque == 0.0
    old = _device("0.5.1")
    with pytest.raises(AttributeError):
        old.axis0.controller.config.vel_integrator_limit


# -- row 12: USB -------------------------------------------------------------------------

def test_each_transaction_costs_the_cited_latency():
    """One request-response per property (fibre's legacy protocol, legacy_protocol.cpp:
    456-497). The mean per transaction is the plant's usb_latency (0.36 ms: the Python
    client on a v3.x, plant_default.toml cites it); its spread and tail are the host's
    measured share (tables/usb_client_latency.json): the median below the mean, a tail of
    milliseconds. usb_jitter 0 gives a constant latency."""
    from leglib.device.virtual import transport
    odrv = _device()
    lat = odrv.twin.plant.usb_latency
    steps = []
    for _ in range(4000):
        t0 = odrv.time
        odrv.axis0.encoder.shadow_count
        steps.append(odrv.time - t0)
    steps = np.asarray(steps)
    tick = odrv.twin.dt                  # the clock moves in whole ticks, the rest carried
    assert abs(np.mean(steps) - lat) < 0.05 * lat
    host = transport.client_cost()
    assert np.median(steps) < np.mean(steps)                  # a right-skewed cost
    assert np.quantile(steps, 0.999) > lat + 0.5 * (host["seconds"][-3] - host["mean_s"]) - tick
    assert steps.min() >= 0.0
    flat = _device(plant=load_plant("default", usb_jitter=0.0))
    t0 = flat.time
    for _ in range(200):
        flat.axis0.encoder.shadow_count
    assert flat.time - t0 == pytest.approx(200 * lat, abs=tick)
