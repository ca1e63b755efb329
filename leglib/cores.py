"""A batch's compiled work over the cores: a kernel called on parts of the batch from a
pool of threads, a part at a time to whichever thread is free.

The kernels are numba functions compiled with ``nogil=True``, called on parts of their
arrays (slices, or a range of rows passed as two numbers): each part is the same call the
serial path makes, so the numbers do not depend on how many threads ran or in which order.

numba's own ``parallel=True`` loops (``prange``) did the same in earlier versions. They
were dropped for this pool for what they cost. A ``prange`` is lowered into a function of
its own (a gufunc) for every kernel that has one (numba's pipeline times with an empty
cache: the twin's two paths 4.0 and 4.8 s of CPU, the step fit 6.2 s, its refit 2.8 s):
over the five kernels about 18 of a first compile's 90 CPU seconds. Calling the serial
kernel from threads compiles nothing more. numba's threads were also as many as the
machine has cores even in a process kept to one core (a notebook of ``make run``), and its
threading layer here was GNU OpenMP, which is not fork-safe and whose threads spin on
after each call: in a process kept to no core, 200 calls of a small ``prange`` kernel 16
ms apart took 3.4 s and 5.0 s of CPU, the serial kernel 3.3 s and 3.3 s. This pool takes a
thread per core the process may run on; its idle threads sleep.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import wait as _wait

_pool: ThreadPoolExecutor | None = None
_pool_lock = threading.Lock()


def cores() -> int:
    """How many cores this process may run on (its affinity; all of the machine's where the
    system does not say)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def _executor() -> ThreadPoolExecutor:
    global _pool
    with _pool_lock:
        if _pool is None:
            # as many threads as the machine has cores at most; a call uses only as many as
            # the process may run on at the time (cores())
            _pool = ThreadPoolExecutor(max_workers=max(1, os.cpu_count() or 1), thread_name_prefix="leglib-cores")
        return _pool


def _forget_pool() -> None:
    """In a forked child the parent's threads do not exist: a new pool on first use."""
    global _pool, _pool_lock
    _pool, _pool_lock = None, threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


@contextlib.contextmanager
def _ctrl_c_after():
    """A Ctrl-C (SIGINT) that arrives inside the block is handled when the block has ended,
    by the handler that was in place (the default one raises KeyboardInterrupt there). Only
    the main thread runs Python's signal handlers, so elsewhere nothing is held back; nor
    where the handler in place was not installed from Python (it cannot be put back)."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) is None:
        yield
        return
    held = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: held.append(frame))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if held and callable(previous):
            previous(signal.SIGINT, held[0])
        elif held and previous == signal.SIG_DFL:
            signal.raise_signal(signal.SIGINT)


def over_cores(call, n: int, chunk: int = 1, serial_below: int = 2) -> None:
    """``call(i0, i1)`` for every part ``[i0, i1)`` of ``range(n)`` (``chunk`` long, the
    last one shorter), on a thread per core, each thread taking the next part when it is
    done with one (a core busy with something else takes fewer). Returns when every part
    has run.

    Every part runs exactly once, whatever happens meanwhile: a Ctrl-C (KeyboardInterrupt)
    in the calling thread is raised after the last part ended, as it is after one compiled
    call, so a batch is never left advanced in some rows and not in others. An exception
    in a part is raised after the others ended (the first one, in the order of the parts'
    threads). A batch of one part, or of fewer than ``serial_below`` items (where the
    pool's hand-offs cost more than they give), is one ``call(0, n)`` in the calling thread."""
    if not isinstance(chunk, int) or chunk < 1:
        raise ValueError(f"chunk must be a positive integer, got {chunk!r}")
    if n <= 0:
        return
    parts = [(i, min(n, i + chunk)) for i in range(0, n, chunk)]
    if len(parts) == 1 or n < serial_below:
        call(0, n)
        return
    taken = iter(parts)
    take = threading.Lock()

    def work():
        while True:
            with take:
                part = next(taken, None)
            if part is None:
                return
            call(*part)

    # a Ctrl-C while the parts are handed out or run is raised once every part has run
    # (caught around the wait alone, one that came while the threads were handed their
    # work left the parts running behind the KeyboardInterrupt)
    with _ctrl_c_after():
        futures = [_executor().submit(work) for _ in range(min(cores(), len(parts)))]
        _wait(futures)
    for f in futures:
        f.result()


__all__ = ["cores", "over_cores"]
