"""numba's inliner with leglib._numba_inline: installed wherever a kernel compiles, and the
machine code it gives the same as numba's own inliner's."""

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent / "leglib"

# nested inline="always" functions with loops and branches (a callee of several blocks,
# inlined into a function that is itself inlined), compiled with numba's inliner ("stock")
# or with the linear copy; prints the kernel's LLVM IR and how many Vars the inliner copied
SCRIPT = """
import sys
from numba.core import inline_closurecall as ic, ir
import leglib._numba_inline as fix
if sys.argv[1] == "stock":
    ic.InlineWorker.inline_ir = ic.InlineWorker.inline_ir.__wrapped__
assert fix.installed() == (sys.argv[1] == "linear")
copies = [0]
var_deepcopy = ir.Var.__deepcopy__
def counted(self, memo):
    copies[0] += 1
    return var_deepcopy(self, memo)
ir.Var.__deepcopy__ = counted

import numpy as np
from numba import njit

@njit(inline="always")
def clamp(x, lo, hi):
    if x < lo:
        return lo
    if x > hi:
        return hi
    return x

@njit(inline="always")
def stage(a, i, gain):
    acc = 0.0
    for k in range(a.shape[0]):
        v = a[k] * gain
        if k == i:
            v = clamp(v, -1.0, 1.0)
        elif v > 2.0:
            v -= 1.0
        acc += v
    a[i] = clamp(acc, -5.0, 5.0)
    return acc

@njit(inline="always")
def tick(a, n):
    s = 0.0
    for i in range(n):
        s += stage(a, i % a.shape[0], 0.5)
        if s > 3.0:
            s = clamp(s, 0.0, 3.0)
    return s

@njit
def kernel(a, n):
    return tick(a, n) + stage(a, 0, 2.0)

kernel(np.linspace(-1.0, 1.0, 8), 5)
print(copies[0])
print(kernel.inspect_llvm(kernel.signatures[0]))
"""


def _compile(mode: str) -> tuple[int, str]:
    env = {**os.environ, "PYTHONHASHSEED": "0"}
    proc = subprocess.run([sys.executable, "-c", SCRIPT, mode], capture_output=True, text=True, env=env,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    count, llvm = proc.stdout.split("\n", 1)
    return int(count), llvm


def test_the_linear_copy_gives_the_same_llvm_ir_with_fewer_copies():
    stock_copies, stock = _compile("stock")
    linear_copies, linear = _compile("linear")
    assert "define" in stock and linear == stock
    assert linear_copies < stock_copies / 2, (linear_copies, stock_copies)


def test_installed_on_the_pinned_numba():
    """A numba whose inliner no longer copies block by block leaves the fix out (and compiles
    as slowly as before): this says so, so that the fix is measured again or removed."""
    import leglib.twin.kernel  # noqa: F401
    from leglib import _numba_inline
    assert _numba_inline.installed()


def _imports(tree: ast.Module) -> list[tuple[int, str, list[str]]]:
    out = []
    for node in tree.body:
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name, []) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            out.append((node.lineno, "." * node.level + (node.module or ""), [a.name for a in node.names]))
    return out


@pytest.mark.parametrize("fix", ["_numba_inline", "_numba_gc"])   # the second: tests/test_numba_gc.py
def test_every_module_that_imports_numba_imports_the_fix(fix):
    kernels = []
    for path in sorted(p for p in ROOT.rglob("*.py") if p.name not in ("_numba_inline.py", "_numba_gc.py")):
        imports = _imports(ast.parse(path.read_text()))
        if any(name == "numba" or name.startswith("numba.") for _, name, _ in imports):
            kernels.append(path.relative_to(ROOT.parent))
            assert any(fix in names or name.endswith(fix) for _, name, names in imports), \
                f"{kernels[-1]} imports numba at module level but not leglib.{fix}"
    assert Path("leglib/twin/kernel.py") in kernels and len(kernels) >= 10, kernels
