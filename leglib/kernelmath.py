"""Elementary functions for the twin's tick loop (:mod:`leglib.twin`).

In the tick loop a library call (``math.sin``, ``math.tanh``) costs its own time plus the
registers it makes the loop spill, and it sits on the loop's critical path (the next tick
needs the joint angles this one produces). These are inlined instead, with fused
multiply-adds (``llvm.fma``: one rounding, the same result on every machine) and short
dependency chains, and without branches (selects instead), so that a loop over legs that
calls them vectorizes. Each is within a few ulp of the math module's (tests/test_twin.py).
"""

from __future__ import annotations

import math

from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

from . import _numba_gc, _numba_inline  # noqa: F401  (before any kernel compiles)


@intrinsic
def fma(typingctx, a, b, c):
    """a * b + c with one rounding (llvm.fma.f64)."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        d = ir.DoubleType()
        fn = builder.module.declare_intrinsic("llvm.fma", [d], ir.FunctionType(d, [d, d, d]))
        return builder.call(fn, [context.cast(builder, v, t, types.float64)
                                 for v, t in zip(args, signature.args)])
    return sig, codegen


@intrinsic
def select(typingctx, cond, a, b):
    """``a if cond else b`` as one select instruction, both operands already evaluated: no
    branch for the compiler to keep (a conditional expression becomes control flow, and
    several of them on one condition are merged into regions a vectorizer cannot use)."""
    ty = types.unliteral(typingctx.unify_types(types.unliteral(a), types.unliteral(b)))
    if ty is None:
        return None
    sig = ty(types.boolean, a, b)

    def codegen(context, builder, signature, args):
        c = context.cast(builder, args[0], signature.args[0], types.boolean)
        x = context.cast(builder, args[1], signature.args[1], ty)
        y = context.cast(builder, args[2], signature.args[2], ty)
        return builder.select(c, x, y)
    return sig, codegen


@njit(cache=True, inline="always")
def py_max(a, b):
    """max(a, b) as Python and numba define it (``b`` when ``b > a``, else ``a``: NaN and
    signed zeros alike), as one select (numba's own max keeps some loops from vectorizing)."""
    return select(b > a, b, a)


@njit(cache=True, inline="always")
def py_min(a, b):
    """min(a, b) as Python and numba define it (``b`` when ``b < a``, else ``a``)."""
    return select(b < a, b, a)


@intrinsic
def pow2(typingctx, n):
    """2.0 ** n for an integral float ``n`` in [-1022, 1023], its exponent bits set directly
    (no table: a table lookup keeps a loop over legs from vectorizing)."""
    sig = types.float64(types.float64)

    def codegen(context, builder, signature, args):
        i64 = ir.IntType(64)
        k = builder.fptosi(args[0], i64)
        bits = builder.shl(builder.add(k, ir.Constant(i64, 1023)), ir.Constant(i64, 52))
        return builder.bitcast(bits, ir.DoubleType())
    return sig, codegen


# sin, cos: fdlibm's reduction by pi/2 (in two parts, exact for |x| < 1e6) and its kernels,
# the polynomials evaluated by Estrin's scheme
_INVPIO2 = 6.36619772367581382433e-01
_PIO2_1 = 1.57079632673412561417e+00    # the first 33 bits of pi/2
_PIO2_1T = 6.07710050650619224932e-11   # pi/2 - _PIO2_1
_S1, _S2, _S3, _S4, _S5, _S6 = (-1.66666666666666324348e-01, 8.33333333332248946124e-03,
                                -1.98412698298579493134e-04, 2.75573137070700676789e-06,
                                -2.50507602534068634195e-08, 1.58969099521155010221e-10)
_C1, _C2, _C3, _C4, _C5, _C6 = (4.16666666666666019037e-02, -1.38888888888741095749e-03,
                                2.48015872894767294178e-05, -2.75573143513906633035e-07,
                                2.08757232129817482790e-09, -1.13596475577881948265e-11)


@njit(cache=True, inline="always")
def sincos(x):
    """(sin x, cos x) for |x| < 1e6 (a joint angle)."""
    n = math.floor(fma(x, _INVPIO2, 0.5))
    y = fma(-n, _PIO2_1T, fma(-n, _PIO2_1, x))   # in [-pi/4, pi/4]; the inner one is exact
    z = y * y
    z2 = z * z
    z4 = z2 * z2
    ps = fma(z4, fma(z, _S6, _S5), fma(z2, fma(z, _S4, _S3), fma(z, _S2, _S1)))
    pc = fma(z4, fma(z, _C6, _C5), fma(z2, fma(z, _C4, _C3), fma(z, _C2, _C1)))
    s = fma(y * z, ps, y)
    hz = 0.5 * z
    w = 1.0 - hz
    c = w + fma(z2, pc, (1.0 - w) - hz)
    # the quadrant by selects, not branches: a loop over legs calling this vectorizes
    quadrant = n - 4.0 * math.floor(0.25 * n)   # 0, 1, 2 or 3, exactly
    odd = quadrant == 1.0 or quadrant == 3.0
    so = c if odd else s
    co = s if odd else c
    so = -so if quadrant >= 2.0 else so
    co = -co if (quadrant == 1.0 or quadrant == 2.0) else co
    return so, co


# exp: Cephes' Pade form (exp below, and tanh's e = exp(2|x|)); tanh: Cephes' rational form
# below 0.625, else (e - 1) / (e + 1), e the Pade form times a power of two (one division
# either way)
_LOG2E = 1.4426950408889634073599
_LN2_HI, _LN2_LO = 6.93145751953125e-1, 1.42860682030941723212e-6
_EP0, _EP1, _EP2 = 1.26177193074810590878e-4, 3.02994407707441961300e-2, 9.99999999999999999910e-1
_EQ0, _EQ1, _EQ2, _EQ3 = (3.00198505138664455042e-6, 2.52448340349684104192e-3,
                          2.27265548208155028766e-1, 2.00000000000000000009e0)
_TP0, _TP1, _TP2 = -9.64399179425052238628e-1, -9.92877231001918586564e1, -1.61468768441708447952e3
_TQ0, _TQ1, _TQ2 = 1.12811678491632931402e2, 2.23548839060100448583e3, 4.84406305325125486048e3


@njit(cache=True, inline="always")
def _exp_pade(x):
    """Cephes' exp kernel: (n, p, q) with exp(x) = 2^n (q + p) / (q - p), n = round(x / ln2)
    (an integral float), p, q its Pade form at r = x - n ln2, |r| <= ln2 / 2 (x finite)."""
    n = math.floor(fma(x, _LOG2E, 0.5))
    r = fma(-n, _LN2_LO, fma(-n, _LN2_HI, x))
    rr = r * r
    p = r * fma(fma(_EP0, rr, _EP1), rr, _EP2)
    q = fma(fma(fma(_EQ0, rr, _EQ1), rr, _EQ2), rr, _EQ3)
    return n, p, q


# exp: 0 below _EXP_LO (math.exp's result rounds to 0 there), inf above _EXP_HI (overflow)
_EXP_LO, _EXP_HI = -745.2, 709.782712893384


@njit(cache=True, inline="always")
def exp(x):
    """exp x as Cephes computes it, 1 + 2 p / (q - p) times 2^n (:func:`_exp_pade`), over the
    whole range: 0 below -745.2, inf above the largest finite result, NaN for NaN; results
    below 2^-1022 rounded once into the subnormals (2^n as two normal factors)."""
    xc = select(x > _EXP_HI, _EXP_HI, x)
    xc = select(xc < _EXP_LO, _EXP_LO, xc)   # NaN stays NaN here ...
    xc = select(xc == xc, xc, 0.0)           # ... and the kernel sees 0 (n must be a number)
    n, p, q = _exp_pade(xc)
    e = 1.0 + 2.0 * (p / (q - p))
    h = math.floor(0.5 * n)                  # n in [-1075, 1024]: h, n - h in [-538, 512]
    y = (e * pow2(h)) * pow2(n - h)
    return select(x > _EXP_HI, math.inf, select(x < _EXP_LO, 0.0, select(x == x, y, x)))


@njit(cache=True, inline="always")
def tanh(x):
    """tanh x (+-1 exactly beyond |x| = 20, as math.tanh). Both forms are evaluated and one
    selected (no branch: a loop over legs calling this vectorizes)."""
    a = abs(x)
    z = x * x
    num = fma(fma(_TP0, z, _TP1), z, _TP2)
    den = fma(fma(z + _TQ0, z, _TQ1), z, _TQ2)
    small = fma(x * z, num / den, x)
    # exp(2a) = 2^n (q + p) / (q - p), n in [0, 58] (a clamped to 20, NaN too)
    ac = a if a <= 20.0 else 20.0
    n, p, q = _exp_pade(2.0 * ac)
    e = (q + p) * pow2(n)
    t = (e - (q - p)) / (e + (q - p))
    mid = t if x > 0.0 else -t
    big = 1.0 if x > 0.0 else (-1.0 if x < 0.0 else x)   # x itself: NaN
    return small if a < 0.625 else (mid if a <= 20.0 else big)
