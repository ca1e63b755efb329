"""A sweep's directory: interrupted writes repaired on resume, near-equal gains both
measured, two writers sharing a directory, provenance refused when the leg differs."""

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import leglib as lg
from leglib.experiments import sweep as sweep_module
from leglib.files import atomic
from leglib.files.measurements import (
    BATCH_FORMAT,
    FORMAT,
    batch_filename,
    claim,
    is_batch_name,
    read_file,
)
from leglib.files.sweepdir import ProvenanceError, find_uncommitted, list_measurements
from leglib.params import load_plant

GRID = [(20.0, 0.0021, 0.02), (20.0, 0.0024, 0.02), (30.0, 0.05, 0.02)]
SHORT = {"duration": 0.3, "progress": False}


@pytest.fixture(scope="module")
def dev():
    d = lg.connect("virtual", seed=11)
    lg.configure(d)
    lg.calibrate(d)
    return d


def _complete_and_correct(directory, grid):
    """Every grid point has exactly one readable file with exactly its gains."""
    found = {}
    for p in list_measurements(directory):
        for m in read_file(p):  # raises for anything damaged
            assert m.absolute and m.meta["format"] == (BATCH_FORMAT if is_batch_name(p)
                                                       else FORMAT)
            key = tuple(m.gains)
            assert key not in found, (found.get(key), m.where)
            found[key] = m.where
    assert set(found) == {tuple(g) for g in grid}
    return found


def test_near_equal_gains_are_both_measured(dev, tmp_path):
    res = lg.sweep(dev, GRID, tmp_path, **SHORT)
    assert res.measured == 3 and len(res.written) == 1 and res.skipped == 0   # one batch file
    _complete_and_correct(tmp_path, GRID)
    again = lg.sweep(dev, GRID, tmp_path, **SHORT)
    assert again.skipped == 3 and not again.written and again.measured == 0


# the writes of one file (sweep.json, then the batch): sidecar temp, sidecar name, CSV
# temp, CSV name (the commit)
STEPS = [(fn, when) for fn in ("_write_temp", "_commit") for when in ("before", "after")]


@pytest.mark.parametrize("nth", range(1, 11))
@pytest.mark.parametrize("before_or_after", ["before", "after"])
def test_interrupt_at_every_point_of_writing_then_resume(dev, tmp_path, monkeypatch, nth, before_or_after):
    """The n-th low-level write operation of the sweep (2 for sweep.json, then 4 for each of
    two batches: two points, one) is interrupted before or after it happens; resume gives
    every point complete and correct."""
    calls = {"n": 0}
    real = {name: getattr(atomic, name) for name in ("_write_temp", "_commit")}

    def wrap(name):
        def inner(*a, **kw):
            calls["n"] += 1
            if calls["n"] == nth and before_or_after == "before":
                raise KeyboardInterrupt
            out = real[name](*a, **kw)
            if calls["n"] == nth and before_or_after == "after":
                raise KeyboardInterrupt
            return out
        return inner

    for name in real:
        monkeypatch.setattr(atomic, name, wrap(name))
    with pytest.raises(KeyboardInterrupt):
        lg.sweep(dev, GRID, tmp_path, chunk=2, **SHORT)
    monkeypatch.undo()
    for p in list_measurements(tmp_path):
        read_file(p)  # what is listed is complete
    res = lg.sweep(dev, GRID, tmp_path, **SHORT)
    _complete_and_correct(tmp_path, GRID)
    assert find_uncommitted(tmp_path) == []
    assert res.skipped + res.measured == len(GRID)
    assert not list(tmp_path.glob(".*.tmp"))


def test_a_live_writers_unfinished_batch_is_left_alone_and_a_dead_ones_set_aside(dev, tmp_path):
    lg.sweep(dev, GRID, tmp_path, **SHORT)
    # a batch whose sidecar is written and whose CSV is not yet: its writer holds its name
    side = (tmp_path / batch_filename(uid="0123456789ab")).with_suffix(".json")
    side.write_text("{}")
    writer = claim(tmp_path, "lg0123456789ab")
    assert find_uncommitted(tmp_path) == [side]
    res = lg.sweep(dev, GRID, tmp_path, **SHORT)
    assert res.set_aside == [] and side.exists()
    writer.release()   # the writer is gone
    res = lg.sweep(dev, GRID, tmp_path, **SHORT)
    assert [p.name for p in res.set_aside] == [side.name] and not side.exists()
    assert (tmp_path / "incomplete" / side.name).exists()
    _complete_and_correct(tmp_path, GRID)


def test_a_batch_committed_after_it_was_listed_as_unfinished_stays(dev, tmp_path, monkeypatch):
    """A resumed sweep lists another writer's sidecar while that writer is between sidecar
    and commit; the writer commits and ends before the claim is tried: the batch stays."""
    lg.sweep(dev, GRID, tmp_path, **SHORT)
    (batch,) = [p for p in list_measurements(tmp_path) if is_batch_name(p)]
    monkeypatch.setattr(sweep_module, "find_uncommitted", lambda d: [batch.with_suffix(".json")])
    res = lg.sweep(dev, GRID, tmp_path, **SHORT)
    assert res.set_aside == [] and res.skipped == len(GRID)
    _complete_and_correct(tmp_path, GRID)


def test_old_orphan_csv_is_set_aside_and_measured_again(dev, tmp_path):
    """A CSV of the previous format whose sidecar was never written (absolute angles)."""
    orphan = tmp_path / "20210701_123005_30.000;0.050;0.020_positions.csv"
    orphan.write_text("0.000000,267.000000,273.000000\n0.002000,267.000000,273.000000\n")
    res = lg.sweep(dev, GRID, tmp_path, **SHORT)
    assert res.measured == 3 and [p.name for p in res.set_aside] == [orphan.name]
    assert (tmp_path / "incomplete" / orphan.name).exists()
    _complete_and_correct(tmp_path, GRID)


def test_thesis_files_are_the_real_leg_and_count_as_done(dev, tmp_path, monkeypatch):
    thesis = tmp_path / "20210701_123005_30.000;0.050;0.020_positions.csv"
    thesis.write_text("0.000000,0.000000,0.000000\n0.002000,-0.5,0.5\n")
    with pytest.raises(ProvenanceError, match="backend: \"usb\" there, \"virtual\" now"):
        lg.sweep(dev, GRID, tmp_path, **SHORT)  # the twin never completes a real leg's sweep
    # on the real leg (its description stood in for here) the thesis file's point is done,
    # matched on the three decimals its name holds
    monkeypatch.setattr(dev, "describe", lambda: {"backend": "usb", "firmware": "0.5.6"})
    res = lg.sweep(dev, [(30.0, 0.0501, 0.02), (20.0, 0.0021, 0.02)], tmp_path, **SHORT)
    assert res.skipped == 1 and res.measured == 1


def test_sweep_on_another_payload_is_refused(dev, tmp_path):
    lg.sweep(dev, GRID[:1], tmp_path, **SHORT)
    heavy = lg.connect("virtual", seed=11, plant=load_plant("default", payload_mass=0.5))
    with pytest.raises(ProvenanceError, match=r"payload_mass: 0\.0 there, 0\.5 now"):
        lg.sweep(heavy, GRID, tmp_path, **SHORT)
    with pytest.raises(ProvenanceError, match="experiment.duration"):
        lg.sweep(dev, GRID, tmp_path, duration=0.5, progress=False)
    assert len(list_measurements(tmp_path)) == 1


def test_legacy_directory_compared_by_its_sidecars(dev, tmp_path):
    lg.sweep(dev, GRID[:1], tmp_path, **SHORT)
    (tmp_path / "sweep.json").unlink()  # a directory written before sweep.json existed
    other = lg.connect("virtual", seed=12)
    with pytest.raises(ProvenanceError, match="twin_seed: 11 there, 12 now"):
        lg.sweep(other, GRID, tmp_path, **SHORT)


WORKER = textwrap.dedent("""
    import json, sys
    import numpy as np
    import leglib as lg
    d = lg.connect("virtual", seed=11)
    lg.configure(d)
    lg.calibrate(d)
    grid = [(p, v, 0.02) for p in (20.0, 30.0) for v in np.linspace(0.01, 0.05, 6)]
    r = lg.sweep(d, grid, sys.argv[1], duration=0.3, progress=False, chunk=2)
    print(json.dumps({"measured": r.measured, "skipped": r.skipped}))
""")


@pytest.mark.slow
def test_two_concurrent_sweeps_into_one_directory_lose_and_duplicate_nothing(tmp_path):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    procs = [subprocess.Popen([sys.executable, "-c", WORKER, str(tmp_path)], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, env=env) for _ in range(2)]
    outs = []
    for p in procs:
        out, err = p.communicate(timeout=300)
        assert p.returncode == 0, err[-2000:]
        outs.append(json.loads(out.strip().splitlines()[-1]))
    grid = [(p, v, 0.02) for p in (20.0, 30.0) for v in np.linspace(0.01, 0.05, 6)]
    _complete_and_correct(tmp_path, grid)
    assert sum(o["measured"] for o in outs) == len(grid)
