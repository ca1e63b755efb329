"""The names of measurement files: what a name says (time stamp, exact gains, leglib's own
``lg`` part, a batch) and how it is made.

A measurement is ``<stem>_positions.csv`` with a sidecar ``<stem>_positions.json``: thesis
files ``YYYYmmdd_HHMMSS_<posP>;<velP>;<velI>_positions.csv`` (three-decimal gains, no
sidecar), leglib's earlier files (the same with a sidecar) and leglib's files
``YYYYmmdd_HHMMSS_<posP>;<velP>;<velI>_lg<12 hex>_positions.csv`` (the exact gains, shortest
round-trip decimal, and a random part that makes every name unique); a twin's batch is
``YYYYmmdd_HHMMSS_lg<12 hex>_batch.csv``.
"""

from __future__ import annotations

import datetime as _dt
import math
import re
import secrets
from pathlib import Path

from ..errors import MeasurementError

EXCERPT = 60                      # characters of a bad line or value quoted in a message
_NUM = r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?"
NUMBER_RE = re.compile(rf"^{_NUM}$", re.ASCII)
NAME_RE = re.compile(r"^(?P<stamp>[0-9]{8}_[0-9]{6})(?:_(?P<gains>(?!lg)[^_]+))?"
                     r"(?:_(?P<uid>lg[0-9a-f]{12}))?_positions\.csv$", re.ASCII)
_UID_RE = re.compile(r"_lg[0-9a-f]{12}_positions\.json$", re.ASCII)
BATCH_RE = re.compile(r"^(?P<stamp>[0-9]{8}_[0-9]{6})_(?P<uid>lg[0-9a-f]{12})_batch\.csv$", re.ASCII)
_BATCH_SIDE_RE = re.compile(r"^[0-9]{8}_[0-9]{6}_lg[0-9a-f]{12}_batch\.json$", re.ASCII)


def _excerpt(text: str) -> str:
    return repr(text) if len(text) <= EXCERPT else repr(text[:EXCERPT]) + f" ... ({len(text)} characters)"


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


def batch_filename(when: _dt.datetime | None = None, uid: str | None = None) -> str:
    """A batch file's name: ``<stamp>_lg<uid>_batch.csv``."""
    when = when or _dt.datetime.now()
    return f"{when.strftime('%Y%m%d_%H%M%S')}_lg{uid or secrets.token_hex(6)}_batch.csv"


def is_batch_name(path: str | Path) -> bool:
    """True for a batch file's name (several measurements in one file, see the module notes)."""
    return bool(BATCH_RE.match(Path(path).name))
