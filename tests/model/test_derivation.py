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


def test_a_derivation_is_kept_between_processes_and_a_bad_copy_derived_again(tmp_path, monkeypatch):
    """derive_* keep their result beside the bytecode, keyed by the derivation's source and
    sympy's version; a later process reads it back whole (every field the same
    expression); a copy that cannot be read is derived again and rewritten."""
    fresh = derivation.derive_parallelogram()
    path = tmp_path / "__pycache__" / "derivation-parallelogram-key.pickle"
    monkeypatch.setattr(derivation, "cache_path", lambda name: path)
    calls = []

    def derive():
        calls.append(1)
        return fresh

    assert derivation._kept("parallelogram", derive) is fresh and calls == [1] and path.is_file()
    back = derivation._kept("parallelogram", derive)
    assert calls == [1] and back is not fresh
    for field in ("q", "dq", "D", "C", "h", "G", "T", "V", "constraint"):
        assert sp.srepr(getattr(back, field)) == sp.srepr(getattr(fresh, field)), field
    assert back.equations_of_motion() == fresh.equations_of_motion()
    path.write_bytes(b"not a pickle")
    assert derivation._kept("parallelogram", derive) is fresh and calls == [1, 1]
    assert derivation._kept("parallelogram", derive) is not fresh and calls == [1, 1]


def test_the_cache_key_follows_the_source_and_sympy(monkeypatch):
    key = derivation.cache_path("fivebar")
    assert key.parent.name == "__pycache__" and key != derivation.cache_path("parallelogram")
    monkeypatch.setattr(sp, "__version__", sp.__version__ + ".other")
    assert derivation.cache_path("fivebar") != key
