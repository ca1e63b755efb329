"""Extract the firmware's configuration defaults from its sources into
``defaults_fw-v<version>.json`` (maintainer tool; the JSON files ship with leglib).

Usage: ``python -m leglib.device.virtual.tables.extract_defaults /path/to/ODrive.git`` (a clone,
or a bare mirror, of https://github.com/odriverobotics/ODrive with the tags fw-v0.5.1 and
fw-v0.5.6).

Each ``Config_t`` (and similar) struct of the firmware's headers initializes its members,
``float calibration_current = 10.0f;``; the endpoint ``axis0.motor.config.calibration_current``
is such a member. This tool maps the endpoint prefixes to those structs (a struct nested in
a class, ``OffboardThermistorCurrentLimiter::Config_t``, by its class), evaluates the
initializers with the constants of the board the virtual ODrive presents -- an ODrive v3.6
**56 V** (the thesis's board, Table 4.1), following the headers' ``#if`` branches on
``HW_VERSION_*`` -- and the enums of the tag's own ``odrive-interface.yaml``, and writes
``{"axis*.motor.config.calibration_current": {"value": 10.0, "source":
"Firmware/MotorControl/motor.hpp:20"}, ...}``. Defaults that differ by axis (set by the
firmware when it clears the configuration) carry ``"axes": [axis0, axis1]``. Members whose
initializer it cannot evaluate are listed under ``"_unparsed"``; the virtual ODrive holds
them at zero.
"""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from pathlib import Path

from ..wire import FIRMWARE_TABLES, endpoint_table, flatten

# endpoint prefix (generic axis) -> (header, struct name, enclosing class or None)
STRUCTS = {
    "axis*.config.": ("MotorControl/axis.hpp", "Config_t", None),
    "axis*.config.can.": ("MotorControl/axis.hpp", "CANConfig_t", None),
    "axis*.config.general_lockin.": ("MotorControl/axis.hpp", "LockinConfig_t", None),
    "axis*.config.calibration_lockin.": ("MotorControl/axis.hpp", "LockinConfig_t", None),
    "axis*.config.sensorless_ramp.": ("MotorControl/axis.hpp", "LockinConfig_t", None),
    "axis*.motor.config.": ("MotorControl/motor.hpp", "Config_t", None),
    "axis*.encoder.config.": ("MotorControl/encoder.hpp", "Config_t", None),
    "axis*.controller.config.": ("MotorControl/controller.hpp", "Config_t", None),
    "axis*.controller.config.anticogging.": ("MotorControl/controller.hpp", "Anticogging_t", None),
    "axis*.trap_traj.config.": ("MotorControl/trapTraj.hpp", "Config_t", None),
    "axis*.sensorless_estimator.config.": ("MotorControl/sensorless_estimator.hpp", "Config_t", None),
    "axis*.min_endstop.config.": ("MotorControl/endstop.hpp", "Config_t", None),
    "axis*.max_endstop.config.": ("MotorControl/endstop.hpp", "Config_t", None),
    "axis*.mechanical_brake.config.": ("MotorControl/mechanical_brake.hpp", "Config_t", None),
    # the board's FET thermistors and the (optional) motor thermistors are two classes,
    # each with its own Config_t (thermistor.hpp)
    "axis*.motor.fet_thermistor.config.": ("MotorControl/thermistor.hpp", "Config_t", "OnboardThermistorCurrentLimiter"),
    "axis*.fet_thermistor.config.": ("MotorControl/thermistor.hpp", "Config_t", "OnboardThermistorCurrentLimiter"),
    "axis*.motor.motor_thermistor.config.": ("MotorControl/thermistor.hpp", "Config_t", "OffboardThermistorCurrentLimiter"),
    "axis*.motor_thermistor.config.": ("MotorControl/thermistor.hpp", "Config_t", "OffboardThermistorCurrentLimiter"),
    "axis*.acim_estimator.config.": ("MotorControl/acim_estimator.hpp", "Config_t", None),
    "config.": ("MotorControl/odrive_main.h", "BoardConfig_t", None),
    "can.config.": (("communication/can/odrive_can.hpp", "communication/interface_can.hpp"), "Config_t", None),
}
# axis.cpp overrides LockinConfig_t for these (Axis::default_calibration / default_sensorless)
LOCKIN_FUNCTIONS = {"axis*.config.calibration_lockin.": "default_calibration",
                    "axis*.config.sensorless_ramp.": "default_sensorless"}

# the board the virtual ODrive presents: an ODrive v3.6, 56 V variant (the thesis's board,
# Table 4.1). board.h:40-47 then gives a 2.0 ohm brake resistor, error pin 0, 8 V minimum.
BOARD = {"HW_VERSION_MAJOR": 3, "HW_VERSION_MINOR": 6, "HW_VERSION_VOLTAGE": 56}
CONSTANTS = {**{k: float(v) for k, v in BOARD.items()}, "DEFAULT_MIN_DC_VOLTAGE": 8.0,
             "DEFAULT_ERROR_PIN": 0, "M_PI": math.pi, "INFINITY": math.inf, "true": True,
             "false": False, "nullptr": 0, "CAN_BAUD_250K": 250000, "__cplusplus": 201703,
             # 0.5.x enum values the interface names differently (odrive-interface.yaml: ODrive.Motor.MotorType)
             "MOTOR_TYPE_HIGH_CURRENT": 0, "MOTOR_TYPE_GIMBAL": 2, "MOTOR_TYPE_ACIM": 3}

# members the firmware sets outside the struct initializers, per version: generic endpoint
# -> (value or [axis0, axis1], source). Read at the tags (file:line below).
SPECIAL = {
    "0.5.6": {
        # config_clear_all sets each axis's load encoder to itself (main.cpp:133)
        "axis*.controller.config.load_encoder_axis": ([0, 1], "Firmware/MotorControl/main.cpp:133"),
        # Axis::clear_config: node id = axis number (axis.cpp:88)
        "axis*.config.can.node_id": ([0, 1], "Firmware/MotorControl/axis.cpp:88"),
        # the axes' default step/dir pins (board.cpp:126-127, 140-141 for v3.5 and newer)
        "axis*.config.step_gpio_pin": ([1, 7], "Firmware/Board/v3/board.cpp:126,140"),
        "axis*.config.dir_gpio_pin": ([2, 8], "Firmware/Board/v3/board.cpp:127,141"),
        # the motor thermistor's polynomial is value-initialized by config_clear_all (main.cpp:140)
        **{f"axis*.motor.motor_thermistor.config.poly_coefficient_{i}": (0.0, "Firmware/MotorControl/main.cpp:140")
           for i in range(4)},
        # the PWM and analog mappings: PWMMapping_t's initializers (odrive_main.h:57-59)
        **{f"config.gpio{g}_pwm_mapping.{m}": (0 if m == "endpoint" else 0.0, f"Firmware/MotorControl/odrive_main.h:{line}")
           for g in (1, 2, 3, 4) for m, line in (("endpoint", 57), ("min", 58), ("max", 59))},
        **{f"config.gpio{g}_analog_mapping.{m}": (0 if m == "endpoint" else 0.0, f"Firmware/MotorControl/odrive_main.h:{line}")
           for g in (3, 4) for m, line in (("endpoint", 57), ("min", 58), ("max", 59))},
    },
    "0.5.1": {
        "axis*.controller.config.load_encoder_axis": ([0, 1], "Firmware/MotorControl/main.cpp:96"),
        "axis*.config.can_node_id": ([0, 1], "Firmware/MotorControl/axis.cpp:133"),
        "axis*.config.step_gpio_pin": ([1, 7], "Firmware/MotorControl/board_config_v3.h:79,119"),
        "axis*.config.dir_gpio_pin": ([2, 8], "Firmware/MotorControl/board_config_v3.h:80,120"),
        **{f"axis*.motor_thermistor.config.poly_coefficient_{i}": (0.0, "Firmware/MotorControl/main.cpp:88")
           for i in range(4)},
        **{f"config.gpio{g}_pwm_mapping.{m}": (0 if m == "endpoint" else 0.0, "Firmware/MotorControl/odrive_main.h:80-82")
           for g in (1, 2, 3, 4) for m in ("endpoint", "min", "max")},
        **{f"config.gpio{g}_analog_mapping.{m}": (0 if m == "endpoint" else 0.0, "Firmware/MotorControl/odrive_main.h:80-82")
           for g in (3, 4) for m in ("endpoint", "min", "max")},
    },
}


def _git_show(repo: Path, tag: str, path: str) -> list[str] | None:
    git = ["git", "--git-dir", str(repo)] if (repo / "HEAD").exists() else ["git", "-C", str(repo)]
    out = subprocess.run([*git, "show", f"{tag}:Firmware/{path}"], capture_output=True, text=True)
    return out.stdout.splitlines() if out.returncode == 0 else None


# -- enums of the tag's own interface description ---------------------------------------

def _snake(name: str) -> str:
    """``AsciiAndStdout`` -> ``ASCII_AND_STDOUT``; ``DIGITAL_PULL_UP`` stays."""
    if name.isupper() or "_" in name:
        return name.upper()
    return re.sub(r"(?<=[a-z0-9])(?=[A-Z])", "_", name).upper()


def interface_enums(yaml_text: str) -> dict[str, int]:
    """``{"GPIO_MODE_DIGITAL": 0, "INPUT_MODE_PASSTHROUGH": 1, "PROTOCOL_SIMPLE": 1, ...}``:
    the C names of the enums in ``odrive-interface.yaml`` (``values``: 0, 1, ...;
    ``flags``: 1, 2, 4, ...; an explicit ``value`` or ``bit`` wins and the count goes on
    from it)."""
    import yaml  # load time: the maintainer tool only
    doc = yaml.safe_load(yaml_text)
    out: dict[str, int] = {}
    for name, spec in (doc.get("valuetypes") or {}).items():
        if not isinstance(spec, dict):
            continue
        prefix = _snake(name.split(".")[-1]) + "_"
        for kind in ("values", "flags"):
            members = spec.get(kind)
            if not members:
                continue
            n = bit = 0
            for member, info in members.items():
                if isinstance(info, dict) and "value" in info:
                    n = int(info["value"])
                if isinstance(info, dict) and "bit" in info:
                    bit = int(info["bit"])
                out.setdefault(prefix + _snake(member), (1 << bit) if kind == "flags" else n)
                n, bit = n + 1, bit + 1
    return out


ENUMS: dict[str, int] = {}


def _enum_value(name: str):
    for cand in (name, name.split("::")[-1]):
        if cand in ENUMS:
            return ENUMS[cand]
    return None


# -- a minimal C preprocessor for the headers' #if HW_VERSION_* branches ---------------

def _condition(expr: str) -> bool:
    e = expr.split("//")[0].strip()
    e = e.replace("&&", " and ").replace("||", " or ")
    e = re.sub(r"!(?!=)", " not ", e)
    e = re.sub(r"defined\s*\(?\s*(\w+)\s*\)?", lambda m: str(m.group(1) in CONSTANTS), e)
    for tok in set(re.findall(r"[A-Za-z_]\w*", e)):
        if tok in ("and", "or", "not", "True", "False"):
            continue
        e = re.sub(rf"\b{tok}\b", repr(CONSTANTS.get(tok, 0)), e)
    return bool(eval(e, {"__builtins__": {}}))  # noqa: S307 - digits and operators only


def preprocess(lines: list[str]) -> list[str]:
    """The lines with the inactive ``#if`` branches blanked (line numbers kept)."""
    out, stack = [], []       # stack of (this branch active, some branch taken)
    for line in lines:
        s = line.strip()
        active = all(a for a, _ in stack)
        if s.startswith("#if"):
            cond = _condition(s[3:]) if s.startswith("#if ") else (
                (s.split()[1] in CONSTANTS) == s.startswith("#ifdef"))
            stack.append((cond, cond))
            out.append("")
        elif s.startswith("#elif") and stack:
            _, taken = stack.pop()
            cond = not taken and _condition(s[5:])
            stack.append((cond, taken or cond))
            out.append("")
        elif s.startswith("#else") and stack:
            _, taken = stack.pop()
            stack.append((not taken, True))
            out.append("")
        elif s.startswith("#endif") and stack:
            stack.pop()
            out.append("")
        else:
            out.append(line if active else "")
    return out


def evaluate(expr: str):
    """The value of a C++ initializer, or raise ValueError."""
    e = expr.strip()
    e = e.replace("std::numeric_limits<float>::infinity()", "INFINITY")
    e = re.sub(r"(?<=[0-9.])f\b", "", e)                 # 10.0f -> 10.0
    e = re.sub(r"\b(\d+)u\b", r"\1", e)
    e = re.sub(r"\((?:float|int32_t|uint32_t)\)", "", e)
    names = {}
    ident = r"(?<![0-9.A-Za-z_])[A-Za-z_][A-Za-z_0-9:]*"   # not the e of 1.5e-3
    for tok in set(re.findall(ident, e)):
        if tok in CONSTANTS:
            names[tok] = CONSTANTS[tok]
        else:
            v = _enum_value(tok)
            if v is None:
                raise ValueError(f"unknown name {tok!r} in {expr!r}")
            names[tok] = v
    safe = e
    for tok, v in sorted(names.items(), key=lambda kv: -len(kv[0])):
        safe = re.sub(rf"(?<![A-Za-z_0-9:]){re.escape(tok)}(?![A-Za-z_0-9])", repr(v) if not isinstance(v, float) or math.isfinite(v) else ("float('inf')" if v > 0 else "-float('inf')"), safe)
    if re.search(ident, safe.replace("float('inf')", "").replace("True", "").replace("False", "")):
        raise ValueError(f"cannot evaluate {expr!r}")
    return eval(safe, {"__builtins__": {}, "float": float})  # noqa: S307 - sanitized above


MEMBER = re.compile(r"^\s*(?:const\s+)?[A-Za-z_][\w:<>]*\s+(\w+)\s*=\s*([^;{]+);")


def struct_members(lines: list[str], name: str, within: str | None = None) -> dict:
    """{member: (initializer, line number)} of the first ``struct name {`` at its own level
    (after ``class within`` when given)."""
    out = {}
    first = 0
    if within is not None:
        first = next((i for i, ln in enumerate(lines) if re.search(rf"\bclass\s+{within}\b[^;]*$", ln)), None)
        if first is None:
            return out
    start = next((i for i in range(first, len(lines)) if re.search(rf"\bstruct\s+{name}\b[^;]*$", lines[i])), None)
    if start is None:
        return out
    depth = 0
    for i in range(start, len(lines)):
        line = lines[i].split("//")[0]
        if depth == 1:
            m = MEMBER.match(line)
            if m:
                out[m.group(1)] = (m.group(2), i + 1)
        depth += line.count("{") - line.count("}")
        if depth <= 0 and i > start and "}" in line:
            break
    return out


def function_overrides(lines: list[str], func: str) -> dict:
    out = {}
    start = next((i for i, ln in enumerate(lines) if re.search(rf"::{func}\(\)\s*{{?", ln)), None)
    if start is None:
        return out
    for i in range(start + 1, len(lines)):
        if lines[i].startswith("}"):
            break
        m = re.match(r"^\s*config\.(\w+)\s*=\s*([^;]+);", lines[i].split("//")[0])
        if m:
            out[m.group(1)] = (m.group(2), i + 1)
    return out


def gpio_modes(board_h: list[str]) -> list[tuple[int, int]] | None:
    """[(mode, line)] of ``DEFAULT_GPIO_MODES`` in board.h, GPIO 0 first."""
    start = next((i for i, ln in enumerate(board_h) if "#define DEFAULT_GPIO_MODES" in ln), None)
    if start is None:
        return None
    out = []
    for i in range(start + 1, len(board_h)):
        m = re.search(r"(\w+::)?(GPIO_MODE_\w+)", board_h[i])
        if not m:
            break
        out.append((_enum_value(m.group(2)), i + 1))
    return out


def extract(repo: Path, version: str, endpoints: list[str]) -> dict:
    tag = f"fw-v{version}"
    ENUMS.clear()
    ENUMS.update(interface_enums("\n".join(_git_show(repo, tag, "odrive-interface.yaml") or [])))
    result, unparsed = {}, []
    cache: dict[str, list[str]] = {}

    def source(header: str) -> list[str]:
        if header not in cache:
            cache[header] = preprocess(_git_show(repo, tag, header) or [])
        return cache[header]

    board_h = source("Board/v3/Inc/board.h")
    for line in board_h:   # board.h's own constants for this board (brake resistance, ...)
        m = re.match(r"\s*#define\s+(DEFAULT_\w+)\s+\(?([-0-9.e]+)f?\)?", line.split("//")[0])
        if m:
            CONSTANTS[m.group(1)] = float(m.group(2))
    modes = gpio_modes(board_h)
    special = SPECIAL.get(version, {})
    for path in endpoints:
        head, _, rest = path.partition(".")
        generic = "axis*." + rest if head.startswith("axis") and head[4:].isdigit() else path
        if generic in special:
            value, src = special[generic]
            entry = {"value": value[0], "axes": value, "source": src} if isinstance(value, list) else \
                {"value": value, "source": src}
            result[generic] = entry
            continue
        gm = re.fullmatch(r"config\.gpio(\d+)_mode", generic)
        if gm and modes is not None and int(gm.group(1)) < len(modes):
            mode, line = modes[int(gm.group(1))]
            result[generic] = {"value": mode, "source": f"Firmware/Board/v3/Inc/board.h:{line}"}
            continue
        prefix = max((p for p in STRUCTS if generic.startswith(p) and "." not in generic[len(p):]),
                     key=len, default=None)
        if prefix is None:
            continue
        headers, struct, within = STRUCTS[prefix]
        member = generic[len(prefix):]
        found, src = None, None
        for header in ((headers,) if isinstance(headers, str) else headers):
            found = struct_members(source(header), struct, within).get(member)
            if found is not None:
                src = header
                break
        if prefix in LOCKIN_FUNCTIONS:
            over = function_overrides(source("MotorControl/axis.cpp"), LOCKIN_FUNCTIONS[prefix]).get(member)
            if over:
                found, src = over, "MotorControl/axis.cpp"
        if found is None:
            continue
        try:
            value = evaluate(found[0])
        except (ValueError, SyntaxError):
            unparsed.append(f"{generic} = {found[0].strip()} (Firmware/{src}:{found[1]})")
            continue
        result[generic] = {"value": value, "source": f"Firmware/{src}:{found[1]}"}
    board = f"ODrive v{BOARD['HW_VERSION_MAJOR']}.{BOARD['HW_VERSION_MINOR']}, {BOARD['HW_VERSION_VOLTAGE']} V"
    return {"_comment": f"defaults of the configuration endpoints of {tag}, extracted by "
                        f"leglib/device/virtual/tables/extract_defaults.py ({board})",
            "board": dict(BOARD),
            "defaults": dict(sorted(result.items())), "_unparsed": sorted(set(unparsed))}


def main(argv):
    repo = Path(argv[0])
    here = Path(__file__).parent
    for version in FIRMWARE_TABLES:
        paths = [p for p, e in flatten(endpoint_table(version)).items() if e["type"] != "function"]
        data = extract(repo, version, paths)
        out = here / f"defaults_fw-v{version}.json"
        out.write_text(json.dumps(data, indent=1) + "\n")  # Infinity as Python's json writes it
        print(f"{out.name}: {len(data['defaults'])} defaults, {len(data['_unparsed'])} unparsed")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
