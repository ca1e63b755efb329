"""The notebooks on the bench: their hardware is a parameter checked in the first cell, and
on the real leg (here: leglib's USB code path, the twin put behind ``odrive.find_any`` in the
notebook's kernel) a run longer than ``max_bench_minutes`` is refused before anything moves,
with its estimate; allowed, it runs."""

import json
import re

import nbformat
import pytest

from leglib.notebook.run import execute, notebook_paths

NOTEBOOKS = notebook_paths()
NB05 = NOTEBOOKS[4]

# run by the notebook's kernel at its start (IPython's startup files): the virtual board of
# seed 26 answers odrive.find_any, as a real ODrive would on USB
STARTUP = """\
import functools

import odrive

from leglib.device.virtual import find_any

odrive.find_any = functools.partial(find_any, seed=26)
"""


@pytest.fixture
def usb_kernel(tmp_path, monkeypatch):
    """Kernels started from now on find the twin behind ``odrive.find_any``; zeros of real
    boards are kept under tmp_path."""
    startup = tmp_path / "ipython" / "profile_default" / "startup"
    startup.mkdir(parents=True)
    (startup / "00-twin-behind-find-any.py").write_text(STARTUP)
    monkeypatch.setenv("IPYTHONDIR", str(tmp_path / "ipython"))
    monkeypatch.setenv("LEGLIB_STATE_DIR", str(tmp_path / "state"))
    return tmp_path


def _failed_cell(out_dir, path):
    nb = nbformat.read(str(out_dir / path.name), as_version=4)
    code = [c for c in nb.cells if c.cell_type == "code"]
    failed = [i for i, c in enumerate(code) if any(o.get("output_type") == "error" for o in c.outputs)]
    return failed[0], code


@pytest.mark.notebook
@pytest.mark.parametrize("index, params, message", [
    (1, {"odrive_config": "nope"}, "parameter 'odrive_config' = 'nope': "),
    (3, {"leg_name": "nope"}, "parameter 'leg_name' = 'nope': "),
    (3, {"motor_name": "nope"}, "parameter 'motor_name' = 'nope': "),
    (4, {"max_bench_minutes": 0.0}, "parameter 'max_bench_minutes' must be >= 0.1"),
], ids=["odrive_config", "leg_name", "motor_name", "max_bench_minutes"])
def test_hardware_parameters_are_checked_in_the_first_cell(tmp_path, index, params, message):
    import papermill as pm
    with pytest.raises(pm.PapermillExecutionError) as err:
        execute(NOTEBOOKS[index], tmp_path, {"smoke": True, **params}, html=False)
    assert message in str(err.value)
    if "nope" in message:
        assert "no parameter set named 'nope'" in str(err.value)
    first, code = _failed_cell(tmp_path, NOTEBOOKS[index])
    assert first <= 2 and all(c.execution_count is None for c in code[first + 1:])


@pytest.mark.notebook
@pytest.mark.parametrize("smoke, limit, estimate", [
    (False, 5.0, r"a sweep of 400 steps"),    # the thesis grid, about 24 minutes
    (True, 1.0, r"a sweep of 32 steps"),      # the smoke grid, 2 x 4 x 4
], ids=["thesis grid", "smoke grid"])
def test_05_with_an_empty_sweep_dir_on_the_leg_is_refused_with_its_estimate(usb_kernel, smoke, limit, estimate):
    import papermill as pm
    out, sweep = usb_kernel / "out", usb_kernel / "sweep"
    with pytest.raises(pm.PapermillExecutionError) as err:
        execute(NB05, out, {"backend": "usb", "smoke": smoke, "sweep_dir": str(sweep), "max_bench_minutes": limit,
                            "processed_dir": str(usb_kernel / "processed")}, html=False)
    text = re.sub(r"\x1b\[[0-9;]*m", "", str(err.value)).strip().splitlines()[-1]   # the error's own line
    assert text.startswith("BenchLimitError: this run (") and estimate in text
    assert f"more than max_bench_minutes = {limit:g} min allows: set max_bench_minutes to at least" in text
    minutes = float(re.search(r"takes about ([\d.]+) min on the leg", text).group(1))
    assert (minutes > 24 if not smoke else 2 < minutes < 10)
    # refused in its first cells, before anything moved or was written
    first, code = _failed_cell(out, NB05)
    assert first <= 2 and all(c.execution_count is None for c in code[first + 1:])
    assert not sweep.exists() or not any(sweep.iterdir())
    assert "rehearsal" not in text                     # said as the leg's, not the twin's


@pytest.mark.notebook
def test_05_with_an_empty_sweep_dir_on_the_leg_runs_when_allowed(usb_kernel):
    out, sweep = usb_kernel / "out", usb_kernel / "sweep"
    execute(NB05, out, {"backend": "usb", "smoke": True, "sweep_dir": str(sweep), "max_bench_minutes": 10.0,
                        "processed_dir": str(usb_kernel / "processed")}, html=False)
    m = json.loads((out / "metrics" / f"{NB05.stem}.json").read_text())
    b = m["bench"]
    assert m["backend"] == "usb" and b["backend"] == "usb"
    # swept here, a file per point as on a real leg; configured and calibrated once
    assert len(list(sweep.glob("*_positions.csv"))) == 32 and b["counts"]["sweep"] == 1
    assert b["counts"]["reboot"] == 1 and b["counts"]["calibration"] == 2
    assert b["counts"]["step"] >= 32 + 2 + 5
    # the estimate beforehand is an upper bound (it counts every step that may run)
    assert b["planned_s"] >= b["bench_s"] > 0.5 * b["planned_s"]
    assert b["limit_s"] == 600.0
