"""Setting up the ODrive for the leg (thesis Listings 7.1, 7.2): configuration, calibration,
zeroing and stored gains, the firmware's way.

Saving reboots the board on 0.5.2+ (main.cpp:159-184): the device is reconnected by serial
number and checked value by value on the rebooted board. Calibration moves the leg.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from ..errors import ExperimentError
from ..params import OdriveConfig
from .session import (
    AXIS_ERROR_WATCHDOG_TIMER_EXPIRED,
    AXIS_STATE_ENCODER_OFFSET_CALIBRATION,
    AXIS_STATE_FULL_CALIBRATION_SEQUENCE,
    AXIS_STATE_IDLE,
    AXIS_STATE_UNDEFINED,
    ENCODER_ERROR_CPR_POLEPAIRS_MISMATCH,
    ENCODER_ERROR_NO_RESPONSE,
    MOTOR_ERROR_BRAKE_RESISTOR_DISARMED,
    Deadline,
    Device,
    _reconnect,
    as_device,
    check_gains,
    clear_errors,
    describe_errors,
    error_text,
    errors,
    has_system_error,
    safe,
    state_name,
    wait_states,
)

# written into axis0's input_pos before a save: volatile (0 after a boot) and unused while the
# axis is IDLE (entering closed loop sets input_pos := pos_estimate, controller.cpp:115-128),
# so still reading it after the save means the board did not reboot
_REBOOT_MARKER = 1234.5


def _save_and_reconnect(dev: Device, timeout: float = 10.0) -> None:
    """``save_configuration()`` the firmware's way, confirmed: axes idle first; on 0.5.2+ the
    board refuses while armed and otherwise writes flash and reboots (main.cpp:159-184), so
    the connection is re-made by serial number and the save counts only once the board is
    seen to have rebooted: a volatile value written before the save (axis0's input_pos, which
    a boot clears) is gone. A link lost
    at the save is no reboot: that raises, saying what state the board is in. Calibration is
    lost by the reboot (unless pre-calibrated).

    Raises
    ------
    ExperimentError
        The board refused (an armed motor), did not come back, or did not reboot.
    """
    dev.__dict__["serial_number_at_connect"] = int(dev.raw.serial_number)
    dev.idle_all()
    wait_states(dev, (0, 1), AXIS_STATE_IDLE, what="going IDLE before saving")
    reboots = has_system_error(dev)
    if reboots:
        dev.set(0, "input_pos", _REBOOT_MARKER)
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
    if not reboots:
        return
    try:
        dev.rebind(_reconnect(dev, timeout))
    except Exception as exc:
        raise ExperimentError(f"save_configuration ({lost!r}) was not confirmed: the ODrive did not come back "
                              f"within {timeout:g} s ({exc}); whether it saved is unknown. Power-cycle it, "
                              f"reconnect and check its configuration (configure reads every value back)") from exc
    marker = float(dev.get(0, "input_pos"))
    if marker == _REBOOT_MARKER:
        dev.set(0, "input_pos", 0.0)
        raise ExperimentError(
            f"save_configuration was not confirmed: the board did not reboot (a value a boot clears is still "
            f"there; the call ended with {lost!r}), so nothing was saved to flash: the new values are in its "
            f"RAM only, and the brake resistor, if newly enabled, is not armed. Check the USB link, then "
            f"configure (or apply_gains) again")
    dev.axes = dev.axes.zeroed((0.0, 0.0))  # the counts restarted: the old zero is void


def configure(dev: Device, config: OdriveConfig | None = None, save: bool = True) -> dict:
    """Apply Listing 7.1's configuration to both axes, check it reads back, enable the brake
    resistor, and save it.

    The thesis's board has a 2.05 ohm brake resistor; firmware 0.5.2+ leaves it disabled by
    default (odrive_main.h:82) and then trips ODRIVE_ERROR_DC_BUS_OVER_REGEN_CURRENT as soon as
    a braking motor feeds back more than 10 mA (odrive_main.h:111, low_level.cpp:374-376).
    The resistor is armed only at boot or by ``clear_errors`` (low_level.cpp:181-183,
    main.cpp:246-248): with ``save`` the reboot arms it, without, ``clear_errors`` does.
    On 0.5.2+ saving reboots the board: the device is reconnected by serial number
    (``dev`` is rebound in place) and must be calibrated again.

    Parameters
    ----------
    dev : Device or an ODrive object (``odrive.find_any()``, the virtual one)
    config : OdriveConfig, optional
        What to write (default: the device's, ``dev.config``).
    save : bool
        Store it on the board (``save_configuration``, which reboots 0.5.2+), then check every
        value read back from the rebooted board.

    Returns
    -------
    dict
        The values written, per axis (``{"axis0": {...}, "axis1": {...}, "brake_resistance": ...}``).

    Raises
    ------
    ExperimentError
        A value does not read back as written (before or after the reboot), the board refuses
        to save, or it does not come back within the timeout.
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
        if has_system_error(dev):
            dev.raw.config.enable_brake_resistor = True
            written["enable_brake_resistor"] = True
        if save:
            _save_and_reconnect(dev)
            for a in (0, 1):
                for key, value in written[f"axis{a}"].items():
                    back = dev.get(a, key)
                    if not math.isclose(float(back), float(value), rel_tol=1e-6, abs_tol=1e-9):
                        raise ExperimentError(f"axis{a}.{key}: saved {value}, the rebooted device reports {back}")
        elif has_system_error(dev):
            clear_errors(dev)   # arms the brake resistor
    return written


def calibrate(dev: Device, timeout: float = 60.0, poll: float = 0.1, zero: bool = True) -> None:
    """Calibrate both axes (Listing 7.2), one after the other, then zero the joint angles.

    The encoder offset calibration turns the rotor about 0.73 turn (16 pi electrical rad
    over 11 pole pairs, encoder.hpp:22; 87 deg of joint on the 1:3 belt) at
    ``calibration_current``; the leg must be free to swing that far. The axes go one at a
    time: the idle link is carried along through the stop between the links, whereas two
    simultaneous locks can squeeze the links against their stop (each rotor jumps to its
    nearest electrical alignment, up to 1/22 turn, 5.5 deg of joint) and the two scans then
    fight. A motor with ``motor.config.pre_calibrated`` skips its motor calibration; the
    encoders (incremental, no index) always need the offset calibration after a boot
    (encoder.cpp:19-30,130-138).

    With ``zero`` the joint angles are defined at the rest pose from ``pos_estimate``: read
    before the calibration (the leg resting on its stop, as :func:`zero_joints` does) and
    carried through the calibration (found from the positions before and after, whole turns
    allowed for). A leg that calibration left at rest within the friction dead band (about
    1 deg here) would give a zero that far off; the pose before calibration is the one the leg
    settled into undisturbed. When the leg does not come back to within 0.05 turn of that
    pose, it is zeroed where it rests after calibration instead (with a warning).

    Parameters
    ----------
    dev : Device or an ODrive object
    timeout : float
        Seconds each axis may take (device and wall clock).
    poll : float
        Seconds between state checks.
    zero : bool
        Zero the joint angles at the rest pose afterwards.

    Raises
    ------
    ValueError
        ``timeout`` is not a positive number.
    ExperimentError
        An axis has an error before it starts, its calibration fails (the message names the
        axis and its flags) or it does not finish within ``timeout``; or the leg is not at rest
        for the zeroing.
    """
    dev = as_device(dev)
    if isinstance(timeout, bool) or not (isinstance(timeout, (int, float)) and math.isfinite(timeout) and timeout > 0):
        raise ValueError(f"timeout must be a positive number of seconds, got {timeout!r}")
    if isinstance(poll, bool) or not (isinstance(poll, (int, float)) and 0 < poll <= CALIBRATION_WATCHDOG / 3):
        raise ValueError(f"poll must be a number of seconds in (0, {CALIBRATION_WATCHDOG / 3:g}] (the watchdog of "
                         f"{CALIBRATION_WATCHDOG:g} s is fed every poll), got {poll!r}")
    for a in (0, 1):
        state, pending = int(dev.get(a, "current_state")), int(dev.get(a, "requested_state"))
        if state != AXIS_STATE_IDLE or pending != AXIS_STATE_UNDEFINED:
            raise ExperimentError(f"axis{a} is in {state_name(state)}"
                                  + (f" with {state_name(pending)} requested" if pending else "")
                                  + ": an earlier calibration or experiment still runs (an interrupted one "
                                    "finishes on the board by itself and ends IDLE); wait for it, or set "
                                    "both axes IDLE, then calibrate")
    before = _rest_positions(dev) if zero else None
    with safe(dev):
        for a in (0, 1):
            if int(dev.get(a, "error")):
                raise ExperimentError(f"axis{a} has an error before calibration: {error_text(dev, a)}; "
                                      f"inspect it, then call leglib.device.session.clear_errors(odrv)")
        # the calibration moves the leg: under the watchdog, so a link lost meanwhile stops it
        # (the watchdog counts down in every state, calibration included, axis.cpp:165-182)
        for a in (0, 1):
            dev.set(a, "watchdog_timeout", CALIBRATION_WATCHDOG)
            dev.axis(a).watchdog_feed()
            dev.set(a, "enable_watchdog", True)
        for a in (0, 1):
            request = (AXIS_STATE_ENCODER_OFFSET_CALIBRATION if bool(dev.get(a, "is_calibrated"))
                       else AXIS_STATE_FULL_CALIBRATION_SEQUENCE)
            dev.set(a, "requested_state", request)
            deadline = Deadline(dev, timeout, f"calibration of axis{a}")
            while True:
                dev.sleep(poll)
                for b in (0, 1):
                    dev.axis(b).watchdog_feed()
                if int(dev.get(a, "requested_state")) == AXIS_STATE_UNDEFINED \
                        and int(dev.get(a, "current_state")) == AXIS_STATE_IDLE:
                    break
                deadline.check(f" (state {state_name(int(dev.get(a, 'current_state')))})")
            if int(dev.get(a, "error")) or not bool(dev.get(a, "is_ready")):
                raise ExperimentError(f"axis{a} calibration failed: {describe_errors(errors(dev))}"
                                      f"{_calibration_advice(dev, a)}")
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


# the watchdog of a calibration [s] (fed every poll)
CALIBRATION_WATCHDOG = 0.5


def _calibration_advice(dev, a: int) -> str:
    """What to do about a failed calibration, from the flags that failed it."""
    e = errors(dev)[f"axis{a}"]
    if e["motor_error"] & MOTOR_ERROR_BRAKE_RESISTOR_DISARMED:
        return (": the brake resistor is enabled but not armed (a save that did not reboot the board, or a "
                "bus fault): clear_errors re-arms it, a reboot does too")
    if e["error"] & AXIS_ERROR_WATCHDOG_TIMER_EXPIRED:
        return ": the watchdog expired (the link was lost or the host stalled); check the cable, clear, retry"
    if e["encoder_error"] & ENCODER_ERROR_CPR_POLEPAIRS_MISMATCH:
        return (": the scan moved more or less than cpr and pole_pairs say: check them against the hardware "
                "and that the leg can swing freely (and carries no payload)")
    if e["encoder_error"] & ENCODER_ERROR_NO_RESPONSE:
        return ": the scan did not move the encoder: check its cable, the motor phases, the calibration current"
    return ""


def _rest_positions(dev: Device, settle: float = 1.0, max_speed: float = 0.01,
                    patience: float = 10.0) -> np.ndarray:
    """Motor positions [turn] (joint 0's motor, joint 1's motor) of the leg at rest: both
    axes IDLE, ``settle`` s, then the mean of a few ``pos_estimate`` readings once both
    motors turn slower than ``max_speed`` turn/s; a leg still swinging after ``patience``
    more seconds (a heavy foot rocking on its stop) is refused."""
    with safe(dev):
        wait_states(dev, (0, 1), AXIS_STATE_IDLE, what="going IDLE before zeroing")
        dev.sleep(settle)
        a1, a2 = dev.axes.axis_of_joint

        def mean_pos(n=8):
            return np.mean([(float(dev.get(a1, "pos_estimate")), float(dev.get(a2, "pos_estimate")))
                            for _ in range(n)], axis=0)
        deadline = Deadline(dev, patience, "the leg coming to rest for zeroing")
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

    Parameters
    ----------
    odrv : Device or an ODrive object
    gains : (3,) sequence
        pos_gain [(turn/s)/turn], vel_gain [N*m/(turn/s)], vel_integrator_gain [N*m/turn], each
        within the configuration's ``[experiment]`` bounds.
    save : bool
        Store them on the board (the board reboots on 0.5.2+).
    timeout : float
        Seconds to wait for the rebooted board [s].

    Returns
    -------
    Device
        The same device, rebound to the new connection after a reboot (on 0.5.2+ it must be
        calibrated again before it moves).

    Raises
    ------
    ValueError
        ``gains`` is not three finite numbers within the configured bounds.
    ExperimentError
        A gain does not read back as written, before or after the reboot.
    """
    dev = as_device(odrv)
    g = tuple(gains) if not isinstance(gains, (str, bytes)) else ()
    if len(g) != 3:
        raise ValueError(f"gains must be (pos_gain, vel_gain, vel_integrator_gain), got {gains!r}")
    check_gains(dev.config, *g)
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
