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

Files are never rewritten (writing an existing name is an error) and are created with
the user's umask.
"""

from __future__ import annotations

import contextlib
import contextvars
import datetime as _dt
import errno
import fcntl
import hashlib
import json
import math
import os
import re
import secrets
import stat
import subprocess
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import __version__

FORMAT = 2
MAX_CSV_BYTES = 64 << 20          # a 60 s run at 8 kHz is about 20 MB
MAX_SIDECAR_BYTES = 16 << 20
MAX_LINE_CHARS = 512
EXCERPT = 60                      # characters of a bad line or value quoted in a message
ANGLE_LIMIT_DEG = 3600.0          # |angle| beyond ten turns of a joint is not a measurement
RELATIVE_START_DEG = 10.0         # a thesis file's first row is within this of zero
COLUMNS = ["time [s]", "q1 [deg]", "q2 [deg]"]
INCOMPLETE_DIR = "incomplete"
PROVENANCE_FILE = "sweep.json"

_NUM = r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?"
NUMBER_RE = re.compile(rf"^{_NUM}$", re.ASCII)
_ROW_RE = re.compile(rf"^[ \t]*({_NUM})[ \t]*,[ \t]*({_NUM})[ \t]*,[ \t]*({_NUM})[ \t]*\r?$", re.ASCII)
NAME_RE = re.compile(r"^(?P<stamp>[0-9]{8}_[0-9]{6})(?:_(?P<gains>(?!lg)[^_]+))?"
                     r"(?:_(?P<uid>lg[0-9a-f]{12}))?_positions\.csv$", re.ASCII)
_UID_RE = re.compile(r"_lg[0-9a-f]{12}_positions\.json$", re.ASCII)
BATCH_FORMAT = 3
BATCH_RE = re.compile(r"^(?P<stamp>[0-9]{8}_[0-9]{6})_(?P<uid>lg[0-9a-f]{12})_batch\.csv$", re.ASCII)
_BATCH_SIDE_RE = re.compile(r"^[0-9]{8}_[0-9]{6}_lg[0-9a-f]{12}_batch\.json$", re.ASCII)
MAX_BATCH_CSV_BYTES = 1 << 30     # a batch holds many measurements (the thesis grid: 9 MB)
MAX_BATCH_SIDECAR_BYTES = 64 << 20
BATCH_POINT_FIELDS = ("abort_reason", "completed", "gains", "samples")   # a batch's points hold these


class MeasurementError(ValueError):
    """A measurement file is malformed; the message names the file (and line, field)."""


class ProvenanceError(ValueError):
    """A directory holds measurements of another leg or experiment."""


def _excerpt(text: str) -> str:
    return repr(text) if len(text) <= EXCERPT else repr(text[:EXCERPT]) + f" ... ({len(text)} characters)"


# -- names -------------------------------------------------------------------------------

def gains_key(gains) -> str:
    """The thesis's gains part of a file name: three decimals, ';'-separated (Listing 7.4)."""
    return ";".join(f"{float(g):.3f}" for g in gains)


def exact_gains_key(gains) -> str:
    """The gains part of a format-2 name: each gain's shortest exact decimal, ';'-separated.

    ``float(part)`` gives back the gain bit for bit, so near-equal gains never share a name.
    """
    parts = []
    for g in gains:
        g = float(g)
        if not math.isfinite(g):
            raise ValueError(f"gains must be finite, got {tuple(gains)}")
        parts.append(repr(g))
    return ";".join(parts)


def measurement_filename(gains=None, when: _dt.datetime | None = None, uid: str | None = None) -> str:
    """A format-2 name: ``<stamp>[_<exact gains>]_lg<uid>_positions.csv``."""
    when = when or _dt.datetime.now()
    uid = uid or secrets.token_hex(6)
    stamp = when.strftime("%Y%m%d_%H%M%S")
    middle = f"_{exact_gains_key(gains)}" if gains is not None else ""
    return f"{stamp}{middle}_lg{uid}_positions.csv"


def parse_filename(path: str | Path) -> tuple[str, tuple[float, float, float] | None]:
    """(timestamp, gains or None) from a measurement file name; MeasurementError otherwise.

    Gains are strict decimal numbers (digits, one point, an optional exponent): ``2_66.97``,
    full-width digits, ``nan`` and ``inf`` are refused.
    """
    return _parse_name(path)[:2]


def is_leglib_name(path: str | Path) -> bool:
    """True for a format-2 name (with the ``lg`` part): it must have a committed sidecar."""
    m = NAME_RE.match(Path(path).name)
    return bool(m and m.group("uid"))


def _parse_name(path):
    name = Path(path).name
    m = NAME_RE.match(name)
    if not m:
        raise MeasurementError(f"{path}: cannot parse file name (expected "
                               f"YYYYmmdd_HHMMSS_<posP>;<velP>;<velI>_positions.csv)")
    gains = None
    if m.group("gains") is not None:
        parts = m.group("gains").split(";")
        if len(parts) != 3 or not all(NUMBER_RE.match(p) for p in parts):
            raise MeasurementError(f"{path}: cannot parse gains {_excerpt(m.group('gains'))} from file name "
                                   f"(expected three decimal numbers separated by ';')")
        gains = tuple(float(p) for p in parts)
        if not all(math.isfinite(g) for g in gains):
            raise MeasurementError(f"{path}: gains in the file name are not finite")
    return m.group("stamp"), gains, m.group("uid")


def sidecar_path(path: str | Path) -> Path:
    """The sidecar of a measurement CSV: ``<stem>.json``."""
    return Path(path).with_suffix(".json")


# -- provenance of the code ---------------------------------------------------------------

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


# -- writing -----------------------------------------------------------------------------

def _write_temp(directory: Path, final_name: str, data: bytes) -> Path:
    """``data`` in a new hidden temporary file next to ``final_name``, flushed to disk
    (not within :func:`deferred_sync`).

    Created with mode 0666 less the umask (``tempfile.mkstemp`` would force 0600).
    """
    for _ in range(100):
        tmp = directory / f".{final_name}.{secrets.token_hex(4)}.tmp"
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except FileExistsError:
            continue
        try:
            try:
                view = memoryview(data)
                while view:
                    view = view[os.write(fd, view):]
                if _DEFERRED.get() is None:
                    os.fsync(fd)
            finally:
                os.close(fd)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        return tmp
    raise FileExistsError(f"{directory}: cannot create a temporary file for {final_name}")


def _commit(tmp: Path, path: Path) -> None:
    """Give the complete ``tmp`` its final name; fails if the name exists (never overwrites)."""
    try:
        os.link(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _fsync_dir(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


_DEFERRED: contextvars.ContextVar = contextvars.ContextVar("leglib_dataio_deferred_sync", default=None)


@contextlib.contextmanager
def deferred_sync():
    """Within, files written here are not flushed to disk one by one; on leaving (also by
    an exception), every directory written to is flushed once.

    For writes that are cheap to repeat (a twin sweep's batch): the commit protocol is
    unchanged, but after a power loss the files written since the last flush may be
    missing, empty or cut (the reader refuses them; see the module notes). Measurements
    of the real leg are written without it.
    """
    dirs: set = set()
    token = _DEFERRED.set(dirs)
    try:
        yield
    finally:
        _DEFERRED.reset(token)
        for d in sorted(dirs):
            _fsync_dir(d)


def write_bytes_atomic(path: str | Path, data: bytes, overwrite: bool = False) -> Path:
    """Write ``data`` to ``path`` via a temporary file: the name shows a complete file or
    none. ``overwrite=False`` raises FileExistsError rather than replace a file."""
    path = Path(path)
    tmp = _write_temp(path.parent, path.name, data)
    try:
        if overwrite:
            os.replace(tmp, path)
        else:
            _commit(tmp, path)  # removes tmp
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, FileExistsError):
            raise FileExistsError(f"{path}: exists; not overwriting") from None
        raise
    deferred = _DEFERRED.get()
    if deferred is None:
        _fsync_dir(path.parent)
    else:
        deferred.add(path.parent)
    return path


def _csv_bytes(data: np.ndarray):
    """Rows of ``data`` as ``"%.6f,%.6f,...\\n"`` ASCII (bytes, or a uint8 array of them
    valid until the next call in this thread: hash and write it at once): compiled, or
    (for the values it cannot format exactly: ties, huge, non-finite) one Python format of
    the whole table."""
    from . import csvcodec  # numba: imported on first use

    data = np.atleast_2d(np.asarray(data, dtype=float))
    body = csvcodec.format_fixed6_array(data, reuse=True)
    if body is None:
        row = ",".join(["%.6f"] * data.shape[1]) + "\n"
        body = ((row * data.shape[0]) % tuple(data.ravel().tolist())).encode("ascii")
    return body


def write_measurement(out_dir: str | Path, t, angle1_deg, angle2_deg, meta: dict,
                      gains=None, when: _dt.datetime | None = None) -> Path:
    """Write one measurement (sidecar, then the CSV as the commit); returns the CSV path.

    Parameters
    ----------
    out_dir : directory (created if missing)
    t : (n,) sample times [s], increasing
    angle1_deg, angle2_deg : (n,) absolute joint angles q1, q2 [deg]
    meta : extra sidecar fields (JSON-serializable); ``completed`` must be a bool if given
    gains : (pos_gain, vel_gain, vel_integrator_gain) or None
    when : time stamp of the name (default now)

    The name carries the exact gains and a random part, so it never collides with another
    writer's; an interruption at any point leaves either the whole measurement or an
    uncommitted sidecar/temporary file that readers ignore (see the module notes).
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
        text = _json_text(sidecar)
        try:
            write_bytes_atomic(side, text)
        except FileExistsError:
            continue  # the random part collided: draw another
        write_bytes_atomic(path, body)  # the commit
        return path
    raise FileExistsError(f"{out_dir}: could not find a free measurement name")


def batch_filename(when: _dt.datetime | None = None, uid: str | None = None) -> str:
    """A batch file's name: ``<stamp>_lg<uid>_batch.csv``."""
    when = when or _dt.datetime.now()
    return f"{when.strftime('%Y%m%d_%H%M%S')}_lg{uid or secrets.token_hex(6)}_batch.csv"


def is_batch_name(path: str | Path) -> bool:
    """True for a batch file's name (several measurements in one file, see the module notes)."""
    return bool(BATCH_RE.match(Path(path).name))


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
    meta = json.loads(_COMPACT.encode(meta))   # plain JSON values (numpy scalars too); TypeError else
    sidecar = {**provenance(), **meta, "format": BATCH_FORMAT, "columns": COLUMNS, "angles": "absolute",
               "points": points, "samples": int(data.shape[0]),
               "csv_sha256": hashlib.sha256(body).hexdigest()}
    text = _json_text(sidecar, one_per_line=("points",))
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


_LAYOUTS: dict = {}  # compact JSON of a nested value -> its indented layout (see _json_text)
_json_string = json.encoder.encode_basestring_ascii  # what json writes for a str (ensure_ascii)
_JSON_SCALARS = (str, int, float, type(None))  # bool is an int


def _json_text(obj, one_per_line=()) -> bytes:
    """``json.dumps(obj, indent=2, sort_keys=True, default=_json_default)``, the same text;
    except that the lists under the keys ``one_per_line`` are written one compact element
    a line (a batch's measurements).

    json lays out indented text in Python (about 0.2 ms for a sidecar). Here the top level
    is laid out directly and each nested value's layout is remembered by its compact JSON
    (written by json's compiled encoder): a sweep's sidecars repeat the same device
    description. Anything else (no dict, other key or value types) goes to json.dumps.
    """
    if not (isinstance(obj, dict) and obj and all(type(k) is str for k in obj)
            and all(isinstance(v, _JSON_SCALARS + (dict, list, tuple)) for v in obj.values())):
        if one_per_line:
            raise TypeError("_json_text: one_per_line needs a dict of JSON values")
        return json.dumps(obj, indent=2, sort_keys=True, default=_json_default).encode()
    lines = []
    for k in sorted(obj):
        v = obj[k]
        if k in one_per_line and isinstance(v, (list, tuple)) and v:
            text = "[\n    " + ",\n    ".join(_COMPACT.encode(x) for x in v) + "\n  ]"
        elif isinstance(v, (dict, list, tuple)) and v:
            compact = _COMPACT.encode(v)
            text = _LAYOUTS.get(compact)
            if text is None:
                text = _INDENTED.encode(v).replace("\n", "\n  ")
                if len(_LAYOUTS) >= 64:
                    _LAYOUTS.clear()
                _LAYOUTS[compact] = text
        elif type(v) is str:
            text = _json_string(v)
        elif v is None or v is True or v is False:
            text = "null" if v is None else "true" if v else "false"
        elif type(v) is int or (type(v) is float and math.isfinite(v)):
            text = repr(v)
        else:
            text = _COMPACT.encode(v)
        lines.append(f"  {_json_string(k)}: {text}")
    return ("{\n" + ",\n".join(lines) + "\n}").encode()


def write_table(path: str | Path, data) -> Path:
    """Write a numeric table as CSV atomically (never overwriting)."""
    return write_bytes_atomic(path, _csv_bytes(data))


# -- reading -----------------------------------------------------------------------------

def _read_into_scratch(fd: int, size: int):
    """The ``size`` bytes of the open regular file ``fd`` in this thread's scratch buffer
    for reading (:func:`leglib.csvcodec.scratch`; a memoryview of it, valid until the next
    call), or None when the file reads otherwise than its size said (the caller reads it
    the careful way)."""
    from . import csvcodec  # numba: imported on first use

    view = memoryview(csvcodec.scratch("read", size + 1))[:size + 1]
    n = os.readv(fd, [view])
    if n != size:
        os.lseek(fd, 0, os.SEEK_SET)
        return None
    return view[:n]


def _read_regular(path: Path, limit: int, what: str, missing_ok: bool = False, scratch: bool = False):
    """The bytes of ``path`` if it is a regular file (symlinks followed) of at most ``limit``
    bytes; MeasurementError otherwise. Never blocks on a FIFO or reads a device.
    ``missing_ok``: None when no such name exists (a dangling symlink is an error).
    ``scratch``: the file is read into this thread's scratch buffer and a memoryview of it
    returned, valid until the next such read (fresh memory is what reading a sweep's batch
    costs most where the system hands out pages slowly)."""
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
        if scratch:
            got = _read_into_scratch(fd, st.st_size)
            if got is not None:
                return got
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


def _decode(path: Path, raw, what: str) -> str:
    raw = raw if isinstance(raw, bytes) else bytes(raw)
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


def _parse_csv(path: Path, raw: bytes, what: str, columns: int = 3, names: str = "",
               increasing_first: bool = False, angle_columns=()) -> np.ndarray:
    """:func:`_parse_rows` of the UTF-8 text ``raw``, the same numbers and the same errors.

    Three-column files go through the compiled parser first (:func:`leglib.csvcodec.parse3`,
    one pass over the bytes, bit for bit as ``float()``); whatever it does not accept --
    a bad file, or one it cannot be sure of -- is decoded and parsed row by row here,
    which reads it or raises the error naming file and line."""
    if columns == 3 and tuple(angle_columns) in ((), (1, 2)):
        from . import csvcodec  # numba: imported on first use

        data = csvcodec.parse3(raw, MAX_LINE_CHARS, ANGLE_LIMIT_DEG if angle_columns else math.inf,
                               increasing_first)
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


_COMPACT = json.JSONEncoder(sort_keys=True, default=_json_default)
_INDENTED = json.JSONEncoder(indent=2, sort_keys=True, default=_json_default)


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
                               f"dataio.read_file (or read_measurements)")
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
    raw = _read_regular(path, MAX_BATCH_CSV_BYTES, "batch file", scratch=True)   # (not kept)
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
    """Read every measurement of a directory (or a list of paths).

    ``strict=True`` raises the first file's MeasurementError; ``strict=False`` skips bad
    files, lists them in ``problems`` and warns with their count, never silently.
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
    appeared and hidden temporary files. (A concurrent writer's in-flight files look the
    same: hold the point's :func:`claim` before removing them.)"""
    d = _directory(directory)
    found = [p for pattern, name_re in (("*_positions.json", _UID_RE), ("*_batch.json", _BATCH_SIDE_RE))
             for p in d.glob(pattern) if name_re.search(p.name) and not os.path.lexists(p.with_suffix(".csv"))]
    found += [p for p in d.glob(".*.tmp") if "_positions." in p.name or "_batch." in p.name]
    return sorted(found)


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


# -- claims: one writer per point --------------------------------------------------------

class Claim:
    """An exclusive claim on one grid point of a directory: held while the point is
    measured and written, released when the process ends (the kernel drops the lock), so a
    crashed writer never blocks the point."""

    def __init__(self, fd: int):
        self._fd = fd

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __del__(self):   # a claim nobody holds any more is released
        try:
            self.release()
        except Exception:  # noqa: BLE001 - never raise from a finalizer (e.g. at exit)
            pass


CLAIMS_FILE = ".claims.lock"
# Linux: one byte of one lock file per point, locked with an open-file-description lock
# (F_OFD_SETLK: owned by the open file, as flock, so two claims of one process exclude each
# other too). A sweep then creates one file for its claims, not one per point (creating a
# file is the costly part of a claim). Elsewhere: one lock file per point, with flock.
_OFD = (getattr(fcntl, "F_OFD_SETLK", None), getattr(fcntl, "F_OFD_SETLKW", None))
_FLOCK_STRUCT = "hhqqi4x"   # struct flock on 64-bit Linux: type, whence, start, len, pid


def _ofd_lock(fd: int, digest: bytes, wait: bool) -> bool:
    """Lock the byte of ``digest`` on the open file ``fd``; False if another holds it."""
    import struct
    offset = int.from_bytes(digest[:7], "big")   # a byte of a sparse range below 2^56
    lock = struct.pack(_FLOCK_STRUCT, fcntl.F_WRLCK, os.SEEK_SET, offset, 1, 0)
    try:
        fcntl.fcntl(fd, _OFD[1] if wait else _OFD[0], lock)
    except OSError as exc:
        if exc.errno in (errno.EAGAIN, errno.EACCES):
            return False
        raise
    return True


def _use_ofd() -> bool:
    return _OFD[0] is not None and sys.platform == "linux"


def _digest(key) -> bytes:
    return hashlib.sha1((key if isinstance(key, str) else exact_gains_key(key)).encode()).digest()


def _claim_ofd(directory: str | Path, digest: bytes, wait: bool) -> Claim | None:
    fd = os.open(os.path.join(directory, CLAIMS_FILE), os.O_RDWR | os.O_CREAT, 0o666)
    try:
        if _ofd_lock(fd, digest, wait):
            return Claim(fd)
    except BaseException:
        os.close(fd)
        raise
    os.close(fd)
    return None


class _Claims(Claim):
    """Claims of many points held together (released together)."""

    def __init__(self, claims: list):
        super().__init__(None)
        self._claims = claims

    def release(self) -> None:
        while self._claims:
            self._claims.pop().release()


def claim_many(directory: str | Path, keys, limit: int | None = None) -> tuple[Claim, list]:
    """:func:`claim` of each of ``keys`` (gains), up to ``limit`` taken: (one Claim that
    releases them all, a list of True where a key was taken). On Linux all are bytes
    locked on one open lock file (one open for a sweep's batch, not one per point)."""
    keys = list(keys)
    limit = len(keys) if limit is None else limit
    taken = []
    if _use_ofd():
        fd = os.open(os.path.join(directory, CLAIMS_FILE), os.O_RDWR | os.O_CREAT, 0o666)
        try:
            n, seen = 0, set()
            for key in keys:
                digest = _digest(key)
                # a key twice: taken once (one open file's locks never refuse each other)
                ok = n < limit and digest not in seen and _ofd_lock(fd, digest, False)
                seen.add(digest)
                n += ok
                taken.append(ok)
        except BaseException:
            os.close(fd)
            raise
        return Claim(fd), taken
    held = []
    try:
        for key in keys:
            c = claim(directory, key) if len(held) < limit else None
            if c is not None:
                held.append(c)
            taken.append(c is not None)
    except BaseException:
        _Claims(held).release()
        raise
    return _Claims(held), taken


def claim(directory: str | Path, gains, wait: bool = False) -> Claim | None:
    """Claim the point ``gains`` in ``directory`` (or, given a string, that name: a batch
    being written); None if another process holds it (``wait=True`` blocks until it is
    released)."""
    digest = _digest(gains)
    if _use_ofd():
        return _claim_ofd(directory, digest, wait)
    locks = os.path.join(directory, ".claims")
    lock = os.path.join(locks, digest.hex()[:20] + ".lock")
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
    except FileNotFoundError:  # the first claim in this directory
        try:
            os.mkdir(locks)
        except FileExistsError:
            pass
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
    except BlockingIOError:
        os.close(fd)
        return None
    except BaseException:
        os.close(fd)
        raise
    return Claim(fd)


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


# -- provenance of a directory ------------------------------------------------------------

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
