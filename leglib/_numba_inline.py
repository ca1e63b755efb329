"""numba's inliner, made linear in the size of what it inlines; the machine code unchanged.

The twin's tick (:mod:`leglib.twin.kernel`) and the step fit (:mod:`leglib.identify.fastfit`)
are built from small functions marked ``inline="always"``: numba pastes their IR into the
caller (with none of them marked, the thesis grid on the twin took 630 ms instead of 170).
The pasting was half of the device kernel's compile, and most of that was numba's copy of
the callee's IR (``InlineWorker.inline_ir``, its ``copy_ir``): it deep-copies each block on
its own, and every block's variables refer to the function's one scope, which holds every
variable of the function; so each block copies all of them again (blocks x variables: 4.7
million ``Var`` copies for the device kernel).
numba's own issue: https://github.com/numba/numba/issues/8989 (open).

:func:`install` wraps ``inline_ir`` so that the blocks of one copy share one ``deepcopy``
memo: the scope and its variables are copied once per copy, and the copy's blocks share
one scope, as the original's do (numba's copy gives each block its own, equal, scope, and
uses the first). Everything else in ``inline_ir`` is numba's. Measured on the three compile
groups of :mod:`leglib.notebook.warmup` (one process, empty cache, CPU time): device
51.5 -> 35.9 s, batch 54.7 -> 45.7 s, fits 34.3 -> 34.4 s. The LLVM IR and the machine
code of all 52 compiled kernels are identical with and without it, once the names that
differ between any two processes are set aside (byte constants named by Python's
randomized ``hash``, a parfor's address); tests/test_numba_inline.py checks the same on a
small kernel.

It is installed on import, before any kernel compiles (every leglib module that imports
numba imports this one first; tests/test_numba_inline.py checks that), and only where
``inline_ir`` still copies as described: a numba whose inliner changed keeps its own.
It also serves any other function compiled in the same process (the semantics are
numba's: only the copying is shared).
"""

from __future__ import annotations

import copy as _copy
import functools
import inspect
import types

from numba.core import inline_closurecall as _ic
from numba.core import ir as _ir

# the line of numba's copy_ir this changes (numba 0.68.1, environment.txt): one deepcopy per block
_PER_BLOCK_COPY = "copy.deepcopy(the_ir.blocks[block_label])"


def _stock_copies_per_block() -> bool:
    try:
        return _PER_BLOCK_COPY in inspect.getsource(_ic.InlineWorker.inline_ir)
    except (OSError, TypeError):   # no source to read: leave numba as it is
        return False


def _linear(inline_ir):
    @functools.wraps(inline_ir)
    def wrapper(self, *args, **kwargs):
        memos = {}   # per scope of the IR being copied: one copy's blocks share a memo

        def deepcopy(x, memo=None):
            if memo is None and isinstance(x, _ir.Block):
                memo = memos.setdefault(id(x.scope), {})
            return _copy.deepcopy(x, memo)

        module_copy = _ic.copy
        _ic.copy = types.SimpleNamespace(deepcopy=deepcopy, copy=_copy.copy)
        try:
            return inline_ir(self, *args, **kwargs)
        finally:
            _ic.copy = module_copy
    wrapper.__leglib_linear__ = True
    return wrapper


def installed() -> bool:
    """Whether numba's inliner copies linearly in this process."""
    return getattr(_ic.InlineWorker.inline_ir, "__leglib_linear__", False)


def install() -> bool:
    """Wrap numba's ``InlineWorker.inline_ir`` (once); False where numba's copy differs from
    the one this was measured on, which is then left alone."""
    if not installed() and _stock_copies_per_block():
        _ic.InlineWorker.inline_ir = _linear(_ic.InlineWorker.inline_ir)
    return installed()


install()
