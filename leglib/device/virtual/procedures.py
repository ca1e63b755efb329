"""The axis thread of the virtual ODrive: the state machine and the procedures it runs
(a mixin of :class:`leglib.device.virtual.firmware.VirtualODrive`).

Each axis runs the firmware's ``Axis::run_state_machine_loop`` (axis.cpp:455-602): a
request (``requested_state``, or ``STARTUP_SEQUENCE`` at every boot, axis.hpp:202) loads a
task chain, each state's handler runs until it ends or a new request arrives, a failed
state clears the chain and drops to IDLE. The handlers that move the rotor open-loop --
motor calibration, encoder offset calibration, direction find, index search, lock-in spin
-- are written here as generators that read like the firmware's loops: ``yield dt`` is the
firmware's ``osDelay`` (the loop's next check ``dt`` seconds later, on the virtual clock),
and between two yields the compiled kernel moves the rotor after the rotating field
(``MODE_CALIB``: the leg, its friction and its hard stops in the loop). A state the model
cannot run is refused at the request with :class:`UnmodeledError` naming it and why.

File:line of fw-v0.5.6 unless marked; fw-v0.5.1 runs its own variants where they differ.
"""

from __future__ import annotations

import math

from ...twin import layout as L
from .tree import UnmodeledError

# axis states (odrive-interface.yaml ODrive.Axis.AxisState)
(UNDEFINED, IDLE, STARTUP_SEQUENCE, FULL_CALIBRATION_SEQUENCE, MOTOR_CALIBRATION, SENSORLESS_CONTROL,
 ENCODER_INDEX_SEARCH, ENCODER_OFFSET_CALIBRATION, CLOSED_LOOP_CONTROL, LOCKIN_SPIN, ENCODER_DIR_FIND,
 HOMING, ENCODER_HALL_POLARITY_CALIBRATION, ENCODER_HALL_PHASE_CALIBRATION) = range(14)

# errors (odrive-interface.yaml of each tag: the flags and their bits)
AXIS_ERROR_INVALID_STATE = 0x1
AXIS_ERROR_MOTOR_FAILED = 0x40
AXIS_ERROR_ENCODER_FAILED = 0x100
AXIS_ERROR_HOMING_WITHOUT_ENDSTOP = 0x20000          # 0.5.6 and 0.5.1
MOTOR_ERROR_PHASE_RESISTANCE_OUT_OF_RANGE = 0x1
MOTOR_ERROR_PHASE_INDUCTANCE_OUT_OF_RANGE = 0x2
MOTOR_ERROR_UNKNOWN_PHASE_ESTIMATE = 0x4000000       # 0.5.6 (foc.cpp:85)
ENCODER_ERROR_CPR_POLEPAIRS_MISMATCH = 0x2
ENCODER_ERROR_NO_RESPONSE = 0x4
ENCODER_ERROR_INDEX_NOT_FOUND_YET = 0x20

# firmware timings and constants (fw-v0.5.6)
AXIS_THREAD_PERIOD = 1e-3        # axis.cpp:447-451 osDelay(1): the state machine's iteration
R_MEASUREMENT_TIME = 3.0         # motor.cpp:423: 3000 iterations of 1 ms
L_MEASUREMENT_TIME = 1.25        # motor.cpp:463: 1250 iterations of 1 ms
OFFSET_LOCK_TIME = 1.0           # encoder.cpp:329 start_lock_duration
R_MEASUREMENT_KI = 1.0           # motor.cpp:71: the resistance law's integrator gain [(V/s)/A]
L_RANGE = (2e-6, 4000e-6)        # motor.cpp:481 [H]
CONTROL_PERIOD = 1.0 / 8000.0    # the current measurement period [s]

# the procedures' loops run every 1 ms on the board (osDelay(1)); the model steps them every
# LOOP_STEP and takes the iterations between from the rotor's motion, which is steady at that
# scale (the count at each 1 ms iteration interpolated between the step's ends, the field's
# speed stepped once per step): a finish condition is seen up to LOOP_STEP late
LOOP_STEP = 0.02

# how long after a reset the axis threads start: rtos_main waits until the motors' current
# measurements are valid (main.cpp:561-584), i.e. until the current sensors' DC calibration
# has run dc_calib_tau * 7.5 = 1.5 s (motor.cpp:606-607, motor.hpp dc_calib_tau 0.2 s);
# the host finds the board on USB about then too (firmware.BOOT_TIME)
THREAD_START_AFTER_RESET = 1.5

# the states that run the current controller on the configured gains
_FOC_STATES = frozenset({ENCODER_INDEX_SEARCH, ENCODER_OFFSET_CALIBRATION, CLOSED_LOOP_CONTROL, LOCKIN_SPIN,
                         ENCODER_DIR_FIND, HOMING})

# Axis::default_calibration (axis.cpp:40-52; fw-v0.5.1 axis.cpp:55-67): the finish conditions
# of the calibration lock-in, which the table does not expose
CALIBRATION_LOCKIN_FINISH = {"finish_distance": 100.0 * 2.0 * math.pi, "finish_on_vel": False,
                             "finish_on_distance": True, "finish_on_enc_idx": True}


def _interpolated_sum(c0: int, c1: int, n: int) -> float:
    """The sum of the counts at the n iterations of a step from count c0 to c1 (sampled at
    the start of each iteration, the count moving steadily)."""
    return n * c0 + (c1 - c0) * (n - 1) / 2.0


class AxisThread:
    """The axis state machine and its procedures (see the module docstring)."""

    # -- the state machine ------------------------------------------------------------
    def _start_axis_threads(self, at: float):
        """At boot: ``requested_state`` starts as STARTUP_SEQUENCE (axis.hpp:202), taken up
        when the thread starts; ``current_state`` reads UNDEFINED until then."""
        for ax in self._axis:
            ax.update({"requested_state": STARTUP_SEQUENCE, "pending": (STARTUP_SEQUENCE, at),
                       "state": UNDEFINED, "chain": [], "task": None, "wake": None})

    def _next_event(self):
        times = []
        for ax in self._axis:
            if ax["pending"] is not None:
                times.append(ax["pending"][1])
            if ax["wake"] is not None:
                times.append(ax["wake"])
        return min(times) if times else None

    def _axis_events(self, now: float):
        st = self.st
        for a, ax in enumerate(self._axis):
            # a fault (or leglib's abort) disarmed the motor: the running state ends
            # (axis.cpp:343: the closed loop runs while the motor is armed; the procedures
            # check is_armed_ every iteration)
            if st.AI[0, a, L.I_MODE] == L.MODE_IDLE:
                if ax["state"] == CLOSED_LOOP_CONTROL:
                    self._task_done(a, self._closed_loop_exit_ok(a))
                elif ax["task"] is not None and ax.get("armed_by_task"):
                    self._abort_task(a)
                    self._task_done(a, False)
            if ax["pending"] is not None and now >= ax["pending"][1]:
                self._consume_request(a, ax["pending"][0])
            while ax["wake"] is not None and now >= ax["wake"]:
                self._step_task(a)
            # the index interrupt fires whenever the encoder passes its index while armed
            # (encoder.cpp:86-117), not only in the index search's spin (whose loop checks it)
            if ax.get("index_armed") and ax["use_index"] and not ax.get("index_found") and ax["task"] is None:
                turns = self._rotor_encoder_turns(a)
                if ax.get("index_turns") is not None:
                    self._index_check(a, ax["index_turns"])
                ax["index_turns"] = turns
            else:
                ax["index_turns"] = None

    def _closed_loop_exit_ok(self, a: int) -> bool:
        # axis.cpp:348-350: stop_closed_loop_control returns check_for_errors()
        return self.st.AI[0, a, L.I_AXIS_ERR] == 0

    def _request_state(self, a: int, value: int):
        """axis.cpp:455-488: the axis thread picks the request up on its next iteration.
        A state the model cannot run is refused here, at the write."""
        refusal = self._refusal(a, int(value))
        if refusal is not None:
            raise UnmodeledError(f"odrv.axis{a}.requested_state = {int(value)}: {refusal}")
        t = self.time
        consume = (math.floor(t / AXIS_THREAD_PERIOD + 1e-9) + 1) * AXIS_THREAD_PERIOD
        self._axis[a]["pending"] = (value, consume)
        self._axis[a]["requested_state"] = value

    def _refusal(self, a: int, state: int) -> str | None:
        """Why the model cannot run ``state`` on axis ``a`` now (None: it can)."""
        if state in (ENCODER_HALL_POLARITY_CALIBRATION, ENCODER_HALL_PHASE_CALIBRATION):
            return ("the hall calibrations read hall sensors; this leg's AS5047D encoders are wired "
                    "through ABI (incremental) and are not modelled as hall sensors")
        if state == SENSORLESS_CONTROL and self.firmware == "0.5.1":
            return ("sensorless control (a lock-in spin to speed, then the flux observer) is not "
                    "modelled: the leg cannot spin freely (hard stops)")
        if state in _FOC_STATES and not (self.firmware == "0.5.1" and state == ENCODER_OFFSET_CALIBRATION):
            refusal = self._gains_refusal(a)
            if refusal is not None:
                return refusal
        if state == CLOSED_LOOP_CONTROL:
            return self._commutation_refusal(a)
        return None

    def _gains_refusal(self, a: int) -> str | None:
        """The current controller's gains come from motor.config.phase_resistance and
        phase_inductance (motor.cpp:297-302), and the kernel runs the firmware's q-axis PI
        on them (C_PHASE_R, C_PHASE_L). Its d axis is held at 0: that holds while the gains
        fit the motor, within the accuracy the firmware's own calibration test accepts
        (calibration_test.py:48-49: R to 20 %, L to 50 %); further off, the d-axis current
        and its coupling to q, which the board's loop would show, are not modelled."""
        ax, m = self._axis[a], self.twin.motor
        if not ax["motor_calibrated"]:
            return None          # the state is invalid anyway (axis.cpp:509-559)
        r, ind = ax["phase_resistance"], ax["phase_inductance"]
        if abs(r / m.phase_resistance - 1.0) <= 0.2 and abs(ind / m.phase_inductance - 1.0) <= 0.5:
            return None
        return (f"motor.config.phase_resistance = {r:.4g} ohm and phase_inductance = {ind:.4g} H set the "
                f"current controller's gains; this motor has {m.phase_resistance:.4g} ohm and "
                f"{m.phase_inductance:.4g} H: a current loop tuned that far off (its d axis) is not modelled; "
                f"run MOTOR_CALIBRATION")

    def _commutation_refusal(self, a: int) -> str | None:
        """The twin's ideal commutation holds for a pre-calibrated encoder only if its
        stored phase_offset is this board's: a written one (a configuration restored from
        another board) would commutate the motor wrongly (encoder.cpp:833-838)."""
        ax = self._axis[a]
        if not (ax["encoder_ready"] and ax.get("ready_by_index")):
            return None
        key = "axis*.encoder.config.phase_offset" if self.firmware != "0.5.1" else "axis*.encoder.config.offset"
        stored = self._settings[a][key]
        if stored == ax.get("offset_measured"):
            return None          # the offset this board measured against its index
        return (f"the encoder's stored phase_offset {stored} is not the one this board measured "
                f"against its index ({ax.get('offset_measured')}; written or restored from another "
                f"board?): commutation with it is not modelled; run ENCODER_OFFSET_CALIBRATION")

    def _consume_request(self, a: int, value: int):
        ax = self._axis[a]
        ax["pending"] = None
        ax["requested_state"] = UNDEFINED
        self.st.AI[0, a, L.I_AXIS_ERR] &= ~AXIS_ERROR_INVALID_STATE   # axis.cpp:487
        # the running state ends (handlers exit on a new request): disarm
        self._abort_task(a)
        self._disarm(a)
        ax["chain"] = self._chain(a, value) + [IDLE]
        self._start_task(a)

    def _chain(self, a: int, value: int) -> list[int]:
        """axis.cpp:458-483 (fw-v0.5.1 axis.cpp:477-500): the task chain of a request."""
        ax = self._axis[a]
        s = self._settings[a]
        if value == STARTUP_SEQUENCE:
            chain = [MOTOR_CALIBRATION] if ax["startup_motor_calibration"] else []
            if s.get("axis*.config.startup_encoder_index_search") and ax["use_index"]:
                chain.append(ENCODER_INDEX_SEARCH)
            if ax["startup_encoder_offset_calibration"]:
                chain.append(ENCODER_OFFSET_CALIBRATION)
            if s.get("axis*.config.startup_homing"):
                chain.append(HOMING)
            if ax["startup_closed_loop_control"]:
                chain.append(CLOSED_LOOP_CONTROL)
            elif self.firmware == "0.5.1" and s.get("axis*.config.startup_sensorless_control"):
                chain.append(SENSORLESS_CONTROL)    # refused on its write: never reached
            return chain
        if value == FULL_CALIBRATION_SEQUENCE:
            return ([MOTOR_CALIBRATION] + ([ENCODER_INDEX_SEARCH] if ax["use_index"] else [])
                    + [ENCODER_OFFSET_CALIBRATION])
        if value == IDLE:
            return []
        return [value]

    def _start_task(self, a: int):
        ax = self._axis[a]
        state = ax["chain"][0] if ax["chain"] else IDLE
        ax["state"] = state
        if state == IDLE:
            ax["chain"] = []
            return
        handler = self._handler(a, state)
        if handler is None:
            return                       # closed loop: runs until a request or a fault
        ax["task"], ax["wake"], ax["armed_by_task"] = handler, self.time, False
        self._step_task(a)

    def _handler(self, a: int, state: int):
        """The generator running ``state`` (None: a state that runs in the kernel)."""
        ax = self._axis[a]
        calibrated = ax["motor_calibrated"]
        direction_ok = ax["direction"] != 0
        if state == MOTOR_CALIBRATION:
            return self._run_motor_calibration(a)
        if state == ENCODER_OFFSET_CALIBRATION:
            return self._run_offset_calibration(a) if calibrated else self._invalid_state(a)
        if state == ENCODER_INDEX_SEARCH:
            if not calibrated or (self.firmware == "0.5.1" and self._settings[a].get(
                    "axis*.encoder.config.idx_search_unidirectional") and not direction_ok):
                return self._invalid_state(a)
            return self._run_index_search(a)
        if state == ENCODER_DIR_FIND:
            return self._run_direction_find(a) if calibrated else self._invalid_state(a)
        if state == LOCKIN_SPIN:
            if not calibrated or not direction_ok:
                return self._invalid_state(a)
            return self._run_lockin(a, self._lockin_config(a, "general_lockin"))
        if state == HOMING:
            return self._run_homing(a)
        if state == CLOSED_LOOP_CONTROL:
            # axis.cpp:572-578 (fw-v0.5.1 axis.cpp:553-558 also needs encoder.is_ready)
            if not calibrated or not direction_ok or (self.firmware == "0.5.1" and not ax["encoder_ready"]):
                return self._invalid_state(a)
            self._enter_closed_loop(a)
            if self.st.AI[0, a, L.I_MODE] == L.MODE_IDLE:
                return self._failed(a)
            if not ax["encoder_ready"]:
                return self._unknown_phase(a)
            if not (ax["torque_constant"] != 0.0 and math.isfinite(ax["torque_constant"])):
                return self._modulation_nan(a)
            return None
        return self._invalid_state(a)     # axis.cpp:586-590: any other state

    def _step_task(self, a: int):
        ax = self._axis[a]
        try:
            delay = next(ax["task"])
        except StopIteration as stop:
            ax["task"], ax["wake"], ax["armed_by_task"] = None, None, False
            self._task_done(a, bool(stop.value))
            return
        ax["wake"] = ax["wake"] + delay

    def _abort_task(self, a: int):
        ax = self._axis[a]
        if ax.get("task") is not None:
            ax["task"].close()
        ax["task"], ax["wake"], ax["armed_by_task"] = None, None, False

    def _task_done(self, a: int, ok: bool):
        """axis.cpp:593-600: a failed state clears the chain and drops to IDLE, else the
        chain moves on."""
        ax = self._axis[a]
        self._disarm(a)
        if not ok:
            ax["chain"] = []
        elif ax["chain"]:
            ax["chain"].pop(0)
        self._start_task(a)

    # -- small handlers ---------------------------------------------------------------
    def _invalid_state(self, a: int):
        self.st.AI[0, a, L.I_AXIS_ERR] |= AXIS_ERROR_INVALID_STATE     # axis.cpp:586-589
        return False
        yield  # a generator that ends at once

    def _failed(self, a: int):
        return False
        yield

    def _unknown_phase(self, a: int):
        """0.5.6 closes the loop without checking the encoder (axis.cpp:575): with no
        offset calibration the encoder gives no phase (encoder.cpp:836-839) and the first
        FOC update disarms the motor (foc.cpp:84-85, motor.cpp:337-341)."""
        yield CONTROL_PERIOD
        st = self.st
        st.AI[0, a, L.I_MOTOR_ERR] |= MOTOR_ERROR_UNKNOWN_PHASE_ESTIMATE
        st.AI[0, a, L.I_AXIS_ERR] |= AXIS_ERROR_MOTOR_FAILED
        return False

    def _modulation_nan(self, a: int):
        """torque_constant 0: the torque limit is 0 (motor.cpp:385-393) and the current
        command 0 / 0; the FOC's modulation is NaN (foc.cpp) and the motor disarms with
        MODULATION_IS_NAN (0x10000) at the first update."""
        yield CONTROL_PERIOD
        self.st.AI[0, a, L.I_MOTOR_ERR] |= 0x10000
        self.st.AI[0, a, L.I_AXIS_ERR] |= AXIS_ERROR_MOTOR_FAILED
        return False

    def _run_homing(self, a: int):
        """axis.cpp:356-361: homing needs the min endstop; this leg has none (enabling one is
        refused), so homing fails at once with HOMING_WITHOUT_ENDSTOP."""
        self.st.AI[0, a, L.I_AXIS_ERR] |= AXIS_ERROR_HOMING_WITHOUT_ENDSTOP
        return False
        yield

    # -- the open loop (open_loop_controller.cpp, the kernel's MODE_CALIB) --------------
    def _electrical_lock(self, a: int, phase_el: float) -> float:
        """Motor turns where electrical angle ``phase_el`` holds the rotor: the alignment
        nearest to where it is now (the kernel's frame)."""
        j = self.twin.axes.joint_of_axis(a)
        turns = float(self.twin.axes.motor_turns(self.twin.motor_angle(self.st, j)[0], j))
        pp = self.twin.motor.pole_pairs
        off = (self._magnet_offset[a] + phase_el / (2 * math.pi)) / pp
        return off + round((turns - off) * pp) / pp

    def _open_loop(self, a: int, phase_el: float, current: float, ramp: float) -> bool:
        """Arm the motor with the field at electrical angle ``phase_el``, its current ramping
        at ``ramp`` [A/s] to ``current`` [A]; False (and the chain fails) if arming is refused."""
        st = self.st
        if not self._arm(a):
            return False
        st.AS[0, a, L.S_CAL_POS] = self._electrical_lock(a, phase_el)
        st.C[0, a, L.C_CAL_VEL] = 0.0
        st.AS[0, a, L.S_CAL_I] = 0.0
        st.C[0, a, L.C_CAL_CURRENT] = current
        st.C[0, a, L.C_CAL_RAMP] = ramp
        st.AI[0, a, L.I_MODE] = L.MODE_CALIB
        self._axis[a]["armed_by_task"] = True
        return True

    def _field_velocity(self, a: int, omega_el: float):
        """The field turns at ``omega_el`` [rad/s electrical] (C_CAL_VEL in motor turn/s)."""
        self.st.C[0, a, L.C_CAL_VEL] = omega_el / (2 * math.pi * self.twin.motor.pole_pairs)

    def _count(self, a: int) -> int:
        return int(self.st.AI[0, a, L.I_COUNTS])

    def _armed(self, a: int) -> bool:
        return self.st.AI[0, a, L.I_MODE] != L.MODE_IDLE

    # -- motor calibration (motor.cpp:416-511) -------------------------------------------
    def _run_motor_calibration(self, a: int):
        ax, st, m = self._axis[a], self.st, self.twin.motor
        ax["motor_calibrated"] = False
        s = self._settings[a]
        max_voltage = float(s.get("axis*.motor.config.resistance_calib_max_voltage", 2.0))
        test_current = float(ax["calibration_current"])
        # measure_phase_resistance: the voltage integrator (kI = 1 V/s/A) drives I_alpha to
        # the test current; the rotor locks to electrical angle 0 (the alpha axis)
        R = m.phase_resistance
        tau = R / R_MEASUREMENT_KI
        if not self._open_loop(a, 0.0, test_current, test_current / (3.0 * tau)):
            return False
        v_final = R * test_current
        if abs(v_final) > max_voltage:
            # the voltage crosses max_voltage on its way: PHASE_RESISTANCE_OUT_OF_RANGE then
            t_cross = -tau * math.log(1.0 - max_voltage / abs(v_final))
            yield min(t_cross, R_MEASUREMENT_TIME)
            self._motor_error(a, MOTOR_ERROR_PHASE_RESISTANCE_OUT_OF_RANGE)
            return False
        yield R_MEASUREMENT_TIME
        if not self._armed(a):
            return False
        noise = float(self.twin.plant.current_noise) if self.twin.noise else 0.0
        # the integrator low-passes the current noise (a first-order loop, pole kI / R): the
        # voltage it ends on scatters by noise * sqrt(kI R dt / 2)
        sigma_v = noise * math.sqrt(R_MEASUREMENT_KI * R * CONTROL_PERIOD / 2.0)
        # motor.cpp:421-423: the measurement is phase_resistance, and with it the current
        # controller's gains (motor.cpp:297-302: C_PHASE_R)
        self._set_phase_resistance(a, float((v_final + sigma_v * self._cal_rng.standard_normal()) / test_current))
        # measure_phase_inductance: +-test voltage toggled every period, no net torque: the
        # rotor is free; L = V / (mean |dI| / dt) over 1.25 s (motor.cpp:88-134)
        st.C[0, a, L.C_CAL_CURRENT] = 0.0
        yield L_MEASUREMENT_TIME
        if not self._armed(a):
            return False
        n = int(L_MEASUREMENT_TIME / CONTROL_PERIOD)
        step = max_voltage * CONTROL_PERIOD / m.phase_inductance   # |dI| per period [A]
        delta = n * step + math.sqrt(2.0 * n) * noise * self._cal_rng.standard_normal()
        L_meas = max_voltage / (delta / L_MEASUREMENT_TIME) if delta > 0 else math.inf
        self._set_phase_inductance(a, float(L_meas))              # motor.cpp:478-479, 297-302
        self._disarm(a)
        if not (L_RANGE[0] <= L_meas <= L_RANGE[1]):
            st.AI[0, a, L.I_MOTOR_ERR] |= MOTOR_ERROR_PHASE_INDUCTANCE_OUT_OF_RANGE   # motor.cpp:481-483
            return False
        ax["motor_calibrated"] = True                  # motor.cpp:509
        return True

    def _motor_error(self, a: int, error: int):
        """motor.cpp:337-341 disarm_with_error: the motor's error, the axis's MOTOR_FAILED."""
        self.st.AI[0, a, L.I_MOTOR_ERR] |= error
        self.st.AI[0, a, L.I_AXIS_ERR] |= AXIS_ERROR_MOTOR_FAILED
        self._disarm(a)

    # -- encoder offset calibration (encoder.cpp:327-462; fw-v0.5.1 encoder.cpp:183-285) ---
    def _offset_calibration_frame(self, a: int):
        """encoder.cpp:344 sets shadow_count := count_in_cpr, but the next tick's incremental
        update (encoder.cpp:480,657-662,762) adds the int16 difference between the timer's
        count and that value: shadow_count is the timer's count again, in the boot frame, up
        to a multiple of 2^16 when the count is that far from [0, cpr). The PLL's estimate is
        not touched (it follows such a jump as it would on the board)."""
        ax, st = self._axis[a], self.st
        cpr = ax["cpr"]
        count = int(st.AI[0, a, L.I_COUNTS])
        in_cpr = count % cpr if cpr else count      # a cpr of 0: mod reads the count (see _count_in_cpr)
        shift = in_cpr + ((count - in_cpr + 0x8000) % 0x10000 - 0x8000) - count
        if shift:
            st.C[0, a, L.C_COUNT_OFFSET] += shift
            st.AI[0, a, L.I_COUNTS] += shift
            st.AS[0, a, L.S_COUNT_F] += shift

    def _shift_counts(self, a: int, shift: int):
        """The counts moved by ``shift`` with the PLL's estimate (set_linear_count,
        encoder.cpp:141-154: the estimate in turns is counts / the configured cpr,
        encoder.cpp:800); the circular position keeps its value."""
        st = self.st
        st.C[0, a, L.C_COUNT_OFFSET] += shift
        st.AI[0, a, L.I_COUNTS] += shift
        st.AS[0, a, L.S_COUNT_F] += shift
        d_pe = shift / float(st.C[0, a, L.C_CPR])
        st.AS[0, a, L.S_POS_EST] += d_pe
        st.AS[0, a, L.S_POS_CIRC] -= d_pe

    def _run_offset_calibration(self, a: int):
        ax = self._axis[a]
        enc = self._settings[a]
        scan_distance = float(ax["calib_scan_distance"])
        scan_omega = float(ax["calib_scan_omega"])
        if ax["use_index"] and not ax.get("index_found"):
            self._encoder_error(a, ENCODER_ERROR_INDEX_NOT_FOUND_YET)          # encoder.cpp:331-334
            return False
        self._offset_calibration_frame(a)
        ax["encoder_ready"] = False
        ax["ready_by_index"] = False
        current = float(ax["calibration_current"])
        if self.firmware == "0.5.1":
            # fw-v0.5.1 encoder.cpp:197-201: a voltage R_config * I_cal, the current follows
            # through the winding's L/R
            current = current * ax["phase_resistance"] / self.twin.motor.phase_resistance
            ramp = abs(current) / (3.0 * self.twin.motor.phase_inductance / self.twin.motor.phase_resistance)
        else:
            ramp = abs(current) / OFFSET_LOCK_TIME * 2.0                      # encoder.cpp:353
        # the lock at the start of the forward scan: -scan_distance / 2 (encoder.cpp:361)
        start = (-scan_distance / 2.0 + math.pi) % (2 * math.pi) - math.pi
        if not self._open_loop(a, start, current, ramp):
            return False
        yield OFFSET_LOCK_TIME
        if not self._armed(a):
            return False
        init = self._count(a)
        total, steps, distance = 0.0, 0, 0.0
        # scan forward (encoder.cpp:389-398): one sample of the count per 1 ms iteration
        self._field_velocity(a, scan_omega)
        iterations = int(math.ceil(scan_distance / (scan_omega * AXIS_THREAD_PERIOD) - 1e-9))
        for n in self._loop_steps(iterations):
            c0 = self._count(a)
            yield n * AXIS_THREAD_PERIOD
            if not self._armed(a):
                return False
            total += _interpolated_sum(c0, self._count(a), n)
            steps += n
            distance += scan_omega * AXIS_THREAD_PERIOD * n
        count = self._count(a)
        if count > init + 8:                            # encoder.cpp:401-412
            ax["direction"] = 1
        elif count < init - 8:
            ax["direction"] = -1
        else:
            self._encoder_error(a, ENCODER_ERROR_NO_RESPONSE)
            return False
        pp = ax["pole_pairs"]
        cpr = ax["cpr"]
        with_nan = float("nan")
        expected = scan_distance / (pp * 2 * math.pi / cpr) if pp and cpr else with_nan
        ax["calib_scan_response"] = float(abs(count - init))
        if not abs(ax["calib_scan_response"] - expected) / expected <= float(ax["calib_range"]):
            self._encoder_error(a, ENCODER_ERROR_CPR_POLEPAIRS_MISMATCH)      # encoder.cpp:415-421
            return False
        # scan backwards (encoder.cpp:427-436)
        self._field_velocity(a, -scan_omega)
        for n in self._loop_steps(iterations):
            c0 = self._count(a)
            yield n * AXIS_THREAD_PERIOD
            if not self._armed(a):
                return False
            total += _interpolated_sum(c0, self._count(a), n)
            steps += n
        self._disarm(a)
        # encoder.cpp:445-447: the mean count of the scans is electrical angle 0
        total = int(round(total))
        offset = int(total / steps) if steps else 0     # C's int64 division truncates
        residual = total - offset * steps
        enc["axis*.encoder.config.phase_offset" if self.firmware != "0.5.1" else "axis*.encoder.config.offset"] = offset
        enc["axis*.encoder.config.phase_offset_float" if self.firmware != "0.5.1" else "axis*.encoder.config.offset_float"] = \
            float(residual / steps + 0.5) if steps else 0.5
        ax["encoder_ready"] = True                       # encoder.cpp:449
        # what a pre-calibrated encoder may use after its index at a later boot: the offset
        # measured in the index's frame (kept with the configuration)
        ax["offset_measured"] = offset if ax.get("index_found") else None
        return True

    def _encoder_error(self, a: int, error: int):
        # encoder.cpp:68-73: the encoder's error and the axis's ENCODER_FAILED
        self._axis[a]["encoder_error"] |= error
        self.st.AI[0, a, L.I_AXIS_ERR] |= AXIS_ERROR_ENCODER_FAILED
        self._disarm(a)

    @staticmethod
    def _loop_steps(iterations: int):
        """The thread's iterations in runs of at most LOOP_STEP."""
        per = max(1, int(round(LOOP_STEP / AXIS_THREAD_PERIOD)))
        while iterations > 0:
            n = min(per, iterations)
            yield n
            iterations -= n

    # -- lock-in spins (axis.cpp:184-254, encoder.cpp:174-207) ---------------------------
    def _lockin_config(self, a: int, which: str) -> dict:
        """A lock-in configuration: its endpoints, and the members the table does not expose
        (calibration_lockin's finish conditions) at the firmware's values (axis.cpp:40-52)."""
        s = self._settings[a]
        cfg = dict(CALIBRATION_LOCKIN_FINISH) if which == "calibration_lockin" else {}
        for k in ("current", "ramp_time", "ramp_distance", "accel", "vel", "finish_distance", "finish_on_vel",
                  "finish_on_distance", "finish_on_enc_idx"):
            key = f"axis*.config.{which}.{k}"
            if key in s:
                cfg[k] = s[key]
        return cfg

    def _run_index_search(self, a: int):
        """encoder.cpp:174-181: use_index on, the index forgotten, a calibration lock-in spin
        until the index pulse (or its finish distance)."""
        ax = self._axis[a]
        ax["use_index"] = True
        ax["index_found"] = False
        if self.firmware == "0.5.1" and ax["direction"] == 0 and not self._settings[a].get(
                "axis*.encoder.config.idx_search_unidirectional"):
            ax["direction"] = 1                          # fw-v0.5.1 encoder.cpp:143-145
        ax["index_armed"] = True                         # set_idx_subscribe (encoder.cpp:110-118)
        result = yield from self._run_lockin(a, self._lockin_config(a, "calibration_lockin"))
        ax["index_armed"] = False
        return result

    def _run_direction_find(self, a: int):
        """encoder.cpp:183-207: a 3 s calibration lock-in spin; the direction from the count."""
        ax = self._axis[a]
        init = self._count(a)
        cfg = self._lockin_config(a, "calibration_lockin")
        cfg.update(finish_distance=cfg["vel"] * 3.0, finish_on_distance=True, finish_on_enc_idx=False,
                   finish_on_vel=False)
        if self.firmware == "0.5.1":
            ax["direction"] = 1                          # fw-v0.5.1 encoder.cpp:154
        ok = yield from self._run_lockin(a, cfg)
        if ok:
            count = self._count(a)
            ax["direction"] = 1 if count > init + 8 else -1 if count < init - 8 else 0
        return ok

    def _run_lockin(self, a: int, cfg: dict):
        """axis.cpp:184-254 with the open-loop controller (open_loop_controller.cpp): the
        field at electrical 0, the current ramping over ramp_time, the field accelerating
        at accel to vel; every 1 ms the loop checks its finish conditions. The field's speed
        steps once per iteration (its mean over the iteration), the kernel turns it at that
        speed; the rotor follows, or stalls and slips at a hard stop."""
        ax = self._axis[a]
        current, target = float(cfg["current"]), float(cfg["vel"])
        ramp_time = float(cfg["ramp_time"])
        if self.firmware == "0.5.1":
            return (yield from self._run_lockin_051(a, cfg))
        ramp = abs(current) / ramp_time if ramp_time > 0 else math.inf
        if not self._open_loop(a, 0.0, current, ramp):
            return False
        vel, distance = 0.0, 0.0
        direction = 1.0 if target >= 0 else -1.0
        accel = abs(float(cfg["accel"]))
        while True:
            reached_vel = abs(vel - target) <= 1.1920929e-07
            reached_dist = distance * direction >= float(cfg["finish_distance"]) * direction
            if (reached_vel and cfg["finish_on_vel"]) or (reached_dist and cfg["finish_on_distance"]) \
                    or (ax.get("index_found") and cfg["finish_on_enc_idx"]):
                return True
            step = LOOP_STEP
            new_vel = min(max(target, vel - accel * step), vel + accel * step)
            # the mean speed over the step: the distance the firmware's ramp covers in it
            # (a ramp that ends inside the step runs on at the target speed)
            t_ramp = abs(new_vel - vel) / accel if accel > 0 else 0.0
            mean = (0.5 * (vel + new_vel) * t_ramp + new_vel * (step - t_ramp)) / step
            self._field_velocity(a, mean)
            before = self._rotor_encoder_turns(a)
            yield step
            if not self._armed(a):
                return False
            distance += mean * step
            vel = new_vel
            self._index_check(a, before)

    def _run_lockin_051(self, a: int, cfg: dict):
        """fw-v0.5.1 axis.cpp:231-297: a spiral-in ramp (current and phase over ramp_time),
        then accelerate from ramp_distance / ramp_time, then the constant speed; the
        lock-in state reads 1, 2, 3 meanwhile."""
        ax = self._axis[a]
        current, ramp_time = float(cfg["current"]), float(cfg["ramp_time"])
        ramp_distance = float(cfg["ramp_distance"])
        if not self._open_loop(a, 0.0, current, abs(current) / ramp_time if ramp_time > 0 else math.inf):
            return False
        ax["lockin_state"] = 1
        self._field_velocity(a, ramp_distance / ramp_time if ramp_time > 0 else 0.0)
        yield ramp_time
        if not self._armed(a):
            ax["lockin_state"] = 0
            return False
        distance = ramp_distance
        vel = ramp_distance / ramp_time if ramp_time > 0 else 0.0

        def done(vel_override=False):
            d = False
            if cfg["finish_on_vel"] or vel_override:
                d = d or abs(vel) >= abs(float(cfg["vel"]))
            if cfg["finish_on_distance"]:
                d = d or abs(distance) >= abs(float(cfg["finish_distance"]))
            if cfg["finish_on_enc_idx"]:
                d = d or bool(ax.get("index_found"))
            return d

        ax["lockin_state"] = 2
        accel = float(cfg["accel"])
        while not done(True):
            mean = vel + 0.5 * accel * LOOP_STEP
            self._field_velocity(a, mean)
            before = self._rotor_encoder_turns(a)
            yield LOOP_STEP
            if not self._armed(a):
                ax["lockin_state"] = 0
                return False
            distance += mean * LOOP_STEP
            vel += accel * LOOP_STEP
            self._index_check(a, before)
        if not done():
            ax["lockin_state"] = 3
            vel = float(cfg["vel"])
            self._field_velocity(a, vel)
            while not done():
                before = self._rotor_encoder_turns(a)
                yield LOOP_STEP
                if not self._armed(a):
                    ax["lockin_state"] = 0
                    return False
                distance += vel * LOOP_STEP
                self._index_check(a, before)
        ax["lockin_state"] = 0
        return self.st.AI[0, a, L.I_AXIS_ERR] == 0       # check_for_errors()

    # -- the encoder's index pulse (encoder.cpp:86-107) ---------------------------------
    def _rotor_encoder_turns(self, a: int) -> float:
        j = self.twin.axes.joint_of_axis(a)
        return float(self.twin.encoder_turns(self.st, j)[0])

    def _index_check(self, a: int, before: float):
        """The index pulse: once per motor turn, where the AS5047D's zero is (a position per
        motor, drawn from the seed). Found while the index interrupt is armed: the circular
        count goes to 0 and, with use_index_offset, the linear count to index_offset * cpr
        (set_linear_count also writes the timer: the frame stays); a pre-calibrated encoder
        is ready then, any other waits for its offset calibration."""
        ax = self._axis[a]
        if not (ax.get("index_armed") and ax["use_index"]) or ax.get("index_found"):
            return
        after = self._rotor_encoder_turns(a)
        idx = self._index_position[a]
        if math.floor(before - idx) == math.floor(after - idx):
            return
        crossed = idx + max(math.floor(before - idx), math.floor(after - idx))
        s = self._settings[a]
        cpr = self.twin.axes.cpr
        count_here = self._count(a)
        count_at_index = count_here - round((after - crossed) * cpr)
        target = round(float(s.get("axis*.encoder.config.index_offset", 0.0)) * ax["cpr"]) \
            if s.get("axis*.encoder.config.use_index_offset", True) else count_at_index
        self._shift_counts(a, int(target - count_at_index))
        ax["index_found"] = True
        ax["index_armed"] = False
        if ax["encoder_pre_calibrated"]:
            ax["encoder_ready"] = True
            ax["ready_by_index"] = True
        else:
            ax["encoder_ready"] = False                  # encoder.cpp:97-102
