"""Every notebook's first cell checks every parameter before any experiment runs."""

import os

import nbformat
import pytest

from leglib.notebook import setup as nbtools
from leglib.notebook.run import notebook_paths

BOOKS = {p.stem[:2]: p for p in notebook_paths()}


def _check_cell(stem, tmp_path, **params):
    nb = nbformat.read(str(BOOKS[stem]), as_version=4)
    code = [c.source for c in nb.cells if c.cell_type == "code"]
    ns = {}
    exec(code[0], ns)
    for k in list(ns):
        if k.endswith(("_dir", "_path")) and k != "identified_path":
            ns[k] = str(tmp_path / k)
    ns.update(params)
    cwd = os.getcwd()
    try:
        exec(code[1].split("odrv = io.connect(")[0], ns)  # 05 connects after its checks
    finally:
        os.chdir(cwd)
    return ns


@pytest.mark.parametrize("stem,params,message", [
    ("04", {"pos_min": 60.0, "pos_max": 20.0}, "parameter 'pos_min' (60.0) must be below 'pos_max' (20.0)"),
    ("04", {"vint_min": 0.0}, "parameter 'vint_min' must be >= 1e-09"),
    ("04", {"pos_max": 500.0}, "parameter 'pos_max' must be <= 200.0"),
    ("04", {"smoke": "no"}, "parameter 'smoke' must be bool, got 'no'"),
    ("04", {"seed": -5}, "parameter 'seed' must be >= 0"),
    ("02", {"seed": 2**40}, "parameter 'seed' must be <= 4294967295"),
    ("02", {"smoke": True, "fit_start": 6.5}, "parameter 'fit_start' must be <= 4.0"),
    ("04", {"sweep_dir": "/etc/hostname/sweep"}, "parameter 'sweep_dir': /etc/hostname/sweep cannot be created"),
    ("01", {"metrics_path": "/"}, "parameter 'metrics_path': / is a directory"),
    ("03", {"identified_path": "/nonexistent/friction.json"}, "parameter 'identified_path': /nonexistent/friction.json does not exist"),
    ("05", {"figures_dir": "/etc/hostname"}, "parameter 'figures_dir': /etc/hostname exists and is not a directory"),
    ("05", {"plant": 3}, "parameter 'plant' must be str"),
])
def test_bad_parameters_stop_the_check_cell(tmp_path, stem, params, message):
    with pytest.raises(nbtools.NotebookParameterError) as err:
        _check_cell(stem, tmp_path, **params)
    assert message in str(err.value)


def test_good_parameters_pass_and_nothing_is_created(tmp_path):
    ns = _check_cell("04", tmp_path, smoke=True)
    assert len(ns["grid"]) == 32
    assert not (tmp_path / "sweep_dir").exists()  # checked, not created


def test_require_helpers(tmp_path):
    nbtools.require_order("a", 1.0, "b", 1.0, allow_equal=True)
    with pytest.raises(nbtools.NotebookParameterError, match="must be below"):
        nbtools.require_order("a", 1.0, "b", 1.0)
    f = tmp_path / "file"
    f.write_text("x")
    assert nbtools.require_readable_file("p", str(f)) == f
    with pytest.raises(nbtools.NotebookParameterError, match="is not a regular file"):
        nbtools.require_readable_file("p", str(tmp_path))
    assert nbtools.require_writable_dir("d", str(tmp_path / "new" / "deeper")) == tmp_path / "new" / "deeper"
    with pytest.raises(nbtools.NotebookParameterError, match="must be a directory path"):
        nbtools.require_writable_dir("d", "  ")
