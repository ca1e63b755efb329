"""Every endpoint of the firmware's table that the hand-written rows do not cover, each
with what the virtual ODrive does with it and why.

The rows of :data:`leglib.device.virtual.firmware.ENDPOINTS` model what acts on the leg (the
state machine, the cascade, the calibration, the bus). The firmware's table has some 380
more endpoints per axis pair: I/O settings, estimators of other motor types, diagnostics,
counters. :func:`fill` gives each of them a row from the rules below, so the object tree is
the firmware's whole tree and nothing is silently held:

``store``
    a setting accepted and stored as the firmware stores it (any value of its type), read
    back, saved with the configuration when its path is a configuration path, erased to
    the firmware's default; it acts on nothing the model simulates, and the rule says why
    (nothing is wired to the pin, it belongs to a mode the leg does not run, ...).
``only``
    a setting that would change the motion in a way the model does not simulate: the
    firmware's default (the value the model honours) is accepted and stored, any other value
    raises :class:`UnmodeledError` at the write, naming the endpoint and why (stricter than
    the board, which would act on it).
``read``
    a reading computed by a method of the device (``VirtualODrive.<method>(a, *args)``).
``const``
    a reading that is constant on this bench (the rule says why).
``unknown``
    a reading the model cannot know (the MCU's task timings and stack high-water marks):
    it raises :class:`UnmodeledError` at the read with the reason.
``call`` / ``refuse``
    a function the device models, or one that raises :class:`UnmodeledError` at the call
    with the reason.

A hand row for an endpoint always wins (:func:`fill` skips what the rows cover), so
modelling an endpoint more closely is adding its row. An endpoint no rule matches falls to
the strict default (``only`` for a setting, a read that raises for a reading); the tests
list those, and there are none.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass
from typing import Any

from .tree import Call, Const, Endpoint, Get, Setting, UnmodeledError, model_paths

# the pins of the encoder connectors (board.h:59-64: GPIO 9/10 ENC0 A/B, 11 ENC0 Z, 12/13
# ENC1 A/B, 14 ENC1 Z): changing their mode disconnects the encoders
_ENCODER_PINS = "9|10|11|12|13|14"

_IO = ("I/O only: nothing is wired to the board's GPIO, UART, CAN or I2C connectors on this "
       "bench (the AS5047D boards use the encoder connectors)")
_CAN = "CAN: no bus is connected on this bench; the setting acts only on CAN messages"
_SENSORLESS = "used only in sensorless mode, which the model refuses (the leg runs on its encoders)"
_ACIM = "used only by an induction motor (motor_type ACIM); this leg's motors are HIGH_CURRENT"
_NOT_ABS = "used only by the hall, sin/cos and SPI encoder modes; the leg's AS5047D boards are wired through ABI (incremental)"
_NO_CPU = "no CPU is simulated: the firmware's task timings (TIM13 counts, task_timer.hpp) are not modelled"
_ENDSTOP = "used only by an enabled endstop; this leg has hard stops and no endstop switches"


@dataclass(frozen=True)
class Rule:
    """What the device does with the endpoints whose generic path matches ``pattern``."""

    pattern: str
    kind: str                    # store, only, read, const, unknown, call, refuse
    reason: str = ""
    method: str = ""             # read / call
    args: tuple = ()
    value: Any = None            # const
    versions: tuple = ()         # () all, else the firmware versions the rule is for

    def matches(self, generic: str, firmware: str) -> bool:
        return (not self.versions or firmware in self.versions) and re.fullmatch(self.pattern, generic) is not None


RULES: tuple[Rule, ...] = (
    # -- the axis ----------------------------------------------------------------------
    Rule(r"axis\*\.config\.can\..*", "store", _CAN),
    Rule(r"axis\*\.config\.can_(node_id|node_id_extended|heartbeat_rate_ms)", "store", _CAN),
    Rule(r"axis\*\.config\.(step|dir)_gpio_pin", "store",
         "the step/dir pins act only with the step/dir interface, which the model refuses (enable_step_dir)"),
    Rule(r"axis\*\.config\.turns_per_step", "store",
         "acts only with the step/dir interface, which the model refuses (enable_step_dir)"),
    Rule(r"axis\*\.config\.(enable_step_dir|step_dir_always_on)", "only",
         "no step/dir signal source on this bench: an enabled step/dir interface drives "
         "input_pos from its step counter (axis.cpp:117-122); not modelled"),
    Rule(r"axis\*\.config\.(enable_sensorless_mode|startup_sensorless_control)", "only",
         "sensorless control (a lock-in spin, then the flux observer) is not modelled: the leg "
         "runs on its encoders and cannot spin freely to lock in (axis.cpp:257-265)"),
    Rule(r"axis\*\.config\.sensorless_ramp\..*", "store", _SENSORLESS),
    Rule(r"axis\*\.config\.(calibration_lockin|general_lockin)\..*", "store",
         "read by the lock-in spins (direction find, index search, LOCKIN_SPIN), which the model runs"),
    Rule(r"axis\*\.config\.(startup_encoder_index_search|startup_homing)", "store",
         "read by the startup sequence (axis.cpp:458-471), which the model runs"),
    Rule(r"axis\*\.is_homed", "store", "set by a successful homing; the model's homing fails (no endstop)"),
    Rule(r"axis\*\.step_dir_active", "const", "the step/dir interface is never active (enable_step_dir is refused)", value=False),
    Rule(r"axis\*\.steps", "const", "no step pulses arrive (no step/dir signal source)", value=0),
    Rule(r"axis\*\.last_drv_fault", "const", "the DRV8301 gate drivers report no fault on this bench", value=0),
    Rule(r"axis\*\.motor\.gate_driver\.drv_fault", "const", "the DRV8301 gate drivers report no fault on this bench", value=0),
    Rule(r"axis\*\.loop_counter", "read", method="_r_ticks"),
    Rule(r"axis\*\.lockin_state", "read", method="_r_lockin_state"),
    Rule(r"axis\*\.task_times\..*", "unknown", _NO_CPU),
    Rule(r"axis\*\.motor\.timing_log\..*", "unknown", _NO_CPU),
    # -- endstops and the mechanical brake
    Rule(r"axis\*\.(min|max)_endstop\.config\.enabled", "only",
         "this leg has hard stops and no endstop switches: an enabled endstop on an unconnected "
         "pin would let homing drive the leg into its stop (not modelled)"),
    Rule(r"axis\*\.(min|max)_endstop\.config\..*", "store", _ENDSTOP),
    Rule(r"axis\*\.(min|max)_endstop\.endstop_state", "const", "no endstop switch (the endstops are disabled)", value=False),
    Rule(r"axis\*\.mechanical_brake\.config\..*", "store", "no mechanical brake is wired on this bench"),
    Rule(r"axis\*\.mechanical_brake\.(engage|release)", "call", method="_nothing_wired"),
    # -- the controller
    Rule(r"axis\*\.controller\.config\.anticogging\.(calib_anticogging|cogging_ratio|index)", "read",
         method="_r_setting"),
    Rule(r"axis\*\.controller\.config\.anticogging\..*", "store",
         "the cogging map stays all zero (the anticogging calibration is refused), so the "
         "compensation adds nothing"),
    Rule(r"axis\*\.controller\.anticogging_valid", "store",
         "the cogging map stays all zero (the anticogging calibration is refused)"),
    Rule(r"axis\*\.controller\.get_anticogging_value", "call", method="_anticogging_value"),
    Rule(r"axis\*\.controller\.remove_anticogging_bias", "call", method="_remove_anticogging_bias"),
    Rule(r"axis\*\.controller\.start_anticogging_calibration", "refuse",
         "the anticogging calibration steps the rotor through whole turns in position control "
         "(controller.cpp:63-84): the leg cannot turn freely (hard stops)"),
    Rule(r"axis\*\.controller\.config\.homing_speed", "store", "read only by homing, which fails without an endstop"),
    Rule(r"axis\*\.controller\.last_error_time", "read", method="_r_last_error_time", args=("controller",)),
    # -- the encoder
    Rule(r"axis\*\.encoder\.config\.mode", "only",
         "the leg's AS5047D boards are wired through ABI: the incremental mode (0); other modes read other pins"),
    Rule(r"axis\*\.encoder\.config\.(abs_spi_cs_gpio_pin|sincos_gpio_pin_sin|sincos_gpio_pin_cos|hall_polarity|"
         r"hall_polarity_calibrated|ignore_illegal_hall_state)", "store", _NOT_ABS),
    Rule(r"axis\*\.encoder\.config\.enable_phase_interpolation", "only",
         "the twin commutates ideally; commutation on raw counts is not modelled"),
    Rule(r"axis\*\.encoder\.config\.(phase_offset|phase_offset_float|offset|offset_float)", "store",
         "written by the offset calibration; a pre-calibrated encoder uses it after its index is found"),
    Rule(r"axis\*\.encoder\.config\.(index_offset|use_index_offset|find_idx_on_lockin_only|"
         r"idx_search_unidirectional|zero_count_on_find_idx)", "store", "read by the index search, which the model runs"),
    Rule(r"axis\*\.encoder\.(pos_estimate_counts|vel_estimate_counts|pos_cpr_counts|pos_cpr|"
         r"delta_pos_cpr_counts|interpolation|phase|index_found|calib_scan_response)", "read",
         method="_r_encoder"),
    Rule(r"axis\*\.encoder\.(pos_abs|spi_error_rate)", "store", _NOT_ABS),
    Rule(r"axis\*\.encoder\.hall_state", "const", "decoded only in hall mode (encoder.cpp:652-655): stays 0", value=0),
    # -- the sensorless and induction-motor estimators
    Rule(r"axis\*\.sensorless_estimator\.config\..*", "store", _SENSORLESS),
    Rule(r"axis\*\.sensorless_estimator\.error", "store", _SENSORLESS),
    Rule(r"axis\*\.sensorless_estimator\.(phase|phase_vel|pll_pos|vel_estimate)", "read", method="_r_sensorless"),
    Rule(r"axis\*\.acim_estimator\.config\..*", "store", _ACIM),
    Rule(r"axis\*\.acim_estimator\..*", "const", _ACIM + ": the estimator is inactive and reads 0", value=0.0),
    Rule(r"axis\*\.motor\.config\.acim_.*", "store", _ACIM),
    Rule(r"axis\*\.motor\.current_control\.(acim_rotor_flux|async_phase_offset)", "store", _ACIM),
    Rule(r"axis\*\.motor\.current_control\.async_phase_vel", "const", _ACIM, value=0.0),
    # -- the motor
    Rule(r"axis\*\.motor\.config\.I_leak_max", "store",
         "declared (motor.hpp:48) but read by no code of the firmware"),
    Rule(r"axis\*\.motor\.config\.dc_calib_tau", "store",
         "the current sensors' offset calibration filter: the twin's sensors have no offset to calibrate"),
    Rule(r"axis\*\.motor\.config\.(inverter_temp_limit_lower|inverter_temp_limit_upper)", "store",
         "the FET temperature stays at the bench's ambient: no derating is reached"),
    Rule(r"axis\*\.motor\.config\.resistance_calib_max_voltage", "store",
         "read by the motor calibration, which the model runs"),
    Rule(r"axis\*\.motor\.(DC_calib_phA|DC_calib_phB|DC_calib_phC)", "store",
         "the current sensors' measured offsets: the twin's sensors have none (0)"),
    Rule(r"axis\*\.motor\.phase_current_rev_gain", "only",
         "the current-sense amplifier gain set at setup (motor.cpp:316-332); another gain would "
         "rescale the measured currents (not modelled)"),
    Rule(r"axis\*\.motor\.current_control\.I_measured_report_filter_k", "only",
         "the reported currents are not filtered (the default 1.0)"),
    Rule(r"axis\*\.motor\.current_control\.v_current_control_integral_d", "only",
         "the current controller's d axis is not modelled (Id held at 0: its integrator reads the steady-state "
         "voltage)",
         method="_r_motor"),
    Rule(r"axis\*\.motor\.current_control\.(Ibus|I_measured_report_filter_k)", "read", method="_r_current_control"),
    Rule(r"axis\*\.motor\.(current_control\.\w+|current_meas_ph[ABC]|I_bus|effective_current_lim|"
         r"max_allowed_current|max_dc_calib|armed_state)", "read", method="_r_motor"),
    Rule(r"axis\*\.motor\.(n_evt_current_measurement|n_evt_pwm_update)", "read", method="_r_ticks"),
    Rule(r"axis\*\.motor\.last_error_time", "read", method="_r_last_error_time", args=("motor",)),
    # -- thermistors: the FETs' at the bench's ambient, the motors' not wired
    Rule(r"axis\*\.(motor\.)?motor_thermistor\.config\.enabled", "only",
         "no thermistor is wired to the motors: enabled, the open input would read a temperature "
         "that derates or trips the motor (thermistor.cpp:30-47); off by default (thermistor.hpp:63)"),
    Rule(r"axis\*\.(motor\.)?(motor|fet)_thermistor\.config\..*", "store",
         "the FET temperature stays at the bench's ambient and the motor thermistor is off: no derating"),
    Rule(r"axis\*\.(motor\.)?(motor|fet)_thermistor\.temperature", "read", method="_r_temperature"),
    Rule(r"axis\*\.(motor\.)?(motor|fet)_thermistor\.error", "store", "no thermistor error occurs on this bench"),
    # -- the board
    Rule(r"config\.gpio(" + _ENCODER_PINS + r")_mode", "only",
         "these pins carry the encoders (board.h:59-64); another mode disconnects them (not modelled)"),
    Rule(r"config\.gpio\d+_mode", "store", _IO),
    Rule(r"config\.gpio\d+_analog_mapping\.endpoint", "only",
         "an analog mapping writes the floating pin's voltage into the endpoint every loop "
         "(not modelled: nothing is wired to the pin)"),
    Rule(r"config\.gpio\d+_(pwm|analog)_mapping\..*", "store",
         "no PWM signal arrives on the pins (nothing is wired): a mapping never writes"),
    Rule(r"config\.(enable_uart\w*|uart\w*|usb_cdc_protocol|enable_can_a|enable_i2c_a|enable_i2c_instead_of_can|"
         r"enable_ascii_protocol_on_usb|error_gpio_pin)", "store", _IO),
    Rule(r"config\.(enable_dc_bus_overvoltage_ramp)", "only",
         "the brake resistor's over-voltage duty ramp (low_level.cpp:340-344) is not modelled"),
    Rule(r"config\.(dc_bus_overvoltage_ramp_start|dc_bus_overvoltage_ramp_end)", "store",
         "act only with the over-voltage ramp, which the model refuses"),
    Rule(r"can\.config\..*|can\.error", "store", _CAN),
    Rule(r"can\.set_baud_rate", "call", method="_store_can_baud_rate"),
    Rule(r"ibus_report_filter_k", "only", "the reported ibus is not filtered (the default 1.0)"),
    Rule(r"brake_resistor_saturated", "read", method="_r_brake_saturated"),
    Rule(r"(n_evt_control_loop|n_evt_sampling)", "read", method="_r_ticks"),
    Rule(r"task_timers_armed", "read", method="_r_task_timers_armed"),
    Rule(r"task_times\..*", "unknown", _NO_CPU),
    Rule(r"system_stats\.(i2c\..*)", "const", "I2C is disabled (config.enable_i2c_a): nothing is counted", value=0),
    Rule(r"system_stats\.usb\.(rx_cnt|tx_cnt)", "read", method="_r_usb_count"),
    Rule(r"system_stats\.usb\.tx_overrun_cnt", "const", "the model's USB never overruns", value=0),
    Rule(r"system_stats\..*", "read", method="_r_system_stats"),
    Rule(r"hw_version_variant", "read", method="_r_board", args=("variant",)),
    Rule(r"otp_valid", "const", "a genuine v3.6 carries its board version in OTP (board.cpp:264-270)", value=True),
    Rule(r"user_config_loaded", "read", method="_r_user_config_loaded"),
    Rule(r"misconfigured", "read", method="_r_misconfigured"),
    Rule(r"test_property", "store", "a test register, no function (odrive_main.h:239)"),
    Rule(r"oscilloscope\.size", "const", "OSCILLOSCOPE_SIZE (oscilloscope.hpp:7)", value=4096),
    Rule(r"(oscilloscope\.get_val|get_oscilloscope_val)", "call", method="_oscilloscope_val"),
    Rule(r"test_function", "call", method="_test_function"),
    Rule(r"get_adc_voltage", "call", method="_get_adc_voltage"),
    Rule(r"get_interrupt_status", "call", method="_get_interrupt_status"),
    Rule(r"get_dma_status", "call", method="_get_dma_status"),
    Rule(r"get_gpio_states", "call", method="_get_gpio_states"),
    Rule(r"get_drv_fault", "call", method="_get_drv_fault"),
    Rule(r"erase_configuration", "call", method="_erase_configuration"),
    Rule(r"enter_dfu_mode", "refuse",
         "the virtual board has no DFU bootloader: it cannot take firmware (main.cpp:197-213)"),
)


# the firmware's version numbers: answered by the wire from the table it serves
_IDENTITY = frozenset({"fw_version_major", "fw_version_minor", "fw_version_revision", "fw_version_unreleased"})


def _kind(codec: str):
    return bool if codec == "bool" else float if codec == "float" else int


def _generic(path: str) -> str:
    head, _, rest = path.partition(".")
    return "axis*." + rest if head.startswith("axis") and head[4:].isdigit() else path


def rule_for(generic: str, firmware: str) -> Rule | None:
    """The first rule matching ``generic`` on ``firmware`` (None: the strict default)."""
    return next((r for r in RULES if r.matches(generic, firmware)), None)


def _table_entries(firmware: str) -> dict[str, dict]:
    """{generic path: table entry} of the firmware's table (axis 0's entry for axis paths)."""
    from .wire import endpoint_table, flatten  # load time: the tables live with the wire
    out: dict[str, dict] = {}
    for path, entry in flatten(endpoint_table(firmware)).items():
        out.setdefault(_generic(path), entry)
    return out


@functools.lru_cache(maxsize=None)
def table_types(firmware: str) -> dict[str, str]:
    """{generic path: the table's type} of the firmware's endpoints."""
    return {generic: entry["type"] for generic, entry in _table_entries(firmware).items()}


@functools.lru_cache(maxsize=None)
def _filled(rows: tuple, firmware: str) -> tuple[Endpoint, ...]:
    covered = {_generic(path) for path in model_paths(rows, firmware)}
    out = []
    for generic, entry in sorted(_table_entries(firmware).items()):
        if generic in covered or generic in _IDENTITY:
            continue
        out.append(row_for(generic, entry, firmware))
    return tuple(out)


def row_for(generic: str, entry: dict, firmware: str) -> Endpoint:
    """The row of endpoint ``generic`` (its table ``entry``) on ``firmware`` by its rule."""
    pin = {"since": firmware} if firmware != "0.5.1" else {"until": "0.5.1"}
    rule = rule_for(generic, firmware)
    function = entry["type"] == "function"
    if function:
        if rule is None or rule.kind == "refuse":
            reason = rule.reason if rule is not None else "not modelled"
            return Endpoint(generic, Call("_refuse", (generic.replace("axis*.", ""), reason)), **pin)
        return Endpoint(generic, Call(rule.method, rule.args), **pin)
    kind = _kind(entry["type"])
    writable = "w" in entry.get("access", "")
    if rule is None:
        if writable:
            return Endpoint(generic, Setting(generic, only=True, reason="not modelled", codec=entry["type"]), kind, **pin)
        return Endpoint(generic, Get("_r_unmodelled", (generic, "not modelled")), kind, **pin)
    if rule.kind in ("store", "only"):
        if not writable:
            return Endpoint(generic, Get("_r_setting", (generic,)), kind, **pin)
        reader = (rule.method, rule.args or (generic,)) if rule.method else None
        return Endpoint(generic, Setting(generic, only=rule.kind == "only", reason=rule.reason, reader=reader,
                                         codec=entry["type"]), kind, **pin)
    if rule.kind == "const":
        return Endpoint(generic, Const(rule.value), kind, **pin)
    if rule.kind == "unknown":
        # a reading the model cannot know: raises at the read; a write is stored (the
        # firmware takes it: max_length is reset by writing 0)
        if writable:
            return Endpoint(generic, Setting(generic, reason=rule.reason, codec=entry["type"],
                                             reader=("_r_unmodelled", (generic, rule.reason))), kind, **pin)
        return Endpoint(generic, Get("_r_unmodelled", (generic, rule.reason)), kind, **pin)
    if rule.kind == "read":
        args = rule.args or (generic,)
        if writable:
            # a writable reading (a counter the host may reset): the firmware stores the
            # write; the model holds it as a setting read through the method
            return Endpoint(generic, Setting(generic, reason=rule.reason, reader=(rule.method, args),
                                             codec=entry["type"]), kind, **pin)
        return Endpoint(generic, Get(rule.method, args), kind, **pin)
    raise ValueError(f"rule {rule.pattern!r}: kind {rule.kind!r} does not fit property {generic}")


def fill(rows: tuple, firmware: str) -> tuple[Endpoint, ...]:
    """The rows the firmware's table needs beyond ``rows`` on ``firmware``: one per endpoint
    the rows do not cover, by the first matching :data:`RULES` entry."""
    return _filled(tuple(rows), firmware)


def disposition(firmware: str = "0.5.6") -> dict[str, list[str]]:
    """{kind: [generic paths]} of the endpoints the rules give (``"strict"``: no rule
    matched), for the documentation and the tests."""
    from .firmware import VirtualODrive  # load time: the model's own rows
    out: dict[str, list[str]] = {}
    covered = {_generic(p) for p in model_paths(VirtualODrive.endpoints, firmware)}
    for generic, entry in sorted(_table_entries(firmware).items()):
        if generic in covered:
            out.setdefault("row", []).append(generic)
            continue
        if generic in _IDENTITY:
            out.setdefault("identity", []).append(generic)
            continue
        rule = rule_for(generic, firmware)
        out.setdefault("strict" if rule is None else rule.kind, []).append(generic)
    return out


__all__ = ["RULES", "Rule", "UnmodeledError", "disposition", "fill", "row_for", "rule_for", "table_types"]
