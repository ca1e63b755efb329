"""Physical parameters: TOML files -> frozen dataclasses in SI units.

Every constant of a parameter file is an inline table ``{ value, unit, source }``.
The loader converts ``unit`` to SI, checks that it has the dimension the field expects and
that the value is finite, in range and plausible (the fields a typo or a wrong unit makes
absurd carry physical or configured bounds: ``current_lim``, the gain maxima, ``payload_mass``,
``gear_ratio``, the cprs, ``usb_latency``, ...), and raises :class:`ParameterError` (a ``ValueError``)
naming the file and the field otherwise. Nothing silently defaults: every field of a
dataclass must be present in its file, and nothing is silently ignored: a section, field or
inline-table key the dataclass does not declare is an error with a "did you mean".

Keyword overrides (``load_leg("thesis", g=0.0)``, ``load_plant(payload_mass=0.5)``) are SI
values and pass the same checks as the file's values. After the field checks, each loader
checks the relations between fields: a centre of mass inside its link, a five-bar that
closes at the operating point, ``gap_min < gap_max``, enums in range, a plant's ``leg_set``
that exists. Every check runs once, at load; :meth:`LegParams.replace` and
:meth:`LegParams.scaled` are programmatic and unchecked (identification builds legs with
zero masses on purpose).

Public entry points: :func:`load_leg`, :func:`load_motor`, :func:`load_odrive_config`,
:func:`load_plant` (and :func:`plant_names`, the plants that can be loaded by name).

Where the files are
-------------------
A name (``load_leg("thesis")``) means ``<kind>_<name>.toml`` (``leg_thesis.toml``), looked
for in the user's directories first -- every directory of the environment variable
``LEGLIB_PARAMS`` (separated by ``os.pathsep``), then ``data/params/`` of the current
directory -- and then among the files shipped inside the package (this directory,
:data:`SHIPPED_DIR`). A path (anything ending in ``.toml``, or an existing file) is read as
it is. Every loaded dataclass records the file it came from (``source_file``).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from .. import checks
from ..errors import ParameterError

# the parameter files shipped with leglib (package data), and the user's own directories
SHIPPED_DIR = Path(str(resources.files(__name__)))
USER_DIR = Path("data") / "params"     # relative to the current directory
ENV_VAR = "LEGLIB_PARAMS"
PARAMS_DIR = SHIPPED_DIR   # the name earlier versions used


def search_path() -> list[Path]:
    """The directories a parameter set's name is looked for in, in order: ``$LEGLIB_PARAMS``,
    ``data/params/`` of the current directory (where they exist), then the shipped files."""
    dirs = [Path(d) for d in os.environ.get(ENV_VAR, "").split(os.pathsep) if d]
    dirs.append(USER_DIR)
    out = []
    for d in dirs:
        if d.is_dir() and d.resolve() not in [o.resolve() for o in out] and d.resolve() != SHIPPED_DIR:
            out.append(d)
    return out + [SHIPPED_DIR]

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
    "mN*m": (1e-3, "N*m"),
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




_ENTRY_KEYS = ("value", "unit", "source")

# enums with their allowed values (ODrive firmware 0.5: MOTOR_TYPE_HIGH_CURRENT = 0,
# MOTOR_TYPE_GIMBAL = 2, MOTOR_TYPE_ACIM = 3)
_ENUMS: dict[str, tuple] = {"motor_type": (0, 2, 3), "mechanism": ("fivebar", "independent")}


def _did_you_mean(name: str, known) -> str:
    close = difflib.get_close_matches(str(name), list(known), n=1, cutoff=0.6)
    return f"; did you mean {close[0]!r}?" if close else f"; known: {', '.join(sorted(known))}"


def _short(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit] + "...'"


def _p(section: str, unit: str, check: str = "positive", bounds: tuple | None = None,
       plausible: tuple | None = None):
    """Field metadata: TOML section, expected SI unit, value check, plausible range.

    check is one of "positive", "nonnegative", "finite", "count" (positive integer),
    "index" (non-negative integer), "sign" (+1 or -1), "string" (plain TOML string, no unit).
    bounds is ``(low, high, why)``: the SI value must lie in [low, high] (None: no bound on
    that side), ``why`` says where the bound comes from; checked for file values and
    keyword overrides alike. ``plausible`` has the same form: the physical range of a leg of
    this class, which a loader's named flag (``allow_implausible``) may waive for a leg
    that really is outside it.
    """
    meta = {"section": section, "unit": unit, "check": check}
    if bounds is not None:
        meta["bounds"] = bounds
    if plausible is not None:
        meta["plausible"] = plausible
    return field(metadata=meta)


# plausible ranges of the fields a typo or a wrong unit makes absurd (SI, or the ODrive's units)
# a leg of this class: a coaxial five-bar of two hobby BLDC motors (T-motor MN5212) through
# 1:3 belts (Stanford Doggo: links 0.09 and 0.162 m, 55-100 g each, about 1e-3 kg m^2 of drive
# inertia per joint); ten times beyond these on either side is a typo or a wrong unit
_LENGTH = (0.01, 1.0, "a link of a leg of this class: Doggo's are 0.09 and 0.162 m")
_MASS = (1e-3, 5.0, "a link of a leg of this class: Doggo's weigh 55-100 g, and its motors lift well under "
                    "1 kg at the foot")
_LINK_INERTIA = (None, 0.05, "a link's inertia about its centre of mass, at most m l^2 (about 2e-4 kg*m^2 for "
                             "Doggo's lower link)")
_DRIVE_INERTIA = (None, 0.05, "pulley, shaft and rotor through the belt (about 1e-3 kg*m^2 on the thesis's leg)")
_CPR = (12, 1 << 24, "an ODrive encoder mode gives 12 (hall sensors) to 2^24 counts per turn")
_VEL = (None, 300.0, "the MN5212 KV340 at the ODrive v3.6's 56 V turns at most 317 turn/s")


def _resolve(name_or_path: str | Path, prefix: str) -> Path:
    p = Path(name_or_path)
    if p.suffix == ".toml" or p.exists():
        if not p.exists():
            raise ParameterError(f"{p}: parameter file not found")
        return p
    name = f"{prefix}_{name_or_path}.toml"
    dirs = search_path()
    for d in dirs:
        candidate = d / name
        if candidate.is_file():
            return candidate
    raise ParameterError(f"no parameter set named {name_or_path!r}: {name} is in none of "
                         f"{[str(d) for d in dirs]} (${ENV_VAR}, ./{USER_DIR}, then the shipped files); "
                         f"known: {_names(prefix)}")


def _names(prefix: str) -> list[str]:
    return sorted({q.stem[len(prefix) + 1:] for d in search_path() for q in d.glob(f"{prefix}_*.toml")})


def _check_value(path: str, key: str, value: Any, check: str) -> float | int:
    where = f"{path}: field {key!r}"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ParameterError(f"{where}: value must be a number, got {_short(value)}")
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


def _read_toml(path: Path) -> dict:
    """The TOML document at ``path``; ParameterError for anything but a readable regular
    UTF-8 TOML file of sane size."""
    text = checks.text_file(path, "parameter file", ParameterError, form="TOML", max_bytes=_MAX_TOML_BYTES)
    try:
        return tomllib.loads(text), text
    except tomllib.TOMLDecodeError as exc:
        raise ParameterError(f"{path}: not valid TOML: {str(exc)[:200]}") from None


def _locate(path: Path, text: str, section: str, name: str | None = None) -> str:
    """``path:line`` of ``[section]`` (or of ``name = `` inside it); ``path`` when not found."""
    sec_line, lines = None, text.splitlines()
    for i, line in enumerate(lines, start=1):
        stripped = line.strip()
        if stripped.startswith("["):
            if sec_line is not None and name is not None:
                break
            if stripped.split("#")[0].strip() == f"[{section}]":
                sec_line = i
                if name is None:
                    return f"{path}:{i}"
        elif sec_line is not None and name is not None:
            key = stripped.split("=")[0].strip().strip('"\'')
            if key == name:
                return f"{path}:{i}"
    return str(path)


_MAX_TOML_BYTES = 1 << 20


def _check_entry(where: str, key: str, value: Any, check: str, si_unit: str):
    """One field's SI value: type, finiteness, range; returns it (ints for integer checks)."""
    if check == "string":
        if not isinstance(value, str) or not value:
            raise ParameterError(f"{where}: field {key!r} must be a non-empty string, got {_short(value)}")
        return value
    return _check_value(where, key, value, check)


def load_dataclass(cls, path: Path, overrides: dict[str, Any] | None = None, allow_implausible: bool = False,
                   flag_hint: str = ""):
    """Read ``path`` into dataclass ``cls`` whose fields carry :func:`_p` metadata.

    Every section, field and inline-table key of the file must be one the dataclass
    declares; ``overrides`` (SI values, by field name) replace file values and pass the
    same checks. Raises ParameterError naming the file (and line, where known) and field.
    ``allow_implausible`` waives the ``plausible`` ranges (not the ``bounds``);
    ``flag_hint`` is how the error tells the caller to waive them.
    """
    path = Path(path)
    doc, text = _read_toml(path)
    declared = {f.name: f for f in dataclasses.fields(cls) if f.metadata}
    sections: dict[str, set] = {}
    for f in declared.values():
        sections.setdefault(f.metadata["section"], set()).add(f.name)
    for sec, table in doc.items():
        if sec not in sections:
            raise ParameterError(f"{_locate(path, text, sec)}: unknown section [{sec}]"
                                 f"{_did_you_mean(sec, sections)}")
        if not isinstance(table, dict):
            raise ParameterError(f"{path}: {sec!r} must be a section [{sec}], got {_short(table)}")
        for name, entry in table.items():
            if name not in sections[sec]:
                elsewhere = [s for s, names in sections.items() if name in names]
                hint = (f"; it belongs in section [{elsewhere[0]}]" if elsewhere
                        else _did_you_mean(name, sections[sec]))
                raise ParameterError(f"{_locate(path, text, sec, name)}: unknown field '{sec}.{name}'{hint}")
            if isinstance(entry, dict):
                for k in entry:
                    if k not in _ENTRY_KEYS:
                        raise ParameterError(f"{_locate(path, text, sec, name)}: field '{sec}.{name}': unknown key {k!r} "
                                             f"(an entry holds {', '.join(_ENTRY_KEYS)})"
                                             f"{_did_you_mean(k, _ENTRY_KEYS)}")

    values: dict[str, Any] = {}
    sources: dict[str, str] = {}
    for f in declared.values():
        section, si_unit, check = f.metadata["section"], f.metadata["unit"], f.metadata["check"]
        key = f"{section}.{f.name}"
        table = doc.get(section)
        if not isinstance(table, dict) or f.name not in table:
            raise ParameterError(f"{path}: missing field {key!r} [{si_unit}]")
        entry = table[f.name]
        at = _locate(path, text, section, f.name)
        if check == "string":
            values[f.name] = _check_entry(at, key, entry, check, si_unit)
            continue
        if not isinstance(entry, dict) or "value" not in entry or "unit" not in entry:
            raise ParameterError(
                f"{at}: field {key!r} must be an inline table {{ value = ..., unit = \"...\", "
                f"source = \"...\" }}, got {_short(entry)}")
        unit = entry["unit"]
        if not isinstance(unit, str) or unit not in _UNITS:
            raise ParameterError(f"{at}: field {key!r}: unknown unit {_short(unit)}"
                                 f"{_did_you_mean(unit, [u for u, (_, d) in _UNITS.items() if d == si_unit])}")
        factor, dim = _UNITS[unit]
        if dim != si_unit:
            raise ParameterError(
                f"{at}: field {key!r}: unit {unit!r} is {dim}, expected a unit of {si_unit}")
        raw = _check_value(at, key, entry["value"], check)
        value = raw if isinstance(raw, int) and factor == 1.0 else raw * factor
        if not math.isfinite(value):
            raise ParameterError(f"{at}: field {key!r}: {raw!r} {unit} overflows in SI")
        values[f.name] = value
        source = entry.get("source", "")
        if not isinstance(source, str):
            raise ParameterError(f"{at}: field {key!r}: source must be a string, got {_short(source)}")
        sources[f.name] = source
    for name, val in (overrides or {}).items():
        if name not in values:
            raise ParameterError(f"{path}: override of unknown field {name!r}{_did_you_mean(name, values)}")
        f = declared[name]
        values[name] = _check_entry(f"{path} (keyword override)", f"{f.metadata['section']}.{name}", val,
                                    f.metadata["check"], f.metadata["unit"])
    for name, f in declared.items():
        for kind in ("bounds", "plausible"):
            if kind not in f.metadata or isinstance(values[name], str) or (kind == "plausible" and allow_implausible):
                continue
            low, high, why = f.metadata[kind]
            v = values[name]
            if (low is not None and v < low) or (high is not None and v > high):
                sec = f.metadata["section"]
                at = (f"{path} (keyword override)" if name in (overrides or {})
                      else _locate(path, text, sec, name))
                rng = (f"[{low:g}, {high:g}]" if low is not None and high is not None
                       else f"at most {high:g}" if low is None else f"at least {low:g}")
                waive = f"; {flag_hint} to use it anyway" if kind == "plausible" and flag_hint else ""
                raise ParameterError(f"{at}: field '{sec}.{name}' = {v:g} {f.metadata['unit']} is implausible: "
                                     f"it must be {rng} ({why}){waive}")
    for name, allowed in _ENUMS.items():
        if name in values and values[name] not in allowed:
            sec = declared[name].metadata["section"]
            raise ParameterError(f"{_locate(path, text, sec, name)}: field '{sec}.{name}' must be one of "
                                 f"{allowed}, got {_short(values[name])}")
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

    l1: float = _p("geometry", "m", plausible=_LENGTH)
    l2: float = _p("geometry", "m", plausible=_LENGTH)
    l3: float = _p("geometry", "m", plausible=_LENGTH)
    l4: float = _p("geometry", "m", plausible=_LENGTH)
    m1: float = _p("mass", "kg", plausible=_MASS)
    m2: float = _p("mass", "kg", plausible=_MASS)
    m3: float = _p("mass", "kg", plausible=_MASS)
    m4: float = _p("mass", "kg", plausible=_MASS)
    lc1: float = _p("com", "m")
    lc2: float = _p("com", "m")
    lc3: float = _p("com", "m")
    lc4: float = _p("com", "m")
    I1: float = _p("inertia", "kg*m^2", plausible=_LINK_INERTIA)
    I2: float = _p("inertia", "kg*m^2", plausible=_LINK_INERTIA)
    I3: float = _p("inertia", "kg*m^2", plausible=_LINK_INERTIA)
    I4: float = _p("inertia", "kg*m^2", plausible=_LINK_INERTIA)
    Jd1: float = _p("inertia", "kg*m^2", "nonnegative", plausible=_DRIVE_INERTIA)
    Jd2: float = _p("inertia", "kg*m^2", "nonnegative", plausible=_DRIVE_INERTIA)
    c11: float = _p("damping", "N*m*s/rad", "nonnegative")
    c12: float = _p("damping", "N*m*s/rad", "finite")
    c21: float = _p("damping", "N*m*s/rad", "finite")
    c22: float = _p("damping", "N*m*s/rad", "nonnegative")
    coulomb1: float = _p("damping", "N*m", "nonnegative")
    coulomb2: float = _p("damping", "N*m", "nonnegative")
    g: float = _p("environment", "m/s^2", "nonnegative")
    q1: float = _p("operating_point", "rad", "finite")
    q2: float = _p("operating_point", "rad", "finite")
    gear_ratio: float = _p("drive", "-", bounds=(0.1, 100.0, "a belt or gear reduction of the leg's drive"))
    encoder_cpr: int = _p("drive", "count/turn", "count", bounds=_CPR)
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
    phase_inductance: float = _p("motor", "H", bounds=(1e-6, 1e-2, "a BLDC phase of 1 uH .. 10 mH; the ODrive's "
                                                        "calibration refuses beyond 2 uH .. 4 mH (motor.cpp:481)"))
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

    current_lim: float = _p("config", "A", bounds=(None, 60.0, "the ODrive v3.6's current sense range, 60 A"))
    vel_limit: float = _p("config", "turn/s", bounds=_VEL)
    brake_resistance: float = _p("config", "ohm")
    pole_pairs: int = _p("config", "-", "count")
    torque_constant: float = _p("config", "N*m/A")
    motor_type: int = _p("config", "-", "index")
    cpr: int = _p("config", "count/turn", "count", bounds=_CPR)
    loop_frequency: float = _p("firmware", "Hz")
    current_control_bandwidth: float = _p("firmware", "rad/s")
    encoder_bandwidth: float = _p("firmware", "rad/s")
    vel_limit_tolerance: float = _p("firmware", "-")
    step_vel_limit: float = _p("experiment", "turn/s", bounds=_VEL)
    max_pos_gain: float = _p("experiment", "(turn/s)/turn", bounds=(None, 1000.0, "a safety bound: the ODrive's default pos_gain is 20"))
    max_vel_gain: float = _p("experiment", "N*m/(turn/s)", bounds=(None, 10.0, "a safety bound: the ODrive's default vel_gain is 0.17"))
    max_vel_integrator_gain: float = _p("experiment", "N*m/turn", bounds=(None, 1000.0, "a safety bound: the ODrive's default vel_integrator_gain is 0.33"))
    source_file: str = ""


@dataclass(frozen=True)
class PlantParams:
    """The virtual leg's plant (``plant_<name>.toml``): what the twin simulates.

    The twin's true leg is the base leg set ``leg_set`` with inertias and masses scaled,
    a payload at the foot, and its own friction (viscous, Coulomb, Stribeck per joint).

    Effects the fitting models do not have, each off at zero (``plant_default.toml`` has
    them all off): a compliant belt drive with backlash ([belt]: the rotor, reflected
    through the belt, is its own inertia, taken out of the joint's drive inertia), cogging
    torque periodic in the motor angle ([cogging]), an encoder reading error periodic in
    the motor angle ([encoder_error]), and in [friction] direction-dependent Coulomb levels,
    LuGre presliding friction and a friction level that drifts down with joint travel.
    """

    leg_set: str = _p("leg", "", "string")
    mechanism: str = _p("leg", "", "string")
    inertia_scale: float = _p("scale", "-")
    mass_scale: float = _p("scale", "-")
    payload_mass: float = _p("scale", "kg", "nonnegative", bounds=(None, 5.0, "the leg's motors lift well under 1 kg at the foot"))
    viscous1: float = _p("friction", "N*m*s/rad", "nonnegative")
    viscous2: float = _p("friction", "N*m*s/rad", "nonnegative")
    coulomb1: float = _p("friction", "N*m", "nonnegative")
    coulomb2: float = _p("friction", "N*m", "nonnegative")
    stribeck1: float = _p("friction", "N*m", "nonnegative")
    stribeck2: float = _p("friction", "N*m", "nonnegative")
    stribeck_velocity: float = _p("friction", "rad/s")
    coulomb_smoothing: float = _p("friction", "rad/s")
    coulomb_asymmetry: float = _p("friction", "-", "finite")
    lugre_stiffness: float = _p("friction", "N*m/rad", "nonnegative")
    lugre_damping: float = _p("friction", "N*m*s/rad", "nonnegative")
    friction_drift: float = _p("friction", "-", "nonnegative")
    drift_travel: float = _p("friction", "rad")
    belt_stiffness: float = _p("belt", "N*m/rad", "nonnegative")
    belt_damping: float = _p("belt", "N*m*s/rad", "nonnegative")
    backlash: float = _p("belt", "rad", "nonnegative")
    rotor_inertia: float = _p("belt", "kg*m^2")
    cogging_periods: int = _p("cogging", "-", "count")
    cogging1: float = _p("cogging", "N*m", "nonnegative")
    cogging2: float = _p("cogging", "N*m", "nonnegative")
    cogging3: float = _p("cogging", "N*m", "nonnegative")
    cogging_phase1: float = _p("cogging", "rad", "finite")
    cogging_phase2: float = _p("cogging", "rad", "finite")
    cogging_phase3: float = _p("cogging", "rad", "finite")
    encoder_error1: float = _p("encoder_error", "rad", "nonnegative")
    encoder_error2: float = _p("encoder_error", "rad", "nonnegative")
    encoder_phase1: float = _p("encoder_error", "rad", "finite")
    encoder_phase2: float = _p("encoder_error", "rad", "finite")
    gap_min: float = _p("stop", "rad", "nonnegative")
    gap_max: float = _p("stop", "rad")
    stop_stiffness: float = _p("stop", "N*m/rad", "nonnegative")
    stop_damping: float = _p("stop", "N*m*s/rad", "nonnegative")
    encoder_noise: float = _p("sensing", "count", "nonnegative")
    current_noise: float = _p("sensing", "A", "nonnegative")
    usb_latency: float = _p("sensing", "s", "nonnegative", bounds=(None, 0.1, "a USB transaction takes about 0.4 ms; each advances the twin by it"))
    usb_jitter: float = _p("sensing", "-", "nonnegative")
    calibration_time: float = _p("sensing", "s", "nonnegative", bounds=(None, 60.0, "the firmware's motor calibration takes 4.25 s"))
    source_file: str = ""

    def replace(self, **changes) -> "PlantParams":
        """A copy with some fields changed, e.g. ``plant.replace(payload_mass=0.5)``."""
        return dataclasses.replace(self, **changes)

    @property
    def belt_compliant(self) -> bool:
        """The belt drive is compliant (the rotor is its own inertia, coupled by the belt)."""
        return self.belt_stiffness > 0.0

    @property
    def lugre(self) -> bool:
        """Joint friction is the LuGre model (presliding bristles) instead of tanh Coulomb."""
        return self.lugre_stiffness > 0.0

    @property
    def unmodeled(self) -> tuple[str, ...]:
        """The effects beyond the fitting models' structure that are on in this plant."""
        on = {"belt": self.belt_compliant, "backlash": self.backlash > 0.0,
              "cogging": self.cogging1 + self.cogging2 + self.cogging3 > 0.0,
              "encoder_error": self.encoder_error1 + self.encoder_error2 > 0.0,
              "coulomb_asymmetry": self.coulomb_asymmetry != 0.0, "lugre": self.lugre,
              "friction_drift": self.friction_drift > 0.0}
        return tuple(k for k, v in on.items() if v)

    def base_leg(self) -> "LegParams":
        """The base leg parameter set named by ``leg_set``."""
        p = Path(self.leg_set)
        if not p.is_absolute() and p.suffix == ".toml" and self.source_file:
            p = Path(self.source_file).parent / p
        return load_leg(p if p.suffix == ".toml" else self.leg_set)


def load_plant(name_or_path: str | Path = "default", **overrides) -> PlantParams:
    """Load a twin plant: the simulated physical leg behind the virtual ODrive.

    Parameters
    ----------
    name_or_path : str or Path
        A plant's name (``"default"`` -> ``plant_default.toml``; the shipped ones are
        :func:`plant_names`, see :func:`search_path`) or a path.
    **overrides
        Field values (SI) replacing the file's, e.g. ``payload_mass=0.5`` [kg].

    Returns
    -------
    PlantParams

    Raises
    ------
    ParameterError
        The file is missing or malformed, a value is out of range, or fields contradict each
        other (the stop's gaps, the jitter, the base leg set, an unmodeled effect); the
        message names the file and field.
    """
    plant = load_dataclass(PlantParams, _resolve(name_or_path, "plant"), overrides)
    where = plant.source_file
    if not plant.gap_min < plant.gap_max:
        raise ParameterError(f"{where}: fields 'stop.gap_min' ({math.degrees(plant.gap_min):g} deg) and "
                             f"'stop.gap_max' ({math.degrees(plant.gap_max):g} deg): gap_min must be "
                             f"below gap_max")
    if plant.gap_max > math.pi:
        raise ParameterError(f"{where}: field 'stop.gap_max' must be at most 180 deg, got "
                             f"{math.degrees(plant.gap_max):g} deg")
    if plant.usb_jitter > 1.0:
        raise ParameterError(f"{where}: field 'sensing.usb_jitter' is the relative spread of the latency "
                             f"and must lie in [0, 1] (a latency cannot be negative), got {plant.usb_jitter!r}")
    try:
        base = plant.base_leg()
    except ParameterError as exc:
        raise ParameterError(f"{where}: field 'leg.leg_set' = {plant.leg_set!r}: {exc}") from None
    _check_unmodeled(plant, base)
    return plant


# the encoder error's largest slope (1 + e'(angle) must stay positive: a reading that runs
# backwards is not an encoder); amplitudes are kept well inside it
_MAX_ENCODER_ERROR = 0.05   # rad of motor angle, per term (2.9 deg; the AS5047D is ~0.5 deg)


def _check_unmodeled(plant: "PlantParams", base: "LegParams") -> None:
    """Relations of the unmodeled-effect fields: ParameterError naming the file and field."""
    where = plant.source_file
    if not -1.0 < plant.coulomb_asymmetry < 1.0:
        raise ParameterError(f"{where}: field 'friction.coulomb_asymmetry' must lie in (-1, 1) (the "
                             f"Coulomb levels are coulomb * (1 +- asymmetry)), got {plant.coulomb_asymmetry!r}")
    if not plant.friction_drift < 1.0:
        raise ParameterError(f"{where}: field 'friction.friction_drift' is the fraction the friction "
                             f"levels fall by with use and must lie in [0, 1), got {plant.friction_drift!r}")
    if plant.lugre_damping > 0.0 and not plant.lugre:
        raise ParameterError(f"{where}: field 'friction.lugre_damping' needs the LuGre model "
                             f"('friction.lugre_stiffness' > 0; 0 is the tanh model)")
    if plant.lugre and not (plant.coulomb1 > 0.0 and plant.coulomb2 > 0.0):
        raise ParameterError(f"{where}: field 'friction.lugre_stiffness' > 0 (LuGre) needs a Coulomb level "
                             f"on both joints ('friction.coulomb1', 'friction.coulomb2' > 0)")
    for name in ("belt_damping", "backlash"):
        if getattr(plant, name) > 0.0 and not plant.belt_compliant:
            raise ParameterError(f"{where}: field 'belt.{name}' needs a compliant belt "
                                 f"('belt.belt_stiffness' > 0; 0 is a rigid belt)")
    if plant.backlash > math.radians(10.0):
        raise ParameterError(f"{where}: field 'belt.backlash' = {math.degrees(plant.backlash):g} deg of "
                             f"joint: a belt that loose skips teeth (at most 10 deg)")
    if plant.belt_compliant:
        reflected = plant.rotor_inertia * base.gear_ratio ** 2
        for j in (1, 2):
            jd = getattr(base, f"Jd{j}") * plant.inertia_scale
            if not reflected < jd:
                raise ParameterError(
                    f"{where}: field 'belt.rotor_inertia' = {plant.rotor_inertia:.4g} kg*m^2: reflected "
                    f"through the belt ({reflected:.4g} kg*m^2) it must be part of the joint's drive "
                    f"inertia (Jd{j} * inertia_scale = {jd:.4g} kg*m^2), which it is taken out of")
    for name in ("encoder_error1", "encoder_error2"):
        if getattr(plant, name) > _MAX_ENCODER_ERROR:
            raise ParameterError(f"{where}: field 'encoder_error.{name}' = {math.degrees(getattr(plant, name)):g} "
                                 f"deg: at most {math.degrees(_MAX_ENCODER_ERROR):.3g} deg (a magnetic "
                                 f"encoder's error is a fraction of a degree)")


def plant_names() -> list[str]:
    """The plants ``load_plant(name)`` can load by name: ``plant_<name>.toml`` in the user's
    directories or among the shipped files (:func:`search_path`)."""
    return _names("plant")


def load_leg(name_or_path: str | Path = "thesis", allow_implausible: bool = False, **overrides) -> LegParams:
    """Load the nominal leg's parameters (geometry, masses, inertias, friction, the drive).

    Parameters
    ----------
    name_or_path : str or Path
        A set's name (``"thesis"`` -> ``leg_thesis.toml``, see :func:`search_path`) or a path.
    allow_implausible : bool
        Waive the physical plausibility ranges of the lengths, masses and inertias (a leg
        of this class: links 0.01-1 m, 1 g-5 kg, a link's inertia at most m l^2 and 0.05
        kg*m^2, a drive's at most 0.05 kg*m^2), for a leg that really is outside them. Off,
        a value outside them is an error naming the file, line and field.
    **overrides
        Field values (SI) replacing the file's, e.g. ``g=0.0``.

    Returns
    -------
    LegParams
        Frozen, in SI units (m, kg, kg*m^2, rad).

    Raises
    ------
    ParameterError
        The file is missing or malformed, a value is out of range, a centre of mass lies
        beyond its link, or the five-bar cannot close at the operating point; the message
        names the file and field.
    """
    leg = load_dataclass(LegParams, _resolve(name_or_path, "leg"), overrides, allow_implausible=allow_implausible,
                         flag_hint="pass load_leg(..., allow_implausible=True)")
    _check_leg(leg, allow_implausible)
    return leg


def _check_leg(leg: "LegParams", allow_implausible: bool = False) -> None:
    """Relations between a leg's fields: ParameterError naming the file and field."""
    where = leg.source_file
    for i in (1, 2, 3, 4):
        lc, link = getattr(leg, f"lc{i}"), getattr(leg, f"l{i}")
        if lc > link:
            raise ParameterError(f"{where}: field 'com.lc{i}' = {lc:g} m lies beyond its link "
                                 f"(geometry.l{i} = {link:g} m)")
        m, inertia = getattr(leg, f"m{i}"), getattr(leg, f"I{i}")
        if not allow_implausible and inertia > m * link ** 2:
            raise ParameterError(f"{where}: field 'inertia.I{i}' = {inertia:g} kg*m^2 is implausible: a link's "
                                 f"inertia about its centre of mass is at most m{i} l{i}^2 = {m * link ** 2:g} "
                                 f"kg*m^2 (all its mass at its far end); pass load_leg(..., allow_implausible=True) "
                                 f"to use it anyway")
    if {leg.axis_of_q1, leg.axis_of_q2} != {0, 1}:
        raise ParameterError(f"{where}: fields 'drive.axis_of_q1' and "
                             f"'drive.axis_of_q2' must be 0 and 1 in some order")
    # the five-bar closes when the knees (ends of links 1 and 2) are no further apart than
    # l3 + l4 and no closer than |l3 - l4|; checked at the operating point
    d = math.hypot(leg.l1 * math.cos(leg.q1) - leg.l2 * math.cos(leg.q2),
                   leg.l1 * math.sin(leg.q1) - leg.l2 * math.sin(leg.q2))
    if not abs(leg.l3 - leg.l4) <= d <= leg.l3 + leg.l4:
        raise ParameterError(
            f"{where}: fields 'geometry.l1'..'geometry.l4' and 'operating_point.q1', 'q2': the five-bar "
            f"cannot close at the operating point (knees {d:.4g} m apart; the lower links "
            f"reach between {abs(leg.l3 - leg.l4):.4g} and {leg.l3 + leg.l4:.4g} m)")


def load_motor(name_or_path: str | Path = "mn5212", **overrides) -> MotorParams:
    """Load a motor's parameters.

    Parameters
    ----------
    name_or_path : str or Path
        A motor's name (``"mn5212"``, the thesis's T-motor MN5212 KV340) or a path.
    **overrides
        Field values (SI) replacing the file's.

    Returns
    -------
    MotorParams

    Raises
    ------
    ParameterError
        The file is missing or malformed or a value is out of range (file and field named).
    """
    return load_dataclass(MotorParams, _resolve(name_or_path, "motor"), overrides)


def load_odrive_config(name_or_path: str | Path = "thesis", **overrides) -> OdriveConfig:
    """Load an ODrive configuration: Listing 7.1's settings and the experiments' safety bounds.

    Parameters
    ----------
    name_or_path : str or Path
        A configuration's name (``"thesis"``: Listing 7.1) or a path.
    **overrides
        Field values in the ODrive's own units (A, turn/s, N*m/A, counts) replacing the file's.

    Returns
    -------
    OdriveConfig

    Raises
    ------
    ParameterError
        The file is missing or malformed or a value is out of range (file and field named).
    """
    cfg = load_dataclass(OdriveConfig, _resolve(name_or_path, "odrive"), overrides)
    if cfg.vel_limit_tolerance < 1.0:
        raise ParameterError(f"{cfg.source_file}: field 'firmware.vel_limit_tolerance' must be >= 1 "
                             f"(a factor on vel_limit), got {cfg.vel_limit_tolerance!r}")
    return cfg
