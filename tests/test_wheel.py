"""leglib is installable: a wheel built from the repository, installed into a fresh virtual
environment (no repository on its path), carries its parameter files and firmware tables and
runs the twin end to end: connect, configure, calibrate, one step, its identification."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent

SCRIPT = textwrap.dedent("""
    import sys
    import leglib as lg
    assert "site-packages" in lg.__file__, lg.__file__
    dev = lg.connect("virtual", seed=3)
    lg.configure(dev)
    lg.calibrate(dev)
    r = lg.step_response(dev, 50.0, 0.046, 0.001)
    fit = lg.second_order(r.t, r.y)
    assert r.completed and 0.05 < fit.zeta < 1.0 and fit.r2 > 0.9, (r.completed, fit)
    print(f"zeta {fit.zeta:.3f} fn {fit.fn:.2f} Hz r2 {fit.r2:.3f}")
""")


@pytest.mark.wheel
def test_a_wheel_installs_into_a_fresh_venv_and_runs_the_twin(tmp_path):
    dist = tmp_path / "dist"
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w",
                            str(dist), str(REPO)], capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, build.stdout[-2000:] + build.stderr[-2000:]
    (wheel,) = dist.glob("leglib-*.whl")
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    py = venv / "bin" / "python"
    # the dependencies at the versions of environment.txt (pip's cache serves them offline)
    pins = [ln for ln in (REPO / "environment.txt").read_text().splitlines() if ln and not ln.startswith("#")]
    install = subprocess.run([str(py), "-m", "pip", "install", "-q", str(wheel), "-c", "/dev/stdin"],
                             input="\n".join(pins), capture_output=True, text=True, timeout=900)
    assert install.returncode == 0, install.stdout[-2000:] + install.stderr[-2000:]
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "NUMBA_CACHE_DIR")}
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "numba-cache")
    run = subprocess.run([str(py), "-c", SCRIPT], capture_output=True, text=True, timeout=900, cwd=tmp_path,
                         env=env)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-3000:]
    assert "zeta" in run.stdout
