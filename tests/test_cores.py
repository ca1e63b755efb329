"""A batch's compiled work over the cores (leglib.cores): every part once, at once, whatever
happens meanwhile; and the kernels that use it give the numbers of one thread.

The test workers keep to one core each (tests/conftest.py), where the pool takes one
thread: the tests that are about several threads ask for them (``cores`` replaced)."""

import multiprocessing
import os
import signal
import threading
import time

import numpy as np
import pytest

from leglib import cores as K


def test_every_part_runs_once_and_the_parts_cover_the_batch():
    for n, chunk in [(0, 1), (1, 1), (7, 1), (7, 3), (64, 4), (5, 9)]:
        seen = []
        lock = threading.Lock()

        def call(i0, i1):
            with lock:
                seen.append((i0, i1))
        K.over_cores(call, n, chunk)
        covered = sorted(i for i0, i1 in seen for i in range(i0, i1))
        assert covered == list(range(n)), (n, chunk, seen)
        assert all(0 < i1 - i0 <= chunk for i0, i1 in seen)


def test_parts_run_at_once_on_two_threads(monkeypatch):
    """Two parts that each wait for the other: they end only if two threads run them."""
    monkeypatch.setattr(K, "cores", lambda: 2)
    both = threading.Barrier(2, timeout=10)
    names = set()

    def call(i0, i1):
        names.add(threading.current_thread().name)
        both.wait()
    K.over_cores(call, 2)
    assert len(names) == 2 and all(n.startswith("leglib-cores") for n in names)


def _kept_to_one_core(queue):
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    names = set()

    def call(i0, i1):
        names.add(threading.current_thread().name)
        time.sleep(0.01)   # long enough that a second thread, if there were one, would take a part
    K.over_cores(call, 8)
    queue.put((K.cores(), len(names)))


def test_a_process_kept_to_one_core_runs_its_parts_on_one_thread():
    """As many threads as cores the process may run on (its affinity, not the machine's
    cores): a notebook kept to a core by ``make run`` runs its batches on one thread."""
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_kept_to_one_core, args=(queue,))
    child.start()
    child.join(timeout=30)
    assert child.exitcode == 0 and queue.get(timeout=5) == (1, 1)


def test_an_exception_in_a_part_is_raised_after_the_other_parts_ran(monkeypatch):
    monkeypatch.setattr(K, "cores", lambda: 2)
    done = []

    def call(i0, i1):
        if i0 == 3:
            raise ValueError("part 3")
        time.sleep(0.01)
        done.append(i0)
    with pytest.raises(ValueError, match="part 3"):
        K.over_cores(call, 8)
    assert sorted(done) == [0, 1, 2, 4, 5, 6, 7]


@pytest.mark.parametrize("when", ["while the parts run", "while the threads are handed their parts"])
def test_a_ctrl_c_is_raised_after_every_part_ran(monkeypatch, when):
    """A Ctrl-C while the parts run, or while the threads are handed them, leaves no row of
    the batch behind: it is raised when the last part ended, as after one compiled call."""
    monkeypatch.setattr(K, "cores", lambda: 2)

    def ctrl_c():
        signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)
    if when == "while the threads are handed their parts":
        pool, handed = K._executor(), []

        class Pool:
            def submit(self, fn):
                handed.append(fn)
                if len(handed) == 2:       # the first thread already runs parts
                    ctrl_c()
                    time.sleep(0.01)       # the main thread runs the handler here
                return pool.submit(fn)
        monkeypatch.setattr(K, "_executor", Pool)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    done = []

    def call(i0, i1):
        if i0 == 1 and when == "while the parts run":
            ctrl_c()
        time.sleep(0.02)
        done.append(i0)
    try:
        with pytest.raises(KeyboardInterrupt):
            K.over_cores(call, 10)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert sorted(done) == list(range(10))


def test_after_the_parts_a_ctrl_c_is_the_handlers_in_place_at_once(monkeypatch):
    """over_cores puts back the SIGINT handler that was in place before it."""
    monkeypatch.setattr(K, "cores", lambda: 2)
    seen = []

    def handler(signum, frame):
        seen.append(signum)
    previous = signal.signal(signal.SIGINT, handler)
    try:
        K.over_cores(lambda i0, i1: time.sleep(0.001), 4)
        assert signal.getsignal(signal.SIGINT) is handler and not seen
        signal.raise_signal(signal.SIGINT)
        assert seen == [signal.SIGINT]
    finally:
        signal.signal(signal.SIGINT, previous)


def test_a_small_batch_is_one_call_in_the_calling_thread(monkeypatch):
    """Below ``serial_below`` items (a fit of fewer than PARALLEL_FROM responses, fewer than
    PARALLEL_POINTS foot positions) the pool's hand-offs cost more than they give."""
    monkeypatch.setattr(K, "cores", lambda: 2)
    seen = []
    K.over_cores(lambda i0, i1: seen.append((i0, i1, threading.current_thread().name)), 10, 2, serial_below=16)
    assert seen == [(0, 10, threading.current_thread().name)]
    K.over_cores(lambda i0, i1: seen.append((i0, i1)), 0, 2)
    assert len(seen) == 1                       # an empty batch: no call


def test_a_bad_chunk_is_named():
    with pytest.raises(ValueError, match="chunk must be a positive integer, got 0"):
        K.over_cores(lambda i0, i1: None, 4, 0)


def _in_a_forked_child(queue):
    out = []
    K.over_cores(lambda i0, i1: out.append(i0), 6)
    queue.put(sorted(out))


def test_a_forked_child_gets_a_pool_of_its_own(monkeypatch):
    """The parent's pool threads do not exist in a child forked from it (``make run``'s
    notebooks, a Dask worker): the child's first batch must not wait on them forever."""
    monkeypatch.setattr(K, "cores", lambda: 2)
    K.over_cores(lambda i0, i1: time.sleep(0.01), 4)   # the parent's pool exists
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_in_a_forked_child, args=(queue,))
    child.start()
    child.join(timeout=30)
    if child.is_alive():
        child.kill()
        pytest.fail("a forked child's batch hung on its parent's pool")
    assert child.exitcode == 0 and queue.get(timeout=5) == [0, 1, 2, 3, 4, 5]


def test_a_twin_batch_on_two_threads_gives_the_numbers_of_one(monkeypatch):
    """The blocks of a batch of legs on two threads at once, against one thread: the same
    numbers, bit for bit (every block changes only its own legs' rows)."""
    from leglib.twin.host import Twin
    from leglib.twin.layout import C_VBUS_CHECKS

    twin = Twin(seed=3)
    gains = np.column_stack([np.linspace(8, 60, 40), np.linspace(0.03, 0.2, 40), np.linspace(0, 0.5, 40)])

    def run(n):
        monkeypatch.setattr(K, "cores", lambda: n)
        start = twin._initial_state(40)
        start.C[::3, 0, C_VBUS_CHECKS] = 1.0    # every third leg through the reference path
        return twin.step_batch(gains, duration=0.2, start=start)
    one, two = run(1), run(2)
    assert one.keys() == two.keys()
    for key in one:
        if isinstance(one[key], np.ndarray):
            np.testing.assert_array_equal(one[key], two[key], err_msg=key)


def test_fits_on_two_threads_give_the_numbers_of_one(monkeypatch):
    from leglib.identify import fastfit as F

    t = np.arange(500) * 0.002
    ys = [F.model(t, 0.1 + 0.02 * k, 25.0 + k, 0.05, 0.0, 0.01) + 1e-4 * np.sin(7 * k * t) for k in range(F.PARALLEL_FROM + 5)]
    monkeypatch.setattr(K, "cores", lambda: 1)
    one = F.fit_packed([t] * len(ys), ys), F.refit_from([t] * len(ys), ys, [[0.3, 30.0, 0.05, 0.0, 0.01]] * len(ys))
    monkeypatch.setattr(K, "cores", lambda: 2)
    two = F.fit_packed([t] * len(ys), ys), F.refit_from([t] * len(ys), ys, [[0.3, 30.0, 0.05, 0.0, 0.01]] * len(ys))
    np.testing.assert_array_equal(one[0][0], two[0][0])
    np.testing.assert_array_equal(one[0][1], two[0][1])
    np.testing.assert_array_equal(one[1], two[1])
    assert np.isfinite(one[1]).all(axis=1).sum() > len(ys) // 2   # the refits mostly succeed: compared on numbers
