"""Every motion is guarded: a link lost at any transaction of an operation that arms the
motors, or an interrupt followed by a second one during the cleanup, leaves both axes IDLE
within the watchdog time (the watchdog counts down in every state, axis.cpp:165-182 of
fw-v0.5.6; an expired one disarms the motor, axis.cpp:343-350)."""

import _thread
import warnings

import numpy as np
import pytest

import leglib as lg
from leglib.device.session import HOLD_WATCHDOG, clear_errors
from leglib.device.virtual import firmware as V
from leglib.experiments.step import return_to_rest
from leglib.twin import layout as L


def _ready(seed=31):
    d = lg.connect("virtual", seed=seed)
    lg.configure(d)
    lg.calibrate(d)
    return d


class _Faults:
    """Counts the model's transactions from now on and, at the chosen ones, cuts the link or
    interrupts the main thread as a Ctrl-C would (``_thread.interrupt_main``: the
    KeyboardInterrupt arrives in the main thread wherever it is, as from the terminal)."""

    def __init__(self, sim, interrupts=(), disconnect=None):
        self.sim, self.count = sim, 0
        self.interrupts, self.disconnect = set(interrupts), disconnect
        self.real = sim._transaction
        sim._transaction = self

    def __call__(self):
        n = self.count
        self.count += 1
        if self.disconnect is not None and n >= self.disconnect:
            self.sim.lost = True
        if n in self.interrupts:
            _thread.interrupt_main()
        self.real()

    def remove(self):
        del self.sim._transaction


def _armed(sim):
    return [int(m) for m in sim.st.AI[0, :, L.I_MODE]]


def _recover(dev):
    """What the README says to do after a lost link: reconnect, inspect, clear."""
    dev.sim.lost = False
    clear_errors(dev)


def _idle_within(sim, seconds):
    """Both motors disarmed once ``seconds`` of device time have passed (no host involved).
    A closed-loop request still pending when the link went is taken up at the axis thread's
    next iteration (up to 1 ms later, axis.cpp:447-488) and feeds the watchdog there
    (axis.cpp:577): the bound counts from then."""
    sim._advance(seconds + V.AXIS_THREAD_PERIOD)
    return _armed(sim) == [L.MODE_IDLE, L.MODE_IDLE]


def _count(dev, operation):
    n0 = dev.sim.transactions
    operation(dev)
    return dev.sim.transactions - n0


def test_return_to_rest_is_held_under_the_watchdog():
    """return_to_rest holds the leg in closed loop: it runs with the watchdog enabled and
    fed (a plain sleep with the watchdog off left the leg armed after a lost link)."""
    dev = _ready()
    seen = []
    real_sleep = dev.sleep

    def watch(seconds):
        seen.append((_armed(dev.sim), [bool(dev.sim.st.C[0, a, L.C_WD_ENABLE]) for a in (0, 1)]))
        real_sleep(seconds)
    dev.sleep = watch
    return_to_rest(dev, move_time=1.0, settle=0.2)
    armed = [wd for modes, wd in seen if L.MODE_POSITION in modes]
    assert armed and all(all(wd) for wd in armed)
    assert _armed(dev.sim) == [L.MODE_IDLE, L.MODE_IDLE]


@pytest.mark.parametrize("operation", ["return_to_rest"])
def test_a_link_lost_at_any_transaction_leaves_both_axes_idle(operation):
    run = {"return_to_rest": lambda d: return_to_rest(d, move_time=0.6, settle=0.1)}[operation]
    dev = _ready()
    n = _count(dev, run)
    assert n > 20
    for k in range(n):
        faults = _Faults(dev.sim, disconnect=k)
        with pytest.raises(V.DeviceLostError), warnings.catch_warnings():
            warnings.filterwarnings("ignore", "could not set IDLE")   # the link is gone: it cannot
            run(dev)
        faults.remove()
        assert _idle_within(dev.sim, HOLD_WATCHDOG + 2 * dev.sim.twin.dt), f"armed after a link lost at {k}/{n}"
        _recover(dev)


@pytest.mark.parametrize("operation", ["return_to_rest"])
def test_a_second_interrupt_during_the_cleanup_leaves_both_axes_idle(operation):
    run = {"return_to_rest": lambda d: return_to_rest(d, move_time=0.6, settle=0.1)}[operation]
    dev = _ready()
    n = _count(dev, run)
    rng = np.random.default_rng(5)
    first = sorted(set(rng.integers(0, n, 12).tolist()) | {0, n // 2, n - 1})
    for k in first:
        for gap in (1, 2, 5):
            faults = _Faults(dev.sim, interrupts={k, k + gap})
            with pytest.raises(KeyboardInterrupt):
                run(dev)
            # the second interrupt may still be on its way: let it land here
            try:
                dev.sim._advance(0.0)
                dev.get(0, "current_state")
            except KeyboardInterrupt:
                pass
            faults.remove()
            assert _idle_within(dev.sim, HOLD_WATCHDOG + 2 * dev.sim.twin.dt), \
                f"armed after interrupts at {k} and {k + gap} of {n}"
            _recover(dev)
