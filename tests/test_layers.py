"""The layers of leglib, one direction only: a module imports only from its own layer or a
lower one, no module takes part in an import circle, and an import inside a function is
there for load time only and says why (``# load time: ...`` on its line).

The layers, bottom to top (docs: leglib/__init__.py, README's layout):
"""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent / "leglib"

LAYERS = [
    ("leglib._version", "leglib._numba_inline", "leglib._numba_gc", "leglib.errors", "leglib.checks", "leglib.kernelmath", "leglib.cores", "leglib.abort",
     "leglib.params", "leglib.units"),
    ("leglib.model",),
    ("leglib.plots",),
    ("leglib.twin",),
    ("leglib.device",),
    ("leglib.files",),
    ("leglib.experiments",),
    ("leglib.identify",),
    ("leglib.design",),
    ("leglib.thesis", "leglib.evaluation"),
    ("leglib.notebook",),
    ("leglib", "leglib.__main__", "leglib._compat"),   # the public face and the old paths, on top
]


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def layer_of(module: str) -> int:
    best, depth = None, -1
    for i, names in enumerate(LAYERS):
        for n in names:
            if (module == n or module.startswith(n + ".")) and n.count(".") > depth:
                best, depth = i, n.count(".")
    assert best is not None, f"{module} is in no layer: add it to LAYERS"
    return best


def _resolve(module: str, is_pkg: bool, node: ast.ImportFrom) -> list[str]:
    """The leglib modules an ``from ... import ...`` names (a name may be a submodule)."""
    if node.level:
        base = module.split(".") if is_pkg else module.split(".")[:-1]
        base = base[:len(base) - node.level + 1]
        target = ".".join(base + ([node.module] if node.module else []))
    else:
        target = node.module or ""
    if not target.startswith("leglib"):
        return []
    out = []
    for alias in node.names:
        sub = f"{target}.{alias.name}"
        out.append(sub if _exists(sub) else target)
    return out


def _exists(module: str) -> bool:
    p = ROOT.parent.joinpath(*module.split("."))
    return p.with_suffix(".py").exists() or (p / "__init__.py").exists()


def imports():
    """(module, imported module, line, at module level, the line's text) for every import
    of a leglib module anywhere in leglib."""
    out = []
    for path in sorted(ROOT.rglob("*.py")):
        mod = module_name(path)
        is_pkg = path.name == "__init__.py"
        text = path.read_text()
        lines = text.splitlines()
        tree = ast.parse(text)
        top = set(map(id, tree.body))
        for node in ast.walk(tree):
            targets = []
            if isinstance(node, ast.ImportFrom):
                targets = _resolve(mod, is_pkg, node)
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names if a.name.startswith("leglib")]
            for t in targets:
                out.append((mod, t, node.lineno, id(node) in top, lines[node.lineno - 1]))
    return out


def test_every_module_is_in_a_layer():
    for path in ROOT.rglob("*.py"):
        layer_of(module_name(path))


def test_no_import_from_a_higher_layer():
    bad = [f"{m}:{line} imports {t} (layer {layer_of(t)} above {layer_of(m)})"
           for m, t, line, _, _ in imports() if layer_of(t) > layer_of(m)]
    assert not bad, "\n".join(bad)


def test_no_import_circle():
    graph = {}
    for m, t, _, at_top, _ in imports():
        if at_top and t != m and not t.startswith(m + "."):
            graph.setdefault(m, set()).add(t)
    # a package's __init__ importing its own modules is not a circle with them
    circles = []
    state = {}

    def visit(node, stack):
        state[node] = 1
        for nxt in graph.get(node, ()):
            if state.get(nxt) == 1:
                circles.append(" -> ".join(stack[stack.index(nxt):] + [nxt]))
            elif state.get(nxt) is None:
                visit(nxt, stack + [nxt])
        state[node] = 2
    for node in sorted(graph):
        if state.get(node) is None:
            visit(node, [node])
    assert not circles, "\n".join(circles)


def test_deferred_imports_say_why():
    """An import inside a function is for load time only (numba, matplotlib, the odrive
    client, papermill, ...) and its line says so."""
    bad = []
    for path in sorted(ROOT.rglob("*.py")):
        lines = path.read_text().splitlines()
        tree = ast.parse("\n".join(lines))
        top = set(map(id, tree.body))
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)) and id(node) not in top:
                if isinstance(node, ast.ImportFrom) and node.module == "__future__":
                    continue
                text = " ".join(lines[node.lineno - 1:node.end_lineno])
                if "# load time:" not in text:
                    bad.append(f"{path.relative_to(ROOT.parent)}:{node.lineno}: {lines[node.lineno - 1].strip()}")
    assert not bad, "imports inside functions without a '# load time: ...' reason:\n" + "\n".join(bad)


@pytest.mark.parametrize("module", ["leglib", "leglib.device", "leglib.experiments"])
def test_a_real_leg_does_not_load_the_twin(module):
    """The real leg's code path imports neither the simulator nor numba's kernels."""
    import subprocess
    import sys
    code = (f"import sys, {module}; import leglib.experiments.step; "
            "bad = [m for m in sys.modules if m.startswith(('leglib.twin', 'leglib.device.virtual'))]; "
            "print(bad); sys.exit(1 if bad else 0)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
