"""An ODrive, real or virtual, with the leg it drives: :func:`connect` and :class:`Device`.

``connect(backend="virtual" | "usb")`` returns a :class:`Device`: the ODrive's object tree
(``dev.axis0.controller.config.pos_gain`` works as on the device) plus what experiments
need: property access by logical name (firmware 0.5.1 to 0.5.6; the v3.6 has no 0.6
firmware), the leg's unit conversions and zeroing, a clock and a sleep that work on both
backends, the error flags, and fail-safe idling (:func:`safe`): both axes IDLE when a block
ends, however it ends, and every armed motion under the watchdog.
"""

from __future__ import annotations

import contextlib
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from ..errors import ExperimentError
from ..model.drive import AxisMap
from ..params import LegParams, OdriveConfig, load_leg, load_odrive_config
from .usb import _find_usb

AXIS_STATE_UNDEFINED = 0
AXIS_STATE_IDLE = 1
AXIS_STATE_FULL_CALIBRATION_SEQUENCE = 3
AXIS_STATE_ENCODER_OFFSET_CALIBRATION = 7
AXIS_STATE_CLOSED_LOOP_CONTROL = 8
CONTROL_MODE_TORQUE, CONTROL_MODE_VELOCITY, CONTROL_MODE_POSITION = 1, 2, 3
INPUT_MODE_PASSTHROUGH = 1


# logical property -> path below an axis (firmware 0.5.x endpoint names); the third item of
# a tuple entry is the first firmware revision that has it
PROPERTY_PATHS = {
    "0.5": {
        "requested_state": "requested_state", "current_state": "current_state", "error": "error",
        "control_mode": "controller.config.control_mode", "input_mode": "controller.config.input_mode",
        "pos_gain": "controller.config.pos_gain", "vel_gain": "controller.config.vel_gain",
        "vel_integrator_gain": "controller.config.vel_integrator_gain",
        "vel_integrator_limit": ("controller.config.vel_integrator_limit", 4),
        "input_filter_bandwidth": "controller.config.input_filter_bandwidth",
        "vel_limit": "controller.config.vel_limit", "input_pos": "controller.input_pos",
        "input_vel": "controller.input_vel", "input_torque": "controller.input_torque",
        "controller_error": "controller.error", "motor_error": "motor.error",
        "encoder_error": "encoder.error",
        "enable_watchdog": "config.enable_watchdog", "watchdog_timeout": "config.watchdog_timeout",
        "pos_estimate": "encoder.pos_estimate", "vel_estimate": "encoder.vel_estimate",
        "shadow_count": "encoder.shadow_count", "cpr": "encoder.config.cpr",
        "is_ready": "encoder.is_ready", "is_calibrated": "motor.is_calibrated",
        "current_lim": "motor.config.current_lim", "torque_constant": "motor.config.torque_constant",
        "pole_pairs": "motor.config.pole_pairs", "motor_type": "motor.config.motor_type",
        "calibration_current": "motor.config.calibration_current",
        "motor_pre_calibrated": "motor.config.pre_calibrated",
        "Iq_measured": "motor.current_control.Iq_measured"},
}


# how long leglib waits for the axis thread to take up a requested state (it does so within
# about 1 ms, fw-v0.5.6 axis.cpp:447-488) [s]
STATE_TIMEOUT = 2.0
# the axis states of firmware 0.5.x by number (Firmware/odrive-interface.yaml, AxisState)
STATE_NAMES = ("UNDEFINED", "IDLE", "STARTUP_SEQUENCE", "FULL_CALIBRATION_SEQUENCE", "MOTOR_CALIBRATION",
               "SENSORLESS_CONTROL", "ENCODER_INDEX_SEARCH", "ENCODER_OFFSET_CALIBRATION", "CLOSED_LOOP_CONTROL",
               "LOCKIN_SPIN", "ENCODER_DIR_FIND", "HOMING", "ENCODER_HALL_POLARITY_CALIBRATION",
               "ENCODER_HALL_PHASE_CALIBRATION")
# error flags of firmware 0.5.x that leglib acts on (odrive.enums keeps these values)
AXIS_ERROR_WATCHDOG_TIMER_EXPIRED = 0x800
MOTOR_ERROR_BRAKE_RESISTOR_DISARMED = 0x800000
ENCODER_ERROR_CPR_POLEPAIRS_MISMATCH = 0x2
ENCODER_ERROR_NO_RESPONSE = 0x4


def state_name(state: int) -> str:
    """An axis state's firmware name with its number, e.g. ``CLOSED_LOOP_CONTROL (8)``."""
    name = STATE_NAMES[state] if 0 <= state < len(STATE_NAMES) else "an unknown state"
    return f"{name} ({state})"


def _virtual_model(odrv):
    """The firmware model behind a virtual ODrive's object (any node of its tree, or the
    model itself), None for a real ODrive. A virtual ODrive exists only once its module was
    imported, so a real one never loads the twin."""
    wire = sys.modules.get("leglib.device.virtual.wire")
    return None if wire is None else wire.device_of(odrv)


class Device:
    """An ODrive (virtual or real) with the leg it drives.

    Attribute access falls through to the object tree (``dev.axis0``, ``dev.config``).
    Use as a context manager: both axes go IDLE when the block ends, however it ends.
    """

    def __init__(self, odrv, backend: str, leg: LegParams, config: OdriveConfig, options: dict | None = None):
        self.raw = odrv
        board = _virtual_model(odrv)
        if backend == "virtual" and board is None:
            raise ValueError("backend='virtual' does not match the device object (not a virtual ODrive)")
        if backend not in ("virtual", "usb"):
            raise ValueError(f"backend must be 'virtual' or 'usb', got {backend!r}")
        #: the firmware model behind a virtual ODrive (virtual clock, twin, step_batch,
        #: fault injection); None on USB
        self.sim = board if backend == "virtual" else None
        # a virtual board reached through ``odrive.find_any`` (the USB code path, as a test
        # puts the twin behind it) is driven exactly as a real one; only its clock is the
        # board's own (the virtual clock, which runs with the wall clock in real time)
        self.__dict__["_board_sim"] = board
        self.backend = backend
        self.leg = leg
        self.config = config
        self.axes = AxisMap.from_leg(leg)
        self.options = dict(options or {})
        self._read_firmware_version()
        self._t0 = time.monotonic()

    def _read_firmware_version(self):
        odrv = self.raw
        major = int(odrv.fw_version_major)
        minor = int(odrv.fw_version_minor)
        self.firmware_version = (major, minor, int(odrv.fw_version_revision))
        if (major, minor) == (0, 5):
            self.firmware = "0.5"
        else:
            raise ExperimentError(f"firmware {major}.{minor}.{self.firmware_version[2]} is not supported: "
                                  f"the ODrive v3.6 runs 0.5.x (0.6.x is for ODrive Pro, S1 and Micro)")

    def reconnect(self, timeout: float = 10.0) -> None:
        """Find the same ODrive again after it rebooted (``save_configuration()`` on
        firmware 0.5.2+, ``reboot()``): the old object raises on any access, as on USB.
        Replaces :attr:`raw`; the virtual device is found by its seed, the USB one by its
        serial number (see :func:`_reconnect`)."""
        self.rebind(_reconnect(self, timeout))

    # -- the tree ----------------------------------------------------------------------
    def __getattr__(self, name):
        if name in ("raw",):
            raise AttributeError(name)
        return getattr(self.raw, name)

    def axis(self, a: int):
        if a not in (0, 1):
            raise ValueError(f"axis must be 0 or 1, got {a!r}")
        return getattr(self.raw, f"axis{a}")

    def _path(self, key: str) -> list[str]:
        table = PROPERTY_PATHS.get(self.firmware)
        if table is None:
            raise ExperimentError(f"firmware {self.firmware}.x is not an ODrive v3.6 firmware: the v3.6 runs "
                                  f"0.5.x (0.6.x is for ODrive Pro, S1 and Micro)")
        try:
            path = table[key]
        except KeyError:
            raise KeyError(f"unknown ODrive property {key!r}; known: {sorted(table)}") from None
        if isinstance(path, tuple):
            path, since = path
            if self.firmware_version[2] < since:
                raise ExperimentError(f"property {key!r} ({path}) does not exist on firmware "
                                      f"{'.'.join(map(str, self.firmware_version))} (0.5.{since}+)")
        return path.split(".")

    def has(self, key: str) -> bool:
        """True when this firmware has the logical property ``key``."""
        try:
            self._path(key)
        except ExperimentError:
            return False
        return True

    def get(self, a: int, key: str):
        """Read an axis property by logical name."""
        node = self.axis(a)
        for part in self._path(key):
            node = getattr(node, part)
        return node

    def set(self, a: int, key: str, value) -> None:
        """Write an axis property by logical name."""
        *head, last = self._path(key)
        node = self.axis(a)
        for part in head:
            node = getattr(node, part)
        setattr(node, last, value)

    def counts(self, a: int) -> int:
        """Encoder counts (``shadow_count``) of axis ``a``."""
        return int(self.get(a, "shadow_count"))

    @property
    def sim(self):
        """The :class:`leglib.device.virtual.firmware.VirtualODrive` behind this device (its clock,
        twin and whole-experiment runner), or None for a real ODrive."""
        s = self.__dict__.get("_sim")
        if s is not None:
            return s
        firmware = sys.modules.get("leglib.device.virtual.firmware")
        raw = self.__dict__.get("raw")
        return raw if firmware is not None and isinstance(raw, firmware.VirtualODrive) else None

    @sim.setter
    def sim(self, value):
        self.__dict__["_sim"] = value

    def rebind(self, odrv) -> None:
        """Use the object tree ``odrv`` of a new connection to the same ODrive (after a
        reboot); the leg, configuration and zeroing stay."""
        serial = int(odrv.serial_number)
        known = self.__dict__.get("serial_number_at_connect")
        if known is not None and serial != known:
            raise ExperimentError(f"reconnected to ODrive {serial:012X}, expected {known:012X}")
        self.__dict__["raw"] = odrv

    # -- time --------------------------------------------------------------------------
    def time(self) -> float:
        """Seconds: the virtual clock on the twin (since its power-up), the wall clock
        since connect on USB."""
        board = self.__dict__.get("_board_sim")
        if board is not None:
            return board.time
        return time.monotonic() - self._t0

    def sleep(self, seconds: float) -> None:
        """Wait; on the twin the simulated leg moves on meanwhile."""
        board = self.__dict__.get("_board_sim")
        if board is not None:
            board.sleep(seconds)
        else:
            time.sleep(seconds)

    def board_clock(self) -> float:
        """Seconds on a clock that runs with the board from connection to connection: the
        virtual board's own clock (since its power-up), else the host's monotonic clock."""
        board = self.__dict__.get("_board_sim")
        return board.time if board is not None else time.monotonic()

    @property
    def serial(self) -> int:
        """The board's serial number (read once; a virtual board's from its model, without a
        USB transaction)."""
        serial = self.__dict__.get("_serial")
        if serial is None:
            board = self.__dict__.get("_board_sim")
            serial = int(board._serial()) if board is not None else int(self.raw.serial_number)
            self.__dict__["_serial"] = serial
        return serial

    # -- safety ------------------------------------------------------------------------
    def idle_all(self, confirm: float = 0.05) -> list[str]:
        """Request IDLE on both axes and wait up to ``confirm`` s (device and wall clock) until
        both report it (the axis thread takes a request up within about 1 ms); returns the
        failures (never raises)."""
        failures = []
        for a in (0, 1):
            try:
                self.set(a, "requested_state", AXIS_STATE_IDLE)
            except Exception as exc:  # noqa: BLE001 - the link may be gone: the watchdog must then act
                failures.append(f"axis{a}: {type(exc).__name__}: {exc}")
        if not failures:
            try:
                t_dev, t_wall = self.time() + confirm, time.monotonic() + max(confirm, 0.5)
                while True:
                    if all(int(self.get(a, "requested_state")) == AXIS_STATE_UNDEFINED
                           and int(self.get(a, "current_state")) == AXIS_STATE_IDLE for a in (0, 1)):
                        break
                    if self.time() > t_dev or time.monotonic() > t_wall:
                        failures.append("IDLE requested but not confirmed by both axes")
                        break
                    self.sleep(0.0005)
            except Exception as exc:  # noqa: BLE001 - never raise from the safety path
                failures.append(f"confirming IDLE: {type(exc).__name__}: {exc}")
        if failures:
            warnings.warn("could not set IDLE: " + "; ".join(failures) +
                          " -- the ODrive's watchdog idles the motors when the link is lost", stacklevel=2)
        return failures

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.idle_all()
        return False

    def close(self):
        self.idle_all()

    def describe(self) -> dict:
        """Backend facts for sidecars."""
        d = {"backend": self.backend, "firmware": ".".join(map(str, self.firmware_version))}
        if self.sim is not None:
            tw = self.sim.twin
            d.update({"twin_seed": tw.seed, "twin_plant": tw.plant.source_file,
                      "twin_plant_values": {k: v for k, v in vars(tw.plant).items() if k != "source_file"},
                      "twin_noise": tw.noise})
        return d


@contextlib.contextmanager
def safe(dev: Device):
    """Both axes IDLE when the block ends: normally, on an exception, on KeyboardInterrupt.

    Once both are IDLE the watchdog is switched off again: it counts down in IDLE too
    (axis.cpp:171-182) and, unfed, would flag an error that blocks the next experiment.
    When the link is gone it stays on, which is what stops the motors then.
    """
    try:
        yield dev
    finally:
        if not dev.idle_all():
            for a in (0, 1):
                try:
                    dev.set(a, "enable_watchdog", False)
                except Exception as exc:  # noqa: BLE001 - never raise from the safety path
                    warnings.warn(f"both axes are IDLE but axis{a}'s watchdog could not be switched off "
                                  f"({type(exc).__name__}: {exc}): it will flag WATCHDOG_TIMER_EXPIRED; "
                                  f"clear_errors after reconnecting", stacklevel=3)
                    break


def connect(backend: str = "virtual", *, leg: str | LegParams = "thesis",
            config: str | OdriveConfig = "thesis", timeout: float = 10.0,
            serial_number: str | None = None, **virtual_options) -> Device:
    """Connect to an ODrive.

    Parameters
    ----------
    backend : "virtual" (the twin, through :func:`leglib.device.virtual.wire.find_any`) or
        "usb" (a real ODrive via ``odrive.find_any``)
    leg : the leg it drives (nominal parameters: units, kinematics)
    config : the ODrive configuration to apply and check against (Listing 7.1); on the twin
        also the virtual device's initial configuration
    timeout : USB search timeout [s]
    serial_number : the ODrive to find (USB; on the twin the virtual device's serial)
    **virtual_options : for the twin: ``seed``, ``plant`` (name, path or PlantParams),
        ``realtime``, ``firmware`` ("0.5.6", "0.5.1"), ``disconnect_after``, ``noise``

    Returns
    -------
    Device
        ``dev.raw`` is the ``odrive`` client's object on both backends; ``dev.sim`` the
        firmware model on the twin (None on USB). A virtual device lives for the process
        under its seed: connecting with the same seed again gives the same device.
    """
    leg = load_leg(leg) if isinstance(leg, (str, Path)) else leg
    config = load_odrive_config(config) if isinstance(config, (str, Path)) else config
    if backend == "virtual":
        allowed = {"seed", "plant", "realtime", "firmware", "disconnect_after", "noise",
                   "payload_off_for_calibration"}
        unknown = set(virtual_options) - allowed
        if unknown:
            raise TypeError(f"connect(backend='virtual'): unknown option(s) {sorted(unknown)}; "
                            f"allowed: {sorted(allowed)}")
        opts = {"config": config, **virtual_options}
        if serial_number is not None:
            opts["serial_number"] = serial_number
        from .virtual import find_any  # load time: the twin (numba) and the odrive client, on this backend only
        odrv = find_any(**opts)
        return Device(odrv, "virtual", leg, config, opts)
    if backend == "usb":
        if virtual_options:
            raise TypeError(f"connect(backend='usb'): options {sorted(virtual_options)} are for the "
                            f"virtual backend")
        return Device(_find_usb(timeout, serial_number), "usb", leg, config)
    raise ValueError(f"backend must be 'virtual' or 'usb', got {backend!r}")


def as_device(odrv, leg: str | LegParams = "thesis", config: str | OdriveConfig = "thesis") -> Device:
    """Wrap an ODrive object (from ``odrive.find_any``, odrivetool, or
    :func:`leglib.device.virtual.wire.find_any`) as a Device; a Device passes through. A client
    object of a virtual ODrive is recognised as virtual; so is the firmware model itself
    (its own tree carries the firmware's endpoint names, without the client in between)."""
    if isinstance(odrv, Device):
        return odrv
    leg = load_leg(leg) if isinstance(leg, (str, Path)) else leg
    config = load_odrive_config(config) if isinstance(config, (str, Path)) else config
    sim = _virtual_model(odrv)
    options = {}
    if sim is not None:
        options = sys.modules["leglib.device.virtual.wire"].connect_options(sim)
    return Device(odrv, "virtual" if sim is not None else "usb", leg, config, options)


class Deadline:
    """A time limit on the device's clock and on the wall clock: a virtual clock that stops
    (a plant that never finishes) cannot make a wait loop forever."""

    def __init__(self, dev: Device, seconds: float, what: str, wall_seconds: float | None = None):
        self.dev, self.what, self.seconds = dev, what, seconds
        self.t_dev = dev.time() + seconds
        self.t_wall = time.monotonic() + (seconds if wall_seconds is None else wall_seconds)

    def expired(self) -> bool:
        return self.dev.time() > self.t_dev or time.monotonic() > self.t_wall

    def check(self, detail=lambda: "") -> None:
        """Raise ExperimentError once the time is up; ``detail()`` (a callable, so that what
        it reads from the device is read only then, not on every poll) ends its message."""
        if self.expired():
            raise ExperimentError(f"{self.what} did not finish within {self.seconds:g} s{detail()}: "
                                  f"axes set IDLE")


def wait_states(dev: Device, axes, state: int, timeout: float = STATE_TIMEOUT, poll: float = 0.0005,
                 what: str | None = None) -> None:
    """Wait until every axis in ``axes`` has taken up its request and is in ``state``; raise
    ExperimentError naming the axis, its state and errors when it drops to IDLE instead or
    the time runs out."""
    deadline = Deadline(dev, timeout, what or f"entering state {state}")
    while True:
        # the request first: once it reads 0 it has been taken up, and the state read after it
        # is the new one
        pending = {a: int(dev.get(a, "requested_state")) for a in axes}
        states = {a: int(dev.get(a, "current_state")) for a in axes}
        if all(states[a] == state and pending[a] == AXIS_STATE_UNDEFINED for a in axes):
            return
        for a in axes:
            if pending[a] == AXIS_STATE_UNDEFINED and states[a] == AXIS_STATE_IDLE and state != AXIS_STATE_IDLE:
                raise ExperimentError(f"axis{a} did not enter state {state} (it is IDLE): "
                                      f"{error_text(dev, a)}")
        deadline.check(lambda: f" (states {states})")
        dev.sleep(poll)


def error_text(dev: Device, a: int) -> str:
    parts = [f"axis{a}.error = 0x{int(dev.get(a, 'error')):x}",
             f"motor.error = 0x{int(dev.get(a, 'motor_error')):x}",
             f"encoder.error = 0x{int(dev.get(a, 'encoder_error')):x}",
             f"controller.error = 0x{int(dev.get(a, 'controller_error')):x}"]
    if has_system_error(dev):
        parts.append(f"odrv.error = 0x{int(dev.raw.error):x}")
    return ", ".join(parts)


def has_system_error(dev: Device) -> bool:
    """Firmware 0.5.2+ keeps board errors in ``odrv.error`` (main.cpp:313-320)."""
    return dev.firmware_version[:2] == (0, 5) and dev.firmware_version[2] >= 2


def errors(odrv) -> dict:
    """All error flags: ``{"odrv": int or None, "axis0": {...}, "axis1": {...}}``."""
    dev = as_device(odrv)
    out = {"odrv": int(dev.raw.error) if has_system_error(dev) else None}
    for a in (0, 1):
        out[f"axis{a}"] = {k: int(dev.get(a, k)) for k in ("error", "motor_error", "encoder_error",
                                                          "controller_error")}
    return out
_ERROR_ENUMS = {"error": "AxisError", "motor_error": "MotorError", "encoder_error": "EncoderError",
                "controller_error": "ControllerError"}


def describe_errors(errs: dict) -> str:
    """:func:`errors`' flags as text with the firmware's names, e.g.
    ``axis0.error = WATCHDOG_TIMER_EXPIRED (0x800)``; "no errors" when none is set. Names
    come from ``odrive.enums`` (which keeps the 0.5.x enums; ``odrv.error`` is its
    ``LegacyODriveError``); a bit it does not name is shown in hex."""
    try:
        from odrive import enums  # load time: the odrive client (needs libusb)
    except Exception:  # noqa: BLE001 - the client's native part missing: hex only
        enums = None

    def flags(value: int, enum_name: str) -> str:
        enum = getattr(enums, enum_name, None) if enums is not None else None
        names = []
        if enum is not None:
            known = 0
            for member in sorted(enum, key=lambda m: m.value):
                if member.value and value & member.value == member.value and member.value & (member.value - 1) == 0:
                    names.append(member.name)
                    known |= member.value
            if value & ~known:
                names.append(f"0x{value & ~known:x}")
        return f"{'|'.join(names) or hex(value)} (0x{value:x})"

    parts = []
    if errs.get("odrv"):
        parts.append(f"odrv.error = {flags(int(errs['odrv']), 'LegacyODriveError')}")
    for a in (0, 1):
        for key, value in (errs.get(f"axis{a}") or {}).items():
            if value:
                where = f"axis{a}.error" if key == "error" else f"axis{a}.{key.replace('_error', '')}.error"
                parts.append(f"{where} = {flags(int(value), _ERROR_ENUMS.get(key, ''))}")
    return ", ".join(parts) or "no errors"


def any_error(dev: Device) -> bool:
    e = errors(dev)
    return bool(e["odrv"]) or any(v for a in (0, 1) for v in e[f"axis{a}"].values())


def _reconnect(dev: Device, timeout: float = 10.0):
    """A new connection to the same ODrive after it rebooted, found by serial number (the
    virtual one through :func:`leglib.device.virtual.wire.find_any` with its seed, as a script
    would). Returns the new object tree (give it to :meth:`Device.rebind`)."""
    serial = dev.__dict__.get("serial_number_at_connect")
    if dev.sim is not None:
        opts = {k: v for k, v in dev.options.items() if k != "disconnect_after"}
        return sys.modules["leglib.device.virtual.wire"].find_any(**opts)
    time.sleep(1.0)  # the board resets; searching at once may find the old USB device still
    return _find_usb(timeout, None if serial is None else f"{serial:012X}")


def clear_errors(odrv) -> None:
    """Clear all error flags the firmware's way (after inspecting them): ``odrv.clear_errors()``
    on 0.5.2+ (main.cpp:236-249; it also re-arms an enabled brake resistor),
    ``axis.clear_errors()`` on 0.5.1 (fw-v0.5.1 axis.hpp:108-116).

    An IDLE axis's watchdog is switched off first: left on after a lost link, unfed, it
    would expire again at once (axis.cpp:165-182) and the flag would be back before the
    next experiment starts."""
    dev = as_device(odrv)
    for a in (0, 1):
        if bool(dev.get(a, "enable_watchdog")) and int(dev.get(a, "current_state")) == AXIS_STATE_IDLE:
            dev.set(a, "enable_watchdog", False)
    if has_system_error(dev):
        dev.raw.clear_errors()
    else:
        for a in (0, 1):
            dev.axis(a).clear_errors()


def check_gains(cfg: OdriveConfig, pos_gain, vel_gain, vel_integrator_gain):
    for name, value, high in (("pos_gain", pos_gain, cfg.max_pos_gain),
                              ("vel_gain", vel_gain, cfg.max_vel_gain),
                              ("vel_integrator_gain", vel_integrator_gain, cfg.max_vel_integrator_gain)):
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)) \
                or not math.isfinite(value):
            raise ValueError(f"{name} must be a finite number, got {value!r}")
        if not 0.0 <= value <= high:
            raise ValueError(f"{name} = {value} is outside the allowed range [0, {high}] "
                             f"({cfg.source_file}, [experiment] max_{name})")


def prepare_closed_loop(dev: Device, vel_limit: float, watchdog: float | None) -> None:
    """Refuse to start on a stale fault; then limits, then the watchdog (on with a timeout
    [s], off with None); both axes.

    The watchdog is fed before it is enabled: its timer counts down in every state while
    enabled and is only reloaded by a feed (axis.cpp:165-182), so enabling it unfed trips
    AXIS_ERROR_WATCHDOG_TIMER_EXPIRED at once.
    """
    if not (isinstance(vel_limit, (int, float, np.integer, np.floating)) and not isinstance(vel_limit, bool)
            and math.isfinite(vel_limit) and vel_limit > 0):
        raise ValueError(f"vel_limit must be a positive finite number [turn/s], got {vel_limit!r}")
    if watchdog is not None and not (math.isfinite(watchdog) and watchdog > 0):
        raise ValueError(f"watchdog must be a positive timeout [s] or None, got {watchdog!r}")
    if any_error(dev):
        raise ExperimentError(f"an earlier fault is still flagged ({describe_errors(errors(dev))}); inspect it, then call "
                              f"leglib.device.session.clear_errors(odrv)")
    for a in (0, 1):
        if not (bool(dev.get(a, "is_calibrated")) and bool(dev.get(a, "is_ready"))):
            raise ExperimentError(f"axis{a} is not calibrated (motor.is_calibrated, encoder.is_ready): "
                                  f"run leglib.device.setup.calibrate(odrv) first")
    for a in (0, 1):
        dev.set(a, "current_lim", dev.config.current_lim)
        dev.set(a, "vel_limit", vel_limit)
        if watchdog:
            dev.set(a, "watchdog_timeout", watchdog)
            dev.axis(a).watchdog_feed()
            dev.set(a, "enable_watchdog", True)
        else:
            dev.set(a, "enable_watchdog", False)


def enter_closed_loop(dev: Device) -> None:
    """Request closed loop on both axes and wait until both are in it: the request is taken
    up by the axis thread about 1 ms later, and entering sets ``input_pos := pos_estimate``
    (axis.cpp:290-291, 455-488), so targets are written only after this returns."""
    for a in (0, 1):
        dev.set(a, "requested_state", AXIS_STATE_CLOSED_LOOP_CONTROL)
    wait_states(dev, (0, 1), AXIS_STATE_CLOSED_LOOP_CONTROL, what="entering closed loop")
    for a in (0, 1):
        dev.axis(a).watchdog_feed()


# the watchdog of a hold in closed loop (return_to_rest) and how often it is fed [s]: the
# feed period leaves room for a slow USB transaction or a busy host
HOLD_WATCHDOG = 0.5
HOLD_FEED_PERIOD = 0.1


def hold_under_watchdog(dev: Device, seconds: float, feed_period: float = HOLD_FEED_PERIOD) -> None:
    """Let ``seconds`` pass with both axes armed, feeding their watchdogs every
    ``feed_period`` s (a plain sleep would let an enabled watchdog expire, and a disabled
    one would not stop the motors if the link died meanwhile)."""
    end = dev.time() + seconds
    while True:
        left = end - dev.time()
        if left <= 0:
            return
        dev.sleep(min(feed_period, left))
        for a in (0, 1):
            dev.axis(a).watchdog_feed()
