"""leglib._numba_gc: the garbage collector paused while a leglib function compiles, and as
it was before once the compile ends (also when it fails); other functions' compiles left as
they are. (That every module with kernels imports it: tests/test_numba_inline.py.)"""

import gc

import numba
import pytest
from numba.core import event
from numba.core.errors import TypingError

import leglib._numba_gc  # noqa: F401  (the listener, registered on import)


def _function(module: str, body: str = "return x + 1"):
    """A new function ``f(x)`` defined in a module named ``module`` (numba reads its name
    from the function's globals), not yet compiled."""
    ns = {"__name__": module}
    exec(f"def f(x):\n    {body}\n", ns)
    return numba.njit(ns["f"])


class _Seen(event.Listener):
    """Whether the collector ran enabled in each compiler pass (numba's "numba:run_pass")."""

    def __init__(self):
        self.enabled = []

    def on_start(self, ev):
        self.enabled.append(gc.isenabled())

    def on_end(self, ev):
        pass


def _compile(f, arg):
    seen = _Seen()
    with event.install_listener("numba:run_pass", seen):
        f(arg)
    return seen.enabled


@pytest.fixture
def collector_on():
    was = gc.isenabled()
    gc.enable()
    yield
    (gc.enable if was else gc.disable)()


def test_paused_while_a_leglib_function_compiles_and_enabled_after(collector_on):
    f = _function("leglib._gc_probe")
    enabled = _compile(f, 1.0)
    assert enabled and not any(enabled)    # every pass ran with the collector paused
    assert gc.isenabled()
    assert f(2.0) == 3.0


def test_a_leglib_function_calling_another_keeps_it_paused_through_the_nested_compile(collector_on):
    inner = _function("leglib._gc_probe_inner", "return x * 2")
    ns = {"__name__": "leglib._gc_probe_outer", "inner": inner}
    exec("def f(x):\n    return inner(x) + 1\n", ns)
    outer = numba.njit(ns["f"])
    enabled = _compile(outer, 1.0)
    assert inner.signatures                # compiled inside outer's compile
    assert enabled and not any(enabled) and gc.isenabled()


def test_enabled_again_after_a_compile_that_fails(collector_on):
    f = _function("leglib._gc_probe_bad", "return x.no_such_attribute")
    with pytest.raises(TypingError):
        f(1.0)
    assert gc.isenabled()
    assert not any(_compile(_function("leglib._gc_probe_after"), 1.0)) and gc.isenabled()   # still counted right


def test_other_functions_compile_with_the_collector_as_it_is(collector_on):
    assert all(_compile(_function("someone_elses_module"), 1.0))
    assert all(_compile(_function("leglibrary"), 1.0))      # a name that only starts like leglib's


def test_a_collector_paused_before_stays_paused(collector_on):
    gc.disable()
    _compile(_function("leglib._gc_probe_off"), 1.0)
    assert not gc.isenabled()
