"""Conformance of the virtual ODrive with firmware 0.5.x (odriverobotics/ODrive, tags
fw-v0.5.6 and fw-v0.5.1; file:line of Firmware/MotorControl/ at fw-v0.5.6 unless marked).
The checklist is /work/shared/odrive/README.md, rows 1-12."""

import math

import numpy as np
import pytest

import leglib as lg
from leglib.device.session import ExperimentError, as_device, clear_errors
from leglib.device.virtual import firmware as V
from leglib.device.virtual.tree import UnmodeledError
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
    odrv.axis0.encoder.set_linear_count(5000)          # encoder.cpp:141-154: far from 0
    odrv.axis1.encoder.set_linear_count(-7000)
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
    assert max(map(abs, after)) < 200 and min(map(abs, before)) > 4000  # counts restart at 0
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

def test_calibration_swings_the_leg_and_keeps_the_counts_in_the_boot_frame():
    """encoder.hpp:22-23 (16 pi rad at 4 pi rad/s: 8/11 motor turn, 87 deg of joint),
    encoder.cpp:329,378-447 (1 s lock, forward and back), axis.cpp:472-479 (states 4 -> 7 ->
    1). encoder.cpp:344 sets shadow_count := count_in_cpr, but the incremental encoder's
    next update (encoder.cpp:480,657-662,762) adds the int16 difference to the timer's
    count, which never moved: the counts stay in the boot frame (no whole-turn shift)."""
    odrv = _device(seed=5)
    start = np.degrees(odrv.st.X[0, [0, 2]]).copy()
    assert abs(odrv.axis0.encoder.shadow_count) <= 2 and abs(odrv.axis1.encoder.shadow_count) <= 2
    boot_turns = [float(odrv.twin.encoder_turns(odrv.st, odrv.twin.axes.joint_of_axis(a))[0]) for a in (0, 1)]
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
    # the counts are the rotor's travel since boot, whatever count_in_cpr was
    for a, ax in enumerate((odrv.axis0, odrv.axis1)):
        turns = float(odrv.twin.encoder_turns(odrv.st, odrv.twin.axes.joint_of_axis(a))[0])
        assert ax.encoder.shadow_count == pytest.approx((turns - boot_turns[a]) * 4000, abs=3)
        assert abs(ax.encoder.shadow_count) < 4000 // 2          # near the start: no turn added
        assert ax.encoder.count_in_cpr == ax.encoder.shadow_count % 4000


def test_zeroing_after_calibration_gives_the_rest_pose():
    """Whatever frame the counts are in, the zeroing step (read pos_estimate at rest) makes
    the joint angles the rest pose's, on both firmwares."""
    for seed, firmware in ((8, "0.5.6"), (9, "0.5.1")):
        dev = lg.connect("virtual", seed=seed, firmware=firmware)
        lg.configure(dev)
        lg.calibrate(dev)
        q_true = dev.sim.st.X[0, [0, 2]]
        a1, a2 = dev.axes.axis_of_joint
        q = [float(dev.axes.counts_to_joint(dev.counts(a1), 0)), float(dev.axes.counts_to_joint(dev.counts(a2), 1))]
        # the leg rests within its friction dead band of where it rested at zeroing
        assert np.degrees(np.abs(np.array(q) - q_true)).max() < 1.5, firmware


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
    # fw-v0.5.1 low_level.cpp:87-95: low_level_fault also disarms the brake resistor, which
    # only start_adc_pwm arms (low_level.cpp:239-243, at boot): axis.cpp:168-172 then reports
    # BRAKE_RESISTOR_DISARMED in every check and MOTOR_DISARMED for an axis that ran (0x30:
    # axis1, in closed loop since the brake step); 0.5.1 never sets MOTOR_FAILED (0x40)
    assert odrv.axis1.error == 0x30 and odrv.axis0.error in (0x10, 0x30)
    assert odrv.brake_resistor_armed is False
    odrv.config.dc_max_positive_current = float("inf")
    odrv.axis0.clear_errors()
    assert odrv.axis0.error == 0x10                       # set again by the next check
    _closed_loop(odrv, odrv.axis0)
    assert odrv.axis0.current_state == V.AXIS_STATE_IDLE   # refused: an axis error
    odrv.reboot()
    odrv.reconnect()
    assert odrv.brake_resistor_armed is True and odrv.axis0.error == 0 and odrv.axis1.error == 0


def test_firmware_051_dc_max_negative_current_default():
    """fw-v0.5.1 odrive_main.h:124: dc_max_negative_current = -0.000001 A (0.5.2+: -0.01 A,
    odrive_main.h:111)."""
    assert _device("0.5.1").config.dc_max_negative_current == pytest.approx(-1e-6)
    assert _device("0.5.6").config.dc_max_negative_current == pytest.approx(-0.01)


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
    motor.armed_state instead (its odrive-interface.yaml:517: 0 disarmed, 3 armed): the twin
    refuses the name as the board would."""
    with pytest.raises(AttributeError, match="no attribute 'is_armed'"):
        V.VirtualODrive(firmware="0.5.1").axis0.motor.is_armed
    assert V.VirtualODrive().axis0.motor.is_armed is False
    assert V.VirtualODrive(firmware="0.5.1").axis0.motor.armed_state == 0


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


# -- the startup sequence (axis.hpp:202, axis.cpp:458-471) ---------------------------------

def _save_and_boot(odrv):
    with pytest.raises(V.DeviceLostError):
        odrv.save_configuration()
    odrv.reconnect()


def test_a_fresh_board_takes_up_its_startup_sequence_into_idle():
    """axis.hpp:202: requested_state starts as STARTUP_SEQUENCE; with no startup flag the
    chain is IDLE alone (axis.cpp:458-471), and the request reads back 0 once taken."""
    odrv = _device()
    assert odrv.axis0.current_state == V.AXIS_STATE_IDLE and odrv.axis0.requested_state == 0
    _save_and_boot(odrv)
    assert odrv.axis0.current_state == V.AXIS_STATE_IDLE and odrv.axis1.requested_state == 0


def test_startup_sequence_runs_at_every_boot_and_closes_the_loop_under_the_watchdog():
    """axis.cpp:458-471 at every boot, also after a save's reset: motor calibration, offset
    calibration, then closed loop, which arms the motor holding position; axis.cpp:577 feeds
    the watchdog at the entry and it counts down from there (axis.cpp:171-182): a host that
    does not feed it within the timeout gets WATCHDOG_TIMER_EXPIRED and the axis idles."""
    odrv = _device()
    ax = odrv.axis0
    ax.config.startup_motor_calibration = True
    ax.config.startup_encoder_offset_calibration = True
    ax.config.startup_closed_loop_control = True
    ax.config.watchdog_timeout = 2.0        # longer than the boot (1.5 s), or it expires first
    ax.watchdog_feed()
    ax.config.enable_watchdog = True
    _save_and_boot(odrv)
    ax = odrv.axis0                         # the handle of the new boot
    assert ax.current_state == V.AXIS_STATE_MOTOR_CALIBRATION
    assert odrv.axis1.current_state == V.AXIS_STATE_IDLE
    t_cal = V.CALIBRATION_DURATION
    for _ in range(int(t_cal / 0.4)):        # the host feeds the watchdog meanwhile
        ax.watchdog_feed()
        odrv.sleep(0.4)
    while ax.current_state != V.AXIS_STATE_CLOSED_LOOP_CONTROL and odrv.time < 60:
        ax.watchdog_feed()
        odrv.sleep(0.05)
    assert ax.current_state == V.AXIS_STATE_CLOSED_LOOP_CONTROL and ax.motor.is_armed
    assert ax.encoder.is_ready and ax.error == 0
    assert ax.controller.input_pos == pytest.approx(ax.encoder.pos_estimate, abs=0.01)
    odrv.sleep(2.1)                           # nobody feeds it now
    assert ax.current_state == V.AXIS_STATE_IDLE
    assert ax.error & V.AXIS_ERROR_WATCHDOG_TIMER_EXPIRED
    # the flags are saved: the next boot runs the chain again
    ax.config.enable_watchdog = False
    odrv.clear_errors()
    _save_and_boot(odrv)
    assert odrv.axis0.current_state == V.AXIS_STATE_MOTOR_CALIBRATION


def test_a_saved_watchdog_shorter_than_the_boot_expires_before_the_startup_sequence():
    """axis.cpp:77-81 feeds the watchdog when the configuration is applied, the control loop
    counts it down from then (main.cpp:410-421), while rtos_main waits for the current
    sensors before it starts the axis threads (main.cpp:561-584, 1.5 s): a saved timeout
    shorter than that expires first, and the startup calibration cannot arm."""
    odrv = _device()
    ax = odrv.axis0
    ax.config.startup_motor_calibration = True
    ax.config.watchdog_timeout = 0.5
    ax.watchdog_feed()
    ax.config.enable_watchdog = True
    _save_and_boot(odrv)
    assert odrv.axis0.current_state == V.AXIS_STATE_IDLE
    assert odrv.axis0.error & V.AXIS_ERROR_WATCHDOG_TIMER_EXPIRED


def test_startup_closed_loop_on_an_uncalibrated_board_is_refused_at_boot():
    """axis.cpp:572-578: closed loop needs a calibrated motor (and 0.5.6 an encoder
    direction): at boot without the calibration flags the chain fails with INVALID_STATE."""
    odrv = _device()
    odrv.axis1.config.startup_closed_loop_control = True
    _save_and_boot(odrv)
    assert odrv.axis1.current_state == V.AXIS_STATE_IDLE
    assert odrv.axis1.error == V.AXIS_ERROR_INVALID_STATE


# -- the board: a v3.6 56 V on the thesis's battery (board.h:40-47, odrive_main.h:83-111) --

def test_the_board_is_the_thesis_56v_v36_with_its_defaults():
    """odrive_main.h:210-212: hw_version 3.6, variant HW_VERSION_VOLTAGE = 56; board.h:40-44:
    a 2.0 ohm brake resistor on a 48 V+ board; odrive_main.h:83-84: under-voltage 8 V,
    over-voltage 1.07 * 56 V; motor.hpp:24: torque_constant 0.04 before Listing 7.1 writes
    its 8.27/340; thermistor.hpp:63: the motor thermistor off. Every configuration endpoint
    of a fresh board reads the firmware's default (tables/defaults_fw-v*.json)."""
    from leglib.device.virtual import catalog, wire
    for fw in V.FIRMWARES:
        odrv = V.VirtualODrive(firmware=fw)
        assert (odrv.hw_version_major, odrv.hw_version_minor, odrv.hw_version_variant) == (3, 6, 56)
        assert odrv.config.brake_resistance == 2.0
        assert odrv.config.dc_bus_undervoltage_trip_level == 8.0
        assert odrv.config.dc_bus_overvoltage_trip_level == pytest.approx(1.07 * 56, rel=1e-6)
        assert odrv.axis0.motor.config.torque_constant == pytest.approx(0.04)
        thermistor = odrv.axis0.motor.motor_thermistor if fw != "0.5.1" else odrv.axis0.motor_thermistor
        assert thermistor.config.enabled is False
        defaults = wire.firmware_defaults(fw)
        rows = catalog.fill(V.ENDPOINTS, fw) + tuple(V.ENDPOINTS)
        checked = 0
        for path, (a, row) in T_model_paths(rows, fw).items():
            hit = defaults.get(row.path)
            if hit is None or row.function or path.endswith(("requested_state",)):
                continue
            value = odrv._leaves[path].node._props[odrv._leaves[path].name].get()
            want = hit["axes"][a] if "axes" in hit and a is not None else hit["value"]
            if row.kind is int and want < 0:
                continue                          # C's conversion (axis_to_mirror = -1 reads 255)
            assert value == pytest.approx(want, rel=1e-6), (fw, path, value, want)
            checked += 1
        assert checked > 150


def T_model_paths(rows, fw):
    from leglib.device.virtual import tree
    return tree.model_paths(rows, fw)


def test_vbus_is_the_battery_less_its_drop_and_trips_at_its_levels():
    """main.cpp:300-305, checked every current measurement, armed or not: below
    dc_bus_undervoltage_trip_level (or above the over-voltage level) disarm_with_error
    (main.cpp:313-321): both motors SYSTEM_LEVEL, the axes MOTOR_FAILED (motor.cpp:340), the
    brake resistor disarmed, odrv.error DC_BUS_UNDER_VOLTAGE (0x2) / OVER_VOLTAGE (0x4). The
    bus is the 6S pack (Table 4.4) at 24 V less 30 mOhm times the bus current."""
    odrv = _device()
    v = np.mean([odrv.vbus_voltage for _ in range(50)])
    assert v == pytest.approx(24.0, abs=0.05)
    odrv.config.dc_bus_undervoltage_trip_level = 24.5
    odrv.sleep(0.002)
    assert odrv.error == L.ODRIVE_ERROR_DC_BUS_UNDER_VOLTAGE
    assert odrv.axis0.motor.error & L.MOTOR_ERROR_SYSTEM_LEVEL and odrv.axis1.error & V.AXIS_ERROR_MOTOR_FAILED
    assert odrv.brake_resistor_armed is False
    odrv.config.dc_bus_undervoltage_trip_level = 8.0
    odrv.clear_errors()
    assert odrv.error == 0 and odrv.brake_resistor_armed
    odrv.config.dc_bus_overvoltage_trip_level = 23.0
    odrv.sleep(0.002)
    assert odrv.error == L.ODRIVE_ERROR_DC_BUS_OVER_VOLTAGE
    old = _device("0.5.1")                     # fw-v0.5.1 axis.cpp:173-176: the axes' own errors
    old.config.dc_bus_undervoltage_trip_level = 30.0
    old.sleep(0.002)
    assert old.axis0.error & L.AXIS_ERROR_DC_BUS_UNDER_VOLTAGE and old.axis1.error & L.AXIS_ERROR_DC_BUS_UNDER_VOLTAGE


def test_an_enabled_brake_resistor_needs_a_positive_resistance():
    """low_level.cpp:332-336: every PWM update with the resistor enabled, a resistance that
    is not positive disarms the board with INVALID_BRAKE_RESISTANCE (0x80): the firmware
    stores the value, then trips on it."""
    odrv = _device()
    odrv.config.brake_resistance = 0.0
    assert odrv.config.brake_resistance == 0.0
    assert odrv.error & 0x80 and not odrv.brake_resistor_armed


# -- settings, functions, readings ---------------------------------------------------------

def test_limits_are_stored_as_any_float():
    """The firmware stores any float in its config (odrive-interface.yaml: no range); a
    zero or negative limit is taken and acts as the firmware's arithmetic makes it act
    (vel_limit 0: the velocity setpoint clamps to 0, controller.cpp:286-288)."""
    odrv = _device()
    odrv.axis0.controller.config.vel_limit = -1.0
    odrv.axis0.motor.config.current_lim = 0.0
    odrv.axis1.encoder.config.bandwidth = -5.0
    assert odrv.axis0.controller.config.vel_limit == -1.0 and odrv.axis0.motor.config.current_lim == 0.0
    assert odrv.axis1.encoder.config.bandwidth == -5.0


def test_erase_configuration_resets_to_the_firmwares_defaults_and_reboots():
    """main.cpp:186-195: NVM_erase then NVIC_SystemReset: the handle is lost and the board
    comes back with the defaults (config_clear_all, main.cpp:126-143)."""
    odrv = _device()
    odrv.axis0.controller.config.pos_gain = 42.0
    _save_and_boot(odrv)
    assert odrv.axis0.controller.config.pos_gain == 42.0 and odrv.user_config_loaded > 0
    with pytest.raises(V.DeviceLostError):
        odrv.erase_configuration()
    odrv.reconnect()
    assert odrv.axis0.controller.config.pos_gain == 20.0          # controller.hpp default
    assert odrv.axis0.encoder.config.cpr == 8192 and odrv.user_config_loaded == 0


def test_motor_calibration_measures_r_and_l_and_the_gains_follow():
    """motor.cpp:416-463: R from the resistance law's integrator at calibration_current, L
    from the current ripple of an alternating test voltage; motor.cpp:297-302 and
    motor.hpp:58-60: p_gain = bandwidth * L, i_gain = p_gain * R / L, also after a write;
    the kernel's current PI runs on the measured or written values (C_PHASE_R, C_PHASE_L),
    not on the motor's own."""
    odrv = _device()
    _calibrate(odrv, (0,))
    m = odrv.twin.motor
    ax = odrv.axis0
    assert ax.motor.config.phase_resistance == pytest.approx(m.phase_resistance, rel=0.01)
    assert ax.motor.config.phase_inductance == pytest.approx(m.phase_inductance, rel=0.02)
    assert ax.motor.config.phase_resistance != m.phase_resistance        # a measurement, with its noise
    assert odrv.st.C[0, 0, L.C_PHASE_R] == ax.motor.config.phase_resistance
    assert odrv.st.C[0, 0, L.C_PHASE_L] == ax.motor.config.phase_inductance
    bw = ax.motor.config.current_control_bandwidth
    assert ax.motor.current_control.p_gain == pytest.approx(bw * ax.motor.config.phase_inductance, rel=1e-5)
    assert ax.motor.current_control.i_gain == pytest.approx(
        bw * ax.motor.config.phase_resistance, rel=1e-5)
    ax.motor.config.phase_inductance = 1.2 * m.phase_inductance
    assert ax.motor.current_control.p_gain == pytest.approx(bw * 1.2 * m.phase_inductance, rel=1e-5)
    assert odrv.st.C[0, 0, L.C_PHASE_L] == 1.2 * m.phase_inductance
    ax.motor.config.phase_resistance = 1.1 * m.phase_resistance
    assert odrv.st.C[0, 0, L.C_PHASE_R] == 1.1 * m.phase_resistance
    # a fresh motor: R = L = 0 give i_gain = 0 * 0/0, NaN as in float32 (motor.cpp:300)
    assert math.isnan(odrv.axis1.motor.current_control.i_gain)


def test_the_resistance_measurement_fails_beyond_its_voltage():
    """motor.cpp:38-40,443: the test voltage beyond resistance_calib_max_voltage is
    PHASE_RESISTANCE_OUT_OF_RANGE (as calibration_test.py:53-78 expects of an open phase)."""
    odrv = _device()
    odrv.axis0.motor.config.resistance_calib_max_voltage = 0.2    # R * 10 A = 0.69 V needed
    odrv.axis0.requested_state = V.AXIS_STATE_MOTOR_CALIBRATION
    odrv.sleep(4.5)
    assert odrv.axis0.current_state == V.AXIS_STATE_IDLE
    assert odrv.axis0.motor.error == 0x1 and odrv.axis0.error == V.AXIS_ERROR_MOTOR_FAILED


def test_calibration_settings_act_on_the_offset_calibration():
    """encoder.cpp:361,389-421: calib_scan_distance and calib_scan_omega shape the scan (the
    response is the distance in counts), calib_range is the CPR check's tolerance; the
    mean count of the scans is phase_offset (encoder.cpp:445-447)."""
    odrv = _device()
    _calibrate(odrv, (0,))
    ax = odrv.axis0
    pp, cpr = 11, 4000
    expect = 16 * math.pi / (pp * 2 * math.pi / cpr)
    assert ax.encoder.calib_scan_response == pytest.approx(expect, rel=0.02)
    ax.encoder.config.calib_scan_distance = 8 * math.pi
    ax.encoder.config.calib_scan_omega = 2 * math.pi
    ax.requested_state = V.AXIS_STATE_ENCODER_OFFSET_CALIBRATION
    odrv.sleep(1.0 + 8.0 + 0.1)
    assert ax.current_state == V.AXIS_STATE_IDLE and ax.error == 0
    assert ax.encoder.calib_scan_response == pytest.approx(expect / 2, rel=0.02)
    assert isinstance(ax.encoder.config.phase_offset, int) and 0.0 <= ax.encoder.config.phase_offset_float < 1.5
    ax.encoder.config.calib_range = 1e-5
    ax.requested_state = V.AXIS_STATE_ENCODER_OFFSET_CALIBRATION
    odrv.sleep(1.0 + 4.0 + 0.1)
    assert ax.encoder.error == V.ENCODER_ERROR_CPR_POLEPAIRS_MISMATCH


def test_derived_readings_are_computed():
    """encoder.cpp:800-845 (counts, circular position), main.cpp:342,366 and motor.cpp:605
    (the counters: one per 125 us period), main.cpp:263 (uptime), interface_usb.cpp (USB
    packets), board.cpp:499,573 (task_timers_armed cleared by the next control iteration),
    main.cpp:470-484 (get_interrupt_status: SysTick at priority 15, 1 kHz), low_level.cpp:
    250-309 (get_adc_voltage: -3.3 V for a pin without ADC channel, the idle UART line
    at 4095 of 4096 counts, a floating input refused), odrive_main.h:184-187 (test_function's counter)."""
    odrv = _device()
    _calibrate(odrv, (0,))
    ax = odrv.axis0
    _closed_loop(odrv, ax)
    ax.controller.input_pos = ax.encoder.pos_estimate + 0.3
    odrv.sleep(0.5)
    pos = ax.encoder.pos_estimate
    assert ax.encoder.pos_estimate_counts == pytest.approx(pos * 4000, abs=40)
    assert ax.encoder.pos_circular == pytest.approx(pos % 1.0, abs=0.01)
    assert ax.encoder.pos_cpr_counts == pytest.approx((pos * 4000) % 4000, abs=40)
    t0, n0 = odrv.time, odrv.n_evt_control_loop
    odrv.sleep(0.1)
    n1 = odrv.n_evt_control_loop
    assert (n1 - n0) == pytest.approx((odrv.time - t0) * 8000, abs=16)
    assert odrv.system_stats.uptime == pytest.approx(odrv.time * 1000, abs=5)
    rx = odrv.system_stats.usb.rx_cnt
    odrv.vbus_voltage
    assert odrv.system_stats.usb.rx_cnt == rx + 2
    odrv.task_timers_armed = True
    assert odrv.task_timers_armed is False
    status = odrv.get_interrupt_status(-1)
    assert status & 0xff == 15 and status & 0x80000000
    assert (status >> 8) & 0x7fffff == pytest.approx(odrv.time * 1000, abs=5)
    assert odrv.get_adc_voltage(6) == -3.3 and odrv.get_adc_voltage(1) == pytest.approx(4095 / 4096 * 3.3)
    with pytest.raises(UnmodeledError, match="floating"):
        odrv.get_adc_voltage(3)
    assert odrv.test_function(2) == 2 and odrv.test_function(3) == 5
    assert ax.motor.effective_current_lim == pytest.approx(10.0)
    assert ax.motor.max_allowed_current == pytest.approx(60.75)      # 2430 A / gain 40


# -- open-loop procedures -------------------------------------------------------------------

def test_direction_find_lockin_and_index_search_move_the_rotor():
    """encoder.cpp:183-207: a 3 s calibration lock-in sets the direction from the count;
    axis.cpp:564-570: LOCKIN_SPIN needs a calibrated motor and a direction and spins until
    a new request; encoder.cpp:174-181,86-107: the index search finds the AS5047D's index
    and references the count there (index_offset * cpr)."""
    odrv = _device()
    ax = odrv.axis0
    ax.requested_state = V.AXIS_STATE_MOTOR_CALIBRATION
    odrv.sleep(4.5)
    ax.requested_state = 9                                    # LOCKIN_SPIN: no direction yet
    odrv.sleep(0.01)
    assert ax.error == V.AXIS_ERROR_INVALID_STATE
    c0 = ax.encoder.shadow_count
    ax.requested_state = 10                                   # ENCODER_DIR_FIND
    odrv.sleep(6.0)
    assert ax.current_state == V.AXIS_STATE_IDLE and ax.error == 0
    assert ax.encoder.config.direction == (1 if ax.encoder.shadow_count > c0 else -1)
    ax.requested_state = 9
    odrv.sleep(3.0)
    assert ax.current_state == 9 and abs(ax.encoder.vel_estimate) > 0.3     # still spinning
    ax.requested_state = V.AXIS_STATE_IDLE
    odrv.sleep(0.01)
    ax.encoder.config.use_index = True
    assert ax.encoder.index_found is False
    ax.requested_state = V.AXIS_STATE_ENCODER_INDEX_SEARCH
    for _ in range(40):
        odrv.sleep(0.5)
        if ax.current_state == V.AXIS_STATE_IDLE:
            break
    assert ax.encoder.index_found is True and ax.error == 0
    # the count is referenced to the index: index_offset (0) * cpr where the index is
    turns = odrv._rotor_encoder_turns(0)
    idx = odrv._index_position[0]
    from_index = turns - (idx + round(turns - idx))
    assert ax.encoder.shadow_count == pytest.approx(from_index * 4000, abs=6)


def test_homing_fails_without_an_endstop_and_enabling_one_is_refused():
    """axis.cpp:356-361: homing needs the min endstop, else HOMING_WITHOUT_ENDSTOP (0x20000);
    this leg has none: enabling one is refused with the reason (the model is stricter)."""
    odrv = _device()
    odrv.axis0.requested_state = 11
    odrv.sleep(0.01)
    assert odrv.axis0.error == 0x20000 and odrv.axis0.current_state == V.AXIS_STATE_IDLE
    with pytest.raises(UnmodeledError, match="min_endstop.config.enabled.*endstop"):
        odrv.axis0.min_endstop.config.enabled = True


def test_states_the_model_cannot_run_are_refused_at_the_request():
    """The hall calibrations (axis.cpp:527-544) need hall sensors; a current loop on gains
    from written R and L far off the motor's (motor.cpp:297-302) is not the twin's: both
    refused at the write of requested_state, naming why."""
    odrv = _device()
    with pytest.raises(UnmodeledError, match="hall"):
        odrv.axis0.requested_state = 12
    _calibrate(odrv, (0,))
    odrv.axis0.motor.config.phase_resistance = 1.0
    with pytest.raises(UnmodeledError, match="phase_resistance.*gains"):
        odrv.axis0.requested_state = V.AXIS_STATE_CLOSED_LOOP_CONTROL
    assert odrv.axis0.requested_state == 0


def test_a_pre_calibrated_encoder_is_ready_once_its_index_is_found_after_a_boot():
    """encoder.cpp:130-138: pre_calibrated stays only on a ready encoder whose index was
    found; axis.cpp:463-464 and encoder.cpp:86-95: at boot the startup index search finds it
    and the encoder is ready without an offset calibration; closed loop works."""
    odrv = _device()
    ax = odrv.axis0
    ax.requested_state = V.AXIS_STATE_MOTOR_CALIBRATION
    odrv.sleep(4.5)
    ax.encoder.config.use_index = True
    ax.requested_state = V.AXIS_STATE_ENCODER_INDEX_SEARCH    # the spin swings the leg:
    for _ in range(40):
        odrv.sleep(0.5)
        if ax.current_state == V.AXIS_STATE_IDLE:
            break
    odrv.sleep(8.0)                                          # let it come to rest first
    ax.requested_state = V.AXIS_STATE_ENCODER_OFFSET_CALIBRATION
    odrv.sleep(V.CALIBRATION_DURATION)
    assert ax.error == 0 and ax.encoder.is_ready and ax.encoder.index_found
    ax.encoder.config.pre_calibrated = True
    ax.motor.config.pre_calibrated = True
    assert ax.encoder.config.pre_calibrated is True
    ax.config.startup_encoder_index_search = True
    _save_and_boot(odrv)
    ax = odrv.axis0
    assert not ax.encoder.is_ready
    for _ in range(40):
        odrv.sleep(0.5)
        if ax.current_state == V.AXIS_STATE_IDLE:
            break
    assert ax.encoder.index_found and ax.encoder.is_ready
    odrv.sleep(8.0)                          # the search swung the leg: at rest, no OVERSPEED
    ax.controller.input_pos = ax.encoder.pos_estimate
    _closed_loop(odrv, ax)
    assert ax.current_state == V.AXIS_STATE_CLOSED_LOOP_CONTROL, hex(ax.controller.error)
    # an offset written over the measured one (a configuration restored from another board)
    # would commutate the motor wrongly (encoder.cpp:833-838): refused at the request
    ax.requested_state = V.AXIS_STATE_IDLE
    odrv.sleep(0.01)
    ax.encoder.config.phase_offset = ax.encoder.config.phase_offset + 500
    with pytest.raises(UnmodeledError, match="phase_offset"):
        ax.requested_state = V.AXIS_STATE_CLOSED_LOOP_CONTROL


def test_real_time_never_runs_ahead_of_the_wall_clock():
    """Paced in real time, the virtual clock is never ahead of the wall clock after a
    transaction returns (firmware.py _pace): a request written is taken up by the axis thread
    on its next iteration (axis.cpp:447-451, a 1 ms period), so a script that sleeps 1 ms
    after writing requested_state finds it taken (requested_state read back as UNDEFINED,
    axis.cpp:455-459), as on a board; a clock that ran ahead left it pending."""
    import time
    odrv = _device(realtime=True)
    ax = odrv.axis0
    ahead, pending = [], 0
    for _ in range(40):
        ax.requested_state = V.AXIS_STATE_IDLE
        ahead.append(odrv.time - (time.monotonic() - odrv._t0_wall))
        time.sleep(0.001)
        pending += ax.requested_state != V.AXIS_STATE_UNDEFINED
        ahead.append(odrv.time - (time.monotonic() - odrv._t0_wall))
    assert max(ahead) <= 1e-9, f"the virtual clock ran {max(ahead) * 1e3:.3f} ms ahead of the wall clock"
    assert pending == 0, f"{pending} of 40 requests not taken 1 ms after their write"
