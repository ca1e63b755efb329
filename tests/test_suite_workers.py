"""One process per core, each kept to its own (leglib.notebook.run.core_of): the suite's
pytest-xdist workers with every process they start (tests/conftest.py) but a JupyterLab
and a browser, and ``make run``'s notebooks with their kernels; and the suite's spare worker,
which takes only its own tests (tests/xdist_spare.py)."""

import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

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


# -- the spare worker (tests/conftest.py, tests/xdist_spare.py) --------------------------------

class _Node:
    """A pytest-xdist worker as the scheduler sees it: what it was sent, whether it stopped."""
    def __init__(self, wid):
        self.gateway = type("Gateway", (), {"id": wid})()
        self.shutting_down = False
        self.sent = []

    def send_runtest_some(self, indexes):
        self.sent.extend(indexes)

    def shutdown(self):
        self.shutting_down = True


def _scheduler(collection, spare_ok):
    from xdist_spare import SpareScheduling

    config = SimpleNamespace(getvalue={"tx": ["3*popen"]}.get, option=SimpleNamespace(loadscopereorder=True))
    sched = SpareScheduling(config, spare="gw2", takes=spare_ok)
    nodes = [_Node(f"gw{k}") for k in range(3)]
    for node in nodes:
        sched.add_node(node)
        sched.add_node_collection(node, collection)
    sched.schedule()
    return sched, nodes


def _run_to_the_end(sched, nodes, order):
    """Each worker in ``order`` (repeated) finishes one of its tests while it can: as
    pytest-xdist's workers, it holds back its last test until it gets more or is told to
    stop. Returns {worker: the tests it ran}."""
    def can_run(node):
        return len(node.sent) > 1 or (node.sent and node.shutting_down)

    ran = {n.gateway.id: [] for n in nodes}
    while any(can_run(nodes[k]) for k in order):
        for k in order:
            node = nodes[k]
            if can_run(node):
                index = node.sent.pop(0)
                ran[node.gateway.id].append(sched.collection[index])
                sched.mark_test_complete(node, index)
    return ran


def test_the_spare_worker_takes_only_its_tests_in_order_and_the_others_take_theirs_first():
    collection = [f"tests/s.py::t{k}" for k in range(5)] + [f"tests/a.py::t{k}" for k in range(12)] \
        + ["tests/a.py::u0@lab", "tests/a.py::u1@lab"]
    sched, nodes = _scheduler(collection, lambda nodeid: nodeid.startswith("tests/s.py"))
    ran = _run_to_the_end(sched, nodes, order=[0, 1, 2])
    assert sorted(sum(ran.values(), [])) == sorted(collection)      # each test once
    assert ran["gw2"] and all(t.startswith("tests/s.py") for t in ran["gw2"])
    assert ran["gw2"] == sorted(ran["gw2"], key=collection.index)  # in the collection's order
    kept = ran["gw0"] + ran["gw1"]
    assert {"tests/a.py::u0@lab", "tests/a.py::u1@lab"} <= set(ran["gw0"]) or \
        {"tests/a.py::u0@lab", "tests/a.py::u1@lab"} <= set(ran["gw1"])   # a group stays on one worker
    assert all(t.startswith("tests/a.py") for t in kept[:4])       # the kept workers' own tests first
    assert all(n.shutting_down for n in nodes)


def test_a_spare_worker_that_is_never_free_leaves_its_tests_to_the_others():
    collection = [f"tests/a.py::t{k}" for k in range(4)] + [f"tests/s.py::t{k}" for k in range(6)]
    sched, nodes = _scheduler(collection, lambda nodeid: nodeid.startswith("tests/s.py"))
    first = [sched.collection[i] for i in nodes[2].sent]           # what the spare one holds
    ran = _run_to_the_end(sched, nodes, order=[0, 1])               # it never runs (its core is never free):
    assert first == collection[4:4 + len(first)]                    # it held the first of its own,
    assert set(ran["gw0"] + ran["gw1"]) == set(collection) - set(first)   # the others ran all the rest
    assert all(t.startswith("tests/s.py") for t in ran["gw0"][-1:] + ran["gw1"][-1:])


def test_nothing_for_the_spare_worker_stops_it():
    collection = [f"tests/a.py::t{k}" for k in range(4)]
    sched, nodes = _scheduler(collection, lambda nodeid: False)
    assert nodes[2].shutting_down and not nodes[2].sent
    ran = _run_to_the_end(sched, nodes, order=[0, 1])
    assert sorted(ran["gw0"] + ran["gw1"]) == sorted(collection)


def test_the_spare_workers_tests_exist_and_the_timed_ones_are_left_out():
    """Every file of SPARE_TESTS exists, and every test NOT_SPARE_TESTS leaves out is a test
    of one of them (a renamed test would otherwise go to the spare worker unnoticed)."""
    import ast

    root = Path(conftest.__file__).resolve().parent.parent
    for prefix in conftest.SPARE_TESTS:
        assert (root / prefix).exists(), prefix
    for nodeid in conftest.NOT_SPARE_TESTS:
        path, name = nodeid.split("::")
        tests = {f.name for f in ast.parse((root / path).read_text()).body if isinstance(f, ast.FunctionDef)}
        assert name.split("[")[0] in tests, nodeid
        assert not conftest.for_the_spare(nodeid) and conftest.for_the_spare(f"{path}::another")
