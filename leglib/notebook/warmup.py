"""The numba kernels compiled ahead of their first use: ``python -m leglib compile``.

numba compiles a kernel on its first call in a process and keeps the machine code in its
cache (beside the source, ``leglib/**/__pycache__``, or under ``$NUMBA_CACHE_DIR``); a
later process loads it in a fraction of a second. With an empty cache the first
calibration of the twin waits about 16 s and the first step fit about 9 s more (2 cores), and a
first ``make run`` compiles the same kernels in two notebook kernels at once. So ``make
venv`` compiles them once at install, a group per process, each group's line printed as it
ends; ``python -m leglib run`` does it again first when a kernel's source changed since
(an edit, a pull), and the test suite before its workers start (tests/conftest.py).

The groups are chosen so that no two processes compile the same heavy function:

- ``device``: a device's calibration and a step (the twin's kernel on a batch of one), and
  a batch of legs on the same reference path (the blocks' choice of path);
- ``batch``: the twin's vectorized path for a batch of legs (a sweep's blocks);
- ``fits``: the step fit (one and many responses), the friction fit's simulator, the
  model's terms, energy, kinematics and the torque-table simulator.

Every call in a group is an ordinary use of leglib, so whatever a group compiles is what
that use needs. Whether the cache is current is read from a stamp written after a
successful compile (:func:`stamp_path`): the numba version and the size and modification
time of every source file with cached kernels and of the leglib files they import from.
numba's own index checks only the file a
kernel is defined in, not the files it inlines or takes constants from; so when any of them
changed, the compile first removes leglib's cached kernels (:func:`purge_cache`).
"""

from __future__ import annotations

import ast
import json
import os
import re
import subprocess
import sys
import tempfile
import time
import types
from pathlib import Path

import numpy as np

PACKAGE = Path(__file__).resolve().parents[1]
GROUPS = ("device", "batch", "fits")
WHAT = {"device": "the twin's reference kernel (a device's calibration and steps)",
        "batch": "the twin's vectorized kernel (sweeps)",
        "fits": "the step and friction fits, the model's terms"}


def _device():
    from ..device.session import connect  # load time: each group imports only what it compiles
    from ..device.setup import calibrate, configure  # load time: as above
    from ..experiments.step import step_response  # load time: as above
    dev = connect("virtual", seed=1)
    configure(dev)
    calibrate(dev)
    step_response(dev, 50.0, 0.046, 0.001, duration=0.05)
    # the polled step (a live view, the leg): its host-side abort rule is a kernel of its own
    step_response(dev, 50.0, 0.046, 0.001, duration=0.01, path="polled")
    # a batch of legs whose boards check their bus voltage: the same reference path, in
    # blocks (the batch group compiles the vectorized path only)
    from ..twin.host import Twin  # load time: as above
    from ..twin.layout import C_VBUS_CHECKS  # load time: as above
    twin = Twin()
    st = twin._initial_state(2)
    st.C[:, 0, C_VBUS_CHECKS] = 1.0
    twin.run(st, ticks=8)
    # a plant's encoder error read from the host (Twin.encoder_turns)
    from ..twin.effects import _encoder_error  # load time: as above
    _encoder_error(twin.FR[None, :], 0, 0.0)


def _batch():
    from ..twin.host import Twin  # load time: as above
    twin = Twin()
    twin.run(twin._initial_state(2), ticks=8)    # a sweep's blocks: the vectorized path


def _fits():
    from .. import model as M  # load time: as above
    from ..identify import fastfit  # load time: as above
    from ..identify.friction import FrictionFit  # load time: as above
    from ..identify.step import second_order, standard_errors  # load time: as above
    from ..params import load_leg  # load time: as above

    t = np.arange(750) * 0.002
    y = fastfit.model(t, 0.24, 31.4, 0.05, 0.0, 0.01)
    standard_errors(second_order(t, y), t, y)   # a fit and its intervals (the Jacobian's kernel)
    fastfit.fit_packed([t] * fastfit.PARALLEL_FROM, [y] * fastfit.PARALLEL_FROM)
    fastfit.shape_numbers([t], [y])
    fastfit.refit_from([t], [y], [[0.24, 31.4, 0.05, 0.0, 0.01]])   # a fit's refits on parts of its record
    leg = load_leg("thesis")
    q1, q2 = np.full(3, leg.q1), np.full(3, leg.q2)
    M.mass_matrix(leg, q1, q2)
    M.energy(leg, q1, q2, q1, q2)
    M.lower_link_angles(leg, q1, q2)
    M.foot_position(leg, q1, q2)
    M.simulate_torque_table(leg, [leg.q1, 0.0, leg.q2, 0.0], np.zeros((3, 2)), 0.002)
    FrictionFit(0.01, 0.01, 0.001, 1e-4, 0.0, 0.01, {}, 1.0, 0.0, 0.0, 3).simulate(t[:3], np.zeros(3))


_RUN = {"device": _device, "batch": _batch, "fits": _fits}


def cache_dir() -> Path:
    """Where numba keeps leglib's compiled kernels: ``$NUMBA_CACHE_DIR`` when set, else
    beside the sources (numba falls back to a per-user directory when that cannot be
    written; the stamp then cannot be written either, and :func:`ensure` compiles -- that
    is, loads -- every time, a few seconds)."""
    env = os.environ.get("NUMBA_CACHE_DIR")
    return Path(env) if env else PACKAGE / "__pycache__"


def stamp_path() -> Path:
    return cache_dir() / "leglib-compiled.json"


_CACHED = re.compile(r"^\s*@(numba\.)?(njit|jit)\(.*cache=True", re.M)   # a decorator of a cached kernel


def _imported(rel: Path) -> set:
    """The leglib source files that the file ``rel`` (relative to the package) imports from
    (relative imports: a module, a package's ``__init__``, or a submodule named)."""
    tree = ast.parse((PACKAGE / rel).read_text(encoding="utf-8", errors="replace"))
    out = set()
    for node in ast.walk(tree):
        if not (isinstance(node, ast.ImportFrom) and node.level):
            continue
        base = rel.parent
        for _ in range(node.level - 1):
            base = base.parent
        mod = base.joinpath(*(node.module or "").split(".")) if node.module else base
        subs = [mod / f"{a.name}.py" for a in node.names]
        if node.module is None:   # `from .. import x`: x a submodule, else a name of the package
            cands = [c if (PACKAGE / c).is_file() else mod / "__init__.py" for c in subs]
        else:
            cands = [mod.with_suffix(".py"), mod / "__init__.py", *subs]
        out |= {c for c in cands if (PACKAGE / c).is_file()}
    return out


def _sources() -> dict:
    """Size and modification time of every leglib source file with cached kernels and of
    every leglib file they import from, and so on (constants, inlined helpers)."""
    todo = {path.relative_to(PACKAGE) for path in PACKAGE.rglob("*.py")
            if _CACHED.search(path.read_text(encoding="utf-8", errors="replace"))}
    seen: set = set()
    while todo:
        rel = todo.pop()
        seen.add(rel)
        todo |= _imported(rel) - seen
    out = {}
    for rel in sorted(seen):
        st = (PACKAGE / rel).stat()
        out[str(rel)] = [st.st_size, st.st_mtime_ns]
    return out


def _fingerprint() -> dict:
    import numba  # load time: only to name its version
    return {"numba": numba.__version__, "python": sys.version.split()[0], "sources": _sources()}


def cached_files() -> list[Path]:
    """leglib's compiled kernels in numba's cache (index ``.nbi`` and data ``.nbc`` files)."""
    env = os.environ.get("NUMBA_CACHE_DIR")
    if env:   # numba mirrors the source's directory under it
        return sorted((Path(env) / PACKAGE.relative_to(PACKAGE.anchor)).rglob("*.nb[ic]"))
    return sorted(PACKAGE.rglob("__pycache__/*.nb[ic]"))


def purge_cache() -> int:
    """Remove leglib's compiled kernels from numba's cache; returns how many files went.

    numba checks a cached kernel against its own source file only: a kernel compiled
    before an edit of a file it inlines or takes constants from (``twin/layout.py``,
    ``twin/effects.py``, ``kernelmath.py``, ...) would load unchanged and run the old code.
    So when any kernel source changed since the last compile, every kernel is compiled anew."""
    n = 0
    for path in cached_files():
        try:
            path.unlink()
            n += 1
        except OSError:
            pass
    return n


def up_to_date() -> bool:
    """Whether the kernels were compiled after the last change of their sources (the stamp
    of the last successful :func:`compile_kernels` matches)."""
    try:
        return json.loads(stamp_path().read_text()) == _fingerprint()
    except (OSError, ValueError):
        return False


def compile_kernels(groups=GROUPS, stream=None) -> dict:
    """Compile (or, with a current cache, load) the kernels of ``groups``, each in its own
    process, all at once; a line on ``stream`` (standard error) when one starts and as each
    ends, with its time. Returns ``{group: seconds}``; raises RuntimeError naming the group
    and its output when one fails. Writes the stamp when all succeeded."""
    stream = sys.stderr if stream is None else stream
    unknown = [g for g in groups if g not in _RUN]
    if unknown:
        raise ValueError(f"unknown kernel group(s) {unknown}; known: {list(GROUPS)}")
    fingerprint = _fingerprint()   # of the sources as they are when the compiles start
    if not up_to_date():
        purge_cache()
    print(f"[compile] numba kernels, {len(groups)} groups at once (about 30 s on 2 cores with an "
          f"empty cache, a few seconds with a current one): {', '.join(groups)}", file=stream, flush=True)
    t0 = time.monotonic()
    # each group's output into a file (a pipe read only at the end could fill and stall it)
    outs = {g: tempfile.TemporaryFile("w+") for g in groups}
    procs = {g: subprocess.Popen([sys.executable, "-m", "leglib.notebook.warmup", g], stdout=outs[g],
                                 stderr=subprocess.STDOUT, text=True) for g in groups}
    times, failed = {}, {}
    pending = dict(procs)
    while pending:
        for g, p in list(pending.items()):
            if p.poll() is None:
                continue
            outs[g].seek(0)
            out = outs[g].read()
            outs[g].close()
            del pending[g]
            if p.returncode:
                failed[g] = out[-3000:]
                print(f"[compile] {g}: FAILED (exit {p.returncode})", file=stream, flush=True)
            else:
                times[g] = time.monotonic() - t0
                print(f"[compile] {g} ({WHAT[g]}): ready after {times[g]:.1f} s", file=stream, flush=True)
        time.sleep(0.1)
    if failed:
        raise RuntimeError("compiling leglib's kernels failed in group(s) "
                           + "; ".join(f"{g}:\n{out}" for g, out in failed.items()))
    if tuple(groups) == GROUPS:
        try:
            stamp_path().parent.mkdir(parents=True, exist_ok=True)
            stamp_path().write_text(json.dumps(fingerprint))
        except OSError:
            pass   # a read-only install: compiled (or loaded) again next time, see cache_dir
    return times


def ensure(stream=None) -> dict:
    """:func:`compile_kernels` when the kernels' sources changed since the last compile;
    a line saying so otherwise. Returns the groups' times (empty when nothing was done)."""
    stream = sys.stderr if stream is None else stream
    if up_to_date():
        print(f"[compile] numba kernels current (compiled since their sources last changed; "
              f"{stamp_path()})", file=stream, flush=True)
        return {}
    return compile_kernels(stream=stream)


def _call(fn):
    return fn()


# ``_call`` with a frame that claims 64 Ki slots (512 KiB) of value stack. CPython 3.11 keeps
# its frames on a stack of chunks: a call that passes a chunk's end gets a new chunk
# (``_PyThreadState_BumpFramePointerSlow``, fresh pages from mmap) and the return frees it
# again. numba's compile recurses deeply up and down across such an end, millions of times:
# in the batch group about 5 M page faults, 34 of its 88 CPU-s in the kernel (perf, on the
# page-fault event). Called through this frame, the compile runs in the rest of the 1 MiB
# chunk made for it and never crosses an end: the batch group in 50 CPU-s (0.2 M faults),
# the device group 45-64 -> 42-49 CPU-s. On other Pythons it is an ordinary call.
_on_one_stack_chunk = types.FunctionType(_call.__code__.replace(co_stacksize=1 << 16), globals())


def main(argv: list[str]) -> int:
    """One group in this process (the worker of :func:`compile_kernels`)."""
    for name in argv:
        _on_one_stack_chunk(_RUN[name])
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
