"""The suite's workers: with one pytest-xdist worker per core, each keeps to a core of its own
(tests/conftest.py, ``_keep_worker_to_its_core``), and so does every process it starts."""

import os
import subprocess
import sys

import conftest
import pytest
from conftest import worker_core


def test_one_worker_per_core_gives_each_its_own_core():
    cores = [0, 1]
    assert [worker_core(f"gw{k}", 2, cores) for k in range(2)] == [0, 1]
    assert [worker_core(f"gw{k}", 3, [2, 5, 7]) for k in range(3)] == [2, 5, 7]


def test_more_or_fewer_workers_than_cores_are_left_to_the_system():
    assert worker_core("gw0", 3, [0, 1]) is None
    assert worker_core("gw0", 1, [0, 1]) is None


def test_this_worker_and_the_processes_it_starts_keep_to_its_core():
    if conftest.WORKER_CORE is None:
        pytest.skip("not one pytest-xdist worker per core: the workers are left to the system")
    assert os.sched_getaffinity(0) == {conftest.WORKER_CORE}
    child = subprocess.run([sys.executable, "-c", "import os; print(sorted(os.sched_getaffinity(0)))"],
                           capture_output=True, text=True, check=True).stdout.strip()
    assert child == str([conftest.WORKER_CORE])
