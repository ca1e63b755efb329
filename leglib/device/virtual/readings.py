"""The virtual ODrive's derived readings of an axis: the encoder's other estimates, the
current controller's voltages, gains and currents, the estimators of other modes (a mixin
of :class:`leglib.device.virtual.firmware.VirtualODrive`).

The twin's current loop is the firmware's q-axis PI (foc.cpp:120-160) with the commutation
exact and the d axis held at 0: the q axis's setpoint, voltage, integrator and power are the
kernel's; the rest follows from the kernel's state (measured Iq, the encoder's estimates, the
bus) through the motor's equations with the plant's own R, L and flux linkage -- the steady
state of the firmware's d axis (foc.cpp:80-180). File:line of fw-v0.5.6.
"""

from __future__ import annotations

import math

import numpy as np

from ...twin import layout as L

CURRENT_MEAS_PERIOD = 1.0 / 8000.0


def _f32(x) -> float:
    """As the firmware computes it in float32 (division by zero gives inf or NaN)."""
    return float(np.float32(x))


def _div(a, b) -> float:
    with np.errstate(divide="ignore", invalid="ignore"):
        return float(np.float32(a) / np.float32(b))


class AxisReadings:
    """Readings of the axes computed from the kernel's state."""

    # -- helpers --------------------------------------------------------------------
    def _leaf(self, path: str):
        """A model endpoint's value without a USB transaction (its row's getter)."""
        leaf = self._leaves[path]
        return leaf.node._props[leaf.name].get()

    def _electrical(self, a: int) -> tuple[float, float]:
        """(electrical angle [rad] in [-pi, pi), electrical velocity [rad/s]) of the rotor:
        the encoder's phase (encoder.cpp:830-845) as the calibration aligned it."""
        pp = self.twin.motor.pole_pairs
        j = self.twin.axes.joint_of_axis(a)
        turns = float(self.twin.axes.motor_turns(self.twin.motor_angle(self.st, j)[0], j))
        theta = 2 * math.pi * pp * (turns - self._magnet_offset[a] / pp)
        theta = (theta + math.pi) % (2 * math.pi) - math.pi
        omega = 2 * math.pi * pp * float(self.st.AS[0, a, L.S_VEL_EST])
        return theta, omega

    def _motor_state(self, a: int) -> dict:
        """The current controller's quantities in the steady state of ideal FOC."""
        st, m = self.st, self.twin.motor
        mode = st.AI[0, a, L.I_MODE]
        armed = mode != L.MODE_IDLE
        closed_loop = armed and mode != L.MODE_CALIB     # the kernel's current PI runs
        iq = float(st.AS[0, a, L.S_IQ_MEAS]) if armed else 0.0
        iq_sp = float(st.AS[0, a, L.S_IQ_SP]) if closed_loop else float(st.AS[0, a, L.S_IQ]) if armed else 0.0
        theta, omega = self._electrical(a)
        flux = m.torque_constant / (1.5 * m.pole_pairs)          # amplitude-invariant [V s]
        R, Lq = m.phase_resistance, m.phase_inductance
        # Vq: the PI's voltage of this period (foc.cpp:139-154), the open loop's steady state
        vq = float(st.AS[0, a, L.S_V_PREV]) if closed_loop else R * iq + omega * flux if armed else 0.0
        vd = -omega * Lq * iq if armed else 0.0
        pwm_phase = theta + 1.5 * CURRENT_MEAS_PERIOD * omega   # foc.cpp:150
        c, s = math.cos(theta), math.sin(theta)
        cp, sp = math.cos(pwm_phase), math.sin(pwm_phase)
        ialpha, ibeta = -s * iq, c * iq
        return {"iq": iq, "iq_sp": iq_sp, "id": 0.0, "vd": vd, "vq": vq, "theta": theta, "omega": omega,
                "closed_loop": closed_loop,
                "ialpha": ialpha, "ibeta": ibeta,
                "v_alpha": cp * vd - sp * vq, "v_beta": sp * vd + cp * vq,
                "ibus": float(st.AS[0, a, L.S_IBUS_MOTOR]) if armed else 0.0}

    # -- the motor ------------------------------------------------------------------
    def _r_motor(self, a: int, generic: str):
        name = generic.split(".", 2)[2]                 # "current_control.p_gain", "I_bus", ...
        ax = self._axis[a]
        if name in ("current_control.p_gain", "current_control.i_gain"):
            # motor.cpp:297-302: p = bandwidth * L, i = p * R / L (float32: 0/0 is NaN)
            bw = float(self.st.C[0, a, L.C_CURRENT_BW])
            p = _f32(bw * ax["phase_inductance"])
            return p if name.endswith("p_gain") else _f32(p * _div(ax["phase_resistance"], ax["phase_inductance"]))
        # the current sense's range: motor.cpp:312-332, set up by the IDLE loop from
        # requested_current_range (the kernel's C_MAX_CURRENT)
        max_current = _f32(self.st.C[0, a, L.C_MAX_CURRENT])
        if name in ("max_allowed_current", "current_control.max_allowed_current"):
            return max_current
        if name == "max_dc_calib":
            return _f32(0.1 * max_current)
        if name == "effective_current_lim":
            # motor.cpp:365-380: the configured limit, the sense range, the thermistors
            # (the FETs at ambient, the motor thermistor off: no derating)
            return min(float(self.st.C[0, a, L.C_CURRENT_LIM]), max_current)
        if name == "current_control.overcurrent_trip_level":      # fw-v0.5.1 motor.cpp
            return _f32(float(self.st.C[0, a, L.C_CURRENT_LIM]) + float(self.st.C[0, a, L.C_CURRENT_LIM_MARGIN]))
        if name == "armed_state":                                  # fw-v0.5.1: 0 disarmed, 3 armed
            return 3 if self.st.AI[0, a, L.I_MODE] != L.MODE_IDLE else 0
        ms = self._motor_state(a)
        vbus = self._vbus()
        values = {
            "I_bus": ms["ibus"],
            "current_control.Iq_measured": ms["iq"], "current_control.Iq_setpoint": ms["iq_sp"],
            "current_control.Id_measured": ms["id"], "current_control.Id_setpoint": 0.0,
            "current_control.Vd_setpoint": ms["vd"], "current_control.Vq_setpoint": ms["vq"],
            "current_control.Ialpha_measured": ms["ialpha"], "current_control.Ibeta_measured": ms["ibeta"],
            "current_control.final_v_alpha": ms["v_alpha"], "current_control.final_v_beta": ms["v_beta"],
            "current_control.phase": ms["theta"], "current_control.phase_vel": ms["omega"],
            # foc.cpp:175-179: vbus x (mod . Idq), the kernel's in closed loop
            "current_control.power": float(self.st.AS[0, a, L.S_FOC_POWER]) if ms["closed_loop"] else vbus * ms["ibus"],
            "current_control.v_current_control_integral_d": ms["vd"],
            "current_control.v_current_control_integral_q": ms["vq"],
            "current_control.Ibus": ms["ibus"],
            "current_meas_phA": ms["ialpha"],
            "current_meas_phB": -0.5 * ms["ialpha"] + math.sqrt(3) / 2 * ms["ibeta"],
            "current_meas_phC": -0.5 * ms["ialpha"] - math.sqrt(3) / 2 * ms["ibeta"],
        }
        if name not in values:
            raise KeyError(f"no reading {generic}")
        return values[name]

    def _r_current_control(self, a: int, generic: str):
        return self._r_motor(a, generic)

    def _set_torque_constant(self, a: int, value: float):
        """motor.hpp: stored as written. The kernel divides by it (torque to current), so it
        takes only a finite value that is not zero; with 0 the firmware's torque limit is 0
        and the current 0/0 (motor.cpp:385-393): the closed loop fails at once
        (procedures.py), the kernel keeps its last usable value meanwhile."""
        self._axis[a]["torque_constant"] = value
        if value != 0.0 and math.isfinite(value):
            self.st.C[0, a, L.C_KT] = value

    def _set_phase_resistance(self, a: int, value: float):
        """motor.hpp:58-59: stored, and the current controller's gains follow
        (motor.cpp:297-302: the kernel's current PI reads C_PHASE_R)."""
        self._axis[a]["phase_resistance"] = value
        self.st.C[0, a, L.C_PHASE_R] = value

    def _set_phase_inductance(self, a: int, value: float):
        """As :meth:`_set_phase_resistance`: the PI's gains from it (C_PHASE_L)."""
        self._axis[a]["phase_inductance"] = value
        self.st.C[0, a, L.C_PHASE_L] = value

    # -- the controller ---------------------------------------------------------------
    def _r_last_error_time(self, a: int, which: str) -> float:
        # controller.cpp:23, motor.cpp:343: the control-loop count times its period at the
        # error (taken where the model notices it: at the end of the tick batch it occurred in)
        return float(self._axis[a]["last_error_time"].get(which, 0.0))

    def _note_error_times(self):
        AI = self.st.AI
        words = (int(AI[0, 0, L.I_CTRL_ERR]), int(AI[0, 0, L.I_MOTOR_ERR]),
                 int(AI[0, 1, L.I_CTRL_ERR]), int(AI[0, 1, L.I_MOTOR_ERR]))
        if words == self.__dict__.get("_error_words"):
            return                       # nothing changed since the last look
        self.__dict__["_error_words"] = words
        for a, ax in enumerate(self._axis):
            seen = ax.setdefault("errors_seen", {})
            for which, slot in (("controller", L.I_CTRL_ERR), ("motor", L.I_MOTOR_ERR)):
                word = int(self.st.AI[0, a, slot])
                if word & ~seen.get(which, 0):
                    ax.setdefault("last_error_time", {})[which] = self._ticks() * CURRENT_MEAS_PERIOD
                seen[which] = word

    # -- the encoder ------------------------------------------------------------------
    def _r_encoder(self, a: int, generic: str):
        """encoder.cpp:740-845: the estimates in counts, the circular position, the
        interpolation and the electrical phase, from the kernel's PLL."""
        name = generic.rsplit(".", 1)[1]
        ax = self._axis[a]
        cpr = ax["cpr"]
        if name == "index_found":
            return bool(ax.get("index_found", False))
        if name == "calib_scan_response":
            return float(ax.get("calib_scan_response", 0.0))
        pos = self._leaf(f"axis{a}.encoder.pos_estimate")
        vel = self._leaf(f"axis{a}.encoder.vel_estimate")
        pos_counts, vel_counts = pos * cpr, vel * cpr
        if name == "pos_estimate_counts":
            return pos_counts
        if name == "vel_estimate_counts":
            return vel_counts
        if name in ("pos_cpr_counts", "pos_cpr"):
            return math.fmod(pos_counts, cpr) % cpr if cpr else math.nan
        if name == "delta_pos_cpr_counts":
            # the PLL's phase-detector error (encoder.cpp:771-773): the count less the estimate
            return float(int(self.st.AI[0, a, L.I_COUNTS]) - math.floor(pos_counts))
        if name == "interpolation":
            kp = 2.0 * float(self.st.C[0, a, L.C_ENCODER_BW])
            if abs(vel_counts) < 0.5 * CURRENT_MEAS_PERIOD * 0.25 * kp * kp:
                return 0.5                                   # encoder.cpp:787-791,815-817
            return pos_counts - math.floor(pos_counts)
        if name == "phase":
            return self._electrical(a)[0]
        raise KeyError(f"no reading {generic}")

    def _r_sensorless(self, a: int, generic: str):
        """The flux observer's estimates (sensorless_estimator.cpp), taken as ideal: it
        tracks the rotor's electrical angle and speed (its low-speed error is not modelled;
        these are readings only: sensorless control itself is refused)."""
        name = generic.rsplit(".", 1)[1]
        theta, omega = self._electrical(a)
        return {"phase": theta, "pll_pos": theta, "phase_vel": omega,
                "vel_estimate": omega / (2 * math.pi * self.twin.motor.pole_pairs)}[name]

    def _r_lockin_state(self, a: int, generic: str = "") -> int:
        # fw-v0.5.1 axis.hpp: INACTIVE 0, RAMP 1, ACCELERATE 2, CONST_VEL 3
        return int(self._axis[a].get("lockin_state", 0))
