"""Compile the numba kernels the test suite uses, once, before its workers start.

numba compiles a kernel on first use in each process and writes it to its cache (beside the
source: ``leglib/**/__pycache__``); the next process loads it in a fraction of a second. On
a fresh clone every pytest-xdist worker, notebook kernel and Dask worker would otherwise
compile the same kernels at the same time (the cache is written only when a compile ends).
``tests/conftest.py`` runs this script in a few processes at once before the workers start,
one group of kernels each, chosen so that no two processes compile the same heavy function:

- ``serial``: a device's calibration and a step (the twin's kernel on a batch of one);
- ``batch``: the twin's kernel on a batch of several legs (the thread-parallel kernel);
- ``fit``: the step fit (one and many responses), the friction fit's simulator, the model's
  terms, energy, kinematics and torque-table simulator.

Every call here is an ordinary use of leglib: with a warm cache the script only loads.
``python tests/warm_kernels.py serial batch fit`` runs the groups one after another.
"""

from __future__ import annotations

import sys
import time

import numpy as np


def serial():
    import leglib as lg
    dev = lg.connect("virtual", seed=1)
    lg.configure(dev)
    lg.calibrate(dev)
    lg.step_response(dev, 50.0, 0.046, 0.001, duration=0.05)


def batch():
    from leglib.twin.host import Twin
    twin = Twin()
    twin.run(twin._initial_state(2), ticks=8)


def fit():
    from leglib import model as M
    from leglib.identify import fastfit
    from leglib.identify.step import second_order
    from leglib.params import load_leg

    t = np.arange(750) * 0.002
    y = fastfit.model(t, 0.24, 31.4, 0.05, 0.0, 0.01)
    second_order(t, y)
    fastfit.fit_packed([t] * fastfit.PARALLEL_FROM, [y] * fastfit.PARALLEL_FROM)
    fastfit.shape_numbers([t], [y])
    leg = load_leg("thesis")
    q1, q2 = np.full(3, leg.q1), np.full(3, leg.q2)
    M.mass_matrix(leg, q1, q2)
    M.energy(leg, q1, q2, q1, q2)
    M.lower_link_angles(leg, q1, q2)
    M.foot_position(leg, q1, q2)
    from leglib.model.terms import PARALLEL_POINTS
    big = np.full(PARALLEL_POINTS, leg.q1)
    M.foot_position(leg, big, big)
    M.simulate_torque_table(leg, [leg.q1, 0.0, leg.q2, 0.0], np.zeros((3, 2)), 0.002)
    from leglib.identify.friction import FrictionFit
    FrictionFit(0.01, 0.01, 0.001, 1e-4, 0.0, 0.01, {}, 1.0, 0.0, 0.0, 3).simulate(t[:3], np.zeros(3))


GROUPS = {"serial": serial, "batch": batch, "fit": fit}


def main(names: list[str]) -> int:
    for name in names:
        t0, c0 = time.perf_counter(), time.process_time()
        GROUPS[name]()
        print(f"warm_kernels {name}: {time.perf_counter() - t0:.1f} s ({time.process_time() - c0:.1f} s CPU)",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:] or list(GROUPS)))
