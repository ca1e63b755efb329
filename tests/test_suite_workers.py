"""One process per core, each kept to its own (leglib.notebook.run.core_of): the suite's
pytest-xdist workers with every process they start (tests/conftest.py) but a JupyterLab
and a browser, and ``make run``'s notebooks with their kernels."""

import os
import subprocess
import sys

import conftest
import pytest

from leglib.notebook.run import core_of


def test_one_process_per_core_gives_each_its_own_core():
    assert [core_of(k, 2, [0, 1]) for k in range(2)] == [0, 1]
    assert [core_of(k, 3, [2, 5, 7]) for k in range(3)] == [2, 5, 7]


def test_more_or_fewer_processes_than_cores_are_left_to_the_system():
    assert core_of(0, 3, [0, 1]) is None
    assert core_of(0, 1, [0, 1]) is None
    assert core_of(0, 2, []) is None            # a system that cannot keep a process to a core


def _cores_of_a_child() -> str:
    """The cores a process started now may run on, as its ``sorted(...)`` prints them."""
    return subprocess.run([sys.executable, "-c", "import os; print(sorted(os.sched_getaffinity(0)))"],
                          capture_output=True, text=True, check=True).stdout.strip()


def test_this_worker_and_the_processes_it_starts_keep_to_its_core():
    if conftest.WORKER_CORE is None:
        pytest.skip("not one pytest-xdist worker per core: the workers are left to the system")
    assert os.sched_getaffinity(0) == {conftest.WORKER_CORE}
    child = _cores_of_a_child()
    assert child == str([conftest.WORKER_CORE])


def test_a_process_started_on_any_core_keeps_to_none():
    if conftest.WORKER_CORE is None:
        pytest.skip("not one pytest-xdist worker per core: the workers are left to the system")
    with conftest.on_any_core():
        child = _cores_of_a_child()
    assert child == str(sorted(conftest._CORES_BEFORE)) and len(conftest._CORES_BEFORE) > 1
    assert os.sched_getaffinity(0) == {conftest.WORKER_CORE}     # this worker keeps to its core again
