"""leglib.notebook.warmup: the kernels compiled ahead of use, and the stamp that says whether
that compile is still current."""

import io
import os

import pytest

from leglib.notebook import cli, warmup


@pytest.fixture
def fake_package(tmp_path, monkeypatch):
    """A package of two files, one with a cached kernel, and a cache directory of its own."""
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "kernels.py").write_text("from .consts import N\n@njit(cache=True)\ndef f(): return N\n")
    (pkg / "consts.py").write_text("N = 3\n")
    (pkg / "plain.py").write_text("def g(): pass\n")
    monkeypatch.setattr(warmup, "PACKAGE", pkg)
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    return pkg


def test_the_sources_are_the_files_with_cached_kernels_and_what_they_import():
    """The kernels' files, and the files they take constants and inlined helpers from (an
    edit of twin/layout.py must make the kernels compile anew, though it has no cached
    kernel of its own); not the notebook layer."""
    sources = warmup._sources()
    assert {"twin/kernel.py", "identify/fastfit.py", "twin/vector.py", "twin/effects.py"} <= set(sources)
    assert "twin/layout.py" in sources and "kernelmath.py" in sources
    assert not any(rel.startswith("notebook/") for rel in sources)


def test_the_stamp_goes_stale_when_a_kernel_source_changes(fake_package):
    assert warmup.stamp_path().parent == fake_package.parent / "cache"
    assert not warmup.up_to_date()                                  # never compiled
    warmup.stamp_path().parent.mkdir()
    warmup.stamp_path().write_text(__import__("json").dumps(warmup._fingerprint()))
    assert warmup.up_to_date()
    (fake_package / "plain.py").write_text("def g(): return 1\n")   # no kernel in it
    assert warmup.up_to_date()
    (fake_package / "consts.py").write_text("N = 4\n")                # a constant a kernel uses
    assert not warmup.up_to_date()
    warmup.stamp_path().write_text(__import__("json").dumps(warmup._fingerprint()))
    st = (fake_package / "kernels.py").stat()
    os.utime(fake_package / "kernels.py", ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))   # an edit, a pull
    assert not warmup.up_to_date()


def test_ensure_says_current_and_compiles_nothing(fake_package, monkeypatch, capsys):
    warmup.stamp_path().parent.mkdir()
    warmup.stamp_path().write_text(__import__("json").dumps(warmup._fingerprint()))
    monkeypatch.setattr(warmup.subprocess, "Popen", lambda *a, **k: pytest.fail("compiled although current"))
    assert cli.main(["compile", "--if-changed"]) == 0
    assert "numba kernels current" in capsys.readouterr().err


def test_an_unknown_group_is_named():
    with pytest.raises(ValueError, match=r"unknown kernel group\(s\) \['sweep'\]; known: \['device', 'batch', 'fits'\]"):
        warmup.compile_kernels(["sweep"])


def test_a_failing_group_is_reported_and_leaves_no_stamp(fake_package, monkeypatch):
    """A group whose process fails (here one its worker does not know: KeyError) is named with
    its output; the stamp is not written, so the next run compiles again."""
    monkeypatch.setattr(warmup, "_RUN", {**warmup._RUN, "boom": None})
    monkeypatch.setattr(warmup, "WHAT", {**warmup.WHAT, "boom": "nothing"})
    monkeypatch.setattr(warmup, "GROUPS", ("boom",))
    lines = io.StringIO()
    with pytest.raises(RuntimeError, match=r"(?s)failed in group\(s\) boom:.*KeyError: 'boom'"):
        warmup.compile_kernels(("boom",), stream=lines)
    assert "[compile] boom: FAILED (exit 1)" in lines.getvalue()
    assert not warmup.stamp_path().exists()


@pytest.mark.slow
def test_a_compile_prints_a_line_per_group_and_writes_the_stamp(fake_package, monkeypatch):
    """The real groups with the repository's numba cache (warm in a test run: they load), the
    stamp under the fake cache directory: one line when they start, one as each is ready."""
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    cache = fake_package.parent / "cache"
    monkeypatch.setattr(warmup, "cache_dir", lambda: cache)
    lines = io.StringIO()
    times = warmup.compile_kernels(stream=lines)
    assert set(times) == set(warmup.GROUPS) and all(t > 0 for t in times.values())
    out = lines.getvalue().splitlines()
    assert out[0].startswith("[compile] numba kernels, 3 groups at once")
    assert sorted(line.split()[1] for line in out[1:]) == sorted(warmup.GROUPS)
    assert all("ready after" in line for line in out[1:])
    assert warmup.up_to_date()


def test_a_stale_cache_is_purged_before_compiling(fake_package, monkeypatch):
    """An edit of any kernel source (a constant in layout.py, an inlined helper) removes every
    cached kernel first: numba checks a kernel against its own file only, and would load the
    old machine code of a kernel whose file did not change."""
    cache = fake_package.parent / "cache"
    mirrored = cache / fake_package.relative_to(fake_package.anchor) / "twin"
    mirrored.mkdir(parents=True)
    old = [mirrored / "kernel._run-100.py311.nbi", mirrored / "kernel._run-100.py311.1.nbc"]
    for p in old:
        p.write_bytes(b"old")
    (mirrored / "unrelated.txt").write_text("kept")
    assert warmup.cached_files() == sorted(old)
    monkeypatch.setattr(warmup, "_RUN", {**warmup._RUN, "noop": None})
    monkeypatch.setattr(warmup, "WHAT", {**warmup.WHAT, "noop": "nothing"})
    monkeypatch.setattr(warmup.subprocess, "Popen", lambda *a, **k: _Done())
    warmup.compile_kernels(("noop",), stream=io.StringIO())
    assert not any(p.exists() for p in old) and (mirrored / "unrelated.txt").exists()
    # current: nothing purged
    warmup.stamp_path().write_text(__import__("json").dumps(warmup._fingerprint()))
    for p in old:
        p.write_bytes(b"new")
    warmup.compile_kernels(("noop",), stream=io.StringIO())
    assert all(p.exists() for p in old)


class _Done:
    """A finished group process (for the purge test: nothing is compiled)."""
    returncode = 0

    def poll(self):
        return 0



def test_a_group_runs_on_one_stack_chunk_and_returns_or_raises_as_called(monkeypatch):
    """A group's function is called through a frame that reserves 512 KiB of value stack
    (its deep recursion then stays in one chunk of CPython's frame stack); deep calls run
    under it, and a group's exception comes out of main unchanged."""
    assert warmup._on_one_stack_chunk.__code__.co_stacksize >= 1 << 16

    def deep(n=0):
        return n if n == 500 else deep(n + 1)

    assert warmup._on_one_stack_chunk(deep) == 500
    ran = []

    def boom():
        raise KeyError("boom")

    monkeypatch.setattr(warmup, "_RUN", {"a": lambda: ran.append("a"), "boom": boom})
    assert warmup.main(["a"]) == 0 and ran == ["a"]
    with pytest.raises(KeyError, match="boom"):
        warmup.main(["boom"])


def _literal_twins(signatures) -> list:
    """Pairs of one kernel's compiled signatures where the first is the second with some
    argument types literal (``Literal[bool](False)`` for ``bool``)."""
    from numba.core import types

    pairs = []
    for lit in signatures:
        plain = tuple(types.unliteral(t) for t in lit)
        if plain != tuple(lit) and any(tuple(other) == plain for other in signatures):
            pairs.append((lit, plain))
    return pairs


def test_literal_twins_are_found():
    from numba.core import types

    lit = (types.int64, types.literal(False))
    assert _literal_twins([lit, (types.int64, types.boolean)]) == [(lit, (types.int64, types.boolean))]
    # two literals of one argument are two specializations the code asks for (a branch
    # pruned in each), not a twin
    assert _literal_twins([lit, (types.int64, types.literal(True))]) == []


def test_no_kernel_is_compiled_again_for_a_literal_argument():
    """numba types a kernel's call with a constant argument for its literal type: a kernel
    called both with a constant and with a variable of the same type is compiled twice
    (``_control_vector`` was, for ``Literal[bool](False)`` and ``bool``: a third of the
    batch group's compile, for code no run uses). numba's cache index of each compiled
    kernel holds no such pair among what the compile groups compiled (written before their
    stamp; a test calling a kernel from Python with a plain value compiles one later)."""
    import pickle

    warmup.ensure(stream=io.StringIO())   # current, or compiled now
    compiled = warmup.stamp_path().stat().st_mtime_ns
    found, twins = 0, {}
    for index in warmup.cached_files():
        if index.suffix != ".nbi":
            continue
        with open(index, "rb") as f:
            pickle.load(f)                                   # numba's version
            _stamp, overloads = pickle.loads(f.read())
        sigs = [key[0] for key, data in overloads.items() if (index.parent / data).stat().st_mtime_ns <= compiled]
        found += len(sigs)
        if _literal_twins(sigs):
            twins[index.name] = [[str(t) for t in lit] for lit, _ in _literal_twins(sigs)]
    assert found >= 40, f"only {found} compiled kernels found under {warmup.cache_dir()}"
    assert not twins, twins
