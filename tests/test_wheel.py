"""leglib is installable: a wheel built from the repository, installed into a new virtual
environment (no repository on its path), carries its parameter files and firmware tables and
runs the twin end to end: connect, configure, calibrate, one step, its identification, the
kernels compiled from the installed files (an empty numba cache).

The environment gets leglib from the wheel and nothing else: its dependencies are those of
the environment running the tests (environment.txt's pins, which ``make test`` installs),
reached through a path entry, and the test checks that they satisfy every requirement the
wheel declares. Installing the pinned set again from pip's cache proved nothing the test
environment's own install does not, and cost two minutes."""

import os
import subprocess
import sys
import sysconfig
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent

SCRIPT = textwrap.dedent("""
    import importlib.metadata as md
    import sys
    from pathlib import Path

    from packaging.requirements import Requirement

    import leglib as lg

    # leglib is the wheel's, installed in this environment; the repository is not reachable
    here = Path(sys.prefix).resolve()
    assert here in Path(lg.__file__).resolve().parents, lg.__file__
    assert here in Path(md.distribution("leglib").locate_file("")).resolve().parents
    assert not any(Path(p).resolve() == Path(sys.argv[1]) for p in sys.path if p), sys.path
    # every requirement the wheel declares (without extras) is met here
    unmet = []
    for text in md.requires("leglib"):
        req = Requirement(text)
        if req.marker is not None and not req.marker.evaluate({"extra": ""}):
            continue
        try:
            version = md.version(req.name)
        except md.PackageNotFoundError:
            unmet.append(f"{req}: not installed")
            continue
        if version not in req.specifier:
            unmet.append(f"{req}: {version} installed")
    assert not unmet, unmet

    dev = lg.connect("virtual", seed=3)
    lg.configure(dev)
    lg.calibrate(dev)
    r = lg.step_response(dev, 50.0, 0.046, 0.001)
    fit = lg.second_order(r.t, r.y)
    assert r.completed and 0.05 < fit.zeta < 1.0 and fit.r2 > 0.9, (r.completed, fit)
    print(f"zeta {fit.zeta:.3f} fn {fit.fn:.2f} Hz r2 {fit.r2:.3f}")
""")


def _clean_env(**extra) -> dict:
    """The environment without the repository on the path (``PYTHONPATH`` would make pip
    think leglib installed already, and the script import the repository's)."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "NUMBA_CACHE_DIR", "PYTHONHOME")}
    env.update(extra)
    return env


@pytest.mark.wheel
def test_a_wheel_installs_into_a_fresh_venv_and_runs_the_twin(tmp_path):
    dist = tmp_path / "dist"
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q",
                            "-w", str(dist), str(REPO)], capture_output=True, text=True, timeout=300,
                           env=_clean_env())
    assert build.returncode == 0, build.stdout[-2000:] + build.stderr[-2000:]
    (wheel,) = dist.glob("leglib-*.whl")
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    py = venv / "bin" / "python"
    # the wheel alone into the new environment (pip of this one acting on it)
    install = subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "-q", "--no-deps",
                              "--no-index", str(wheel)], capture_output=True, text=True, timeout=300,
                             env=_clean_env())
    assert install.returncode == 0, install.stdout[-2000:] + install.stderr[-2000:]
    site = Path(subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               capture_output=True, text=True, check=True, env=_clean_env()).stdout.strip())
    assert (site / "leglib" / "params").is_dir() and (site / "leglib" / "device" / "virtual" / "tables").is_dir()
    # then the dependencies: this environment's packages, after leglib's own (a path entry
    # runs none of their .pth files: the repository's editable leglib is not among them)
    deps = {sysconfig.get_paths()[k] for k in ("purelib", "platlib")}
    (site / "zz_test_dependencies.pth").write_text("".join(f"{p}\n" for p in sorted(deps)))
    run = subprocess.run([str(py), "-c", SCRIPT, str(REPO)], capture_output=True, text=True, timeout=900,
                         cwd=tmp_path, env=_clean_env(NUMBA_CACHE_DIR=str(tmp_path / "numba-cache")))
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-3000:]
    assert "zeta" in run.stdout
