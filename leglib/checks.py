"""Checks of values where they enter leglib: numbers, booleans and numeric arrays.

Each check raises the error class it is given (one of :mod:`leglib.errors`), with a message
that names the argument (or file and field). Booleans are not numbers here, and numbers are
not booleans: ``True`` is refused as a gain, ``"no"`` as a switch.
"""

from __future__ import annotations

import math
import numbers
import os
import stat
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ArgumentError

__all__ = ["number", "integer", "boolean", "real_array", "text_file"]


def _short(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit] + "..."


def number(value, name: str, error=ArgumentError, *, low: float | None = None, high: float | None = None,
           low_open: bool = False, unit: str = "") -> float:
    """``value`` as a finite real float in [low, high] (``(low, high]`` with ``low_open``);
    ``error`` naming ``name`` otherwise (a bool, a string, a complex number, NaN, inf)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise error(f"{name} must be a real number, got {_short(value)}")
    try:
        v = float(value)
    except OverflowError:
        v = math.inf
    if not math.isfinite(v):
        raise error(f"{name} must be finite, got {_short(value)}")
    u = f" {unit}" if unit else ""
    if low is not None and (v <= low if low_open else v < low):
        raise error(f"{name} must be {'above' if low_open else 'at least'} {low:g}{u}, got {v:g}")
    if high is not None and v > high:
        raise error(f"{name} must be at most {high:g}{u}, got {v:g}")
    return v


def integer(value, name: str, error=ArgumentError, *, low: int | None = None, high: int | None = None) -> int:
    """``value`` as an int (an integral number, not a bool, not 2.5) in [low, high]."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise error(f"{name} must be an integer, got {_short(value)}")
    v = int(value)
    if low is not None and v < low:
        raise error(f"{name} must be at least {low}, got {v}")
    if high is not None and v > high:
        raise error(f"{name} must be at most {high}, got {v}")
    return v


def boolean(value, name: str, error=ArgumentError) -> bool:
    """``value`` as a bool: only True or False (numpy's too), never a string or a number."""
    if not isinstance(value, (bool, np.bool_)):
        raise error(f"{name} must be True or False, got {_short(value)}")
    return bool(value)


def real_array(value, name: str, error=ArgumentError, *, ndim: int | None = None, finite: bool = True,
               max_size: int | None = None) -> np.ndarray:
    """``value`` as a float ndarray; ``error`` naming ``name`` for anything that is not an array
    of real numbers (strings, objects, complex numbers), for a masked array with masked
    elements (masks are not honoured: drop those samples first), a wrong ``ndim``, more than
    ``max_size`` elements, and (with ``finite``) NaN or inf."""
    if isinstance(value, np.ma.MaskedArray):
        masked = int(np.count_nonzero(np.ma.getmaskarray(value)))
        if masked:
            raise error(f"{name} is a masked array with {masked} masked element(s): leglib does not honour "
                        f"masks; drop the masked samples first (e.g. x[~mask] for every series)")
        value = np.ma.getdata(value)
    if isinstance(value, (str, bytes)):
        raise error(f"{name} must be an array of real numbers, got {_short(value)}")
    a = np.asarray(value)
    if a.dtype.kind == "c":
        raise error(f"{name} must be real, got a complex array (take .real or abs() deliberately)")
    if a.dtype.kind not in "iuf":
        raise error(f"{name} must be an array of real numbers, got {a.dtype.name} values "
                    f"({_short(a.ravel()[:3].tolist()) if a.size else '[]'})")
    if ndim is not None and a.ndim != ndim:
        raise error(f"{name} must be a {ndim}-D array, got shape {a.shape}")
    if max_size is not None and a.size > max_size:
        raise error(f"{name} has {a.size} samples; at most {max_size} are accepted (decimate it first, "
                    f"e.g. x[::k])")
    a = a.astype(float)
    if finite and not np.all(np.isfinite(a)):
        raise error(f"{name} must hold finite numbers only (it has NaN or inf)")
    return a


def text_file(path, what: str, error=ArgumentError, *, form: str = "", max_bytes: int = 1 << 20) -> str:
    """The UTF-8 text of the regular file ``path`` of at most ``max_bytes``, else ``error``
    naming the file (and the line of a byte that is not UTF-8). A directory, a FIFO or a
    device is never read (a FIFO swapped in after the check cannot block the open either).

    Parameters
    ----------
    path : the file
    what : what the file is, for the messages ("design file", "spec", "parameter file")
    error : the error class raised
    form : its format, for the messages ("JSON", "TOML"), or ""
    max_bytes : the largest file read
    """
    path = Path(path)
    regular = f"a {what} is a regular {form + ' ' if form else ''}file"
    try:
        st = path.stat()
    except FileNotFoundError:
        raise error(f"{path}: no such {what}") from None
    except OSError as exc:
        raise error(f"{path}: cannot read {what} ({exc.strerror})") from None
    if not stat.S_ISREG(st.st_mode):
        what_it_is = "a directory, not a regular file" if stat.S_ISDIR(st.st_mode) else "not a regular file"
        raise error(f"{path}: {what_it_is}; {regular}")
    if st.st_size > max_bytes:
        raise error(f"{path}: {st.st_size} bytes; a {what} is at most {max_bytes}")
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
        with os.fdopen(fd, "rb") as fh:
            if not stat.S_ISREG(os.fstat(fh.fileno()).st_mode):
                raise error(f"{path}: not a regular file; {regular}")
            raw = fh.read(max_bytes + 1)
    except OSError as exc:
        raise error(f"{path}: cannot read {what} ({exc.strerror})") from None
    if len(raw) > max_bytes:
        raise error(f"{path}: more than {max_bytes} bytes; a {what} is at most {max_bytes}")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        raise error(f"{path}:{line}: not UTF-8 text (byte 0x{raw[exc.start]:02x})") from None
