"""One writer per point: claims on a directory's grid points (and on a batch being written).

A claim is held while a point is measured and written and released when the process ends
(the operating system drops the lock), so a crashed writer never blocks the point; two
sweeps into one directory share the grid without losing or duplicating a point.
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import os
import struct
import sys
from pathlib import Path

from .names import exact_gains_key


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
