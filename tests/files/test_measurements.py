"""Measurement files: committed as one unit, never overwritten, strict reader with
file:line errors; thesis files still load."""

import datetime as dt
import json
import os
import sys

import numpy as np
import pytest

import leglib as lg
from leglib.files import claims, measurements
from leglib.files.claims import CLAIMS_FILE, claim_many
from leglib.files.measurements import (
    FORMAT,
    MeasurementError,
    claim,
    is_batch_name,
    read_file,
    read_measurement,
    write_batch,
    write_bytes_atomic,
    write_measurement,
)
from leglib.files.names import is_leglib_name, parse_filename
from leglib.files.sweepdir import (
    ProvenanceError,
    check_provenance,
    check_result_provenance,
    committed_gains,
    find_uncommitted,
    gains_of_uncommitted,
    list_measurements,
    uncommitted_claim_key,
)

WHEN = dt.datetime(2021, 7, 1, 12, 30, 5)
THESIS = "20210701_123005_50.000;0.046;0.001_positions.csv"


def _write(tmp_path, gains=(50, 0.046, 0.001), n=5, **kw):
    t = np.arange(n) * 0.002
    return write_measurement(tmp_path, t, 267 + t, 273 - t, {"backend": "virtual", "completed": True},
                                    gains=gains, when=WHEN, **kw)


def test_round_trip_exact_gains_in_the_name(tmp_path):
    p = _write(tmp_path)
    assert p.name.startswith("20210701_123005_50.0;0.046;0.001_lg") and p.name.endswith("_positions.csv")
    assert is_leglib_name(p) and not is_leglib_name(THESIS)
    m = read_measurement(p)
    assert m.gains == (50, 0.046, 0.001) and m.absolute and m.stable
    np.testing.assert_allclose(m.angle1, 267 + m.t)
    side = json.loads(p.with_suffix(".json").read_text())
    assert {"backend", "leglib_version", "git_commit", "gains", "samples", "csv_sha256", "format"} <= set(side)
    assert side["format"] == FORMAT and side["samples"] == 5


def test_near_equal_gains_and_same_second_writers_never_collide(tmp_path):
    a = _write(tmp_path, gains=(20, 0.0021, 0.02))
    b = _write(tmp_path, gains=(20, 0.0024, 0.02))
    c = _write(tmp_path, gains=(20, 0.0024, 0.02))  # a second writer, same second, same gains
    assert len({a, b, c}) == 3 and len(list_measurements(tmp_path)) == 3
    assert read_measurement(a).gains == (20, 0.0021, 0.02)
    assert read_measurement(b).gains == (20, 0.0024, 0.02)
    # an ugly float survives the name exactly
    g = (np.linspace(20, 50, 4)[1], np.linspace(0.002, 0.18, 10)[3], 1e-5)
    assert parse_filename(_write(tmp_path, gains=g))[1] == tuple(float(x) for x in g)
    assert not list(tmp_path.glob(".*.tmp"))


def test_files_follow_the_umask(tmp_path):
    old = os.umask(0o022)
    try:
        p = _write(tmp_path)
    finally:
        os.umask(old)
    assert p.stat().st_mode & 0o777 == 0o644 == p.with_suffix(".json").stat().st_mode & 0o777


def _interrupted_at_the_csv(monkeypatch, write, then=lambda path: None):
    """Run ``write`` with its CSV's commit interrupted (KeyboardInterrupt), after ``then(path)``."""
    real = write_bytes_atomic

    def dying(path, data, overwrite=False):
        if str(path).endswith(".csv"):
            then(path)
            raise KeyboardInterrupt
        return real(path, data, overwrite)

    monkeypatch.setattr(measurements, "write_bytes_atomic", dying)
    with pytest.raises(KeyboardInterrupt):
        write()
    monkeypatch.undo()


def test_interrupt_between_sidecar_and_csv_is_uncommitted(tmp_path, monkeypatch):
    _interrupted_at_the_csv(monkeypatch, lambda: _write(tmp_path))
    assert list_measurements(tmp_path) == []          # nothing committed
    left = find_uncommitted(tmp_path)
    assert [p.suffix for p in left] == [".json"]
    assert gains_of_uncommitted(left[0]) == (50, 0.046, 0.001)


def _thesis(tmp_path, body, name=THESIS):
    p = tmp_path / name
    p.write_text(body)
    return p


@pytest.mark.parametrize("body,message", [
    ("0.0,1,2\n0.002,1\n", ":2: expected 3 comma-separated columns"),
    ("0.0,1,2\n0.002,1,x\n", ":2: column 3: not a number"),
    ("0.0,1,2\n0.002,nan,2\n", ":2: column 2: NaN or infinite"),
    ("0.0,1,2\n0.002,1e400,2\n", ":2: column 2: NaN or infinite"),
    ("0.0,1,2\n0.002,1e308,2\n", ":2: column 2: angle 1e+308 deg beyond"),
    ("0.0,1,2\n0.002,1_0,2\n", ":2: column 2: not a number"),
    ("0.0,1,2\n0.002,\uff11,2\n", ":2: column 2: not a number"),
    ("0.0,1,2\n0.004,1,2\n0.003,1,2\n", ":3: time 0.003 does not increase"),
    ("0.0,1,2\n", "fewer than two data rows"),
    ("", "no data rows"),
    ("0.0,1,2\n" + "9" * 100_000 + "\n", ":2: line of 100000 characters"),
])
def test_malformed_rows_name_file_and_line(tmp_path, body, message):
    p = _thesis(tmp_path, body)
    with pytest.raises(MeasurementError) as err:
        read_measurement(p)
    assert message in str(err.value) and str(p) in str(err.value)
    assert len(str(err.value)) < 400


@pytest.mark.parametrize("name", ["positions.csv", "20210701_123005_50;0.04_positions.csv",
                                  "20210701_123005_a;b;c_positions.csv",
                                  "20210701_123005_50.000;2_66.97;0.001_positions.csv",
                                  "20210701_123005_50.000;\uff12.0;0.001_positions.csv",
                                  "20210701_123005_50.000;nan;0.001_positions.csv"])
def test_unparseable_names(tmp_path, name):
    with pytest.raises(MeasurementError, match="cannot parse"):
        read_measurement(_thesis(tmp_path, "0,1,2\n1,1,2\n", name=name))


def _with_sidecar(tmp_path, **changes):
    p = _write(tmp_path, n=750)
    side = p.with_suffix(".json")
    meta = json.loads(side.read_text())
    meta.update(changes)
    side.write_text(json.dumps(meta))
    return p


@pytest.mark.parametrize("changes,message", [
    ({"completed": "false"}, "field 'completed' must be true or false"),
    ({"gains": [20.0, 0.1, 0.5]}, "gains in the name (50.0, 0.046, 0.001) differ from the sidecar's"),
    ({"gains": [50, "x", 1]}, "field 'gains' must be a list of three finite numbers"),
    ({"samples": 376}, "750 samples, but its sidecar"),
    ({"samples": "750"}, "field 'samples' must be an integer"),
    ({"angles": "radians"}, "field 'angles' must be 'absolute' or 'relative'"),
    ({"columns": ["t", "a", "b"]}, "field 'columns' must be"),
    ({"csv_sha256": "0" * 64}, "SHA-256 mismatch"),
    ({"format": 99}, "field 'format' must be an integer"),
])
def test_sidecar_checked_against_file_and_name(tmp_path, changes, message):
    p = _with_sidecar(tmp_path, **changes)
    with pytest.raises(MeasurementError) as err:
        read_measurement(p)
    assert message in str(err.value)


def test_cut_file_is_refused(tmp_path):
    p = _write(tmp_path, n=750)
    lines = p.read_text().splitlines(keepends=True)
    p.write_text("".join(lines[:376]))
    with pytest.raises(MeasurementError, match="376 samples, but its sidecar .* says 750"):
        read_measurement(p)


@pytest.mark.parametrize("text,kind", [("[1, 2]", "list"), ("null", "NoneType"), ('"hello"', "str"),
                                       ("{not json", "not valid JSON"), ("[" * 100_000, "sidecar")])
def test_sidecar_that_is_not_an_object(tmp_path, text, kind):
    p = _thesis(tmp_path, "0,0,0\n1,1,2\n")
    p.with_suffix(".json").write_text(text)
    with pytest.raises(MeasurementError, match=kind) as err:
        read_measurement(p)
    assert str(p.with_suffix(".json")) in str(err.value)


def test_not_regular_files_are_refused_without_blocking(tmp_path):
    d = tmp_path / THESIS
    d.mkdir()
    with pytest.raises(MeasurementError, match="a directory"):
        read_measurement(d)
    for name, make, kind in [("20210701_123006_1.0;1.0;1.0_positions.csv", os.mkfifo, "a FIFO"),
                             ("20210701_123007_1.0;1.0;1.0_positions.csv",
                              lambda p: os.symlink("/dev/zero", p), "a device"),
                             ("20210701_123008_1.0;1.0;1.0_positions.csv",
                              lambda p: os.symlink(p.name, p), "symlink loop")]:
        p = tmp_path / name
        make(p)
        with pytest.raises(MeasurementError, match=kind):
            read_measurement(p)


def test_latin1_and_oversized_files(tmp_path, monkeypatch):
    p = tmp_path / THESIS
    p.write_bytes("0,0,0\n1,1,2 \u00e9\n".encode("latin-1"))
    with pytest.raises(MeasurementError, match=r":2: measurement file is not UTF-8 text \(byte 0xe9"):
        read_measurement(p)
    monkeypatch.setattr(measurements, "MAX_CSV_BYTES", 10)
    p.write_text("0,0,0\n1,1,2\n")
    with pytest.raises(MeasurementError, match="12 bytes, more than the 10"):
        read_measurement(p)


def test_thesis_file_without_sidecar_is_relative(tmp_path):
    m = read_measurement(_thesis(tmp_path, "0.000000,0.000000,0.000000\n0.002,0.1,-0.1\n"))
    assert not m.absolute and m.gains == (50.0, 0.046, 0.001) and m.stable


def test_orphan_csv_of_an_old_leglib_write_is_not_a_thesis_file(tmp_path):
    """Before format 2 a CSV could be committed without its sidecar: absolute angles."""
    p = _thesis(tmp_path, "0.000000,267.000000,273.000000\n0.002,267.1,272.9\n")
    with pytest.raises(MeasurementError, match="absolute angles without their sidecar"):
        read_measurement(p)
    # a format-2 CSV without its sidecar is never read as a thesis file
    q = _write(tmp_path)
    q.with_suffix(".json").unlink()
    with pytest.raises(MeasurementError, match="sidecar .* missing"):
        read_measurement(q)


def test_old_leglib_files_with_sidecar_still_load(tmp_path):
    p = tmp_path / THESIS
    t = np.arange(4) * 0.002
    p.write_text("".join(f"{a:.6f},{267 + a:.6f},{273 - a:.6f}\n" for a in t))
    p.with_suffix(".json").write_text(json.dumps({
        "columns": ["time [s]", "q1 [deg]", "q2 [deg]"], "angles": "absolute", "gains": [50.0, 0.046, 0.0012],
        "samples": 4, "completed": False, "backend": "virtual"}))
    m = read_measurement(p)
    assert m.absolute and not m.stable and m.gains == (50.0, 0.046, 0.0012)


def test_directory_reads(tmp_path):
    with pytest.raises(MeasurementError, match="no such directory"):
        list_measurements(tmp_path / "missing_dir")
    with pytest.raises(MeasurementError, match="not a directory"):
        list_measurements(_write(tmp_path))
    bad = _thesis(tmp_path, "0,0,0\n1,x,2\n", name="20210701_123009_1.0;1.0;1.0_positions.csv")
    with pytest.raises(MeasurementError, match="not a number"):
        lg.read_measurements(tmp_path)
    with pytest.warns(UserWarning, match="1 of 2 measurement files skipped"):
        r = lg.read_measurements(tmp_path, strict=False)
    assert len(r.measurements) == 1 and r.problems[0][0] == bad


def test_gainmap_refuses_duplicate_gains_and_missing_dirs(tmp_path):
    with pytest.raises(MeasurementError, match="no such directory"):
        lg.GainMap.from_measurements(str(tmp_path / "missing_dir"))
    a = _write(tmp_path, gains=(20, 0.05, 0.02))
    b = _write(tmp_path, gains=(20, 0.05, 0.02))
    with pytest.raises(MeasurementError) as err:
        lg.GainMap.from_measurements(tmp_path)
    assert str(a) in str(err.value) and str(b) in str(err.value)


def test_provenance_refuses_another_leg(tmp_path):
    rec = {"device": {"backend": "virtual", "firmware": "0.5.6", "twin_seed": 1,
                      "twin_plant_values": {"payload_mass": 0.0, "_sources": {"a": "b"}}},
           "experiment": {"step": 0.4, "duration": 1.5}}
    check_provenance(tmp_path, rec, write=True)
    assert (tmp_path / "sweep.json").exists()
    check_provenance(tmp_path, rec)             # the same: fine
    other = json.loads(json.dumps(rec))
    other["device"]["twin_plant_values"]["payload_mass"] = 0.5
    with pytest.raises(ProvenanceError, match=r"twin_plant_values\.payload_mass: 0\.0 there, 0\.5 now"):
        check_provenance(tmp_path, other)
    other = json.loads(json.dumps(rec))
    other["experiment"]["duration"] = 0.3
    with pytest.raises(ProvenanceError, match="experiment.duration"):
        check_provenance(tmp_path, other)


def test_claims_are_exclusive_and_released(tmp_path):
    c = claim(tmp_path, (1.0, 2.0, 3.0))
    assert c is not None and claim(tmp_path, (1.0, 2.0, 3.0)) is None
    assert claim(tmp_path, (1.0, 2.0, 3.0000001)) is not None
    c.release()
    assert claim(tmp_path, (1.0, 2.0, 3.0)) is not None


def test_many_claims_at_once_take_the_free_points_up_to_a_limit(tmp_path):
    keys = [(float(i), 0.05, 0.01) for i in range(10)]
    other = claim(tmp_path, keys[3])
    held, taken = claim_many(tmp_path, keys, limit=6)
    assert taken == [True, True, True, False, True, True, True, False, False, False]
    last = claim(tmp_path, keys[9])
    assert claim(tmp_path, keys[0]) is None and last is not None
    for c in (held, other, last):
        c.release()
    again, taken = claim_many(tmp_path, keys + keys[:1])
    assert taken == [True] * 10 + [False]   # all released; a key twice is taken once
    again.release()


def test_a_claim_held_by_another_process_is_refused_until_it_ends(tmp_path):
    import subprocess
    import sys
    code = ("import sys, time; from leglib.files.claims import claim; c = claim(sys.argv[1], (4.0, 5.0, 6.0)); "
            "print('held' if c else 'refused', flush=True); time.sleep(60)")
    proc = subprocess.Popen([sys.executable, "-c", code, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "held"
        assert claim(tmp_path, (4.0, 5.0, 6.0)) is None
        assert claim(tmp_path, (4.0, 5.0, 6.5)) is not None
    finally:
        proc.kill()
        proc.wait()
    assert claim(tmp_path, (4.0, 5.0, 6.0)) is not None   # its process gone: released


def test_claims_of_a_sweep_share_one_lock_file(tmp_path):
    held = [claim(tmp_path, (float(i), 0.05, 0.01)) for i in range(50)]
    assert all(c is not None for c in held)
    assert [p.name for p in tmp_path.rglob("*")] == [CLAIMS_FILE]


_HOLDER = ("import sys, time; from leglib.files.claims import claim; "
           "cs = [claim(sys.argv[1], (4.0, 5.0, float(g))) for g in sys.argv[2:]]; "
           "print(' '.join('held' if c else 'refused' for c in cs), flush=True); "
           "line = sys.stdin.readline(); cs[0].release(); print('released', flush=True); time.sleep(60)")


def _holder(tmp_path, *gains):
    import subprocess
    return subprocess.Popen([sys.executable, "-c", _HOLDER, str(tmp_path), *map(str, gains)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)


def test_releasing_one_claim_keeps_the_others_of_its_process(tmp_path):
    """Record locks belong to the process and closing a file drops them all: a released
    claim must leave the process's other claims in the directory held."""
    proc = _holder(tmp_path, 6.0, 7.0)
    try:
        assert proc.stdout.readline().split() == ["held", "held"]
        assert claim(tmp_path, (4.0, 5.0, 6.0)) is None and claim(tmp_path, (4.0, 5.0, 7.0)) is None
        proc.stdin.write("go\n")
        proc.stdin.flush()
        assert proc.stdout.readline().strip() == "released"
        assert claim(tmp_path, (4.0, 5.0, 7.0)) is None   # still held by its living process
        c = claim(tmp_path, (4.0, 5.0, 6.0))
        assert c is not None
        c.release()
    finally:
        proc.kill()
        proc.wait()


def test_a_waiting_claim_gets_the_point_when_its_holder_releases_it(tmp_path):
    import time
    proc = _holder(tmp_path, 6.0)
    try:
        assert proc.stdout.readline().split() == ["held"]
        assert claim(tmp_path, (4.0, 5.0, 6.0)) is None
        proc.stdin.write("go\n")
        proc.stdin.flush()
        t0 = time.monotonic()
        c = claim(tmp_path, (4.0, 5.0, 6.0), wait=True)
        assert c is not None and time.monotonic() - t0 < 30 and proc.poll() is None
        c.release()
    finally:
        proc.kill()
        proc.wait()


def test_claims_of_one_process_exclude_each_other_across_threads(tmp_path):
    from concurrent.futures import ThreadPoolExecutor
    keys = [(float(i), 0.05, 0.01) for i in range(40)]
    with ThreadPoolExecutor(4) as pool:
        results = list(pool.map(lambda k: claim_many(tmp_path, keys), range(8)))
    taken = np.array([t for _, t in results])
    assert (taken.sum(axis=0) == 1).all()   # each point taken by exactly one claim
    for held, _ in results:
        held.release()
    again, t = claim_many(tmp_path, keys)
    assert all(t)
    again.release()
    st = os.stat(tmp_path / CLAIMS_FILE)
    assert (st.st_dev, st.st_ino) not in claims._OPEN   # the lock file closed with its last claim


def test_cached_result_from_another_leg_is_refused(tmp_path):
    t = np.arange(5) * 0.002
    meta = {"backend": "virtual", "twin_seed": 4, "twin_plant_values": {"payload_mass": 0.0, "inertia_scale": 0.9}}
    src = write_measurement(tmp_path, t, 267 + t, 273 - t, meta)
    result = tmp_path / "identified.json"
    result.write_text(json.dumps({"source": str(src), "leg": {}}))
    here = {"backend": "virtual", "twin_seed": 2, "twin_plant_values": {"payload_mass": 0.0, "inertia_scale": 0.9}}
    check_result_provenance(result, here)  # another noise seed: the same leg
    heavy = {"backend": "virtual", "twin_plant_values": {"payload_mass": 0.5, "inertia_scale": 0.9}}
    with pytest.raises(ProvenanceError, match=r"payload_mass: 0\.0 there, 0\.5 now"):
        check_result_provenance(result, heavy)
    result.write_text(json.dumps({"source": str(tmp_path / "gone_positions.csv")}))
    with pytest.warns(UserWarning, match="cannot check"):
        check_result_provenance(result, heavy)


# -- batch files ------------------------------------------------------------------------

BATCH_GAINS = [(20.0, 0.002, 0.002), (20.0, 0.0024, 0.02), (35.5, 0.1, 0.08)]


def _batch(tmp_path, sizes=(5, 7, 4)):
    series = []
    for k, (g, n) in enumerate(zip(BATCH_GAINS, sizes)):
        t = np.arange(n) * 0.002
        series.append((t, 267 + k + t, 273 - k - t, g, {"completed": k != 2,
                                                         "abort_reason": "diverged" if k == 2 else None}))
    return write_batch(tmp_path, series, {"backend": "virtual", "step_turns": 0.4}, when=WHEN), series


def _edit_sidecar(p, fn):
    side = p.with_suffix(".json")
    meta = json.loads(side.read_text())
    fn(meta)
    side.write_text(json.dumps(meta))


def test_a_batch_round_trips_its_measurements_in_order(tmp_path):
    p, series = _batch(tmp_path)
    assert is_batch_name(p) and p.name.startswith("20210701_123005_lg") and p.name.endswith("_batch.csv")
    assert list_measurements(tmp_path) == [p]
    ms = read_file(p)
    assert [m.gains for m in ms] == BATCH_GAINS and [m.point for m in ms] == [0, 1, 2]
    for m, (t, a1, a2, _, pm) in zip(ms, series):
        np.testing.assert_array_equal(m.t, t)
        np.testing.assert_allclose(m.angle1, a1, atol=5e-7)
        np.testing.assert_allclose(m.angle2, a2, atol=5e-7)
        assert m.absolute and m.stable == pm["completed"] and m.meta["abort_reason"] == pm["abort_reason"]
        assert m.meta["backend"] == "virtual" and m.meta["samples"] == len(t) and m.meta["format"] == 3
    assert "measurement 3 of the batch" in ms[2].where
    # one file of its own next to the batch: both kinds are read, and committed_gains has all
    single = _write(tmp_path)
    assert [m.path for m in lg.read_measurements(tmp_path).measurements].count(p) == 3
    assert committed_gains(tmp_path) == {*BATCH_GAINS, (50, 0.046, 0.001)}
    with pytest.raises(MeasurementError, match="batch file holds several measurements.*read_file"):
        read_measurement(p)
    assert read_file(single)[0].point is None


def test_batches_read_one_after_another_keep_their_numbers(tmp_path):
    """A batch is read through a buffer reused from file to file: what was read stays."""
    first, _ = _batch(tmp_path / "a")
    second, _ = _batch(tmp_path / "b", sizes=(3, 9, 2))
    a = read_file(first)
    kept = [m.angle1.copy() for m in a]
    b = read_file(second)
    assert [m.t.size for m in b] == [3, 9, 2]
    for m, k in zip(a, kept):
        np.testing.assert_array_equal(m.angle1, k)


def test_committed_gains_of_a_damaged_batch_sidecar_are_none(tmp_path):
    p, _ = _batch(tmp_path)
    assert committed_gains(tmp_path) == set(BATCH_GAINS)
    _edit_sidecar(p, lambda m: m["points"][1].update(gains="123"))
    assert committed_gains(tmp_path) == set()
    p.with_suffix(".json").write_text("[" * 100_000)   # nested too deeply to parse
    assert committed_gains(tmp_path) == set()


def test_a_batch_takes_numpy_values_and_only_its_names_are_listed(tmp_path):
    t = np.arange(5) * 0.002
    p = write_batch(tmp_path, [(t, 267 + t, 273 - t, np.array([20, 0.01, 0.02]), {"completed": np.True_})],
                           {"step_turns": np.float32(0.5), "twin_seed": np.int64(3)})
    (m,) = read_file(p)
    assert m.meta["step_turns"] == 0.5 and m.meta["twin_seed"] == 3 and m.meta["completed"] is True
    (tmp_path / "notes_batch.csv").write_text("not a measurement\n")
    (tmp_path / "20210701_123005_lgABCDEF012345_batch.csv").write_text("0,0,0\n")
    assert list_measurements(tmp_path) == [p]


def test_a_batch_refuses_bad_measurements_naming_which(tmp_path):
    t = np.arange(5) * 0.002
    good = (t, 267 + t, 273 - t, (20, 0.01, 0.02), {})
    with pytest.raises(ValueError, match="measurement 1: gains must be three finite numbers"):
        write_batch(tmp_path, [good, (t, t, t, (20, float("nan"), 0.02), {})], {})
    with pytest.raises(ValueError, match="measurement 0: t, angle1, angle2 must be 1-D of equal length"):
        write_batch(tmp_path, [(t, t[:4], t, (20, 0.01, 0.02), {})], {})
    with pytest.raises(ValueError, match="measurement 1: values must be finite and angles within"):
        write_batch(tmp_path, [good, (t, t + 4000, t, (20, 0.01, 0.02), {})], {})
    with pytest.raises(ValueError, match=r"measurement 0: point_meta\['completed'\] must be a bool"):
        write_batch(tmp_path, [(t, t, t, (20, 0.01, 0.02), {"completed": 1})], {})
    with pytest.raises(ValueError, match="no measurements"):
        write_batch(tmp_path, [], {})
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("damage, message", [
    (lambda p: p.write_bytes(p.read_bytes()[:-20]), r"_batch\.csv:16: expected 3 comma-separated columns"),
    (lambda p: p.write_bytes(b"".join(p.read_bytes().splitlines(True)[:-1])),
     "15 samples, but its sidecar .* says 16 .a cut or extended file"),
    (lambda p: p.write_bytes(p.read_bytes().replace(b"267.", b"268.", 1)), "SHA-256 mismatch"),
    (lambda p: p.with_suffix(".json").unlink(), "sidecar .* missing: a batch without its sidecar"),
    (lambda p: _edit_sidecar(p, lambda m: m["points"][1].update(gains=[20, "x", 0.02])),
     r"field points\[1\]\.'gains' must be a list of three finite numbers"),
    (lambda p: _edit_sidecar(p, lambda m: m["points"][0].update(samples=6)), "'samples' add up to 17, but .* has 16 rows"),
    (lambda p: _edit_sidecar(p, lambda m: m["points"][2].update(completed="yes")),
     r"field points\[2\]\.'completed' must be true or false"),
    (lambda p: _edit_sidecar(p, lambda m: m.update(format=2)), "field 'format' must be 3"),
    (lambda p: _edit_sidecar(p, lambda m: m.update(points=[])), "field 'points' must be a non-empty list"),
    (lambda p: _edit_sidecar(p, lambda m: m.update(format=3.0)), "field 'format' must be 3"),
    (lambda p: _edit_sidecar(p, lambda m: m.update(angles="relative")), "field 'angles' must be 'absolute'"),
    (lambda p: _edit_sidecar(p, lambda m: m.pop("angles")), "field 'angles' must be 'absolute'"),
    (lambda p: _edit_sidecar(p, lambda m: m["points"][0].update(angles="relative")),
     r"field points\[0\]\.'angles' does not belong to one measurement of a batch"),
    (lambda p: _edit_sidecar(p, lambda m: m["points"][1].pop("completed")),
     r"field points\[1\]\.'completed' must be true or false"),
    (lambda p: _edit_sidecar(p, lambda m: m["points"].__setitem__(1, [20, 0.01, 0.02])),
     r"field points\[1\] must be a JSON object, got list"),
])
def test_a_damaged_batch_is_refused_naming_file_and_field(tmp_path, damage, message):
    p, _ = _batch(tmp_path)
    damage(p)
    with pytest.raises(MeasurementError, match=message):
        read_file(p)
    with pytest.warns(UserWarning, match="1 of 1 measurement files skipped"):
        read = lg.read_measurements(tmp_path, strict=False)
    assert read.measurements == [] and read.problems[0][0] == p


def test_time_must_increase_within_each_measurement_of_a_batch(tmp_path):
    p, _ = _batch(tmp_path)
    lines = p.read_text().splitlines(keepends=True)
    lines[7] = lines[6]   # the third row of the second measurement repeats its second
    text = "".join(lines).encode()
    p.write_bytes(text)
    _edit_sidecar(p, lambda m: m.update(csv_sha256=__import__("hashlib").sha256(text).hexdigest()))
    with pytest.raises(MeasurementError, match=r"_batch\.csv:8: time 0\.002 does not increase .* "
                                                      r"within measurement 2 of the batch"):
        read_file(p)


def test_an_unfinished_batch_is_uncommitted_and_claimed_while_written(tmp_path, monkeypatch):
    held = []

    def try_to_claim(path):   # the writer holds its batch's name
        held.append(claim(tmp_path, uncommitted_claim_key(path.with_suffix(".json"))))

    _interrupted_at_the_csv(monkeypatch, lambda: _batch(tmp_path), try_to_claim)
    assert held == [None]   # claimed by the writer while it wrote
    assert list_measurements(tmp_path) == []
    (left,) = find_uncommitted(tmp_path)
    assert left.name.endswith("_batch.json")
    key = uncommitted_claim_key(left)
    assert key.startswith("lg") and claim(tmp_path, key) is not None   # released: the writer is gone


def test_a_full_disk_names_the_file(tmp_path, monkeypatch):
    """A write that fails for want of space (or permission) says which file it was writing."""
    import errno

    from leglib.files import atomic

    def full(fd, data):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(atomic.os, "write", full)
    target = tmp_path / "x.csv"
    with pytest.raises(OSError, match=f"writing {target}: No space left on device") as err:
        atomic.write_bytes_atomic(target, b"1,2,3\n")
    assert err.value.errno == errno.ENOSPC and not target.exists()
    assert not list(tmp_path.glob(".*.tmp"))
