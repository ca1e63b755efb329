"""PNG bytes of a canvas's pixels, for the panels and the live view that redraw on every
change.

Pillow's PNG writer (``compress_level=1``) took 16-18 ms for a 1500 x 380 panel figure,
most of it in its per-row filter search; writing the rows unfiltered and deflating them
with ``zlib`` at level 1 takes about 6 ms for the same pixels and a file of about the same
size (text and lines on white compress as well without a filter). The file is a plain
PNG (IHDR, one IDAT, IEND; 8 bits per channel) that any reader decodes to the same pixels.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

from ..errors import ArgumentError

_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def encode(rgba, level: int = 1) -> bytes:
    """PNG of an ``(h, w, 4)`` uint8 RGBA array (e.g. ``canvas.buffer_rgba()``): RGB when
    every pixel is opaque, RGBA otherwise. ``level``: zlib's compression level 0-9."""
    px = np.asarray(rgba)
    if px.dtype != np.uint8 or px.ndim != 3 or px.shape[2] != 4 or 0 in px.shape[:2]:
        raise ArgumentError(f"png.encode: rgba must be a non-empty (h, w, 4) uint8 array, "
                            f"got {px.dtype} of shape {px.shape}")
    if not 0 <= level <= 9:
        raise ArgumentError(f"png.encode: level = {level!r} must lie in 0 ... 9 (zlib)")
    opaque = bool(px[:, :, 3].min() == 255)
    if opaque:
        px = px[:, :, :3]
    h, w, channels = px.shape
    rows = np.empty((h, 1 + w * channels), np.uint8)
    rows[:, 0] = 0   # filter type 0 (none) on every row
    rows[:, 1:] = px.reshape(h, w * channels)
    header = struct.pack(">IIBBBBB", w, h, 8, 2 if opaque else 6, 0, 0, 0)
    return (_SIGNATURE + _chunk(b"IHDR", header) + _chunk(b"IDAT", zlib.compress(rows.tobytes(), level))
            + _chunk(b"IEND", b""))
