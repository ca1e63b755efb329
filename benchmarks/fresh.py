"""A fresh clone of the committed HEAD with this environment's packages: what a newcomer
has after ``git clone`` and ``make venv`` (no new venv is built: the packages are these;
leglib's bytecode is written, as ``make venv`` writes it). The clone's numba cache (beside
its sources) and matplotlib's font cache start empty; :func:`env` points Python at the clone."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def clone(tmp: Path) -> tuple[Path, str]:
    """``git clone`` of REPO's HEAD into ``tmp/leglib`` with leglib's bytecode written (as
    ``make venv`` does); returns the clone and its short commit."""
    path = Path(tmp) / "leglib"
    subprocess.run(["git", "clone", "-q", str(REPO), str(path)], check=True)
    subprocess.run([sys.executable, "-m", "compileall", "-q", str(path / "leglib")], check=True)
    head = subprocess.run(["git", "-C", str(path), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True, check=True).stdout.strip()
    return path, head


def env(path: Path, **extra) -> dict:
    """The environment of a process of the clone: its leglib first on the path, its own
    numba cache (none set: beside its sources; ``extra`` may set one), a matplotlib config and font cache of its
    own under the clone (empty at first, as on a new machine)."""
    out = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    return {**out, "PYTHONPATH": str(path), "MPLBACKEND": "Agg", "MPLCONFIGDIR": str(path / ".mplconfig"), **extra}


def timed_run(args: list[str], path: Path, environ: dict) -> float:
    """Wall time of ``python args...`` in the clone; raises with its output when it fails."""
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, *args], cwd=path, env=environ, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode:
        raise RuntimeError(f"python {' '.join(args)} failed ({proc.returncode}) in {path}:\n"
                           f"{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}")
    return wall
