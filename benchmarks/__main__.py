"""Benchmarks: ``make bench`` or ``python -m benchmarks [name ...]``.

Each benchmark reports the median (and min, max) of several runs after one warm-up run
(numba compiles on first use), and the figure it is measured against. After the runs a
side-by-side table puts the thesis-grid pipeline, its parts and the references (a naive
numpy loop of one axis, solve_ivp point by point) against the numpy loop. Results are
written to benchmarks/results/latest.json and the table to benchmarks/results/latest.txt.
"""

from __future__ import annotations

import json
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

import leglib as lg
from leglib.design.points import identify_many
from leglib.device.virtual import device_of, find_any
from leglib.experiments.step import _responses_from_batch
from leglib.notebook import liveview
from leglib.params import load_leg
from leglib.twin.host import Twin
from leglib.twin.layout import I_MODE, MODE_POSITION

RESULTS = Path(__file__).with_name("results")


def timed(fn, repeat: int) -> dict:
    """Wall-clock median, min and max of ``repeat`` runs after a warm-up; also the median
    CPU time of this process (on a shared machine the wall clock includes waiting)."""
    fn()  # warm-up (compilation, caches)
    runs, cpu = [], []
    for _ in range(repeat):
        c0 = time.process_time()
        t0 = time.perf_counter()
        fn()
        runs.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return {"median_s": statistics.median(runs), "min_s": min(runs), "max_s": max(runs), "runs": repeat,
            "cpu_median_s": statistics.median(cpu)}


def _device(seed: int):
    """A configured, calibrated virtual ODrive."""
    dev = lg.connect("virtual", seed=seed)
    lg.configure(dev)
    lg.calibrate(dev)
    return dev


def bench_twin_single_step():
    """One 1.5 s step on the twin through odrive_io (target <= 50 ms)."""
    dev = _device(1)
    r = timed(lambda: lg.step_response(dev, 50, 0.046, 0.001), repeat=15)
    return {**r, "target_s": 0.050}


def bench_device_tick():
    """One leg's tick on the device path (the virtual ODrive advancing its twin between USB
    transactions: calibrations, polled steps, every notebook on the virtual backend), both
    axes in closed-loop position control holding the rest pose under a 0.5 s watchdog, fed
    between runs of 2000 ticks (0.25 s of device time); reported per tick (target <= 0.4
    us: 0.79 us while the tick loop counted references to its arrays, 0.30 us since, see
    leglib.twin.kernel._run_block_ticks)."""
    from leglib.device.session import enter_closed_loop, prepare_closed_loop
    dev = _device(1)
    sim = dev.sim
    prepare_closed_loop(dev, vel_limit=2.0, watchdog=0.5)
    try:
        enter_closed_loop(dev)

        def run():
            sim.twin.run(sim.st, ticks=2000)
            for a in (0, 1):
                dev.axis(a).watchdog_feed()
        r = timed(run, repeat=25)
        modes = [int(m) for m in sim.st.AI[0, :, I_MODE]]
    finally:
        dev.idle_all()
    if modes != [MODE_POSITION, MODE_POSITION]:
        raise RuntimeError(f"device_tick: the axes left position control (kernel modes {modes})")
    per = {k: r[k] / 2000 for k in ("median_s", "min_s", "max_s", "cpu_median_s")}
    return {**r, **per, "target_s": 0.4e-6, "ticks": 2000}


def bench_twin_thesis_grid():
    """The thesis grid, 4 x 10 x 10 = 400 steps of 1.5 s, through odrive_io.sweep's batch
    path without writing files (target <= 5 s)."""
    dev = _device(1)
    grid = lg.thesis_grid()

    def run():
        out = dev.sim.step_batch(grid, vel_limit=dev.config.step_vel_limit, abort_error_turns=0.8)
        _responses_from_batch(dev, grid, out, 0.4)
    return {**timed(run, repeat=5), "target_s": 5.0, "points": len(grid)}


def bench_second_order():
    """second_order on a 750-sample noisy step (target <= 0.5 ms: 1/400 of the numpy loop
    of one axis over the thesis grid, about 0.19 s)."""
    from leglib.identify.fastfit import model as _model
    from leglib.identify.step import second_order
    t = np.arange(750) * 0.002
    y = np.floor(_model(t, 0.24, 31.4, 1600.0, 0.0, 0.01) + np.random.default_rng(0).normal(0, 0.35, 750) + 0.5)
    return {**timed(lambda: second_order(t, y), repeat=200), "target_s": 0.0005}


def _thesis_grid_responses(seed: int = 11):
    """The thesis grid's 400 step responses on the twin (simulated once)."""
    dev = _device(seed)
    grid = lg.thesis_grid()
    out = dev.sim.step_batch(grid, vel_limit=dev.config.step_vel_limit, abort_error_turns=0.8)
    return _responses_from_batch(dev, grid, out, 0.4)


def bench_identify_thesis_grid():
    """Second-order identification of the thesis grid's 400 twin responses in one compiled
    call (gainmap.identify_many; unstable points are skipped, as in the map); target
    <= 1 s, a quarter of the process-pool least squares it replaces."""
    responses = _thesis_grid_responses()
    leg = load_leg("thesis")
    return {**timed(lambda: identify_many(responses, leg), repeat=7), "target_s": 1.0,
            "points": len(responses), "completed": sum(r.completed for r in responses)}


def numpy_single_axis(gains, inertia, viscous, torque_constant, current_bandwidth, vel_limit,
                      step=0.4, duration=1.5, loop_hz=8000.0, sample_hz=500.0):
    """The reference to beat: one axis of the ODrive cascade for every grid point, written
    as a student would, a Python loop over the 8 kHz ticks vectorized over the points.

    Position P (turns -> turns/s, clamped at ``vel_limit``), velocity PI (turns/s -> N*m),
    the current loop as a first-order lag of ``current_bandwidth`` [rad/s], and the motor
    shaft as ``inertia`` [kg*m^2] with ``viscous`` damping [N*m*s/rad]; semi-implicit Euler
    at ``loop_hz``, positions recorded at ``sample_hz``. No PLL, no five-bar, no files.

    Parameters
    ----------
    gains : (M, 3) pos_gain [(turn/s)/turn], vel_gain [N*m/(turn/s)],
        vel_integrator_gain [N*m/turn]
    inertia : [kg*m^2] and viscous [N*m*s/rad], at the motor shaft
    torque_constant : [N*m/A]
    current_bandwidth : [rad/s]
    vel_limit : [turn/s]
    step : position step [turn]; duration [s]; loop_hz, sample_hz [Hz]

    Returns
    -------
    (M, N) motor positions [turn] at the sample times
    """
    gains = np.asarray(gains, dtype=float)
    kp, kv, ki = gains[:, 0], gains[:, 1], gains[:, 2]
    dt = 1.0 / loop_hz
    ticks = int(round(duration * loop_hz))
    every = int(round(loop_hz / sample_hz))
    pos = np.zeros(len(gains))       # turns
    vel = np.zeros(len(gains))       # turns/s
    integ = np.zeros(len(gains))     # N*m
    iq = np.zeros(len(gains))        # A
    out = np.empty((len(gains), ticks // every))
    for k in range(ticks):
        if k % every == 0:
            out[:, k // every] = pos
        vel_sp = np.clip(kp * (step - pos), -vel_limit, vel_limit)
        err = vel_sp - vel
        integ += ki * err * dt
        torque_sp = kv * err + integ
        iq += dt * current_bandwidth * (torque_sp / torque_constant - iq)
        acc = (torque_constant * iq - viscous * vel * 2 * np.pi) / inertia   # rad/s^2
        vel += acc * dt / (2 * np.pi)
        pos += vel * dt
    return out


def bench_numpy_single_axis():
    """The reference: numpy_single_axis over the 400 thesis-grid points (the issue measured
    0.19 s here); the target of the whole pipeline."""
    from leglib.model import mass_matrix
    from leglib.twin.host import Twin
    tw = Twin(seed=1, noise=False)
    N = tw.axes.gear_ratio
    # the first joint's inertia and viscous friction at rest, seen at the motor shaft
    J = float(mass_matrix(tw.leg, *tw.axes.q_rest)[0, 0]) / N ** 2
    kw = dict(inertia=J, viscous=tw.plant.viscous1 / N ** 2, torque_constant=tw.config.torque_constant,
              current_bandwidth=tw.config.current_control_bandwidth, vel_limit=tw.config.step_vel_limit,
              loop_hz=tw.config.loop_frequency)
    grid = lg.thesis_grid()
    return {**timed(lambda: numpy_single_axis(grid, **kw), repeat=5), "target_s": None, "points": len(grid)}


def bench_thesis_pipeline_files():
    """The thesis grid through the user path: 400 twin steps written as measurement files
    (lg.sweep), GainMap.from_measurements (read, foot height, identify, map), one inverse
    query (target <= 1 s to a map: the files are plain numpy and json, not optimised
    further; the earlier target, 1.5 x the numpy loop of one axis, is withdrawn). Also
    where the time goes: each part's median, wall and this process's CPU time."""
    import shutil
    import tempfile

    dev = _device(11)
    grid = lg.thesis_grid()
    root = Path(tempfile.mkdtemp(prefix="bench_sweep_"))
    runs = iter(range(1 << 30))
    parts = []   # per run: {part: (wall, cpu)}

    def part(record, name, fn):
        c0, t0 = time.process_time(), time.perf_counter()
        value = fn()
        record[name] = (time.perf_counter() - t0, time.process_time() - c0)
        return value

    def run():
        # each run into a new directory, all removed at the end: deleting the previous
        # run's 2000 files just before a run makes its file creation slow on filesystems
        # that skip recently freed inodes (ext4 without a journal), a cost of the clean-up
        out = root / f"sweep{next(runs)}"
        record = {}
        part(record, "sweep", lambda: lg.sweep(dev, grid, out, progress=False))
        gm = part(record, "from_measurements", lambda: lg.GainMap.from_measurements(out))
        part(record, "gains_for", lambda: gm.gains_for(0.24, 5.0))
        parts.append(record)
    try:
        res = timed(run, repeat=3)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    measured = parts[1:]   # without the warm-up
    med = {k: tuple(statistics.median(r[k][i] for r in measured) for i in (0, 1)) for k in measured[0]}
    print("      " + ", ".join(f"{k} {w * 1e3:.0f} ms (cpu {c * 1e3:.0f})" for k, (w, c) in med.items()))
    return {**res, "target_s": 1.0, "points": len(grid),
            "parts_median_s": {k: w for k, (w, _) in med.items()},
            "parts_cpu_median_s": {k: c for k, (_, c) in med.items()}}


def bench_sweep_map_pipeline():
    """The thesis grid on the twin end to end, in memory: 400 step simulations, 400
    identifications (one compiled batch), the map with gap filling and interpolation, one
    inverse query (target <= 5 s)."""
    dev = _device(11)
    grid = lg.thesis_grid()

    def run():
        out = dev.sim.step_batch(grid, vel_limit=dev.config.step_vel_limit, abort_error_turns=0.8)
        gm = lg.GainMap.from_responses(_responses_from_batch(dev, grid, out, 0.4), dev.leg)
        gm.gains_for(0.24, 5.0)
    return {**timed(run, repeat=5), "target_s": 5.0, "points": len(grid)}


def _ivp_step(tw, gains, step=0.4, duration=1.5):
    """Reference: the same cascade and leg as the twin's kernel, but continuous-time (PLL,
    PI, current lag as ODEs) and integrated point by point with scipy's solve_ivp."""
    import math

    from scipy.integrate import solve_ivp

    from leglib.model.terms import _fivebar_dynamics
    kp_g, kv_g, ki_g = gains
    N, dirn, kt = tw.axes.gear_ratio, tw.axes.direction, tw.motor.torque_constant
    bw_e, wc = tw.config.encoder_bandwidth, tw.config.current_control_bandwidth
    kp_e, ki_e = 2 * bw_e, (2 * bw_e) ** 2 / 4
    P, FR = tw.P, tw.FR
    qr = tw.axes.q_rest
    joint = [tw.axes.joint_of_axis(a) for a in (0, 1)]
    target = [step if joint[a] == 0 else -step for a in (0, 1)]

    def rhs(t, s):
        q1, dq1, q2, dq2 = s[:4]
        q, dq = (q1, q2), (dq1, dq2)
        tau = [0.0, 0.0]
        d = np.empty(16)
        d[0], d[1], d[2], d[3] = dq1, 0.0, dq2, 0.0
        for a in (0, 1):
            j = joint[a]
            pe, ve, z, iq = s[4 + 4 * a: 8 + 4 * a]
            pos = dirn * (q[j] - qr[j]) * N / (2 * math.pi)
            vd = max(min(kp_g * (target[a] - pe), 12.0), -12.0)
            torque = kv_g * (vd - ve) + z
            d[4 + 4 * a] = ve + kp_e * (pos - pe)
            d[5 + 4 * a] = ki_e * (pos - pe)
            d[6 + 4 * a] = ki_g * (vd - ve)
            d[7 + 4 * a] = wc * (torque / kt - iq)
            tau[j] = dirn * N * kt * iq
        d11, d12, d22, b1, b2 = _fivebar_dynamics(q1, q2, dq1, dq2, P)[:5]
        f = [FR[j] * dq[j] + FR[2 + j] * math.tanh(dq[j] / FR[7]) for j in (0, 1)]
        t1, t2 = tau[0] - b1 - f[0], tau[1] - b2 - f[1]
        gap = q2 - q1
        if gap < FR[8]:
            push = max(FR[9] * (FR[8] - gap) - FR[10] * (dq2 - dq1), 0.0)
            t1, t2 = t1 - push, t2 + push
        det = d11 * d22 - d12 * d12
        d[1] = (d22 * t1 - d12 * t2) / det
        d[3] = (-d12 * t1 + d11 * t2) / det
        return d[:12]

    s0 = np.zeros(12)
    s0[0], s0[2] = qr
    return solve_ivp(rhs, (0, duration), s0, t_eval=np.arange(0, duration, 0.002), rtol=1e-6, atol=1e-9,
                     max_step=1e-3)


def bench_vs_solve_ivp():
    """Per-point cost: the twin's batch kernel (400 steps at once) against solve_ivp of the
    same cascade and leg, one point at a time (8 points, extrapolated); target >= 200x."""
    from leglib.twin.host import Twin
    tw = Twin(seed=1, noise=False)
    grid = np.array([(p, v, i) for p in (20.0, 50.0) for v in (0.03, 0.08) for i in (0.002, 0.04)])
    full = np.repeat(grid, 50, axis=0)  # 400 points
    batch = timed(lambda: tw.step_batch(full), repeat=5)
    runs = []
    for g in grid:
        t0 = time.perf_counter()
        sol = _ivp_step(tw, g)
        runs.append(time.perf_counter() - t0)
        assert sol.success
    per_ivp = statistics.median(runs)
    per_twin = batch["median_s"] / len(full)
    speedup = per_ivp / per_twin
    print(f"      solve_ivp per point: median {per_ivp * 1e3:.0f} ms (n={len(runs)}), "
          f"twin per point in a 400-batch: {per_twin * 1e3:.3f} ms -> {speedup:.0f}x")
    # reported as "time" = twin per-point cost; target = solve_ivp per point / 200
    return {"median_s": per_twin, "min_s": batch["min_s"] / len(full), "max_s": batch["max_s"] / len(full),
            "runs": batch["runs"], "target_s": per_ivp / 200, "solve_ivp_per_point_s": per_ivp, "speedup": speedup}


def bench_client_transaction():
    """One property read and one write through the installed odrive client on the virtual
    ODrive (leglib.virtual_odrive.find_any): per transaction, median of runs of 200 reads
    and 200 writes. Target 0.5 ms: Listing 7.4 samples with 4 transactions every ~2 ms
    (the thesis's loop), so the host must keep up with the virtual clock in real time."""
    odrv = find_any(seed=9001)
    sim = device_of(odrv)
    n = 200

    def reads():
        for _ in range(n):
            odrv.axis0.encoder.pos_estimate

    def writes():
        for _ in range(n):
            odrv.axis0.controller.input_pos = 0.1

    def model_reads():
        for _ in range(n):
            sim.axis0.encoder.pos_estimate
    r = timed(reads, repeat=7)
    w = timed(writes, repeat=7)
    m = timed(model_reads, repeat=7)
    per = {k: {q: v / n if q.endswith("_s") else v for q, v in d.items()} for k, d in
           (("read", r), ("write", w), ("model_read", m))}
    print(f"      per transaction: read {per['read']['median_s'] * 1e6:.0f} us, write "
          f"{per['write']['median_s'] * 1e6:.0f} us (firmware model alone: "
          f"{per['model_read']['median_s'] * 1e6:.0f} us per read; medians of {r['runs']} runs of {n})")
    return {**per["read"], "target_s": 0.0005, "write_median_s": per["write"]["median_s"],
            "model_read_median_s": per["model_read"]["median_s"]}


def _liveview_run(n=1500, period=0.002):
    import types

    from leglib.params import load_leg
    leg = load_leg("thesis")
    t = np.arange(n) * period
    e = 1 - np.exp(-6 * t) * np.cos(25 * t)
    run = types.SimpleNamespace(t=t, q1=leg.q1 - 0.3 * e, q2=leg.q2 + 0.3 * e,
                                iq=np.column_stack([3 * np.exp(-4 * t), -2.5 * np.exp(-4 * t)]))
    return leg, run


def bench_liveview_callback():
    """Cost of one LiveView.on_sample call (what an experiment's loop pays per sample),
    median over batches of 10,000 calls; target <= 20 us (1 % of a 2 ms period)."""
    from leglib.notebook.liveview import LiveView
    view = LiveView(queue_size=1_000_000, renderer="thread")
    sample = {"t": 0.1, "q1": 4.66, "q2": 4.76, "iq": (0.5, -0.4), "setpoint": (4.5, 4.9)}
    per_call = []
    for _ in range(15):
        view._queue.clear()
        t0 = time.perf_counter()
        for _ in range(10_000):
            view.on_sample(sample)
        per_call.append((time.perf_counter() - t0) / 10_000)
    return {"median_s": statistics.median(per_call), "min_s": min(per_call), "max_s": max(per_call),
            "runs": len(per_call), "target_s": 20e-6}


def bench_liveview_sampling():
    """A 3 s experiment loop paced at 500 Hz (liveview.replay, sleeping between samples)
    with a LiveView redrawing at 10 Hz, against the same loop without a view: the achieved
    median sample period (target: the requested 2 ms, within 1 %), how late samples came
    (99th percentile, maximum), the achieved redraw rate and one drawing's cost. Both
    renderers; "time" is the process renderer's median period."""
    leg, run = _liveview_run()
    out = {}
    for mode in ("none", "process", "thread"):
        rows = []
        for _ in range(3):
            view = None if mode == "none" else liveview.LiveView(leg=leg, renderer=mode).start()
            r = liveview.replay(run, (lambda s: None) if view is None else view.on_sample, setpoint=(leg.q1, leg.q2))
            if view is not None:
                st = view.stop()
                r.update(redraw_rate_hz=st["redraw_rate_hz"], draw_median_s=st["draw_median_s"],
                         dropped=st["dropped"])
            rows.append(r)
        out[mode] = {k: statistics.median(r[k] for r in rows) for k in rows[0]}
        print(f"      {mode:8s} period {out[mode]['achieved_period_s'] * 1e3:.4f} ms, late p99 "
              f"{out[mode]['late_p99_s'] * 1e3:.2f} ms, max {out[mode]['late_max_s'] * 1e3:.2f} ms"
              + (f", redraws {out[mode]['redraw_rate_hz']:.1f} Hz, drawing {out[mode]['draw_median_s'] * 1e3:.1f} ms"
                 if mode != "none" else ""))
    p = out["process"]["achieved_period_s"]
    return {"median_s": p, "min_s": p, "max_s": p, "runs": 3, "target_s": 0.002 * 1.01, **out}


def bench_twin_unmodeled_effects():
    """The thesis grid (400 steps) on the twin's kernel with every unmodeled effect on
    (plant_bench: compliant belt, cogging, encoder error, LuGre) against the default plant
    (all off); reported: the bench plant's median and the ratio of CPU medians (target <= 2)."""
    grid = lg.thesis_grid()
    default, bench = Twin("default", seed=1), Twin("bench", seed=1)
    off = timed(lambda: default.step_batch(grid), repeat=3)
    on = timed(lambda: bench.step_batch(grid), repeat=3)
    print(f"      effects off {off['median_s']:.3f} s, on {on['median_s']:.3f} s (cpu x "
          f"{on['cpu_median_s'] / off['cpu_median_s']:.2f})")
    return {**on, "off_median_s": off["median_s"], "off_cpu_median_s": off["cpu_median_s"],
            "cpu_ratio": on["cpu_median_s"] / off["cpu_median_s"], "cpu_ratio_target": 2.0, "points": len(grid)}


FIRST_RESULT = """
import numpy as np
import leglib as lg
from leglib.identify.step import second_order
dev = lg.connect("virtual", seed=1)
lg.configure(dev)
lg.calibrate(dev)
r = lg.step_response(dev, 50.0, 0.046, 0.001)
print(second_order(np.asarray(r.t), np.asarray(r.y)))
"""


def bench_first_result():
    """A newcomer's first result in a new process on a fresh install: connect, configure and
    calibrate the twin, one step, its second-order fit (target <= 10 s). The install is
    ``make venv``, which ends with ``python -m leglib compile`` (its time reported beside);
    each run in an empty numba cache of its own. Reported for reference: the same first
    result with no compile at install (numba compiles at first use)."""
    import shutil
    import tempfile

    from .fresh import REPO, timed_run
    from .fresh import env as fresh_env

    compile_s, first_s, no_install_s = [], [], []
    for _ in range(3):
        cache = tempfile.mkdtemp(prefix="bench_numba_cache_")
        try:
            environ = fresh_env(REPO, NUMBA_CACHE_DIR=cache, MPLCONFIGDIR=tempfile.mkdtemp(prefix="bench_mpl_"))
            compile_s.append(timed_run(["-m", "leglib", "compile"], REPO, environ))
            first_s.append(timed_run(["-c", FIRST_RESULT], REPO, environ))
        finally:
            shutil.rmtree(cache, ignore_errors=True)
        cache = tempfile.mkdtemp(prefix="bench_numba_cache_")
        try:
            environ = fresh_env(REPO, NUMBA_CACHE_DIR=cache, MPLCONFIGDIR=tempfile.mkdtemp(prefix="bench_mpl_"))
            no_install_s.append(timed_run(["-c", FIRST_RESULT], REPO, environ))
        finally:
            shutil.rmtree(cache, ignore_errors=True)
    med = statistics.median
    print(f"      install's compile median {med(compile_s):.1f} s; first result after it median {med(first_s):.1f} s; "
          f"with no compile at install median {med(no_install_s):.1f} s")
    return {"median_s": med(first_s), "min_s": min(first_s), "max_s": max(first_s), "runs": len(first_s),
            "target_s": 10.0, "install_compile_s": compile_s, "install_compile_median_s": med(compile_s),
            "no_install_compile_s": no_install_s, "no_install_compile_median_s": med(no_install_s)}


def bench_make_run():
    """``make run`` on a fresh clone right after its install (``python -m leglib compile``, as
    make venv ends; numba's and matplotlib's caches otherwise empty) against the same run
    again, warm: each run a new process as make's (targets: warm <= 55 s, half of the
    1 min 50 s it took before the notebooks ran two at a time; cold <= 1.3 x warm)."""
    import shutil
    import tempfile

    from .fresh import clone, env, timed_run

    cold, warm = [], []
    for _ in range(3):
        tmp = tempfile.mkdtemp(prefix="bench_make_run_")
        try:
            path, _ = clone(tmp)
            environ = env(path)
            timed_run(["-m", "leglib", "compile"], path, environ)
            cold.append(timed_run(["-m", "leglib", "run", "--out", str(path / "out1")], path, environ))
            warm.append(timed_run(["-m", "leglib", "run", "--out", str(path / "out2")], path, environ))
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    med = statistics.median
    ratio = med(cold) / med(warm)
    print(f"      cold median {med(cold):.1f} s, warm median {med(warm):.1f} s: cold / warm = {ratio:.2f} "
          f"(target <= 1.3)")
    return {"median_s": med(warm), "min_s": min(warm), "max_s": max(warm), "runs": len(warm), "target_s": 55.0,
            "cold_s": cold, "cold_median_s": med(cold), "cold_over_warm": ratio, "cold_over_warm_target": 1.3}


def bench_slider():
    """From a slider's release to the redrawn figure in JupyterLab (Chromium), notebooks 03
    and 04: the browser test's slider sessions, seven moves each (target <= 0.2 s for each
    notebook's median; reported: the slower notebook's moves)."""
    import subprocess
    slider_times = Path(__file__).resolve().parents[1] / "reports" / "browser" / "slider_times.json"
    subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:xdist", "-p", "no:cacheprovider",
                    "tests/notebook/test_browser.py", "-k", "slider"], check=True,
                   cwd=slider_times.parents[2], stdout=subprocess.DEVNULL)
    record = json.loads(slider_times.read_text())
    slower = max(record, key=lambda k: record[k]["median_s"])
    times = record[slower]["times_s"]
    print("      " + "; ".join(f"{k} ({v['slider']}): median {v['median_s'] * 1e3:.0f} ms of {len(v['times_s'])} moves"
                              for k, v in sorted(record.items())))
    return {"median_s": statistics.median(times), "min_s": min(times), "max_s": max(times), "runs": len(times),
            "target_s": 0.2, "slower": slower, "notebooks": {k: v["median_s"] for k, v in record.items()}}


def bench_suite():
    """The test suite on a fresh clone of HEAD (benchmarks.suite: it compiles the kernels
    first, as a fresh clone's make test does after make venv): one run of several minutes,
    not a median (target <= 5 min)."""
    from . import suite
    r = suite.run([])
    if r["returncode"]:
        raise RuntimeError(f"the suite failed on a fresh clone of {r['commit']}: {r['summary']}")
    return {"median_s": r["wall_s"], "min_s": r["wall_s"], "max_s": r["wall_s"], "runs": 1, "target_s": 300.0,
            "cpu_s": r["cpu_s"], "summary": r["summary"], "load_before": r["load_before"],
            "load_after": r["load_after"]}


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
        target = res.get("target_s")
        # a ratio a benchmark is also held to ("<name>" and "<name>_target", e.g. cold over warm)
        ratios = {k[:-7]: (res[k[:-7]], v) for k, v in res.items() if k.endswith("_target") and k[:-7] in res}
        met = (target is None or res["median_s"] <= target) and all(x <= lim for x, lim in ratios.values())
        ok = "ref " if target is None and not ratios else "ok  " if met else "MISS"
        # milliseconds, or microseconds for what is measured in them (a tick, a callback)
        scale, unit = (1e6, "us") if res["median_s"] < 1e-4 else (1e3, "ms")
        print(f"[{ok}] {name:26s} median {res['median_s'] * scale:9.3g} {unit}  "
              f"(min {res['min_s'] * scale:.3g}, max {res['max_s'] * scale:.3g}, n={res['runs']}"
              + (f"; target {target * scale:.3g} {unit}" if target is not None else "")
              + "".join(f"; {k} {x:.2f}, target <= {lim:g}" for k, (x, lim) in ratios.items()) + ")")
    table = side_by_side(results)
    if table:
        print(table)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "latest.json").write_text(json.dumps(results, indent=2))
    if table:
        (RESULTS / "latest.txt").write_text(table + "\n")
    return 0


def side_by_side(results: dict) -> str:
    """The thesis grid's figures of this run against the numpy loop of one axis (empty
    when that reference was not run)."""
    ref = results.get("numpy_single_axis")
    if ref is None:
        return ""
    base = ref["median_s"]
    rows = [("numpy loop, one axis, 400 points (reference)", base, ref.get("cpu_median_s"))]
    for name, label, per_point in (
            ("thesis_pipeline_files", "pipeline: sweep to files, from_measurements, gains_for", False),
            ("sweep_map_pipeline", "pipeline in memory: twin, identify_many, map, gains_for", False),
            ("twin_thesis_grid", "twin kernel, 400 steps of two axes", False),
            ("identify_thesis_grid", "identification, 400 responses (one batch)", False),
            ("second_order", "second_order, one 750-sample response", False),
            ("vs_solve_ivp", "solve_ivp point by point x 400 (extrapolated)", True)):
        if name not in results:
            continue
        r = results[name]
        if per_point:
            rows.append((label, r["solve_ivp_per_point_s"] * 400, None))
        else:
            rows.append((label, r["median_s"], r.get("cpu_median_s")))
    lines = ["", "thesis grid (400 points), medians of this run, against the numpy loop of one axis",
             f"{'':58s} {'wall':>12s} {'x numpy':>9s} {'cpu':>12s}"]
    for label, sec, cpu in rows:
        c = f"{cpu * 1e3:9.2f} ms" if cpu is not None else f"{'':12s}"
        lines.append(f"{label:58s} {sec * 1e3:9.2f} ms {sec / base:9.4f} {c}")
    if "second_order" in results:
        lines.append(f"{'numpy loop / 400 (per-response budget)':58s} {base / 400 * 1e3:9.3f} ms")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
