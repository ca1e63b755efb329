"""The stages of the firmware's control tick, shared by both of the twin's kernel paths.

Each is a small compiled function, inlined where it is called, named after the firmware
file whose code it follows (fw-v0.5.6 unless marked):

- ``encoder.cpp``: :func:`encoder_counts` (the reading as the encoder keeps it) and
  :func:`encoder_pll` (the position/velocity estimator);
- ``controller.cpp``: :func:`overspeed`, :func:`torque_command`, :func:`torque_limit`, :func:`integrator_step`
  (the velocity integrator's anti-windup), :func:`clamp` (``std::clamp``);
- ``utils.hpp``: :func:`wrap_pm`, :func:`fmodf_pos` (the circular setpoints' arithmetic);
- ``motor.cpp``, ``foc.cpp``: :func:`max_torque` (max_available_torque), :func:`current_setpoint`,
  :func:`foc_voltage` (the current PI with its voltage limit), :func:`motor_current` (the
  motor's phase current under that voltage, applied half a period late),
  :func:`current_violation`, :func:`motor_bus_current`;
- ``low_level.cpp``: :func:`brake_current`, :func:`bus_fault`.

The reference tick (:func:`leglib.twin.kernel._run_block`) and the vectorized one
(:mod:`leglib.twin.vector`) call the same stages with the same operands, so the two paths
do the same operations in the same order and give the same numbers, bit for bit. The stages
are written with selects, not branches, so that a loop over legs calling them vectorizes;
on one leg a select costs what the branch did.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .. import _numba_gc, _numba_inline  # noqa: F401  (before any kernel compiles)
from ..kernelmath import py_max, py_min, select

TWO_PI = 2.0 * math.pi


# -- encoder.cpp ------------------------------------------------------------------------

@njit(cache=True, inline="always")
def encoder_counts(raw, offset, quantize):
    """The encoder's reading of ``raw`` counts (noise and reading error included): (what the
    estimator sees, the integer ``shadow_count``). Quantized to whole counts unless
    ``quantize`` is False (exact positions, for models fitted by finite differences); the
    count offset is the incremental count's reference at boot (encoder.cpp:480,657-662)."""
    rounded = math.floor(raw + 0.5)
    return select(quantize, rounded, raw) + offset, np.int64(rounded + offset)


@njit(cache=True, inline="always")
def encoder_pll(pe0, ve0, counts, dt, kp, ki, inv_cpr):
    """One tick of the encoder's PLL (encoder.cpp:784-801; kp = 2 bw, ki = kp^2 / 4 from
    encoder.config.bandwidth, encoder.cpp:121-122): (pos_estimate [turn], vel_estimate [turn/s]); a velocity
    below half a count per tick's worth of ki is snapped to zero, as the firmware does."""
    pe = pe0 + dt * ve0
    delta = counts * inv_cpr - pe
    pe += dt * kp * delta
    ve = ve0 + dt * ki * delta
    ve = select(abs(ve) < 0.5 * dt * ki * inv_cpr, 0.0, ve)
    return pe, ve


# -- controller.cpp ---------------------------------------------------------------------

@njit(cache=True, inline="always")
def clamp(v, lo, hi):
    """``std::clamp(v, lo, hi)`` as libstdc++ computes it (``lo`` when ``v < lo``, else ``hi``
    when ``hi < v``, else ``v``): what the firmware's limits do, also with ``lo > hi`` (a
    negative limit, which the firmware stores as written). For ``lo <= hi`` it is
    ``min(max(v, lo), hi)``, bit for bit."""
    return select(v < lo, lo, select(hi < v, hi, v))


@njit(cache=True, inline="always")
def overspeed(checked, ve, vel_limit, tolerance):
    """controller.cpp:331-341: |vel_estimate| above vel_limit * vel_limit_tolerance is an
    OVERSPEED error wherever the controller runs with the check enabled (``checked``: on
    0.5.6 every tick in every state, main.cpp:438-446; on 0.5.1 in closed loop)."""
    return checked & (abs(ve) > tolerance * vel_limit)


@njit(cache=True, inline="always")
def torque_command(vel_gain, verr, integrator, torque_ff):
    """controller.cpp:374-386: vel_gain times the velocity error, the integrator's torque
    and the torque feed-forward [N*m]."""
    return vel_gain * verr + integrator + torque_ff


@njit(cache=True, inline="always")
def torque_limit(torque, t_lim):
    """controller.cpp:396-405: the torque clamped to +-t_lim (current_lim times the torque
    constant); (the torque, whether it was limited)."""
    neg_t_lim = -t_lim
    limited = (torque > t_lim) | (torque < neg_t_lim)
    return select(torque > t_lim, t_lim, select(torque < neg_t_lim, neg_t_lim, torque)), limited


@njit(cache=True, inline="always")
def integrator_step(integrator, limited, gain, dt, verr, lim):
    """controller.cpp:407-420: the velocity integrator decays by 0.99 per tick while the
    torque is limited (anti-windup) and grows by gain * dt * error otherwise, clamped to
    +-vel_integrator_limit (0.5.4+; inf before)."""
    integ = select(limited, integrator * 0.99, integrator + gain * dt * verr)
    return py_min(py_max(integ, -lim), lim)


@njit(cache=True, inline="always")
def spinout(mech0, elec0, torque, ve, foc_power, iq_meas, r_phase, mech_bw, elec_bw, dt, mech_threshold,
            elec_threshold):
    """controller.cpp:422-441: the mechanical power the controller asks for (torque x
    velocity) and the motor's electrical power less its copper loss (the current
    controller's last power, foc.cpp:175-179; the configured R), each through a first-order
    filter; braking mechanically while taking electrical power is a spinout (a wrong encoder
    offset). (mechanical power [W], electrical power [W], spun out)."""
    mech = mech0 + mech_bw * dt * (torque * ve * (2.0 * math.pi) - mech0)
    ideal = foc_power - iq_meas * iq_meas * 1.5 * r_phase
    elec = elec0 + elec_bw * dt * (ideal - elec0)
    return mech, elec, (mech < mech_threshold) & (elec > elec_threshold)


# -- utils.hpp --------------------------------------------------------------------------

@njit(cache=True, inline="always")
def wrap_pm(x, y):
    """utils.hpp:108-130: ``x`` wrapped into [-y/2, y/2]: x minus the nearest multiple of
    ``y``, the multiple's count rounded by the Cortex-M4's vcvtr.s32.f32 (to nearest, ties
    to even; saturating at the int32 range, NaN to 0), so that ``y`` = 0 leaves ``x`` as it
    is, as on the board (no division by zero here: the count is formed with selects)."""
    q = x / select(y == 0.0, 1.0, y)
    q = select(y == 0.0, select(x > 0.0, 2147483647.0, select(x < 0.0, -2147483648.0, 0.0)), q)
    q = select(q == q, q, 0.0)
    n = np.rint(select(q > 2147483647.0, 2147483647.0, select(q < -2147483648.0, -2147483648.0, q)))
    return x - n * y


@njit(cache=True, inline="always")
def fmodf_pos(x, y):
    """utils.hpp:133-137: ``x`` wrapped into [0, y)."""
    r = wrap_pm(x, y)
    return select(r < 0.0, r + y, r)


# -- motor.cpp --------------------------------------------------------------------------

@njit(cache=True, inline="always")
def max_torque(current_lim, max_current, kt, torque_lim):
    """motor.cpp:365-394: the largest torque the motor may give [N*m]: the effective current
    limit (current_lim capped by the current sense's range, motor.cpp:372) times the torque
    constant, clamped to [0, torque_lim]."""
    ilim = py_min(current_lim, max_current)
    return clamp(ilim * kt, 0.0, torque_lim)

@njit(cache=True, inline="always")
def current_gains(bandwidth, r, ind, dt):
    """motor.cpp:297-302: the current PI's gains from current_control_bandwidth [rad/s]
    and the configured phase resistance [ohm] and inductance [H]: (p_gain [V/A], i_gain *
    dt [V/A]; i_gain = p_gain * R / L)."""
    p_gain = bandwidth * ind
    if not ind != 0.0:     # an uncalibrated motor (L = 0): the firmware's R / L is inf or NaN
        return p_gain, math.nan
    return p_gain, (r / ind) * p_gain * dt


@njit(cache=True, inline="always")
def motor_plant(DRV, dt):
    """The motor's electrical invariants for :func:`motor_current` from its true phase
    resistance DRV[11] [ohm] and inductance DRV[12] [H] over half a control period:
    (exp(-R dt / 2L), 1 / R, the half's mean of the exponential)."""
    x = DRV[11] * dt / (2.0 * DRV[12])
    a_half = math.exp(-x)
    return a_half, 1.0 / DRV[11], (1.0 - a_half) / x


@njit(cache=True, inline="always")
def current_setpoint(torque, inv_kt, ilim):
    """motor.cpp:538-548: the torque's current (torque / torque_constant) clamped to the
    effective current limit (the 2-norm clamp with Id = 0) [A]."""
    return clamp(torque * inv_kt, -ilim, ilim)


@njit(cache=True, inline="always")
def foc_voltage(iq_sp, iq_meas, integ, kp, ki_dt, v_ff, vmax):
    """foc.cpp:131-154: the q-axis voltage of the current PI (p_gain = bandwidth * L,
    i_gain = bandwidth * R from the configured R and L, motor.cpp:297-302) on the measured
    current, with the feed-forward ``v_ff``; the modulation's magnitude limited to 0.8 of
    sqrt(3)/2 (``vmax`` = 0.8 sqrt(3)/2 * 2/3 vbus [V]), the integrator decaying by 0.99 per
    tick while limited. (voltage [V], integrator [V])."""
    err = iq_sp - iq_meas
    v = v_ff + integ + err * kp
    limited = abs(v) > vmax
    v = select(limited, select(v > 0.0, vmax, -vmax), v)
    return v, select(limited, integ * 0.99, integ + err * ki_dt)


@njit(cache=True, inline="always")
def motor_current(i0, v_prev, v, e_bemf, a_half, inv_r, m_half):
    """The phase current's response over one control period [A]: the RL circuit
    (L di/dt = v - R i - e) driven during the period's first half by the voltage of the
    previous tick and during its second by this tick's: the PWM timings the control
    interrupt writes take effect at the next timer update, half a control period after the
    current was sampled (board.cpp:543-563, foc.cpp:163). ``a_half`` = exp(-R dt / 2L),
    ``inv_r`` = 1 / R, ``m_half`` = (1 - a_half) 2L / (R dt) (a half's mean of the
    exponential). (the current at the next sample, its mean over the period)."""
    s1 = (v_prev - e_bemf) * inv_r
    i1 = s1 + (i0 - s1) * a_half
    mean1 = s1 + (i0 - s1) * m_half
    s2 = (v - e_bemf) * inv_r
    i2 = s2 + (i1 - s2) * a_half
    mean2 = s2 + (i1 - s2) * m_half
    return i2, 0.5 * (mean1 + mean2)


@njit(cache=True, inline="always")
def current_violation(iq_measured, current_lim, max_current, margin):
    """motor.cpp:635-643: a measured current beyond the effective current limit plus
    current_lim_margin (Inorm^2 > Itrip^2; with one current component, |Iq| > Itrip)."""
    itrip = py_min(current_lim, max_current) + margin
    return iq_measured * iq_measured > itrip * itrip


@njit(cache=True, inline="always")
def motor_bus_current(r_phase, iq, kt, ve, inv_vbus):
    """The DC bus current a motor draws: copper loss plus mechanical power, over vbus [A]
    (``ve`` the rotor's speed [turn/s], ``kt`` the motor's true torque constant)."""
    w = ve * TWO_PI
    return (1.5 * r_phase * iq * iq + kt * iq * w) * inv_vbus


# -- low_level.cpp ----------------------------------------------------------------------

@njit(cache=True, inline="always")
def brake_current(ibus_axes, max_regen, brake_r, inv_vbus, vbus, inv_brake_r):
    """low_level.cpp:322-366: the brake resistor takes the regenerated current beyond
    max_regen_current, its duty cycle clamped to [0, 0.95] [A]."""
    duty = (-ibus_axes - max_regen) * brake_r * inv_vbus
    duty = py_min(py_max(duty, 0.0), 0.95)
    return duty * vbus * inv_brake_r


@njit(cache=True, inline="always")
def bus_fault(ibus, dc_max_positive, dc_max_negative):
    """low_level.cpp:369-376: (over current, over regeneration) of the DC bus."""
    over_pos = ibus > dc_max_positive
    over_neg = (not over_pos) & (ibus < dc_max_negative)
    return over_pos, over_neg
