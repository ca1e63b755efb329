"""Setting up the ODrive for the leg (thesis Listings 7.1, 7.2): configuration, calibration,
zeroing and stored gains, the firmware's way.

Saving reboots the board on 0.5.2+ (main.cpp:159-184): the device is reconnected by serial
number and checked value by value on the rebooted board. Calibration moves the leg.
"""

from __future__ import annotations

import json
import math
import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ExperimentError
from ..params import OdriveConfig
from . import bench
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
    bench.note(dev, "save")
    if not reboots:
        return
    _forget_zero(dev)   # the counts restart at the boot: this power-up's zero is void
    try:
        with bench.timed(dev, "reboot"):
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


# Listing 7.1's values of each axis, by logical name (OdriveConfig's fields of the same name)
CONFIG_KEYS = ("current_lim", "vel_limit", "pole_pairs", "torque_constant", "motor_type", "cpr")
#: values every experiment writes itself before it arms a motor (prepare_closed_loop, e.g. a
#: step's ``step_vel_limit``): a difference there is written for the session, never a reason
#: to save and reboot
RUNTIME_KEYS = ("vel_limit",)


class Configuration(dict):
    """What :func:`configure` found and did.

    As a dict, the configuration now on the board: ``{"axis0": {...}, "axis1": {...},
    "brake_resistance": ..., "enable_brake_resistor": ...}`` (the last on 0.5.2+).
    ``differences`` lists the values that differed from the wanted ones
    (``"axis0.encoder.config.cpr: 8192 -> 4000"``), ``written`` and ``saved`` say what was
    done, ``rebooted`` whether the save rebooted the board (0.5.2+: calibration is then
    gone), ``text`` is what was said.
    """

    def __init__(self, values: dict):
        super().__init__(values)
        self.differences: list = []
        self.written = self.saved = self.rebooted = False
        self.text = ""

    def __str__(self) -> str:
        return self.text


@dataclass
class _Difference:
    path: str            # the firmware's name, e.g. axis0.encoder.config.cpr
    have: object
    want: object
    runtime: bool        # one of RUNTIME_KEYS
    axis: int | None = None
    key: str = ""        # the logical name (an axis value) or the board's config field

    def __str__(self) -> str:
        return f"{self.path}: {_show(self.have)} -> {_show(self.want)}"


def _show(v) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def _same(have, want) -> bool:
    return math.isclose(float(have), float(want), rel_tol=1e-6, abs_tol=1e-9)


def _wanted(dev: Device, cfg: OdriveConfig) -> dict:
    values = {k: getattr(cfg, k) for k in CONFIG_KEYS}
    wanted = {"axis0": dict(values), "axis1": dict(values), "brake_resistance": cfg.brake_resistance}
    if has_system_error(dev):   # 0.5.2+: the brake resistor is off unless enabled (odrive_main.h:82)
        wanted["enable_brake_resistor"] = True
    return wanted


def _differences(dev: Device, wanted: dict) -> list[_Difference]:
    """The board's values that differ from ``wanted`` (each read once)."""
    out = []
    for a in (0, 1):
        for key, value in wanted[f"axis{a}"].items():
            have = dev.get(a, key)
            if not _same(have, value):
                out.append(_Difference(f"axis{a}.{'.'.join(dev._path(key))}", have, value, key in RUNTIME_KEYS,
                                       a, key))
    for key in ("brake_resistance", "enable_brake_resistor"):
        if key in wanted:
            have = getattr(dev.raw.config, key)
            if not _same(have, wanted[key]):
                out.append(_Difference(f"config.{key}", have, wanted[key], False, None, key))
    return out


def _ready(dev: Device, a: int) -> bool:
    """Axis ``a`` can enter closed loop: its motor is calibrated and its encoder ready (both
    volatile: a boot clears them unless pre-calibrated, motor.cpp:306, encoder.cpp:19-30)."""
    return bool(dev.get(a, "is_calibrated")) and bool(dev.get(a, "is_ready"))


@dataclass
class Needs:
    """What a board still needs before it can run experiments (:func:`needs`)."""

    differences: list
    save: bool            # a stored value differs: configure writes and saves
    reboot: bool          # ... and the save reboots the board (0.5.2+)
    calibrate_axes: tuple  # axes calibrate will calibrate (all of them after a reboot)


def needs(odrv, config: OdriveConfig | None = None) -> Needs:
    """What :func:`configure` and :func:`calibrate` would do on this board now, read from it
    without changing anything: the configuration's differences, whether it would be saved
    (and the board reboot), and which axes would be calibrated."""
    dev = as_device(odrv)
    diffs = _differences(dev, _wanted(dev, config or dev.config))
    save = any(not d.runtime for d in diffs)
    reboot = save and has_system_error(dev)
    axes = (0, 1) if reboot else tuple(a for a in (0, 1) if not _ready(dev, a))
    return Needs([str(d) for d in diffs], save, reboot, axes)


def start_run(dev, plan: bench.Plan, max_minutes=None, parameter: str = "max_bench_minutes") -> bench.Run:
    """Start a run on ``dev``'s leg: the estimate of ``plan`` with what the board still needs
    (a configuration to save, axes to calibrate: :func:`needs`), said in one line. On a real
    leg a run whose estimate is over ``max_minutes`` (None:
    :data:`leglib.device.bench.DEFAULT_MAX_BENCH_MINUTES`) is refused with
    :class:`leglib.errors.BenchLimitError`, which gives the estimate and names ``parameter``;
    on the twin the estimate is said and kept for the report. Call it after connecting and
    before configuring: nothing has moved yet.

    Returns
    -------
    leglib.device.bench.Run
        Its :meth:`~leglib.device.bench.Run.report` says what the run did on the leg and
        its bench time, beside this estimate.
    """
    dev = as_device(dev)
    need = needs(dev)
    planned = plan.seconds(reboot=need.reboot, calibrate_axes=len(need.calibrate_axes))
    what = plan.what(save=need.save, reboot=need.reboot, calibrate_axes=len(need.calibrate_axes))
    max_minutes = bench.DEFAULT_MAX_BENCH_MINUTES if max_minutes is None else max_minutes
    limit = bench.limit_seconds(max_minutes, parameter)
    bench.require(dev, planned, max_minutes, f"this run ({what})", parameter)
    where = "rehearsal on the twin: on the leg this run will do" if dev.backend == "virtual" else "on the leg:"
    print(f"{where} {what}: about {bench.minutes(planned)} of bench time (limit: {parameter} = {limit / 60:g} min)"
          + (f"; {plan.note}" if plan.note else ""), flush=True)
    return bench.Run(dev, plan, planned, limit, what)


def _say(dev: Device, text: str, verbose: bool | None) -> None:
    """Print ``text`` when ``verbose`` (None: on a real leg, where someone watches the bench)."""
    if verbose or (verbose is None and dev.backend == "usb"):
        print(text, flush=True)


def configure(dev: Device, config: OdriveConfig | None = None, save: bool = True, force: bool = False,
              verbose: bool | None = None) -> Configuration:
    """Give the board Listing 7.1's configuration (and the brake resistor), writing and
    saving only what differs.

    The board's values are read back and compared with the wanted ones first; the
    differences are said. When a stored value differs (or with ``force``) every value is
    written, checked, and with ``save`` saved: on 0.5.2+ the board then reboots, is
    reconnected by serial number (``dev`` is rebound in place), every value is checked on
    the rebooted board, and its calibration is gone. When only a value that every
    experiment sets itself before arming differs (:data:`RUNTIME_KEYS`: ``vel_limit``) it
    is written for the session, without a save. When nothing differs nothing is written:
    a board configured once keeps its configuration (and its calibration) from notebook to
    notebook. The values read back are the saved ones unless they were written since the
    board's boot: leglib writes without saving only the run-time values.

    The thesis's board has a 2.05 ohm brake resistor; firmware 0.5.2+ leaves it disabled by
    default (odrive_main.h:82) and then trips ODRIVE_ERROR_DC_BUS_OVER_REGEN_CURRENT as soon as
    a braking motor feeds back more than 10 mA (odrive_main.h:111, low_level.cpp:374-376).
    The resistor is armed only at boot or by ``clear_errors`` (low_level.cpp:181-183,
    main.cpp:246-248): with ``save`` the reboot arms it, without, ``clear_errors`` does.

    Parameters
    ----------
    dev : Device or an ODrive object (``odrive.find_any()``, the virtual one)
    config : OdriveConfig, optional
        What the board should hold (default: the device's, ``dev.config``).
    save : bool
        Store written values on the board (``save_configuration``, which reboots 0.5.2+),
        then check every value read back from the rebooted board.
    force : bool
        Write (and with ``save`` save) every value even when the board holds them already.
    verbose : bool, optional
        Print what was found and done (default: on a real leg only; the twin's run reports
        it in its :mod:`~leglib.device.bench` report).

    Returns
    -------
    Configuration
        The configuration on the board, per axis, with the differences found and what was done.

    Raises
    ------
    ExperimentError
        A value does not read back as written (before or after the reboot), the board refuses
        to save, or it does not come back within the timeout.
    """
    dev = as_device(dev)
    cfg = config or dev.config
    wanted = _wanted(dev, cfg)
    result = Configuration(wanted)
    name = Path(cfg.source_file).stem if cfg.source_file else "the wanted"
    with bench.timed(dev, "configure") as entry, safe(dev):
        diffs = _differences(dev, wanted)
        result.differences = [str(d) for d in diffs]
        stored = [d for d in diffs if not d.runtime]
        if force or stored:
            _write(dev, wanted)
            result.written = True
            if save:
                boots = has_system_error(dev)
                _save_and_reconnect(dev)
                result.saved, result.rebooted = True, boots
                for a in (0, 1):
                    for key, value in wanted[f"axis{a}"].items():
                        back = dev.get(a, key)
                        if not _same(back, value):
                            raise ExperimentError(f"axis{a}.{key}: saved {value}, the rebooted device reports {back}")
            elif has_system_error(dev):
                clear_errors(dev)   # arms the brake resistor
            what = (", saved; the board rebooted (its calibration is gone)" if result.rebooted
                    else ", saved" if result.saved else ", not saved")
            found = (f"{len(stored)} stored value(s) differ ({'; '.join(map(str, stored))})" if stored
                     else "nothing differs (written anyway: force)")
            result.text = f"configure: {found}: written, read back{what}"
        elif diffs:
            for d in diffs:
                dev.set(d.axis, d.key, d.want)
                back = dev.get(d.axis, d.key)
                if not _same(back, d.want):
                    raise ExperimentError(f"{d.path}: wrote {d.want}, device reports {back}")
            result.written = True
            result.text = (f"configure: the board holds {name}'s configuration except the run-time "
                           f"{'; '.join(map(str, diffs))}: written for this session (every experiment sets it "
                           f"before arming), not saved")
        else:
            result.text = f"configure: the board holds {name}'s configuration (read back): nothing written"
        entry["text"] = result.text
    _say(dev, result.text, verbose)
    return result


def _write(dev: Device, wanted: dict) -> None:
    """Write every value of ``wanted``, each checked as it reads back."""
    for a in (0, 1):
        for key, value in wanted[f"axis{a}"].items():
            dev.set(a, key, value)
            back = dev.get(a, key)
            if not _same(back, value):
                raise ExperimentError(f"axis{a}.{key}: wrote {value}, device reports {back}")
    dev.raw.config.brake_resistance = wanted["brake_resistance"]
    if "enable_brake_resistor" in wanted:
        dev.raw.config.enable_brake_resistor = True


# ---------------------------------------------------------------------------------------
# the zero of a calibration, kept for the board's power-up
# ---------------------------------------------------------------------------------------

#: how far [motor turn] the leg may rest from the pose it was zeroed at and keep that zero:
#: 3 deg of joint on the 1:3 belt, about three times the friction dead band the leg rests
#: anywhere within (after a step or a torque run the twin's comes back within 0.01 turn)
REST_TOLERANCE = 0.025
# the board's uptime (system_stats.uptime, ms, main.cpp:263) agrees with the host's clock
# within this [s] plus this fraction of the time since the zero was noted while the board
# runs from the same power-up (USB latency, the crystals' drift); a boot since then is
# further off by at least the time the calibration before the note took (about 27 s)
_SAME_BOOT_SLACK, _SAME_BOOT_DRIFT = 2.0, 1e-3


@dataclass
class _Zero:
    """The rest pose a calibration zeroed the joints at, on one power-up of one board."""

    serial: int
    turns: tuple          # motor positions [turn] (joint 0's motor, joint 1's motor)
    uptime_ms: int        # the board's uptime when noted
    clock: float | None   # the board clock (Device.board_clock) when noted, this process
    wall: float           # the host's wall clock when noted (across processes)


_ZEROS: dict[int, _Zero] = {}


def _state_dir() -> Path:
    """Where zeros of real boards are kept between processes (a notebook is a process):
    ``$LEGLIB_STATE_DIR``, else ``$XDG_STATE_HOME/leglib``, else ``~/.local/state/leglib``."""
    env = os.environ.get("LEGLIB_STATE_DIR")
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_STATE_HOME") or str(Path("~/.local/state").expanduser())
    return Path(base) / "leglib"


def _zero_file(serial: int) -> Path:
    return _state_dir() / "boards" / f"{serial:012X}.json"


def _uptime_ms(dev: Device) -> int:
    return int(dev.raw.system_stats.uptime)


def _same_boot(z: _Zero, uptime_ms: int, clock: float, wall: float) -> bool:
    """``z`` was noted on the board's present power-up: its uptime grew by the time that
    passed (uint32 ms, wraps after 49.7 days)."""
    grown = ((uptime_ms - z.uptime_ms) % (1 << 32)) / 1000.0
    passed = clock - z.clock if z.clock is not None else wall - z.wall
    return passed >= -_SAME_BOOT_SLACK and abs(grown - passed) <= _SAME_BOOT_SLACK + _SAME_BOOT_DRIFT * abs(passed)


def _known_zero(dev: Device) -> _Zero | None:
    """The zero noted on this board's present power-up (this process's, else a real board's
    file), or None."""
    serial = dev.serial
    uptime, clock, wall = _uptime_ms(dev), dev.board_clock(), time.time()
    z = _ZEROS.get(serial)
    if z is not None and _same_boot(z, uptime, clock, wall):
        return z
    if dev.__dict__.get("_board_sim") is None:   # a real board: another process may have noted it
        try:
            d = json.loads(_zero_file(serial).read_text())
            z = _Zero(int(d["serial"], 16), tuple(float(x) for x in d["turns"]), int(d["uptime_ms"]), None,
                      float(d["wall"]))
        except (OSError, ValueError, KeyError, TypeError):
            return None
        if z.serial == serial and len(z.turns) == 2 and _same_boot(z, uptime, clock, wall):
            return z
    return None


def _note_zero(dev: Device, turns) -> None:
    """Zero the joints at ``turns`` and keep it for the board's power-up."""
    dev.axes = dev.axes.zeroed(turns)
    z = _Zero(dev.serial, tuple(float(t) for t in turns), _uptime_ms(dev), dev.board_clock(), time.time())
    _ZEROS[z.serial] = z
    if dev.__dict__.get("_board_sim") is None:
        path = _zero_file(z.serial)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f".{path.name}.{os.getpid()}")
            tmp.write_text(json.dumps({"serial": f"{z.serial:012X}", "turns": list(z.turns),
                                       "uptime_ms": z.uptime_ms, "wall": z.wall}))
            os.replace(tmp, path)
        except OSError as exc:
            warnings.warn(f"could not keep the zero of ODrive {z.serial:012X} in {path} ({exc}): the next "
                          f"process zeroes at the rest pose again", stacklevel=3)


def _forget_zero(dev: Device) -> None:
    """The board rebooted (its counts restarted): its zero is void."""
    serial = dev.__dict__.get("_serial")
    if serial is not None:
        _ZEROS.pop(serial, None)


@dataclass
class Calibration:
    """What :func:`calibrate` did: ``axes`` calibrated now (none when the board was ready),
    ``zeroing`` how the joint angles were defined (``"calibration"``: at the rest pose around
    this calibration; ``"kept"``: the zero of this power-up's calibration, the leg resting
    within :data:`REST_TOLERANCE` of it; ``"moved"``: the leg rests elsewhere, zeroed there;
    ``"rest"``: no zero known for this power-up, zeroed at the rest pose; ``"none"``: not
    zeroed), ``zero`` the motor positions [turn] of the rest pose, ``text`` what was said."""

    axes: tuple
    zeroing: str
    zero: tuple | None
    text: str

    def __str__(self) -> str:
        return self.text


def calibrate(dev: Device, timeout: float = 60.0, poll: float = 0.1, zero: bool = True, force: bool = False,
              verbose: bool | None = None) -> Calibration:
    """Calibrate the axes that need it (Listing 7.2), one after the other, then zero the
    joint angles at the rest pose.

    An axis whose motor is calibrated and whose encoder is ready (``motor.is_calibrated``,
    ``encoder.is_ready``: both hold until the board reboots) is not calibrated again: on a
    ready board nothing moves, and the zero of this power-up's calibration is kept when the
    leg rests within :data:`REST_TOLERANCE` of it (measured, without motion); a leg that
    rests elsewhere is zeroed there, and that is said. ``force`` calibrates both axes anyway.

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
    pose, it is zeroed where it rests after calibration instead (with a warning). The zero
    is kept for the board's power-up: in this process, and for a real board also in a file
    (``$LEGLIB_STATE_DIR``, default ``~/.local/state/leglib``), so the next notebook on the
    same powered board finds it.

    Parameters
    ----------
    dev : Device or an ODrive object
    timeout : float
        Seconds each axis may take (device and wall clock).
    poll : float
        Seconds between state checks.
    zero : bool
        Zero the joint angles at the rest pose afterwards.
    force : bool
        Calibrate both axes even when they are ready.
    verbose : bool, optional
        Print what was done (default: on a real leg only).

    Returns
    -------
    Calibration
        The axes calibrated, how the joints were zeroed, and what was said.

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
    todo = tuple(a for a in (0, 1) if force or not _ready(dev, a))
    if not todo:
        result = _zero_ready_board(dev) if zero else Calibration((), "none", None, "")
        result.text = ("calibrate: both axes are calibrated since the board's power-up (motor.is_calibrated, "
                       "encoder.is_ready): not calibrated again, the leg did not move"
                       + (f"; {result.text}" if result.text else ""))
        bench.note(dev, "calibration", count=0, text=result.text)
        _say(dev, result.text, verbose)
        return result
    with bench.timed(dev, "calibration", count=len(todo)) as entry:
        before = _rest_positions(dev) if zero else None
        _calibrate_axes(dev, todo, timeout, poll)
        result = Calibration(todo, "none", None, "")
        if zero:
            after = _rest_positions(dev)
            shift = np.round(after - before)   # whole turns: the counts' re-reference
            if np.all(np.abs(after - before - shift) < 0.05):
                turns, result.zeroing = before + shift, "calibration"
            else:
                warnings.warn(f"the leg did not come back to its rest pose after calibration (moved "
                              f"{np.round(after - before - shift, 3)} turn): zeroed where it rests now",
                              stacklevel=2)
                turns, result.zeroing = after, "moved"
            _note_zero(dev, turns)
            result.zero = tuple(float(t) for t in turns)
        result.text = (f"calibrate: axis{' and axis'.join(map(str, todo))} calibrated (the leg swung)"
                       + ("; zeroed at the rest pose" if zero else ""))
        entry["text"] = result.text
    _say(dev, result.text, verbose)
    return result


def _zero_ready_board(dev: Device) -> Calibration:
    """The joints' zero on a board that needs no calibration: this power-up's, when the leg
    rests near it; else where it rests (said)."""
    with bench.timed(dev, "rest check"):
        rest = _rest_positions(dev)
    known = _known_zero(dev)
    if known is not None:
        ref = np.asarray(known.turns)
        shift = np.round(rest - ref)   # whole turns: a calibration elsewhere re-referenced the counts
        moved = rest - ref - shift
        if np.all(np.abs(moved) < REST_TOLERANCE):
            dev.axes = dev.axes.zeroed(ref + shift)
            return Calibration((), "kept", tuple(float(t) for t in ref + shift),
                               f"the zero of this power-up's calibration kept (the leg rests within "
                               f"{np.max(np.abs(moved)) * 360 / dev.axes.gear_ratio:.1f} deg of joint of it)")
        deg = np.round(moved * 360 / dev.axes.gear_ratio, 1)
        text = (f"the rest pose moved since this power-up's calibration (by {deg[0]:+.1f} and {deg[1]:+.1f} deg of "
                f"joint, more than {REST_TOLERANCE * 360 / dev.axes.gear_ratio:g} deg): zeroed where the leg rests now")
        warnings.warn(text, stacklevel=3)
        _note_zero(dev, rest)
        return Calibration((), "moved", tuple(float(t) for t in rest), text)
    _note_zero(dev, rest)
    return Calibration((), "rest", tuple(float(t) for t in rest),
                       "no zero known for this power-up (calibrated by another program, or its note is gone): "
                       "zeroed at the rest pose now")


def _calibrate_axes(dev: Device, axes, timeout: float, poll: float) -> None:
    """Listing 7.2 on ``axes``, one after the other, under the watchdog."""
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
        for a in axes:
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
                deadline.check(lambda: f" (state {state_name(int(dev.get(a, 'current_state')))})")
            if int(dev.get(a, "error")) or not bool(dev.get(a, "is_ready")):
                raise ExperimentError(f"axis{a} calibration failed: {describe_errors(errors(dev))}"
                                      f"{_calibration_advice(dev, a)}")


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
    with bench.timed(dev, "zeroing"):
        turns = _rest_positions(dev, settle, max_speed)
    _note_zero(dev, turns)
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
