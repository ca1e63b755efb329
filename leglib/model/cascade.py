"""The ODrive cascade as linear continuous-time models (python-control).

:func:`axis_closed_loop` is one ODrive axis as the firmware runs it, linearized: position P
-> velocity PI -> current loop (first order at the current-control bandwidth) -> rotor and
load inertia, with the encoder PLL estimating position and velocity. It is the analytic
reference the twin is tested against. Motor-side, ODrive units: turns, turn/s, N*m.
"""

from __future__ import annotations

import math

import control
import numpy as np


def pll_gains(bandwidth: float) -> tuple[float, float]:
    """The firmware's encoder PLL gains for a bandwidth [rad/s]: kp = 2 bw, ki = kp^2 / 4."""
    kp = 2.0 * bandwidth
    return kp, 0.25 * kp * kp


def motor_side_inertia(joint_inertia: float, gear_ratio: float) -> float:
    """Inertia seen by the motor in ODrive units [N*m / (turn/s^2)]: 2 pi J / N^2."""
    return 2 * math.pi * joint_inertia / gear_ratio ** 2


def axis_closed_loop_matrices(inertia_turns: float, torque_constant: float, pos_gain: float,
                              vel_gain: float, vel_integrator_gain: float, current_bandwidth: float = 1000.0,
                              encoder_bandwidth: float = 1000.0,
                              viscous: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A, B, C) of :func:`axis_closed_loop` as plain arrays (no python-control object:
    cheap enough for an optimizer's inner loop)."""
    J, kt = inertia_turns, torque_constant
    kp_e, ki_e = pll_gains(encoder_bandwidth)
    wc = current_bandwidth
    Kp, Kv, Ki = pos_gain, vel_gain, vel_integrator_gain
    A = np.array([
        [0, 1, 0, 0, 0, 0],
        [0, -viscous / J, kt / J, 0, 0, 0],
        [0, 0, -wc, -wc * Kv * Kp / kt, -wc * Kv / kt, wc / kt],
        [kp_e, 0, 0, -kp_e, 1, 0],
        [ki_e, 0, 0, -ki_e, 0, 0],
        [0, 0, 0, -Ki * Kp, -Ki, 0],
    ], dtype=float)
    B = np.array([[0], [0], [wc * Kv * Kp / kt], [0], [0], [Ki * Kp]], dtype=float)
    C = np.array([[1, 0, 0, 0, 0, 0]], dtype=float)
    return A, B, C


def axis_closed_loop(inertia_turns: float, torque_constant: float, pos_gain: float,
                     vel_gain: float, vel_integrator_gain: float, current_bandwidth: float = 1000.0,
                     encoder_bandwidth: float = 1000.0, viscous: float = 0.0) -> control.StateSpace:
    """Closed loop from position command [turn] to motor position [turn] of one axis.

    Parameters
    ----------
    inertia_turns : load + rotor inertia at the motor [N*m/(turn/s^2)] (see
        :func:`motor_side_inertia`)
    torque_constant : [N*m/A]
    pos_gain [(turn/s)/turn], vel_gain [N*m/(turn/s)], vel_integrator_gain [N*m/turn]
    current_bandwidth, encoder_bandwidth : [rad/s]
    viscous : motor-side viscous friction [N*m/(turn/s)]

    States: position, velocity, Iq, PLL position, PLL velocity, velocity integrator torque.
    """
    A, B, C = axis_closed_loop_matrices(inertia_turns, torque_constant, pos_gain, vel_gain, vel_integrator_gain,
                                        current_bandwidth, encoder_bandwidth, viscous)
    return control.ss(A, B, C, [[0.0]], states=["pos", "vel", "iq", "pos_est", "vel_est", "integrator"],
                      inputs=["input_pos"], outputs=["pos"], name="odrive_axis")


def bldc_closed_loop(motor, pos_gain: float, vel_gain: float, vel_integrator_gain: float,
                     current_bandwidth: float = 1000.0) -> control.StateSpace:
    """The thesis's BLDC + ODrive cascade (6.2-6.3, Table 6.1, Krishnan's current loop):
    position P -> velocity PI -> current PI (the firmware's gains from the bandwidth:
    Kp = La bw, Ki = Ra bw) -> inverter (first-order lag) -> La di/dt = v - Ra i - Kb w,
    J dw/dt = Kt i - B1 w. Position command [turn] -> position [turn].

    States: position [turn], speed [rad/s], current [A], inverter voltage [V], current
    integrator [V], velocity integrator [N*m].
    """
    m = motor
    La, Ra, Kb, Kt, J, B1, Hc, tinv = m.La, m.Ra, m.Kb, m.Kt, m.J, m.B1, m.Hc, m.inverter_time_constant
    kpi, kii = La * current_bandwidth, Ra * current_bandwidth
    Kp, Kv, Ki = pos_gain, vel_gain, vel_integrator_gain
    c = 1 / (2 * math.pi)  # rad/s -> turn/s
    # torque command tau = Kv (Kp (r - x) - c w) + z ; current reference i_ref = tau / Kt
    # inverter input u = kpi (i_ref - Hc i) + zi
    A = np.zeros((6, 6))
    B = np.zeros((6, 1))
    A[0, 1] = c                                   # x' = w / 2 pi
    A[1, 1] = -B1 / J
    A[1, 2] = Kt / J                              # J w' = Kt i - B1 w
    A[2, 1] = -Kb / La
    A[2, 2] = -Ra / La
    A[2, 3] = 1 / La                              # La i' = v - Ra i - Kb w
    # tau/Kt as a row over the states, plus the input part
    tau_x = np.array([-Kv * Kp, -Kv * c, 0, 0, 0, 1.0]) / Kt
    tau_r = Kv * Kp / Kt
    u_x = kpi * tau_x
    u_x[2] -= kpi * Hc
    u_x[4] += 1.0
    u_r = kpi * tau_r
    A[3] = u_x / tinv
    A[3, 3] -= 1 / tinv                           # tinv v' = u - v
    B[3, 0] = u_r / tinv
    A[4] = kii * tau_x                            # zi' = kii (i_ref - Hc i)
    A[4, 2] -= kii * Hc
    B[4, 0] = kii * tau_r
    A[5] = Ki * np.array([-Kp, -c, 0, 0, 0, 0])   # z' = Ki (Kp (r - x) - w / 2 pi)
    B[5, 0] = Ki * Kp
    C = np.zeros((1, 6))
    C[0, 0] = 1.0
    return control.ss(A, B, C, [[0.0]], states=["pos", "speed", "current", "voltage", "current_int", "vel_int"],
                      inputs=["input_pos"], outputs=["pos"], name="bldc_cascade")
