"""Extract the firmware's configuration defaults from its sources into
``defaults_fw-v<version>.json`` (maintainer tool; the JSON files ship with leglib).

Usage: ``python -m leglib.device.virtual.tables.extract_defaults /path/to/ODrive.git`` (a clone of
https://github.com/odriverobotics/ODrive with the tags fw-v0.5.1 and fw-v0.5.6).

Each ``Config_t`` (and similar) struct of the firmware's headers initializes its members,
``float calibration_current = 10.0f;``; the endpoint ``axis0.motor.config.calibration_current``
is such a member. This tool maps the endpoint prefixes to those structs, evaluates the
initializers (constants of an ODrive v3.6 24 V board, enums from ``odrive.enums``) and
writes ``{"axis*.motor.config.calibration_current": {"value": 10.0, "source":
"Firmware/MotorControl/motor.hpp:20"}, ...}``. Members whose initializer it cannot evaluate
are listed under ``"_unparsed"`` and stay at zero in the virtual ODrive.
"""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from pathlib import Path

from ..wire import FIRMWARE_TABLES, endpoint_table, flatten

# endpoint prefix (generic axis) -> (header, struct name)
STRUCTS = {
    "axis*.config.": ("MotorControl/axis.hpp", "Config_t"),
    "axis*.config.can.": ("MotorControl/axis.hpp", "CANConfig_t"),
    "axis*.config.general_lockin.": ("MotorControl/axis.hpp", "LockinConfig_t"),
    "axis*.config.calibration_lockin.": ("MotorControl/axis.hpp", "LockinConfig_t"),
    "axis*.config.sensorless_ramp.": ("MotorControl/axis.hpp", "LockinConfig_t"),
    "axis*.motor.config.": ("MotorControl/motor.hpp", "Config_t"),
    "axis*.encoder.config.": ("MotorControl/encoder.hpp", "Config_t"),
    "axis*.controller.config.": ("MotorControl/controller.hpp", "Config_t"),
    "axis*.trap_traj.config.": ("MotorControl/trapTraj.hpp", "Config_t"),
    "axis*.sensorless_estimator.config.": ("MotorControl/sensorless_estimator.hpp", "Config_t"),
    "axis*.min_endstop.config.": ("MotorControl/endstop.hpp", "Config_t"),
    "axis*.max_endstop.config.": ("MotorControl/endstop.hpp", "Config_t"),
    "axis*.mechanical_brake.config.": ("MotorControl/mechanical_brake.hpp", "Config_t"),
    "axis*.motor.fet_thermistor.config.": ("MotorControl/thermistor.hpp", "Config_t"),
    "axis*.motor_thermistor.config.": ("MotorControl/thermistor.hpp", "Config_t"),
    "axis*.motor.motor_thermistor.config.": ("MotorControl/thermistor.hpp", "Config_t"),
    "axis*.acim_estimator.config.": ("MotorControl/acim_estimator.hpp", "Config_t"),
    "config.": ("MotorControl/odrive_main.h", "BoardConfig_t"),
    "can.config.": ("communication/interface_can.hpp", "Config_t"),
}
# axis.cpp overrides LockinConfig_t for these (Axis::default_calibration / default_sensorless)
LOCKIN_FUNCTIONS = {"axis*.config.calibration_lockin.": "default_calibration",
                    "axis*.config.sensorless_ramp.": "default_sensorless"}

# board constants of an ODrive v3.6 (24 V variant, as the twin's bus)
# (Firmware/Board/v3/Inc/board.h:40-47: 0.47 ohm below 48 V, error pin 0, 8 V minimum)
CONSTANTS = {"HW_VERSION_VOLTAGE": 24.0, "DEFAULT_MIN_DC_VOLTAGE": 8.0, "DEFAULT_BRAKE_RESISTANCE": 0.47,
             "DEFAULT_ERROR_PIN": 0, "M_PI": math.pi, "INFINITY": math.inf, "true": True,
             "false": False, "nullptr": 0,
             # 0.5.x enum values the 0.6 client renamed (odrive-interface.yaml: ODrive.Motor.MotorType)
             "MOTOR_TYPE_HIGH_CURRENT": 0, "MOTOR_TYPE_GIMBAL": 2, "MOTOR_TYPE_ACIM": 3}


def _git_show(repo: Path, tag: str, path: str) -> list[str] | None:
    out = subprocess.run(["git", "--git-dir", str(repo), "show", f"{tag}:Firmware/{path}"],
                         capture_output=True, text=True)
    return out.stdout.splitlines() if out.returncode == 0 else None


def _enum_value(name: str):
    import odrive.enums as E  # load time: the odrive client (needs libusb), only for this tool
    for cand in (name, name.split("::")[-1]):
        for prefix in ("", "ENCODER_", "MOTOR_TYPE_", "CONTROL_MODE_", "INPUT_MODE_", "GPIO_MODE_",
                       "THERMISTOR_", "STREAM_PROTOCOL_TYPE_", "CAN_PROTOCOL_"):
            v = getattr(E, prefix + cand, None)
            if v is not None:
                return int(v)
    return None


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


def struct_members(lines: list[str], name: str) -> dict:
    """{member: (initializer, line number)} of the first ``struct name {`` at its own level."""
    out = {}
    start = next((i for i, ln in enumerate(lines) if re.search(rf"\bstruct\s+{name}\b[^;]*$", ln)), None)
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


def extract(repo: Path, version: str, endpoints: list[str]) -> dict:
    tag = f"fw-v{version}"
    result, unparsed = {}, []
    cache = {}
    for path in endpoints:
        head, _, rest = path.partition(".")
        generic = "axis*." + rest if head.startswith("axis") and head[4:].isdigit() else path
        prefix = max((p for p in STRUCTS if generic.startswith(p) and "." not in generic[len(p):]),
                     key=len, default=None)
        if prefix is None:
            continue
        header, struct = STRUCTS[prefix]
        if header not in cache:
            cache[header] = _git_show(repo, tag, header) or []
        member = generic[len(prefix):]
        found = struct_members(cache[header], struct).get(member)
        src = header
        if prefix in LOCKIN_FUNCTIONS:
            if "MotorControl/axis.cpp" not in cache:
                cache["MotorControl/axis.cpp"] = _git_show(repo, tag, "MotorControl/axis.cpp") or []
            over = function_overrides(cache["MotorControl/axis.cpp"], LOCKIN_FUNCTIONS[prefix]).get(member)
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
    return {"_comment": f"defaults of the configuration endpoints of {tag}, extracted by "
                        f"leglib/device/virtual/tables/extract_defaults.py (ODrive v3.6, 24 V)",
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
