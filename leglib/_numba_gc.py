"""numba's compiles of leglib's kernels run with Python's cyclic garbage collector paused.

numba builds a kernel's IR, its types and its LLVM module out of many small objects that
refer to each other. The collector runs after every 700 new objects it tracks and walks
them again each time: 15 % of the device kernel's compile in a sampling profile (empty
cache, one core).
A :class:`numba.core.event.Listener` on numba's ``"numba:compile"`` event pauses the
collector when the compile of a leglib function starts and enables it again when that
compile ends (and every compile nested in it: the functions it calls), when it was enabled
before. The objects a compile left behind are collected at the collector's next run.
numba compiles under its global compiler lock, one compile at a time per process, so one
counter of nested compiles serves every thread.

Measured on the groups of :mod:`leglib.notebook.warmup` (one core, empty cache, CPU
seconds, two runs each): device 17.2 -> 14.6, batch 21.2 -> 17.9, fits 15.0 -> 12.6; their
peak memory 310-320 MB -> 410-460 MB. ``python -m leglib compile`` on 2 cores, six
interleaved pairs: median 58.5 -> 53.7 CPU-s, 32.8 -> 30.1 s. A first result in a new
process with an empty cache (connect, configure, calibrate, a step, its fit), three pairs:
28.2 -> 25.4 CPU-s. A collector threshold of 20,000 instead of a pause saved half as much
(one core: 15.7-15.9, 19.3, 13.0). Loading a kernel from numba's cache is not a compile
and runs as before.

It is registered on import (every leglib module that imports numba imports this one first;
tests/test_numba_inline.py checks that). Compiles of functions outside leglib are left as
they are, unless a leglib kernel's compile reaches them.
"""

from __future__ import annotations

import gc

from numba.core import event as _event


def _ours(dispatcher) -> bool:
    """Whether ``dispatcher`` (a numba dispatcher whose compile starts) compiles a leglib function."""
    module = getattr(getattr(dispatcher, "py_func", None), "__module__", None) or ""
    return module == "leglib" or module.startswith("leglib.")


class _PausedCollector(_event.Listener):
    """Pauses the collector from the start of a leglib compile to its end (see module docstring)."""

    def __init__(self):
        self.depth = 0          # compiles running, the outermost a leglib one; 0: none
        self.was_enabled = False

    def on_start(self, ev):
        if self.depth == 0:
            if not _ours(ev.data.get("dispatcher") if isinstance(ev.data, dict) else None):
                return
            self.was_enabled = gc.isenabled()
            gc.disable()
        self.depth += 1

    def on_end(self, ev):
        if self.depth == 0:
            return
        self.depth -= 1
        if self.depth == 0 and self.was_enabled:
            gc.enable()


_LISTENER = _PausedCollector()
_event.register("numba:compile", _LISTENER)   # once: a module is imported once per process
