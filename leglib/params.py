"""Physical parameters: TOML files -> frozen dataclasses in SI units.

Every constant in ``data/params/*.toml`` is an inline table ``{ value, unit, source }``.
The loader converts ``unit`` to SI, checks that it has the dimension the field expects and
that the value is finite and in range, and raises :class:`ParameterError` (a ``ValueError``)
naming the file and the field otherwise. Nothing silently defaults: every field of a
dataclass must be present in its file.

Public entry points: :func:`load_leg`, :func:`load_motor`, :func:`load_odrive_config`.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

PARAMS_DIR = Path(__file__).resolve().parent.parent / "data" / "params"

# unit string -> (factor to SI, SI unit string). The SI unit string is what a field declares.
_UNITS: dict[str, tuple[float, str]] = {
    "m": (1.0, "m"),
    "mm": (1e-3, "m"),
    "cm": (1e-2, "m"),
    "kg": (1.0, "kg"),
    "g": (1e-3, "kg"),
    "kg*m": (1.0, "kg*m"),
    "kg*m^2": (1.0, "kg*m^2"),
    "g*cm^2": (1e-7, "kg*m^2"),
    "N*m": (1.0, "N*m"),
    "N*m*s/rad": (1.0, "N*m*s/rad"),
    "N*m/A": (1.0, "N*m/A"),
    "N*m/rad": (1.0, "N*m/rad"),
    "V*s/rad": (1.0, "V*s/rad"),
    "V/A": (1.0, "V/A"),
    "rad": (1.0, "rad"),
    "deg": (math.pi / 180.0, "rad"),
    "rad/s": (1.0, "rad/s"),
    "rpm/V": (2.0 * math.pi / 60.0, "rad/s/V"),
    "m/s^2": (1.0, "m/s^2"),
    "s": (1.0, "s"),
    "ms": (1e-3, "s"),
    "Hz": (1.0, "Hz"),
    "A": (1.0, "A"),
    "ohm": (1.0, "ohm"),
    "mohm": (1e-3, "ohm"),
    "H": (1.0, "H"),
    "mH": (1e-3, "H"),
    "-": (1.0, "-"),
    "count/turn": (1.0, "count/turn"),
    "count": (1.0, "count"),
    # ODrive-native units are kept native in OdriveConfig: they exist only at the device boundary.
    "turn/s": (1.0, "turn/s"),
    "(turn/s)/turn": (1.0, "(turn/s)/turn"),
    "N*m/(turn/s)": (1.0, "N*m/(turn/s)"),
    "N*m/turn": (1.0, "N*m/turn"),
}


class ParameterError(ValueError):
    """A parameter file is missing, malformed, or holds an invalid value."""


def _p(section: str, unit: str, check: str = "positive"):
    """Field metadata: TOML section, expected SI unit, value check.

    check is one of "positive", "nonnegative", "finite", "count" (positive integer),
    "index" (non-negative integer), "sign" (+1 or -1), "string" (plain TOML string, no unit).
    """
    return field(metadata={"section": section, "unit": unit, "check": check})


def _resolve(name_or_path: str | Path, prefix: str) -> Path:
    p = Path(name_or_path)
    if p.suffix == ".toml" or p.exists():
        if not p.exists():
            raise ParameterError(f"{p}: parameter file not found")
        return p
    candidate = PARAMS_DIR / f"{prefix}_{name_or_path}.toml"
    if not candidate.exists():
        known = sorted(q.stem[len(prefix) + 1:] for q in PARAMS_DIR.glob(f"{prefix}_*.toml"))
        raise ParameterError(
            f"no parameter set named {name_or_path!r} (looked for {candidate}); known: {known}")
    return candidate


def _check_value(path: Path, key: str, value: Any, check: str) -> float | int:
    where = f"{path}: field {key!r}"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ParameterError(f"{where}: value must be a number, got {value!r}")
    if not math.isfinite(value):
        raise ParameterError(f"{where}: value must be finite, got {value!r}")
    if check == "positive" and not value > 0:
        raise ParameterError(f"{where}: value must be positive, got {value!r}")
    if check == "nonnegative" and value < 0:
        raise ParameterError(f"{where}: value must be non-negative, got {value!r}")
    if check == "sign":
        if value not in (-1, 1):
            raise ParameterError(f"{where}: value must be +1 or -1, got {value!r}")
        return int(value)
    if check in ("count", "index"):
        if float(value) != int(value):
            raise ParameterError(f"{where}: value must be an integer, got {value!r}")
        if check == "count" and value <= 0:
            raise ParameterError(f"{where}: value must be a positive integer, got {value!r}")
        if check == "index" and value < 0:
            raise ParameterError(f"{where}: value must be a non-negative integer, got {value!r}")
        return int(value)
    return value


def load_dataclass(cls, path: Path, overrides: dict[str, float] | None = None):
    """Read ``path`` into dataclass ``cls`` whose fields carry :func:`_p` metadata."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            doc = tomllib.load(fh)
    except FileNotFoundError:
        raise ParameterError(f"{path}: parameter file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise ParameterError(f"{path}: not valid TOML: {exc}") from None

    values: dict[str, Any] = {}
    sources: dict[str, str] = {}
    for f in dataclasses.fields(cls):
        if not f.metadata:
            continue
        section, si_unit, check = f.metadata["section"], f.metadata["unit"], f.metadata["check"]
        key = f"{section}.{f.name}"
        table = doc.get(section)
        if not isinstance(table, dict) or f.name not in table:
            raise ParameterError(f"{path}: missing field {key!r} [{si_unit}]")
        entry = table[f.name]
        if check == "string":
            if not isinstance(entry, str) or not entry:
                raise ParameterError(f"{path}: field {key!r} must be a non-empty string, "
                                     f"got {entry!r}")
            values[f.name] = entry
            continue
        if not isinstance(entry, dict) or "value" not in entry or "unit" not in entry:
            raise ParameterError(
                f"{path}: field {key!r} must be an inline table {{ value = ..., unit = \"...\", "
                f"source = \"...\" }}, got {entry!r}")
        unit = entry["unit"]
        if unit not in _UNITS:
            raise ParameterError(f"{path}: field {key!r}: unknown unit {unit!r}")
        factor, dim = _UNITS[unit]
        if dim != si_unit:
            raise ParameterError(
                f"{path}: field {key!r}: unit {unit!r} is {dim}, expected a unit of {si_unit}")
        raw = _check_value(path, key, entry["value"], check)
        values[f.name] = raw if isinstance(raw, int) and factor == 1.0 else raw * factor
        sources[f.name] = str(entry.get("source", ""))
    for name, val in (overrides or {}).items():
        if name not in values:
            raise ParameterError(f"{path}: override of unknown field {name!r}")
        values[name] = val
    obj = cls(**values, source_file=str(path))
    object.__setattr__(obj, "_sources", sources)
    return obj


@dataclass(frozen=True)
class LegParams:
    """Five-bar leg: geometry, masses, inertias, damping, operating point (SI).

    Link numbering follows the thesis (Fig. 5.1, after Spong): links 1 and 2 are the driven
    upper links on the coaxial shafts (joint angles q1, q2 measured from +x,
    counter-clockwise); link 3 hangs from the end of link 2 and link 4 from the end of
    link 1; the foot is the joint of links 3 and 4.
    """

    l1: float = _p("geometry", "m")
    l2: float = _p("geometry", "m")
    l3: float = _p("geometry", "m")
    l4: float = _p("geometry", "m")
    m1: float = _p("mass", "kg")
    m2: float = _p("mass", "kg")
    m3: float = _p("mass", "kg")
    m4: float = _p("mass", "kg")
    lc1: float = _p("com", "m")
    lc2: float = _p("com", "m")
    lc3: float = _p("com", "m")
    lc4: float = _p("com", "m")
    I1: float = _p("inertia", "kg*m^2")
    I2: float = _p("inertia", "kg*m^2")
    I3: float = _p("inertia", "kg*m^2")
    I4: float = _p("inertia", "kg*m^2")
    Jd1: float = _p("inertia", "kg*m^2", "nonnegative")
    Jd2: float = _p("inertia", "kg*m^2", "nonnegative")
    c11: float = _p("damping", "N*m*s/rad", "nonnegative")
    c12: float = _p("damping", "N*m*s/rad", "finite")
    c21: float = _p("damping", "N*m*s/rad", "finite")
    c22: float = _p("damping", "N*m*s/rad", "nonnegative")
    coulomb1: float = _p("damping", "N*m", "nonnegative")
    coulomb2: float = _p("damping", "N*m", "nonnegative")
    g: float = _p("environment", "m/s^2", "nonnegative")
    q1: float = _p("operating_point", "rad", "finite")
    q2: float = _p("operating_point", "rad", "finite")
    gear_ratio: float = _p("drive", "-")
    encoder_cpr: int = _p("drive", "count/turn", "count")
    axis_of_q1: int = _p("drive", "-", "index")
    axis_of_q2: int = _p("drive", "-", "index")
    direction: int = _p("drive", "-", "sign")
    source_file: str = ""

    def replace(self, **changes) -> "LegParams":
        """A copy with some fields changed (e.g. ``leg.replace(g=0.0)``)."""
        new = dataclasses.replace(self, **changes)
        object.__setattr__(new, "_sources", getattr(self, "_sources", {}))
        return new

    def scaled(self, inertia: float = 1.0, mass: float = 1.0, payload: float = 0.0) -> "LegParams":
        """The same leg with inertias (links and drives) times ``inertia``, masses times
        ``mass``, and a point mass ``payload`` [kg] on the foot, folded into link 4 (exact
        for a mass on the foot joint, which is link 4's end)."""
        m4, lc4, I4 = self.m4 * mass, self.lc4, self.I4 * inertia
        if payload > 0:
            lc4_new = (m4 * lc4 + payload * self.l4) / (m4 + payload)
            I4 = I4 + m4 * (lc4_new - lc4) ** 2 + payload * (self.l4 - lc4_new) ** 2
            m4, lc4 = m4 + payload, lc4_new
        return self.replace(m1=self.m1 * mass, m2=self.m2 * mass, m3=self.m3 * mass, m4=m4, lc4=lc4,
                            I1=self.I1 * inertia, I2=self.I2 * inertia, I3=self.I3 * inertia, I4=I4,
                            Jd1=self.Jd1 * inertia, Jd2=self.Jd2 * inertia)

    @property
    def q0(self) -> tuple[float, float]:
        """Operating point (q1, q2) [rad]."""
        return (self.q1, self.q2)

    @property
    def damping_matrix(self):
        import numpy as np
        return np.array([[self.c11, self.c12], [self.c21, self.c22]])

    def source(self, name: str) -> str:
        """Where the value of field ``name`` comes from (the TOML ``source`` text)."""
        return getattr(self, "_sources", {}).get(name, "")


@dataclass(frozen=True)
class MotorParams:
    """BLDC motor (T-motor MN5212 KV340) and the thesis's electrical model (Table 6.1)."""

    kv: float = _p("motor", "rad/s/V")
    torque_constant: float = _p("motor", "N*m/A")
    phase_resistance: float = _p("motor", "ohm")
    pole_pairs: int = _p("motor", "-", "count")
    max_continuous_current: float = _p("motor", "A")
    idle_current: float = _p("motor", "A")
    Ra: float = _p("bldc_model", "ohm")
    La: float = _p("bldc_model", "H")
    Kt: float = _p("bldc_model", "N*m/A")
    tm: float = _p("bldc_model", "s")
    J: float = _p("bldc_model", "kg*m^2")
    phases: int = _p("bldc_model", "-", "count")
    Kb: float = _p("bldc_model", "V*s/rad")
    B1: float = _p("bldc_model", "N*m*s/rad", "nonnegative")
    Hc: float = _p("bldc_model", "V/A")
    inverter_time_constant: float = _p("bldc_model", "s")
    source_file: str = ""


@dataclass(frozen=True)
class OdriveConfig:
    """ODrive configuration (Listing 7.1) in the device's native units (turns, turn/s)."""

    current_lim: float = _p("config", "A")
    vel_limit: float = _p("config", "turn/s")
    brake_resistance: float = _p("config", "ohm")
    pole_pairs: int = _p("config", "-", "count")
    torque_constant: float = _p("config", "N*m/A")
    motor_type: int = _p("config", "-", "index")
    cpr: int = _p("config", "count/turn", "count")
    loop_frequency: float = _p("firmware", "Hz")
    current_control_bandwidth: float = _p("firmware", "rad/s")
    encoder_bandwidth: float = _p("firmware", "rad/s")
    vel_limit_tolerance: float = _p("firmware", "-")
    step_vel_limit: float = _p("experiment", "turn/s")
    max_pos_gain: float = _p("experiment", "(turn/s)/turn")
    max_vel_gain: float = _p("experiment", "N*m/(turn/s)")
    max_vel_integrator_gain: float = _p("experiment", "N*m/turn")
    source_file: str = ""


@dataclass(frozen=True)
class PlantParams:
    """The virtual leg's plant (data/params/plant_*.toml): what the twin simulates.

    The twin's true leg is the base leg set ``leg_set`` with inertias and masses scaled,
    a payload at the foot, and its own friction (viscous, Coulomb, Stribeck per joint).
    """

    leg_set: str = _p("leg", "", "string")
    mechanism: str = _p("leg", "", "string")
    inertia_scale: float = _p("scale", "-")
    mass_scale: float = _p("scale", "-")
    payload_mass: float = _p("scale", "kg", "nonnegative")
    viscous1: float = _p("friction", "N*m*s/rad", "nonnegative")
    viscous2: float = _p("friction", "N*m*s/rad", "nonnegative")
    coulomb1: float = _p("friction", "N*m", "nonnegative")
    coulomb2: float = _p("friction", "N*m", "nonnegative")
    stribeck1: float = _p("friction", "N*m", "nonnegative")
    stribeck2: float = _p("friction", "N*m", "nonnegative")
    stribeck_velocity: float = _p("friction", "rad/s")
    coulomb_smoothing: float = _p("friction", "rad/s")
    gap_min: float = _p("stop", "rad", "nonnegative")
    gap_max: float = _p("stop", "rad")
    stop_stiffness: float = _p("stop", "N*m/rad", "nonnegative")
    stop_damping: float = _p("stop", "N*m*s/rad", "nonnegative")
    encoder_noise: float = _p("sensing", "count", "nonnegative")
    current_noise: float = _p("sensing", "A", "nonnegative")
    usb_latency: float = _p("sensing", "s", "nonnegative")
    usb_jitter: float = _p("sensing", "-", "nonnegative")
    calibration_time: float = _p("sensing", "s", "nonnegative")
    source_file: str = ""

    def replace(self, **changes) -> "PlantParams":
        """A copy with some fields changed, e.g. ``plant.replace(payload_mass=0.5)``."""
        return dataclasses.replace(self, **changes)

    def base_leg(self) -> "LegParams":
        """The base leg parameter set named by ``leg_set``."""
        p = Path(self.leg_set)
        if not p.is_absolute() and p.suffix == ".toml" and self.source_file:
            p = Path(self.source_file).parent / p
        return load_leg(p if p.suffix == ".toml" else self.leg_set)


def load_plant(name_or_path: str | Path = "default", **overrides) -> PlantParams:
    """Load a twin plant (``"default"`` -> ``data/params/plant_default.toml``)."""
    plant = load_dataclass(PlantParams, _resolve(name_or_path, "plant"), overrides)
    if plant.mechanism not in ("fivebar", "independent"):
        raise ParameterError(f"{plant.source_file}: field 'leg.mechanism' must be 'fivebar' or "
                             f"'independent', got {plant.mechanism!r}")
    return plant


def load_leg(name_or_path: str | Path = "thesis", **overrides) -> LegParams:
    """Load leg parameters.

    Parameters
    ----------
    name_or_path : str or Path
        A shipped set name (``"thesis"`` -> ``data/params/leg_thesis.toml``) or a path.
    **overrides
        Field values (SI) replacing the file's, e.g. ``g=0.0``.
    """
    leg = load_dataclass(LegParams, _resolve(name_or_path, "leg"), overrides)
    if leg.lc1 > leg.l1 or leg.lc2 > leg.l2:
        raise ParameterError(f"{leg.source_file}: centre of mass lc1/lc2 lies beyond its link")
    if {leg.axis_of_q1, leg.axis_of_q2} != {0, 1}:
        raise ParameterError(f"{leg.source_file}: fields 'drive.axis_of_q1' and "
                             f"'drive.axis_of_q2' must be 0 and 1 in some order")
    return leg


def load_motor(name_or_path: str | Path = "mn5212") -> MotorParams:
    """Load motor parameters (``"mn5212"`` is the thesis's motor)."""
    return load_dataclass(MotorParams, _resolve(name_or_path, "motor"))


def load_odrive_config(name_or_path: str | Path = "thesis") -> OdriveConfig:
    """Load an ODrive configuration (``"thesis"`` is Listing 7.1)."""
    return load_dataclass(OdriveConfig, _resolve(name_or_path, "odrive"))
