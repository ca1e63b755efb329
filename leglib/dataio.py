"""Measurement files: the thesis's CSV plus a JSON sidecar, written atomically, read strictly.

A step response is ``YYYYmmdd_HHMMSS_<pos_gain>;<vel_gain>;<vel_integrator_gain>_positions.csv``
(Listing 7.4's name, gains with three decimals) holding rows ``time [s], angle1 [deg],
angle2 [deg]`` with no header. leglib writes absolute joint angles q1, q2; the thesis's own
files hold angles relative to the start (no sidecar). The sidecar ``<stem>.json`` carries
the exact gains, the backend, firmware, achieved sample rate, leglib version and git commit,
the twin's seed and plant, and whether the response completed or was aborted.

Files are never rewritten: writing to an existing name is an error.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import re
import subprocess
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import __version__

NAME_RE = re.compile(r"^(?P<stamp>\d{8}_\d{6})(?:_(?P<gains>[^_]+))?_positions\.csv$")


class MeasurementError(ValueError):
    """A measurement file is malformed; the message names the file (and line)."""


def gains_key(gains) -> str:
    """The gains part of a file name: three decimals, ';'-separated (Listing 7.4)."""
    return ";".join(f"{float(g):.3f}" for g in gains)


def measurement_filename(gains=None, when: _dt.datetime | None = None) -> str:
    when = when or _dt.datetime.now()
    stamp = when.strftime("%Y%m%d_%H%M%S")
    return f"{stamp}_{gains_key(gains)}_positions.csv" if gains is not None else f"{stamp}_positions.csv"


def parse_filename(path: str | Path) -> tuple[str, tuple[float, float, float] | None]:
    """(timestamp, gains or None) from a measurement file name; MeasurementError otherwise."""
    name = Path(path).name
    m = NAME_RE.match(name)
    if not m:
        raise MeasurementError(f"{path}: cannot parse file name (expected "
                               f"YYYYmmdd_HHMMSS_<posP>;<velP>;<velI>_positions.csv)")
    gains = None
    if m.group("gains") is not None:
        parts = m.group("gains").split(";")
        try:
            gains = tuple(float(p) for p in parts)
        except ValueError:
            gains = None
        if gains is None or len(gains) != 3 or not all(math.isfinite(g) for g in gains):
            raise MeasurementError(f"{path}: cannot parse gains {m.group('gains')!r} from file name "
                                   f"(expected three numbers separated by ';')")
    return m.group("stamp"), gains


def _git_commit() -> str | None:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).resolve().parent,
                             capture_output=True, text=True, timeout=5)
        return out.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


_COMMIT = None


def provenance() -> dict:
    """leglib version and git commit, for sidecars."""
    global _COMMIT
    if _COMMIT is None:
        _COMMIT = _git_commit() or "unknown"
    return {"leglib_version": __version__, "git_commit": _COMMIT}


def _atomic_write(path: Path, write) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix="." + path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        # link, not rename: fails if the target exists, so nothing is ever overwritten
        os.link(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)


def write_measurement(out_dir: str | Path, t, angle1_deg, angle2_deg, meta: dict,
                      gains=None, when: _dt.datetime | None = None) -> Path:
    """Write one measurement (CSV + JSON sidecar) atomically; returns the CSV path.

    Raises FileExistsError rather than overwrite a finished measurement.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t, a1, a2 = (np.asarray(v, dtype=float) for v in (t, angle1_deg, angle2_deg))
    if not (t.shape == a1.shape == a2.shape) or t.ndim != 1:
        raise ValueError(f"write_measurement: t, angle1, angle2 must be 1-D of equal length, "
                         f"got {t.shape}, {a1.shape}, {a2.shape}")
    path = out_dir / measurement_filename(gains, when)
    if path.exists() or path.with_suffix(".json").exists():
        raise FileExistsError(f"{path}: a measurement with this name exists; not overwriting")
    data = np.column_stack([t, a1, a2])
    sidecar = {"columns": ["time [s]", "q1 [deg]", "q2 [deg]"], "angles": "absolute",
               "gains": None if gains is None else [float(g) for g in gains],
               "samples": int(t.size), **provenance(), **meta}
    _atomic_write(path, lambda fh: np.savetxt(fh, data, fmt="%.6f", delimiter=","))
    _atomic_write(path.with_suffix(".json"),
                  lambda fh: json.dump(sidecar, fh, indent=2, sort_keys=True, default=_json_default))
    return path


def write_table(path: str | Path, data) -> Path:
    """Write a numeric table as CSV atomically (never overwriting)."""
    path = Path(path)
    if path.exists():
        raise FileExistsError(f"{path}: exists; not overwriting")
    _atomic_write(path, lambda fh: np.savetxt(fh, np.asarray(data, dtype=float), fmt="%.6f", delimiter=","))
    return path


def _read_rows(path: Path, columns: int, names: str = "", increasing_first: bool = False) -> np.ndarray:
    """Parse a numeric CSV strictly: MeasurementError naming file and line for a wrong
    column count, a non-number, NaN or infinity, or (``increasing_first``) a first column
    that does not increase."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise MeasurementError(f"{path}: file not found") from None
    except UnicodeDecodeError:
        raise MeasurementError(f"{path}: not a text file") from None
    rows = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        parts = line.split(",")
        if len(parts) != columns:
            raise MeasurementError(f"{path}:{lineno}: expected {columns} comma-separated columns {names}, "
                                   f"got {len(parts)}: {line!r}")
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            raise MeasurementError(f"{path}:{lineno}: not a number in {line!r}") from None
        if not all(math.isfinite(v) for v in vals):
            raise MeasurementError(f"{path}:{lineno}: NaN or infinite value in {line!r}")
        if increasing_first and rows and vals[0] <= rows[-1][0]:
            raise MeasurementError(f"{path}:{lineno}: time {vals[0]} does not increase (previous {rows[-1][0]})")
        rows.append(vals)
    if not rows:
        raise MeasurementError(f"{path}: no data rows")
    return np.array(rows)


def read_table(path: str | Path, columns: int) -> np.ndarray:
    """Read a numeric CSV with ``columns`` columns; MeasurementError naming file and line."""
    return _read_rows(Path(path), columns)


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serializable: {type(o).__name__}")


@dataclass
class Measurement:
    """A measurement read back: ``t`` [s], ``angle1``, ``angle2`` [deg] as in the file,
    ``gains`` (from the sidecar, else the file name, else None), ``meta`` (sidecar or {}),
    and ``absolute`` (True when the angles are absolute joint angles)."""

    path: Path
    t: np.ndarray
    angle1: np.ndarray
    angle2: np.ndarray
    gains: tuple | None
    meta: dict = field(default_factory=dict)

    @property
    def absolute(self) -> bool:
        return self.meta.get("angles") == "absolute"

    @property
    def stable(self) -> bool:
        """False when the experiment aborted (unstable); thesis files count as completed."""
        return bool(self.meta.get("completed", True))


def read_measurement(path: str | Path) -> Measurement:
    """Read and validate a measurement CSV (and its sidecar, if any).

    Raises MeasurementError naming the file and line for: an unparseable file name, a row
    without exactly three numbers, NaN or infinite values, non-increasing time, fewer than
    two rows, or a sidecar that is not JSON.
    """
    path = Path(path)
    _, name_gains = parse_filename(path)
    data = _read_rows(path, 3, "(time, angle1, angle2)", increasing_first=True)
    if len(data) < 2:
        raise MeasurementError(f"{path}: fewer than two data rows")
    meta = {}
    side = path.with_suffix(".json")
    if side.exists():
        try:
            meta = json.loads(side.read_text())
        except json.JSONDecodeError as exc:
            raise MeasurementError(f"{side}: sidecar is not valid JSON: {exc}") from None
    gains = tuple(meta["gains"]) if meta.get("gains") else name_gains
    return Measurement(path=path, t=data[:, 0], angle1=data[:, 1], angle2=data[:, 2],
                       gains=gains, meta=meta)


def list_measurements(directory: str | Path) -> list[Path]:
    """Measurement CSVs (``*_positions.csv``) in ``directory``, sorted by name."""
    return sorted(Path(directory).glob("*_positions.csv"))
