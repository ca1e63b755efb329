"""A virtual ODrive v3.6: the firmware's object tree over a :class:`leglib.twin.Twin`.

The tree mirrors firmware 0.5.x (``odrv.axis0.controller.config.pos_gain``,
``odrv.axis1.encoder.shadow_count``, ...), or 0.6.x with ``firmware="0.6"`` (estimates on
the axis, motor limits in ``axis.config.motor``). Unknown attributes raise AttributeError,
as on the device. Every property read or write is one USB transaction: the virtual clock
advances by the link latency and the simulated leg moves on in the compiled kernel (no
Python per tick). ``realtime=True`` paces the virtual clock to the wall clock, so host code
that sleeps with ``time.sleep`` sees the leg move.

Extras the real device does not have (used by :mod:`leglib.odrive_io`): ``sleep(s)``,
``time``, ``twin``, ``step_batch`` and ``disconnect_after`` for fault-injection tests.
"""

from __future__ import annotations

import time as _time

import numpy as np

from . import twin as T
from .params import OdriveConfig, PlantParams

# odrive.enums values (firmware 0.5.x), kept here so the twin runs without the odrive package
AXIS_STATE_UNDEFINED, AXIS_STATE_IDLE = 0, 1
AXIS_STATE_FULL_CALIBRATION_SEQUENCE = 3
AXIS_STATE_MOTOR_CALIBRATION = 4
AXIS_STATE_ENCODER_OFFSET_CALIBRATION = 7
AXIS_STATE_CLOSED_LOOP_CONTROL = 8
AXIS_ERROR_INVALID_STATE = 0x1
AXIS_ERROR_ENCODER_FAILED = 0x100
ENCODER_ERROR_CPR_POLEPAIRS_MISMATCH = 0x2
CONTROL_MODES = (1, 2, 3)  # torque, velocity, position
INPUT_MODE_PASSTHROUGH = 1


class DeviceLostError(ConnectionError):
    """The connection to the ODrive was lost."""


class _Prop:
    """One property of the tree: getter, optional setter, value type."""

    def __init__(self, get, set=None, kind=float):
        self.get, self.set, self.kind = get, set, kind


class _Node:
    """A node of the object tree with a fixed set of properties, children and methods."""

    def __init__(self, dev, path, props=None, children=None, methods=None):
        object.__setattr__(self, "_dev", dev)
        object.__setattr__(self, "_path", path)
        object.__setattr__(self, "_props", props or {})
        object.__setattr__(self, "_children", children or {})
        object.__setattr__(self, "_methods", methods or {})

    def __getattr__(self, name):
        if name in self._children:
            return self._children[name]
        if name in self._props:
            self._dev._transaction()
            return self._props[name].get()
        if name in self._methods:
            fn = self._methods[name]

            def call(*args, **kwargs):
                self._dev._transaction()
                return fn(*args, **kwargs)
            return call
        raise AttributeError(f"'{self._path}' has no attribute '{name}'")

    def __setattr__(self, name, value):
        prop = self._props.get(name)
        if prop is None:
            if name in self._children or name in self._methods:
                raise AttributeError(f"'{self._path}.{name}' cannot be assigned")
            raise AttributeError(f"'{self._path}' has no attribute '{name}'")
        if prop.set is None:
            raise AttributeError(f"'{self._path}.{name}' is read-only")
        if prop.kind is bool:
            if not isinstance(value, (bool, int, np.integer)):
                raise TypeError(f"'{self._path}.{name}' expects a bool, got {value!r}")
            value = bool(value)
        elif prop.kind is int:
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise TypeError(f"'{self._path}.{name}' expects an integer, got {value!r}")
            value = int(value)
        else:
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
                raise TypeError(f"'{self._path}.{name}' expects a number, got {value!r}")
            value = float(value)
            if not np.isfinite(value):
                raise ValueError(f"'{self._path}.{name}' must be finite, got {value!r}")
        self._dev._transaction()
        prop.set(value)

    def __dir__(self):
        return sorted(set(self._props) | set(self._children) | set(self._methods))

    def __repr__(self):
        return f"<virtual ODrive node {self._path}>"


class VirtualODrive:
    """The virtual ODrive. Build it with :func:`leglib.odrive_io.connect` (backend
    ``"virtual"``) or directly.

    Parameters
    ----------
    plant, config : the simulated leg and the ODrive's initial configuration
    seed : noise seed; the same seed gives the same measurements
    realtime : pace the virtual clock to the wall clock
    firmware : "0.5" (default) or "0.6" object tree
    disconnect_after : raise :class:`DeviceLostError` from the N-th transaction on (tests)
    noise : encoder and current noise on (default) or off
    """

    def __init__(self, plant: PlantParams | str = "default", config: OdriveConfig | str = "thesis",
                 seed: int = 0, realtime: bool = False, firmware: str = "0.5",
                 disconnect_after: int | None = None, noise: bool = True):
        if firmware not in ("0.5", "0.6"):
            raise ValueError(f"firmware must be '0.5' or '0.6', got {firmware!r}")
        self.twin = T.Twin(plant, config, batch=1, seed=seed, noise=noise)
        self.firmware = firmware
        self.realtime = bool(realtime)
        self.disconnect_after = disconnect_after
        self.transactions = 0
        self.lost = False
        self.saved_configuration = None
        self._rng = np.random.default_rng(seed)
        self.st = self.twin.rest_state()
        self._pending = 0.0
        self._t0_wall = _time.monotonic()
        cfg = self.twin.config
        motor = self.twin.motor
        self._brake_resistance = cfg.brake_resistance
        self._axis = []
        for a in range(2):
            self._axis.append({
                "requested_state": AXIS_STATE_UNDEFINED, "state": AXIS_STATE_IDLE,
                "cal_end": None, "calibrated": False, "encoder_ready": False,
                "control_mode": 3, "input_mode": INPUT_MODE_PASSTHROUGH,
                "enable_watchdog": False, "watchdog_timeout": 0.0,
                "cpr": 8192, "pole_pairs": 7, "motor_type": 0,
                "encoder_error": 0, "true_cpr": self.twin.axes.cpr, "true_pole_pairs": motor.pole_pairs,
            })
        self._tree = self._build_tree()

    # -- clock and transactions --------------------------------------------------------
    @property
    def time(self) -> float:
        """Virtual time since power-up [s]."""
        return float(self.st.X[0, 4])

    def _advance(self, seconds: float, progress: bool = False) -> None:
        # whole ticks only; the remainder is carried, so many short waits add up exactly.
        # With ``progress`` a positive wait always moves at least one tick (borrowing it),
        # so a host loop waiting for a sample time cannot spin on a rounding residue.
        self._pending += max(seconds, 0.0)
        n = int(self._pending / self.twin.dt + 1e-9)
        if progress and n == 0 and seconds > 0:
            n = 1
        if n > 0:
            self._pending -= n * self.twin.dt
            self.twin.run(self.st, ticks=n)
        self._update_state_machine()

    def sleep(self, seconds: float) -> None:
        """Let ``seconds`` of (virtual) time pass; in real-time mode also wait."""
        self._check_link()
        self._advance(seconds, progress=True)
        if self.realtime:
            self._pace()

    def _pace(self):
        ahead = self.time - (_time.monotonic() - self._t0_wall)
        if ahead > 0:
            _time.sleep(ahead)
        elif ahead < -self.twin.dt:
            self._advance(-ahead)

    def _check_link(self):
        if self.lost:
            raise DeviceLostError("virtual ODrive: device lost (injected disconnect)")
        if self.disconnect_after is not None and self.transactions >= self.disconnect_after:
            self.lost = True
            raise DeviceLostError(f"virtual ODrive: device lost after {self.transactions} transactions "
                                  f"(injected disconnect)")

    def _transaction(self) -> None:
        self._check_link()
        self.transactions += 1
        p = self.twin.plant
        latency = p.usb_latency * (1.0 + p.usb_jitter * (self._rng.random() - 0.5) * 2.0)
        self._advance(latency)
        if self.realtime:
            self._pace()

    # -- firmware state machine --------------------------------------------------------
    def _update_state_machine(self):
        now = self.time
        for a in range(2):
            ax = self._axis[a]
            if ax["cal_end"] is not None:
                if now >= ax["cal_end"]:
                    ax["cal_end"] = None
                    if ax["cpr"] != ax["true_cpr"] or ax["pole_pairs"] != ax["true_pole_pairs"]:
                        ax["encoder_error"] |= ENCODER_ERROR_CPR_POLEPAIRS_MISMATCH
                        self.st.AI[0, a, T.I_AXIS_ERR] |= AXIS_ERROR_ENCODER_FAILED
                        ax["calibrated"] = ax["encoder_ready"] = False
                    else:
                        ax["calibrated"] = ax["encoder_ready"] = True
                    ax["state"] = AXIS_STATE_IDLE
                else:
                    half = ax["cal_start"] + 0.4 * self.twin.plant.calibration_time
                    ax["state"] = (AXIS_STATE_MOTOR_CALIBRATION if now < half
                                   else AXIS_STATE_ENCODER_OFFSET_CALIBRATION)
            elif ax["state"] == AXIS_STATE_CLOSED_LOOP_CONTROL and self.st.AI[0, a, T.I_MODE] == T.MODE_IDLE:
                ax["state"] = AXIS_STATE_IDLE  # a fault (or leglib's abort) dropped the axis

    def _request_state(self, a: int, value: int):
        ax = self._axis[a]
        ax["requested_state"] = value
        st = self.st
        if value == AXIS_STATE_IDLE:
            st.AI[0, a, T.I_MODE] = T.MODE_IDLE
            ax["cal_end"] = None
            ax["state"] = AXIS_STATE_IDLE
        elif value == AXIS_STATE_FULL_CALIBRATION_SEQUENCE:
            st.AI[0, a, T.I_MODE] = T.MODE_IDLE
            ax["cal_start"] = self.time
            ax["cal_end"] = self.time + self.twin.plant.calibration_time
            ax["state"] = AXIS_STATE_MOTOR_CALIBRATION
        elif value == AXIS_STATE_CLOSED_LOOP_CONTROL:
            if not (ax["calibrated"] and ax["encoder_ready"]) or st.AI[0, a, T.I_AXIS_ERR]:
                st.AI[0, a, T.I_AXIS_ERR] |= AXIS_ERROR_INVALID_STATE
                return
            st.C[0, a, T.C_INPUT_POS] = st.AS[0, a, T.S_POS_EST]
            st.AS[0, a, T.S_INTEGRATOR] = 0.0
            st.AS[0, a, T.S_WD_TIMER] = 0.0
            st.AI[0, a, T.I_MODE] = ax["control_mode"]
            ax["state"] = AXIS_STATE_CLOSED_LOOP_CONTROL
        else:
            st.AI[0, a, T.I_AXIS_ERR] |= AXIS_ERROR_INVALID_STATE

    def _set_control_mode(self, a: int, value: int):
        if value not in CONTROL_MODES:
            raise ValueError(f"axis{a}.controller.config.control_mode: unsupported value {value}")
        self._axis[a]["control_mode"] = value
        if self._axis[a]["state"] == AXIS_STATE_CLOSED_LOOP_CONTROL:
            self.st.AI[0, a, T.I_MODE] = value

    def _set_watchdog(self, a, enable=None, timeout=None):
        ax = self._axis[a]
        if enable is not None:
            ax["enable_watchdog"] = enable
        if timeout is not None:
            ax["watchdog_timeout"] = timeout
        self.st.C[0, a, T.C_WD_TIMEOUT] = ax["watchdog_timeout"] if ax["enable_watchdog"] else 0.0
        self.st.AS[0, a, T.S_WD_TIMER] = 0.0

    def _clear_errors(self, a=None):
        for i in ((0, 1) if a is None else (a,)):
            self.st.AI[0, i, T.I_AXIS_ERR] = 0
            self.st.AI[0, i, T.I_CTRL_ERR] = 0
            self.st.AI[0, i, T.I_MOTOR_ERR] = 0
            self._axis[i]["encoder_error"] = 0

    # -- the tree ----------------------------------------------------------------------
    def _cfg_prop(self, a, index, kind=float, check_positive=False):
        st = self.st

        def get():
            return float(st.C[0, a, index])

        def set_(v):
            if check_positive and v <= 0:
                raise ValueError(f"axis{a}: value must be positive, got {v}")
            st.C[0, a, index] = v
        return _Prop(get, set_, kind)

    def _axis_tree(self, a: int) -> _Node:
        st, ax, dev = self.st, self._axis[a], self
        path = f"odrv.axis{a}"

        def err_prop(index):
            def set_(v):
                st.AI[0, a, index] = v
            return _Prop(lambda: int(st.AI[0, a, index]), set_, int)

        ctrl_cfg = _Node(dev, path + ".controller.config", {
            "control_mode": _Prop(lambda: ax["control_mode"], lambda v: self._set_control_mode(a, v), int),
            "input_mode": _Prop(lambda: ax["input_mode"], lambda v: ax.__setitem__("input_mode", v), int),
            "pos_gain": self._cfg_prop(a, T.C_POS_GAIN),
            "vel_gain": self._cfg_prop(a, T.C_VEL_GAIN),
            "vel_integrator_gain": self._cfg_prop(a, T.C_VEL_INT_GAIN),
            "vel_limit": self._cfg_prop(a, T.C_VEL_LIMIT, check_positive=True),
            "vel_limit_tolerance": self._cfg_prop(a, T.C_VEL_TOL, check_positive=True),
        })
        controller = _Node(dev, path + ".controller", {
            "input_pos": self._cfg_prop(a, T.C_INPUT_POS),
            "input_vel": self._cfg_prop(a, T.C_INPUT_VEL),
            "input_torque": self._cfg_prop(a, T.C_INPUT_TORQUE),
            "error": err_prop(T.I_CTRL_ERR),
            "vel_integrator_torque": _Prop(lambda: float(st.AS[0, a, T.S_INTEGRATOR])),
        }, {"config": ctrl_cfg})
        mcfg_props = {
            "pole_pairs": _Prop(lambda: ax["pole_pairs"], lambda v: ax.__setitem__("pole_pairs", v), int),
            "torque_constant": self._cfg_prop(a, T.C_KT, check_positive=True),
            "motor_type": _Prop(lambda: ax["motor_type"], lambda v: ax.__setitem__("motor_type", v), int),
            "current_control_bandwidth": self._cfg_prop(a, T.C_CURRENT_BW, check_positive=True),
        }
        iq = _Prop(lambda: float(st.AS[0, a, T.S_IQ_MEAS]))
        iq_sp = _Prop(lambda: float(st.AS[0, a, T.S_IQ]))
        counts = _Prop(lambda: int(st.AI[0, a, T.I_COUNTS]), None, int)
        pos = _Prop(lambda: float(st.AS[0, a, T.S_POS_EST]))
        vel = _Prop(lambda: float(st.AS[0, a, T.S_VEL_EST]))
        axis_cfg_props = {
            "enable_watchdog": _Prop(lambda: ax["enable_watchdog"], lambda v: self._set_watchdog(a, enable=v), bool),
            "watchdog_timeout": _Prop(lambda: ax["watchdog_timeout"], lambda v: self._set_watchdog(a, timeout=v)),
        }
        axis_props = {
            "requested_state": _Prop(lambda: ax["requested_state"], lambda v: self._request_state(a, v), int),
            "current_state": _Prop(lambda: ax["state"], None, int),
            "error": err_prop(T.I_AXIS_ERR),
        }
        methods = {"watchdog_feed": lambda: self._feed(a)}
        if self.firmware == "0.5":
            mcfg_props["current_lim"] = self._cfg_prop(a, T.C_CURRENT_LIM, check_positive=True)
            motor = _Node(dev, path + ".motor", {
                "error": err_prop(T.I_MOTOR_ERR),
                "is_calibrated": _Prop(lambda: ax["calibrated"], None, bool),
            }, {"config": _Node(dev, path + ".motor.config", mcfg_props),
                "current_control": _Node(dev, path + ".motor.current_control",
                                         {"Iq_measured": iq, "Iq_setpoint": iq_sp})})
            encoder = _Node(dev, path + ".encoder", {
                "pos_estimate": pos, "vel_estimate": vel, "shadow_count": counts,
                "is_ready": _Prop(lambda: ax["encoder_ready"], None, bool),
                "error": _Prop(lambda: ax["encoder_error"], lambda v: ax.__setitem__("encoder_error", v), int),
            }, {"config": _Node(dev, path + ".encoder.config", {
                "cpr": _Prop(lambda: ax["cpr"], lambda v: ax.__setitem__("cpr", v), int),
                "bandwidth": self._cfg_prop(a, T.C_ENCODER_BW, check_positive=True)})})
            children = {"controller": controller, "motor": motor, "encoder": encoder,
                        "config": _Node(dev, path + ".config", axis_cfg_props)}
        else:
            mcfg_props["current_soft_max"] = self._cfg_prop(a, T.C_CURRENT_LIM, check_positive=True)
            motor = _Node(dev, path + ".motor", {"error": err_prop(T.I_MOTOR_ERR),
                                                 "is_calibrated": _Prop(lambda: ax["calibrated"], None, bool)},
                          {"foc": _Node(dev, path + ".motor.foc", {"Iq_measured": iq, "Iq_setpoint": iq_sp})})
            axis_props.update({"pos_estimate": pos, "vel_estimate": vel})
            axis_cfg_props["encoder_cpr"] = _Prop(lambda: ax["cpr"], lambda v: ax.__setitem__("cpr", v), int)
            children = {"controller": controller, "motor": motor,
                        "config": _Node(dev, path + ".config", axis_cfg_props,
                                        {"motor": _Node(dev, path + ".config.motor", mcfg_props)})}
            methods["clear_errors"] = lambda: self._clear_errors(a)
        return _Node(dev, path, axis_props, children, methods)

    def _feed(self, a):
        self.st.AS[0, a, T.S_WD_TIMER] = 0.0

    def _save_configuration(self):
        if any(ax["state"] == AXIS_STATE_CLOSED_LOOP_CONTROL for ax in self._axis):
            raise RuntimeError("save_configuration refused: an axis is in closed loop (set IDLE first)")
        self.saved_configuration = {
            "brake_resistance": self._brake_resistance,
            "axes": [{k: ax[k] for k in ("cpr", "pole_pairs", "motor_type", "enable_watchdog", "watchdog_timeout")}
                     | {"C": self.st.C[0, a].copy()} for a, ax in enumerate(self._axis)]}
        return True

    def _build_tree(self) -> _Node:
        def set_brake(v):
            if v <= 0:
                raise ValueError("odrv.config.brake_resistance must be positive")
            self._brake_resistance = v
        minor = 5 if self.firmware == "0.5" else 6
        props = {
            "vbus_voltage": _Prop(lambda: 24.0 + 0.05 * float(self._rng.standard_normal())),
            "serial_number": _Prop(lambda: 0x3A7F1E2D4B00 + self.twin.seed, None, int),
            "fw_version_major": _Prop(lambda: 0, None, int),
            "fw_version_minor": _Prop(lambda: minor, None, int),
            "fw_version_revision": _Prop(lambda: 6 if minor == 5 else 11, None, int),
            "hw_version_major": _Prop(lambda: 3, None, int),
            "hw_version_minor": _Prop(lambda: 6, None, int),
        }
        methods = {"save_configuration": self._save_configuration,
                   "clear_errors": self._clear_errors}
        return _Node(self, "odrv", props, {
            "axis0": self._axis_tree(0), "axis1": self._axis_tree(1),
            "config": _Node(self, "odrv.config", {"brake_resistance": _Prop(lambda: self._brake_resistance, set_brake)}),
        }, methods)

    # the tree's attributes are the device's
    def __getattr__(self, name):
        if name.startswith("_") or name in ("twin", "st", "firmware", "realtime"):
            raise AttributeError(name)
        return getattr(self._tree, name)

    def __setattr__(self, name, value):
        if name in ("axis0", "axis1", "config", "vbus_voltage"):
            setattr(self._tree, name, value)
        else:
            object.__setattr__(self, name, value)

    def __dir__(self):
        return dir(self._tree)

    # -- whole experiments through the kernel (inputs known in advance) ------------------
    def step_batch(self, gains, **kwargs) -> dict:
        """Run Listing 7.4's step for each gain triple from the leg at rest (see
        :meth:`leglib.twin.Twin.step_batch`); the device ends IDLE, at rest, with virtual
        time advanced by the steps' duration plus the settling wait. Counts as one
        transaction (for disconnect injection)."""
        self._check_link()
        self.transactions += 1
        for a in range(2):
            if not (self._axis[a]["calibrated"] and self._axis[a]["encoder_ready"]):
                raise RuntimeError(f"axis{a} is not calibrated: run the calibration first")
        out = self.twin.step_batch(gains, **kwargs)
        duration = kwargs.get("duration", 1.5)
        n = len(np.atleast_2d(gains))
        rest = self.twin.rest_state()
        t_now = self.time + n * (duration + 2.0)
        for arr_name in ("X", "AS", "AI", "RNG"):
            getattr(self.st, arr_name)[...] = getattr(rest, arr_name)
        self.st.X[0, 4] = t_now
        last = np.atleast_2d(gains)[-1]
        for a in range(2):
            self.st.AI[0, a, T.I_MODE] = T.MODE_IDLE
            self._axis[a]["state"] = AXIS_STATE_IDLE
            self.st.C[0, a, [T.C_POS_GAIN, T.C_VEL_GAIN, T.C_VEL_INT_GAIN]] = last
        return out


# ---------------------------------------------------------------------------------------
# the virtual ODrive through the odrive client: find_any, device_of (leglib.fibre_device)
# ---------------------------------------------------------------------------------------

def find_any(*, seed: int = 0, plant="default", firmware: str = "0.5.6", realtime: bool = False,
             timeout: float | None = None, serial_number=None, **options):
    """A drop-in for ``odrive.find_any()``: the virtual ODrive v3.6 of ``seed`` as the
    installed ``odrive`` client's object tree.

    The client builds its tree from the firmware's own endpoint table and talks to the
    firmware model by endpoint id (:mod:`leglib.fibre_device`), so the object is the same
    kind as a USB device's: ``odrv.axis0.controller.config.pos_gain = 50``,
    ``odrv.save_configuration()``, ``odrive.utils.dump_errors(odrv)``.

    Parameters
    ----------
    seed : int
        Identifies the device: its serial number is derived from it, and the same seed
        gives the same device (and the same noise) for the life of the process.
    plant : str, path or PlantParams
        The simulated leg (``data/params/plant_<name>.toml``).
    firmware : str
        "0.5.6" (default; "0.5" is an alias) or "0.5.1": the endpoint table served. An
        ODrive v3.6 has no 0.6 firmware: "0.6" raises ValueError.
    realtime : bool
        Pace the virtual clock to the wall clock, so scripts that ``time.sleep`` and
        ``time.time()`` (the thesis's listings) see the leg move in real time.
    timeout : float or None
        Accepted as ``odrive.find_any`` does; the virtual device is always present.
    serial_number : str or int, optional
        Find the device by serial number (hex string as the client reports it) instead.
    **options
        ``config`` (initial ODrive configuration), ``noise``, ``disconnect_after``.

    Returns
    -------
    odrive.sync_tree.SyncObject
        The client's object. After the device reboots (``save_configuration()`` on
        0.5.2+, ``reboot()``) it raises ``odrive.DeviceLostException``; call ``find_any``
        with the same seed for a new handle to the same device and its saved configuration.
    """
    from . import fibre_device
    return fibre_device.find_any(seed=seed, plant=plant, firmware=firmware, realtime=realtime,
                                 timeout=timeout, serial_number=serial_number, **options)


def device_of(odrv):
    """The :class:`VirtualODrive` behind a client object from :func:`find_any` (or any node
    of its tree, or a :class:`leglib.odrive_io.Device`); None for a USB ODrive."""
    from . import fibre_device
    return fibre_device.device_of(odrv)
