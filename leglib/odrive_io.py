"""One experiment code for the real leg and its digital twin.

``connect(backend="virtual" | "usb")`` returns a :class:`Device`: the ODrive's object tree
(``dev.axis0.controller.config.pos_gain`` works as on the device) plus what experiments
need: firmware-independent property access (0.5.x and 0.6.x names), the leg's unit
conversions, a clock and a sleep that work on both backends, and fail-safe idling.

Experiments (the thesis listings, done properly): :func:`apply_configuration` (7.1),
:func:`calibrate` (7.2), :func:`play_torque_table` (7.3), :func:`step_response` and
:func:`sweep` (7.4). Every one leaves both axes IDLE, on normal exit, on any exception and
on KeyboardInterrupt.
"""

from __future__ import annotations

import contextlib
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

AXIS_STATE_IDLE = 1
AXIS_STATE_FULL_CALIBRATION_SEQUENCE = 3
AXIS_STATE_CLOSED_LOOP_CONTROL = 8
CONTROL_MODE_TORQUE, CONTROL_MODE_VELOCITY, CONTROL_MODE_POSITION = 1, 2, 3
INPUT_MODE_PASSTHROUGH = 1

# logical property -> path below an axis, per firmware line. None: not available.
_COMMON = {
    "requested_state": "requested_state", "current_state": "current_state", "error": "error",
    "control_mode": "controller.config.control_mode", "input_mode": "controller.config.input_mode",
    "pos_gain": "controller.config.pos_gain", "vel_gain": "controller.config.vel_gain",
    "vel_integrator_gain": "controller.config.vel_integrator_gain",
    "vel_limit": "controller.config.vel_limit", "input_pos": "controller.input_pos",
    "input_vel": "controller.input_vel", "input_torque": "controller.input_torque",
    "controller_error": "controller.error", "motor_error": "motor.error",
    "enable_watchdog": "config.enable_watchdog", "watchdog_timeout": "config.watchdog_timeout",
}
PROPERTY_PATHS = {
    "0.5": {**_COMMON,
            "pos_estimate": "encoder.pos_estimate", "vel_estimate": "encoder.vel_estimate",
            "shadow_count": "encoder.shadow_count", "cpr": "encoder.config.cpr",
            "current_lim": "motor.config.current_lim", "torque_constant": "motor.config.torque_constant",
            "pole_pairs": "motor.config.pole_pairs", "motor_type": "motor.config.motor_type",
            "Iq_measured": "motor.current_control.Iq_measured"},
    "0.6": {**_COMMON,
            "pos_estimate": "pos_estimate", "vel_estimate": "vel_estimate",
            "shadow_count": None, "cpr": None,
            "current_lim": "config.motor.current_soft_max",
            "torque_constant": "config.motor.torque_constant",
            "pole_pairs": "config.motor.pole_pairs", "motor_type": "config.motor.motor_type",
            "Iq_measured": "motor.foc.Iq_measured"},
}


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
        elif (major, minor) >= (0, 6):
            self.firmware = "0.6"
        else:
            raise ExperimentError(f"firmware {major}.{minor} is not supported (0.5.x or 0.6.x)")

    def reconnect(self, timeout: float = 10.0) -> None:
        """Find the same ODrive again after it rebooted (``save_configuration()`` on
        firmware 0.5.2+, ``reboot()``): the old object raises on any access, as on USB.
        Replaces :attr:`raw`; the virtual device is found by its seed, the USB one by its
        serial number."""
        if self.sim is not None:
            from .virtual_odrive import find_any
            opts = {k: v for k, v in self.options.items() if k != "disconnect_after"}
            self.raw = find_any(**opts)
        else:
            serial = getattr(getattr(self.raw, "_dev", None), "serial_number", None)
            self.raw = _find_usb(timeout, serial)
        self._read_firmware_version()

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
        try:
            path = PROPERTY_PATHS[self.firmware][key]
        except KeyError:
            raise KeyError(f"unknown ODrive property {key!r}; known: {sorted(PROPERTY_PATHS['0.5'])}") from None
        if path is None:
            raise ExperimentError(f"property {key!r} does not exist on firmware {self.firmware}.x")
        return path.split(".")

    def get(self, a: int, key: str):
        """Read an axis property by logical name (firmware-independent)."""
        node = self.axis(a)
        for part in self._path(key):
            node = getattr(node, part)
        return node

    def set(self, a: int, key: str, value) -> None:
        """Write an axis property by logical name (firmware-independent)."""
        *head, last = self._path(key)
        node = self.axis(a)
        for part in head:
            node = getattr(node, part)
        setattr(node, last, value)

    def counts(self, a: int) -> int:
        """Encoder counts of axis ``a`` (0.6 has no shadow_count: from pos_estimate)."""
        if self.firmware == "0.5":
            return int(self.get(a, "shadow_count"))
        return int(round(float(self.get(a, "pos_estimate")) * self.axes.cpr))

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
    def idle_all(self) -> list[str]:
        """Request IDLE on both axes; returns the failures (never raises)."""
        failures = []
        for a in (0, 1):
            try:
                self.set(a, "requested_state", AXIS_STATE_IDLE)
            except Exception as exc:  # the link may be gone: the watchdog must then act
                failures.append(f"axis{a}: {type(exc).__name__}: {exc}")
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
    """Both axes IDLE when the block ends: normally, on an exception, on KeyboardInterrupt."""
    try:
        yield dev
    finally:
        dev.idle_all()


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
        allowed = {"seed", "plant", "realtime", "firmware", "disconnect_after", "noise"}
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
    object of a virtual ODrive is recognised as virtual."""
    if isinstance(odrv, Device):
        return odrv
    from .virtual_odrive import VirtualODrive, device_of
    if isinstance(odrv, VirtualODrive):
        raise TypeError("as_device: pass the client object of leglib.virtual_odrive.find_any(), not "
                        "the VirtualODrive model (or use connect('virtual', ...))")
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

def apply_configuration(dev: Device, config: OdriveConfig | None = None, save: bool = True) -> dict:
    """Apply Listing 7.1's configuration to both axes, check it reads back, and save it.

    Returns the values written, per axis.
    """
    dev = as_device(dev)
    cfg = config or dev.config
    written = {}
    with safe(dev):
        for a in (0, 1):
            values = {"current_lim": cfg.current_lim, "vel_limit": cfg.vel_limit,
                      "pole_pairs": cfg.pole_pairs, "torque_constant": cfg.torque_constant,
                      "motor_type": cfg.motor_type}
            if PROPERTY_PATHS[dev.firmware]["cpr"] is not None:
                values["cpr"] = cfg.cpr
            for key, value in values.items():
                dev.set(a, key, value)
                back = dev.get(a, key)
                if not math.isclose(float(back), float(value), rel_tol=1e-6, abs_tol=1e-9):
                    raise ExperimentError(f"axis{a}.{key}: wrote {value}, device reports {back}")
            written[f"axis{a}"] = values
        if dev.firmware == "0.5":
            dev.raw.config.brake_resistance = cfg.brake_resistance
            written["brake_resistance"] = cfg.brake_resistance
        if save:
            dev.raw.save_configuration()
    return written


def calibrate(dev: Device, timeout: float = 60.0, poll: float = 0.1) -> None:
    """Run the full calibration sequence on both axes and wait for it (Listing 7.2).

    Raises ExperimentError naming the axis and its error flags when calibration fails.
    """
    dev = as_device(dev)
    with safe(dev):
        for a in (0, 1):
            dev.set(a, "requested_state", AXIS_STATE_FULL_CALIBRATION_SEQUENCE)
        start = dev.time()
        while True:
            dev.sleep(poll)
            states = [int(dev.get(a, "current_state")) for a in (0, 1)]
            if all(s == AXIS_STATE_IDLE for s in states):
                break
            if dev.time() - start > timeout:
                raise ExperimentError(f"calibration did not finish within {timeout} s (states {states})")
        for a in (0, 1):
            err = int(dev.get(a, "error"))
            if err:
                raise ExperimentError(f"axis{a} calibration failed: axis.error = 0x{err:x} "
                                      f"(check cpr and pole_pairs against the hardware)")


def _check_gains(cfg: OdriveConfig, pos_gain, vel_gain, vel_integrator_gain):
    for name, value, high in (("pos_gain", pos_gain, cfg.max_pos_gain),
                              ("vel_gain", vel_gain, cfg.max_vel_gain),
                              ("vel_integrator_gain", vel_integrator_gain, cfg.max_vel_integrator_gain)):
        if not isinstance(value, (int, float, np.integer, np.floating)) or not math.isfinite(value):
            raise ValueError(f"{name} must be a finite number, got {value!r}")
        if not 0.0 <= value <= high:
            raise ValueError(f"{name} = {value} is outside the allowed range [0, {high}] "
                             f"({cfg.source_file}, [experiment] max_{name})")


# ---------------------------------------------------------------------------------------
# Listing 7.4: step responses and sweeps
# ---------------------------------------------------------------------------------------

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
        meta = {"experiment": "step_response", "step_turns": self.step, "completed": self.completed,
                "abort_reason": self.abort_reason, **self.meta}
        return dataio.write_measurement(out_dir, self.t, np.degrees(self.q1), np.degrees(self.q2),
                                        meta, gains=self.gains, when=when)

    @classmethod
    def from_measurement(cls, m: "dataio.Measurement", leg: LegParams) -> "StepResponse":
        """Rebuild from a file; thesis files (relative angles) are placed at the rest pose."""
        q1 = np.radians(m.angle1)
        q2 = np.radians(m.angle2)
        if not m.absolute:
            # Listing 7.4 zeroes the angles at the start and records 360/cpr/3 * counts of
            # the motor, i.e. joint angle changes in the motor's sense: convert to joint
            q1 = leg.q1 + leg.direction * q1
            q2 = leg.q2 + leg.direction * q2
        _, y = foot_position(leg, q1, q2)
        return cls(t=m.t - m.t[0], q1=q1, q2=q2, y=y, gains=m.gains, step=m.meta.get("step_turns", 0.4),
                   completed=m.stable, abort_reason=m.meta.get("abort_reason"), meta=m.meta)


def clear_errors(odrv) -> None:
    """Clear the error flags of both axes (after inspecting them)."""
    dev = as_device(odrv)
    for a in (0, 1):
        for key in ("error", "controller_error", "motor_error"):
            dev.set(a, key, 0)


def _prepare_closed_loop(dev: Device, vel_limit: float, watchdog: float | None) -> None:
    """Refuse to start on a stale fault; then limits, then the watchdog (on with a timeout
    [s], off with None); both axes."""
    for a in (0, 1):
        err = int(dev.get(a, "error"))
        if err:
            raise ExperimentError(f"axis{a} has error 0x{err:x} from an earlier fault; inspect it, then "
                                  f"call leglib.odrive_io.clear_errors(odrv)")
    for a in (0, 1):
        dev.set(a, "current_lim", dev.config.current_lim)
        dev.set(a, "vel_limit", vel_limit)
        if watchdog:
            dev.set(a, "watchdog_timeout", watchdog)
            dev.set(a, "enable_watchdog", True)
        else:
            dev.set(a, "enable_watchdog", False)


def _abort_reason_of(code: int) -> str | None:
    from . import twin as T
    return {T.ABORT_NONE: None, T.ABORT_POSITION_ERROR: "position error past bound",
            T.ABORT_NONFINITE: "simulation left the valid configuration",
            T.ABORT_OSCILLATION: "oscillation not decaying (growing or sustained)"}[int(code)]


def _responses_from_batch(dev: Device, gains, out: dict, step: float) -> list[StepResponse]:
    ax = dev.axes
    a1, a2 = ax.axis_of_joint
    res = []
    for i, g in enumerate(np.atleast_2d(gains)):
        q1 = ax.counts_to_joint(out["counts"][i, :, a1], 0)
        q2 = ax.counts_to_joint(out["counts"][i, :, a2], 1)
        completed = out["abort_tick"][i] < 0 and not np.any(out["axis_error"][i])
        reason = _abort_reason_of(out["abort_reason"][i])
        if reason is None and not completed:
            reason = f"axis error 0x{int(out['axis_error'][i].max()):x} (firmware fault)"
        n = len(out["t"]) if completed else max(2, int(out["abort_tick"][i] * dev.sim.twin.dt /
                                                     max(out["t"][1] - out["t"][0], 1e-12)) + 1)
        n = min(n, len(out["t"]))
        _, y = foot_position(dev.leg, q1[:n], q2[:n])
        res.append(StepResponse(t=out["t"][:n] - out["t"][0], q1=q1[:n], q2=q2[:n], y=y,
                                gains=tuple(float(x) for x in g), step=step, completed=bool(completed),
                                abort_reason=reason,
                                meta={**dev.describe(), "sample_rate_hz": 1.0 / (out["t"][1] - out["t"][0])}))
    return res


def _step_usb(dev: Device, gains, step, duration, sample_period, vel_limit, abort_error) -> StepResponse:
    """Listing 7.4 on a real device: a paced polling loop with safety checks."""
    from . import twin as T
    ax = dev.axes
    a_q1, a_q2 = ax.axis_of_joint
    with safe(dev):
        _prepare_closed_loop(dev, vel_limit, watchdog=0.5)
        for a in (0, 1):
            dev.set(a, "pos_gain", gains[0])
            dev.set(a, "vel_gain", gains[1])
            dev.set(a, "vel_integrator_gain", gains[2])
            dev.set(a, "control_mode", CONTROL_MODE_POSITION)
            dev.set(a, "input_mode", INPUT_MODE_PASSTHROUGH)
        start_pos = {a: float(dev.get(a, "pos_estimate")) for a in (0, 1)}
        target = {a_q1: start_pos[a_q1] + step, a_q2: start_pos[a_q2] - step}
        for a in (0, 1):
            dev.set(a, "requested_state", AXIS_STATE_CLOSED_LOOP_CONTROL)
        for a in (0, 1):
            dev.set(a, "input_pos", target[a])
        t0 = dev.time()
        ts, c1, c2 = [], [], []
        reason = None
        monitors = {a: np.zeros(T.N_OSC) for a in (0, 1)}
        next_sample = 0.0
        while True:
            now = dev.time() - t0
            if now > duration:
                break
            if now < next_sample:
                dev.sleep(min(next_sample - now, sample_period))
                continue
            next_sample += sample_period
            n1, n2 = dev.counts(a_q1), dev.counts(a_q2)
            ts.append(dev.time() - t0)
            c1.append(n1)
            c2.append(n2)
            for a in (0, 1):
                dev.axis(a).watchdog_feed()
            # safety, as the twin's kernel: position error bound and non-decaying oscillation
            errs = {a_q1: target[a_q1] - n1 / ax.cpr, a_q2: target[a_q2] - n2 / ax.cpr}
            if max(abs(e) for e in errs.values()) > abort_error:
                reason = "position error past bound"
                break
            if any(T.oscillation_update(monitors[a], errs[a], 0.025 * abort_error) for a in (0, 1)):
                reason = "oscillation not decaying (growing or sustained)"
                break
            if any(int(dev.get(a, "current_state")) != AXIS_STATE_CLOSED_LOOP_CONTROL for a in (0, 1)):
                errs = [int(dev.get(a, "error")) for a in (0, 1)]
                reason = f"axis dropped out of closed loop (errors 0x{errs[0]:x}, 0x{errs[1]:x})"
                break
    t = np.asarray(ts)
    q1 = ax.counts_to_joint(np.asarray(c1), 0)
    q2 = ax.counts_to_joint(np.asarray(c2), 1)
    _, y = foot_position(dev.leg, q1, q2)
    rate = (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 else float("nan")
    return StepResponse(t=t, q1=q1, q2=q2, y=y, gains=tuple(map(float, gains)), step=step,
                        completed=reason is None, abort_reason=reason,
                        meta={**dev.describe(), "sample_rate_hz": rate})


def step_response(odrv, pos_gain: float, vel_gain: float, vel_integrator_gain: float,
                  step: float = 0.4, duration: float = 1.5, sample_period: float = 0.002,
                  vel_limit: float | None = None, settle: float = 2.0) -> StepResponse:
    """Listing 7.4's position step with the given gains, from the leg at rest.

    The axis driving q1 moves by +``step`` motor turns, the other by -``step``. Gains are
    refused outside the configured bounds. The experiment aborts, sets IDLE and marks the
    response not completed when the position error passes 2*|step| or the oscillation
    stops decaying (three half-cycles in a row no smaller than the one before). Afterwards the axes are IDLE and the leg is left ``settle`` s to
    come to rest.

    On the twin the step runs whole in the compiled kernel (a batch of one, the same path
    :func:`sweep` uses for many); on USB it is a paced polling loop.
    """
    dev = as_device(odrv)
    _check_gains(dev.config, pos_gain, vel_gain, vel_integrator_gain)
    if not (0 < duration <= 30):
        raise ValueError(f"duration must be in (0, 30] s, got {duration}")
    if not (0 < abs(step) <= 1.0):
        raise ValueError(f"step must be a non-zero motor step of at most 1 turn, got {step}")
    gains = (float(pos_gain), float(vel_gain), float(vel_integrator_gain))
    vl = dev.config.step_vel_limit if vel_limit is None else vel_limit
    if dev.backend == "virtual":
        with safe(dev):
            out = dev.sim.step_batch(np.array([gains]), step_turns=step, duration=duration,
                                     sample_period=sample_period, vel_limit=vl,
                                     abort_error_turns=2 * abs(step))
        return _responses_from_batch(dev, [gains], out, step)[0]
    resp = _step_usb(dev, gains, step, duration, sample_period, vl, 2 * abs(step))
    dev.sleep(settle)
    return resp


@dataclass
class SweepResult:
    """What :func:`sweep` did: files written now, points skipped (already measured)."""

    written: list[Path]
    skipped: int
    unstable: int
    out_dir: Path

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
          chunk: int = 100) -> SweepResult:
    """Measure a step response for every (pos_gain, vel_gain, vel_integrator_gain) in
    ``grid`` and write each as a measurement file in ``out_dir``.

    Resumable: points whose file exists are skipped (``resume=False`` refuses a non-empty
    directory instead). Each file is written atomically when its point is done, so an
    interruption (exception, lost device, KeyboardInterrupt) loses no finished point; the
    axes go IDLE whatever happens. On the twin, pending points run in batches of ``chunk``
    through the compiled kernel; on USB one after the other.
    """
    from tqdm.auto import tqdm

    dev = as_device(odrv)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    grid = np.atleast_2d(np.asarray(list(grid), dtype=float))
    if grid.shape[1] != 3:
        raise ValueError(f"grid must hold (pos_gain, vel_gain, vel_integrator_gain) triples, "
                         f"got shape {grid.shape}")
    for g in grid:
        _check_gains(dev.config, *g)
    done = {dataio.gains_key(dataio.parse_filename(p)[1]) for p in dataio.list_measurements(out_dir)
            if dataio.parse_filename(p)[1] is not None}
    if done and not resume:
        raise FileExistsError(f"{out_dir} already holds {len(done)} measurements; pass resume=True "
                              f"to complete the sweep, or choose an empty directory")
    pending, seen = [], set(done)
    for g in grid:
        k = dataio.gains_key(g)
        if k not in seen:
            seen.add(k)
            pending.append(g)
    skipped = len(grid) - len(pending)
    written: list[Path] = []
    unstable = 0
    vl = dev.config.step_vel_limit
    bar = tqdm(total=len(grid), initial=skipped, desc="sweep", unit="step", disable=not progress)
    try:
        with safe(dev):
            if dev.backend == "virtual":
                for i in range(0, len(pending), chunk):
                    block = np.array(pending[i:i + chunk])
                    out = dev.sim.step_batch(block, step_turns=step, duration=duration,
                                             sample_period=sample_period, vel_limit=vl,
                                             abort_error_turns=2 * abs(step))
                    for resp in _responses_from_batch(dev, block, out, step):
                        written.append(resp.write(out_dir))
                        unstable += not resp.completed
                        bar.update(1)
            else:
                for g in pending:
                    resp = step_response(dev, *g, step=step, duration=duration, sample_period=sample_period)
                    written.append(resp.write(out_dir))
                    unstable += not resp.completed
                    bar.update(1)
    finally:
        bar.close()
    return SweepResult(written=written, skipped=skipped, unstable=unstable, out_dir=out_dir)


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
                record_current: bool = True, check_every: int = 1) -> TorqueRun:
    """Both joints in torque control; each cycle reads the joint angles, asks
    ``policy(t, q1, q2) -> (tau1, tau2)`` [N*m at the joints] and writes the torques.

    With ``period`` the cycles are paced to t = k * period (a controller's sample time);
    without, the loop runs as fast as the link allows (the thesis's playback). Records the
    actual read and write time of every value. Aborts to IDLE when a joint moves faster
    than ``max_joint_speed`` rad/s or an axis drops out of closed loop (checked every
    ``check_every`` cycles; each check and each Iq read costs a USB transaction).
    """
    dev = as_device(odrv)
    ax = dev.axes
    a_q1, a_q2 = ax.axis_of_joint
    limit = dev.config.current_lim * dev.config.torque_constant
    ts, t_cmd, t_read, c1, c2, iq, applied = [], [], [], [], [], [], []
    with safe(dev):
        _prepare_closed_loop(dev, dev.config.vel_limit, watchdog=0.2)
        for a in (0, 1):
            dev.set(a, "input_torque", 0.0)
            dev.set(a, "control_mode", CONTROL_MODE_TORQUE)
            dev.set(a, "requested_state", AXIS_STATE_CLOSED_LOOP_CONTROL)
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
            for a in (0, 1):
                dev.axis(a).watchdog_feed()
            if prev is not None and ts[-1] > prev[0]:
                speed = max(abs(n1 - prev[1]), abs(n2 - prev[2])) / ax.cpr * 2 * math.pi / ax.gear_ratio / (ts[-1] - prev[0])
                if speed > max_joint_speed:
                    raise ExperimentError(f"joint speed {speed:.1f} rad/s exceeds {max_joint_speed} rad/s "
                                          f"at t = {ts[-1]:.3f} s: aborted, axes IDLE")
            prev = (ts[-1], n1, n2)
            if k % check_every == 0 and int(dev.get(a_q1, "current_state")) != AXIS_STATE_CLOSED_LOOP_CONTROL:
                raise ExperimentError(f"axis{a_q1} dropped out of closed loop at t = {ts[-1]:.3f} s "
                                      f"(error 0x{int(dev.get(a_q1, 'error')):x})")
        for a in (0, 1):
            dev.set(a, "input_torque", 0.0)
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
    """Bring the leg back to its rest pose (motor position zero, where it was powered up)
    with soft position control, then IDLE and let it settle. Returns the joint angles [rad]
    it ends at. Experiments that start "from rest" call it between runs on a real bench."""
    dev = as_device(odrv)
    _check_gains(dev.config, pos_gain, vel_gain, vel_integrator_gain)
    with safe(dev):
        _prepare_closed_loop(dev, min(dev.config.vel_limit, 2.0), watchdog=None)
        for a in (0, 1):
            dev.set(a, "pos_gain", pos_gain)
            dev.set(a, "vel_gain", vel_gain)
            dev.set(a, "vel_integrator_gain", vel_integrator_gain)
            dev.set(a, "control_mode", CONTROL_MODE_POSITION)
            dev.set(a, "input_mode", INPUT_MODE_PASSTHROUGH)
            dev.set(a, "requested_state", AXIS_STATE_CLOSED_LOOP_CONTROL)
            dev.set(a, "input_pos", 0.0)
        dev.sleep(move_time)
    dev.sleep(settle)
    a1, a2 = dev.axes.axis_of_joint
    return float(dev.axes.counts_to_joint(dev.counts(a1), 0)), float(dev.axes.counts_to_joint(dev.counts(a2), 1))


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
