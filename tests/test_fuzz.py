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


# -- batch specs by value, parameters the batch sets, several problems at once ----------------

_GRID_VALUES = [0, 0.0, 0.5, 0.50, 1, 1.0, 0.25, 2, 0.75, True, "0", -0.0]


def test_fuzz_batch_spec_values_and_problems(tmp_path):
    """Grids of values equal or not by value, parameters the batch sets, and several typos at
    once: an accepted spec never runs one point twice nor takes a path the batch sets; a
    refused one is one SpecError naming the file and every field it refuses."""
    accepted = refused = 0
    for k in range(80):
        rng = _rng(9000 + k)
        values = [_pick(rng, _GRID_VALUES) for _ in range(int(rng.integers(1, 5)))]
        lines = ['name = "v"', 'notebooks = ["04_pid_sweeps"]', "[parameters]"]
        bad_fields = []
        if rng.random() < 0.25:
            key = _pick(rng, ["figures_dir", "metrics_path"])
            lines.append(f'{key} = "/tmp/{k}"')
            bad_fields.append(f"parameters.{key}")
        for _ in range(int(rng.integers(0, 3)) if rng.random() < 0.4 else 0):
            key = _pick(rng, ["smok", "sede", "pos_nn", "plnt"])
            if f"parameters.{key}" not in bad_fields:
                lines.append(f"{key} = 1")
                bad_fields.append(f"parameters.{key}")
        lines += ["[grid]", f"payload_mass = {json.dumps(values)}"]
        if rng.random() < 0.15:
            lines.append('metrics_path = ["/a", "/b"]')
            bad_fields.append("grid.metrics_path")
        p = tmp_path / f"v{k}.toml"
        p.write_text("\n".join(lines) + "\n")
        numeric = [v for v in values if isinstance(v, (int, float)) and not isinstance(v, bool)]
        valid_values = len(numeric) == len(values) and len(set(numeric)) == len(numeric)
        try:
            spec = batch.load_spec(p)
        except batch.SpecError as exc:
            refused += 1
            msg = str(exc)
            assert msg.startswith(str(p)) and len(msg) < MAX_MESSAGE + len(str(p)) and "\n" not in msg, msg
            for field in bad_fields:
                assert field in msg, (field, msg)
            if not valid_values:
                assert "grid.payload_mass" in msg, msg
            if len(bad_fields) + (not valid_values) > 1:
                assert " problems: " in msg, msg
            continue
        accepted += 1
        assert not bad_fields and valid_values, (lines, spec)
        runs = batch.runs_of(spec)
        assert len(runs) == len(values) and len({r["id"] for r in runs}) == len(runs)
        seen = [r["params"]["payload_mass"] for r in runs]
        assert all(a != b for i, a in enumerate(seen) for b in seen[i + 1:])  # no point twice, by value
        assert not any(key in r["params"] for r in runs for key in batch.BATCH_SET)
    assert accepted >= 10 and refused >= 30, (accepted, refused)


# -- command-line arguments --------------------------------------------------------------------

def test_fuzz_cli_arguments(tmp_path, monkeypatch, capsys):
    """Random, mostly bad command lines (payloads, plants, worker counts, schedulers, output
    directories, specs): each either reaches its command with values in range, or ends with
    exit code 2 and one error line on stderr; never a traceback. The commands' work is
    replaced by a record of the call (the arguments are what is fuzzed)."""
    from leglib.evaluation import robustness
    from leglib.notebook import cli
    from leglib.notebook import run as nbrun
    from leglib.params import plant_names

    calls = []
    monkeypatch.chdir(tmp_path)  # the commands' default --out are relative: here, not in the repository

    def fake_batch(spec, out, scheduler=None, **kw):
        if scheduler is not None:
            batch.connect_scheduler(scheduler, timeout=0.5)  # the real check; no address here answers
        calls.append(("batch", kw["workers"]))
        return {}

    monkeypatch.setattr(batch, "run_batch", fake_batch)
    monkeypatch.setattr(robustness, "run", lambda plants, payload, quick: calls.append(("rob", plants, payload)))
    monkeypatch.setattr(robustness, "write", lambda table, out: _written(out))
    monkeypatch.setattr(nbrun, "run_all", lambda out, smoke: calls.append(("run", out)) or [])
    good_spec = tmp_path / "good.toml"
    good_spec.write_text('name = "c"\nnotebooks = ["01_derivation"]\n[grid]\ngrid_n = [6, 7]\n')
    bad_spec = tmp_path / "bad.toml"
    bad_spec.write_text('name = "c"\nnotebook = ["01_derivation"]\n')
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    outs = [str(tmp_path / "out"), str(tmp_path / "o" / "deep"), str(blocker), str(blocker / "x")]
    payloads = ["0", "0.3", "5", "5.01", "-0.1", "1e9", "nan", "-inf", "heavy", "", "0x10"]
    workers = ["1", "2", "256", "0", "-1", "257", "2.5", "many"]
    schedulers = [None, "nonsense", "foo://h:1", "tcp://", "a b", "", "tcp://[::1", "tls:///x"]
    plants = plant_names() + ["nope", "", "../etc", "default "]
    ran = refused = 0
    for k in range(70):
        rng = _rng(9500 + k)
        cmd = _pick(rng, ["robustness", "batch", "run"])
        argv, ok = [cmd], True
        out = _pick(rng, outs)
        if rng.random() < 0.8:
            argv += ["--out", out]
            ok &= "a_file" not in out
        if cmd == "robustness":
            if rng.random() < 0.7:
                pay = _pick(rng, payloads)
                argv += ["--payload", pay]
                ok &= pay in ("0", "0.3", "5")
            if rng.random() < 0.5:
                names = [_pick(rng, plants) for _ in range(int(rng.integers(1, 3)))]
                argv += ["--plants", *names]
                ok &= all(n in plant_names() for n in names)
        elif cmd == "batch":
            spec = good_spec if rng.random() < 0.8 else bad_spec
            argv.append(str(spec))
            ok &= spec == good_spec
            if rng.random() < 0.5:
                w = _pick(rng, workers)
                argv += ["--workers", w]
                ok &= w in ("1", "2", "256")
            if rng.random() < 0.5:
                s = _pick(rng, schedulers)
                if s is not None:
                    argv += ["--scheduler", s]
                    ok = False
        elif rng.random() < 0.3:
            argv.append("--smoke")
        if rng.random() < 0.1:
            argv.append(_pick(rng, ["--bogus", "-x", "extra"]))
            ok = False
        before = len(calls)
        try:
            code = cli.main(argv)
        except SystemExit as exc:
            code = exc.code
        err = capsys.readouterr().err
        assert "Traceback" not in err, (argv, err)
        if ok:
            ran += 1
            assert code == 0 and len(calls) == before + 1, (argv, code, err)
            if calls[-1][0] == "rob":
                assert 0 <= calls[-1][2] <= cli.MAX_PAYLOAD
            if calls[-1][0] == "batch":
                assert 1 <= calls[-1][1] <= 256
        else:
            refused += 1
            assert code == 2, (argv, code, err)
            errors = [line for line in err.splitlines() if "error: " in line]
            assert len(errors) == 1 and len(errors[0]) < 400, (argv, err)
            assert not any(c[0] in ("rob", "run") for c in calls[before:]), argv  # nothing ran
    assert ran >= 10 and refused >= 25, (ran, refused)


def _written(out):
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "robustness.md").write_text("# table\n")
    return out / "robustness.md"
