"""The virtual leg: firmware-like behaviour, analytic cascade, batch == single, faults."""

import time

import control
import numpy as np
import pytest

import leglib as lg
from leglib import kernelmath as K
from leglib.abort import oscillation_update
from leglib.device.virtual import firmware as V
from leglib.model import cascade
from leglib.params import load_plant
from leglib.twin import layout as L
from leglib.twin.host import ABORT_NONE, Twin, _run_serial, seeds_for
from leglib.twin.kernel import _plain_block, _vector_block
from leglib.twin.rng import _seed_words


def _frictionless_single_axis():
    return load_plant("default", viscous1=0.0, viscous2=0.0, coulomb1=0.0, coulomb2=0.0).replace(
        mechanism="independent")


@pytest.mark.parametrize("gains", [(20, 0.05, 0.1), (50, 0.02, 0.05), (30, 0.1, 0.5)])
def test_single_axis_matches_analytic_cascade(gains):
    tw = Twin(_frictionless_single_axis(), noise=False)
    a_q1 = tw.axes.axis_of_joint[0]
    step = 0.05
    out = tw.step_batch([gains], step_turns=step, duration=0.6, sample_period=0.0005)
    t = out["t"]
    pos = out["counts"][0, :, a_q1] / tw.axes.cpr
    sys = cascade.axis_closed_loop(cascade.motor_side_inertia(tw.FR[11], tw.axes.gear_ratio),
                                   tw.motor.torque_constant, *gains,
                                   current_bandwidth=tw.config.current_control_bandwidth,
                                   encoder_bandwidth=tw.config.encoder_bandwidth)
    ref = control.forced_response(sys, t, np.full(t.size, step)).outputs
    assert np.max(np.abs(pos - ref)) < 0.02 * step
    assert np.ptp(pos) > 0.9 * step  # it really moved


def test_batch_gives_the_same_numbers_as_single_points():
    tw = Twin(seed=7)
    grid = np.array([[20, 0.02, 0.01], [50, 0.046, 0.001], [35, 0.1, 0.05]])
    batch = tw.step_batch(grid)
    for i, g in enumerate(grid):
        single = tw.step_batch([g])
        np.testing.assert_array_equal(single["counts"][0], batch["counts"][i])


def test_seeded_noise_and_quantization():
    a = Twin(seed=1).step_batch([[50, 0.046, 0.001]])["counts"]
    b = Twin(seed=1).step_batch([[50, 0.046, 0.001]])["counts"]
    c = Twin(seed=2).step_batch([[50, 0.046, 0.001]])["counts"]
    np.testing.assert_array_equal(a, b)
    assert np.any(a != c)
    assert np.all(a == np.round(a))  # encoder counts are integers


def test_plant_differs_from_nominal_model():
    tw = Twin()
    assert tw.leg.c11 != tw.nominal_leg.c11 and tw.leg.Jd1 != tw.nominal_leg.Jd1
    assert tw.leg.coulomb1 > 0


def test_payload_moves_the_leg_differently():
    light = Twin().step_batch([[50, 0.046, 0.001]])["counts"]
    heavy = Twin(load_plant("default", payload_mass=0.5)).step_batch([[50, 0.046, 0.001]])["counts"]
    assert np.max(np.abs(light - heavy)) > 20


@pytest.fixture
def odrv():
    dev = V.VirtualODrive(seed=0)
    for a in (dev.axis0, dev.axis1):
        a.encoder.config.cpr = 4000
        a.motor.config.pole_pairs = 11
    dev.config.enable_brake_resistor = True
    dev.clear_errors()   # arms the brake resistor
    return dev


def _calibrate(odrv):
    for a in (odrv.axis0, odrv.axis1):
        a.requested_state = V.AXIS_STATE_FULL_CALIBRATION_SEQUENCE
    odrv.sleep(V.CALIBRATION_DURATION + 0.1)


def _closed_loop(odrv, ax):
    ax.requested_state = V.AXIS_STATE_CLOSED_LOOP_CONTROL
    odrv.sleep(0.002)   # the axis thread takes the request up within 1 ms


def test_object_tree_is_strict(odrv):
    with pytest.raises(AttributeError, match="no attribute 'pos_gian'"):
        odrv.axis0.controller.config.pos_gian = 3
    with pytest.raises(AttributeError):
        odrv.axis0.encoder.pos_estimate_typo
    with pytest.raises(AttributeError, match="read-only"):
        odrv.axis0.encoder.pos_estimate = 1.0
    with pytest.raises(TypeError):
        odrv.axis0.controller.config.pos_gain = "fast"
    with pytest.raises(ValueError, match="vel_limit"):
        odrv.axis0.controller.config.vel_limit = float("nan")
    odrv.axis0.controller.config.pos_gain = 33
    assert odrv.axis0.controller.config.pos_gain == 33.0
    assert odrv.fw_version_minor == 5 and odrv.fw_version_revision == 6
    assert odrv.config.brake_resistance == pytest.approx(2.0)   # DEFAULT_BRAKE_RESISTANCE


def test_state_machine_calibration_takes_time_and_gates_closed_loop(odrv):
    _closed_loop(odrv, odrv.axis0)
    assert odrv.axis0.current_state == V.AXIS_STATE_IDLE
    assert odrv.axis0.error & V.AXIS_ERROR_INVALID_STATE
    odrv.axis0.requested_state = V.AXIS_STATE_FULL_CALIBRATION_SEQUENCE
    odrv.axis1.requested_state = V.AXIS_STATE_FULL_CALIBRATION_SEQUENCE
    odrv.sleep(0.002)
    assert odrv.axis0.current_state == V.AXIS_STATE_MOTOR_CALIBRATION
    assert not odrv.axis0.error & V.AXIS_ERROR_INVALID_STATE   # cleared by the new request
    odrv.sleep(V.R_MEASUREMENT_TIME + V.L_MEASUREMENT_TIME + 0.5)
    assert odrv.axis0.current_state == V.AXIS_STATE_ENCODER_OFFSET_CALIBRATION
    assert odrv.axis0.motor.is_calibrated and not odrv.axis0.encoder.is_ready
    odrv.sleep(V.CALIBRATION_DURATION)
    assert odrv.axis0.current_state == V.AXIS_STATE_IDLE and odrv.axis0.encoder.is_ready
    _closed_loop(odrv, odrv.axis0)
    assert odrv.axis0.current_state == V.AXIS_STATE_CLOSED_LOOP_CONTROL


def test_wrong_cpr_fails_calibration():
    odrv = V.VirtualODrive()
    odrv.axis0.encoder.config.cpr = 8192  # the encoder has 4000
    odrv.axis0.motor.config.pole_pairs = 11
    odrv.axis0.requested_state = V.AXIS_STATE_FULL_CALIBRATION_SEQUENCE
    odrv.sleep(V.CALIBRATION_DURATION + 0.1)
    assert odrv.axis0.encoder.error & V.ENCODER_ERROR_CPR_POLEPAIRS_MISMATCH
    assert odrv.axis0.error & V.AXIS_ERROR_ENCODER_FAILED
    assert not odrv.axis0.encoder.is_ready


def test_watchdog_trips_when_not_fed(odrv):
    _calibrate(odrv)
    ax = odrv.axis1
    ax.config.watchdog_timeout = 0.1
    ax.watchdog_feed()
    ax.config.enable_watchdog = True
    _closed_loop(odrv, ax)
    for _ in range(10):
        odrv.sleep(0.05)
        ax.watchdog_feed()
    assert ax.current_state == V.AXIS_STATE_CLOSED_LOOP_CONTROL
    odrv.sleep(0.2)
    assert ax.current_state == V.AXIS_STATE_IDLE
    assert ax.error & L.AXIS_ERROR_WATCHDOG_TIMER_EXPIRED


def test_overspeed_drops_axis_to_idle(odrv):
    _calibrate(odrv)
    ax = odrv.axis1
    ax.controller.config.vel_limit = 12.0
    ax.controller.config.pos_gain = 50.0
    ax.controller.config.vel_gain = 0.05
    _closed_loop(odrv, ax)
    ax.controller.input_pos = ax.encoder.pos_estimate + 0.4
    odrv.sleep(0.03)
    assert abs(ax.encoder.vel_estimate) > 1.0
    ax.controller.config.vel_limit = 0.5
    odrv.sleep(0.01)
    assert ax.current_state == V.AXIS_STATE_IDLE
    assert ax.controller.error & L.CONTROLLER_ERROR_OVERSPEED
    assert ax.error & L.AXIS_ERROR_CONTROLLER_FAILED


def test_current_limit_violation_sets_motor_error():
    odrv = V.VirtualODrive(plant=load_plant("default", current_noise=8.0))
    for a in (odrv.axis0, odrv.axis1):
        a.encoder.config.cpr = 4000
        a.motor.config.pole_pairs = 11
    odrv.config.enable_brake_resistor = True
    odrv.clear_errors()
    _calibrate(odrv)
    odrv.clear_errors()   # the noisy calibration current may have flagged too
    odrv.axis0.motor.config.current_lim = 1.0
    _closed_loop(odrv, odrv.axis0)
    odrv.sleep(0.05)
    assert odrv.axis0.motor.error & L.MOTOR_ERROR_CURRENT_LIMIT_VIOLATION
    assert odrv.axis0.current_state == V.AXIS_STATE_IDLE


def test_virtual_clock_is_fast_and_realtime_mode_paces():
    odrv = V.VirtualODrive()
    t0 = time.monotonic()
    odrv.sleep(1.5)
    assert time.monotonic() - t0 < 0.5
    rt = V.VirtualODrive(realtime=True)
    t0 = time.monotonic()
    rt.sleep(0.2)
    assert time.monotonic() - t0 >= 0.19
    assert rt.time >= 0.2 - 1e-9


def test_a_realtime_sleep_takes_its_seconds_after_a_busy_host():
    """The board runs on while the host is busy; a sleep that follows still waits all its
    seconds from the call, as a real host's does (it waited only the rest: 0.15 s of 0.2 s
    after 50 ms of host work)."""
    rt = V.VirtualODrive(realtime=True)
    t = time.monotonic()
    while time.monotonic() - t < 0.05:   # the host busy, the virtual board idle
        pass
    t0 = time.monotonic()
    rt.sleep(0.2)
    assert time.monotonic() - t0 >= 0.2 - 1e-3
    assert rt.time >= 0.25 - 1e-3   # the 50 ms the board ran on, then the 0.2 s asked for


def test_each_transaction_costs_latency(odrv):
    t0 = odrv.time
    for _ in range(100):
        odrv.axis0.encoder.shadow_count
    lat = odrv.twin.plant.usb_latency
    assert 80 * lat < odrv.time - t0 < 120 * lat


def test_kernel_elementary_functions_match_the_math_module():
    """The tick loop's inlined sin/cos and tanh are within a few ulp of the library's."""
    import math

    from numba import njit


    @njit
    def worst_ulp(xs):
        e_sc, e_th = 0.0, 0.0
        for x in xs:
            s, c = K.sincos(x)
            e_sc = max(e_sc, abs(s - math.sin(x)) / np.spacing(1.0), abs(c - math.cos(x)) / np.spacing(1.0))
            t, r = K.tanh(x), math.tanh(x)
            if r != 0.0:
                e_th = max(e_th, abs(t - r) / np.spacing(abs(r)))
        return e_sc, e_th

    rng = np.random.default_rng(0)
    for scale in (1e-6, 0.5, 1.0, 8.0, 30.0, 200.0):
        e_sc, e_th = worst_ulp(rng.uniform(-scale, scale, 200_000))
        assert e_sc <= 1.0 and e_th <= 4.0, (scale, e_sc, e_th)   # sin, cos: absolute, in eps
    assert K.tanh(25.0) == 1.0 and K.tanh(-25.0) == -1.0 and math.isnan(K.tanh(math.nan))
    assert K.sincos(0.0) == (0.0, 1.0)


def _monitor(signal, min_amp=0.01):
    st = np.zeros(L.N_OSC)
    return any(oscillation_update(st, e, min_amp) for e in signal)


@pytest.mark.parametrize("zeta", [0.05, 0.2, 0.7])
def test_oscillation_monitor_passes_damped_responses(zeta):
    from leglib.identify.step import model as _model
    t = np.arange(12000) / 8000
    err = 0.4 - _model(t, zeta, 30.0, 0.4, 0.0, 0.0)
    assert not _monitor(err)


@pytest.mark.parametrize("growth", [1.0, 1.3])
def test_oscillation_monitor_flags_sustained_and_growing(growth):
    t = np.arange(12000) / 8000
    env = 0.2 * growth ** t
    err = 0.4 * np.exp(-20 * t) + env * np.sin(2 * np.pi * 3 * t) * (1 - np.exp(-20 * t))
    assert _monitor(err)


def test_the_polled_path_on_the_twin_agrees_with_the_batched_path():
    """step_response(path="polled") is the real leg's polling loop; path="batched" the twin's
    kernel running the whole step: the same responses, up to the polling loop's timing."""
    dev = lg.connect("virtual", seed=8, noise=False)
    lg.configure(dev)
    lg.calibrate(dev)
    polled = lg.step_response(dev, 50.0, 0.046, 0.001, vel_limit=12.0, path="polled")
    batch = lg.step_response(dev, 50.0, 0.046, 0.001, path="batched")
    assert polled.completed
    n = min(len(polled.t), len(batch.t))
    # same leg, same gains: the responses agree up to the polling loop's timing
    # the leg falls back to a rest pose a little different each time (friction): compare
    # the motion from where each step started
    moved_polled = polled.q2[:n] - polled.q2[0]
    moved_batch = np.interp(polled.t[:n], batch.t, batch.q2 - batch.q2[0])
    assert np.max(np.abs(moved_polled - moved_batch)) < np.radians(2.0)
    unstable = lg.step_response(dev, 50.0, 0.002, 0.08, vel_limit=12.0, path="polled")
    assert not unstable.completed and "oscillation" in unstable.abort_reason
    assert all(int(dev.get(a, "current_state")) == 1 for a in (0, 1))


def test_a_vectorized_block_gives_the_leg_by_leg_numbers():
    """A block of legs that share a plain plant, every axis in position control or IDLE,
    runs vectorized (_run_block_vector: controllers and mechanics each one loop over the
    legs, branches turned into selects); a block holding one leg of another plant runs leg
    by leg (_run_block). For the same legs both give the same numbers, bit for bit, through
    every event the vectorized controller handles: noise, the safety abort, overspeed, a
    regenerative bus fault (both error styles), an axis left IDLE."""
    tw = Twin(seed=4)
    gains = np.array([[20, 0.02, 0.01], [50, 0.046, 0.001], [35, 0.1, 0.05], [200, 0.5, 5.0],
                      [5, 0.001, 0.0], [80, 0.03, 0.2], [12, 0.2, 0.0], [60, 0.06, 0.02], [40, 0.01, 0.3]])
    B = len(gains)
    start = tw.step_batch(gains, duration=0.0)["final"]   # prepared for the step, not yet run
    start.C[1, :, L.C_VEL_TOL] = 0.02                     # overspeed at once
    start.C[2, 0, L.C_BRAKE_ON] = 0.0                     # no brake resistor: regen trips the bus
    start.C[6, 0, L.C_BRAKE_ON] = 0.0
    start.C[6, 0, L.C_REGEN_ERR_STYLE] = 1.0              # ... with 0.5.1's error flags
    start.AI[7, 1, L.I_MODE] = L.MODE_IDLE                # one axis left IDLE

    def run(st, P, FR, block):
        rec = np.zeros((st.batch, 400, 5))
        _run_serial(4000, tw.dt, st.X, st.AS, st.AI, st.C, P, FR, np.zeros(st.batch, np.int64), tw.DRV,
                      st.RNG, st.ABORT, np.zeros((st.batch, 0, 2)), 1, rec, 10, 0, block)
        return st, rec

    P = np.ascontiguousarray(np.broadcast_to(tw.P, (B + 1, tw.P.size)))
    FR = np.ascontiguousarray(np.broadcast_to(tw.FR, (B + 1, tw.FR.size)))
    FR[B, 0] *= 1.5   # one more leg, of another plant: its block is not plain
    MECH = np.zeros(B + 1, np.int64)
    mixed = start.take(list(range(B)) + [0])
    assert _plain_block(0, B, P, FR, MECH) and _vector_block(0, B, FR, start.C, start.AI)
    assert not _plain_block(0, B + 1, P, FR, MECH)
    vec, rec_vec = run(start.copy(), P[:B], FR[:B], B)
    leg, rec_leg = run(mixed, P, FR, B + 1)
    # the events happened
    assert (vec.ABORT[:, 1] != ABORT_NONE).sum() >= 1
    assert vec.AI[1, 0, L.I_CTRL_ERR] & L.CONTROLLER_ERROR_OVERSPEED
    assert vec.AI[2, 0, L.I_SYS_ERR] & L.ODRIVE_ERROR_DC_BUS_OVER_REGEN_CURRENT
    assert vec.AI[6, 0, L.I_MOTOR_ERR] & L.MOTOR_ERROR_DC_BUS_OVER_REGEN_CURRENT
    assert vec.AI[7, 0, L.I_MODE] == L.MODE_POSITION and vec.AI[7, 1, L.I_MODE] == L.MODE_IDLE
    # and came out the same
    np.testing.assert_array_equal(rec_vec, rec_leg[:B])
    for name in ("X", "AS", "AI", "ABORT", "RNG"):
        np.testing.assert_array_equal(getattr(vec, name), getattr(leg, name)[:B], err_msg=name)


def test_leg_seeds_are_numpys_seed_sequence_for_every_leg():
    """Each leg's state is SeedSequence's for that leg's words, whatever the batch."""
    rng = np.random.default_rng(0)

    def one_by_one(seed, keys):
        return np.array([np.random.SeedSequence(_seed_words(seed, k)).generate_state(1, np.uint64)[0]
                         | np.uint64(1) for k in keys], dtype=np.uint64)

    for _ in range(150):
        m, n = int(rng.integers(0, 7)), int(rng.integers(1, 20))
        keys = [tuple(float(rng.choice([0.0, -0.0, 0.5e-6, 1.5e-6, -2.5e-6])) if rng.random() < 0.2
                      else rng.normal(0, 10 ** rng.uniform(-7, 6)) for _ in range(m)) for _ in range(n)]
        seed = int(rng.integers(-2 ** 40, 2 ** 40))
        np.testing.assert_array_equal(seeds_for(seed, keys), one_by_one(seed, keys))
    from leglib.experiments.sweep import thesis_grid
    keys = [tuple(g) + (0.4, 1.5) for g in thesis_grid()]
    np.testing.assert_array_equal(seeds_for(11, keys), one_by_one(11, keys))
