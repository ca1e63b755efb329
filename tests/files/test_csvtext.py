"""Measurement files in numpy and json: the CSV text is Python's ``.6f`` to the byte (the
files leglib wrote before, and their SHA-256s); numpy's reading gives ``float``'s numbers bit
for bit and leaves every error to the careful reader; sidecar text is json.dumps; a twin
sweep's batch file flushed once; a sweep read back and mapped exactly as one by one."""

import json
import os
import stat
from pathlib import Path

import numpy as np
import pytest

import leglib as lg
from leglib.design.points import identify_response
from leglib.experiments.step import StepResponse
from leglib.files import measurements
from leglib.files.measurements import (
    _ROW_RE,
    MeasurementError,
    _csv_bytes,
    _json_default,
    _parse_plain,
    _sidecar_text,
    read_file,
    read_measurement,
    write_measurement,
)


def _python_csv(data) -> bytes:
    """Today's writer (Python formatting), the reference."""
    return "".join(",".join(f"{v:.6f}" for v in row) + "\n" for row in np.atleast_2d(data)).encode("ascii")


def _python_rows(raw: bytes) -> np.ndarray:
    return np.array([[float(x) for x in line.split(b",")] for line in raw.split(b"\n") if line.strip()])


def _bits(a) -> list:
    return np.ascontiguousarray(a, dtype=float).view(np.int64).tolist()


def _tables():
    rng = np.random.default_rng(7)
    n = 4000
    t = np.arange(n) * 0.002
    yield np.column_stack([t, 267 + rng.normal(0, 20, n), 273 + rng.normal(0, 20, n)])
    yield rng.normal(0, 1, (n, 3)) * rng.choice([1e-9, 1e-6, 1e-3, 1.0, 1e3, 1e6, 1e9], (n, 3))
    yield (rng.integers(-10 ** 9, 10 ** 9, (n, 3)) + 0.5) / 1e6          # near-ties
    yield rng.integers(-10 ** 6, 10 ** 6, (n, 3)) / 128                  # exact ties
    yield np.array([[0.0, -0.0, -1e-7], [5e-7, -5e-7, 4.9999999e-7], [3599.9999995, -3599.9999995, 1e15],
                    [np.nan, np.inf, -np.inf], [2.0 ** 50 / 1e6, -(2.0 ** 50) / 1e6, 1e-300]])


def test_csv_text_is_pythons_to_the_byte():
    for data in _tables():
        assert _csv_bytes(data) == _python_csv(data)
        for row in data[:300]:  # each row alone: its own widths, its own near-ties
            assert _csv_bytes(row[None]) == _python_csv(row[None])
    assert _csv_bytes(np.zeros((0, 3))) == b""
    rng = np.random.default_rng(5)   # other column counts, every integer width
    for c in (1, 2, 5):
        data = rng.normal(0, 1, (500, c)) * 10.0 ** rng.integers(-7, 10, (500, c))
        assert _csv_bytes(data) == _python_csv(data)


def test_csv_text_of_values_next_to_a_half_millionth_is_pythons():
    """Values within a few ulps of the ties of .6f, where the scaled product's rounding
    could decide: each is written as Python writes it."""
    rng = np.random.default_rng(9)
    ties = (rng.integers(-4 * 10 ** 9, 4 * 10 ** 9, 20000) + 0.5) / 1e6
    near = np.concatenate([np.nextafter(ties, np.inf), ties, np.nextafter(ties, -np.inf),
                           np.nextafter(np.nextafter(ties, np.inf), np.inf)])
    data = near.reshape(-1, 4)
    assert _csv_bytes(data) == _python_csv(data)


WRITTEN_BEFORE = Path(__file__).with_name("written_before")   # by leglib's compiled codec (7cd60a7)


def _written_before_series():
    """The numbers of the files in written_before/, as they were made."""
    rng = np.random.default_rng(20261201)

    def run(n):
        t = np.arange(n) * 0.002
        return t, 267 + np.cumsum(rng.normal(0, 0.3, n)), 273 - np.cumsum(rng.normal(0, 0.3, n))
    single = run(200)
    series = []
    for k, g in enumerate([(20.0, 0.002, 0.002), (30.0, 0.0217, 0.0107), (50.0, 0.18, 0.08)]):
        series.append((*run(100 + 10 * k), g, {"completed": k != 1,
                                                "abort_reason": None if k != 1 else "position bound"}))
    return single, series


def test_the_files_leglib_wrote_before_read_and_keep_their_bytes_and_hashes(tmp_path):
    """A format-2 measurement and a format-3 batch written by the compiled codec (and
    its hand-laid sidecars): read as before, and the same numbers written now give the
    same bytes, so the sidecars' SHA-256s still match."""
    import hashlib
    single, series = _written_before_series()
    (p,) = WRITTEN_BEFORE.glob("*_positions.csv")
    (b,) = WRITTEN_BEFORE.glob("*_batch.csv")
    for path, tables in ((p, [single]), (b, [s[:3] for s in series])):
        raw = path.read_bytes()
        meta = json.loads(path.with_suffix(".json").read_text())
        assert meta["format"] == (2 if path == p else 3)
        assert _csv_bytes(np.concatenate([np.column_stack(x) for x in tables])) == raw
        assert meta["csv_sha256"] == hashlib.sha256(raw).hexdigest()
        ms = read_file(path)
        assert _bits(np.concatenate([np.column_stack([m.t, m.angle1, m.angle2]) for m in ms])) == _bits(_python_rows(raw))
    ms = lg.read_measurements(WRITTEN_BEFORE).measurements
    assert [m.gains for m in ms] == [(50.0, 0.046, 0.001)] + [s[3] for s in series]
    assert [m.stable for m in ms] == [True, True, False, True]
    assert ms[2].meta["abort_reason"] == "position bound" and ms[1].meta["twin_seed"] == 11
    # written again now: the same CSV bytes
    new_single = write_measurement(tmp_path, *single, {"completed": True}, gains=(50.0, 0.046, 0.001))
    assert new_single.read_bytes() == p.read_bytes()
    assert measurements.write_batch(tmp_path, series, {}).read_bytes() == b.read_bytes()


@pytest.mark.slow
def test_a_large_table_round_trips_exactly():
    """120,000 rows (a batch's size): the text is Python's, numpy reads float's numbers,
    and the checks hold anywhere in it (time increasing, a bad line at the end)."""
    rng = np.random.default_rng(3)
    n = 120_000
    data = np.column_stack([np.arange(n) * 0.002, 267 + rng.normal(0, 20, n), 273 + rng.normal(0, 20, n)])
    raw = _csv_bytes(data)
    assert raw == _python_csv(data)
    reference = _python_rows(raw)
    parsed = _parse_plain(raw, 3, True, (1, 2))
    assert _bits(parsed) == _bits(reference)
    lines = raw.split(b"\n")
    for row in (1, n // 4, n // 2, n - 1):
        bad = data[row].copy()
        bad[0] = data[row - 1, 0]   # time stands still there
        # the reference writer and reader work line by line: the text of the table with this
        # one row changed, and its reading, are the table's with that line (and row) replaced
        text = b"\n".join(lines[:row] + [_python_csv(bad).rstrip(b"\n")] + lines[row + 1:])
        expected = reference.copy()
        expected[row] = _python_rows(_python_csv(bad))[0]
        assert _parse_plain(text, 3, True, (1, 2)) is None
        assert _bits(_parse_plain(text, 3, False, (1, 2))) == _bits(expected)
        cut = list(lines)
        cut[row] = cut[row].replace(b",", b";", 1)
        assert _parse_plain(b"\n".join(cut), 3, False, ()) is None


@pytest.mark.slow
def test_numpys_reading_is_floats():
    rng = np.random.default_rng(8)
    for data in _tables():
        finite = data[np.all(np.isfinite(data), axis=1)]
        for raw in (_python_csv(finite),
                    "".join(",".join(repr(float(v)) for v in row) + "\n" for row in finite).encode()):
            got = _parse_plain(raw, 3, False, ())
            if got is not None:
                assert _bits(got) == _bits(_python_rows(raw))
    # random decimal spellings: whatever the plain reader accepts, it reads exactly
    accepted = 0
    for _ in range(20000):
        fields = []
        for _ in range(3):
            digits = str(rng.integers(0, 10 ** int(rng.integers(1, 19))))
            cut = int(rng.integers(0, len(digits) + 1))
            exp = f"e{int(rng.integers(-30, 30))}" if rng.random() < 0.3 else ""
            fields.append(f"{rng.choice(['', '-', '+'])}{digits[:cut]}.{digits[cut:]}{exp}")
        line = ",".join(fields)
        got = _parse_plain((line + "\n").encode(), 3, False, ())
        if got is not None:
            accepted += 1
            assert _bits(got[0]) == _bits([float(f) for f in fields]), line
    assert accepted > 5000


@pytest.mark.parametrize("line", [
    "1,2,3", " 1 ,\t2 , 3 \r", "1,2,3\r\r", "1,2", "1,2,3,4", "1.,2,.5", ".,1,2", "1e5,2,3", "1e,2,3",
    "nan,1,2", "inf,1,2", "1_0,2,3", "\u0661,2,3", "0x1,2,3", "+1,-2,+3", "1 2,3,4", "1,,2", ",1,2",
    "1,2,3\r ", "1,2,3\x0b", "\x0b1,2,3", "--1,2,3", "1.2.3,4,5", "1E-3,2,3", "00012,0.0,-0", "1,2,3e999",
    "1,2,1e-400", "\u00a01,2,3", "1,2,3\x00"])
def test_numpys_reading_accepts_no_row_the_reader_refuses(line):
    got = _parse_plain((line + "\n").encode(), 3, False, ())
    if got is not None:
        assert _ROW_RE.match(line)
        assert _bits(got[0]) == _bits([float(x) for x in line.split(",")])


BAD_BODIES = [
    b"0.0,267.0,273.0\n0.002,267.0\n",                       # columns
    b"0.0,267.0,273.0\n0.002,nan,273.0\n",                   # NaN
    b"0.0,267.0,273.0\n0.002,1e999,273.0\n",                 # overflow to inf
    b"0.0,267.0,273.0\n0.0,267.0,273.0\n",                   # time not increasing
    b"0.0,267.0,273.0\n0.002,3600.5,273.0\n",                # angle beyond the limit
    b"0.0,267.0,273.0\n0.002,2_67.0,273.0\n",                # underscore
    b"0.0,267.0,273.0\n0.002,\xef\xbc\x92,273.0\n",          # full-width digit
    b"0.0,267.0,273.0\n0.002,\xff,273.0\n",                  # not UTF-8
    b"0.0,267.0,273.0\n" + b"0.002," + b"1" * 600 + b",273.0\n",  # long line
    b"0.0,267.0,273.0\n0.002,267.0,273.0,\n",                # trailing comma
    b"\n   \n\t\r\n",                                        # no data rows
    b"0.0,267.0,273.0\n",                                    # one row
    b"0.0,267.0,273.0\r\n0.002,267.0,273.0\r\n",             # CRLF: fine
    b"  0.0 , 267.0 ,273.0\n\n\x0c\n.002,267.,2.73e2",       # blank lines, no final newline: fine
]


@pytest.mark.parametrize("body", BAD_BODIES)
def test_errors_and_numbers_do_not_depend_on_the_fast_path(tmp_path, monkeypatch, body):
    name = "20210701_123005_50.000;0.046;0.001_positions.csv"

    def outcome(directory):
        directory.mkdir()
        p = directory / name
        p.write_bytes(body)
        try:
            m = read_measurement(p)
        except MeasurementError as exc:
            return "error", str(exc).replace(str(directory), "<dir>")
        return "read", (_bits(m.t), _bits(m.angle1), _bits(m.angle2))

    fast = outcome(tmp_path / "fast")
    monkeypatch.setattr(measurements, "_parse_plain", lambda *a, **k: None)  # the careful parser only
    assert outcome(tmp_path / "slow") == fast


def test_sidecar_text_is_json_dumps():
    rng = np.random.default_rng(3)
    docs = [{"b": [1, [2, {}], {"z": 1.5, "a": None}], "a": "x\ny", "c": {}, "d": [], "e": float("nan"),
             "f": True, "g": (1, 2), "h": np.float64(1 / 3), "u": "\u00e9", "v": {"n": np.int64(3), "w": np.arange(2)}},
            {"x": np.arange(3)}, {"x": np.bool_(True)}, {1: 2}, [1, 2], {}, {"k": rng.normal(size=5).tolist()}]
    for doc in docs:
        assert _sidecar_text(doc) == json.dumps(doc, indent=2, sort_keys=True, default=_json_default).encode()


@pytest.fixture(scope="module")
def dev():
    d = lg.connect("virtual", seed=11)
    lg.configure(d)
    lg.calibrate(d)
    return d


def test_a_twin_batch_is_flushed_once_and_a_real_leg_file_by_file(dev, tmp_path, monkeypatch):
    synced = []
    real_fsync = os.fsync

    def fsync(fd):
        synced.append("dir" if stat.S_ISDIR(os.fstat(fd).st_mode) else "file")
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    grid = [(20.0, 0.03, 0.02), (30.0, 0.05, 0.02), (40.0, 0.05, 0.02)]
    res = lg.sweep(dev, grid, tmp_path / "twin", duration=0.2, progress=False)
    assert res.measured == 3 and len(res.written) == 1
    # sweep.json (file and directory), then the batch's two files: their directory, once
    assert synced == ["file", "dir", "dir"]
    synced.clear()
    t = np.arange(5) * 0.002
    write_measurement(tmp_path / "leg", t, 267 + t, 273 - t, {"completed": True}, gains=(50, 0.046, 0.001))
    assert synced == ["file", "dir", "file", "dir"]  # sidecar, then CSV, each flushed before it counts


def test_sweep_reads_back_and_maps_as_before(dev, tmp_path):
    from leglib.params import load_leg

    grid = [(p, v, i) for p in (20.0, 40.0) for v in (0.01, 0.05, 0.1) for i in (0.002, 0.02)]
    res = lg.sweep(dev, grid, tmp_path, duration=0.6, progress=False)
    leg = load_leg("thesis")
    (p,) = res.written   # one batch file
    raw = p.read_bytes()
    ms = read_file(p)
    ref = _python_rows(raw)
    assert len(ms) == len(grid) and [m.gains for m in ms] == [tuple(g) for g in grid]
    assert _bits(np.concatenate([np.column_stack([m.t, m.angle1, m.angle2]) for m in ms])) == _bits(ref)
    assert _python_csv(ref) == raw  # what was written is Python's text of these numbers
    # the map as identifying the measurements one by one builds it
    old = [identify_response(StepResponse.from_measurement(m, leg), leg) for m in ms]
    new = lg.GainMap.from_measurements(tmp_path).points
    assert [(p.gains, p.status, p.reason) for p in new] == [(p.gains, p.status, p.reason) for p in old]
    assert _bits([(p.zeta, p.wn, p.r2) for p in new]) == _bits([(p.zeta, p.wn, p.r2) for p in old])
    assert not [n for n in os.listdir(tmp_path) if n.endswith(".tmp")]
