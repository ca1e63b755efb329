"""Symbolic derivation of the leg's dynamics (Lagrange, sympy) and code generation.

Two models of the same leg:

(a) the thesis's model (chapter 5, Spong's five-bar parallelogram, eqs. 5.1-5.7):
    two coordinates q = (q1, q2); link 3 hangs from link 2 parallel to link 1, link 4 hangs
    from link 1 anti-parallel to link 2. Its inertia matrix, Coriolis terms and gravity
    follow from the Lagrangian directly.

(b) the exact coaxial five-bar: maximal coordinates theta = (q1, q2, phi3, phi4), the
    absolute angles of the four links, forming two open chains (link 1 + link 4 and
    link 2 + link 3) whose ends must meet at the foot: the loop-closure constraint
    Phi(theta) = l1 u(q1) + l4 u(phi4) - l2 u(q2) - l3 u(phi3) = 0, u(a) = (cos a, sin a).
    The Lagrangian of the open chains gives M(theta), the velocity-product terms h and the
    gravity vector; :mod:`leglib.model` reduces them onto q through the constraint.

:func:`generate_source` prints both as numba-compiled scalar functions; the result is
committed as ``leglib/_generated.py`` (regenerate with ``python -m leglib.model.derivation``;
``tests/test_derivation.py`` fails when it is stale). The numeric model and the twin's
compiled kernel both call those functions, so the two can never disagree.
"""

from __future__ import annotations

import hashlib
import os
import pickle
import tempfile
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import sympy as sp
from sympy.printing.pycode import PythonCodePrinter

from .param_names import PARAM_NAMES

GENERATED_PATH = Path(__file__).with_name("_generated.py")


@dataclass(frozen=True)
class Derivation:
    """Result of a Lagrange derivation.

    Attributes
    ----------
    q, dq, ddq : sympy column matrices of the coordinates and their derivatives
    D : inertia matrix (n x n)
    C : Coriolis/centrifugal matrix (Christoffel form, C(q, dq) dq is the velocity term)
    h : velocity-product vector C(q, dq) dq
    G : gravity vector dV/dq
    V : potential energy, T : kinetic energy
    Cd : viscous damping matrix (symbols c11.., only for the driven joints)
    constraint : loop-closure Phi(theta) (model b only, else None)
    """

    name: str
    q: sp.Matrix
    dq: sp.Matrix
    ddq: sp.Matrix
    D: sp.Matrix
    C: sp.Matrix
    h: sp.Matrix
    G: sp.Matrix
    T: sp.Expr
    V: sp.Expr
    Cd: sp.Matrix
    params: dict
    constraint: sp.Matrix | None = None

    def equations_of_motion(self, tau: sp.Matrix | None = None) -> sp.Matrix:
        """D(q) ddq + C(q, dq) dq + Cd dq + G(q) - tau (driven joints only get Cd, tau)."""
        n = len(self.q)
        tau = tau if tau is not None else sp.Matrix(sp.symbols(f"tau1:{n + 1}"))
        friction = sp.zeros(n, 1)
        friction[:2, 0] = self.Cd * self.dq[:2, 0]
        return self.D * self.ddq + self.h + friction + self.G - tau


def _symbols():
    p = {name: sp.Symbol(name, positive=True) for name in PARAM_NAMES}
    c = sp.Matrix(2, 2, sp.symbols("c11 c12 c21 c22", real=True))
    return p, c


def _u(a):
    return sp.Matrix([sp.cos(a), sp.sin(a)])


def _lagrange(name, q, positions, rotations, p, c, constraint=None) -> Derivation:
    """Lagrange's equations for bodies with COM ``positions`` (mass, r(q)) and
    ``rotations`` (inertia, angle(q)) -- all rigid-body terms, no constraint forces."""
    t = sp.Symbol("t")
    n = len(q)
    qt = [sp.Function(str(qi))(t) for qi in q]
    dq = sp.Matrix(sp.symbols(" ".join(f"d{qi}" for qi in q)))
    ddq = sp.Matrix(sp.symbols(" ".join(f"dd{qi}" for qi in q)))
    to_t = dict(zip(q, qt))
    T = 0
    V = 0
    for m, r in positions:
        rt = r.subs(to_t)
        v = rt.diff(t)
        T += sp.Rational(1, 2) * m * (v.T * v)[0]
        V += m * p["g"] * r[1]
    for inertia, angle in rotations:
        w = angle.subs(to_t).diff(t)
        T += sp.Rational(1, 2) * inertia * w ** 2
    # back from functions of t to plain symbols
    back = {}
    for i in range(n):
        back[qt[i].diff(t, 2)] = ddq[i]
    for i in range(n):
        back[qt[i].diff(t)] = dq[i]
    for i in range(n):
        back[qt[i]] = q[i]
    T = sp.simplify(T.subs(back))
    # D from the quadratic form T = 1/2 dq^T D dq
    D = sp.Matrix(n, n, lambda i, j: sp.simplify(sp.diff(T, dq[i], dq[j])))
    G = sp.Matrix([sp.simplify(sp.diff(V, qi)) for qi in q])
    # Christoffel symbols of the first kind: C[k, j] = sum_i c_ijk dq_i
    C = sp.zeros(n, n)
    for k in range(n):
        for j in range(n):
            C[k, j] = sp.simplify(sum(
                sp.Rational(1, 2) * (D[k, j].diff(q[i]) + D[k, i].diff(q[j]) - D[i, j].diff(q[k]))
                * dq[i] for i in range(n)))
    h = (C * dq).applyfunc(sp.simplify)
    return Derivation(name=name, q=sp.Matrix(q), dq=dq, ddq=ddq, D=D, C=C, h=h, G=G, T=T,
                      V=sp.simplify(V), Cd=c, params=p, constraint=constraint)


def cache_path(name: str) -> Path:
    """Where the derivation of model ``name`` is kept between processes: beside this file's
    bytecode, keyed by this file's content and sympy's version (a derivation is a function
    of the two), as Python keeps ``.pyc`` files."""
    key = hashlib.sha256(Path(__file__).read_bytes() + sp.__version__.encode()).hexdigest()[:16]
    return Path(__file__).with_name("__pycache__") / f"derivation-{name}-{key}.pickle"


def _kept(name: str, derive) -> Derivation:
    """``derive()``, or its result from an earlier process (:func:`cache_path`). sympy's
    simplification takes seconds a model (about 6 s for both on 2 cores), every notebook
    01 and every batch run of it paid that. A cache that cannot be read is derived again
    and rewritten; one that cannot be written (a read-only install) is left out."""
    path = cache_path(name)
    try:
        kept = pickle.loads(path.read_bytes())
        if isinstance(kept, Derivation) and kept.name == name:
            return kept
    except (OSError, EOFError, pickle.UnpicklingError, AttributeError, ImportError, TypeError, ValueError):
        pass
    d = derive()
    try:
        path.parent.mkdir(exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(pickle.dumps(d))
            os.replace(tmp, path)   # whole or not at all: readers never see a part
        finally:
            Path(tmp).unlink(missing_ok=True)
    except OSError:
        pass
    return d


@lru_cache(maxsize=None)
def derive_parallelogram() -> Derivation:
    """Model (a): the thesis's parallelogram five-bar (eqs. 5.1-5.7, Spong). Derived once
    for this file's content and sympy's version (:func:`cache_path`)."""
    return _kept("parallelogram", _derive_parallelogram)


@lru_cache(maxsize=None)
def derive_fivebar() -> Derivation:
    """Model (b): the exact coaxial five-bar in maximal coordinates (q1, q2, phi3, phi4).
    Derived once for this file's content and sympy's version (:func:`cache_path`)."""
    return _kept("fivebar", _derive_fivebar)


def _derive_parallelogram() -> Derivation:
    """Model (a): the thesis's parallelogram five-bar (eqs. 5.1-5.7, Spong)."""
    p, c = _symbols()
    q1, q2 = sp.symbols("q1 q2", real=True)
    r1 = p["lc1"] * _u(q1)
    r2 = p["lc2"] * _u(q2)
    r3 = p["l2"] * _u(q2) + p["lc3"] * _u(q1)
    r4 = p["l1"] * _u(q1) - p["lc4"] * _u(q2)
    positions = [(p["m1"], r1), (p["m2"], r2), (p["m3"], r3), (p["m4"], r4)]
    rotations = [(p["I1"] + p["Jd1"], q1), (p["I2"] + p["Jd2"], q2), (p["I3"], q1), (p["I4"], q2)]
    return _lagrange("parallelogram", [q1, q2], positions, rotations, p, c)


def _derive_fivebar() -> Derivation:
    """Model (b): the exact coaxial five-bar in maximal coordinates (q1, q2, phi3, phi4)."""
    p, c = _symbols()
    q1, q2, phi3, phi4 = sp.symbols("q1 q2 phi3 phi4", real=True)
    r1 = p["lc1"] * _u(q1)
    r2 = p["lc2"] * _u(q2)
    r3 = p["l2"] * _u(q2) + p["lc3"] * _u(phi3)
    r4 = p["l1"] * _u(q1) + p["lc4"] * _u(phi4)
    positions = [(p["m1"], r1), (p["m2"], r2), (p["m3"], r3), (p["m4"], r4)]
    rotations = [(p["I1"] + p["Jd1"], q1), (p["I2"] + p["Jd2"], q2),
                 (p["I3"], phi3), (p["I4"], phi4)]
    constraint = p["l1"] * _u(q1) + p["l4"] * _u(phi4) - p["l2"] * _u(q2) - p["l3"] * _u(phi3)
    return _lagrange("fivebar", [q1, q2, phi3, phi4], positions, rotations, p, c, constraint)


# ---------------------------------------------------------------------------------------
# Code generation
# ---------------------------------------------------------------------------------------

def _function_source(name: str, args: list[sp.Symbol], exprs: list[sp.Expr], doc: str,
                     inline: bool = False) -> str:
    """``inline``: numba inlines the function into its callers (a kernel's loop over legs
    that calls it can then vectorize)."""
    used = set().union(*(e.free_symbols for e in exprs))
    lines = ['@njit(cache=True, inline="always")' if inline else "@njit(cache=True)", f"def {name}({', '.join(str(a) for a in args)}, P):",
             f'    """{doc}"""']
    for i, pname in enumerate(PARAM_NAMES):
        if sp.Symbol(pname, positive=True) in used:
            lines.append(f"    {pname} = P[{i}]")
    replacements, reduced = sp.cse(exprs, symbols=sp.numbered_symbols("x"), optimizations="basic")
    printer = PythonCodePrinter({"standard": "python3",
                                                     "fully_qualified_modules": True})
    for sym, expr in replacements:
        lines.append(f"    {sym} = {printer.doprint(expr)}")
    # numba needs a homogeneous tuple: print constant entries as floats
    outs = ", ".join(repr(float(e)) if e.is_number else printer.doprint(e) for e in reduced)
    lines.append(f"    return ({outs},)")
    return "\n".join(lines) + "\n"


def _unit_symbols():
    """(c1, s1, c2, s2, c3, s3, c4, s4): cos and sin of q1, q2, phi3, phi4."""
    return sp.symbols("c1 s1 c2 s2 c3 s3 c4 s4", real=True)


def _in_unit_vectors(expr: sp.Expr, angles) -> sp.Expr:
    """``expr`` with every cos/sin of a sum of ``angles`` expanded and written in the
    angles' unit vectors (see :func:`_unit_symbols`)."""
    cs = _unit_symbols()
    rep = {}
    for a, c, s in zip(angles, cs[0::2], cs[1::2]):
        rep[sp.cos(a)] = c
        rep[sp.sin(a)] = s
    out = sp.expand_trig(expr).subs(rep)
    left = out.atoms(sp.sin, sp.cos)
    if left:
        raise ValueError(f"trigonometric terms left after the substitution: {left}")
    return out


def generate_source() -> str:
    """Python source of the numba functions for both models (see module docstring)."""
    a = derive_parallelogram()
    b = derive_fivebar()
    qa = list(a.q) + list(a.dq)
    qb = list(b.q) + list(b.dq)
    parts = [
        '"""Generated by leglib.model.derivation.generate_source(); do not edit.\n\n'
        "Regenerate with ``python -m leglib.model.derivation``. P is the parameter vector in the\n"
        'order of leglib.model.derivation.PARAM_NAMES (see leglib.model.terms.param_vector)."""\n',
        "import math\n\nfrom numba import njit\n\nfrom .. import _numba_gc, _numba_inline  # noqa: F401  (before any kernel compiles)\n",
        _function_source("parallelogram_terms", qa,
                         list(a.D) + list(a.h) + list(a.G),
                         "Model (a): D (4 entries, row-major), h = C(q, dq) dq (2), G (2)."),
        _function_source("parallelogram_energy", qa, [a.T, a.V],
                         "Model (a): kinetic and potential energy [J]."),
        _function_source("fivebar_terms", qb,
                         list(b.D) + list(b.h) + list(b.G),
                         "Model (b), maximal coordinates (q1, q2, phi3, phi4): "
                         "M (16, row-major), h (4), G (4)."),
        _function_source("fivebar_energy", qb, [b.T, b.V],
                         "Model (b): kinetic and potential energy [J]."),
        _function_source("fivebar_terms_cs", list(_unit_symbols()) + list(b.dq),
                         [_in_unit_vectors(e, b.q) for e in list(b.D) + list(b.h) + list(b.G)],
                         "Model (b) as ``fivebar_terms``, in the unit vectors (c, s) of "
                         "q1, q2, phi3, phi4 (no trigonometric call).", inline=True),
    ]
    return "\n\n".join(parts)


def write_generated(path: Path = GENERATED_PATH) -> Path:
    """Write :func:`generate_source` to ``path`` (atomically)."""
    tmp = path.with_suffix(".tmp")
    tmp.write_text(generate_source())
    tmp.replace(path)
    return path


if __name__ == "__main__":
    print(f"wrote {write_generated()}")
