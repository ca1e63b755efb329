import contextlib
import fcntl
import os
import shutil
import tempfile
import threading
import time
from pathlib import Path

from leglib.device.virtual import wire as F

os.environ.setdefault("MPLBACKEND", "Agg")

import pytest  # noqa: E402

from leglib.params import load_leg  # noqa: E402

# -- the numba kernels compiled once, before the workers use them ---------------------------

WARM_ENV = "LEGLIB_TEST_WARM_KERNELS"      # the file the controller writes when they are done
WARM_TIMEOUT_S = 900


WORKER_CORE = None   # the core this pytest-xdist worker keeps to, when it keeps to one
_CORES_BEFORE = None  # the cores it could run on before
SPARE = False         # this worker is the spare one (below)

# -- a spare worker for the time the kept workers wait ---------------------------------------
#
# With ``-n auto`` the suite starts one worker per core, each kept to its core, and one spare
# worker kept to none at the lowest priority (nice 19): the system gives it a core only while
# that core's worker waits (a real-time step, a notebook kernel starting, a browser) or has
# finished. It takes only the tests below: numerics, the measurement files, the twin and its
# firmware on their own clock; none of them times the wall clock or waits on a process with a
# time limit (a notebook kernel, a browser, a child Python). The kept workers take
# the other tests, and these too once the others are all handed out (tests/xdist_spare.py).
# Measured on fresh clones, three interleaved pairs without and with it: the cores idle 94, 96
# and 94 against 51, 39 and 34 core-seconds; the suite 349, 329 and 363 s against 329, 323 and
# 330 s, at 575, 538 and 601 against 560, 581 and 598 CPU seconds (the spare worker ran 57 to
# 84 CPU seconds of tests, the kept ones 56 to 104 fewer). The first pair ran an earlier version:
# without the two firmware files, the widgets and the animation on the list, and with a stop
# rule that left the spare's last test waiting until the session ended. With the reality-gap and
# the firmware conformance tests on its list too (in-process, the twin on its own clock), three
# more interleaved pairs: the spare ran out of tests 45 to 51 s before the kept workers ended
# without them and 3 to 4 s with them; the cores idle 33, 41 and 45 against 24, 22 and 24
# core-seconds, the suite 321, 290 and 283 s against 284, 295 and 278 s.
SPARE_TESTS = (
    "tests/identify/", "tests/design/", "tests/model/test_model.py", "tests/files/test_csvtext.py",
    "tests/twin/test_twin.py", "tests/device/test_firmware.py", "tests/device/test_firmware_control.py",
    "tests/evaluation/test_robustness.py", "tests/notebook/test_widgets.py", "tests/notebook/test_animation.py",
    "tests/test_fuzz.py", "tests/test_params.py", "tests/test_units.py", "tests/test_thesis.py",
    "tests/test_plots.py", "tests/evaluation/test_reality_gap.py", "tests/device/test_conformance.py",
)
NOT_SPARE_TESTS = (   # within those: tests that time the wall clock
    "tests/twin/test_twin.py::test_virtual_clock_is_fast_and_realtime_mode_paces",
    "tests/twin/test_twin.py::test_a_realtime_sleep_takes_its_seconds_after_a_busy_host",
    "tests/device/test_firmware.py::test_real_time_never_runs_ahead_of_the_wall_clock",
)


def for_the_spare(nodeid: str) -> bool:
    """Whether the spare worker may run the test ``nodeid``."""
    return nodeid.startswith(SPARE_TESTS) and not nodeid.startswith(NOT_SPARE_TESTS)


@pytest.hookimpl(optionalhook=True)   # pytest-xdist's hooks: -p no:xdist loads none
def pytest_xdist_auto_num_workers(config):
    """``-n auto`` with ``--dist loadgroup`` (``make test``): a worker per core and the spare
    one, where the system can keep a process to a core; otherwise pytest-xdist's own count."""
    from leglib.notebook.run import usable_cores

    cores = usable_cores()
    if len(cores) >= 2 and config.getvalue("dist") == "loadgroup":
        return len(cores) + 1
    return None


def _spare_worker(config) -> str | None:
    """The spare worker's id on the controller (``gw2`` on 2 cores), None without one: with
    ``--dist loadgroup``, one worker more than the cores it may keep to."""
    from leglib.notebook.run import usable_cores

    cores = usable_cores()
    if config.getvalue("dist") == "loadgroup" and len(cores) >= 2 and config.option.numprocesses == len(cores) + 1:
        return f"gw{len(cores)}"
    return None


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node):
    node.workerinput["spare_worker"] = _spare_worker(node.config)   # each worker knows which one it is


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadgroup`` with the spare worker: :class:`xdist_spare.SpareScheduling`."""
    spare = _spare_worker(config)
    if spare is None:
        return None
    from xdist_spare import SpareScheduling
    return SpareScheduling(config, log, spare=spare, takes=for_the_spare)


def _keep_worker_to_its_core(config) -> None:
    """With one worker per core (``-n auto``), each worker and every process it starts
    (notebook kernels, a wheel's environment) keep to a core of their own, as ``make run``'s
    notebooks do (:func:`leglib.notebook.run.core_of`: the ``odrive`` client's thread
    wake-up for every property access of the twin costs about twice the CPU across cores).
    The suite makes about 800,000 such accesses; on a fresh clone (benchmarks.suite) it used
    604 CPU seconds with its workers kept to their cores, against 661 to 716 in three runs
    without. A worker past one per core is the spare one (:data:`SPARE_TESTS`): kept to no
    core, at nice 19 from its first test on (:func:`pytest_collection_finish`: collecting at
    that priority would hold up every worker's start).

    Measured and not kept: one worker more, kept to no core, to run where a kept worker's
    test waits. It cut the cores' idle time on a fresh clone (17 against about 90
    core-seconds) but not the wall time: 351 to 374 s in three runs, against 325 to 405 s
    in four runs without, at 20 to 90 CPU seconds more on a machine whose speed varied by a
    third from run to run (benchmarks.suite.probe). Nor when that worker ran only the tests
    that mostly wait (real-time scripts, timeouts, child processes; a scheduler of its own):
    idle 35 and 46 core-seconds against 93 and 89, but 355 against 382 s and 355 against
    351 s in two interleaved pairs of fresh-clone runs, at 5 and 49 CPU seconds more; and in
    each of those runs a timing test failed there (a 500 Hz loop's pace, the reason a
    watchdog trip gave), its real-time loop competing with both kept workers. Both ran at
    the kept workers' priority and took tests that drive the client or time the clock; the
    spare worker takes neither, and yields its core at once (nice 19)."""
    global WORKER_CORE, _CORES_BEFORE, SPARE
    from leglib.notebook.run import core_of, usable_cores

    index, count = int(config.workerinput["workerid"].removeprefix("gw")), int(config.workerinput["workercount"])
    if config.workerinput.get("spare_worker"):
        if config.workerinput["workerid"] == config.workerinput["spare_worker"]:
            SPARE = True
            return
        count -= 1
    cores = usable_cores()
    WORKER_CORE = core_of(index, count, cores)
    if WORKER_CORE is not None:
        _CORES_BEFORE = os.sched_getaffinity(0)
        os.sched_setaffinity(0, {WORKER_CORE})   # this thread, and every thread and process it starts


def pytest_collection_finish(session):
    if SPARE:
        os.setpriority(os.PRIO_PROCESS, 0, 19)   # this thread, and every thread and process it starts


@contextlib.contextmanager
def on_any_core():
    """Processes started inside keep to no core even when this worker keeps to one: a
    JupyterLab with its kernels, a browser. Kept to the worker's core, a page redrawing a
    live view competed on one core with the kernel's real-time step it shows (its sample
    period ran 6 % long on a slow machine)."""
    if _CORES_BEFORE is None:
        yield
        return
    os.sched_setaffinity(0, _CORES_BEFORE)
    try:
        yield
    finally:
        os.sched_setaffinity(0, {WORKER_CORE})


def pytest_configure(config):
    """Under pytest-xdist, the controller compiles the kernels (leglib.notebook.warmup, one
    process per group) while the workers start and collect, unless they are current (``make
    venv`` compiled them and no kernel source changed since); each worker waits for them
    before its first test (:func:`pytest_runtest_setup`). Without this, on a fresh clone every worker
    and every notebook kernel compiles the same kernels at the same time (a minute each):
    numba writes its cache only when a compile ends. Each worker keeps to a core of its own
    (:func:`_keep_worker_to_its_core`)."""
    if hasattr(config, "workerinput"):
        _keep_worker_to_its_core(config)
        return
    if not getattr(config.option, "numprocesses", None) or config.option.collectonly:
        return
    import io

    from leglib.notebook import warmup

    done = Path(tempfile.mkdtemp(prefix="leglib-warm-")) / "done"
    os.environ[WARM_ENV] = str(done)   # the workers inherit it

    def wait():
        lines = io.StringIO()
        try:
            warmup.ensure(stream=lines)
        except RuntimeError as exc:   # reported here; the tests that use the kernel fail on their own
            lines.write(f"[compile] FAILED: {exc}\n")
        done.with_suffix(".tmp").write_text(lines.getvalue())
        os.replace(done.with_suffix(".tmp"), done)   # whole, or not there
    threading.Thread(target=wait, daemon=True).start()


def pytest_terminal_summary(terminalreporter, config):
    done = os.environ.get(WARM_ENV)
    if not hasattr(config, "workerinput") and done and os.path.exists(done):
        for line in Path(done).read_text().splitlines():
            terminalreporter.write_line(line)


def pytest_unconfigure(config):
    done = os.environ.pop(WARM_ENV, None) if not hasattr(config, "workerinput") else None
    if done:
        shutil.rmtree(Path(done).parent, ignore_errors=True)


_warm = False   # this worker has seen the controller's compiles done


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item):
    """Before a worker's test sets up its fixtures, it waits until the controller's compiles
    are done (once: later tests find them done; a failed compile is reported by the tests
    that use the kernel, not here). The wheel test does not wait: it compiles in an
    environment and a numba cache of its own, on the cores the compile groups leave idle as
    they end. A test whose xdist_group was lost fails here, before its fixtures (below)."""
    global _warm
    if LOST_GROUP in item.stash:
        pytest.fail(item.stash[LOST_GROUP], pytrace=False)
    done = os.environ.get(WARM_ENV)
    if _warm or not done or not os.environ.get("PYTEST_XDIST_WORKER") or item.get_closest_marker("wheel"):
        return
    deadline = time.monotonic() + WARM_TIMEOUT_S
    while not os.path.exists(done) and time.monotonic() < deadline:
        time.sleep(0.2)
    _warm = True


# -- the order of the tests: the long ones first -----------------------------------------------

LOST_GROUP = pytest.StashKey[str]()     # why the test lost its xdist_group (see below)
LONG_MARKERS = ("wheel", "browser", "notebook", "slow")   # longest first


@pytest.hookimpl(wrapper=True)
def pytest_collection_modifyitems(config, items):
    """Notebook, browser and wheel tests are slow too (``-m "not slow"`` leaves them all out);
    and the slow tests go first: pytest-xdist hands the tests out in this order, so the
    long ones start early and the short ones fill the workers' ends instead of one long test
    running on alone at the end (the browser tests stay on one worker: xdist_group "lab").

    After the other plugins (a wrapper), with ``--dist loadgroup`` a worker's tests marked
    ``xdist_group`` must carry their group in their node id: pytest-xdist writes it there and
    its scheduler reads it back. Where that write is lost (pytest 9.2 with pytest-xdist 3.8,
    pytest-dev/pytest-xdist#1386) a group's tests spread over the workers, each starting its
    own JupyterLab or sympy derivation: those tests fail, saying why, rather than run slower
    in silence (an error raised here would reach pytest-xdist's controller only as a crashed
    worker, without its message)."""
    def rank(item):
        marks = {m.name for m in item.iter_markers()}
        return next((k for k, name in enumerate(LONG_MARKERS) if name in marks), len(LONG_MARKERS))

    for item in items:
        if rank(item) < len(LONG_MARKERS):
            item.add_marker(pytest.mark.slow)
    items.sort(key=rank)   # stable: the collection's order within each rank
    result = yield
    if hasattr(config, "workerinput") and config.getvalue("loadgroup"):
        lost = [item for item in items
                if item.get_closest_marker("xdist_group") and "@" not in item.nodeid.rpartition("]")[2]]
        for item in lost:
            item.stash[LOST_GROUP] = (
                f"--dist loadgroup lost this test's xdist_group {item.get_closest_marker('xdist_group').args}: "
                f"pytest {pytest.__version__} with this pytest-xdist does not group tests "
                "(pytest-dev/pytest-xdist#1386); install environment.txt's pins (make venv)")
    return result


@pytest.fixture(scope="session")
def leg():
    return load_leg("thesis")


def shared_dir(tmp_path_factory, name: str, make) -> Path:
    """A directory made once per test session by ``make(path)`` and shared by every
    pytest-xdist worker: the first worker to ask makes it while the others wait on a file
    lock; later ones find it made (a fixture of scope "session" or "module" is otherwise
    made again in each worker that runs a test using it). A ``make`` that raises leaves
    nothing behind: the next worker to ask tries again and reports its own error."""
    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent   # the session's directory, above the workers' own
    path = base / f"shared-{name}"
    with open(base / f"shared-{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (path / ".made").exists():
            shutil.rmtree(path, ignore_errors=True)
            path.mkdir()
            make(path)
            (path / ".made").touch()
    return path


@pytest.fixture(scope="session")
def shared(tmp_path_factory):
    """``shared(name, make)``: :func:`shared_dir` of this session."""
    return lambda name, make: shared_dir(tmp_path_factory, name, make)


def _run_notebook_02(out: Path) -> None:
    from leglib.notebook.run import execute, notebook_paths

    execute(notebook_paths()[1], out, {"smoke": True, "raw_dir": str(out / "raw"),
                                       "processed_dir": str(out / "processed")}, html=False)


@pytest.fixture(scope="session")
def processed(shared):
    """Notebook 02 run once (smoke): its output directory and metrics. Its identified leg
    (``processed/friction_identified.json``) is what notebook 03 reads. One run for the
    whole session (:func:`shared_dir`): the notebook tests and the browser test read it."""
    import json

    from leglib.notebook.run import notebook_paths

    out = shared("nb02", _run_notebook_02)
    return out, json.loads((out / "metrics" / f"{notebook_paths()[1].stem}.json").read_text())


@pytest.fixture(autouse=True)
def _fresh_virtual_devices():
    """Each test starts without virtual ODrives: they live for the process under their
    seed (leglib.virtual_odrive.find_any), so tests would otherwise share devices."""
    F.forget()
    yield
