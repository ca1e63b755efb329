"""A sweep's directory: listing and reading its measurements, unfinished writes set aside,
one writer per point (claims), and the directory's provenance.

A resumed sweep reads every file: damaged or unfinished ones go to ``incomplete/`` and are
measured again. Each point is claimed while it is measured, so two sweeps into one
directory share the grid without losing or duplicating a point. ``sweep.json`` records what
was measured on (the device's identity, the experiment); resuming with another leg or
experiment raises :class:`leglib.errors.ProvenanceError` before anything is measured.
"""

from __future__ import annotations

import json
import math
import os
import re
import secrets
import warnings
from dataclasses import dataclass
from pathlib import Path

from .._version import provenance
from ..errors import MeasurementError, ProvenanceError
from .atomic import write_bytes_atomic
from .measurements import (
    MAX_BATCH_SIDECAR_BYTES,
    MAX_SIDECAR_BYTES,
    _decode,
    _is_gains,
    _is_number,
    _json_default,
    _read_regular,
    _sidecar_json,
    read_file,
    read_measurement,
)
from .names import (
    _BATCH_SIDE_RE,
    _UID_RE,
    BATCH_RE,
    EXCERPT,
    NAME_RE,
    _parse_name,
    is_batch_name,
    is_leglib_name,
    sidecar_path,
)

INCOMPLETE_DIR = "incomplete"
PROVENANCE_FILE = "sweep.json"


def _directory(directory: str | Path) -> Path:
    if not isinstance(directory, (str, os.PathLike)):
        raise TypeError(f"expected a directory path, got {type(directory).__name__}")
    d = Path(directory)
    if not d.exists():
        raise MeasurementError(f"{d}: no such directory")
    if not d.is_dir():
        raise MeasurementError(f"{d}: not a directory")
    return d


def list_measurements(directory: str | Path) -> list[Path]:
    """Measurement files in ``directory``: CSVs of one measurement (``*_positions.csv``,
    not hidden) and batch files (named as :data:`BATCH_RE`: ``<stamp>_lg<12 hex>_batch.csv``),
    sorted by name.

    MeasurementError if ``directory`` does not exist or is not a directory. Uncommitted
    writes (sidecars without a CSV, temporary files) are not listed (:func:`find_uncommitted`).
    """
    d = _directory(directory)
    return sorted([p for p in d.glob("*_positions.csv") if not p.name.startswith(".")]
                  + [p for p in d.glob("*_batch.csv") if BATCH_RE.match(p.name)])


@dataclass
class DirectoryRead:
    """What :func:`read_measurements` found: ``measurements`` read, and ``problems``,
    a list of (path, message) of the files that could not be read (``strict=False``)."""

    measurements: list
    problems: list


def read_measurements(paths_or_dir, strict: bool = True) -> DirectoryRead:
    """Read every measurement of a directory (or of a list of paths).

    Parameters
    ----------
    paths_or_dir : str, Path or sequence of paths
        A sweep's directory (its measurement and batch files, :func:`list_measurements`), or
        the files to read.
    strict : bool
        True raises the first bad file's error; False skips bad files, lists them in
        ``problems`` and warns with their count, never silently.

    Returns
    -------
    DirectoryRead
        ``measurements`` (list of :class:`leglib.files.measurements.Measurement`) and
        ``problems`` ((path, message) of each file skipped).

    Raises
    ------
    MeasurementError
        With ``strict``: a file is malformed (the message names file, line and field).
    """
    if isinstance(paths_or_dir, (str, os.PathLike)):
        paths = list_measurements(paths_or_dir)
    else:
        paths = [Path(p) for p in paths_or_dir]
    out, problems = [], []
    for p in paths:
        try:
            out.extend(read_file(p))
        except MeasurementError as exc:
            if strict:
                raise
            problems.append((p, str(exc)))
    if problems:
        warnings.warn(f"{len(problems)} of {len(paths)} measurement files skipped: "
                      + "; ".join(m for _, m in problems[:3]) + (" ..." if len(problems) > 3 else ""),
                      stacklevel=2)
    return DirectoryRead(out, problems)


def find_uncommitted(directory: str | Path) -> list[Path]:
    """Leftovers of interrupted format-2 writes in ``directory``: sidecars whose CSV never
    appeared, companion files (a torque run's table) of a measurement never committed, and
    hidden temporary files. (A concurrent writer's in-flight files look the
    same: hold the point's :func:`claim` before removing them.)"""
    d = _directory(directory)
    found = [p for pattern, name_re in (("*_positions.json", _UID_RE), ("*_batch.json", _BATCH_SIDE_RE))
             for p in d.glob(pattern) if name_re.search(p.name) and not os.path.lexists(p.with_suffix(".csv"))]
    # a measurement's companions (a torque run's table) whose commit never came
    found += [p for p in d.glob("*_lg*_*.csv") if _COMPANION_RE.search(p.name)
              and not os.path.lexists(p.with_name(_COMPANION_RE.sub(r"\1_positions.csv", p.name)))]
    found += [p for p in d.glob(".*.tmp") if "_positions." in p.name or "_batch." in p.name or
              _COMPANION_RE.search(p.name.lstrip(".").rsplit(".", 2)[0])]
    return sorted(found)


# a companion of a leglib measurement: <stem>_lg<12 hex>_<suffix>.csv other than the positions
_COMPANION_RE = re.compile(r"(_lg[0-9a-f]{12})_(?!positions\.csv$|batch\.csv$)[a-z]+\.csv$", re.ASCII)


def uncommitted_claim_key(path: Path):
    """What a leftover file's writer held claimed while writing it (:func:`claim`): the
    gains of a measurement, the ``lg`` part of a batch; None when the name tells neither."""
    name = path.name
    if name.startswith(".") and name.endswith(".tmp"):
        name = name[1:].rsplit(".", 2)[0]
    m = BATCH_RE.match(name.replace("_batch.json", "_batch.csv"))
    return m.group("uid") if m else gains_of_uncommitted(path)


def gains_of_uncommitted(path: Path) -> tuple | None:
    """The gains a leftover file (sidecar or temporary file) belonged to, from its name."""
    name = path.name
    if name.startswith(".") and name.endswith(".tmp"):
        name = name[1:].rsplit(".", 2)[0]
    name = name.replace("_positions.json", "_positions.csv")
    try:
        return _parse_name(name)[1]
    except MeasurementError:
        return None


def set_aside(path: Path, directory: Path | None = None) -> Path:
    """Move ``path`` (and its sidecar) into ``<directory>/incomplete/``; returns the new path.
    Nothing is deleted: a damaged or unfinished file stays there for inspection."""
    path = Path(path)
    target_dir = (directory or path.parent) / INCOMPLETE_DIR
    target_dir.mkdir(exist_ok=True)
    moved = None
    for p in (path, sidecar_path(path)) if path.suffix == ".csv" else (path,):
        if os.path.lexists(p):
            dest = target_dir / p.name.lstrip(".")
            if os.path.lexists(dest):
                dest = target_dir / f"{dest.stem}.{secrets.token_hex(3)}{dest.suffix}"
            os.replace(p, dest)
            moved = moved or dest
    return moved or target_dir / path.name




















def committed_gains(directory: str | Path) -> set:
    """Exact gains of every committed format-2 measurement (from names only: fast) and of
    every measurement of a committed batch (from its sidecar; an unreadable one counts
    none: a resumed sweep sets it aside)."""
    out = set()
    for p in list_measurements(directory):
        if is_batch_name(p):
            side = sidecar_path(p)
            try:
                points = _sidecar_json(side, _read_regular(side, MAX_BATCH_SIDECAR_BYTES, "sidecar"))["points"]
                gains = [pm["gains"] for pm in points]
            except (MeasurementError, TypeError, KeyError):
                continue
            if all(_is_gains(g) for g in gains):
                out.update(tuple(float(x) for x in g) for g in gains)
            continue
        m = NAME_RE.match(p.name)
        if m and m.group("uid") and m.group("gains"):
            try:
                out.add(_parse_name(p)[1])
            except MeasurementError:
                pass
    return out


# the fields of Device.describe() that define "the same leg": what was measured on
DEVICE_IDENTITY = ("backend", "serial_number", "firmware", "twin_seed", "twin_plant_values", "twin_noise")


def sweep_record(device: dict, **experiment) -> dict:
    """The provenance of a sweep: the identity fields of ``Device.describe()`` and the
    experiment's settings (step, duration, sample period, ...)."""
    dev = {k: device[k] for k in DEVICE_IDENTITY if k in device}
    if isinstance(dev.get("twin_plant_values"), dict):  # values only, not their source notes
        dev["twin_plant_values"] = {k: v for k, v in dev["twin_plant_values"].items() if not k.startswith("_")}
    return json.loads(json.dumps({"device": dev, "experiment": experiment}, default=_json_default))


def _differences(theirs, ours, prefix=""):
    if isinstance(theirs, dict) and isinstance(ours, dict):
        out = []
        for k in sorted(set(theirs) | set(ours)):
            if k in theirs and k in ours:
                out += _differences(theirs[k], ours[k], f"{prefix}{k}.")
        return out
    if isinstance(theirs, float) or isinstance(ours, float):
        if _is_number(theirs) and _is_number(ours) and math.isclose(theirs, ours, rel_tol=1e-9, abs_tol=1e-12):
            return []
    return [] if theirs == ours else [(prefix.rstrip("."), theirs, ours)]


def check_provenance(directory: str | Path, record: dict, write: bool = False) -> None:
    """Refuse a directory measured on another leg or with another experiment.

    ``record`` is :func:`sweep_record`'s (or ``{"device": Device.describe()}``): fields
    present on both sides are compared. The directory's record is its ``sweep.json``;
    without one (older directories) the sidecars of its measurements are compared, and a
    thesis file (no sidecar) counts as measured on the real leg (backend "usb"). With
    ``write=True`` the record is stored when the directory has none. Raises
    ProvenanceError naming the file and every differing field.
    """
    d = Path(directory)
    rec_path = d / PROVENANCE_FILE
    ours = sweep_record(record.get("device", {}), **record.get("experiment", {}))
    if os.path.lexists(rec_path):
        raw = _read_regular(rec_path, MAX_SIDECAR_BYTES, "provenance record")
        try:
            theirs = json.loads(_decode(rec_path, raw, "provenance record"))
        except json.JSONDecodeError as exc:
            raise MeasurementError(f"{rec_path}:{exc.lineno}: not valid JSON: {exc.msg}") from None
        if not isinstance(theirs, dict):
            raise MeasurementError(f"{rec_path}: must be a JSON object")
        for tmp in d.glob(f".{PROVENANCE_FILE}.*.tmp"):  # an interrupted or losing writer's copy
            tmp.unlink(missing_ok=True)
        diffs = _differences({k: theirs.get(k, {}) for k in ("device", "experiment")}, ours)
        where = rec_path
    else:
        diffs, where = [], None
        if d.is_dir():
            for p in list_measurements(d):
                side = sidecar_path(p)
                if not side.is_file():
                    try:
                        read_measurement(p)
                    except MeasurementError:
                        continue  # not a thesis file (an orphan, damaged): set aside by a sweep
                    if not is_leglib_name(p):  # a thesis file: measured on the real leg
                        diffs = _differences({"device": {"backend": "usb"}}, ours)
                        if diffs:
                            where = p
                            break
                    continue
                try:
                    meta = json.loads(side.read_text())
                except (OSError, ValueError):
                    continue
                if not isinstance(meta, dict):
                    continue
                theirs = {"device": sweep_record(meta)["device"],
                          "experiment": ({"step": meta["step_turns"]} if "step_turns" in meta else {})}
                diffs = _differences(theirs, ours)
                if diffs:
                    where = side
                    break
        if not diffs and write:
            d.mkdir(parents=True, exist_ok=True)
            body = json.dumps({**ours, **provenance()}, indent=2, sort_keys=True).encode()
            try:
                write_bytes_atomic(rec_path, body)
            except (FileExistsError, FileNotFoundError):  # another writer stored one first
                pass
            return check_provenance(directory, record, write=False)  # compares, tidies
    if diffs:
        text = "; ".join(f"{k}: {_short_json(a)} there, {_short_json(b)} now" for k, a, b in diffs[:6])
        raise ProvenanceError(f"{where}: {d} was measured on another leg or with another experiment "
                              f"({text}); measure into another directory")


def _short_json(v) -> str:
    s = json.dumps(v, default=str)
    return s if len(s) <= EXCERPT else s[:EXCERPT] + "..."


def check_result_provenance(result_path: str | Path, device: dict, ignore=("twin_seed",)) -> None:
    """Refuse a cached result (a JSON file whose ``source`` names the measurement it was
    derived from, e.g. notebook 02's identified leg) that comes from another leg.

    The measurement's sidecar is compared with ``device`` (identity fields of
    ``Device.describe()``, or the subset known before connecting) on the fields both have,
    except ``ignore`` (by default the twin's noise seed: another seed is the same leg).
    A result without a readable source is reported with a warning, not trusted silently.
    """
    result_path = Path(result_path)
    raw = _read_regular(result_path, MAX_SIDECAR_BYTES, "result file")
    try:
        doc = json.loads(_decode(result_path, raw, "result file"))
    except json.JSONDecodeError as exc:
        raise MeasurementError(f"{result_path}:{exc.lineno}: not valid JSON: {exc.msg}") from None
    source = doc.get("source") if isinstance(doc, dict) else None
    side = sidecar_path(source) if isinstance(source, str) else None
    if side is None or not side.is_file():
        warnings.warn(f"{result_path}: its source measurement {source!r} is not available; "
                      f"cannot check that it comes from this leg", stacklevel=2)
        return
    meta = json.loads(_decode(side, _read_regular(side, MAX_SIDECAR_BYTES, "sidecar"), "sidecar"))
    if not isinstance(meta, dict):
        raise MeasurementError(f"{side}: sidecar must be a JSON object, got {type(meta).__name__}")
    theirs = {k: v for k, v in sweep_record(meta)["device"].items() if k not in ignore}
    ours = {k: v for k, v in sweep_record(device)["device"].items() if k not in ignore}
    diffs = _differences(theirs, ours)
    if diffs:
        text = "; ".join(f"{k}: {_short_json(a)} there, {_short_json(b)} now" for k, a, b in diffs[:6])
        raise ProvenanceError(f"{result_path}: derived from {source}, measured on another leg ({text}); "
                              f"derive it again for this leg or point to its own result")
