"""One experiment code for the real leg and its digital twin.

``connect(backend="virtual" | "usb")`` returns a :class:`Device`: the ODrive's object tree
(``dev.axis0.controller.config.pos_gain`` works as on the device) plus what experiments
need: property access by logical name (firmware 0.5.1 to 0.5.6; the v3.6 has no 0.6
firmware), the leg's unit conversions and zeroing, a clock and a sleep that work on both
backends, and fail-safe idling.

Experiments (the thesis listings, done the firmware's way): :func:`apply_configuration`
(7.1; enables the brake resistor, saves, survives the reboot), :func:`calibrate` (7.2; one
axis at a time, then the zeroing), :func:`play_torque_table` (7.3), :func:`step_response`
and :func:`sweep` (7.4), :func:`apply_gains`. Each waits for the axes to take up a requested
state, feeds the watchdog before enabling it, refuses to start on a flagged error (see
:func:`errors`, :func:`clear_errors`), and leaves both axes IDLE, on normal exit, on any
exception and on KeyboardInterrupt. Waits are bounded on the device's clock and on the
wall clock.
"""

from __future__ import annotations

import contextlib
import functools
import math
import threading
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import dataio
from .drive import AxisMap
from .model import foot_position
from .params import LegParams, OdriveConfig, load_leg, load_odrive_config

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


class DeviceNotFoundError(RuntimeError):
    """No ODrive answered on USB."""


class ExperimentError(RuntimeError):
    """An experiment could not run (calibration failed, axis error, ...)."""


class Device:
    """An ODrive (virtual or real) with the leg it drives.

    Attribute access falls through to the object tree (``dev.axis0``, ``dev.config``).
    Use as a context manager: both axes go IDLE when the block ends, however it ends.
    """

    def __init__(self, odrv, backend: str, leg: LegParams, config: OdriveConfig, options: dict | None = None):
        from .virtual_odrive import device_of
        self.raw = odrv
        #: the firmware model behind a virtual ODrive (virtual clock, twin, step_batch,
        #: fault injection); None on USB
        self.sim = device_of(odrv)
        self.backend = backend
        if (backend == "virtual") != (self.sim is not None):
            raise ValueError(f"backend={backend!r} does not match the device object "
                             f"({'a virtual' if self.sim is not None else 'not a virtual'} ODrive)")
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
        """The :class:`leglib.virtual_odrive.VirtualODrive` behind this device (its clock,
        twin and whole-experiment runner), or None for a real ODrive."""
        s = self.__dict__.get("_sim")
        if s is not None:
            return s
        from .virtual_odrive import VirtualODrive
        return self.__dict__["raw"] if isinstance(self.__dict__.get("raw"), VirtualODrive) else None

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
        if self.sim is not None:
            return self.sim.time
        return time.monotonic() - self._t0

    def sleep(self, seconds: float) -> None:
        """Wait; on the twin the simulated leg moves on meanwhile."""
        if self.sim is not None:
            self.sim.sleep(seconds)
        else:
            time.sleep(seconds)

    # -- safety ------------------------------------------------------------------------
    def idle_all(self, confirm: float = 0.05) -> list[str]:
        """Request IDLE on both axes and wait up to ``confirm`` s (device and wall clock) until
        both report it (the axis thread takes a request up within about 1 ms); returns the
        failures (never raises)."""
        failures = []
        for a in (0, 1):
            try:
                self.set(a, "requested_state", AXIS_STATE_IDLE)
            except Exception as exc:  # the link may be gone: the watchdog must then act
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
                except Exception:  # noqa: BLE001 - never raise from the safety path
                    pass


# ---------------------------------------------------------------------------------------
# connecting
# ---------------------------------------------------------------------------------------

def _find_usb(timeout: float, serial_number: str | None):
    try:
        import odrive
    except Exception as exc:  # the native part needs libusb-1.0
        raise DeviceNotFoundError(f"cannot import the odrive package ({exc}); on Debian install "
                                  f"libusb-1.0-0") from exc
    result: dict = {}

    def worker():
        try:
            kwargs = {"timeout": timeout}
            if serial_number:
                kwargs["serial_number"] = serial_number
            result["odrv"] = odrive.find_any(**kwargs)
        except BaseException as exc:  # noqa: BLE001 - reported to the caller below
            result["error"] = exc

    # ipykernel 7 + find_any on the kernel's thread hangs a live JupyterLab kernel: run it
    # on a worker thread and give up ourselves after the timeout.
    th = threading.Thread(target=worker, name="odrive-find-any", daemon=True)
    th.start()
    th.join(timeout + 2.0)
    if "odrv" in result and result["odrv"] is not None:
        return result["odrv"]
    err = result.get("error")
    detail = f" ({type(err).__name__}: {err})" if err is not None else ""
    raise DeviceNotFoundError(f"no ODrive answered on USB within {timeout:g} s{detail}. Check power, "
                              f"the cable, USB permissions (udev rules) and that no other program "
                              f"(odrivetool) holds the device.")


def connect(backend: str = "virtual", *, leg: str | LegParams = "thesis",
            config: str | OdriveConfig = "thesis", timeout: float = 10.0,
            serial_number: str | None = None, **virtual_options) -> Device:
    """Connect to an ODrive.

    Parameters
    ----------
    backend : "virtual" (the twin, through :func:`leglib.virtual_odrive.find_any`) or
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
        from .virtual_odrive import find_any
        allowed = {"seed", "plant", "realtime", "firmware", "disconnect_after", "noise",
                   "payload_off_for_calibration"}
        unknown = set(virtual_options) - allowed
        if unknown:
            raise TypeError(f"connect(backend='virtual'): unknown option(s) {sorted(unknown)}; "
                            f"allowed: {sorted(allowed)}")
        opts = {"config": config, **virtual_options}
        if serial_number is not None:
            opts["serial_number"] = serial_number
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
    :func:`leglib.virtual_odrive.find_any`) as a Device; a Device passes through. A client
    object of a virtual ODrive is recognised as virtual; so is the firmware model itself
    (its own tree carries the firmware's endpoint names, without the client in between)."""
    if isinstance(odrv, Device):
        return odrv
    from .virtual_odrive import device_of
    leg = load_leg(leg) if isinstance(leg, (str, Path)) else leg
    config = load_odrive_config(config) if isinstance(config, (str, Path)) else config
    sim = device_of(odrv)
    options = {}
    if sim is not None:
        from .fibre_device import connect_options
        options = connect_options(sim)
    return Device(odrv, "virtual" if sim is not None else "usb", leg, config, options)


# ---------------------------------------------------------------------------------------
# Listing 7.1, 7.2: configuration and calibration
# ---------------------------------------------------------------------------------------

class _Deadline:
    """A time limit on the device's clock and on the wall clock: a virtual clock that stops
    (a plant that never finishes) cannot make a wait loop forever."""

    def __init__(self, dev: Device, seconds: float, what: str, wall_seconds: float | None = None):
        self.dev, self.what, self.seconds = dev, what, seconds
        self.t_dev = dev.time() + seconds
        self.t_wall = time.monotonic() + (seconds if wall_seconds is None else wall_seconds)

    def expired(self) -> bool:
        return self.dev.time() > self.t_dev or time.monotonic() > self.t_wall

    def check(self, detail: str = "") -> None:
        if self.expired():
            raise ExperimentError(f"{self.what} did not finish within {self.seconds:g} s{detail}: "
                                  f"axes set IDLE")


def _wait_states(dev: Device, axes, state: int, timeout: float = STATE_TIMEOUT, poll: float = 0.0005,
                 what: str | None = None) -> None:
    """Wait until every axis in ``axes`` has taken up its request and is in ``state``; raise
    ExperimentError naming the axis, its state and errors when it drops to IDLE instead or
    the time runs out."""
    deadline = _Deadline(dev, timeout, what or f"entering state {state}")
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
                                      f"{_error_text(dev, a)}")
        deadline.check(f" (states {states})")
        dev.sleep(poll)


def _error_text(dev: Device, a: int) -> str:
    parts = [f"axis{a}.error = 0x{int(dev.get(a, 'error')):x}",
             f"motor.error = 0x{int(dev.get(a, 'motor_error')):x}",
             f"encoder.error = 0x{int(dev.get(a, 'encoder_error')):x}",
             f"controller.error = 0x{int(dev.get(a, 'controller_error')):x}"]
    if _has_system_error(dev):
        parts.append(f"odrv.error = 0x{int(dev.raw.error):x}")
    return ", ".join(parts)


def _has_system_error(dev: Device) -> bool:
    """Firmware 0.5.2+ keeps board errors in ``odrv.error`` (main.cpp:313-320)."""
    return dev.firmware_version[:2] == (0, 5) and dev.firmware_version[2] >= 2


def errors(odrv) -> dict:
    """All error flags: ``{"odrv": int or None, "axis0": {...}, "axis1": {...}}``."""
    dev = as_device(odrv)
    out = {"odrv": int(dev.raw.error) if _has_system_error(dev) else None}
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
        from odrive import enums
    except Exception:   # the client's native part missing: hex only
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


def _any_error(dev: Device) -> bool:
    e = errors(dev)
    return bool(e["odrv"]) or any(v for a in (0, 1) for v in e[f"axis{a}"].values())


def _reconnect(dev: Device, timeout: float = 10.0):
    """A new connection to the same ODrive after it rebooted, found by serial number (the
    virtual one through :func:`leglib.virtual_odrive.find_any` with its seed, as a script
    would). Returns the new object tree (give it to :meth:`Device.rebind`)."""
    serial = dev.__dict__.get("serial_number_at_connect")
    if dev.sim is not None:
        from .virtual_odrive import find_any
        opts = {k: v for k, v in dev.options.items() if k != "disconnect_after"}
        return find_any(**opts)
    time.sleep(1.0)  # the board resets; searching at once may find the old USB device still
    return _find_usb(timeout, None if serial is None else f"{serial:012X}")


def _save_and_reconnect(dev: Device, timeout: float = 10.0) -> None:
    """``save_configuration()`` the firmware's way: axes idle first; on 0.5.2+ the board
    refuses while armed and reboots otherwise (main.cpp:159-184), so the connection is
    re-made by serial number. Calibration is lost by the reboot (unless pre-calibrated)."""
    dev.__dict__["serial_number_at_connect"] = int(dev.raw.serial_number)
    dev.idle_all()
    _wait_states(dev, (0, 1), AXIS_STATE_IDLE, what="going IDLE before saving")
    reboots = _has_system_error(dev)
    try:
        ok = dev.raw.save_configuration()
    except Exception as exc:  # noqa: BLE001 - the board resets before it answers
        if not reboots:
            raise
        lost = exc
    else:
        lost = None
        if ok is False:
            raise ExperimentError("save_configuration refused: a motor is armed (set both axes IDLE first)")
    if reboots:
        try:
            dev.rebind(_reconnect(dev, timeout))
        except Exception as exc:
            raise ExperimentError(f"the ODrive rebooted after save_configuration ({lost!r}) and did not "
                                  f"come back within {timeout:g} s: {exc}") from exc
        dev.axes = dev.axes.zeroed((0.0, 0.0))  # the counts restarted: the old zero is void


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
    if _has_system_error(dev):
        dev.raw.clear_errors()
    else:
        for a in (0, 1):
            dev.axis(a).clear_errors()


def apply_configuration(dev: Device, config: OdriveConfig | None = None, save: bool = True) -> dict:
    """Apply Listing 7.1's configuration to both axes, check it reads back, enable the brake
    resistor, and save it.

    The thesis's board has a 2.05 ohm brake resistor; firmware 0.5.2+ leaves it disabled by
    default (odrive_main.h:82) and then trips ODRIVE_ERROR_DC_BUS_OVER_REGEN_CURRENT as soon as
    a braking motor feeds back more than 10 mA (odrive_main.h:111, low_level.cpp:374-376).
    The resistor is armed only at boot or by ``clear_errors`` (low_level.cpp:181-183,
    main.cpp:246-248): with ``save`` the reboot arms it, without, ``clear_errors`` does.
    On 0.5.2+ saving reboots the board: the device is reconnected by serial number
    (``dev`` is rebound in place) and must be calibrated again.

    Returns the values written, per axis.
    """
    dev = as_device(dev)
    cfg = config or dev.config
    written = {}
    with safe(dev):
        for a in (0, 1):
            values = {"current_lim": cfg.current_lim, "vel_limit": cfg.vel_limit,
                      "pole_pairs": cfg.pole_pairs, "torque_constant": cfg.torque_constant,
                      "motor_type": cfg.motor_type, "cpr": cfg.cpr}
            for key, value in values.items():
                dev.set(a, key, value)
                back = dev.get(a, key)
                if not math.isclose(float(back), float(value), rel_tol=1e-6, abs_tol=1e-9):
                    raise ExperimentError(f"axis{a}.{key}: wrote {value}, device reports {back}")
            written[f"axis{a}"] = values
        dev.raw.config.brake_resistance = cfg.brake_resistance
        written["brake_resistance"] = cfg.brake_resistance
        if _has_system_error(dev):
            dev.raw.config.enable_brake_resistor = True
            written["enable_brake_resistor"] = True
        if save:
            _save_and_reconnect(dev)
            for a in (0, 1):
                for key, value in written[f"axis{a}"].items():
                    back = dev.get(a, key)
                    if not math.isclose(float(back), float(value), rel_tol=1e-6, abs_tol=1e-9):
                        raise ExperimentError(f"axis{a}.{key}: saved {value}, the rebooted device reports {back}")
        elif _has_system_error(dev):
            clear_errors(dev)   # arms the brake resistor
    return written


def calibrate(dev: Device, timeout: float = 60.0, poll: float = 0.1, zero: bool = True) -> None:
    """Calibrate both axes (Listing 7.2), one after the other, then zero the joint angles.

    The encoder offset calibration turns the rotor about +-0.73 turn (16 pi electrical rad
    over 11 pole pairs, encoder.hpp:22; +-87 deg of joint on the 1:3 belt) at
    ``calibration_current``; the leg must be free to swing that far. The axes go one at a
    time: the idle link is carried along through the stop between the links, whereas two
    simultaneous locks can squeeze the links against their stop (each rotor jumps to its
    nearest electrical alignment, up to 1/22 turn, 5.5 deg of joint) and the two scans then
    fight. A motor with ``motor.config.pre_calibrated`` skips its motor calibration; the
    encoders (incremental, no index) always need the offset calibration after a boot
    (encoder.cpp:19-30,130-138).

    With ``zero`` the joint angles are defined at the rest pose from ``pos_estimate``: read
    before the calibration (the leg resting on its stop, as :func:`zero_joints` does) and
    carried through the calibration's re-referencing of the counts (encoder.cpp:344 shifts
    them by whole turns, found from the positions before and after). A leg that calibration
    left at rest within the friction dead band (about 1 deg here) would give a zero that far
    off; the pose before calibration is the one the leg settled into undisturbed. When the
    leg does not come back to within 0.05 turn of that pose, it is zeroed where it rests
    after calibration instead (with a warning).

    Raises ExperimentError naming the axis and its error flags when calibration fails, and
    when an axis does not finish within ``timeout`` s (device and wall clock).
    """
    dev = as_device(dev)
    if isinstance(timeout, bool) or not (isinstance(timeout, (int, float)) and math.isfinite(timeout) and timeout > 0):
        raise ValueError(f"timeout must be a positive number of seconds, got {timeout!r}")
    before = _rest_positions(dev) if zero else None
    with safe(dev):
        for a in (0, 1):
            if int(dev.get(a, "error")):
                raise ExperimentError(f"axis{a} has an error before calibration: {_error_text(dev, a)}; "
                                      f"inspect it, then call leglib.odrive_io.clear_errors(odrv)")
        for a in (0, 1):
            request = (AXIS_STATE_ENCODER_OFFSET_CALIBRATION if bool(dev.get(a, "is_calibrated"))
                       else AXIS_STATE_FULL_CALIBRATION_SEQUENCE)
            dev.set(a, "requested_state", request)
            deadline = _Deadline(dev, timeout, f"calibration of axis{a}")
            while True:
                dev.sleep(poll)
                if int(dev.get(a, "requested_state")) == AXIS_STATE_UNDEFINED \
                        and int(dev.get(a, "current_state")) == AXIS_STATE_IDLE:
                    break
                deadline.check(f" (state {int(dev.get(a, 'current_state'))})")
            if int(dev.get(a, "error")) or not bool(dev.get(a, "is_ready")):
                raise ExperimentError(f"axis{a} calibration failed: {_error_text(dev, a)} "
                                      f"(check cpr and pole_pairs against the hardware, and that the "
                                      f"leg can swing freely)")
    if zero:
        after = _rest_positions(dev)
        shift = np.round(after - before)   # whole turns: the counts' re-reference
        if np.all(np.abs(after - before - shift) < 0.05):
            dev.axes = dev.axes.zeroed(before + shift)
        else:
            warnings.warn(f"the leg did not come back to its rest pose after calibration (moved "
                          f"{np.round(after - before - shift, 3)} turn): zeroed where it rests now",
                          stacklevel=2)
            dev.axes = dev.axes.zeroed(after)


def _rest_positions(dev: Device, settle: float = 1.0, max_speed: float = 0.01,
                    patience: float = 10.0) -> np.ndarray:
    """Motor positions [turn] (joint 0's motor, joint 1's motor) of the leg at rest: both
    axes IDLE, ``settle`` s, then the mean of a few ``pos_estimate`` readings once both
    motors turn slower than ``max_speed`` turn/s; a leg still swinging after ``patience``
    more seconds (a heavy foot rocking on its stop) is refused."""
    with safe(dev):
        _wait_states(dev, (0, 1), AXIS_STATE_IDLE, what="going IDLE before zeroing")
        dev.sleep(settle)
        a1, a2 = dev.axes.axis_of_joint

        def mean_pos(n=8):
            return np.mean([(float(dev.get(a1, "pos_estimate")), float(dev.get(a2, "pos_estimate")))
                            for _ in range(n)], axis=0)
        deadline = _Deadline(dev, patience, "the leg coming to rest for zeroing")
        while True:
            t0, p0 = dev.time(), mean_pos()
            dev.sleep(0.25)
            p1 = mean_pos()
            speed = np.abs(p1 - p0) / max(dev.time() - t0, 1e-9)
            if np.all(speed <= max_speed):
                return p1
            if deadline.expired():
                a, v = max(zip((a1, a2), speed), key=lambda av: av[1])
                raise ExperimentError(f"axis{a} still turns at {v:.3f} turn/s after {patience:g} s: the leg "
                                      f"is not at rest; zeroing needs it resting on its stop")


def zero_joints(odrv, settle: float = 1.0, max_speed: float = 0.01) -> tuple[float, float]:
    """Define the joint angles: with both axes IDLE and the leg resting on its stop (the
    rest pose, q = leg.q0, thesis 5.3), read ``pos_estimate`` of both motors and take it as
    the rest pose (Listing 7.4 zeroes its angles at the start in the same way).

    Waits ``settle`` s first; refuses when a motor still turns faster than ``max_speed``
    turn/s. Returns the motor positions [turn] (joint 0's motor, joint 1's motor). The
    leg rests anywhere within its friction dead band (about 1 deg of joint here): that is
    the accuracy of the zero.
    """
    dev = as_device(odrv)
    turns = _rest_positions(dev, settle, max_speed)
    dev.axes = dev.axes.zeroed(turns)
    return float(turns[0]), float(turns[1])


def apply_gains(odrv, gains, save: bool = True, timeout: float = 10.0):
    """Write (pos_gain, vel_gain, vel_integrator_gain) to both axes and read them back; with
    ``save`` store them on the ODrive so they survive a power cycle (axes IDLE,
    ``save_configuration``, the reboot and the reconnection by serial number handled).

    Returns the device (the same :class:`Device`, rebound to the new connection after a
    reboot; on 0.5.2+ it must be calibrated again before it moves).
    """
    dev = as_device(odrv)
    g = tuple(gains) if not isinstance(gains, (str, bytes)) else ()
    if len(g) != 3:
        raise ValueError(f"gains must be (pos_gain, vel_gain, vel_integrator_gain), got {gains!r}")
    _check_gains(dev.config, *g)
    keys = ("pos_gain", "vel_gain", "vel_integrator_gain")
    with safe(dev):
        for a in (0, 1):
            for key, value in zip(keys, g):
                dev.set(a, key, float(value))
                back = float(dev.get(a, key))
                if not math.isclose(back, float(value), rel_tol=1e-6, abs_tol=1e-12):
                    raise ExperimentError(f"axis{a}.{key}: wrote {value}, device reports {back}")
        if save:
            _save_and_reconnect(dev, timeout)
            for a in (0, 1):
                for key, value in zip(keys, g):
                    back = float(dev.get(a, key))
                    if not math.isclose(back, float(value), rel_tol=1e-6, abs_tol=1e-12):
                        raise ExperimentError(f"axis{a}.{key}: saved {value}, the rebooted device reports {back}")
    return dev


def _check_gains(cfg: OdriveConfig, pos_gain, vel_gain, vel_integrator_gain):
    for name, value, high in (("pos_gain", pos_gain, cfg.max_pos_gain),
                              ("vel_gain", vel_gain, cfg.max_vel_gain),
                              ("vel_integrator_gain", vel_integrator_gain, cfg.max_vel_integrator_gain)):
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)) \
                or not math.isfinite(value):
            raise ValueError(f"{name} must be a finite number, got {value!r}")
        if not 0.0 <= value <= high:
            raise ValueError(f"{name} = {value} is outside the allowed range [0, {high}] "
                             f"({cfg.source_file}, [experiment] max_{name})")


# ---------------------------------------------------------------------------------------
# Listing 7.4: step responses and sweeps
# ---------------------------------------------------------------------------------------

_STEP_FIELDS = {"experiment": "step_response"}   # in every step response's sidecar


@dataclass
class StepResponse:
    """A position step response of the leg.

    ``t`` [s], ``q1``, ``q2`` [rad] absolute joint angles, ``y`` [m] foot height (exact
    five-bar), ``gains`` (pos_gain, vel_gain, vel_integrator_gain); ``completed`` is False
    when the safety abort stopped it (``abort_reason`` says why): such a point is unstable
    and has no damping value.
    """

    t: np.ndarray
    q1: np.ndarray
    q2: np.ndarray
    y: np.ndarray
    gains: tuple
    step: float
    completed: bool = True
    abort_reason: str | None = None
    meta: dict = field(default_factory=dict)

    def write(self, out_dir, when=None) -> Path:
        """Write as a measurement file (CSV + sidecar) in ``out_dir``."""
        meta = {**_STEP_FIELDS, "step_turns": self.step, "completed": self.completed,
                "abort_reason": self.abort_reason, **self.meta}
        return dataio.write_measurement(out_dir, self.t, np.degrees(self.q1), np.degrees(self.q2),
                                        meta, gains=self.gains, when=when)

    @classmethod
    def from_measurement(cls, m: "dataio.Measurement", leg: LegParams) -> "StepResponse":
        """Rebuild from a file; thesis files (relative angles) are placed at the rest pose."""
        return cls.from_measurements([m], leg)[0]

    @classmethod
    def from_measurements(cls, measurements, leg: LegParams) -> list["StepResponse"]:
        """:meth:`from_measurement` of each file, the foot heights of all in one call."""
        measurements = list(measurements)
        if not measurements:
            return []
        # all files' angles at once (elementwise: the same numbers as file by file)
        cuts = np.cumsum([m.angle1.size for m in measurements])[:-1]
        Q1 = np.concatenate([m.angle1 for m in measurements])
        Q2 = np.concatenate([m.angle2 for m in measurements])
        np.radians(Q1, out=Q1)   # (in place: fewer fresh pages)
        np.radians(Q2, out=Q2)
        for m, a, b in zip(measurements, np.concatenate([[0], cuts]), np.concatenate([cuts, [Q1.size]])):
            if not m.absolute:
                # Listing 7.4 zeroes the angles at the start and records 360/cpr/3 * counts of
                # the motor, i.e. joint angle changes in the motor's sense: convert to joint
                Q1[a:b] = leg.q1 + leg.direction * Q1[a:b]
                Q2[a:b] = leg.q2 + leg.direction * Q2[a:b]
        _, Y = foot_position(leg, Q1, Q2)
        return [cls(t=m.t - m.t[0], q1=q1, q2=q2, y=y, gains=m.gains, step=m.meta.get("step_turns", 0.4),
                    completed=m.stable, abort_reason=m.meta.get("abort_reason"), meta=m.meta)
                for m, q1, q2, y in zip(measurements, np.split(Q1, cuts), np.split(Q2, cuts), np.split(Y, cuts))]


def _prepare_closed_loop(dev: Device, vel_limit: float, watchdog: float | None) -> None:
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
    if _any_error(dev):
        raise ExperimentError(f"an earlier fault is still flagged ({describe_errors(errors(dev))}); inspect it, then call "
                              f"leglib.odrive_io.clear_errors(odrv)")
    for a in (0, 1):
        if not (bool(dev.get(a, "is_calibrated")) and bool(dev.get(a, "is_ready"))):
            raise ExperimentError(f"axis{a} is not calibrated (motor.is_calibrated, encoder.is_ready): "
                                  f"run leglib.odrive_io.calibrate(odrv) first")
    for a in (0, 1):
        dev.set(a, "current_lim", dev.config.current_lim)
        dev.set(a, "vel_limit", vel_limit)
        if watchdog:
            dev.set(a, "watchdog_timeout", watchdog)
            dev.axis(a).watchdog_feed()
            dev.set(a, "enable_watchdog", True)
        else:
            dev.set(a, "enable_watchdog", False)


def _enter_closed_loop(dev: Device) -> None:
    """Request closed loop on both axes and wait until both are in it: the request is taken
    up by the axis thread about 1 ms later, and entering sets ``input_pos := pos_estimate``
    (axis.cpp:290-291, 455-488), so targets are written only after this returns."""
    for a in (0, 1):
        dev.set(a, "requested_state", AXIS_STATE_CLOSED_LOOP_CONTROL)
    _wait_states(dev, (0, 1), AXIS_STATE_CLOSED_LOOP_CONTROL, what="entering closed loop")
    for a in (0, 1):
        dev.axis(a).watchdog_feed()


@functools.lru_cache(maxsize=None)
def _abort_reason_of(code: int) -> str | None:
    from . import twin as T
    return {T.ABORT_NONE: None, T.ABORT_POSITION_ERROR: "position error past bound",
            T.ABORT_NONFINITE: "simulation left the valid configuration",
            T.ABORT_OSCILLATION: "oscillation not decaying (growing or sustained)"}[int(code)]


def _batch_points(dev: Device, gains, out: dict):
    """A twin batch's points: joint angles Q1, Q2 (B, samples) [rad] of all at once
    (elementwise: the same numbers as one by one), times from zero, the fields every
    point's sidecar shares, and per point (gains, samples kept, completed, abort reason)."""
    ax = dev.axes
    a1, a2 = ax.axis_of_joint
    Q1 = ax.counts_to_joint(out["counts"][:, :, a1], 0)
    Q2 = ax.counts_to_joint(out["counts"][:, :, a2], 1)
    t = out["t"] - out["t"][0]
    period = out["t"][1] - out["t"][0]
    points = []
    faulted = np.any(out["axis_error"], axis=1).tolist()
    ticks, codes = out["abort_tick"].tolist(), out["abort_reason"].tolist()
    for i, g in enumerate(np.atleast_2d(gains).tolist()):
        completed = ticks[i] < 0 and not faulted[i]
        reason = _abort_reason_of(codes[i])
        if reason is None and not completed:
            reason = f"axis error 0x{int(out['axis_error'][i].max()):x} (firmware fault)"
        n = len(t) if completed else max(2, int(ticks[i] * dev.sim.twin.dt / max(period, 1e-12)) + 1)
        points.append((tuple(g), min(n, len(t)), bool(completed), reason))
    return Q1, Q2, t, {**dev.describe(), "sample_rate_hz": 1.0 / period}, points


def _responses_from_batch(dev: Device, gains, out: dict, step: float) -> list[StepResponse]:
    Q1, Q2, t, meta, points = _batch_points(dev, gains, out)
    _, Y = foot_position(dev.leg, Q1, Q2)   # all points at once
    return [StepResponse(t=t[:n], q1=Q1[i, :n], q2=Q2[i, :n], y=Y[i, :n], gains=g, step=step,
                         completed=completed, abort_reason=reason, meta=dict(meta))
            for i, (g, n, completed, reason) in enumerate(points)]


def _write_batch(dev: Device, gains, out: dict, step: float, out_dir: Path) -> tuple[Path, int]:
    """A twin batch as one batch file (:func:`leglib.dataio.write_batch`), with the fields
    :meth:`StepResponse.write` gives a point's own file; (its path, the unstable points)."""
    Q1, Q2, t, meta, points = _batch_points(dev, gains, out)
    D1, D2 = np.degrees(Q1, out=Q1), np.degrees(Q2, out=Q2)   # (in place: fewer fresh pages)
    series = [(t[:n], D1[i, :n], D2[i, :n], g, {"completed": completed, "abort_reason": reason})
              for i, (g, n, completed, reason) in enumerate(points)]
    path = dataio.write_batch(out_dir, series, {**_STEP_FIELDS, "step_turns": step, **meta})
    return path, sum(not completed for _, _, completed, _ in points)


def _step_usb(dev: Device, gains, step, duration, sample_period, vel_limit, abort_error,
              on_sample=None) -> StepResponse:
    """Listing 7.4 on a real device (and on a real-time twin): a paced polling loop with
    safety checks. Completed only when no abort and no firmware error happened."""
    from . import twin as T
    ax = dev.axes
    a_q1, a_q2 = ax.axis_of_joint
    ts, c1, c2 = [], [], []
    reason = None
    with safe(dev):
        _prepare_closed_loop(dev, vel_limit, watchdog=max(0.5, 5 * sample_period))
        for a in (0, 1):
            dev.set(a, "pos_gain", gains[0])
            dev.set(a, "vel_gain", gains[1])
            dev.set(a, "vel_integrator_gain", gains[2])
            dev.set(a, "control_mode", CONTROL_MODE_POSITION)
            dev.set(a, "input_mode", INPUT_MODE_PASSTHROUGH)
        _enter_closed_loop(dev)
        start_pos = {a: float(dev.get(a, "pos_estimate")) for a in (0, 1)}
        target = {a_q1: start_pos[a_q1] + step, a_q2: start_pos[a_q2] - step}
        for a in (0, 1):
            dev.set(a, "input_pos", target[a])
        setpoint = (float(ax.joint_angle(target[a_q1], 0)), float(ax.joint_angle(target[a_q2], 1)))
        t0 = dev.time()
        monitors = {a: np.zeros(T.N_OSC) for a in (0, 1)}
        next_sample = 0.0
        # each property is one USB transaction (about 0.4 ms): read the counts every sample
        # and do one housekeeping transaction per sample, in turn: feed axis 0, feed axis 1,
        # check the state of axis 0, of axis 1
        k = 0
        dropped = None
        while True:
            now = dev.time() - t0
            if now > duration:
                break
            if now < next_sample:
                dev.sleep(min(next_sample - now, sample_period))
                continue
            # the next slot on the grid; slots already missed are skipped, not caught up in a burst
            next_sample += sample_period * max(1, math.ceil((now - next_sample) / sample_period + 1e-9))
            n1, n2 = dev.counts(a_q1), dev.counts(a_q2)
            ts.append(dev.time() - t0)
            c1.append(n1)
            c2.append(n2)
            task, k = k % 4, k + 1
            if task < 2:
                dev.axis(task).watchdog_feed()
            elif int(dev.get(task - 2, "current_state")) != AXIS_STATE_CLOSED_LOOP_CONTROL:
                dropped = task - 2
            if on_sample is not None:
                on_sample({"t": ts[-1], "q1": float(ax.counts_to_joint(n1, 0)),
                           "q2": float(ax.counts_to_joint(n2, 1)), "iq": None, "setpoint": setpoint})
            # safety, as the twin's kernel: position error bound and non-decaying oscillation
            errs = {a_q1: target[a_q1] - n1 / ax.cpr, a_q2: target[a_q2] - n2 / ax.cpr}
            if max(abs(e) for e in errs.values()) > abort_error:
                reason = "position error past bound"
                break
            if any(T.oscillation_update(monitors[a], errs[a], 0.025 * abort_error) for a in (0, 1)):
                reason = "oscillation not decaying (growing or sustained)"
                break
            if dropped is not None:
                reason = f"axis{dropped} dropped out of closed loop ({describe_errors(errors(dev))})"
                break
        if reason is None and _any_error(dev):
            reason = f"firmware error during the step ({describe_errors(errors(dev))})"
        if reason is None and len(ts) < 2:
            reason = "fewer than two samples were taken"
    t = np.asarray(ts)
    q1 = ax.counts_to_joint(np.asarray(c1), 0)
    q2 = ax.counts_to_joint(np.asarray(c2), 1)
    _, y = foot_position(dev.leg, q1, q2)
    rate = (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 else float("nan")
    return StepResponse(t=t, q1=q1, q2=q2, y=y, gains=tuple(map(float, gains)), step=step,
                        completed=reason is None, abort_reason=reason,
                        meta={**dev.describe(), "sample_rate_hz": rate})


def _check_step(dev: Device, step, duration, sample_period, vel_limit) -> None:
    def number(name, value):
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)) \
                or not math.isfinite(value):
            raise ValueError(f"{name} must be a finite number, got {value!r}")
    number("duration", duration)
    number("sample_period", sample_period)
    number("step", step)
    if not (0 < duration <= 30):
        raise ValueError(f"duration must be in (0, 30] s, got {duration}")
    if not (0 < sample_period < duration):
        raise ValueError(f"sample_period must be positive and shorter than duration ({duration} s), "
                         f"got {sample_period}")
    if not (0 < abs(step) <= 1.0):
        raise ValueError(f"step must be a non-zero motor step of at most 1 turn, got {step}")
    if abs(step) * dev.axes.cpr < 2:
        raise ValueError(f"step = {step} turn is below the encoder's resolution (1/{dev.axes.cpr} turn): "
                         f"at least 2 counts are needed")
    if vel_limit is not None:
        number("vel_limit", vel_limit)
        high = dev.config.step_vel_limit
        if not 0 < vel_limit <= high:
            raise ValueError(f"vel_limit must be in (0, {high}] turn/s, got {vel_limit} "
                             f"({dev.config.source_file}: step_vel_limit, the experiments' safety bound)")


def step_response(odrv, pos_gain: float, vel_gain: float, vel_integrator_gain: float,
                  step: float = 0.4, duration: float = 1.5, sample_period: float = 0.002,
                  vel_limit: float | None = None, settle: float = 2.0, on_sample=None) -> StepResponse:
    """Listing 7.4's position step with the given gains, from the leg at rest.

    The axis driving q1 moves by +``step`` motor turns, the other by -``step``. Gains are
    refused outside the configured bounds. The experiment aborts, sets IDLE and marks the
    response not completed when the position error passes 2*|step|, the oscillation stops
    decaying (three half-cycles in a row no smaller than the one before), or any firmware
    error is raised during it. Afterwards the axes are IDLE and the leg is left ``settle``
    s to come to rest.

    On the twin the step runs whole in the compiled kernel (a batch of one, the same path
    :func:`sweep` uses for many); on USB, and on a twin running in real time
    (``realtime=True``), it is a paced polling loop.

    ``on_sample``, when given, is called from the polling loop as ``on_sample(sample)`` with
    ``{"t": s, "q1": rad, "q2": rad, "iq": None, "setpoint": (q1, q2) rad}`` (a live view).
    It runs between samples and must be cheap (well under ``sample_period``): a slow
    callback delays the next sample. On the compiled (non-real-time) path it is not called.
    """
    dev = as_device(odrv)
    _check_gains(dev.config, pos_gain, vel_gain, vel_integrator_gain)
    _check_step(dev, step, duration, sample_period, vel_limit)
    if on_sample is not None and not callable(on_sample):
        raise TypeError(f"on_sample must be callable, got {on_sample!r}")
    gains = (float(pos_gain), float(vel_gain), float(vel_integrator_gain))
    vl = dev.config.step_vel_limit if vel_limit is None else vel_limit
    sim = dev.sim
    if sim is not None and not sim.realtime:
        with safe(dev):
            _prepare_closed_loop(dev, vl, watchdog=None)
            out = sim.step_batch(np.array([gains]), step_turns=step, duration=duration,
                                 sample_period=sample_period, vel_limit=vl,
                                 abort_error_turns=2 * abs(step))
        return _responses_from_batch(dev, [gains], out, step)[0]
    resp = _step_usb(dev, gains, step, duration, sample_period, vl, 2 * abs(step), on_sample=on_sample)
    dev.sleep(settle)
    return resp


@dataclass
class SweepResult:
    """What :func:`sweep` did: files written now (``written``; a twin batch is one file of
    many points) and the points ``measured`` now, points skipped (already measured, here or
    meanwhile by another writer), unstable points, and files set aside into
    ``incomplete/`` (damaged or unfinished; their points were measured again)."""

    written: list[Path]
    skipped: int
    unstable: int
    out_dir: Path
    set_aside: list[Path] = field(default_factory=list)
    measured: int = 0   # points measured now (a twin batch writes many into one file)

    @property
    def paths(self) -> list[Path]:
        return dataio.list_measurements(self.out_dir)


def thesis_grid() -> np.ndarray:
    """Listing 7.4's grid: pos_gain 20..50 (4), vel_gain 0.002..0.18 (10),
    vel_integrator_gain 0.002..0.08 (10): (400, 3)."""
    pos = np.linspace(20, 50, 4)
    vel = np.linspace(0.002, 0.18, 10)
    vint = np.linspace(0.002, 0.08, 10)
    return np.array([(p, v, i) for p in pos for v in vel for i in vint])


def sweep(odrv, grid, out_dir: str | Path, resume: bool = True, progress: bool = True,
          step: float = 0.4, duration: float = 1.5, sample_period: float = 0.002,
          chunk: int = 400) -> SweepResult:
    """Measure a step response for every (pos_gain, vel_gain, vel_integrator_gain) in
    ``grid`` and write them as measurement files in ``out_dir``: on the twin each batch of
    points as one batch file (:func:`leglib.dataio.write_batch`), on a real leg each point
    as its own file, as it is measured.

    Resumable: a point is done when a readable measurement with exactly its gains exists
    (``resume=False`` refuses a non-empty directory instead). Files that cannot be read
    (damaged, or the orphan of an interrupted write) and uncommitted leftovers are moved to
    ``out_dir/incomplete/`` and their points measured again. The directory's provenance
    (``sweep.json``: the device's identity from ``Device.describe()`` -- backend, serial,
    firmware, twin seed and plant with its payload -- and step, duration, sample period) is
    written by the first sweep; resuming with another leg or experiment raises
    :class:`leglib.dataio.ProvenanceError` before anything is measured.

    Each point is claimed (:func:`leglib.dataio.claim`) while it is measured and written,
    so two sweeps into one directory share the grid: neither loses nor duplicates a point.
    Each file is committed when its point is done, so an interruption (exception, lost
    device, KeyboardInterrupt) loses no finished point; the axes go IDLE whatever happens.
    On the twin, pending points run in batches of ``chunk`` through the compiled kernel
    (the thesis grid in one: a batch costs a fixed setup, and the kernel shares a batch
    out best when it is large); a batch's file is not flushed to disk by itself, only its
    directory at the batch's end (:func:`leglib.dataio.deferred_sync`: after a power loss
    it may be missing or cut, which the reader refuses and a resumed sweep measures
    again); on USB one after the other, each file flushed as it is written.
    """
    import os

    from tqdm.auto import tqdm

    dev = as_device(odrv)
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise NotADirectoryError(f"{out_dir}: not a directory (a file is in the way)") from None
    if not os.access(out_dir, os.W_OK | os.X_OK):
        raise PermissionError(f"{out_dir}: directory not writable")
    grid = np.atleast_2d(np.asarray(list(grid), dtype=float))
    if grid.shape[1] != 3:
        raise ValueError(f"grid must hold (pos_gain, vel_gain, vel_integrator_gain) triples, "
                         f"got shape {grid.shape}")
    for g in grid:
        _check_gains(dev.config, *g)
    record = {"device": dev.describe(),
              "experiment": {"step": step, "duration": duration, "sample_period": sample_period,
                             "step_vel_limit": dev.config.step_vel_limit}}
    existing = dataio.list_measurements(out_dir)
    if existing and not resume:
        raise FileExistsError(f"{out_dir} already holds {len(existing)} measurements; pass resume=True "
                              f"to complete the sweep, or choose an empty directory")
    dataio.check_provenance(out_dir, record, write=True)

    set_aside: list[Path] = []
    done: set = set()
    done_rounded: set = set()
    for p in existing:
        try:
            found = dataio.read_file(p)
        except dataio.MeasurementError:
            set_aside.append(dataio.set_aside(p))  # damaged or unfinished: measured again
            continue
        for m in found:
            if m.gains is not None:
                done.add(tuple(float(x) for x in m.gains))
                if not m.meta.get("gains"):  # a thesis file: its name holds three decimals only
                    done_rounded.add(dataio.gains_key(m.gains))
    for p in dataio.find_uncommitted(out_dir):
        g = dataio.uncommitted_claim_key(p)
        c = dataio.claim(out_dir, g) if g is not None else None
        if c is not None:  # its writer is gone (a live writer holds the claim)
            # a sidecar whose CSV appeared meanwhile was committed by a writer that has
            # finished since it was listed: it stays
            committed = p.suffix == ".json" and os.path.lexists(p.with_suffix(".csv"))
            if os.path.lexists(p) and not committed:
                set_aside.append(dataio.set_aside(p))
            c.release()

    pending, seen = [], set(done)
    for g in grid:
        k = tuple(float(x) for x in g)
        if k not in seen and dataio.gains_key(g) not in done_rounded:
            seen.add(k)
            pending.append(g)
    skipped = len(grid) - len(pending)
    written: list[Path] = []
    unstable = measured = 0
    vl = dev.config.step_vel_limit
    size = chunk if dev.backend == "virtual" else 1
    bar = tqdm(total=len(grid), initial=skipped, desc="sweep", unit="step", disable=not progress)
    queue = pending
    claims: list = []
    try:
        with safe(dev):
            batched = dev.sim is not None and not dev.sim.realtime
            if batched:
                _prepare_closed_loop(dev, vl, watchdog=None)
            else:
                size = 1
            while queue:
                held, taken = dataio.claim_many(out_dir, queue, limit=size)
                claims.append(held)
                block = [g for g, ok in zip(queue, taken) if ok]
                waiting = [g for g, ok in zip(queue, taken) if not ok]
                if block:  # a point another writer committed meanwhile is done
                    now = dataio.committed_gains(out_dir)
                    keep = [tuple(float(x) for x in g) not in now for g in block]
                    skipped += keep.count(False)
                    bar.update(keep.count(False))
                    block = [g for g, k in zip(block, keep) if k]
                if not block and waiting:
                    # every point left is being measured by another writer: wait for one
                    for c in claims:
                        c.release()
                    claims = []
                    dataio.claim(out_dir, waiting[0], wait=True).release()
                    queue = waiting
                    continue
                if block:
                    if batched:
                        # the twin's batch: one batch file, its directory flushed at the
                        # end (dataio.deferred_sync)
                        arr = np.array(block)
                        out = dev.sim.step_batch(arr, step_turns=step, duration=duration,
                                                 sample_period=sample_period, vel_limit=vl,
                                                 abort_error_turns=2 * abs(step))
                        with dataio.deferred_sync():
                            path, bad = _write_batch(dev, arr, out, step, out_dir)
                        written.append(path)
                        unstable += bad
                    else:
                        # a real leg's measurement: its own file, flushed as it is written
                        resp = step_response(dev, *block[0], step=step, duration=duration,
                                             sample_period=sample_period)
                        written.append(resp.write(out_dir))
                        unstable += not resp.completed
                    measured += len(block)
                    bar.update(len(block))
                    if _any_error(dev):   # recorded with the failed point; the sweep goes on
                        clear_errors(dev)
                for c in claims:
                    c.release()
                claims = []
                queue = waiting
    finally:
        for c in claims:
            c.release()
        bar.close()
    return SweepResult(written=written, skipped=skipped, unstable=unstable, out_dir=out_dir,
                       set_aside=set_aside, measured=measured)


# ---------------------------------------------------------------------------------------
# Listing 7.3: torque playback
# ---------------------------------------------------------------------------------------

@dataclass
class TorqueRun:
    """A played-back torque table: actual sample times ``t`` [s], joint angles ``q1``,
    ``q2`` [rad], commanded joint torques ``tau`` (n, 2) [N*m], measured ``iq`` (n, 2) [A]
    per axis, and the achieved loop rate [Hz]."""

    t: np.ndarray
    q1: np.ndarray
    q2: np.ndarray
    tau: np.ndarray
    iq: np.ndarray
    rate_hz: float
    meta: dict = field(default_factory=dict)
    table: np.ndarray | None = None
    period: float = 0.002
    t_cmd: np.ndarray | None = None   # (n, 2) when each joint's torque was written [s]
    t_read: np.ndarray | None = None  # (n, 2) when each joint's angle was read [s]

    def applied_torque(self, t_grid, bandwidth: float | None = None) -> np.ndarray:
        """Joint torque (M, 2) [N*m] at ``t_grid`` as the motors produced it: each written
        value held from its write time, through the current loop's first-order lag
        (``bandwidth`` [rad/s], default the run's configuration). Without write times
        (thesis files) the table is assumed to apply on schedule."""
        t_grid = np.asarray(t_grid, dtype=float)
        if self.t_cmd is not None and len(self.t_cmd) == len(self.tau):
            u = np.empty((t_grid.size, 2))
            for j in (0, 1):
                k = np.searchsorted(self.t_cmd[:, j], t_grid, side="right") - 1
                u[:, j] = np.where(k >= 0, self.tau[np.clip(k, 0, None), j], 0.0)
        else:
            rows = np.clip((t_grid / self.period).astype(int), 0, len(self.table) - 1)
            u = self.table[rows]
        wc = bandwidth or self.meta.get("current_control_bandwidth")
        if not wc:
            return u
        y = np.empty_like(u)
        acc = np.zeros(2)
        for i in range(len(t_grid)):
            h = t_grid[i] - t_grid[i - 1] if i else 0.0
            acc = acc + (1 - math.exp(-wc * h)) * (u[i] - acc)
            y[i] = acc
        return y

    def write(self, out_dir, when=None) -> Path:
        """Write as Listing 7.3 did: ``<stamp>_positions.csv`` (time, q1, q2 [deg]) with a
        JSON sidecar, and ``<stamp>_torque.csv`` (time, tau1, tau2 [N*m]) of the table."""
        meta = {"experiment": "torque_playback", "period_s": self.period, "rate_hz": self.rate_hz,
                **self.meta}
        for name in ("t_cmd", "t_read"):
            value = getattr(self, name)
            if value is not None:
                meta[name] = np.round(value, 7).tolist()
        path = dataio.write_measurement(out_dir, self.t, np.degrees(self.q1), np.degrees(self.q2),
                                        meta, when=when)
        if self.table is not None:
            tt = self.period * np.arange(len(self.table))
            dataio.write_table(path.with_name(path.name.replace("_positions.csv", "_torque.csv")),
                               np.column_stack([tt, self.table]))
        return path

    @classmethod
    def read(cls, path) -> "TorqueRun":
        """Read a torque run written by :meth:`write` (positions, sidecar and table)."""
        m = dataio.read_measurement(path)
        table_path = Path(path).with_name(Path(path).name.replace("_positions.csv", "_torque.csv"))
        table = dataio.read_table(table_path, columns=3)
        period = float(m.meta.get("period_s", table[1, 0] - table[0, 0]))
        rows = np.minimum((m.t / period).astype(int), len(table) - 1)
        extra = {k: np.asarray(m.meta[k]) for k in ("t_cmd", "t_read") if k in m.meta}
        return cls(t=m.t, q1=np.radians(m.angle1), q2=np.radians(m.angle2), tau=table[rows, 1:],
                   iq=np.full((m.t.size, 2), np.nan), rate_hz=float(m.meta.get("rate_hz", np.nan)),
                   meta=m.meta, table=table[:, 1:], period=period, **extra)


def torque_loop(odrv, policy, duration: float, period: float | None = None,
                max_joint_speed: float = 20.0, meta: dict | None = None,
                record_current: bool = True, check_every: int = 1, on_sample=None) -> TorqueRun:
    """Both joints in torque control; each cycle reads the joint angles, asks
    ``policy(t, q1, q2) -> (tau1, tau2)`` [N*m at the joints] and writes the torques.

    With ``period`` the cycles are paced to t = k * period (a controller's sample time);
    without, the loop runs as fast as the link allows (the thesis's playback). Records the
    actual read and write time of every value. Aborts to IDLE when a joint moves faster
    than ``max_joint_speed`` rad/s or an axis drops out of closed loop (checked every
    ``check_every`` cycles; each check and each Iq read costs a USB transaction), and when
    the firmware flags an error during the run.

    ``on_sample``, when given, is called every cycle as ``on_sample(sample)`` with
    ``{"t": s, "q1": rad, "q2": rad, "iq": (A, A) or None, "setpoint": None}`` (a live
    view). It runs inside the loop and must be cheap: a slow callback lowers the loop rate.
    """
    dev = as_device(odrv)
    for name, value in (("duration", duration), ("max_joint_speed", max_joint_speed)):
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
                or not math.isfinite(value) or value <= 0:
            raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    if period is not None and (isinstance(period, bool) or not math.isfinite(period) or not 0 < period < duration):
        raise ValueError(f"period must be positive and shorter than duration ({duration} s), got {period!r}")
    if on_sample is not None and not callable(on_sample):
        raise TypeError(f"on_sample must be callable, got {on_sample!r}")
    ax = dev.axes
    a_q1, a_q2 = ax.axis_of_joint
    limit = dev.config.current_lim * dev.config.torque_constant
    ts, t_cmd, t_read, c1, c2, iq, applied = [], [], [], [], [], [], []
    with safe(dev):
        _prepare_closed_loop(dev, dev.config.vel_limit, watchdog=0.2)
        for a in (0, 1):
            dev.set(a, "input_torque", 0.0)
            dev.set(a, "control_mode", CONTROL_MODE_TORQUE)
            dev.set(a, "input_mode", INPUT_MODE_PASSTHROUGH)
        _enter_closed_loop(dev)
        t0 = dev.time()
        k = 0
        prev = None
        while True:
            now = dev.time() - t0
            if period is not None and now < k * period:
                dev.sleep(k * period - now)
                now = dev.time() - t0
            if now > duration:
                break
            if period is not None:   # slots already missed are skipped, not caught up in a burst
                k = max(k, math.floor(now / period + 1e-9))
            k += 1
            n1 = dev.counts(a_q1)
            r1 = dev.time() - t0
            n2 = dev.counts(a_q2)
            r2 = dev.time() - t0
            q1, q2 = float(ax.counts_to_joint(n1, 0)), float(ax.counts_to_joint(n2, 1))
            tau = np.asarray(policy(r2, q1, q2), dtype=float)
            if tau.shape != (2,) or not np.all(np.isfinite(tau)):
                raise ExperimentError(f"policy returned {tau!r} at t = {r2:.3f} s; expected two finite torques")
            motor = ax.motor_torque(tau)
            dev.set(a_q1, "input_torque", float(np.clip(motor[0], -limit, limit)))
            w1 = dev.time() - t0
            dev.set(a_q2, "input_torque", float(np.clip(motor[1], -limit, limit)))
            w2 = dev.time() - t0
            t_cmd.append((w1, w2))
            t_read.append((r1, r2))
            ts.append(r2)
            c1.append(n1)
            c2.append(n2)
            applied.append(ax.joint_torque(np.clip(motor, -limit, limit)))
            if record_current:
                iq.append((float(dev.get(a_q1, "Iq_measured")), float(dev.get(a_q2, "Iq_measured"))))
            else:
                iq.append((math.nan, math.nan))
            # one USB transaction each: feed the watchdog (0.2 s) every 10th cycle, axes in turn
            if k % 10 in (0, 5):
                dev.axis(0 if k % 10 == 0 else 1).watchdog_feed()
            if on_sample is not None:
                on_sample({"t": r2, "q1": q1, "q2": q2,
                           "iq": None if not record_current else tuple(iq[-1]), "setpoint": None})
            if prev is not None and ts[-1] > prev[0]:
                speed = max(abs(n1 - prev[1]), abs(n2 - prev[2])) / ax.cpr * 2 * math.pi / ax.gear_ratio / (ts[-1] - prev[0])
                if speed > max_joint_speed:
                    raise ExperimentError(f"joint speed {speed:.1f} rad/s exceeds {max_joint_speed} rad/s "
                                          f"at t = {ts[-1]:.3f} s: aborted, axes IDLE")
            prev = (ts[-1], n1, n2)
            if k % check_every == 0:
                for a in (a_q1, a_q2) if check_every == 1 else (a_q1,):
                    if int(dev.get(a, "current_state")) != AXIS_STATE_CLOSED_LOOP_CONTROL:
                        raise ExperimentError(f"axis{a} dropped out of closed loop at t = {ts[-1]:.3f} s: "
                                              f"{_error_text(dev, a)}")
        for a in (0, 1):
            dev.set(a, "input_torque", 0.0)
        if _any_error(dev):
            raise ExperimentError(f"a firmware error was raised during the run: {describe_errors(errors(dev))}")
    t = np.asarray(ts)
    rate = (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 else float("nan")
    return TorqueRun(t=t, q1=ax.counts_to_joint(np.asarray(c1), 0), q2=ax.counts_to_joint(np.asarray(c2), 1),
                     tau=np.asarray(applied), iq=np.asarray(iq), rate_hz=rate,
                     meta={**dev.describe(), "current_control_bandwidth": dev.config.current_control_bandwidth,
                           **(meta or {})},
                     period=period if period is not None else float(np.median(np.diff(t))) if len(t) > 1 else 0.0,
                     t_cmd=np.asarray(t_cmd), t_read=np.asarray(t_read))


def play_torque_table(odrv, tau, period: float = 0.002, duration: float | None = None,
                      max_joint_speed: float = 20.0) -> TorqueRun:
    """Play joint torques ``tau`` (N, 2) [N*m], one row per ``period`` s, on both joints in
    torque control (Listing 7.3), recording the actual timestamps, joint angles and Iq.

    The loop runs as fast as the link allows; rows are chosen by elapsed time, as in the
    thesis (see :func:`torque_loop` for the safety checks).
    """
    dev = as_device(odrv)
    tau = np.asarray(tau, dtype=float)
    if tau.ndim != 2 or tau.shape[1] != 2 or len(tau) < 1 or not np.all(np.isfinite(tau)):
        raise ValueError(f"tau must be a finite (N, 2) table of joint torques, got shape {tau.shape}")
    if period <= 0:
        raise ValueError(f"period must be positive, got {period}")
    duration = len(tau) * period if duration is None else duration
    limit = dev.config.current_lim * dev.config.torque_constant
    peak = float(np.max(np.abs(dev.axes.motor_torque(tau))))
    if peak > limit:
        warnings.warn(f"torque table asks up to {peak:.3f} N*m at the motor; the current limit "
                      f"allows {limit:.3f} N*m: it will saturate", stacklevel=2)
    run = torque_loop(dev, lambda t, q1, q2: tau[min(int(t / period), len(tau) - 1)], duration,
                      max_joint_speed=max_joint_speed, meta={"experiment": "torque_playback"})
    run.table = tau
    run.period = period
    return run


def return_to_rest(odrv, pos_gain: float = 20.0, vel_gain: float = 0.05, vel_integrator_gain: float = 0.3,
                   move_time: float = 2.0, settle: float = 0.5) -> tuple[float, float]:
    """Bring the leg back to its rest pose (the zeroed motor positions, see
    :func:`zero_joints`) with soft position control, then IDLE and let it settle. Returns
    the joint angles [rad] it ends at. Experiments that start "from rest" call it between
    runs on a real bench.

    The leg is held under the watchdog (:data:`HOLD_WATCHDOG` s, fed every
    :data:`HOLD_FEED_PERIOD` s): a link lost or an interrupt while it holds leaves both axes
    IDLE within the watchdog time, as in every other experiment."""
    dev = as_device(odrv)
    _check_gains(dev.config, pos_gain, vel_gain, vel_integrator_gain)
    for name, value in (("move_time", move_time), ("settle", settle)):
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
                or not math.isfinite(value) or not 0 <= value <= 60:
            raise ValueError(f"{name} must be a number of seconds in [0, 60], got {value!r}")
    with safe(dev):
        _prepare_closed_loop(dev, min(dev.config.vel_limit, 2.0), watchdog=HOLD_WATCHDOG)
        for a in (0, 1):
            dev.set(a, "pos_gain", pos_gain)
            dev.set(a, "vel_gain", vel_gain)
            dev.set(a, "vel_integrator_gain", vel_integrator_gain)
            dev.set(a, "control_mode", CONTROL_MODE_POSITION)
            dev.set(a, "input_mode", INPUT_MODE_PASSTHROUGH)
        _enter_closed_loop(dev)
        for j, a in enumerate(dev.axes.axis_of_joint):
            dev.set(a, "input_pos", dev.axes.zero[j])
        _hold(dev, move_time)
    dev.sleep(settle)
    a1, a2 = dev.axes.axis_of_joint
    return float(dev.axes.counts_to_joint(dev.counts(a1), 0)), float(dev.axes.counts_to_joint(dev.counts(a2), 1))


# the watchdog of a hold in closed loop (return_to_rest) and how often it is fed [s]: the
# feed period leaves room for a slow USB transaction or a busy host
HOLD_WATCHDOG = 0.5
HOLD_FEED_PERIOD = 0.1


def _hold(dev: Device, seconds: float, feed_period: float = HOLD_FEED_PERIOD) -> None:
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


def sine_torque_table(bias: float = 0.045, amplitude: float = 0.025, freqs=(0.45, 0.7),
                      duration: float = 8.0, ramp: float = 0.5, period: float = 0.002) -> np.ndarray:
    """Joint torques (N, 2) [N*m] of the friction experiment: an opening bias that holds the
    leg off its stops plus a sine on each joint at its own frequency [Hz] (so the two
    joints' friction can be told apart), both faded in over ``ramp`` s."""
    t = period * np.arange(int(round(duration / period)))
    fade = np.clip(t / ramp, 0.0, 1.0) if ramp > 0 else np.ones_like(t)
    open1 = -(bias + amplitude * np.sin(2 * np.pi * freqs[0] * t))   # q1 down opens the leg
    open2 = bias + amplitude * np.sin(2 * np.pi * freqs[1] * t)      # q2 up opens the leg
    return np.column_stack([fade * open1, fade * open2])


def friction_experiment(odrv, bias: float = 0.045, amplitude: float = 0.025, freqs=(0.45, 0.7),
                        duration: float = 8.0, ramp: float = 0.5, period: float = 0.002) -> TorqueRun:
    """Thesis 5.2's experiment: sine torques on both joints (see :func:`sine_torque_table`),
    played back with :func:`play_torque_table`. The defaults move the thesis's leg over
    q2 - q1 of about 15-60 deg without touching its stops."""
    table = sine_torque_table(bias, amplitude, freqs, duration, ramp, period)
    run = play_torque_table(odrv, table, period=period)
    run.meta.update({"bias_Nm": bias, "amplitude_Nm": amplitude, "freqs_hz": list(freqs), "ramp_s": ramp})
    return run
