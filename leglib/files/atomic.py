"""Files that appear whole or not at all: atomic writes, flushed to disk, never overwritten.

A file is written to a hidden temporary in its directory, flushed (``fsync``), then linked
to its name (an atomic link: it is never visible half-written, and an existing name is never
replaced), and the directory is flushed after. Inside :func:`deferred_sync` the per-file
flushes are left out and each directory written to is flushed once at the end.
"""

from __future__ import annotations

import contextlib
import contextvars
import json
import math
import os
import secrets
from pathlib import Path

import numpy as np


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


def oserror_naming(exc: OSError, path: str | Path, doing: str) -> OSError:
    """``exc`` (a full or read-only disk, no permission) as the same error naming ``path``."""
    if exc.filename is not None and str(path) in str(exc):
        return exc
    new = type(exc)(exc.errno, f"{doing} {path}: {exc.strerror or exc}", str(path))
    new.__cause__ = exc
    return new


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
    try:
        tmp = _write_temp(path.parent, path.name, data)
    except FileNotFoundError:
        raise
    except OSError as exc:   # a full or read-only disk, no permission: say which file
        raise oserror_naming(exc, path, "writing") from exc
    try:
        if overwrite:
            os.replace(tmp, path)
        else:
            _commit(tmp, path)  # removes tmp
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, FileExistsError):
            raise FileExistsError(f"{path}: exists; not overwriting") from None
        if isinstance(exc, OSError):  # the directory's entry could not be made (a full disk, ...)
            raise oserror_naming(exc, path, "committing") from exc
        raise
    deferred = _DEFERRED.get()
    if deferred is None:
        _fsync_dir(path.parent)
    else:
        deferred.add(path.parent)
    return path


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, complex):
        return [obj.real, obj.imag]
    return obj


def write_json_atomic(path: str | Path, data: dict) -> Path:
    """Write ``data`` as JSON via a temporary file and rename (never a half-written file;
    created with the user's umask)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(_jsonable(data), indent=2, sort_keys=True) + "\n"
    return write_bytes_atomic(path, text.encode(), overwrite=True)
