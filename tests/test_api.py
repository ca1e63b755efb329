"""The public face, ``import leglib as lg``: a curated set of names loaded on first use, each
documented in numpydoc (in the spirit of python-control's docstring test): every argument
described, what it returns, and every leglib error it raises itself."""

import ast
import inspect
import re
import subprocess
import sys
import textwrap

import pytest

import leglib as lg
from leglib import errors

API = sorted(lg._API)


def test_the_api_is_curated_and_complete():
    assert 20 <= len(API) <= 35
    assert set(API) <= set(dir(lg)) and set(lg.__all__) == {"__version__", *API}
    for name in API:
        assert getattr(lg, name) is getattr(__import__(lg._API[name][0], fromlist=["x"]), lg._API[name][1])


def test_importing_leglib_loads_nothing_heavy():
    code = ("import sys, leglib; heavy = [m for m in ('numba', 'scipy', 'matplotlib', 'control', 'odrive') "
            "if m in sys.modules]; print(heavy); sys.exit(1 if heavy else 0)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr


def test_an_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'nonsense'"):
        lg.nonsense


def test_every_error_is_a_leglib_error_and_its_builtin():
    for name in errors.__all__:
        cls = getattr(errors, name)
        assert issubclass(cls, errors.LeglibError), name
    assert issubclass(errors.MeasurementError, ValueError) and issubclass(errors.ExperimentError, RuntimeError)
    assert issubclass(errors.DeviceLostError, ConnectionError)
    from leglib.device.virtual.wire import VirtualDeviceLost
    assert issubclass(VirtualDeviceLost, errors.DeviceLostError)


def _sections(doc: str) -> dict:
    out, name = {}, None
    lines = doc.splitlines()
    for i, line in enumerate(lines):
        if i + 1 < len(lines) and re.fullmatch(r"-{3,}", lines[i + 1].strip()) and line.strip():
            name = line.strip()
            out[name] = []
        elif name and not re.fullmatch(r"-{3,}", line.strip()):
            out[name].append(line)
    return {k: "\n".join(v) for k, v in out.items()}


def _documented(section: str) -> set:
    names = set()
    for line in section.splitlines():
        m = re.match(r"^(\*{0,2}[A-Za-z_][\w]*(?:\s*,\s*\*{0,2}[A-Za-z_]\w*)*)\s*(:|$)", line)
        if m and not line.startswith(" "):
            names.update(n.strip().lstrip("*") for n in m.group(1).split(","))
    return names


def _raised(func) -> set:
    """leglib error classes a function raises itself (``raise X(...)`` in its own body)."""
    try:
        src = textwrap.dedent(inspect.getsource(func))
    except (OSError, TypeError):
        return set()
    out = set()
    for node in ast.walk(ast.parse(src)):
        if isinstance(node, ast.Raise) and node.exc is not None:
            exc = node.exc.func if isinstance(node.exc, ast.Call) else node.exc
            if isinstance(exc, ast.Name) and exc.id in errors.__all__:
                out.add(exc.id)
    return out


@pytest.mark.parametrize("name", API)
def test_every_public_name_is_documented(name):
    obj = getattr(lg, name)
    doc = inspect.getdoc(obj) or ""
    assert doc, f"lg.{name} has no docstring"
    if inspect.isclass(obj):
        if issubclass(obj, Exception):
            return
        assert {"Parameters", "Attributes"} & set(_sections(doc)), f"lg.{name}: no Parameters or Attributes"
        func = obj.__init__
        doc = doc if "Parameters" in _sections(doc) else (inspect.getdoc(func) or "")
    else:
        func = obj
    sections = _sections(doc)
    params = [p for p in inspect.signature(func).parameters.values() if p.name != "self"]
    if params and not inspect.isclass(obj) or "Parameters" in sections:
        assert "Parameters" in sections, f"lg.{name}: no Parameters section"
        missing = {p.name for p in params} - _documented(sections["Parameters"])
        assert not missing, f"lg.{name}: parameters not documented: {sorted(missing)}"
    if not inspect.isclass(obj):
        ret = inspect.signature(func).return_annotation
        if ret not in (None, "None", inspect.Signature.empty) or any(
                isinstance(n, ast.Return) and n.value is not None
                for n in ast.walk(ast.parse(textwrap.dedent(inspect.getsource(func))))):
            assert "Returns" in sections, f"lg.{name}: no Returns section"
    raised = _raised(func)
    if raised:
        assert "Raises" in sections, f"lg.{name} raises {sorted(raised)}: no Raises section"
        missing = {r for r in raised if r not in sections["Raises"]}
        assert not missing, f"lg.{name}: raises {sorted(missing)} without saying so"
