"""Benchmarks: ``make bench`` or ``python -m benchmarks [name ...]``.

Each benchmark reports the median (and min, max) of several runs after one warm-up run
(numba compiles on first use), and the figure it is measured against. Results are also
written to benchmarks/results/latest.json.
"""

from __future__ import annotations

import json
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).with_name("results")


def timed(fn, repeat: int) -> dict:
    fn()  # warm-up (compilation, caches)
    runs = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        runs.append(time.perf_counter() - t0)
    return {"median_s": statistics.median(runs), "min_s": min(runs), "max_s": max(runs), "runs": repeat}


def bench_twin_single_step():
    """One 1.5 s step on the twin through odrive_io (target <= 50 ms)."""
    from leglib import odrive_io as io
    dev = io.connect("virtual", seed=1)
    io.apply_configuration(dev)
    io.calibrate(dev)
    r = timed(lambda: io.step_response(dev, 50, 0.046, 0.001), repeat=15)
    return {**r, "target_s": 0.050}


def bench_twin_thesis_grid():
    """The thesis grid, 4 x 10 x 10 = 400 steps of 1.5 s, through odrive_io.sweep's batch
    path without writing files (target <= 5 s)."""
    from leglib import odrive_io as io
    dev = io.connect("virtual", seed=1)
    io.apply_configuration(dev)
    io.calibrate(dev)
    grid = io.thesis_grid()

    def run():
        out = dev.raw.step_batch(grid, vel_limit=dev.config.step_vel_limit, abort_error_turns=0.8)
        io._responses_from_batch(dev, grid, out, 0.4)
    return {**timed(run, repeat=5), "target_s": 5.0, "points": len(grid)}


def bench_second_order():
    """second_order on a 750-sample noisy step (target < 5 ms)."""
    from leglib.identify import _model, second_order
    t = np.arange(750) * 0.002
    y = np.floor(_model(t, 0.24, 31.4, 1600.0, 0.0, 0.01) + np.random.default_rng(0).normal(0, 0.35, 750) + 0.5)
    return {**timed(lambda: second_order(t, y), repeat=50), "target_s": 0.005}


BENCHMARKS = {name[6:]: fn for name, fn in globals().items() if name.startswith("bench_")}


def main(argv: list[str]) -> int:
    names = argv or list(BENCHMARKS)
    unknown = set(names) - set(BENCHMARKS)
    if unknown:
        print(f"unknown benchmark(s) {sorted(unknown)}; known: {sorted(BENCHMARKS)}")
        return 2
    results = {"machine": {"python": sys.version.split()[0], "platform": platform.platform(),
                           "cpus": __import__("os").cpu_count()}}
    for name in names:
        res = BENCHMARKS[name]()
        results[name] = res
        ok = "ok " if res["median_s"] <= res["target_s"] else "MISS"
        print(f"[{ok}] {name:22s} median {res['median_s'] * 1e3:9.2f} ms  "
              f"(min {res['min_s'] * 1e3:.2f}, max {res['max_s'] * 1e3:.2f}, n={res['runs']}; "
              f"target {res['target_s'] * 1e3:.0f} ms)")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "latest.json").write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
