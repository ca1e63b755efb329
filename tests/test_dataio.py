"""Measurement files: atomic, never overwritten, strict reader with file:line errors."""

import datetime as dt
import json

import numpy as np
import pytest

from leglib import dataio

WHEN = dt.datetime(2021, 7, 1, 12, 30, 5)


def _write(tmp_path, **kw):
    t = np.arange(5) * 0.002
    return dataio.write_measurement(tmp_path, t, 267 + t, 273 - t, {"backend": "virtual"},
                                    gains=(50, 0.046, 0.001), when=WHEN, **kw)


def test_round_trip_and_thesis_name(tmp_path):
    p = _write(tmp_path)
    assert p.name == "20210701_123005_50.000;0.046;0.001_positions.csv"
    m = dataio.read_measurement(p)
    assert m.gains == (50, 0.046, 0.001) and m.absolute
    np.testing.assert_allclose(m.angle1, 267 + m.t)
    side = json.loads(p.with_suffix(".json").read_text())
    assert {"backend", "leglib_version", "git_commit", "gains"} <= set(side)


def test_never_overwrites(tmp_path):
    p = _write(tmp_path)
    before = p.read_bytes()
    with pytest.raises(FileExistsError):
        _write(tmp_path)
    assert p.read_bytes() == before
    assert not list(tmp_path.glob("*.tmp"))


def _bad(tmp_path, body, name="20210701_123005_50.000;0.046;0.001_positions.csv"):
    p = tmp_path / name
    p.write_text(body)
    return p


@pytest.mark.parametrize("body,message", [
    ("0.0,1,2\n0.002,1\n", ":2: expected 3 comma-separated columns"),
    ("0.0,1,2\n0.002,1,x\n", ":2: not a number"),
    ("0.0,1,2\n0.002,nan,2\n", ":2: NaN or infinite"),
    ("0.0,1,2\n0.004,1,2\n0.003,1,2\n", ":3: time 0.003 does not increase"),
    ("0.0,1,2\n", "fewer than two data rows"),
])
def test_malformed_rows_name_file_and_line(tmp_path, body, message):
    p = _bad(tmp_path, body)
    with pytest.raises(dataio.MeasurementError) as err:
        dataio.read_measurement(p)
    assert message in str(err.value) and str(p) in str(err.value)


@pytest.mark.parametrize("name", ["positions.csv", "20210701_123005_50;0.04_positions.csv",
                                  "20210701_123005_a;b;c_positions.csv"])
def test_unparseable_names(tmp_path, name):
    with pytest.raises(dataio.MeasurementError, match="cannot parse"):
        dataio.read_measurement(_bad(tmp_path, "0,1,2\n1,1,2\n", name=name))


def test_bad_sidecar(tmp_path):
    p = _bad(tmp_path, "0,1,2\n1,1,2\n")
    p.with_suffix(".json").write_text("{not json")
    with pytest.raises(dataio.MeasurementError, match="sidecar is not valid JSON"):
        dataio.read_measurement(p)


def test_thesis_file_without_sidecar_is_relative(tmp_path):
    m = dataio.read_measurement(_bad(tmp_path, "0.000000,0.000000,0.000000\n0.002,0.1,-0.1\n"))
    assert not m.absolute and m.gains == (50.0, 0.046, 0.001) and m.stable
