"""Measurement files: the thesis's CSV plus a JSON sidecar, committed as one unit, read strictly.

File names
----------
A measurement is ``<stem>_positions.csv`` with rows ``time [s], angle1 [deg], angle2 [deg]``
(no header) and, for leglib's own files, a sidecar ``<stem>_positions.json``. Three kinds
of name are read:

* thesis files (Listing 7.4): ``YYYYmmdd_HHMMSS_<posP>;<velP>;<velI>_positions.csv`` with
  three-decimal gains, angles relative to the start, **no sidecar**;
* leglib files written before format 2: the same name with a sidecar (absolute angles);
* leglib files (format 2): ``YYYYmmdd_HHMMSS_<posP>;<velP>;<velI>_lg<12 hex>_positions.csv``
  with the *exact* gains (shortest round-trip decimal, so near-equal gains never share a
  name) and a random ``lg`` part, which makes every name unique (two writers in one
  directory in the same second never collide) and marks the file as leglib's own.

Commit protocol
---------------
A format-2 measurement is committed by its CSV: the sidecar (holding the sample count and
the SHA-256 of the CSV's bytes) is written first, then the CSV appears by an atomic link
of a complete temporary file. So

* a CSV is never visible before its sidecar is complete;
* a sidecar without its CSV, or a hidden ``.*.tmp`` file, is an uncommitted write: readers
  ignore it, :func:`find_uncommitted` lists it, and a resumed sweep moves it to
  ``incomplete/`` and measures the point again;
* a format-2 CSV without a sidecar, or whose bytes do not match the sidecar's hash, is an
  error, never a thesis file.

Durability: each file is flushed to disk (``fsync``) before its name appears, and its
directory after, so a committed measurement survives a power loss. Inside
:func:`deferred_sync` (a twin sweep's batch: hundreds of files a second, each cheap to
measure again) the per-file flushes are left out and each directory written to is
flushed once at the end. An interrupted *process* still leaves only complete files
(the names appear by atomic links); after a power loss or OS crash, the files of the
batch being written may be missing, empty or cut: the reader refuses those (sample count
and SHA-256 against the sidecar, or a sidecar without its CSV) and a resumed sweep sets
them aside and measures their points again.

Batch files
-----------
A twin sweep measures hundreds of points in one go; writing each as two files costs more
than simulating it (creating a file takes 30-300 us here). It writes them as one batch:
``YYYYmmdd_HHMMSS_lg<12 hex>_batch.csv``, the measurements' rows one after the other
(each starting again at its own time zero), and a sidecar ``..._batch.json`` (format 3)
holding the fields they share, the total sample count and SHA-256, and ``points``: per
measurement (in file order) its gains, sample count, ``completed`` and ``abort_reason``.
The commit protocol is a measurement's; a batch is committed, read and set aside as one
unit (:func:`read_batch`, :func:`read_file`), and :func:`read_measurements` reads both
kinds. Measurements of the real leg are written one file each, as they are taken.

A sidecar-less file with a thesis name is a thesis file; its angles are relative to the
start, so its first row must lie within :data:`RELATIVE_START_DEG` of zero -- an absolute
angle there (e.g. 267 deg) is the orphan CSV of a pre-format-2 leglib write, and is
refused rather than read as relative angles.

Reading
-------
:func:`read_measurement` accepts only regular files of bounded size (:data:`MAX_CSV_BYTES`,
:data:`MAX_SIDECAR_BYTES`), UTF-8 text, strict ASCII decimal numbers (no ``1_0``, no
full-width digits, no NaN or infinity), angles within :data:`ANGLE_LIMIT_DEG`, increasing
time, and checks the sidecar's types, sample count, hash, columns, angle convention,
``completed`` flag and gains against the file and its name. Errors are
:class:`MeasurementError` naming file, line and field, quoting at most
:data:`EXCERPT` characters. :func:`read_measurements` reads a directory; with
``strict=False`` it skips bad files and reports each (and warns), never silently.

Text
----
A row is ``f"{t:.6f},{q1:.6f},{q2:.6f}\\n"`` (the thesis's format), written by numpy
(:func:`_csv_bytes`: the same bytes as Python's formatting, so files written before keep
their SHA-256); a sidecar is ``json.dumps`` with sorted keys, indented by two. A plain
file (digits, signs, points, exponents, commas and newlines: what leglib writes) is read
by ``np.loadtxt``; any other file, and one that breaks a rule, by the row-by-row reader,
which reads it or words the error.

Files are never rewritten (writing an existing name is an error) and are created with
the user's umask.
"""

from __future__ import annotations

import datetime as _dt
import errno
import hashlib
import io
import json
import math
import os
import re
import stat
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._version import provenance
from ..errors import MeasurementError
from .atomic import write_bytes_atomic
from .claims import claim
from .names import (
    _NUM,
    BATCH_RE,
    NUMBER_RE,
    _excerpt,
    _parse_name,
    batch_filename,
    is_batch_name,
    measurement_filename,
    sidecar_path,
)

FORMAT = 2
MAX_CSV_BYTES = 64 << 20          # a 60 s run at 8 kHz is about 20 MB
MAX_SIDECAR_BYTES = 16 << 20
MAX_LINE_CHARS = 512
ANGLE_LIMIT_DEG = 3600.0          # |angle| beyond ten turns of a joint is not a measurement
RELATIVE_START_DEG = 10.0         # a thesis file's first row is within this of zero
COLUMNS = ["time [s]", "q1 [deg]", "q2 [deg]"]
_ROW_RE = re.compile(rf"^[ \t]*({_NUM})[ \t]*,[ \t]*({_NUM})[ \t]*,[ \t]*({_NUM})[ \t]*\r?$", re.ASCII)
BATCH_FORMAT = 3
MAX_BATCH_CSV_BYTES = 1 << 30     # a batch holds many measurements (the thesis grid: 9 MB)
MAX_BATCH_SIDECAR_BYTES = 64 << 20
BATCH_POINT_FIELDS = ("abort_reason", "completed", "gains", "samples")   # a batch's points hold these


def _csv_bytes(data) -> bytes:
    """Rows of ``data`` (2-D float) as ``"%.6f,%.6f,...\\n"`` ASCII: Python's text, to the byte.

    numpy lays out the digits (Python's own formatting of the thesis grid's 900,000
    numbers takes 0.2-0.4 s, a third of the grid's budget from sweep to map; numpy about a
    sixth of that).
    ``.6f`` writes the multiple of 1e-6 nearest to ``x``. The product ``y = |x| 1e6`` is
    off the exact value by at most ``y 2^-53``, so where its fractional part is further
    than ``max(y) 2^-52`` from one half, rounding ``y`` gives ``.6f``'s digits; the few
    values nearer a half take theirs from Python's own format, and a table with a value
    of 2^50 / 1e6 or more (or NaN, infinity) is formatted by Python whole. The
    sign is written for every negative value, -0.0 and values that round to zero
    included, as Python does.
    """
    data = np.atleast_2d(np.asarray(data, dtype=float))
    n, c = data.shape
    if data.size == 0:
        return b"\n" * n if c == 0 else b""
    y = np.abs(data) * 1e6
    top = y.max()
    if not top < 2.0 ** 50:   # also NaN
        row = ",".join(["%.6f"] * c) + "\n"
        return ((row * n) % tuple(data.ravel().tolist())).encode("ascii")
    micro = np.rint(y)
    off = np.abs(np.subtract(y, micro, out=y), out=y)   # distance to the nearest integer
    near = np.flatnonzero(off >= 0.5 - top * 2.0 ** -52)
    micro = micro.astype(np.int64)
    if near.size:
        micro.flat[near] = [int(f"{v:.6f}".replace(".", "")) for v in np.abs(data.flat[near]).tolist()]
    units, millionths = np.divmod(micro, 1_000_000)
    units, millionths = units.astype(np.int32), millionths.astype(np.int32)   # < 2^50 / 1e6 < 2^31
    k = len(str(int(units.max())))   # integer digits of the widest number
    # one field: sign, k integer digits, point, 6 decimals, separator; the bytes left 0
    # (no sign, leading zeros) are dropped at the end
    text = np.zeros((n, c, k + 9), np.uint8)
    text[..., 0] = np.signbit(data) * np.uint8(ord("-"))
    for place in range(k):   # the integer digits from the ones; a zero of place >= 1 where
        # the number is below 10^place (nothing left) is a leading zero, left out
        higher = units // 10
        digit = units - 10 * higher + 48
        text[..., k - place] = digit if place == 0 else digit * (units != 0)
        units = higher
    text[..., k + 1] = ord(".")
    for place in range(6):
        higher = millionths // 10
        text[..., k + 7 - place] = millionths - 10 * higher + 48
        millionths = higher
    text[..., k + 8] = ord(",")
    text[:, -1, k + 8] = ord("\n")
    return text[text != 0].tobytes()


def write_measurement(out_dir: str | Path, t, angle1_deg, angle2_deg, meta: dict,
                      gains=None, when: _dt.datetime | None = None, companions: dict | None = None) -> Path:
    """Write one measurement (sidecar, companions, then the CSV as the commit); returns the
    CSV path.

    Parameters
    ----------
    out_dir : directory (created if missing)
    t : (n,) sample times [s], increasing
    angle1_deg, angle2_deg : (n,) absolute joint angles q1, q2 [deg]
    meta : extra sidecar fields (JSON-serializable); ``completed`` must be a bool if given
    gains : (pos_gain, vel_gain, vel_integrator_gain) or None
    when : time stamp of the name (default now)
    companions : {suffix: bytes}, optional
        Files that belong to the measurement (a torque run's table: ``{"_torque.csv": ...}``),
        named ``<stem><suffix>``: written after the sidecar, which holds their SHA-256s
        (``companions``), and before the commit, so they are part of the one unit.

    The name carries the exact gains and a random part, so it never collides with another
    writer's; an interruption at any point leaves either the whole measurement or an
    uncommitted sidecar/companion/temporary file that readers ignore and a resumed sweep
    sets aside (see the module notes).
    """
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        out_dir.mkdir(parents=True, exist_ok=True)
    t, a1, a2 = (np.asarray(v, dtype=float) for v in (t, angle1_deg, angle2_deg))
    if not (t.shape == a1.shape == a2.shape) or t.ndim != 1 or t.size < 2:
        raise ValueError(f"write_measurement: t, angle1, angle2 must be 1-D of equal length >= 2, "
                         f"got {t.shape}, {a1.shape}, {a2.shape}")
    data = np.column_stack([t, a1, a2])
    if not np.all(np.isfinite(data)) or np.any(np.abs(data[:, 1:]) > ANGLE_LIMIT_DEG):
        raise ValueError(f"write_measurement: angles must be finite and within +-{ANGLE_LIMIT_DEG} deg")
    if "completed" in meta and not isinstance(meta["completed"], (bool, np.bool_)):
        raise ValueError(f"write_measurement: meta['completed'] must be a bool, got {meta['completed']!r}")
    body = _csv_bytes(data)
    for _ in range(100):
        path = out_dir / measurement_filename(gains, when)
        side = sidecar_path(path)
        sidecar = {**provenance(), **meta,
                   "format": FORMAT, "columns": COLUMNS, "angles": "absolute",
                   "gains": None if gains is None else [float(g) for g in gains],
                   "samples": int(t.size), "csv_sha256": hashlib.sha256(body).hexdigest()}
        if companions:
            sidecar["companions"] = {sfx: hashlib.sha256(data).hexdigest() for sfx, data in companions.items()}
        text = _sidecar_text(sidecar)
        try:
            write_bytes_atomic(side, text)
        except FileExistsError:
            continue  # the random part collided: draw another
        for sfx, data in (companions or {}).items():
            write_bytes_atomic(companion_path(path, sfx), data)
        write_bytes_atomic(path, body)  # the commit
        return path
    raise FileExistsError(f"{out_dir}: could not find a free measurement name")






def write_batch(out_dir: str | Path, series, meta: dict, when: _dt.datetime | None = None) -> Path:
    """Write many measurements as one batch file (sidecar, then the CSV as the commit);
    returns the CSV path.

    Parameters
    ----------
    out_dir : directory (created if missing)
    series : sequence of ``(t, angle1_deg, angle2_deg, gains, point_meta)``, one per
        measurement: as :func:`write_measurement`'s ``t``, angles and gains (required
        here), and the sidecar fields of that measurement alone (``completed`` a bool,
        ``abort_reason``)
    meta : the sidecar fields all of them share (device, experiment)
    when : time stamp of the name (default now)

    One file for a whole twin sweep: creating files is what costs (see the module notes).
    While it is written, the batch's name is claimed (:func:`claim`), so a resumed sweep
    does not take a live writer's unfinished batch for a leftover.
    """
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        out_dir.mkdir(parents=True, exist_ok=True)
    series = list(series)
    if not series:
        raise ValueError("write_batch: no measurements to write")
    columns, points = [], []
    for k, item in enumerate(series):
        where = f"write_batch: measurement {k}"
        if len(item) != 5:
            raise ValueError(f"{where}: expected (t, angle1_deg, angle2_deg, gains, point_meta), "
                             f"got {len(item)} items")
        t, a1, a2, gains, pmeta = item
        t, a1, a2 = (np.asarray(v, dtype=float) for v in (t, a1, a2))
        if not (t.shape == a1.shape == a2.shape) or t.ndim != 1 or t.size < 2:
            raise ValueError(f"{where}: t, angle1, angle2 must be 1-D of equal length >= 2, "
                             f"got {t.shape}, {a1.shape}, {a2.shape}")
        g = [float(x) for x in gains] if gains is not None and not isinstance(gains, (str, bytes)) else []
        if len(g) != 3 or not all(math.isfinite(x) for x in g):
            raise ValueError(f"{where}: gains must be three finite numbers, got {gains!r}")
        if not isinstance(pmeta, dict):
            raise ValueError(f"{where}: point_meta must be a dict, got {type(pmeta).__name__}")
        if "completed" in pmeta and not isinstance(pmeta["completed"], (bool, np.bool_)):
            raise ValueError(f"{where}: point_meta['completed'] must be a bool, got {pmeta['completed']!r}")
        points.append({**pmeta, "gains": g, "samples": int(t.size)})
        columns.append((t, a1, a2))
    data = np.empty((sum(p["samples"] for p in points), 3))
    for j in range(3):
        np.concatenate([c[j] for c in columns], out=data[:, j])
    # everything within the angle limit (times too, as in a sweep) is valid; min and max
    # are NaN where a NaN is; only otherwise the columns are looked at one by one (no
    # temporary arrays in the common case: fresh pages cost)
    lo, hi = data.min(), data.max()
    if not (-ANGLE_LIMIT_DEG <= lo and hi <= ANGLE_LIMIT_DEG) and not (
            np.isfinite(data[:, 0]).all() and np.abs(data[:, 1:]).max() <= ANGLE_LIMIT_DEG):
        good = np.isfinite(data).all(axis=1) & (np.abs(data[:, 1:]) <= ANGLE_LIMIT_DEG).all(axis=1)
        k = int(np.searchsorted(np.cumsum([p["samples"] for p in points]), np.argmin(good), side="right"))
        raise ValueError(f"write_batch: measurement {k}: values must be finite and angles within "
                         f"+-{ANGLE_LIMIT_DEG} deg")
    body = _csv_bytes(data)
    meta = json.loads(json.dumps(meta, default=_json_default))   # plain JSON values (numpy scalars too); TypeError else
    sidecar = {**provenance(), **meta, "format": BATCH_FORMAT, "columns": COLUMNS, "angles": "absolute",
               "points": points, "samples": int(data.shape[0]),
               "csv_sha256": hashlib.sha256(body).hexdigest()}
    text = _sidecar_text(sidecar)
    for _ in range(100):
        path = out_dir / batch_filename(when)
        mine = claim(out_dir, BATCH_RE.match(path.name).group("uid"))
        if mine is None:
            continue
        try:
            try:
                write_bytes_atomic(sidecar_path(path), text)
            except FileExistsError:
                continue  # the random part collided: draw another
            write_bytes_atomic(path, body)  # the commit
            return path
        finally:
            mine.release()
    raise FileExistsError(f"{out_dir}: could not find a free batch name")


def _sidecar_text(sidecar: dict) -> bytes:
    """A sidecar's text: ``json.dumps`` with sorted keys, indented by two (numpy values as
    Python's)."""
    return json.dumps(sidecar, indent=2, sort_keys=True, default=_json_default).encode()


def companion_path(path: str | Path, suffix: str) -> Path:
    """The companion file ``suffix`` (e.g. ``"_torque.csv"``) of measurement ``path``."""
    path = Path(path)
    return path.with_name(path.name.replace("_positions.csv", suffix))


def read_companion(path: str | Path, suffix: str, meta: dict, columns: int) -> np.ndarray:
    """A measurement's companion table, checked against the SHA-256 its sidecar holds
    (``meta["companions"]``); a companion the sidecar does not list is read as it is (files
    written before companions were hashed).

    Raises
    ------
    MeasurementError
        The file is missing, malformed, or not the one the sidecar committed.
    """
    file = companion_path(path, suffix)
    raw = _read_regular(file, MAX_CSV_BYTES, "file")
    want = (meta.get("companions") or {}).get(suffix)
    if want is not None and hashlib.sha256(raw).hexdigest() != want:
        raise MeasurementError(f"{file}: its SHA-256 differs from the one {sidecar_path(path).name} committed "
                               f"(companions.{suffix}): not this measurement's file")
    return _parse_csv(file, raw, "file", columns)


def csv_bytes(data) -> bytes:
    """A numeric table as leglib writes it (six decimals, comma-separated)."""
    return _csv_bytes(np.asarray(data, dtype=float))


def write_table(path: str | Path, data) -> Path:
    """Write a numeric table as CSV atomically (never overwriting)."""
    return write_bytes_atomic(path, _csv_bytes(data))


def _read_regular(path: Path, limit: int, what: str, missing_ok: bool = False) -> bytes | None:
    """The bytes of ``path`` if it is a regular file (symlinks followed) of at most ``limit``
    bytes; MeasurementError otherwise. Never blocks on a FIFO or reads a device.
    ``missing_ok``: None when no such name exists (a dangling symlink is an error)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except FileNotFoundError:
        if missing_ok and not os.path.lexists(path):
            return None
        raise MeasurementError(f"{path}: {what} not found") from None
    except OSError as exc:
        reason = {errno.ELOOP: "a symlink loop", errno.EISDIR: "a directory",
                  errno.EACCES: "not readable (permission denied)"}.get(exc.errno, exc.strerror)
        raise MeasurementError(f"{path}: cannot open {what}: {reason}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            kind = ("a directory" if stat.S_ISDIR(st.st_mode) else "a FIFO" if stat.S_ISFIFO(st.st_mode)
                    else "a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode)
                    else "a socket" if stat.S_ISSOCK(st.st_mode) else "not a regular file")
            raise MeasurementError(f"{path}: {what} is {kind}, not a regular file")
        if st.st_size > limit:
            raise MeasurementError(f"{path}: {what} is {st.st_size} bytes, more than the {limit} "
                                   f"a measurement may have")
        # one read when the size is as stat said: a regular file reads short only at its end
        first = os.read(fd, st.st_size + 1)
        if len(first) <= st.st_size:
            return first
        chunks, total = [first], len(first)
        if total > limit:
            raise MeasurementError(f"{path}: {what} grew beyond {limit} bytes while reading")
        while True:
            chunk = os.read(fd, 1 << 20)
            if not chunk:
                break
            total += len(chunk)
            if total > limit:
                raise MeasurementError(f"{path}: {what} grew beyond {limit} bytes while reading")
            chunks.append(chunk)
        return b"".join(chunks)
    except OSError as exc:
        raise MeasurementError(f"{path}: cannot read {what}: {exc.strerror}") from None
    finally:
        os.close(fd)


def _decode(path: Path, raw: bytes, what: str) -> str:
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        raise MeasurementError(f"{path}:{line}: {what} is not UTF-8 text "
                               f"(byte 0x{raw[exc.start]:02x} at offset {exc.start})") from None


def _row_error(path: Path, lineno: int, line: str, columns: int, names: str) -> MeasurementError:
    if len(line) > MAX_LINE_CHARS:
        return MeasurementError(f"{path}:{lineno}: line of {len(line)} characters (at most "
                                f"{MAX_LINE_CHARS}): {_excerpt(line)}")
    parts = line.split(",")
    if len(parts) != columns:
        return MeasurementError(f"{path}:{lineno}: expected {columns} comma-separated columns {names}, "
                                f"got {len(parts)}: {_excerpt(line)}")
    for i, p in enumerate(parts, start=1):
        if not NUMBER_RE.match(p.strip(" \t\r")):
            low = p.strip().lower()
            kind = "NaN or infinite value" if low.lstrip("+-") in ("nan", "inf", "infinity") else "not a number"
            return MeasurementError(f"{path}:{lineno}: column {i}: {kind} in {_excerpt(line)}")
    return MeasurementError(f"{path}:{lineno}: cannot read {_excerpt(line)}")


def _parse_rows(path: Path, text: str, columns: int = 3, names: str = "",
                increasing_first: bool = False, angle_columns=()) -> np.ndarray:
    """Parse numeric CSV text strictly: MeasurementError naming file and line for a wrong
    column count, a non-number (strict ASCII decimal syntax), NaN or infinity, an angle
    beyond ANGLE_LIMIT_DEG, or (``increasing_first``) a first column that does not increase."""
    row_re = _ROW_RE if columns == 3 else None
    rows = []
    prev = -math.inf
    for lineno, line in enumerate(text.split("\n"), start=1):
        if not line.strip():
            continue
        m = row_re.match(line) if row_re is not None and len(line) <= MAX_LINE_CHARS else None
        if m is None:
            parts = line.split(",")
            if (row_re is not None or len(line) > MAX_LINE_CHARS or len(parts) != columns
                    or not all(NUMBER_RE.match(p.strip(" \t\r")) for p in parts)):
                raise _row_error(path, lineno, line, columns, names)
            vals = [float(p) for p in parts]
        else:
            vals = [float(x) for x in m.groups()]
        for i, v in enumerate(vals, start=1):
            if not math.isfinite(v):
                raise MeasurementError(f"{path}:{lineno}: column {i}: NaN or infinite value in {_excerpt(line)}")
        for c in angle_columns:
            if abs(vals[c]) > ANGLE_LIMIT_DEG:
                raise MeasurementError(f"{path}:{lineno}: column {c + 1}: angle {vals[c]:g} deg beyond "
                                       f"+-{ANGLE_LIMIT_DEG:g} deg")
        if increasing_first:
            if not vals[0] > prev:
                raise MeasurementError(f"{path}:{lineno}: time {vals[0]} does not increase (previous {prev})")
            prev = vals[0]
        rows.append(vals)
    if not rows:
        raise MeasurementError(f"{path}: no data rows")
    return np.array(rows)


_PLAIN_BYTES = b"0123456789+-.eE,\n"   # all a plain file holds (what leglib writes)


def _parse_plain(raw: bytes, columns: int, increasing_first: bool, angle_columns) -> np.ndarray | None:
    """numpy's reading (``np.loadtxt``) of a plain file, or None for the careful reader.

    A plain file holds only the bytes of :data:`_PLAIN_BYTES` and no line longer than
    :data:`MAX_LINE_CHARS`. On those bytes the grammar of a number is Python's ``float``
    (its other spellings need letters, ``_`` or white space) and loadtxt converts as
    ``float`` does, so it refuses a field exactly where :func:`_parse_rows` would; empty
    lines are skipped by both. None also where the numbers break a rule (columns, NaN or
    infinity, an angle beyond the limit, time not increasing, no row): the careful
    reader then words the error.
    """
    if raw.translate(None, _PLAIN_BYTES):
        return None
    ends = np.flatnonzero(np.frombuffer(raw, np.uint8) == 10)
    if ends.size == len(raw):   # nothing but newlines
        return None
    starts = np.concatenate(([-1], ends))
    if np.diff(starts).max(initial=0) > MAX_LINE_CHARS + 1 or len(raw) - 1 - starts[-1] > MAX_LINE_CHARS:
        return None
    try:
        data = np.loadtxt(io.BytesIO(raw), delimiter=",", comments=None, ndmin=2, dtype=float)
    except ValueError:
        return None
    if data.shape[1] != columns or not data.size or not np.isfinite(data).all():
        return None
    if angle_columns and np.abs(data[:, list(angle_columns)]).max() > ANGLE_LIMIT_DEG:
        return None
    if increasing_first and not (np.diff(data[:, 0]) > 0).all():
        return None
    return data


def _parse_csv(path: Path, raw: bytes, what: str, columns: int = 3, names: str = "",
               increasing_first: bool = False, angle_columns=()) -> np.ndarray:
    """:func:`_parse_rows` of the UTF-8 text ``raw``, the same numbers and the same errors:
    a plain file (what leglib writes) is read by numpy (:func:`_parse_plain`); any other,
    and one that breaks a rule, row by row, which reads it or raises the error naming
    file and line."""
    data = _parse_plain(raw, columns, increasing_first, angle_columns)
    if data is not None:
        return data
    return _parse_rows(path, _decode(path, raw, what), columns, names, increasing_first, angle_columns)


def read_table(path: str | Path, columns: int) -> np.ndarray:
    """Read a numeric CSV with ``columns`` columns; MeasurementError naming file and line."""
    path = Path(path)
    return _parse_csv(path, _read_regular(path, MAX_CSV_BYTES, "file"), "file", columns)


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serializable: {type(o).__name__}")


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _bad_field(side: Path, meta: dict, fieldname: str, expected: str, prefix: str = "") -> MeasurementError:
    return MeasurementError(f"{side}: field {prefix}{fieldname!r} must be {expected}, got "
                            f"{_excerpt(json.dumps(meta[fieldname]))}")


def _is_gains(g) -> bool:
    """A sidecar's gains: a list of three finite numbers."""
    return isinstance(g, list) and len(g) == 3 and all(_is_number(x) for x in g)


def _check_fields(side: Path, meta, prefix: str = "") -> None:
    """The types of a sidecar's optional fields (of a measurement, or of one measurement
    of a batch: ``prefix`` names where in the sidecar)."""
    if not isinstance(meta, dict):
        what = f"field {prefix.rstrip('.')}" if prefix else "sidecar"
        raise MeasurementError(f"{side}: {what} must be a JSON object, got {type(meta).__name__}")
    if "columns" in meta and meta["columns"] != COLUMNS:
        raise _bad_field(side, meta, "columns", repr(COLUMNS), prefix)
    if "angles" in meta and meta["angles"] not in ("absolute", "relative"):
        raise _bad_field(side, meta, "angles", "'absolute' or 'relative'", prefix)
    if "completed" in meta and not isinstance(meta["completed"], bool):
        raise _bad_field(side, meta, "completed", "true or false (a JSON boolean)", prefix)
    for key in ("step_turns", "sample_rate_hz", "period_s", "rate_hz"):
        if key in meta and meta[key] is not None and not _is_number(meta[key]):
            raise _bad_field(side, meta, key, "a finite number", prefix)
    if "abort_reason" in meta and not (meta["abort_reason"] is None or isinstance(meta["abort_reason"], str)):
        raise _bad_field(side, meta, "abort_reason", "a string or null", prefix)
    companions = meta.get("companions")
    if companions is not None and not (isinstance(companions, dict) and all(
            isinstance(k, str) and k.startswith("_") and isinstance(v, str) and len(v) == 64 for k, v in companions.items())):
        raise _bad_field(side, meta, "companions", "an object of '_<suffix>': SHA-256 hex", prefix)


def _check_contents(side: Path, meta: dict, csv: Path, raw: bytes, n: int, required: bool) -> None:
    """The sidecar's sample count and SHA-256 against the CSV's ``n`` rows and bytes."""
    if "samples" in meta:
        s = meta["samples"]
        if not isinstance(s, int) or isinstance(s, bool):
            raise _bad_field(side, meta, "samples", "an integer")
        if s != n:
            raise MeasurementError(f"{csv}: {n} samples, but its sidecar {side.name} says {s} "
                                   f"(a cut or extended file)")
    elif required:
        raise MeasurementError(f"{side}: field 'samples' missing")
    if "csv_sha256" in meta:
        h = meta["csv_sha256"]
        if not isinstance(h, str) or not re.fullmatch(r"[0-9a-f]{64}", h):
            raise _bad_field(side, meta, "csv_sha256", "64 hexadecimal digits")
        if hashlib.sha256(raw).hexdigest() != h:
            raise MeasurementError(f"{csv}: contents differ from those committed with its sidecar "
                                   f"{side.name} (SHA-256 mismatch): the file was changed after writing")
    elif required:
        raise MeasurementError(f"{side}: field 'csv_sha256' missing")


def _check_sidecar(side: Path, meta, csv: Path, raw: bytes, n: int, name_gains, exact_name: bool) -> tuple | None:
    """Check a sidecar's types and its agreement with the CSV and its name; returns its gains."""
    _check_fields(side, meta)

    def bad(fieldname, expected):
        return _bad_field(side, meta, fieldname, expected)

    fmt = meta.get("format", 1)
    if not isinstance(fmt, int) or isinstance(fmt, bool) or not 1 <= fmt <= FORMAT:
        raise bad("format", f"an integer 1..{FORMAT}")
    _check_contents(side, meta, csv, raw, n, required=fmt >= 2)
    gains = None
    if meta.get("gains") is not None:
        g = meta["gains"]
        if not _is_gains(g):
            raise bad("gains", "a list of three finite numbers or null")
        gains = tuple(float(x) for x in g)
        if name_gains is not None:
            same = (gains == name_gains if exact_name
                    else all(abs(a - b) <= 0.0005 + 1e-9 for a, b in zip(gains, name_gains)))
            if not same:
                raise MeasurementError(f"{csv}: gains in the name {name_gains} differ from the sidecar's "
                                       f"{gains} ({side.name}, field 'gains')")
    elif "gains" in meta and name_gains is not None:
        raise MeasurementError(f"{side}: field 'gains' is null, but the file name gives {name_gains}")
    elif fmt >= 2 and name_gains is not None and "gains" not in meta:
        raise MeasurementError(f"{side}: field 'gains' missing")
    return gains


def _sidecar_json(side: Path, raw: bytes):
    """The JSON value of a sidecar's bytes; MeasurementError naming the file and line."""
    try:
        return json.loads(_decode(side, raw, "sidecar"))
    except json.JSONDecodeError as exc:
        raise MeasurementError(f"{side}:{exc.lineno}: sidecar is not valid JSON: {exc.msg}") from None
    except RecursionError:
        raise MeasurementError(f"{side}: sidecar is nested too deeply") from None


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
    point: int | None = None   # its place in a batch file (0-based); None for a file of its own

    @property
    def where(self) -> str:
        """The file, and for a batch which of its measurements: for messages."""
        return str(self.path) if self.point is None else f"{self.path} (measurement {self.point + 1} of the batch)"

    @property
    def absolute(self) -> bool:
        return self.meta.get("angles") == "absolute"

    @property
    def stable(self) -> bool:
        """False when the experiment aborted (unstable); thesis files count as completed."""
        return self.meta.get("completed", True) is True


def read_measurement(path: str | Path) -> Measurement:
    """Read and validate a measurement CSV and its sidecar.

    Raises MeasurementError naming the file, line and field for: an unparseable file name;
    anything but a regular UTF-8 file of bounded size; a row without exactly three strict
    decimal numbers, NaN or infinite values, angles beyond ANGLE_LIMIT_DEG, non-increasing
    time, fewer than two rows; a sidecar that is not a JSON object, has fields of the wrong
    type, a sample count or hash that does not match the CSV, or gains that differ from the
    name's; a format-2 file without its sidecar; a sidecar-less thesis-named file whose
    angles do not start at zero.
    """
    path = Path(path)
    if is_batch_name(path):
        raise MeasurementError(f"{path}: a batch file holds several measurements: read it with "
                               f"leglib.files.measurements.read_file (or read_measurements)")
    _, name_gains, uid = _parse_name(path)
    raw = _read_regular(path, MAX_CSV_BYTES, "measurement file")
    data = _parse_csv(path, raw, "measurement file", 3, "(time, angle1, angle2)", increasing_first=True,
                      angle_columns=(1, 2))
    if len(data) < 2:
        raise MeasurementError(f"{path}: fewer than two data rows")
    side = sidecar_path(path)
    side_raw = _read_regular(side, MAX_SIDECAR_BYTES, "sidecar", missing_ok=True)
    if side_raw is not None:
        meta = _sidecar_json(side, side_raw)
        gains = _check_sidecar(side, meta, path, raw, len(data), name_gains, exact_name=uid is not None)
        gains = gains if gains is not None else name_gains
    else:
        if uid is not None:
            raise MeasurementError(f"{path}: sidecar {side.name} missing: a leglib measurement without "
                                   f"its sidecar is incomplete or damaged (re-measure it)")
        start = max(abs(data[0, 1]), abs(data[0, 2]))
        if start > RELATIVE_START_DEG:
            raise MeasurementError(
                f"{path}:1: no sidecar, so a thesis file with angles relative to the start, but the "
                f"first row is {data[0, 1]:g}, {data[0, 2]:g} deg: absolute angles without their "
                f"sidecar (an interrupted leglib write?); re-measure it")
        meta, gains = {}, name_gains
    return Measurement(path=path, t=data[:, 0], angle1=data[:, 1], angle2=data[:, 2],
                       gains=gains, meta=meta)


def _row_line(path: Path, raw: bytes, row: int) -> int:
    """The line number of data row ``row`` (0-based; lines of whitespace hold no row)."""
    seen = -1
    for lineno, line in enumerate(_decode(path, raw, "batch file").split("\n"), start=1):
        if line.strip():
            seen += 1
            if seen == row:
                return lineno
    return row + 1


def read_batch(path: str | Path) -> list[Measurement]:
    """Read and validate a batch file and its sidecar: its measurements, in order.

    Checks as :func:`read_measurement` does (regular UTF-8 file of bounded size, strict rows,
    angles within the limit, the sidecar's types, total sample count and SHA-256), and
    for every measurement of the batch its gains (three finite numbers), its sample count
    (at least two; together they make up the file) and increasing time. Errors are
    MeasurementError naming file, line and field (``points[k]`` is measurement k + 1).
    """
    path = Path(path)
    if not is_batch_name(path):
        raise MeasurementError(f"{path}: not a batch file name (expected YYYYmmdd_HHMMSS_lg<12 hex>_batch.csv)")
    raw = _read_regular(path, MAX_BATCH_CSV_BYTES, "batch file")
    data = _parse_csv(path, raw, "batch file", 3, "(time, angle1, angle2)", angle_columns=(1, 2))
    side = sidecar_path(path)
    side_raw = _read_regular(side, MAX_BATCH_SIDECAR_BYTES, "sidecar", missing_ok=True)
    if side_raw is None:
        raise MeasurementError(f"{path}: sidecar {side.name} missing: a batch without its sidecar is "
                               f"incomplete or damaged (re-measure it)")
    meta = _sidecar_json(side, side_raw)
    _check_fields(side, meta)
    fmt = meta.get("format")
    if type(fmt) is not int or fmt != BATCH_FORMAT:
        raise MeasurementError(f"{side}: field 'format' must be {BATCH_FORMAT} (a batch), got "
                               f"{_excerpt(json.dumps(fmt))}")
    if meta.get("angles") != "absolute":
        raise MeasurementError(f"{side}: field 'angles' must be 'absolute' (a batch holds absolute "
                               f"joint angles), got {_excerpt(json.dumps(meta.get('angles')))}")
    _check_contents(side, meta, path, raw, len(data), required=True)
    points = meta.get("points")
    if not isinstance(points, list) or not points:
        raise MeasurementError(f"{side}: field 'points' must be a non-empty list of objects, one per "
                               f"measurement, got {_excerpt(json.dumps(points))}")
    for k, pm in enumerate(points):
        where = f"points[{k}]."
        _check_fields(side, pm, where)
        other = sorted(set(pm) - set(BATCH_POINT_FIELDS))
        if other:
            raise MeasurementError(f"{side}: field {where}{other[0]!r} does not belong to one measurement "
                                   f"of a batch (its fields: {', '.join(BATCH_POINT_FIELDS)})")
        if not isinstance(pm.get("completed"), bool):
            raise MeasurementError(f"{side}: field {where}'completed' must be true or false, got "
                                   f"{_excerpt(json.dumps(pm.get('completed')))}")
        g = pm.get("gains")
        if not _is_gains(g):
            raise MeasurementError(f"{side}: field {where}'gains' must be a list of three finite numbers, "
                                   f"got {_excerpt(json.dumps(g))}")
        n = pm.get("samples")
        if not isinstance(n, int) or isinstance(n, bool) or n < 2:
            raise MeasurementError(f"{side}: field {where}'samples' must be an integer >= 2, "
                                   f"got {_excerpt(json.dumps(n))}")
    total = sum(pm["samples"] for pm in points)
    if total != len(data):
        raise MeasurementError(f"{side}: its measurements' 'samples' add up to {total}, but {path.name} "
                               f"has {len(data)} rows")
    # time increases within each measurement (one pass: a step back is allowed only where
    # the next measurement begins)
    ends = np.cumsum([pm["samples"] for pm in points])
    rises = np.diff(data[:, 0]) > 0
    rises[ends[:-1] - 1] = True
    if not rises.all():
        row = 1 + int(np.argmin(rises))
        k = int(np.searchsorted(ends, row, side="right"))
        raise MeasurementError(f"{path}:{_row_line(path, raw, row)}: time {data[row, 0]} does not increase "
                               f"(previous {data[row - 1, 0]}) within measurement {k + 1} of the batch")
    common = {k: v for k, v in meta.items() if k not in ("points", "samples", "csv_sha256")}
    out, start = [], 0
    for k, pm in enumerate(points):
        n = pm["samples"]
        out.append(Measurement(path=path, t=data[start:start + n, 0], angle1=data[start:start + n, 1],
                               angle2=data[start:start + n, 2], gains=tuple(float(x) for x in pm["gains"]),
                               meta={**common, **pm}, point=k))
        start += n
    return out


def read_file(path: str | Path) -> list[Measurement]:
    """The measurements of one file: a batch's (:func:`read_batch`) or the one of a
    measurement file (:func:`read_measurement`)."""
    return read_batch(path) if is_batch_name(path) else [read_measurement(path)]
