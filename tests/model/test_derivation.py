"""The committed generated kernels are what the sympy derivation produces today."""

import pytest
import sympy as sp

from leglib.model import derivation

# one worker derives the models once (derive_* keep their result in the process: about 10 s
# of sympy) for all the tests of this file
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("derivation")]


def test_generated_module_is_up_to_date():
    assert derivation.GENERATED_PATH.read_text() == derivation.generate_source(), (
        "leglib/_generated.py is stale: run `python -m leglib.derivation`")


def test_parallelogram_matches_thesis_equations():
    d = derivation.derive_parallelogram()
    p = d.params
    q1, q2 = d.q
    d12 = (p["m3"] * p["l2"] * p["lc3"] - p["m4"] * p["l1"] * p["lc4"]) * sp.cos(q2 - q1)
    assert sp.simplify(d.D[0, 1] - d12) == 0                       # eq. 5.2
    g2 = p["g"] * sp.cos(q2) * (p["m2"] * p["lc2"] + p["m3"] * p["l2"] - p["m4"] * p["lc4"])
    assert sp.simplify(d.G[1] - g2) == 0                           # eq. 5.4 (minus sign)
    assert sp.simplify(d.D - d.D.T) == sp.zeros(2, 2)


def test_christoffel_form_is_skew_symmetric():
    # property of a correct Coriolis matrix: dD/dt - 2C is skew-symmetric
    for d in (derivation.derive_parallelogram(), derivation.derive_fivebar()):
        n = len(d.q)
        Ddot = sp.Matrix(n, n, lambda i, j: sum(d.D[i, j].diff(d.q[k]) * d.dq[k] for k in range(n)))
        N = Ddot - 2 * d.C
        assert sp.simplify(N + N.T) == sp.zeros(n, n)
