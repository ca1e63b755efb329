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
    ("04", {"pos_min": 60.0, "pos_max": 20.0}, "parameters pos_min = 60.0, pos_max = 20.0, pos_n = 4: need pos_min < pos_max"),
    ("04", {"vint_min": 0.0}, "parameter 'vint_min' must be >= 1e-09"),
    ("04", {"pos_max": 500.0}, "parameter 'pos_max' must be <= 200.0"),
    ("04", {"smoke": "no"}, "parameter 'smoke' must be bool, got 'no'"),
    ("04", {"seed": -5}, "parameter 'seed' must be >= 0"),
    ("02", {"seed": 2**40}, "parameter 'seed' must be <= 4294967295"),
    ("02", {"smoke": True, "fit_start": 6.5}, "parameters fit_start = 6.5, duration = 5.0: need fit_start <= duration - 1.0"),
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


def test_check_parameters_reads_the_annotations_and_states_only_ranges_and_relations(tmp_path):
    ns = {}
    exec("n: int = 3\nx: float = 1\nname: str = 'a'\nsmoke: bool = True\nout_dir: str = ''\n"
         "in_file: str = ''\n", ns)
    ns["out_dir"] = str(tmp_path / "out")
    nbtools.check_parameters(ns, ranges={"n": (1, 5)}, smoke={"n": 1}, relations=["n == 1"])
    assert ns["n"] == 1                           # shortened before the relations
    for bad, message in (({"x": True}, "parameter 'x' must be float, got True"),
                         ({"n": 7}, "parameter 'n' must be <= 5"),
                         ({"in_file": str(tmp_path / "none")}, "does not exist"),
                         ({"name": 3}, "parameter 'name' must be str")):
        trial = {**ns, **bad, "smoke": False}
        with pytest.raises(nbtools.NotebookParameterError, match=message):
            nbtools.check_parameters(trial, ranges={"n": (1, 5)})
    with pytest.raises(nbtools.NotebookParameterError, match="'nmax', which is no parameter"):
        nbtools.check_parameters(ns, ranges={"nmax": (1, 2)})
    with pytest.raises(nbtools.NotebookParameterError, match="no annotated parameters"):
        nbtools.check_parameters({"n": 1})


def test_every_notebook_checks_its_parameters_in_one_call():
    for stem, path in BOOKS.items():
        nb = nbformat.read(str(path), as_version=4)
        code = [c.source for c in nb.cells if c.cell_type == "code"]
        assert code[1].count("check_parameters(globals()") == 1, stem
        assert "require(" not in "\n".join(code), stem
