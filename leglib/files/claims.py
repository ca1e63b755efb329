"""One writer per point: claims on a directory's grid points (and on a batch being written).

A claim is a lock on one byte of the directory's lock file ``.claims.lock``, at an offset
given by the point's exact gains (or a batch's ``lg`` part): a POSIX record lock
(``fcntl.lockf``), or ``msvcrt.locking`` on Windows. The operating system drops it when the
process ends, so a crashed writer never blocks a point; two sweeps into one directory share
the grid without losing or duplicating a point. A sweep's claims cost no file each:
creating a file is what costs here (30 us to 1.5 ms, on a shared disk), and 400 of them
would be a large part of a thesis-grid sweep.

Record locks belong to the process, so this module keeps a table of the bytes this process
holds: a second claim of a held point is refused (two claims of one process exclude each
other, as two processes' do), and each lock file stays open once while any of its claims
is held (closing any descriptor of a file drops all of a process's record locks on it:
open ``.claims.lock`` nowhere else in a process that holds claims). The byte is the one an
earlier leglib locked with Linux's open-file-description locks, which exclude record locks
and are excluded by them: a sweep of that version and one of this share a directory too.
"""

from __future__ import annotations

import hashlib
import os
import threading
import time
from pathlib import Path

from .names import exact_gains_key

CLAIMS_FILE = ".claims.lock"
WAIT_POLL_S = 0.05   # how often a waiting claim tries again

if os.name == "nt":
    import msvcrt  # load time: the platform's lock module, chosen as the module loads (Windows)

    def _lock(fd: int, offset: int) -> bool:
        """Lock the byte at ``offset`` of the open file ``fd``; False if another holds it."""
        os.lseek(fd, offset, os.SEEK_SET)
        try:
            msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
        except OSError:
            return False
        return True

    def _unlock(fd: int, offset: int) -> None:
        os.lseek(fd, offset, os.SEEK_SET)
        msvcrt.locking(fd, msvcrt.LK_UNLCK, 1)
else:
    import fcntl  # load time: the platform's lock module, chosen as the module loads (POSIX)

    def _lock(fd: int, offset: int) -> bool:
        """Lock the byte at ``offset`` of the open file ``fd``; False if another process holds it."""
        try:
            fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB, 1, offset, os.SEEK_SET)
        except OSError as exc:   # EAGAIN or EACCES: held
            if isinstance(exc, (BlockingIOError, PermissionError)):
                return False
            raise
        return True

    def _unlock(fd: int, offset: int) -> None:
        fcntl.lockf(fd, fcntl.LOCK_UN, 1, offset, os.SEEK_SET)


class _LockFile:
    """A directory's lock file, open once in this process while any of its claims is held,
    and the offsets held."""

    def __init__(self, ident, fd: int):
        self.ident, self.fds, self.held = ident, [fd], set()

    @property
    def fd(self) -> int:
        return self.fds[0]


_OPEN: dict = {}                 # (st_dev, st_ino) of a lock file -> its _LockFile
_TABLE = threading.RLock()       # guards _OPEN and every _LockFile.held (a finalizer may release within)


def _reset_after_fork() -> None:   # a child does not inherit a lock another thread held
    global _TABLE
    _TABLE = threading.RLock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_reset_after_fork)


def _lock_file(directory: str | Path) -> _LockFile:
    """The directory's lock file, opened (and created) unless this process has it open
    already (its descriptor must never be closed while a claim is held); under _TABLE."""
    path = os.path.join(directory, CLAIMS_FILE)
    try:
        st = os.stat(path)
        if (st.st_dev, st.st_ino) in _OPEN:
            return _OPEN[st.st_dev, st.st_ino]
    except FileNotFoundError:
        pass
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    st = os.fstat(fd)
    ident = (st.st_dev, st.st_ino)
    if ident in _OPEN:   # the name changed under us to a file we hold: keep the descriptor open
        _OPEN[ident].fds.append(fd)
        return _OPEN[ident]
    _OPEN[ident] = lf = _LockFile(ident, fd)
    return lf


def _close_if_unused(lf: _LockFile) -> None:
    """Close a lock file none of this process's claims uses any more; under _TABLE."""
    if not lf.held and _OPEN.get(lf.ident) is lf:
        del _OPEN[lf.ident]
        for fd in lf.fds:
            os.close(fd)


def _offset(key) -> int:
    """The byte of a key: from its SHA-1, below 2^56 (a sparse file never grows)."""
    digest = hashlib.sha1((key if isinstance(key, str) else exact_gains_key(key)).encode()).digest()
    return int.from_bytes(digest[:7], "big")


def _take(lf: _LockFile, offset: int) -> bool:
    """Lock ``offset`` unless this process or another holds it; under _TABLE."""
    if offset in lf.held or not _lock(lf.fd, offset):
        return False
    lf.held.add(offset)
    return True


class Claim:
    """An exclusive claim on one grid point of a directory: held while the point is
    measured and written, released by :meth:`release` or when the process ends (the
    operating system drops the lock), so a crashed writer never blocks the point."""

    def __init__(self, lock_file: _LockFile | None, offset: int | None = None):
        self._file, self._offset = lock_file, offset

    def release(self) -> None:
        with _TABLE:
            lf, self._file = self._file, None
            if lf is None:
                return
            try:
                _unlock(lf.fd, self._offset)
            finally:
                lf.held.discard(self._offset)
                _close_if_unused(lf)

    def __del__(self):   # a claim nobody holds any more is released
        try:
            self.release()
        except Exception:  # noqa: BLE001 - never raise from a finalizer (e.g. at exit)
            pass


class _Claims(Claim):
    """Claims of many points held together (released together)."""

    def __init__(self, claims: list):
        super().__init__(None)
        self._claims = claims

    def release(self) -> None:
        while self._claims:
            self._claims.pop().release()


def claim(directory: str | Path, gains, wait: bool = False) -> Claim | None:
    """Claim the point ``gains`` in ``directory`` (or, given a string, that name: a batch
    being written); None if another claim holds it, in this process or another
    (``wait=True`` tries again every :data:`WAIT_POLL_S` until it is released)."""
    offset = _offset(gains)
    while True:
        with _TABLE:
            lf = _lock_file(directory)
            if _take(lf, offset):
                return Claim(lf, offset)
            _close_if_unused(lf)
        if not wait:
            return None
        time.sleep(WAIT_POLL_S)


def claim_many(directory: str | Path, keys, limit: int | None = None) -> tuple[Claim, list]:
    """:func:`claim` of each of ``keys`` (gains), up to ``limit`` taken: (one Claim that
    releases them all, a list of True where a key was taken). A key twice is taken once
    (its second claim is refused by its first)."""
    keys = list(keys)
    limit = len(keys) if limit is None else limit
    offsets = [_offset(k) for k in keys]
    held, taken = [], []
    try:
        with _TABLE:
            lf = _lock_file(directory)
            try:
                for off in offsets:
                    ok = len(held) < limit and _take(lf, off)
                    if ok:
                        held.append(Claim(lf, off))
                    taken.append(ok)
            finally:
                _close_if_unused(lf)
    except BaseException:
        _Claims(held).release()
        raise
    return _Claims(held), taken
