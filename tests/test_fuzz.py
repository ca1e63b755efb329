"""Seeded, bounded fuzzing of every input leglib reads: measurement files and sidecars,
parameter TOML, notebook parameters, batch specs, and interrupts between the files of a
measurement. Each case either gives a result that satisfies the input's invariants or a
clear error of the module's own type that names the input; nothing else."""

import json
import math
import os
import re
from pathlib import Path

import nbformat
import numpy as np
import pytest

import leglib as lg
from leglib.device.session import AXIS_STATE_IDLE, any_error, clear_errors
from leglib.files import atomic
from leglib.files.measurements import (
    ANGLE_LIMIT_DEG,
    Measurement,
    MeasurementError,
    read_file,
    read_measurement,
    write_measurement,
)
from leglib.files.names import parse_filename
from leglib.files.sweepdir import find_uncommitted, list_measurements
from leglib.notebook import batch
from leglib.notebook import setup as nbtools
from leglib.notebook.run import notebook_paths
from leglib.params import PARAMS_DIR, ParameterError, load_leg, load_plant

SEED = 20240917
MAX_MESSAGE = 600  # characters: an error quotes a short excerpt, never the input


def _rng(k):
    return np.random.default_rng([SEED, k])


def _pick(rng, seq):
    return seq[int(rng.integers(len(seq)))]


def _weird_value(rng):
    choices = [None, True, "false", "", "x" * 300, -1, 0, 1e308, -1e308, float("nan"), float("inf"),
               [1, 2], [1, 2, 3], {"a": 1}, "\uff11", 2**70, 0.5, "NaN", [None] * 3]
    return choices[int(rng.integers(len(choices)))]


# -- measurement files ----------------------------------------------------------------------

def _mutate_bytes(rng, data: bytes) -> bytes:
    b = bytearray(data)
    for _ in range(int(rng.integers(1, 4))):
        op = int(rng.integers(6))
        i = int(rng.integers(len(b) + 1)) if b else 0
        if op == 0 and b:
            b[min(i, len(b) - 1)] = int(rng.integers(256))
        elif op == 1:
            b[i:i] = bytes(rng.choice(list(b",.-+eE0123456789 \n\r\t_xnaif\xff\xef\xbc\x91"), int(rng.integers(1, 8))))
        elif op == 2:
            del b[i:i + int(rng.integers(1, 40))]
        elif op == 3:  # cut the file at a line boundary
            lines = bytes(b).split(b"\n")
            b = bytearray(b"\n".join(lines[:int(rng.integers(len(lines) + 1))]))
        elif op == 4:  # a huge line
            b[i:i] = b"9" * int(rng.integers(600, 5000))
        else:  # swap two lines
            lines = bytes(b).split(b"\n")
            if len(lines) > 2:
                a, c = rng.integers(len(lines), size=2)
                lines[a], lines[c] = lines[c], lines[a]
            b = bytearray(b"\n".join(lines))
    return bytes(b)


def _mutate_sidecar(rng, meta: dict) -> dict:
    meta = json.loads(json.dumps(meta))
    for _ in range(int(rng.integers(1, 3))):
        key = ["gains", "samples", "completed", "angles", "columns", "csv_sha256", "format", "step_turns",
               "abort_reason", "sample_rate_hz"][int(rng.integers(10))]
        if rng.random() < 0.2:
            meta.pop(key, None)
        elif key == "gains" and rng.random() < 0.5:
            meta[key] = [float(g) * (1 + float(rng.normal()) * 1e-3) for g in meta[key]]
        elif key == "samples" and rng.random() < 0.5:
            meta[key] = int(meta[key]) + int(rng.integers(-3, 4)) or 1
        else:
            meta[key] = _weird_value(rng)
    return meta


def _check_measurement(m: Measurement):
    assert m.t.ndim == 1 and m.t.size >= 2 and m.t.shape == m.angle1.shape == m.angle2.shape
    assert np.all(np.diff(m.t) > 0)
    assert np.all(np.isfinite(m.angle1)) and np.all(np.abs(m.angle1) <= ANGLE_LIMIT_DEG)
    assert np.all(np.isfinite(m.angle2)) and np.all(np.abs(m.angle2) <= ANGLE_LIMIT_DEG)
    assert m.gains is None or (len(m.gains) == 3 and all(math.isfinite(g) for g in m.gains))
    assert isinstance(m.stable, bool)
    if "samples" in m.meta:
        assert m.meta["samples"] == m.t.size


def _read(path):
    try:
        return read_measurement(path), None
    except MeasurementError as exc:
        msg = str(exc)
        assert len(msg) < MAX_MESSAGE, msg[:200]
        assert Path(path).name in msg or Path(path).with_suffix(".json").name in msg, msg
        return None, msg


def test_fuzz_measurement_files(tmp_path):
    t = np.arange(40) * 0.002
    good = write_measurement(tmp_path / "src", t, 267 + 3 * np.sin(t * 30), 273 - t, {"completed": True},
                                    gains=(35.0, 0.0213, 0.004))
    csv, side = good.read_bytes(), json.loads(good.with_suffix(".json").read_text())
    thesis_csv = b"".join(f"{a:.6f},{np.sin(a):.6f},{-a:.6f}\n".encode() for a in t)
    accepted = refused = 0
    for k in range(150):
        rng = _rng(k)
        d = tmp_path / f"case{k}"
        d.mkdir()
        kind = int(rng.integers(3))
        if kind == 0:  # a leglib file: any change to its bytes must be refused
            body = _mutate_bytes(rng, csv) if rng.random() < 0.7 else csv
            meta = _mutate_sidecar(rng, side) if rng.random() < 0.5 else side
            p = d / good.name
            p.write_bytes(body)
            p.with_suffix(".json").write_text(json.dumps(meta))
            m, err = _read(p)
            if body != csv or meta != side:
                assert m is None or meta != side, "a changed leglib file was accepted"
            else:
                assert m is not None, err
        elif kind == 1:  # a thesis file (no sidecar)
            body = _mutate_bytes(rng, thesis_csv) if rng.random() < 0.8 else thesis_csv
            p = d / "20210701_123005_35.000;0.021;0.004_positions.csv"
            p.write_bytes(body)
            m, err = _read(p)
        else:  # a mutated name
            name = bytearray(good.name.encode())
            for _ in range(int(rng.integers(1, 3))):
                i = int(rng.integers(len(name) - 14))
                name[i] = int(rng.choice(list(b"0123456789._;-xe_")))
            try:
                p = d / name.decode()
            except UnicodeDecodeError:
                continue
            p.write_bytes(csv)
            p.with_suffix(".json").write_text(json.dumps(side))
            m, err = _read(p)
            if m is not None:  # accepted: the name's gains must be those of the sidecar
                assert parse_filename(p)[1] == tuple(side["gains"])
        if m is not None:
            _check_measurement(m)
            accepted += 1
        else:
            refused += 1
    assert accepted > 10 and refused > 50  # the fuzzer reaches both outcomes


# -- parameter files --------------------------------------------------------------------------

def _toml_literal(v) -> str:
    if v is None:
        return '""'
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, (int, str)):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_literal(x) for x in v) + "]"
    return "{ " + ", ".join(f"{k} = {_toml_literal(x)}" for k, x in v.items()) + " }"


def _mutate_toml(rng, text: str):
    """A mutated parameter file and whether the mutation must be refused."""
    lines = text.splitlines()
    entries = [i for i, ln in enumerate(lines) if re.match(r"^\w+ = \{ value = ", ln)]
    i = int(entries[int(rng.integers(len(entries)))])
    op = int(rng.integers(7))
    must_fail = True
    if op == 0:  # a typo in a field name
        key = lines[i].split(" ")[0]
        j = int(rng.integers(len(key)))
        lines[i] = key[:j] + "q" + key[j + 1:] + lines[i][len(key):]
        must_fail = "q" not in key[j] and key != key[:j] + "q" + key[j + 1:]
    elif op == 1:  # a weird value
        lines[i] = re.sub(r"value = [^,]+,", f"value = {_toml_literal(_weird_value(rng))},", lines[i])
        must_fail = None  # some weird values are valid numbers (0.5, 1, 0)
    elif op == 2:  # a unit of another dimension or no unit
        lines[i] = re.sub(r'unit = "[^"]*"', 'unit = "furlong"', lines[i])
    elif op == 3:  # an unknown section
        lines.insert(i, "[geometri]")
    elif op == 4:  # a line removed
        del lines[i]
    elif op == 5:  # an extra key in an entry
        lines[i] = lines[i].replace("value =", "vlaue = 1, value =")
    else:  # a value scaled by a random factor (may or may not violate a relation)
        m = re.search(r"value = ([-0-9.e]+)", lines[i])
        if m:
            lines[i] = lines[i].replace(m.group(0), f"value = {float(m.group(1)) * float(rng.choice([-1, 0.01, 3, 100]))!r}")
        must_fail = None
    return "\n".join(lines) + "\n", must_fail


def _leg_invariants(leg):
    for name, v in vars(leg).items():
        if isinstance(v, float):
            assert math.isfinite(v), name
    for i in (1, 2, 3, 4):
        assert 0 < getattr(leg, f"lc{i}") <= getattr(leg, f"l{i}")
    assert leg.m1 > 0 and leg.I1 > 0 and leg.gear_ratio > 0


@pytest.mark.parametrize("stem,loader,invariants", [
    ("leg_thesis", load_leg, _leg_invariants),
    ("plant_default", load_plant, lambda p: p.gap_min < p.gap_max and 0 <= p.usb_jitter <= 1),
])
def test_fuzz_parameter_files(tmp_path, stem, loader, invariants):
    text = (PARAMS_DIR / f"{stem}.toml").read_text()
    outcomes = {"ok": 0, "refused": 0}
    for k in range(60):
        rng = _rng(1000 + k)
        body, must_fail = _mutate_toml(rng, text)
        p = tmp_path / f"{stem}_{k}.toml"
        p.write_text(body)
        try:
            obj = loader(p)
        except ParameterError as exc:
            assert str(p) in str(exc) and len(str(exc)) < MAX_MESSAGE, str(exc)[:200]
            outcomes["refused"] += 1
            continue
        assert must_fail is not True, f"accepted a mutation that must be refused:\n{body}"
        assert invariants(obj) is not False
        outcomes["ok"] += 1
    assert outcomes["refused"] > 20


def test_fuzz_parameter_overrides():
    names = ["m3", "l1", "lc4", "g", "q1", "encoder_cpr", "direction", "c12", "gg", "Jd1"]
    for k in range(80):
        rng = _rng(2000 + k)
        kw = {names[int(rng.integers(len(names)))]: _weird_value(rng)}
        try:
            leg = load_leg("thesis", **kw)
        except ParameterError as exc:
            assert "leg_thesis.toml" in str(exc) and len(str(exc)) < MAX_MESSAGE
            continue
        _leg_invariants(leg)


# -- notebook parameters ------------------------------------------------------------------------

def _check_cells():
    out = {}
    for path in notebook_paths():
        nb = nbformat.read(str(path), as_version=4)
        code = [c.source for c in nb.cells if c.cell_type == "code"]
        check = code[1].split("odrv = lg.connect(")[0]  # 05 connects after its checks
        out[path.stem] = (code[0], check)
    return out


def _notebook_value(rng, value, name):
    r = rng.random()
    if r < 0.35:
        return _weird_value(rng)
    if r < 0.5 and name.endswith(("_dir", "_path")):
        return str(rng.choice(["/etc/hostname/sub", "", "/proc/1/nope/x", "relative/ok/dir"]))
    if isinstance(value, bool):
        return bool(rng.random() < 0.5)
    if isinstance(value, (int, float)):
        return type(value)(value * float(rng.choice([-1, 0, 0.5, 2, 1e6])))
    return value


def test_fuzz_notebook_parameters(tmp_path):
    cwd = os.getcwd()
    cells = _check_cells()
    try:
        for stem, (params_src, check_src) in cells.items():
            base = {}
            exec(params_src, base)
            names = [k for k in base if not k.startswith("__")]
            refused = 0
            for k in range(25):
                rng = _rng(3000 + k + 100 * int(stem[:2]))
                ns = dict(base)
                for name in rng.choice(names, size=int(rng.integers(1, 3)), replace=False):
                    ns[name] = _notebook_value(rng, base[name], name)
                for name in names:  # outputs of a case stay in its own directory
                    if name.endswith(("_dir", "_path")) and ns[name] == base[name]:
                        ns[name] = str(tmp_path / stem / name)
                if stem.startswith("03"):
                    ident = tmp_path / "identified.json"
                    ident.write_text("{}")
                    if ns["identified_path"] == str(tmp_path / stem / "identified_path"):
                        ns["identified_path"] = str(ident)
                try:
                    exec(check_src, ns)
                except (nbtools.NotebookParameterError, ParameterError) as exc:
                    assert len(str(exc)) < MAX_MESSAGE
                    refused += 1
                    continue
                except ValueError as exc:  # e.g. parse_poles: must name its input
                    assert "pole" in str(exc), exc
                    refused += 1
                    continue
                # accepted: the values the notebook goes on with are sane
                for name in names:
                    v = ns[name]
                    assert type(v) is type(base[name]) or (isinstance(base[name], float) and type(v) is int), (stem, name, v)
                    if isinstance(v, float):
                        assert math.isfinite(v), (stem, name)
                if stem.startswith("04"):
                    assert 0 < ns["pos_min"] <= ns["pos_max"] and 0 < ns["vel_min"] <= ns["vel_max"]
                if "seed" in ns:
                    assert 0 <= ns["seed"] < 2**32
                if "fit_start" in ns:
                    assert ns["fit_start"] <= ns["duration"] - 1.0
            assert refused > 5, stem
    finally:
        os.chdir(cwd)


# -- batch specs ------------------------------------------------------------------------------

def _spec_text(rng):
    def maybe(good, bad):
        return _pick(rng, good) if rng.random() < 0.75 else _pick(rng, bad)

    name = maybe(["run", "ok-name_1.2"], ["..", ".", "a/b", "x" * 65, "caf\u00e9", "", " sp", "-x"])
    nbs = maybe([["04_pid_sweeps"], ["01_derivation"], ["04_pid_sweeps", "05_validation"]],
                [["../x"], ["99_nope"], [], [3], ["04_pid_sweeps", "04_pid_sweeps"]])
    lines = [f"name = {json.dumps(name)}", f"notebooks = {json.dumps(nbs)}"]
    if rng.random() < 0.2:
        lines.append(f"{_pick(rng, ['notebook', 'nmae', 'grids', 'extra'])} = 1")
    params = {"smoke": maybe([True, False], ["no", 1])}
    if rng.random() < 0.5:
        params[_pick(rng, ["payload_mass", "seed", "grid_n", "pos_n", "plant"])] = _pick(rng, [0.5, 3, "no", True, -1, 6])
    grid = {}
    if rng.random() < 0.7:
        own = "torque_step" if nbs == ["01_derivation"] else "payload_mass"
        key = maybe([own], ["seed", "pos_n", "paylod_mass", "torque_step", "payload_mass"])
        grid[key] = maybe([[0.0, 0.05], [0.01]], [[1, 1], [], ["a", "b"]])
    lines.append("[parameters]" if rng.random() < 0.9 else "[parameter]")
    lines += [f"{k} = {json.dumps(v)}" for k, v in params.items()]
    if grid:
        lines.append("[grid]")
        lines += [f"{k} = {json.dumps(v)}" for k, v in grid.items()]
    return "\n".join(lines) + "\n"


def test_fuzz_batch_specs(tmp_path):
    accepted = 0
    reasons = []
    for k in range(100):
        rng = _rng(4000 + k)
        p = tmp_path / f"spec{k}.toml"
        text = _spec_text(rng)
        if rng.random() < 0.1:
            p.write_bytes(text.encode("latin-1", errors="replace") + b"\xe9")
        else:
            p.write_text(text)
        try:
            spec = batch.load_spec(p)
        except batch.SpecError as exc:
            assert str(p) in str(exc) and len(str(exc)) < MAX_MESSAGE, str(exc)[:200]
            reasons.append(str(exc))
            continue
        accepted += 1
        assert batch.NAME_RE.match(spec["name"]) and spec["name"] not in (".", "..")
        root = batch.batch_root(tmp_path / "out", spec)
        assert root.parent == (tmp_path / "out").resolve()
        for run in batch.runs_of(spec):
            assert "/" not in run["id"] and run["id"] not in (".", "..") and len(run["id"]) < 100
    assert accepted >= 5 and len(reasons) > 40, reasons


# -- interrupts between the files of a measurement -------------------------------------------

def test_fuzz_interrupts_then_resume(tmp_path, monkeypatch):
    dev = lg.connect("virtual", seed=3)
    lg.configure(dev)
    lg.calibrate(dev)
    real = {name: getattr(atomic, name) for name in ("_write_temp", "_commit")}
    for k in range(6):
        rng = _rng(5000 + k)
        d = tmp_path / f"sweep{k}"
        grid = [(float(p), float(v), 0.02) for p in rng.choice([20.0, 20.0004, 35.0], 2, replace=False)
                for v in rng.uniform(0.01, 0.05, 2)]
        for _ in range(int(rng.integers(1, 4))):  # several interrupted attempts
            stop_at, after = int(rng.integers(1, 4 * len(grid) + 3)), bool(rng.random() < 0.5)
            calls = {"n": 0}

            def wrap(name, stop_at=stop_at, after=after, calls=calls):
                def inner(*a, **kw):
                    calls["n"] += 1
                    if calls["n"] == stop_at and not after:
                        raise KeyboardInterrupt
                    out = real[name](*a, **kw)
                    if calls["n"] == stop_at and after:
                        raise KeyboardInterrupt
                    return out
                return inner

            for name in real:
                monkeypatch.setattr(atomic, name, wrap(name))
            try:
                lg.sweep(dev, grid, d, duration=0.2, chunk=int(rng.integers(1, 4)), progress=False)
            except KeyboardInterrupt:
                pass
            monkeypatch.undo()
        lg.sweep(dev, grid, d, duration=0.2, progress=False)
        gains = sorted(tuple(m.gains) for p in list_measurements(d) for m in read_file(p))
        assert gains == sorted(grid)  # every point once, complete and correct
        assert find_uncommitted(d) == []


# -- experiment arguments ------------------------------------------------------------------

_EXPERIMENT_VALUES = [True, False, np.bool_(True), math.nan, math.inf, -math.inf, -1.0, 0.0, 1e-9,
                      1e-4, 0.002, 0.4, 1.5, 10.0, 1e308, "0.4", None, [0.4]]


def test_fuzz_step_response_arguments():
    """Random, mostly bad arguments to :func:`leglib.odrive_io.step_response` on the twin:
    each call either raises a ValueError/TypeError naming the argument it refuses, or runs a
    step whose record is finite, sampled as asked and flagged completed only without a
    firmware error; the device is left IDLE and usable either way (seeded, bounded)."""
    rng = _rng(7001)
    names = ("pos_gain", "vel_gain", "vel_integrator_gain", "step", "duration", "sample_period", "vel_limit")
    good = {"pos_gain": 30.0, "vel_gain": 0.05, "vel_integrator_gain": 0.02, "step": 0.4, "duration": 0.3,
            "sample_period": 0.002, "vel_limit": None}
    ran = refused = 0
    with lg.connect("virtual", seed=7001) as dev:
        lg.configure(dev)
        lg.calibrate(dev)
        for _ in range(60):
            args = dict(good)
            bad = list(rng.choice(names, size=int(rng.integers(0, 3)), replace=False))
            for name in bad:
                args[name] = _EXPERIMENT_VALUES[int(rng.integers(len(_EXPERIMENT_VALUES)))]
            try:
                r = lg.step_response(dev, **args)
            except (ValueError, TypeError) as exc:
                refused += 1
                msg = str(exc)
                assert any(n in msg for n in bad), (args, msg)   # the refused argument is named
                assert len(msg) < 400
            else:
                ran += 1
                assert len(r.t) >= 2 and np.all(np.isfinite(r.q1)) and np.all(np.isfinite(r.q2))
                assert np.all(np.diff(r.t) > 0)
                if r.completed:
                    assert r.t[-1] <= args["duration"] + 1e-9
                    assert abs(np.median(np.diff(r.t)) - args["sample_period"]) < 0.5 * args["sample_period"] + dev.sim.twin.dt
                    assert not any_error(dev)   # completed only without a firmware error
            for a in (0, 1):
                assert int(dev.get(a, "current_state")) == AXIS_STATE_IDLE
            if any_error(dev):
                clear_errors(dev)
    assert ran >= 5 and refused >= 20, (ran, refused)
