"""A virtual ODrive v3.6: the firmware's object tree over a :class:`leglib.twin.host.Twin`.

The tree mirrors firmware 0.5.6 (default) or 0.5.1, property for property with the
firmware's endpoint names (``odrv.axis0.controller.config.pos_gain``, ``odrv.error``,
``odrv.config.enable_brake_resistor``, ...; see ``endpoints_fw-v0.5.x.json``), declared
in :data:`ENDPOINTS`: one row per endpoint with its store, type, check and firmware
versions (:mod:`~leglib.device.virtual.tree`), so adding an endpoint is adding a row. A v3.6
board has no 0.6 firmware, so there is no 0.6 tree. Unknown attributes raise
AttributeError, as on the device. Every property read or write is one USB transaction:
the virtual clock advances by the link latency and the simulated leg moves on in the
compiled kernel (no Python per tick). ``realtime=True`` paces the virtual clock to the wall
clock, so host code that sleeps with ``time.sleep`` sees the leg move.

What the firmware does and this device does too (file:line of fw-v0.5.6 unless marked):

- ``requested_state`` is consumed by the axis thread at its next 1 ms iteration and reads
  back 0 (AXIS_STATE_UNDEFINED) afterwards; a new request clears AXIS_ERROR_INVALID_STATE
  (axis.cpp:455-488). Closed-loop entry feeds the watchdog (axis.cpp:577), resets the
  controller (motor.cpp:202, controller.cpp:12-18) and sets ``input_pos := pos_estimate``
  in position control (axis.cpp:290-291, controller.cpp:115-128).
- Calibration is motion: motor calibration locks the rotor at ``calibration_current``
  (3 s resistance, then 1.25 s inductance measurement; motor.cpp:416-423,457-463), then
  the encoder offset calibration (its ``shadow_count := count_in_cpr``, encoder.cpp:344,
  is undone by the incremental encoder's next update, encoder.cpp:480,657-662,762: the
  counts stay in the boot frame) locks 1 s, scans 16*pi electrical rad forward at
  4*pi rad/s and back (encoder.cpp:378-447, encoder.hpp:22-23) with the leg and its stop
  in the loop, and checks the scan against CPR and pole pairs to 2 % (encoder.cpp:425-433).
- The watchdog counts down every tick while enabled, in every state, and is only reloaded
  by a feed, a closed-loop entry or a boot (axis.cpp:77-81,165-182; main.cpp:413-420).
- ``save_configuration()`` refuses (returns False) while a motor is armed, else writes
  flash and reboots (main.cpp:159-184); the handle is lost (:class:`DeviceLostError`), a
  new connection sees the saved configuration, the counts restart at 0, calibration is
  gone unless ``motor.config.pre_calibrated`` (motor.cpp:306). On 0.5.1 it neither
  refuses nor reboots (fw-v0.5.1 main.cpp:43-61).
- The DC bus: each armed motor draws (1.5 R Iq^2 + torque * speed) / vbus; the brake
  resistor takes the regenerated current when enabled (0.5.6 default: disabled,
  odrive_main.h:82; 0.5.1: always); a bus current below ``dc_max_negative_current``
  (default -0.01 A, odrive_main.h:111) disarms both motors with
  ODRIVE_ERROR_DC_BUS_OVER_REGEN_CURRENT on ``odrv.error`` (low_level.cpp:320-376,
  main.cpp:313-320; on 0.5.1 as a motor error, fw-v0.5.1 low_level.cpp:620-668).
- Any axis error disarms and idles the axis (main.cpp:413-420, axis.cpp:343-350).
- The controller updates every tick in every state on 0.5.6 (main.cpp:438-446), on
  estimates connected at the first closed loop (axis.cpp:270-285): its overspeed check
  trips while IDLE too; on 0.5.1 it runs in closed loop only. Its settings and the current
  loop act in the kernel (:mod:`leglib.twin.kernel`; tests/device/test_firmware_control.py).

Extras the real device does not have (used through ``Device.sim`` by
:mod:`leglib.experiments`): ``sleep(s)``, ``time``, ``twin``, ``step_batch``, ``reboot()``,
``boot_count``, ``reconnect()`` and ``disconnect_after`` for fault-injection tests.
"""

from __future__ import annotations

import math
import time as _time

import numpy as np

from ...errors import DeviceLostError
from ...params import OdriveConfig, PlantParams
from ...twin import layout as L
from ...twin.host import Twin, controller_defaults, max_measurable_current
from ...twin.stages import fmodf_pos
from . import catalog, transport
from .board import BATTERY_RESISTANCE, BATTERY_VOLTAGE, BoardMixin
from .procedures import THREAD_START_AFTER_RESET, AxisThread
from .readings import AxisReadings
from .tree import (
    Attr,
    Board,
    C,
    Call,
    Const,
    Endpoint,
    Err,
    Get,
    I,
    Key,
    S,
    UnmodeledError,
    _Node,
    build_tree,
    c_value,
    honoured,
)

FIRMWARES = ("0.5.1", "0.5.6")


# odrive.enums values (firmware 0.5.x), kept here so the twin runs without the odrive package
AXIS_STATE_UNDEFINED, AXIS_STATE_IDLE, AXIS_STATE_STARTUP_SEQUENCE = 0, 1, 2
AXIS_STATE_FULL_CALIBRATION_SEQUENCE = 3
AXIS_STATE_MOTOR_CALIBRATION = 4
AXIS_STATE_ENCODER_INDEX_SEARCH = 6
AXIS_STATE_ENCODER_OFFSET_CALIBRATION = 7
AXIS_STATE_CLOSED_LOOP_CONTROL = 8
AXIS_ERROR_INVALID_STATE = 0x1
AXIS_ERROR_MOTOR_FAILED = 0x40
AXIS_ERROR_ENCODER_FAILED = 0x100
AXIS_ERROR_WATCHDOG_TIMER_EXPIRED = L.AXIS_ERROR_WATCHDOG_TIMER_EXPIRED
MOTOR_ERROR_BRAKE_RESISTOR_DISARMED = 0x800000
ENCODER_ERROR_CPR_POLEPAIRS_MISMATCH = 0x2
ENCODER_ERROR_NO_RESPONSE = 0x4
ODRIVE_ERROR_DC_BUS_OVER_REGEN_CURRENT = L.ODRIVE_ERROR_DC_BUS_OVER_REGEN_CURRENT
CONTROL_MODES = (0, 1, 2, 3)  # voltage (the controller treats it as torque), torque, velocity, position
INPUT_MODE_INACTIVE, INPUT_MODE_PASSTHROUGH, INPUT_MODE_VEL_RAMP = 0, 1, 2
INPUT_MODE_POS_FILTER, INPUT_MODE_TRAP_TRAJ, INPUT_MODE_TORQUE_RAMP = 3, 5, 6
INPUT_MODE_MIRROR, INPUT_MODE_TUNING = 7, 8


# firmware timings (fw-v0.5.6)
AXIS_THREAD_PERIOD = 1e-3        # axis.cpp:447-451 osDelay(1): the state machine's iteration
R_MEASUREMENT_TIME = 3.0         # motor.cpp:423: 3000 iterations of 1 ms
L_MEASUREMENT_TIME = 1.25        # motor.cpp:463: 1250 iterations of 1 ms
OFFSET_LOCK_TIME = 1.0           # encoder.cpp:329 start_lock_duration
CALIB_SCAN_DISTANCE = 16 * math.pi   # encoder.hpp:22 [rad electrical]
CALIB_SCAN_OMEGA = 4 * math.pi       # encoder.hpp:23 [rad/s electrical]
CALIB_RANGE = 0.02                   # encoder.hpp:21


# how fast the calibration current builds up: the offset calibration ramps at
# 2 * calibration_current per second (encoder.cpp:353); the resistance measurement's voltage
# integrator (kI = 1 V/s/A, motor.cpp:71) reaches the current with a time constant R / kI
# (0.07 s for this motor), taken here as a linear ramp over 3 time constants
OFFSET_RAMP_PER_A = 2.0


# a full calibration sequence (motor, then encoder offset) from request to IDLE
CALIBRATION_DURATION = (R_MEASUREMENT_TIME + L_MEASUREMENT_TIME + OFFSET_LOCK_TIME
                        + 2 * CALIB_SCAN_DISTANCE / CALIB_SCAN_OMEGA)


# not in the firmware: how long the board takes from reset until it answers on USB again
# (bootloader, clock and USB enumeration). Assumed; the host must wait for it anyway.
BOOT_TIME = 1.5


# configuration kept per axis in python (the rest lives in the kernel's C array)
_AXIS_CONFIG_KEYS = ("cpr", "pole_pairs", "motor_type", "motor_pre_calibrated",
                     "phase_resistance", "phase_inductance", "calibration_current", "calib_range", "torque_constant",
                     "offset_measured",
                     "calib_scan_distance", "calib_scan_omega",
                     "encoder_pre_calibrated", "use_index", "direction", "trap_vel_limit",
                     "trap_accel_limit", "trap_decel_limit", "startup_motor_calibration",
                     "startup_encoder_offset_calibration", "startup_closed_loop_control",
                     # the controller's and the motor's settings the kernel does not need
                     "steps_per_circular_range", "requested_current_range")


# slots of the kernel's C array that are volatile (inputs, leglib's abort bound, state)
_C_VOLATILE = (L.C_INPUT_POS, L.C_INPUT_VEL, L.C_INPUT_TORQUE, L.C_ABORT_ERROR, L.C_COUNT_OFFSET,
               L.C_CAL_VEL, L.C_CAL_RAMP) + tuple(range(L.C_TT_XI, L.C_TT_YACC + 1))


def _is_config(path: str) -> bool:
    """Whether the firmware saves endpoint ``path`` with its configuration: the members of
    its config structs (main.cpp:106-124), whose paths run through a ``config`` node."""
    return ".config." in f".{path}."


# -- the object tree: one row per endpoint (leglib/device/virtual/tree.py) ---------------
# Names as in the firmware's table (tables/endpoints_fw-v0.5.x.json), axis* for both axes; a
# board row's kernel slots are axis 0's. Stores: C, S, I, Err the kernel's slots; Key the
# axis's Python state (_axis[a]); Board the board's (_board); Attr a device attribute;
# Const a value; Get a reading computed by a method here; Call a function; setter= a method
# here that takes the write with the firmware's side effects. since/until: the first and
# last release with the endpoint (odrive-interface.yaml of each fw-v0.5.x tag). An endpoint
# of the table without a row is unmodeled: the wire holds its firmware default.
ENDPOINTS = (
    # the axis: its state machine (axis.cpp:455-488), errors, watchdog
    Endpoint("axis*.requested_state", Key("requested_state"), int, setter="_request_state"),
    Endpoint("axis*.current_state", Key("state", writable=False), int),
    Endpoint("axis*.error", Err(L.I_AXIS_ERR), int),
    Endpoint("axis*.watchdog_feed", Call("_feed")),                          # axis.cpp:165-168
    Endpoint("axis*.clear_errors", Call("_clear_errors"), until="0.5.1"),    # fw-v0.5.1 axis.hpp:108
    Endpoint("axis*.config.enable_watchdog", C(L.C_WD_ENABLE), bool),
    Endpoint("axis*.config.watchdog_timeout", C(L.C_WD_TIMEOUT)),
    Endpoint("axis*.config.startup_motor_calibration", Key("startup_motor_calibration"), bool),
    Endpoint("axis*.config.startup_encoder_offset_calibration", Key("startup_encoder_offset_calibration"), bool),
    Endpoint("axis*.config.startup_closed_loop_control", Key("startup_closed_loop_control"), bool),
    # the controller
    Endpoint("axis*.controller.error", Err(L.I_CTRL_ERR), int),
    Endpoint("axis*.controller.input_pos", C(L.C_INPUT_POS), setter="_set_input_pos"),
    Endpoint("axis*.controller.input_vel", C(L.C_INPUT_VEL)),
    Endpoint("axis*.controller.input_torque", C(L.C_INPUT_TORQUE)),
    Endpoint("axis*.controller.pos_setpoint", S(L.S_POS_SP)),
    Endpoint("axis*.controller.vel_setpoint", S(L.S_VEL_SP)),
    Endpoint("axis*.controller.trajectory_done", I(L.I_TRAJ_DONE), bool),
    Endpoint("axis*.controller.vel_integrator_torque", S(L.S_INTEGRATOR, writable=True)),
    Endpoint("axis*.controller.config.control_mode", C(L.C_CONTROL_MODE), int, setter="_set_control_mode"),
    Endpoint("axis*.controller.config.input_mode", C(L.C_INPUT_MODE), int, setter="_set_input_mode"),
    Endpoint("axis*.controller.config.pos_gain", C(L.C_POS_GAIN)),
    Endpoint("axis*.controller.config.vel_gain", C(L.C_VEL_GAIN)),
    Endpoint("axis*.controller.config.vel_integrator_gain", C(L.C_VEL_INT_GAIN)),
    Endpoint("axis*.controller.config.vel_integrator_limit", C(L.C_VEL_INT_LIMIT), since="0.5.4"),
    Endpoint("axis*.controller.config.vel_limit", C(L.C_VEL_LIMIT)),
    Endpoint("axis*.controller.config.vel_limit_tolerance", C(L.C_VEL_TOL)),
    Endpoint("axis*.controller.config.input_filter_bandwidth", C(L.C_FILTER_BW)),
    # the motor
    Endpoint("axis*.motor.error", Err(L.I_MOTOR_ERR), int),
    Endpoint("axis*.motor.is_calibrated", Key("motor_calibrated", writable=False), bool),
    Endpoint("axis*.motor.is_armed", Get("_is_armed"), bool, since="0.5.2"),   # 0.5.1: armed_state
    Endpoint("axis*.motor.current_control.Iq_measured", S(L.S_IQ_MEAS), since="0.5.2"),
    # fw-v0.5.1 declares it writable: a write holds until the next measurement overwrites it
    Endpoint("axis*.motor.current_control.Iq_measured", S(L.S_IQ_MEAS, writable=True), until="0.5.1"),
    Endpoint("axis*.motor.current_control.Iq_setpoint", S(L.S_IQ_SP)),
    Endpoint("axis*.motor.config.pole_pairs", Key("pole_pairs"), int),
    Endpoint("axis*.motor.config.torque_constant", Key("torque_constant"), setter="_set_torque_constant"),
    Endpoint("axis*.motor.config.motor_type", Key("motor_type"), int,
             check=honoured(0, "the leg's motors are MN5212s driven as HIGH_CURRENT (0); GIMBAL and ACIM "
                               "control (voltage FOC, slip estimation) are not modelled")),
    Endpoint("axis*.motor.config.current_control_bandwidth", C(L.C_CURRENT_BW)),
    Endpoint("axis*.motor.config.current_lim", C(L.C_CURRENT_LIM)),
    Endpoint("axis*.motor.config.calibration_current", Key("calibration_current")),
    Endpoint("axis*.motor.config.pre_calibrated", Key("motor_pre_calibrated"), bool, setter="_set_motor_pre_calibrated"),
    # motor.hpp:58-59: written by the motor calibration or by the host; either updates the
    # current controller's gains (motor.cpp:297-302)
    Endpoint("axis*.motor.config.phase_resistance", Key("phase_resistance"), setter="_set_phase_resistance"),
    Endpoint("axis*.motor.config.phase_inductance", Key("phase_inductance"), setter="_set_phase_inductance"),
    # the encoder
    Endpoint("axis*.encoder.error", Key("encoder_error"), int),
    Endpoint("axis*.encoder.is_ready", Key("encoder_ready", writable=False), bool),
    Endpoint("axis*.encoder.pos_estimate", S(L.S_POS_EST)),
    Endpoint("axis*.encoder.vel_estimate", S(L.S_VEL_EST)),
    Endpoint("axis*.encoder.shadow_count", I(L.I_COUNTS), int),
    Endpoint("axis*.encoder.count_in_cpr", Get("_count_in_cpr"), int),
    Endpoint("axis*.encoder.config.cpr", Key("cpr"), int, setter="_set_cpr"),
    Endpoint("axis*.encoder.config.bandwidth", C(L.C_ENCODER_BW)),
    Endpoint("axis*.encoder.config.direction", Key("direction"), int, since="0.5.2"),
    Endpoint("axis*.motor.config.direction", Key("direction"), int, until="0.5.1"),     # fw-v0.5.1 motor.hpp
    Endpoint("axis*.encoder.config.pre_calibrated", Key("encoder_pre_calibrated"), bool,
             setter="_set_encoder_pre_calibrated"),
    Endpoint("axis*.encoder.config.use_index", Key("use_index"), bool, setter="_set_use_index"),
    # encoder.hpp:21-23: read by the offset calibration (encoder.cpp:415-436)
    Endpoint("axis*.encoder.config.calib_range", Key("calib_range")),
    Endpoint("axis*.encoder.config.calib_scan_distance", Key("calib_scan_distance")),
    Endpoint("axis*.encoder.config.calib_scan_omega", Key("calib_scan_omega")),
    # the trapezoidal trajectory planner
    Endpoint("axis*.trap_traj.config.vel_limit", Key("trap_vel_limit")),
    Endpoint("axis*.trap_traj.config.accel_limit", Key("trap_accel_limit")),
    Endpoint("axis*.trap_traj.config.decel_limit", Key("trap_decel_limit")),
    # the board
    Endpoint("error", Err(L.I_SYS_ERR), int, since="0.5.2"),
    Endpoint("vbus_voltage", Get("_vbus_voltage")),
    Endpoint("ibus", S(L.S_IBUS)),
    Endpoint("brake_resistor_armed", Attr("_brake_armed"), bool),
    Endpoint("brake_resistor_current", S(L.S_BRAKE_I), since="0.5.3"),
    Endpoint("serial_number", Get("_serial"), int),
    Endpoint("system_stats.uptime", Get("_uptime_ms"), int),   # main.cpp:263, ms since boot
    Endpoint("fw_version_major", Const(0), int),
    Endpoint("fw_version_minor", Const(5), int),
    Endpoint("fw_version_revision", Attr("fw_revision"), int),
    Endpoint("hw_version_major", Const(3), int),
    Endpoint("hw_version_minor", Const(6), int),
    Endpoint("config.brake_resistance", Board("brake_resistance"), setter="_set_brake_resistance"),
    Endpoint("config.enable_brake_resistor", Board("enable_brake_resistor"), bool,
             setter="_set_enable_brake_resistor", since="0.5.2"),                # odrive_main.h:82
    Endpoint("config.max_regen_current", C(L.C_MAX_REGEN)),
    Endpoint("config.dc_max_positive_current", C(L.C_DC_MAX_POS)),
    Endpoint("config.dc_max_negative_current", C(L.C_DC_MAX_NEG)),
    # main.cpp:300-305: checked every current measurement (kernel._board_checks)
    Endpoint("config.dc_bus_undervoltage_trip_level", C(L.C_UV_TRIP)),
    Endpoint("config.dc_bus_overvoltage_trip_level", C(L.C_OV_TRIP)),
    Endpoint("save_configuration", Call("_save_configuration")),             # main.cpp:159-184
    Endpoint("reboot", Call("_reboot_call")),                                # main.cpp:194
    Endpoint("clear_errors", Call("_clear_errors"), since="0.5.2"),          # main.cpp:236-249
    # the controller's and the motor's control settings, each acting in the kernel as the
    # firmware's does (controller.cpp:143-450, motor.cpp:365-394,631-644; tests/device/
    # test_firmware_control.py), or refused at the write where the leg cannot do it
    Endpoint("axis*.controller.torque_setpoint", S(L.S_TQ_SP)),
    Endpoint("axis*.controller.autotuning_phase", S(L.S_TUNE_PHASE, writable=True), since="0.5.3"),
    Endpoint("axis*.controller.config.enable_vel_limit", C(L.C_EN_VEL_LIMIT), bool),
    Endpoint("axis*.controller.config.enable_current_mode_vel_limit", C(L.C_EN_TQ_VEL_LIMIT), bool,
             until="0.5.2"),
    Endpoint("axis*.controller.config.enable_torque_mode_vel_limit", C(L.C_EN_TQ_VEL_LIMIT), bool,
             since="0.5.3"),
    Endpoint("axis*.controller.config.enable_overspeed_error", C(L.C_EN_OVERSPEED), bool),
    Endpoint("axis*.controller.config.enable_gain_scheduling", C(L.C_EN_GAIN_SCHED), bool),
    Endpoint("axis*.controller.config.gain_scheduling_width", C(L.C_GAIN_SCHED_WIDTH)),
    Endpoint("axis*.controller.config.vel_ramp_rate", C(L.C_VEL_RAMP_RATE)),
    Endpoint("axis*.controller.config.torque_ramp_rate", C(L.C_TORQUE_RAMP_RATE)),
    Endpoint("axis*.controller.config.inertia", C(L.C_INERTIA)),
    Endpoint("axis*.controller.config.circular_setpoints", C(L.C_CIRCULAR), bool),
    Endpoint("axis*.controller.config.circular_setpoint_range", C(L.C_CIRC_RANGE),
             setter="_set_circular_setpoint_range"),
    Endpoint("axis*.controller.config.steps_per_circular_range", Key("steps_per_circular_range"), int,
             setter="_set_steps_per_circular_range", since="0.5.2"),
    Endpoint("axis*.controller.config.axis_to_mirror", C(L.C_MIRROR_AXIS), int, setter="_set_axis_to_mirror"),
    Endpoint("axis*.controller.config.mirror_ratio", C(L.C_MIRROR_RATIO)),
    Endpoint("axis*.controller.config.torque_mirror_ratio", C(L.C_TORQUE_MIRROR_RATIO), since="0.5.2"),
    Endpoint("axis*.controller.config.load_encoder_axis", Get("_load_encoder_axis"), int,
             setter="_set_load_encoder_axis"),
    Endpoint("axis*.controller.autotuning.frequency", C(L.C_TUNE_FREQ), since="0.5.2"),
    Endpoint("axis*.controller.autotuning.pos_amplitude", C(L.C_TUNE_POS_AMP), since="0.5.2"),
    Endpoint("axis*.controller.autotuning.vel_amplitude", C(L.C_TUNE_VEL_AMP), since="0.5.2"),
    Endpoint("axis*.controller.autotuning.torque_amplitude", C(L.C_TUNE_TQ_AMP), since="0.5.2"),
    Endpoint("axis*.controller.move_incremental", Call("_move_incremental")),            # controller.cpp:40-48
    Endpoint("axis*.controller.config.mechanical_power_bandwidth", C(L.C_MECH_BW), since="0.5.2"),
    Endpoint("axis*.controller.config.electrical_power_bandwidth", C(L.C_ELEC_BW), since="0.5.2"),
    Endpoint("axis*.controller.config.spinout_mechanical_power_threshold", C(L.C_SPIN_MECH), since="0.5.2"),
    Endpoint("axis*.controller.config.spinout_electrical_power_threshold", C(L.C_SPIN_ELEC), since="0.5.2"),
    Endpoint("axis*.controller.mechanical_power", S(L.S_MECH_P), since="0.5.2"),
    Endpoint("axis*.controller.electrical_power", S(L.S_ELEC_P), since="0.5.2"),
    Endpoint("axis*.motor.config.torque_lim", C(L.C_TORQUE_LIM)),
    Endpoint("axis*.motor.config.current_lim_margin", C(L.C_CURRENT_LIM_MARGIN)),
    Endpoint("axis*.motor.config.requested_current_range", Key("requested_current_range"),
             setter="_set_requested_current_range"),
    Endpoint("axis*.motor.config.bEMF_FF_enable", C(L.C_BEMF_FF), bool, since="0.5.2"),
    Endpoint("axis*.motor.config.R_wL_FF_enable", C(L.C_RWL_FF), bool, since="0.5.2"),
    Endpoint("axis*.motor.config.I_bus_hard_min", C(L.C_IBUS_MIN), since="0.5.2"),
    Endpoint("axis*.motor.config.I_bus_hard_max", C(L.C_IBUS_MAX), since="0.5.2"),
    Endpoint("axis*.motor.current_control.v_current_control_integral_q", S(L.S_V_INT, writable=True)),
    Endpoint("axis*.encoder.set_linear_count", Call("_set_linear_count")),                 # encoder.cpp:141-154
    Endpoint("axis*.encoder.pos_circular", Get("_pos_circular")),                          # encoder.cpp:806-809
)


class VirtualODrive(BoardMixin, AxisReadings, AxisThread):
    """The virtual ODrive. Build it with :func:`leglib.device.session.connect` (backend
    ``"virtual"``) or directly.

    Parameters
    ----------
    plant, config : the simulated leg and the ODrive's configuration (Listing 7.1; the
        device itself starts from the firmware's defaults where the two differ: brake
        resistor, cpr, pole pairs)
    seed : noise seed; the same seed gives the same measurements
    realtime : pace the virtual clock to the wall clock
    firmware : "0.5.6" (default) or "0.5.1"
    disconnect_after : raise :class:`DeviceLostError` from the N-th transaction on (tests)
    noise : encoder and current noise on (default) or off
    payload_off_for_calibration : a plant's foot payload is taken off while an axis
        calibrates and put back afterwards, as it must be on the bench: the encoder offset
        scan at ``calibration_current`` cannot carry a loaded leg and fails the CPR check.
        False keeps it on (the device's failure, for tests).
    """

    # the rows the object tree is built from at each boot; a subclass (or a test) that adds
    # one gets the endpoint in the tree and on the wire
    endpoints: tuple[Endpoint, ...] = ENDPOINTS

    def __init__(self, plant: PlantParams | str = "default", config: OdriveConfig | str = "thesis",
                 seed: int = 0, realtime: bool = False, firmware: str = "0.5.6",
                 disconnect_after: int | None = None, noise: bool = True,
                 payload_off_for_calibration: bool = True):
        if not isinstance(firmware, str) or firmware not in FIRMWARES:
            hint = (" (an ODrive v3.6 has no 0.6 firmware: 0.6.x is for ODrive Pro, S1 and Micro)"
                    if str(firmware).startswith("0.6") else "")
            raise ValueError(f"firmware must be one of {FIRMWARES}, got {firmware!r}{hint}")
        self.boot_count = 0
        self.twin = Twin(plant, config, batch=1, seed=seed, noise=noise)
        self.payload_off_for_calibration = bool(payload_off_for_calibration)
        self.firmware = firmware
        self.fw_revision = int(firmware.split(".")[2])
        self.realtime = bool(realtime)
        self.disconnect_after = disconnect_after
        self.transactions = 0
        self.lost = False
        self.saved_configuration = None
        self._rng = np.random.default_rng(seed)
        # where electrical angle 0 holds each rotor, as a fraction of a pole pitch (the
        # magnets' offset to the encoder at power-up is arbitrary: the lock makes the rotor
        # jump by up to half a pitch, 5.5 deg of joint)
        self._magnet_offset = self._rng.random(2)
        # where each AS5047D's index pulse is, in motor turns from the rest pose, and the
        # calibration's measurement noise: streams of their own (the rest of the device's
        # random numbers are drawn as before)
        self._index_position = np.random.default_rng([seed, 1]).random(2)
        self._cal_rng = np.random.default_rng([seed, 2])
        self.st = self.twin.rest_state()
        self._pending = 0.0
        self._t0_wall = _time.monotonic()
        self._handle_boot = 0
        self._boot_t0 = 0.0              # virtual time of this boot (the counters count from it)
        self._usb_packets = 0            # USB packets since this boot (system_stats.usb)
        self._test_counter = 0           # test_function's static counter
        self._brake_saturated = False    # brake_resistor_saturated (latched)
        self._config_bytes = 0           # user_config_loaded
        self._factory_defaults()
        self._factory = self._config_snapshot()
        self._factory_values = {a: dict(values) for a, values in self._settings.items()}
        self._boot()
        self._tree = self._build_tree()

    # -- configuration, boot and reboot ------------------------------------------------
    def _factory_defaults(self):
        """The firmware's defaults (a fresh board), then nothing saved."""
        C = self.st.C
        C[0, :, L.C_POS_GAIN] = 20.0
        C[0, :, L.C_VEL_GAIN] = 1.0 / 6.0
        C[0, :, L.C_VEL_INT_GAIN] = 1.0 / 3.0
        C[0, :, L.C_WD_ENABLE] = 0.0
        C[0, :, L.C_WD_TIMEOUT] = 0.0
        C[0, :, L.C_VEL_INT_LIMIT] = np.inf
        C[0, :, L.C_INPUT_MODE] = INPUT_MODE_PASSTHROUGH
        C[0, :, L.C_FILTER_BW] = 2.0
        C[0, :, L.C_INT_RESET_TORQUE] = 1.0
        v056 = self.firmware != "0.5.1"
        C[0, 0, L.C_BRAKE_ON] = 0.0 if v056 else 1.0        # odrive_main.h:82 (0.5.2+)
        C[0, 0, L.C_MAX_REGEN] = 0.0
        C[0, 0, L.C_DC_MAX_POS] = np.inf
        C[0, 0, L.C_DC_MAX_NEG] = -0.01                     # odrive_main.h:111
        C[0, 0, L.C_VBUS] = BATTERY_VOLTAGE                 # the thesis's 6S pack (board.py)
        C[0, 0, L.C_VBUS_R] = BATTERY_RESISTANCE
        C[0, 0, L.C_VBUS_CHECKS] = 1.0                      # main.cpp:300-305
        C[0, 0, L.C_REGEN_ERR_STYLE] = 0.0 if v056 else 1.0
        controller_defaults(C[0], cpr=8192)                 # controller.hpp:25-56, encoder.hpp:27
        C[0, :, L.C_PHASE_R] = 0.0                          # motor.hpp:22-23: not measured yet
        C[0, :, L.C_PHASE_L] = 0.0
        C[0, 0, L.C_FW_056] = 1.0 if v056 else 0.0
        self._board = {"enable_brake_resistor": not v056, "brake_resistance": 2.0}
        self._axis = []
        for a in range(2):
            self._axis.append({
                "steps_per_circular_range": 1024, "requested_current_range": 60.0,   # controller.hpp:38, motor.hpp:32
                "cpr": 8192, "pole_pairs": 7, "motor_type": 0,
                "motor_pre_calibrated": False, "encoder_pre_calibrated": False, "use_index": False,
                "direction": 0, "trap_vel_limit": 2.0, "trap_accel_limit": 0.5, "trap_decel_limit": 0.5,
                "startup_motor_calibration": False, "startup_encoder_offset_calibration": False,
                "startup_closed_loop_control": False, "phase_resistance": 0.0, "phase_inductance": 0.0,
                "calibration_current": 10.0, "calib_range": CALIB_RANGE, "calib_scan_distance": CALIB_SCAN_DISTANCE,
                "calib_scan_omega": CALIB_SCAN_OMEGA, "torque_constant": 0.04, "offset_measured": None,
            })
        # every configuration endpoint at the firmware's default for the board presented
        # (tables/defaults_fw-v*.json), the settings of the catalog's rows among them
        self._apply_table_defaults()
        self._settings = self._factory_settings(self._rows())

    def _config_snapshot(self) -> dict:
        C = self.st.C[0].copy()
        C[:, list(_C_VOLATILE)] = 0.0          # inputs and state are not configuration
        return {"C": C, "axes": [{k: ax[k] for k in _AXIS_CONFIG_KEYS} for ax in self._axis],
                "board": dict(self._board),
                "settings": {a: {k: v for k, v in values.items() if _is_config(k)}
                             for a, values in self._settings.items()}}

    def _rows(self) -> tuple:
        """The rows of this device's tree: its own (:attr:`endpoints`) and, for every other
        endpoint of the firmware's table, the catalog's (:mod:`.catalog`)."""
        return tuple(self.endpoints) + catalog.fill(self.endpoints, self.firmware)

    def _apply_table_defaults(self):
        """Set every writable configuration row to the firmware's default (its store
        directly: a fresh board, no side effects)."""
        from .wire import firmware_defaults  # load time: the tables live with the wire (which imports this module)
        defaults = firmware_defaults(self.firmware)
        types = None
        for row in self.endpoints:
            if not row.active(self.firmware) or row.function or ".config." not in f".{row.path}.":
                continue
            hit = defaults.get(row.path)
            if hit is None or not isinstance(row.store, (C, Key, Board)):
                continue
            for a, where in row.concrete():
                _, set_ = row.store.bind(self, a, row.kind, where)
                if set_ is not None:
                    value = hit["axes"][a] if ("axes" in hit and a is not None) else hit["value"]
                    if row.kind is int:
                        # C's conversion to the member's type (uint8 axis_to_mirror = -1 is 255)
                        types = types if types is not None else catalog.table_types(self.firmware)
                        value = c_value(types[row.path], value)
                    set_(row.kind(value))

    def _boot(self):
        """Power-up or reset: volatile state from scratch, the saved configuration loaded."""
        saved = self.saved_configuration if self.saved_configuration is not None else self._factory
        self.st.C[0] = saved["C"]
        for ax, cfg in zip(self._axis, saved["axes"]):
            ax.update(cfg)
        self._board.update(saved["board"])
        # the settings: the firmware's defaults, the saved configuration over them
        for a, values in self._factory_values.items():
            self._settings[a].update(values)
            self._settings[a].update(saved.get("settings", {}).get(a, {}))
        self._config_bytes = 0 if self.saved_configuration is None else self._saved_size()
        self._boot_t0 = self.time
        self._usb_packets = 0
        self._test_counter = 0
        self._brake_saturated = False
        st = self.st
        st.AI[0, :, :] = 0
        st.AI[0, :, L.I_TRAJ_DONE] = 1
        st.AS[0, :, L.S_INTEGRATOR] = 0.0
        st.AS[0, :, L.S_IQ] = 0.0
        st.AS[0, :, L.S_IQ_MEAS] = 0.0
        # the controller's state from scratch (controller.hpp:103-130; its estimate inputs
        # unconnected until the first closed loop: AI zeroed above)
        for slot in (L.S_POS_SP, L.S_VEL_SP, L.S_TQ_SP, L.S_TQ_OUT, L.S_TUNE_PHASE, L.S_POS_CIRC, L.S_MECH_P,
                     L.S_ELEC_P, L.S_FOC_POWER, L.S_V_INT, L.S_V_PREV, L.S_IQ_SP):
            st.AS[0, :, slot] = 0.0
        st.ABORT[...] = 0
        st.C[0, :, L.C_INPUT_POS] = 0.0
        st.C[0, :, L.C_INPUT_VEL] = 0.0
        st.C[0, :, L.C_INPUT_TORQUE] = 0.0
        st.C[0, :, L.C_ABORT_ERROR] = 0.0
        st.C[0, :, L.C_CAL_VEL] = 0.0
        # incremental encoder: the count restarts at 0 wherever the rotor is
        self._rezero_counts()
        # the brake resistor is armed at start-up when enabled (low_level.cpp:181-183)
        self._brake_armed = bool(self._board["enable_brake_resistor"])
        self._sync_brake()
        for a, ax in enumerate(self._axis):
            self._set_torque_constant(a, ax["torque_constant"])
            # the current controller's gains from the configured R and L (motor.cpp:297-302)
            self._set_phase_resistance(a, ax["phase_resistance"])
            self._set_phase_inductance(a, ax["phase_inductance"])
        for a, ax in enumerate(self._axis):
            ax.update({"motor_calibrated": bool(ax["motor_pre_calibrated"]),   # motor.cpp:306
                       # encoder.cpp:19-30: an incremental encoder is ready only after its
                       # offset calibration, or (pre-calibrated) once its index is found
                       "encoder_ready": False, "ready_by_index": False, "index_found": False,
                       "index_armed": False, "encoder_error": 0, "calib_scan_response": 0.0,
                       "lockin_state": 0, "last_error_time": {}, "errors_seen": {}})
            # axis.cpp:77-81: apply_config feeds the watchdog at boot
            self._feed(a)
        # the axis threads take up STARTUP_SEQUENCE (axis.hpp:202) once the board has booted
        self._start_axis_threads(self.time + (THREAD_START_AFTER_RESET if self.boot_count else 0.0))
        self._check_brake_resistance()

    def _rezero_counts(self):
        st = self.st
        for a in range(2):
            j = self.twin.axes.joint_of_axis(a)
            ax_map = self.twin.axes
            turns = float(self.twin.encoder_turns(st, j)[0])
            raw = math.floor(turns * ax_map.cpr + 0.5)
            st.C[0, a, L.C_COUNT_OFFSET] = -raw
            st.AI[0, a, L.I_COUNTS] = 0
            st.AS[0, a, L.S_COUNT_F] = 0.0
            st.AS[0, a, L.S_POS_EST] = 0.0
            st.AS[0, a, L.S_VEL_EST] = 0.0

    def reboot(self) -> None:
        """Reset the board (what ``save_configuration`` and ``reboot()`` do on the device):
        the motors are disarmed, volatile state is lost (calibration unless pre-calibrated,
        encoder counts, errors, states, watchdog timers), the saved configuration is loaded,
        and handles made before raise :class:`DeviceLostError`. The device answers again
        after :data:`BOOT_TIME` s of virtual time; :meth:`reconnect` waits for that."""
        self.st.AI[0, :, L.I_MODE] = L.MODE_IDLE
        self.boot_count += 1
        self._boot()
        self._booted_at = self.time
        self._tree = self._build_tree()
        for hook in list(self.__dict__.get("_reset_hooks", ())):    # the wire: the USB device re-enumerates
            hook(self)

    def handle(self):
        """The object tree of the current boot (what a new USB connection gives)."""
        self._check_link()
        self._handle_boot = self.boot_count
        return self._tree

    def reconnect(self, serial_number: int | None = None) -> "VirtualODrive":
        """Wait until the board answers after a reboot and connect again (by serial number,
        as ``odrive.find_any(serial_number=...)``); returns the device."""
        if serial_number is not None and int(serial_number) != self._serial():
            raise DeviceLostError(f"no ODrive with serial number {int(serial_number):012X}")
        booted = getattr(self, "_booted_at", None)
        if booted is not None and self.time < booted + BOOT_TIME:
            self.sleep(booted + BOOT_TIME - self.time + 2 * self.twin.dt)
        self._check_link()
        self._handle_boot = self.boot_count
        return self

    def _serial(self) -> int:
        return 0x3A7F1E2D4B00 + self.twin.seed

    # -- clock and transactions --------------------------------------------------------
    @property
    def time(self) -> float:
        """Virtual time since power-up [s]."""
        return float(self.st.X[0, 4])

    def _advance(self, seconds: float, progress: bool = False) -> None:
        # whole ticks only; the remainder is carried, so many short waits add up exactly.
        # With ``progress`` a positive wait always moves at least one tick (borrowing it),
        # so a host loop waiting for a sample time cannot spin on a rounding residue.
        dt = self.twin.dt
        self._pending += max(seconds, 0.0)
        n = int(self._pending / dt + 1e-9)
        if progress and n == 0 and seconds > 0:
            n = 1
        self._pending -= n * dt
        # run up to each state-machine event, handle it, go on (the events at one instant
        # are handled once)
        self._process_events()
        while n > 0:
            te = self._next_event()
            k = n if te is None else max(1, min(n, int(math.ceil((te - self.time) / dt - 1e-9))))
            self.twin.run(self.st, ticks=k)
            n -= k
            self._process_events()

    def sleep(self, seconds: float) -> None:
        """Let ``seconds`` of (virtual) time pass; in real-time mode also wait."""
        if not math.isfinite(seconds):
            raise ValueError(f"sleep: seconds must be finite, got {seconds!r}")
        self._check_link()
        if self.realtime:   # the board ran on while the host was busy: catch up first, so the
            self._pace()    # sleep's seconds start now (a real host's sleep takes all of them)
        self._advance(seconds, progress=True)
        if self.realtime:
            self._pace()

    def set_realtime(self, on: bool) -> None:
        """Pace the virtual clock to the wall clock from now on (or stop pacing)."""
        self.realtime = bool(on)
        self._t0_wall = _time.monotonic() - self.time

    def _pace(self):
        """Real time: the virtual clock never runs ahead of the wall clock. A transaction
        that moved it ahead waits (the host's transaction takes that long), one left behind
        by the host's own work catches up (the board ran on meanwhile). So a request is
        taken up within one axis-thread period of wall time after its write returns, as on
        the board (axis.cpp:447-451): a script that sleeps 1 ms sees it taken."""
        ahead = self.time - (_time.monotonic() - self._t0_wall)
        if ahead > 0.0:
            _time.sleep(ahead)
        elif ahead < -self.twin.dt:
            # the remainder _advance carries is counted in: with it added, catching up ran
            # up to one tick past the wall clock
            self._advance(max(0.0, -ahead - self._pending))

    def _check_link(self):
        if self.lost:
            raise DeviceLostError("virtual ODrive: device lost (injected disconnect)")
        if self.disconnect_after is not None and self.transactions >= self.disconnect_after:
            self.lost = True
            raise DeviceLostError(f"virtual ODrive: device lost after {self.transactions} transactions "
                                  f"(injected disconnect)")

    def _transaction(self) -> None:
        self._check_link()
        booted = getattr(self, "_booted_at", None)
        if booted is not None and self.time < booted + BOOT_TIME:
            raise DeviceLostError("virtual ODrive: the board is rebooting and does not answer yet")
        self.transactions += 1
        self._usb_packets += 1
        p = self.twin.plant
        self._advance(transport.latency(p.usb_latency, p.usb_jitter, float(self._rng.random())))
        if self.realtime:
            self._pace()

    # -- firmware state machine (the axis thread: procedures.py) ----------------------
    def _process_events(self):
        now = self.time + 1e-12
        self._board_events()
        self._note_error_times()
        self._axis_events(now)
        if self.payload_off_for_calibration and self.twin.plant.payload_mass > 0:
            calibrating = any(ax["state"] in (AXIS_STATE_MOTOR_CALIBRATION, AXIS_STATE_ENCODER_OFFSET_CALIBRATION)
                              for ax in self._axis)
            if calibrating == self.twin.payload_mounted:
                self.twin.mount_payload(not calibrating)
        # motor.cpp:312-338: the IDLE loop sets the current sense up every iteration, with
        # the requested_current_range written meanwhile (axis.cpp:437-440)
        st = self.st
        for a, ax in enumerate(self._axis):
            if ax["state"] == AXIS_STATE_IDLE and st.AI[0, a, L.I_MODE] == L.MODE_IDLE:
                st.C[0, a, L.C_MAX_CURRENT] = max_measurable_current(ax["requested_current_range"])

    def _disarm(self, a):
        st = self.st
        st.AI[0, a, L.I_MODE] = L.MODE_IDLE
        st.AS[0, a, L.S_IQ] = 0.0
        st.C[0, a, L.C_CAL_VEL] = 0.0

    def _arm(self, a) -> bool:
        """motor.cpp:195-217: refused (motor error) while an enabled brake resistor is not
        armed; the axis error check of the next tick disarms an axis with an error."""
        if self._board["enable_brake_resistor"] and not self._brake_armed:
            self.st.AI[0, a, L.I_MOTOR_ERR] |= MOTOR_ERROR_BRAKE_RESISTOR_DISARMED
            return False
        if self.st.AI[0, a, L.I_AXIS_ERR]:
            return False
        return True

    def _enter_closed_loop(self, a):
        """axis.cpp:577-578, 257-332: the closed loop's entry (its checks: procedures.py)."""
        st = self.st
        self._feed(a)                                  # axis.cpp:577
        if not self._arm(a):
            return
        # the controller's inputs connected to this axis's encoder (axis.cpp:270-285; the
        # controller reads its own axis's encoder: load_encoder_axis)
        st.AI[0, a, L.I_CONNECTED] = 1
        # controller and current controller reset at arming (motor.cpp:202-206,
        # controller.cpp:12-18, foc.cpp:47-53)
        st.AS[0, a, [L.S_IQ, L.S_V_PREV, L.S_V_INT, L.S_FOC_POWER, L.S_MECH_P, L.S_ELEC_P]] = 0.0
        st.AS[0, a, L.S_VEL_SP] = 0.0
        st.AS[0, a, L.S_TQ_SP] = 0.0
        st.AS[0, a, L.S_INTEGRATOR] = 0.0
        st.AS[0, a, L.S_OSC:L.S_OSC + L.N_OSC] = 0.0
        if self.firmware == "0.5.1":
            # fw-v0.5.1 axis.cpp:319-338: setpoint and input from the estimate in every mode
            est = self._position_estimate(a)
            st.AS[0, a, L.S_POS_SP] = est
            st.C[0, a, L.C_INPUT_POS] = est
        else:
            self._control_mode_updated(a)                 # axis.cpp:290-291
        self._plan_trajectory(a)
        st.AI[0, a, L.I_MODE] = self._armed_mode(a)

    def _plan_trajectory(self, a):
        """controller.cpp:31-38 move_to_pos with trapTraj.cpp planTrapezoidal, from the
        current setpoints to input_pos."""
        ax, st = self._axis[a], self.st
        if int(st.C[0, a, L.C_INPUT_MODE]) != INPUT_MODE_TRAP_TRAJ:
            return
        Xf, Xi, Vi = float(st.C[0, a, L.C_INPUT_POS]), float(st.AS[0, a, L.S_POS_SP]), float(st.AS[0, a, L.S_VEL_SP])
        Vmax, Amax, Dmax = ax["trap_vel_limit"], ax["trap_accel_limit"], ax["trap_decel_limit"]
        dX = Xf - Xi
        stop_dist = Vi * Vi / (2.0 * Dmax)
        dXstop = math.copysign(stop_dist, Vi)
        s = -1.0 if math.copysign(1.0, dX - dXstop) < 0 else 1.0
        Ar, Dr, Vr = s * Amax, -s * Dmax, s * Vmax
        if s * Vi > s * Vr:
            Ar = -s * Amax
        Ta = (Vr - Vi) / Ar
        Td = -Vr / Dr
        dXmin = 0.5 * Ta * (Vr + Vi) + 0.5 * Td * Vr
        if s * dX < s * dXmin:
            Vr = s * math.sqrt(max((Dr * Vi * Vi + 2 * Ar * Dr * dX) / (Dr - Ar), 0.0))
            Ta = max(0.0, (Vr - Vi) / Ar)
            Td = max(0.0, -Vr / Dr)
            Tv = 0.0
        else:
            Tv = (dX - dXmin) / Vr
        C = st.C[0, a]
        C[L.C_TT_XI], C[L.C_TT_XF], C[L.C_TT_VI] = Xi, Xf, Vi
        C[L.C_TT_AR], C[L.C_TT_VR], C[L.C_TT_DR] = Ar, Vr, Dr
        C[L.C_TT_TA], C[L.C_TT_TV], C[L.C_TT_TD] = Ta, Tv, Td
        C[L.C_TT_YACC] = Xi + Vi * Ta + 0.5 * Ar * Ta * Ta
        st.AS[0, a, L.S_TT_T] = 0.0
        st.AI[0, a, L.I_TRAJ_DONE] = 0

    # -- property setters with firmware side effects ------------------------------------
    def _armed_mode(self, a: int) -> int:
        """The kernel's armed mode for the configured control mode (VOLTAGE_CONTROL runs as
        torque control: controller.cpp:374,388,408 compare with VELOCITY_CONTROL)."""
        return max(L.MODE_TORQUE, min(int(self.st.C[0, a, L.C_CONTROL_MODE]), L.MODE_POSITION))

    def _position_estimate(self, a: int) -> float:
        """What the controller's position input gives now (controller.cpp:117-119): the
        circular or the linear estimate once connected, 0 before (an unconnected input)."""
        st = self.st
        if not st.AI[0, a, L.I_CONNECTED]:
            return 0.0
        if st.C[0, a, L.C_CIRCULAR]:
            return self._pos_circular(a)
        return float(st.AS[0, a, L.S_POS_EST])

    def _control_mode_updated(self, a: int) -> None:
        """controller.cpp:115-128: in position control the setpoint and input_pos jump to
        the estimate."""
        if self.st.C[0, a, L.C_CONTROL_MODE] >= L.CONTROL_MODE_POSITION:
            est = self._position_estimate(a)
            self.st.AS[0, a, L.S_POS_SP] = est
            self.st.C[0, a, L.C_INPUT_POS] = est

    def _set_control_mode(self, a: int, value: int):
        if value not in CONTROL_MODES:
            # the firmware stores any uint8 (its controller treats >= 3 as position control,
            # controller.cpp:296); a value beyond the enum is refused here (stricter)
            raise UnmodeledError(f"odrv.axis{a}.controller.config.control_mode: {value} is not a ControlMode of "
                                 f"firmware {self.firmware} (0 voltage, 1 torque, 2 velocity, 3 position)")
        st = self.st
        st.C[0, a, L.C_CONTROL_MODE] = value
        if self.firmware != "0.5.1":
            # controller.hpp:62 set_control_mode -> control_mode_updated, in every state;
            # fw-v0.5.1 has no setter: input_pos keeps its value (a closed loop switched to
            # position control goes to the old input_pos)
            self._control_mode_updated(a)
        if st.AI[0, a, L.I_MODE] not in (L.MODE_IDLE, L.MODE_CALIB):
            st.AI[0, a, L.I_MODE] = self._armed_mode(a)

    def _set_input_mode(self, a: int, value: int):
        # the firmware stores any value of the uint8; one its controller does not know (MIX_
        # CHANNELS, TUNING on 0.5.1, anything above 8) fails every update with
        # INVALID_INPUT_MODE (controller.cpp:278-281), which the kernel does
        if not 0 <= value <= 255:
            raise ValueError(f"odrv.axis{a}.controller.config.input_mode: {value} does not fit its uint8")
        self.st.C[0, a, L.C_INPUT_MODE] = value

    def _controller_runs(self, a: int) -> bool:
        """Whether the controller updates now: every tick on 0.5.6 (main.cpp:438-446), in
        closed loop only on 0.5.1 (fw-v0.5.1 axis.cpp:344-355)."""
        return self.firmware != "0.5.1" or self.st.AI[0, a, L.I_MODE] not in (L.MODE_IDLE, L.MODE_CALIB)

    def _set_input_pos(self, a: int, value: float):
        self.st.C[0, a, L.C_INPUT_POS] = value
        if self._controller_runs(a):
            self._plan_trajectory(a)    # input_pos_updated: planned on the next tick (controller.cpp:245-249)

    def _move_incremental(self, a: int, displacement: float, from_input_pos: bool = True):
        """controller.cpp:40-48: input_pos moved by ``displacement`` [turn] from input_pos
        or, with ``from_input_pos`` False, from pos_setpoint; then as an input_pos write."""
        st = self.st
        base = float(st.C[0, a, L.C_INPUT_POS]) if from_input_pos else float(st.AS[0, a, L.S_POS_SP])
        self._set_input_pos(a, base + float(displacement))

    def _set_linear_count(self, a: int, count: int):
        """encoder.cpp:141-154: shadow_count, the PLL's position and the timer's count set to
        ``count``; the velocity, count_in_cpr and the circular position are kept."""
        st = self.st
        count = int(count)
        if not -2 ** 31 <= count < 2 ** 31:
            raise ValueError(f"odrv.axis{a}.encoder.set_linear_count: {count} does not fit its int32")
        shift = count - int(st.AI[0, a, L.I_COUNTS])
        pe_old = float(st.AS[0, a, L.S_POS_EST])
        pe_new = count / float(st.C[0, a, L.C_CPR])
        st.C[0, a, L.C_COUNT_OFFSET] += shift
        st.AI[0, a, L.I_COUNTS] = count
        st.AS[0, a, L.S_COUNT_F] += shift
        st.AS[0, a, L.S_POS_EST] = pe_new
        st.AS[0, a, L.S_POS_CIRC] -= pe_new - pe_old     # pos_circular does not jump

    def _set_cpr(self, a: int, value: int):
        """encoder.config.cpr: the PLL works in counts (encoder.cpp:774-801), so its
        estimate in turns rescales with the cpr it is divided by."""
        if value <= 0:
            # the firmware stores it; its estimate would be counts / 0 or of the wrong sign
            # (encoder.cpp:800) and count_in_cpr a mod by it (encoder.cpp:757): refused
            raise UnmodeledError(f"odrv.axis{a}.encoder.config.cpr = {value}: a cpr that is not positive divides the "
                                 f"encoder's estimate by 0 or turns it (encoder.cpp:757,800); not modelled")
        st, ax = self.st, self._axis[a]
        ratio = float(st.C[0, a, L.C_CPR]) / value
        pc = self._pos_circular(a)
        st.AS[0, a, L.S_POS_EST] *= ratio
        st.AS[0, a, L.S_VEL_EST] *= ratio
        st.AS[0, a, L.S_POS_CIRC] = pc - float(st.AS[0, a, L.S_POS_EST])
        st.C[0, a, L.C_CPR] = float(value)
        ax["cpr"] = value

    def _pos_circular(self, a: int) -> float:
        """encoder.pos_circular (encoder.cpp:806-809): the position wrapped into
        [0, circular_setpoint_range), kept by the kernel as an offset to pos_estimate."""
        st = self.st
        x = float(st.AS[0, a, L.S_POS_EST]) + float(st.AS[0, a, L.S_POS_CIRC])
        return float(fmodf_pos(x, float(st.C[0, a, L.C_CIRC_RANGE])))

    def _set_circular_setpoint_range(self, a: int, value: float):
        if not math.isfinite(value):
            # wrap_pm(x, inf) is x - 0 * inf, NaN (utils.hpp:123-130): every setpoint and
            # pos_circular would turn NaN on the board; refused here (stricter). Zero and
            # negative ranges the firmware wraps by as written: the kernel does too
            raise UnmodeledError(f"odrv.axis{a}.controller.config.circular_setpoint_range must be a finite number "
                                 f"of turns, got {value} (the firmware's wrap multiplies by it: utils.hpp:123-130)")
        st = self.st
        pc = self._pos_circular(a)    # pos_circular of the old range, then wrapped into the new one
        st.C[0, a, L.C_CIRC_RANGE] = value
        st.AS[0, a, L.S_POS_CIRC] = pc - float(st.AS[0, a, L.S_POS_EST])

    def _set_steps_per_circular_range(self, a: int, value: int):
        # controller.hpp:61: a value <= 0 is ignored; the steps only matter to step/dir input
        if value > 0:
            self._axis[a]["steps_per_circular_range"] = value

    def _set_axis_to_mirror(self, a: int, value: int):
        if not 0 <= value <= 255:
            raise ValueError(f"odrv.axis{a}.controller.config.axis_to_mirror: {value} does not fit its uint8")
        self.st.C[0, a, L.C_MIRROR_AXIS] = value

    def _load_encoder_axis(self, a: int) -> int:
        return a                       # load_configuration's default: the axis's own encoder

    def _set_load_encoder_axis(self, a: int, value: int):
        if value != a:
            raise UnmodeledError(f"odrv.axis{a}.controller.config.load_encoder_axis = {value}: the twin's "
                                 f"controller reads its own axis's encoder only (each motor of this leg has its "
                                 f"encoder on its shaft); another axis's encoder (axis.cpp:276-280) or the "
                                 f"sensorless estimator is not modelled")

    def _set_requested_current_range(self, a: int, value: float):
        # applied by the IDLE loop's motor.setup() (see _process_events)
        self._axis[a]["requested_current_range"] = float(value)

    def _feed(self, a):
        # axis.cpp:165-168: reload with watchdog_timeout * control-loop frequency
        timeout = min(max(float(self.st.C[0, a, L.C_WD_TIMEOUT]), 0.0), 1e6)
        self.st.AS[0, a, L.S_WD_TIMER] = float(int(timeout * self.twin.config.loop_frequency))

    def _clear_errors(self, a=None):
        """odrv.clear_errors (main.cpp:236-249) or axis.clear_errors (fw-v0.5.1 axis.hpp:108-116)."""
        st = self.st
        for i in ((0, 1) if a is None else (a,)):
            st.AI[0, i, L.I_AXIS_ERR] = 0
            st.AI[0, i, L.I_CTRL_ERR] = 0
            st.AI[0, i, L.I_MOTOR_ERR] = 0
            self._axis[i]["encoder_error"] = 0
        if a is None:
            st.AI[0, 0, L.I_SYS_ERR] = 0
            if self._board["enable_brake_resistor"]:
                self._brake_armed = True
                self._sync_brake()
            self._check_brake_resistance()
        elif self.firmware == "0.5.1":
            self._board_events_051()          # the next check sets BRAKE_RESISTOR_DISARMED again

    def _set_enable_brake_resistor(self, value: bool):
        # the flag only; the resistor is armed at boot or by clear_errors (main.cpp:246-248,
        # low_level.cpp:181-183)
        self._board["enable_brake_resistor"] = bool(value)
        if not value:
            self._brake_armed = False
            self._sync_brake()
        self._check_brake_resistance()

    def _save_configuration(self):
        if self.firmware == "0.5.1":
            # fw-v0.5.1 main.cpp:43-61: stores, neither refuses nor reboots
            self.saved_configuration = self._config_snapshot()
            return None
        # main.cpp:159-184
        if any(self.st.AI[0, a, L.I_MODE] != L.MODE_IDLE for a in range(2)):
            return False
        self.saved_configuration = self._config_snapshot()
        self.reboot()
        raise DeviceLostError("virtual ODrive: save_configuration rebooted the board; reconnect "
                              "(by serial number)")

    def _reboot_call(self):
        self.reboot()
        raise DeviceLostError("virtual ODrive: reboot() reset the board; reconnect (by serial number)")

    # -- the tree (built from ENDPOINTS) and what its rows name ------------------------
    def _build_tree(self) -> _Node:
        """The object tree of this boot from :attr:`endpoints` (see :mod:`.tree`); the
        endpoints by name in ``_leaves`` (what the wire serves)."""
        tree, self._leaves = build_tree(self, self._rows(), self.firmware)
        return tree

    def _set_motor_pre_calibrated(self, a: int, value: bool):
        # motor.hpp:53-56
        ax = self._axis[a]
        ax["motor_pre_calibrated"] = value
        ax["motor_calibrated"] = ax["motor_calibrated"] or value

    def _set_encoder_pre_calibrated(self, a: int, value: bool):
        # encoder.hpp set_pre_calibrated -> encoder.cpp:130-138 check_pre_calibrated: the flag
        # stays only on a ready encoder, and an incremental one only once its index is found
        ax = self._axis[a]
        ax["encoder_pre_calibrated"] = bool(value) and ax["encoder_ready"] and bool(ax.get("index_found"))

    def _set_use_index(self, a: int, value: bool):
        # encoder.hpp set_use_index: stored, the index interrupt (un)subscribed
        # (encoder.cpp:109-117); the index search finds the AS5047D's index pulse
        ax = self._axis[a]
        ax["use_index"] = bool(value)
        ax["index_armed"] = bool(value) and not ax.get("index_found") and not bool(
            self._settings[a].get("axis*.encoder.config.find_idx_on_lockin_only"))

    def _is_armed(self, a: int) -> bool:
        return bool(self.st.AI[0, a, L.I_MODE] != L.MODE_IDLE)

    def _count_in_cpr(self, a: int) -> int:
        # encoder.cpp:757: mod(count, cpr) (utils.hpp:154-158); a cpr of 0 the firmware
        # stores, its mod divides by: read as the count (a Cortex-M's division by 0 is 0)
        cpr = self._axis[a]["cpr"]
        count = int(self.st.AI[0, a, L.I_COUNTS])
        return count % cpr if cpr else count

    def _uptime_ms(self) -> int:
        """system_stats.uptime: the FreeRTOS tick count (1 ms) since this boot, uint32."""
        return int((self.time - getattr(self, "_booted_at", 0.0)) * 1000.0) & 0xFFFFFFFF

    # the tree's attributes are the device's (through the handle of the last connection)
    def __getattr__(self, name):
        if name.startswith("_") or name in ("twin", "st", "firmware", "realtime"):
            raise AttributeError(name)
        tree = self.__dict__.get("_tree")
        if tree is None:
            raise AttributeError(name)
        if self._handle_boot != self.boot_count:
            raise DeviceLostError(f"virtual ODrive: the board rebooted since this connection was made "
                                  f"(boot {self._handle_boot} -> {self.boot_count}); reconnect")
        return getattr(tree, name)

    def __setattr__(self, name, value):
        if name[0] == "_":               # the model's own state (the common case: fast)
            object.__setattr__(self, name, value)
            return
        tree = self.__dict__.get("_tree")
        if name in ("axis0", "axis1", "config", "vbus_voltage", "error") or (
                tree is not None and not name.startswith("_") and name in tree._props):
            if self._handle_boot != self.boot_count:
                raise DeviceLostError("virtual ODrive: the board rebooted since this connection was made; reconnect")
            setattr(self._tree, name, value)
        else:
            object.__setattr__(self, name, value)

    def __dir__(self):
        return dir(self._tree)

    # -- whole experiments through the kernel (inputs known in advance) ------------------
    def step_batch(self, gains, **kwargs) -> dict:
        """Run Listing 7.4's step for each gain triple (see
        :meth:`leglib.twin.host.Twin.step_batch`), each from the state the device is in now (the
        leg at rest, IDLE) with its configuration and encoder reference. Afterwards the
        device is IDLE with the leg back where it started (as if it had settled there) and
        virtual time advanced by the steps' duration plus a 2 s settling wait per step.
        The joint travel of the steps is added to the device's (a plant whose friction
        drifts with use wears on), though every step starts from the same state. Counts as
        one transaction (for disconnect injection); the watchdog is taken as fed, as the
        polling loop feeds it every sample.
        """
        if self._handle_boot != self.boot_count:
            raise DeviceLostError("virtual ODrive: the board rebooted since this connection was made; reconnect")
        self._transaction()
        for a in range(2):
            ax = self._axis[a]
            if not (ax["motor_calibrated"] and ax["encoder_ready"]):
                raise RuntimeError(f"axis{a} is not calibrated: run the calibration first")
            if self.st.AI[0, a, L.I_AXIS_ERR] or self.st.AI[0, 0, L.I_SYS_ERR]:
                raise RuntimeError(f"axis{a} has an error (0x{int(self.st.AI[0, a, L.I_AXIS_ERR]):x}): "
                                   f"clear it first")
            if ax["state"] != AXIS_STATE_IDLE or ax["pending"] is not None:
                raise RuntimeError(f"axis{a} is not IDLE: a whole step starts from rest")
        if self._vbus_trips_reachable():
            raise RuntimeError("the bus trip levels (config.dc_bus_under/overvoltage_trip_level) are within "
                               "reach of the battery's voltage under load: a whole step batch does not check "
                               "them; run the steps through the polling path")
        start = self.st.copy()
        start.C[0, :, L.C_WD_ENABLE] = 0.0
        start.C[0, 0, L.C_VBUS_CHECKS] = 0.0        # out of reach (checked above)
        start.AI[0, :, L.I_TRAJ_DONE] = 1
        start.ABORT[...] = 0
        out = self.twin.step_batch(gains, start=start, **kwargs)
        # the firmware's error flags of the last step stay on the device, as on the real one
        final = out["final"]
        wear = [L.X_TRAVEL1, L.X_TRAVEL2]
        self.st.X[0, wear] += np.sum(final.X[:, wear] - start.X[0, wear], axis=0)
        self.st.AI[0, :, L.I_AXIS_ERR] |= final.AI[-1, :, L.I_AXIS_ERR]
        self.st.AI[0, :, L.I_CTRL_ERR] |= final.AI[-1, :, L.I_CTRL_ERR]
        self.st.AI[0, :, L.I_MOTOR_ERR] |= final.AI[-1, :, L.I_MOTOR_ERR]
        self.st.AI[0, 0, L.I_SYS_ERR] |= final.AI[-1, 0, L.I_SYS_ERR]
        duration = kwargs.get("duration", 1.5)
        n = len(np.atleast_2d(gains))
        t_now = self.time + n * (duration + 2.0)
        self.st.X[0, 4] = t_now
        last = np.atleast_2d(gains)[-1]
        for a in range(2):
            self.st.AI[0, a, L.I_MODE] = L.MODE_IDLE
            self.st.AI[0, a, L.I_CONNECTED] = 1          # the steps' closed loops connected it
            self.st.C[0, a, L.C_CONTROL_MODE] = L.CONTROL_MODE_POSITION
            self.st.C[0, a, [L.C_POS_GAIN, L.C_VEL_GAIN, L.C_VEL_INT_GAIN]] = last
            self._feed(a)
        return out
