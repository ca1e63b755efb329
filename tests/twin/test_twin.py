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
from leglib.params import load_motor, load_plant
from leglib.twin import layout as L
from leglib.twin.host import ABORT_NONE, Twin, _run_serial, seeds_for
from leglib.twin.kernel import _plain_block, _vector_block
from leglib.twin.mechanics import _shared_block
from leglib.twin.rng import _seed_words


def _frictionless_single_axis():
    return load_plant("default", viscous1=0.0, viscous2=0.0, coulomb1=0.0, coulomb2=0.0).replace(
        mechanism="independent")


def _axis_with_current_pi(J, kt, R, L, bw, bw_e, Kp, Kv, Ki) -> control.StateSpace:
    """One axis in position control as continuous linear dynamics, with the firmware's
    current loop: the PI of motor.cpp:297-302 (p = bw L, i = bw R) on the motor's RL phase
    against its back-EMF ((2/3) kt per rad/s, the flux linkage of motor.cpp:585).
    States: position, velocity [turn, turn/s], current [A], the PI's integrator [V], the
    PLL's position and velocity, the velocity integrator [N*m]; input input_pos [turn]."""
    kp_e, ki_e = cascade.pll_gains(bw_e)
    kpc, kic = bw * L, bw * R
    emf = (2.0 / 3.0) * kt * 2.0 * np.pi          # [V per turn/s]
    A, B = np.zeros((7, 7)), np.zeros((7, 1))
    A[0, 1] = 1.0
    A[1, 2] = kt / J
    isp_x = np.array([0, 0, 0, 0, -Kv * Kp, -Kv, 1.0]) / kt   # Iq setpoint: torque / kt
    isp_r = Kv * Kp / kt
    v_x = kpc * isp_x
    v_x[2] -= kpc
    v_x[3] += 1.0                                             # v = z + kp (isp - i)
    A[2] = v_x / L
    A[2, 2] -= R / L
    A[2, 1] -= emf / L                                        # L i' = v - R i - e
    B[2, 0] = kpc * isp_r / L
    A[3] = kic * isp_x
    A[3, 2] -= kic
    B[3, 0] = kic * isp_r
    A[4, [0, 4, 5]] = kp_e, -kp_e, 1.0
    A[5, [0, 4]] = ki_e, -ki_e
    A[6, [4, 5]] = -Ki * Kp, -Ki
    B[6, 0] = Ki * Kp
    return control.ss(A, B, np.eye(7)[:1], [[0.0]])


@pytest.mark.parametrize("gains", [(20, 0.05, 0.1), (50, 0.02, 0.05), (30, 0.1, 0.5)])
def test_single_axis_matches_analytic_cascade(gains):
    """A frictionless single axis follows the cascade's linear dynamics with the firmware's
    current PI on the motor's R, L and back-EMF to 1 % of the step (an encoder count is
    0.5 %; the rest is the kernel's discrete time and the PWM's half-period delay). The
    first-order current loop of leglib.model.cascade lacks the back-EMF, which the PI
    rejects only at its bandwidth: at vel_gain 0.02 it adds damping worth 3 % of the step."""
    tw = Twin(_frictionless_single_axis(), noise=False)
    a_q1 = tw.axes.axis_of_joint[0]
    step = 0.05
    out = tw.step_batch([gains], step_turns=step, duration=0.6, sample_period=0.0005)
    t = out["t"]
    pos = out["counts"][0, :, a_q1] / tw.axes.cpr
    J = cascade.motor_side_inertia(tw.FR[11], tw.axes.gear_ratio)
    sys = _axis_with_current_pi(J, tw.motor.torque_constant, tw.motor.phase_resistance, tw.motor.phase_inductance,
                                tw.config.current_control_bandwidth, tw.config.encoder_bandwidth, *gains)
    ref = control.forced_response(sys, t, np.full(t.size, step)).outputs
    assert np.max(np.abs(pos - ref)) < 0.01 * step
    assert np.ptp(pos) > 0.9 * step  # it really moved
    first_order = cascade.axis_closed_loop(J, tw.motor.torque_constant, *gains,
                                           current_bandwidth=tw.config.current_control_bandwidth,
                                           encoder_bandwidth=tw.config.encoder_bandwidth)
    ideal = control.forced_response(first_order, t, np.full(t.size, step)).outputs
    assert np.max(np.abs(pos - ideal)) < 0.04 * step


def test_the_current_loop_delay_and_voltage_limit():
    """foc.cpp:131-154 with board.cpp:543-563: the PI's voltage reaches the motor half a
    control period after the current was sampled, and the modulation is held to 0.8 of
    sqrt(3)/2 (a voltage of 0.46 vbus). A stalled rotor asked for 10 A: the first tick's
    current is what half a period of the new voltage gives; with vbus 24 V the current
    settles at 10 A; with vbus 1 V it stops at 0.46 V / R and the PI's integrator, decaying
    (x 0.99) whenever the voltage is limited, stays below the limit instead of winding up (it
    would reach 1.1 V in the 40 ticks)."""
    tw = Twin(_frictionless_single_axis(), noise=False)
    R, Lm = tw.motor.phase_resistance, tw.motor.phase_inductance
    kt = tw.config.torque_constant
    results = {}
    for vbus in (24.0, 1.0):
        st = tw.step_batch([[20, 0.05, 0.0]], step_turns=0.0, duration=0.0)["final"]
        st.C[0, :, L.C_VBUS] = vbus
        st.C[0, :, L.C_CONTROL_MODE] = L.CONTROL_MODE_TORQUE
        st.AI[0, :, L.I_MODE] = L.MODE_TORQUE
        st.C[0, :, L.C_INPUT_TORQUE] = 10.0 * kt
        st.C[0, :, L.C_VEL_LIMIT] = 1e6                      # no torque-mode velocity limiter
        st.C[0, 0, L.C_DC_MAX_POS] = np.inf
        iq = []
        for _ in range(40):
            st.X[0, [L.X_DQ1, L.X_DQ2]] = 0.0                 # the rotor held: no back-EMF
            tw.run(st, ticks=1)
            iq.append(st.AS[0, 0, L.S_IQ])
        results[vbus] = (np.array(iq), float(st.AS[0, 0, L.S_V_INT]))
    iq24, _ = results[24.0]
    v0 = tw.config.current_control_bandwidth * Lm * 10.0    # the first PI output: p_gain * error
    a = np.exp(-R * tw.dt / (2 * Lm))
    assert iq24[0] == pytest.approx(v0 / R * (1 - a), rel=1e-9)           # half a period of it
    assert iq24[-1] == pytest.approx(10.0, abs=0.3)
    iq1, integ1 = results[1.0]
    vmax = 0.8 * np.sqrt(3) / 2 * 2 / 3 * 1.0
    assert iq1[-1] == pytest.approx(vmax / R, rel=0.02) and iq1.max() <= vmax / R * 1.001
    assert 0.0 < integ1 < vmax


def test_the_assumed_motor_inductance_does_not_matter():
    """The motor's phase inductance is assumed (leglib/params/motor_mn5212.toml): with the
    current PI's gains from the calibrated R and L (motor.cpp:297-302) the loop responds at
    its bandwidth whatever L is, so 10 or 100 uH instead of 25 move step responses by a
    few counts at most (3 over the whole thesis grid)."""
    grid = lg.thesis_grid()[[0, 57, 133, 261, 399]]
    runs = [Twin(seed=3, motor=load_motor("mn5212", phase_inductance=h)).step_batch(grid)["counts"]
            for h in (10e-6, 25e-6, 100e-6)]
    assert np.abs(runs[0] - runs[1]).max() <= 4 and np.abs(runs[2] - runs[1]).max() <= 4
    assert np.abs(runs[0] - runs[1]).max() > 0        # it is in the loop


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
    """The tick loop's inlined sin/cos, tanh and exp are within a few ulp of the library's."""
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

    @njit
    def worst_ulp_exp(xs):
        e = 0.0
        for x in xs:
            r = math.exp(x)
            e = max(e, abs(K.exp(x) - r) / np.spacing(r))   # subnormal results: in their spacing
        return e

    @njit
    def exp1(x):
        return K.exp(x)

    rng = np.random.default_rng(0)
    for scale in (1e-6, 0.5, 1.0, 8.0, 30.0, 200.0):
        e_sc, e_th = worst_ulp(rng.uniform(-scale, scale, 200_000))
        assert e_sc <= 1.0 and e_th <= 4.0, (scale, e_sc, e_th)   # sin, cos: absolute, in eps
    for lo, hi in ((-1e-6, 1e-6), (-1.0, 1.0), (-40.0, 40.0), (-745.3, -700.0), (700.0, 709.78), (-750.0, 710.0)):
        assert worst_ulp_exp(rng.uniform(lo, hi, 200_000)) <= 2.0, (lo, hi)
    assert K.tanh(25.0) == 1.0 and K.tanh(-25.0) == -1.0 and math.isnan(K.tanh(math.nan))
    assert K.sincos(0.0) == (0.0, 1.0)
    # exp's ends as math.exp's: 1 at 0, the largest finite result, overflow, the smallest
    # subnormal, underflow to 0, NaN
    assert exp1(0.0) == 1.0 and exp1(709.782712893384) == math.exp(709.782712893384)
    assert exp1(709.7827128933841) == math.inf and exp1(math.inf) == math.inf and exp1(1e300) == math.inf
    assert exp1(-745.13) == math.exp(-745.13) == 5e-324 and exp1(-745.2) == 0.0 and exp1(-math.inf) == 0.0
    assert math.isnan(exp1(math.nan))


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


def _leg_by_leg(st):
    """``st`` with its boards checking the bus voltage against trip levels out of reach
    (no source resistance, 0 V and inf): the same numbers, but kernel._board_checks is not
    on the vectorized path, so its blocks run leg by leg (_run_block, the reference)."""
    ref = st.copy()
    ref.C[:, 0, L.C_VBUS_CHECKS] = 1.0
    ref.C[:, 0, L.C_VBUS_R] = 0.0
    ref.C[:, 0, L.C_UV_TRIP] = 0.0
    ref.C[:, 0, L.C_OV_TRIP] = np.inf
    return ref


def _run_both(tw, start, P, FR, MECH, ticks=4000):
    """``start`` run through the vectorized path and, from the same state, leg by leg:
    ((state, record) vectorized, (state, record) leg by leg)."""
    def run(st):
        rec = np.zeros((st.batch, ticks // 10, 5))
        _run_serial(ticks, tw.dt, st.X, st.AS, st.AI, st.C, P, FR, MECH, tw.DRV, st.RNG, st.ABORT,
                    np.zeros((st.batch, 0, 2)), 1, rec, 10, 0, st.batch)
        return st, rec
    assert _vector_block(0, start.batch, FR, start.C, start.AI)
    ref = _leg_by_leg(start)
    assert not _vector_block(0, start.batch, FR, ref.C, ref.AI)
    return run(start.copy()), run(ref)


def _assert_same(vec, leg):
    (st_vec, rec_vec), (st_leg, rec_leg) = vec, leg
    np.testing.assert_array_equal(rec_vec, rec_leg)
    for name in ("X", "AS", "AI", "ABORT", "RNG"):
        np.testing.assert_array_equal(getattr(st_vec, name), getattr(st_leg, name), err_msg=name)


def test_a_vectorized_block_gives_the_leg_by_leg_numbers():
    """A block of legs that share a plain plant, every axis in position control or IDLE,
    runs vectorized (_run_block_vector: controllers and mechanics each one loop over the
    legs, branches turned into selects); the same legs with their boards checking the bus
    run leg by leg (_run_block). Both give the same numbers, bit for bit, through every
    event the vectorized controller handles: noise, the safety abort, overspeed, a
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
    P = np.ascontiguousarray(np.broadcast_to(tw.P, (B, tw.P.size)))
    FR = np.ascontiguousarray(np.broadcast_to(tw.FR, (B, tw.FR.size)))
    MECH = np.zeros(B, np.int64)
    assert _plain_block(0, B, P, FR, MECH)
    vec, leg = _run_both(tw, start, P, FR, MECH)
    # the events happened
    st = vec[0]
    assert (st.ABORT[:, 1] != ABORT_NONE).sum() >= 1
    assert st.AI[1, 0, L.I_CTRL_ERR] & L.CONTROLLER_ERROR_OVERSPEED
    assert st.AI[2, 0, L.I_SYS_ERR] & L.ODRIVE_ERROR_DC_BUS_OVER_REGEN_CURRENT
    assert st.AI[6, 0, L.I_MOTOR_ERR] & L.MOTOR_ERROR_DC_BUS_OVER_REGEN_CURRENT
    assert st.AI[7, 0, L.I_MODE] == L.MODE_POSITION and st.AI[7, 1, L.I_MODE] == L.MODE_IDLE
    # and came out the same
    _assert_same(vec, leg)


def _encoder_error_only():
    bench = load_plant("bench")
    return load_plant("default", encoder_error1=bench.encoder_error1, encoder_error2=bench.encoder_error2,
                      encoder_phase1=bench.encoder_phase1, encoder_phase2=bench.encoder_phase2)


@pytest.mark.parametrize("name", ["bench", "belt", "cogging", "lugre", "encoder_error", "bench_independent",
                                  "mixed"])
def test_a_vectorized_block_with_unmodeled_effects_gives_the_leg_by_leg_numbers(name):
    """Plants with unmodeled effects take the vectorized controllers too (the encoder's
    reading error computed before the axes' loop; the encoder on the rotor with a compliant
    belt), with the safety abort, an overspeed and an axis left IDLE among them.

    A block of legs that share one plant (every case but "mixed") steps its mechanics in
    loops over the legs (_mechanics_effects; _mechanics_plain when only the encoder errs),
    its encoder errors likewise; "bench_independent": bench's effects on two independent
    inertias. "mixed": a block of legs of different plants (belt, cogging, LuGre, encoder
    error, plain, independent inertias) steps its mechanics leg by leg with the reference's
    own _mechanics_leg. Every case gives the reference's numbers bit for bit: both paths
    take the effects' sines, exponentials and tanh from kernelmath, the harmonics by angle
    addition from the phases' cosines and sines in FR, in the same order."""
    gains = np.array([[20, 0.02, 0.01], [50, 0.046, 0.001], [35, 0.1, 0.05], [200, 0.5, 5.0],
                      [50, 0.002, 0.08], [80, 0.03, 0.2], [12, 0.2, 0.0], [60, 0.06, 0.02]])
    B = len(gains)       # (50, 0.002, 0.08): an oscillation the abort stops at about tick 3750
    if name == "mixed":
        plants = [load_plant(n) for n in ("bench", "belt", "cogging", "lugre")]
        plants += [_encoder_error_only(), load_plant("default"), load_plant("default").replace(mechanism="independent"),
                   load_plant("bench")]
        twins = [Twin(p, seed=4) for p in plants]
    elif name == "bench_independent":
        twins = [Twin(load_plant("bench").replace(mechanism="independent"), seed=4)] * B
    else:
        twins = [Twin(_encoder_error_only() if name == "encoder_error" else name, seed=4)] * B
    tw = twins[0]
    start = tw.step_batch(gains, duration=0.0)["final"]
    P = np.ascontiguousarray(np.stack([t.P for t in twins]))
    FR = np.ascontiguousarray(np.stack([t.FR for t in twins]))
    MECH = np.array([t.mech for t in twins], np.int64)
    for i, t in enumerate(twins):      # each leg starts at rest on its own plant
        rest = t.rest_state()
        start.X[i] = rest.X[0]
    start.C[1, :, L.C_VEL_TOL] = 0.02                     # overspeed at once
    start.AI[7, 1, L.I_MODE] = L.MODE_IDLE                # one axis left IDLE
    # the encoder's error alone leaves the mechanics plain (one vectorized loop)
    assert _plain_block(0, B, P, FR, MECH) == (name == "encoder_error")
    assert _shared_block(0, B, P, FR, MECH) == (name != "mixed")
    vec, leg = _run_both(tw, start, P, FR, MECH)
    st = vec[0]
    if name != "bench_independent":      # two independent inertias: no oscillation to abort
        assert (st.ABORT[:, 1] != ABORT_NONE).sum() >= 1
    assert st.AI[1, 0, L.I_CTRL_ERR] & L.CONTROLLER_ERROR_OVERSPEED
    assert st.AI[7, 0, L.I_MODE] == L.MODE_POSITION and st.AI[7, 1, L.I_MODE] == L.MODE_IDLE
    moved = np.abs(st.X[:, L.X_Q1] - start.X[:, L.X_Q1])
    assert (moved > 1e-3).sum() >= 4                       # the legs moved
    if name in ("bench", "belt"):                          # the rotors turned apart from the joints
        assert np.any(st.X[:, L.X_PHI1] != st.X[:, L.X_Q1])
    if name in ("bench", "lugre", "bench_independent"):
        assert np.any(st.X[:, L.X_Z1] != 0.0)
    _assert_same(vec, leg)


@pytest.mark.parametrize("name", ["bench", "belt", "cogging", "lugre"])
def test_the_thesis_grid_on_a_plant_with_effects_keeps_the_leg_by_leg_outcomes(name):
    """The thesis grid's 400 steps of 1.5 s on one plant with unmodeled effects, through the
    vectorized path (the legs share the plant: _mechanics_effects) and leg by leg (the
    reference): every point completes or aborts alike, at the same tick for the same reason,
    with the same encoder counts and error flags, and every other number bit for bit."""
    tw = Twin(name, seed=1)
    start = tw.step_batch(lg.thesis_grid(), duration=0.0)["final"]    # prepared, not yet run
    ticks, every = int(round(1.5 / tw.dt)), 16

    def run(st):
        rec = np.zeros((st.batch, ticks // every, 5))
        tw.run(st, ticks=ticks, record_every=every, record=rec)
        return st, rec

    B = start.batch
    P = np.ascontiguousarray(np.broadcast_to(tw.P, (B, tw.P.size)))
    FR = np.ascontiguousarray(np.broadcast_to(tw.FR, (B, tw.FR.size)))
    assert _shared_block(0, B, P, FR, np.full(B, tw.mech, np.int64))
    assert _vector_block(0, B, FR, start.C, start.AI)
    vec, leg = run(start.copy()), run(_leg_by_leg(start))
    aborted = vec[0].ABORT[:, 1] != ABORT_NONE
    assert 0 < aborted.sum() < B                 # both outcomes occur on the grid
    _assert_same(vec, leg)


def test_a_batch_of_one_takes_the_reference_path_and_compiles_nothing_twice(monkeypatch):
    """A batch of one (a device, a point run alone) never takes the vectorized path, even in
    a state that allows it: the vectorized path gives the reference's numbers bit for bit
    (above), and a device never compiles it. A batch of two does take it. And the constant
    arrays a batch of one and a batch of two hand the kernel have the same numba types (a
    read-only view typed apart would compile every kernel twice)."""
    from numba import typeof

    from leglib.twin import kernel
    calls = []
    monkeypatch.setattr(kernel, "_run_block_vector", lambda *a: calls.append(a[:2]))
    tw = Twin("bench", seed=2)
    one = tw.step_batch(np.array([[50, 0.046, 0.001]]), duration=0.0)["final"]
    assert _vector_block(0, 1, tw.FR[None, :], one.C, one.AI)
    before = one.X.copy()
    tw.run(one, ticks=50)
    assert calls == [] and np.any(one.X != before)
    two = tw.step_batch(np.array([[50, 0.046, 0.001]] * 2), duration=0.0)["final"]
    P2 = np.broadcast_to(tw.P, (2, tw.P.size)).copy()
    FR2 = np.broadcast_to(tw.FR, (2, tw.FR.size)).copy()
    _run_serial(5, tw.dt, two.X, two.AS, two.AI, two.C, P2, FR2, np.full(2, tw.mech, np.int64), tw.DRV, two.RNG,
                two.ABORT, np.zeros((2, 0, 2)), 1, np.zeros((2, 0, 5)), 0, 0, 2)
    assert calls == [(0, 2)]
    tw.run(tw._initial_state(2), ticks=1)
    assert [typeof(a) for a in tw._fixed[1]] == [typeof(a) for a in tw._fixed[2]]


def test_a_block_whose_board_checks_its_bus_runs_leg_by_leg():
    """kernel._board_checks (main.cpp:300-305: the bus voltage against its trip levels,
    every tick in every state) is not on the vectorized path: legs whose board checks its
    bus (a virtual ODrive's) take the leg-by-leg path, and trip there."""
    tw = Twin(seed=4)
    start = tw.step_batch(np.array([[20, 0.02, 0.01], [50, 0.046, 0.001]]), duration=0.0)["final"]
    FR = np.ascontiguousarray(np.broadcast_to(tw.FR, (2, tw.FR.size)))
    assert _vector_block(0, 2, FR, start.C, start.AI)
    start.C[:, 0, L.C_VBUS_CHECKS] = 1.0
    start.C[:, 0, L.C_OV_TRIP] = 100.0
    start.C[1, 0, L.C_UV_TRIP] = start.C[1, 0, L.C_VBUS] + 0.5     # leg 1's bus is below its level
    assert not _vector_block(0, 2, FR, start.C, start.AI)
    tw.run(start, ticks=8)
    assert start.AI[0, 0, L.I_SYS_ERR] == 0
    assert start.AI[1, 0, L.I_SYS_ERR] & L.ODRIVE_ERROR_DC_BUS_UNDER_VOLTAGE
    assert (start.AI[1, :, L.I_MODE] == L.MODE_IDLE).all()


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
