"""Compiled formatting and parsing of measurement CSVs: one pass over the whole buffer.

:mod:`leglib.files` writes numbers as Python's ``f"{x:.6f}"`` and reads the strict row
grammar of its ``_ROW_RE``; the Python versions cost a few milliseconds per 750-row file,
mostly per-row interpreter work. These functions do the same in one compiled loop each,
with the same results bit for bit, and give up (return -1) wherever they cannot be sure
of that; dataio then takes its careful Python path, which also words every error. So
these functions never decide that a file is bad and never produce a message.

Formatting (:func:`format_fixed6`)
    ``x`` is written as the nearest multiple of 1e-6 to ``x`` (as ``.6f`` does). The
    product ``y = |x| * 1e6`` is off the exact value by at most ``y 2^-53``, so when its
    fractional part is further than ``y 2^-52`` from one half, rounding ``y`` gives the
    same integer as rounding the exact value; otherwise (ties, near-ties, ``|x| >= 2^50 /
    1e6``, non-finite) the caller formats in Python. The sign is written for every
    negative value, -0.0 and values that round to zero included, as Python does.

Parsing (:func:`parse3`)
    Lines are split at ``\\n``; a line of ASCII whitespace only is skipped (``str.strip``);
    any other line must be ``[ \\t]*NUM[ \\t]*,[ \\t]*NUM[ \\t]*,[ \\t]*NUM[ \\t]*\\r?`` with
    ``NUM = [+-]?([0-9]+(\\.[0-9]*)?|\\.[0-9]+)([eE][+-]?[0-9]+)?``, at most ``max_line``
    bytes. A number is converted exactly when its digits (at most 18) form an integer
    ``m <= 2^53`` and its decimal exponent ``e`` lies in [-22, 22]: ``m`` and ``10^|e|``
    are then exact doubles and one IEEE multiplication or division rounds correctly, as
    ``float()`` does (Clinger's fast path). Anything else -- a non-ASCII byte, another
    grammar, more digits, a value beyond the angle limit, time not increasing, no row --
    gives -1.
"""

from __future__ import annotations

import math
import threading

import numpy as np
from numba import get_num_threads, njit, prange

# 10^0 .. 10^22, each exactly a double (parsed from decimal, so exact)
_POW10 = np.array([float(f"1e{k}") for k in range(23)])
FIXED6_MAX_CHARS = 20  # sign, at most 10 integer digits (|x| < 2^50 / 1e6), point, 6 digits, separator


@njit(cache=True)
def _format_fixed6(data, out, r0, r1, k):
    """Rows r0..r1 of ``data`` into ``out`` from byte ``k``; the byte after the text, or -1."""
    c = data.shape[1]
    ten = np.uint32(10)
    for i in range(r0, r1):
        for j in range(c):
            x = data[i, j]
            a = abs(x)
            y = a * 1e6
            if not y < 1125899906842624.0:  # 2^50; also NaN
                return -1
            f = math.floor(y)
            r = y - f
            if abs(r - 0.5) <= y * 2.220446049250313e-16:  # within y 2^-52 of a tie
                return -1
            q = np.uint64(f)
            if r > 0.5:
                q += np.uint64(1)
            if math.copysign(1.0, x) < 0.0:
                out[k] = 45  # '-'
                k += 1
            ip = np.uint32(q // np.uint64(1000000))  # < 2^50 / 1e6 < 2^31
            fr = np.uint32(q - np.uint64(ip) * np.uint64(1000000))
            nd = 1
            t = ip
            while t >= ten:
                t //= ten
                nd += 1
            t = ip
            for d in range(nd - 1, -1, -1):
                out[k + d] = np.uint8(48 + t % ten)
                t //= ten
            k += nd
            out[k] = 46  # '.'
            for d in range(6, 0, -1):
                out[k + d] = np.uint8(48 + fr % ten)
                fr //= ten
            k += 7
            out[k] = 10 if j == c - 1 else 44  # '\n' or ','
            k += 1
    return k


@njit(cache=True, parallel=True)
def _format_parts(data, out, rows, ends):
    """:func:`_format_fixed6` of the row ranges ``rows`` (one per thread) side by side,
    each into its own part of ``out`` (from ``rows[p]`` times the row width), its end
    into ``ends``. (No array expression here: in a parallel function numba would share
    it out among the threads, and the parts are closed up by copies that overlap.)"""
    width = data.shape[1] * FIXED6_MAX_CHARS
    for p in prange(rows.size - 1):
        ends[p] = _format_fixed6(data, out, rows[p], rows[p + 1], rows[p] * width)


PARALLEL_BYTES = 1 << 20   # below about this much text one thread formats or parses it


_SCRATCH = threading.local()   # per thread: byte buffers kept from call to call, by use
SCRATCH_MAX_BYTES = 64 << 20   # larger buffers are not kept


def scratch(use: str, nbytes: int) -> np.ndarray:
    """This thread's uint8 buffer for ``use`` ("text", "read"), at least ``nbytes`` long,
    kept for the next call (up to SCRATCH_MAX_BYTES): what it holds is valid only until
    then. Fresh memory is what large text costs most where the system hands out pages
    slowly (in a VM about 6 us per 4 KiB page: 14 ms for a sweep's 9 MB)."""
    bufs = _SCRATCH.__dict__
    buf = bufs.get(use)
    if buf is None or buf.size < nbytes:
        buf = np.empty(nbytes, np.uint8)
        if nbytes <= SCRATCH_MAX_BYTES:
            bufs[use] = buf
    return buf


def format_fixed6_array(data: np.ndarray, reuse: bool = False) -> np.ndarray | None:
    """:func:`format_fixed6` as a uint8 array (no copy into bytes; hashlib and os.write
    take it as it is); large tables are formatted on the cores present.

    ``reuse=True`` writes into this thread's :func:`scratch` buffer for text: the array
    is then valid only until the next such call (for text that is hashed and written at
    once)."""
    data = np.ascontiguousarray(data, dtype=np.float64)
    if data.ndim != 2:
        return None
    size = data.size * FIXED6_MAX_CHARS
    out = scratch("text", size) if reuse else np.empty(size, np.uint8)
    n = data.shape[0]
    parts = min(get_num_threads(), max(1, data.size * 10 // PARALLEL_BYTES))
    if parts == 1:
        k = _format_fixed6(data, out, 0, n, 0)
    else:
        rows = np.linspace(0, n, parts + 1).astype(np.int64)
        ends = np.empty(parts, np.int64)
        _format_parts(data, out, rows, ends)
        if np.any(ends < 0):
            return None
        k = 0
        for p in range(parts):   # close up (numpy copies overlaps right; text of less than half
            # the widest rows leaves no overlap, so no temporary copy)
            start = rows[p] * data.shape[1] * FIXED6_MAX_CHARS
            out[k:k + ends[p] - start] = out[start:ends[p]]
            k += ends[p] - start
    return None if k < 0 else out[:k]


def format_fixed6(data: np.ndarray) -> bytes | None:
    """Rows of ``data`` (2-D float) as ``"{:.6f},{:.6f},...\\n"`` ASCII bytes, exactly as
    Python formats them; None when a value needs Python's formatting (see module notes)."""
    out = format_fixed6_array(data)
    return None if out is None else out.tobytes()


@njit(cache=True)
def _number(b, i, end):
    """Parse NUM at b[i:end]: (value, index after it, ok); ok False when the grammar does
    not match there or the value is not exactly convertible in the fast path (more than
    18 digits, leading zeros included)."""
    neg = False
    if i < end and (b[i] == 43 or b[i] == 45):  # '+' '-'
        neg = b[i] == 45
        i += 1
    m = np.int64(0)  # the digits as one integer (wraps past 18 digits: then not ok)
    nint = 0
    while i < end:
        c = np.int64(b[i]) - 48
        if c < 0 or c > 9:
            break
        m = m * 10 + c
        nint += 1
        i += 1
    nfrac = 0
    if i < end and b[i] == 46:  # '.'
        i += 1
        while i < end:
            c = np.int64(b[i]) - 48
            if c < 0 or c > 9:
                break
            m = m * 10 + c
            nfrac += 1
            i += 1
    if nint + nfrac == 0 or nint + nfrac > 18:
        return 0.0, i, False
    e = 0
    if i < end and (b[i] == 101 or b[i] == 69):  # 'e' 'E'
        i += 1
        eneg = False
        if i < end and (b[i] == 43 or b[i] == 45):
            eneg = b[i] == 45
            i += 1
        nexp = 0
        while i < end and 48 <= b[i] <= 57:
            if e < 100000:
                e = e * 10 + (b[i] - 48)
            nexp += 1
            i += 1
        if nexp == 0:
            return 0.0, i, False
        if eneg:
            e = -e
    if m == 0:
        v = 0.0
    else:
        if m > 9007199254740992:  # 2^53
            return 0.0, i, False
        e10 = e - nfrac
        if e10 > 22 or e10 < -22:
            return 0.0, i, False
        if e10 >= 0:
            v = float(m) * _POW10[e10]
        else:
            v = float(m) / _POW10[-e10]
    return (-v if neg else v), i, True


@njit(cache=True)
def _parse3(b, lo, n, max_line, angle_limit, increasing, out, r0):
    """The lines of b[lo:n] (whole lines) into rows of ``out`` from ``r0``; their number,
    or -1."""
    pos = lo
    rows = r0
    prev = -math.inf
    while pos < n:
        # leading whitespace: a line of whitespace only is skipped (str.strip); before a
        # number only spaces and tabs may stand
        i = pos
        other_space = False
        while i < n and (b[i] == 32 or 9 <= b[i] <= 13 or 28 <= b[i] <= 31) and b[i] != 10:
            if b[i] != 32 and b[i] != 9:
                other_space = True
            i += 1
        if i == n or b[i] == 10:
            pos = i + 1
            continue
        if other_space:
            return -1
        for col in range(3):
            v, i, ok = _number(b, i, n)
            if not ok:
                return -1
            out[rows, col] = v
            while i < n and (b[i] == 32 or b[i] == 9):
                i += 1
            if col < 2:
                if i >= n or b[i] != 44:  # ','
                    return -1
                i += 1
                while i < n and (b[i] == 32 or b[i] == 9):
                    i += 1
        if i < n and b[i] == 13:  # '\r'
            i += 1
        if i < n and b[i] != 10:
            return -1
        if i - pos > max_line:
            return -1
        if abs(out[rows, 1]) > angle_limit or abs(out[rows, 2]) > angle_limit:
            return -1
        if increasing:
            if not out[rows, 0] > prev:
                return -1
            prev = out[rows, 0]
        rows += 1
        pos = i + 1
    return rows - r0


@njit(cache=True)
def _parse_parts(b, bounds, max_line, angle_limit, increasing):
    return _parse_parts_impl(b, bounds, max_line, angle_limit, increasing)


@njit(cache=True, parallel=True)
def _parse_parts_parallel(b, bounds, max_line, angle_limit, increasing):
    return _parse_parts_impl(b, bounds, max_line, angle_limit, increasing)


@njit(cache=True, inline="always")
def _parse_parts_impl(b, bounds, max_line, angle_limit, increasing):
    """:func:`_parse3` of the parts b[bounds[p]:bounds[p + 1]] (whole lines each), side by
    side (a prange: on the cores present when compiled parallel): (rows, the first row
    of each part, the rows each gave or -1). (No array expression here: in a parallel
    function numba would share it out among the threads.)"""
    parts = bounds.size - 1
    lines = np.empty(parts, np.int64)   # at most this many rows per part
    for p in prange(parts):
        m = 1 if p == parts - 1 else 0   # every part but the last ends with its newline
        for i in range(bounds[p], bounds[p + 1]):
            m += b[i] == 10
        lines[p] = m
    first = np.zeros(parts + 1, np.int64)
    for p in range(parts):
        first[p + 1] = first[p] + lines[p]
    out = np.empty((first[parts], 3))
    got = np.empty(parts, np.int64)
    for p in prange(parts):
        got[p] = _parse3(b, bounds[p], bounds[p + 1], max_line, angle_limit, increasing, out, first[p])
    return out, first, got


def _find_newline(b: np.ndarray, start: int) -> int:
    """The index of the first newline of ``b`` from ``start``, or -1."""
    while start < b.size:
        hits = np.flatnonzero(b[start:start + 4096] == 10)
        if hits.size:
            return start + int(hits[0])
        start += 4096
    return -1


def parse3(raw, max_line: int, angle_limit: float = math.inf, increasing: bool = False) -> np.ndarray | None:
    """The rows of a three-column CSV buffer as an (n, 3) array, bit for bit as
    ``float()`` reads them; None when the careful parser must decide (see module notes).

    ``angle_limit`` bounds |column 2| and |column 3|; ``increasing`` requires column 1 to
    increase strictly."""
    b = np.frombuffer(raw, dtype=np.uint8)
    parts = min(get_num_threads(), max(1, b.size // PARALLEL_BYTES))
    bounds = [0]
    for p in range(1, parts):   # each part whole lines: it starts after a newline
        cut = _find_newline(b, max(bounds[-1], b.size * p // parts))
        if cut < 0:
            break
        bounds.append(cut + 1)
    bounds.append(b.size)
    bounds = np.array(bounds, np.int64)
    parse = _parse_parts if bounds.size == 2 else _parse_parts_parallel
    out, first, got = parse(b, bounds, max_line, float(angle_limit), increasing)
    if np.any(got < 0):
        return None
    k = 0
    for p in range(got.size):   # close up the gaps of blank lines (numpy copies overlaps right)
        if got[p]:
            if increasing and k and not out[first[p], 0] > out[k - 1, 0]:   # across the seam
                return None
            if k != first[p]:
                out[k:k + got[p]] = out[first[p]:first[p] + got[p]]
            k += got[p]
    return None if k == 0 else out[:k]
