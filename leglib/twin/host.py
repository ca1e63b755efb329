"""The twin from Python: :class:`Twin`, a batch simulator of virtual legs sharing one
plant and ODrive configuration, and the batch's state :class:`TwinState`.

A single experiment is a batch of one and a sweep a batch of many; both go through the same
kernel, so they give identical numbers. :class:`leglib.device.virtual.VirtualODrive` puts
the ODrive's object tree on top of a batch of one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .. import _numba_gc, _numba_inline  # noqa: F401  (before any kernel compiles)
from ..abort import ABORT_NONE
from ..cores import cores
from ..model.drive import AxisMap
from ..model.dynamics import mass_matrix
from ..model.terms import param_vector
from ..params import (
    LegParams,
    MotorParams,
    OdriveConfig,
    PlantParams,
    load_motor,
    load_odrive_config,
    load_plant,
)
from .effects import _encoder_error
from .kernel import _run, _run_serial
from .layout import (
    BELT_PHASE_PER_STEP,
    C_ABORT_ERROR,
    C_BEMF_FF,
    C_BRAKE_ON,
    C_BRAKE_R,
    C_CAL_CURRENT,
    C_CIRC_RANGE,
    C_CIRCULAR,
    C_CONTROL_MODE,
    C_CPR,
    C_CURRENT_BW,
    C_CURRENT_LIM,
    C_CURRENT_LIM_MARGIN,
    C_DC_MAX_NEG,
    C_DC_MAX_POS,
    C_ELEC_BW,
    C_EN_GAIN_SCHED,
    C_EN_OVERSPEED,
    C_EN_TQ_VEL_LIMIT,
    C_EN_VEL_LIMIT,
    C_ENCODER_BW,
    C_FILTER_BW,
    C_FW_056,
    C_GAIN_SCHED_WIDTH,
    C_IBUS_MAX,
    C_IBUS_MIN,
    C_INERTIA,
    C_INPUT_MODE,
    C_INPUT_POS,
    C_INPUT_TORQUE,
    C_INPUT_VEL,
    C_INT_RESET_TORQUE,
    C_KT,
    C_MAX_CURRENT,
    C_MAX_REGEN,
    C_MECH_BW,
    C_MIRROR_AXIS,
    C_MIRROR_RATIO,
    C_PHASE_L,
    C_PHASE_R,
    C_POS_GAIN,
    C_RWL_FF,
    C_SPIN_ELEC,
    C_SPIN_MECH,
    C_TORQUE_LIM,
    C_TORQUE_MIRROR_RATIO,
    C_TORQUE_RAMP_RATE,
    C_TUNE_FREQ,
    C_TUNE_TQ_AMP,
    C_VBUS,
    C_VEL_GAIN,
    C_VEL_INT_GAIN,
    C_VEL_INT_LIMIT,
    C_VEL_LIMIT,
    C_VEL_RAMP_RATE,
    C_VEL_TOL,
    CURRENT_LIM_MARGIN,
    DRV_GAINS,
    F_ASYM,
    F_BACKLASH_HALF,
    F_BELT_C,
    F_BELT_K,
    F_BELT_SUB,
    F_COG_A1,
    F_COG_A3,
    F_COG_C1,
    F_COG_ON,
    F_COG_PERIODS,
    F_COG_S3,
    F_DRIFT,
    F_DRIFT_TRAVEL,
    F_ENC_A1,
    F_ENC_A2,
    F_ENC_C1,
    F_ENC_C2,
    F_ENC_ON,
    F_ENC_S1,
    F_ENC_S2,
    F_FRIC_EXT,
    F_JM,
    F_LUGRE_S0,
    F_LUGRE_S1,
    I_AXIS_ERR,
    I_CONNECTED,
    I_MODE,
    INPUT_MODE_PASSTHROUGH,
    MAX_UNITY_GAIN_CURRENT,
    MODE_POSITION,
    N_AXINT,
    N_AXSTATE,
    N_CFG,
    N_FR,
    N_OSC,
    N_X,
    S_ELEC_P,
    S_FOC_POWER,
    S_INTEGRATOR,
    S_IQ,
    S_MECH_P,
    S_OSC,
    S_POS_EST,
    S_V_INT,
    S_V_PREV,
    VECTOR_LEGS,
    X_DPHI1,
    X_DPHI2,
    X_DQ1,
    X_DQ2,
    X_PHI1,
    X_PHI2,
    X_Q1,
    X_Q2,
    X_TRAVEL1,
    X_TRAVEL2,
)
from .rng import seeds_for


def true_leg(plant: PlantParams) -> LegParams:
    """The twin's hidden leg: the base set scaled (inertia, mass), the payload on the foot,
    and the plant's own viscous and Coulomb friction (Stribeck is added in the kernel).
    With a compliant belt the rotor (reflected through the belt, J_rotor N^2) is its own
    inertia in the kernel and is taken out of the drive inertias Jd1, Jd2: the total stays."""
    leg = plant.base_leg().scaled(plant.inertia_scale, plant.mass_scale, plant.payload_mass)
    leg = leg.replace(c11=plant.viscous1, c12=0.0, c21=0.0, c22=plant.viscous2,
                      coulomb1=plant.coulomb1, coulomb2=plant.coulomb2)
    if plant.belt_compliant:
        jm = reflected_rotor_inertia(plant, leg)
        leg = leg.replace(Jd1=leg.Jd1 - jm, Jd2=leg.Jd2 - jm)
    return leg


def reflected_rotor_inertia(plant: PlantParams, leg: LegParams | None = None) -> float:
    """The rotor and its pulley seen at the joint through the belt, J_rotor N^2 [kg*m^2]."""
    leg = plant.base_leg() if leg is None else leg
    return plant.rotor_inertia * leg.gear_ratio ** 2


def effect_parameters(plant: PlantParams, leg: LegParams, dt: float) -> np.ndarray:
    """The kernel's parameters of the plant's unmodeled effects (FR[b, 14:], the F_
    indices), all zero where an effect is off. A compliant belt gets the number of
    sub-steps that keeps its mode (rotor against the lightest joint inertia at rest) and
    its damping well inside semi-implicit Euler's stable range at ``dt``."""
    out = np.zeros(N_FR - 14)
    k = lambda i: i - 14   # noqa: E731 - FR index -> position in this vector
    if plant.belt_compliant:
        jm = reflected_rotor_inertia(plant, leg)
        if plant.mechanism == "fivebar":
            j_min = float(np.min(np.linalg.eigvalsh(mass_matrix(leg, *leg.q0))))
        else:
            j_min = min(leg.I1 + leg.Jd1 + leg.m1 * leg.lc1 ** 2, leg.I2 + leg.Jd2 + leg.m2 * leg.lc2 ** 2)
        inv = 1.0 / jm + 1.0 / j_min
        w = math.sqrt(plant.belt_stiffness * inv)
        sub = max(1, math.ceil(w * dt / BELT_PHASE_PER_STEP), math.ceil(plant.belt_damping * inv * dt / 0.5))
        out[k(F_BELT_K)], out[k(F_BELT_C)] = plant.belt_stiffness, plant.belt_damping
        out[k(F_BACKLASH_HALF)], out[k(F_JM)], out[k(F_BELT_SUB)] = 0.5 * plant.backlash, jm, sub
    amps = (plant.cogging1, plant.cogging2, plant.cogging3)
    if sum(amps) > 0.0:
        out[k(F_COG_ON)], out[k(F_COG_PERIODS)] = 1.0, plant.cogging_periods
        out[k(F_COG_A1):k(F_COG_A3) + 1] = amps
        phases = (plant.cogging_phase1, plant.cogging_phase2, plant.cogging_phase3)
        out[k(F_COG_C1):k(F_COG_S3) + 1] = [f(p) for p in phases for f in (math.cos, math.sin)]
    if plant.encoder_error1 + plant.encoder_error2 > 0.0:
        out[k(F_ENC_ON)] = 1.0
        for a1, c1, s1, amp, phase in ((F_ENC_A1, F_ENC_C1, F_ENC_S1, plant.encoder_error1, plant.encoder_phase1),
                                       (F_ENC_A2, F_ENC_C2, F_ENC_S2, plant.encoder_error2, plant.encoder_phase2)):
            out[k(a1)], out[k(c1)], out[k(s1)] = amp, math.cos(phase), math.sin(phase)
    if plant.lugre or plant.coulomb_asymmetry != 0.0 or plant.friction_drift > 0.0:
        out[k(F_FRIC_EXT)] = 1.0
        out[k(F_LUGRE_S0)], out[k(F_LUGRE_S1)] = plant.lugre_stiffness, plant.lugre_damping
        out[k(F_ASYM)], out[k(F_DRIFT)] = plant.coulomb_asymmetry, plant.friction_drift
        out[k(F_DRIFT_TRAVEL)] = plant.drift_travel
    return out


def controller_defaults(C: np.ndarray, cpr: float) -> None:
    """The firmware's defaults of the controller's and motor's further settings
    (controller.hpp:25-56, motor.hpp:28-30; ``C[..., k]`` of both axes) and the configured
    cpr (encoder.config.cpr)."""
    C[..., C_CONTROL_MODE] = MODE_POSITION
    C[..., C_EN_VEL_LIMIT] = 1.0
    C[..., C_EN_TQ_VEL_LIMIT] = 1.0
    C[..., C_EN_OVERSPEED] = 1.0
    C[..., C_EN_GAIN_SCHED] = 0.0
    C[..., C_GAIN_SCHED_WIDTH] = 10.0
    C[..., C_VEL_RAMP_RATE] = 1.0
    C[..., C_TORQUE_RAMP_RATE] = 0.01
    C[..., C_CIRCULAR] = 0.0
    C[..., C_CIRC_RANGE] = 1.0
    C[..., C_INERTIA] = 0.0
    C[..., C_MIRROR_AXIS] = 255.0                   # uint8 -1
    C[..., C_MIRROR_RATIO] = 1.0
    C[..., C_TORQUE_MIRROR_RATIO] = 0.0
    C[..., C_TUNE_FREQ:C_TUNE_TQ_AMP + 1] = 0.0
    C[..., C_TORQUE_LIM] = np.inf
    C[..., C_CURRENT_LIM_MARGIN] = CURRENT_LIM_MARGIN
    C[..., C_MAX_CURRENT] = max_measurable_current(60.0)
    C[..., C_CPR] = float(cpr)
    C[..., C_BEMF_FF] = 0.0                         # motor.hpp:43-47
    C[..., C_RWL_FF] = 0.0
    C[..., C_IBUS_MIN] = -np.inf
    C[..., C_IBUS_MAX] = np.inf
    C[..., C_MECH_BW] = 20.0                        # controller.hpp:52-55
    C[..., C_ELEC_BW] = 20.0
    C[..., C_SPIN_MECH] = -10.0
    C[..., C_SPIN_ELEC] = 10.0


def max_measurable_current(requested_current_range: float) -> float:
    """motor.cpp:312-330 with drv8301.cpp:21-36: the largest current the shunt amplifier
    measures when ``requested_current_range`` [A] is asked for: the largest DRV8301 gain not
    above the requested one (else the smallest), max_unity_gain_current / gain [A]."""
    requested_gain = MAX_UNITY_GAIN_CURRENT / requested_current_range if requested_current_range != 0 else math.inf
    setting = len(DRV_GAINS) - 1
    while setting and DRV_GAINS[setting] > requested_gain:
        setting -= 1
    return MAX_UNITY_GAIN_CURRENT / DRV_GAINS[setting]


@dataclass
class TwinState:
    """Everything the kernel mutates, for a batch of B legs (arrays, see :func:`_run`)."""

    X: np.ndarray
    AS: np.ndarray
    AI: np.ndarray
    C: np.ndarray
    RNG: np.ndarray
    ABORT: np.ndarray

    def copy(self) -> "TwinState":
        return TwinState(*(a.copy() for a in (self.X, self.AS, self.AI, self.C, self.RNG, self.ABORT)))

    def take(self, idx) -> "TwinState":
        return TwinState(*(a[idx].copy() for a in (self.X, self.AS, self.AI, self.C, self.RNG, self.ABORT)))

    @property
    def batch(self) -> int:
        return self.X.shape[0]


class Twin:
    """Batch simulator of B virtual legs sharing one plant and ODrive configuration.

    Parameters
    ----------
    plant : PlantParams or name, the simulated physical leg (default ``"default"``)
    config : OdriveConfig or name, the ODrive configuration (default Listing 7.1)
    batch : number of legs
    seed : base seed of the noise streams
    noise : encoder and current noise on
    motor : MotorParams or name, the motors (default the thesis's MN5212)
    quantize : encoder readings quantized at the CPR (False: exact positions, for models
        fitted by finite differences)
    """

    def __init__(self, plant: PlantParams | str = "default", config: OdriveConfig | str = "thesis",
                 batch: int = 1, seed: int = 0, noise: bool = True, motor: MotorParams | str = "mn5212",
                 quantize: bool = True):
        self.plant = load_plant(plant) if isinstance(plant, str) else plant
        self.motor = load_motor(motor) if isinstance(motor, str) else motor
        self.config = load_odrive_config(config) if isinstance(config, str) else config
        self.nominal_leg = self.plant.base_leg()
        self.leg = true_leg(self.plant)
        self.axes = AxisMap.from_leg(self.nominal_leg)
        self.seed = int(seed)
        self.noise = bool(noise)
        self.dt = 1.0 / self.config.loop_frequency
        self.P = param_vector(self.leg)
        self.payload_mounted = True
        leg = self.leg
        J1 = leg.I1 + leg.Jd1 + leg.m1 * leg.lc1 ** 2
        J2 = leg.I2 + leg.Jd2 + leg.m2 * leg.lc2 ** 2
        p = self.plant
        self.FR = np.array([p.viscous1, p.viscous2, p.coulomb1, p.coulomb2, p.stribeck1, p.stribeck2,
                            p.stribeck_velocity, p.coulomb_smoothing, p.gap_min, p.stop_stiffness,
                            p.stop_damping, J1, J2, p.gap_max, *effect_parameters(p, leg, self.dt)])
        self.mech = 0 if p.mechanism == "fivebar" else 1
        ax = self.axes
        motor = self.motor
        self.DRV = np.array([ax.gear_ratio, ax.cpr, ax.direction, ax.q_rest[0], ax.q_rest[1],
                             ax.joint_of_axis(0), p.encoder_noise if noise else 0.0,
                             p.current_noise if noise else 0.0, motor.torque_constant, 1.0 if quantize else 0.0,
                             float(motor.pole_pairs), motor.phase_resistance, motor.phase_inductance])
        self.state = self._initial_state(batch)

    def mount_payload(self, mounted: bool) -> None:
        """Put the plant's foot payload on (True) or take it off (False) the simulated leg.
        The plant (its parameters, what the device reports) keeps the payload either way;
        only the mechanics simulated from now on change."""
        p = self.plant if mounted else self.plant.replace(payload_mass=0.0)
        self.leg = true_leg(p)
        self.P = param_vector(self.leg)
        self.payload_mounted = bool(mounted)
        self.__dict__.pop("_fixed", None)   # the kernel's cached copies of P

    # -- state -----------------------------------------------------------------------
    def _initial_state(self, batch: int) -> TwinState:
        X = np.zeros((batch, N_X))
        X[:, X_Q1], X[:, X_Q2] = self.axes.q_rest
        X[:, X_PHI1], X[:, X_PHI2] = self.axes.q_rest
        C = np.zeros((batch, 2, N_CFG))
        cfg = self.config
        C[:, :, C_POS_GAIN] = 20.0       # firmware defaults
        C[:, :, C_VEL_GAIN] = 1.0 / 6.0
        C[:, :, C_VEL_INT_GAIN] = 1.0 / 3.0
        C[:, :, C_VEL_LIMIT] = cfg.vel_limit
        C[:, :, C_VEL_TOL] = cfg.vel_limit_tolerance
        C[:, :, C_CURRENT_LIM] = cfg.current_lim
        C[:, :, C_KT] = cfg.torque_constant
        C[:, :, C_CURRENT_BW] = cfg.current_control_bandwidth
        C[:, :, C_ENCODER_BW] = cfg.encoder_bandwidth
        C[:, :, C_VEL_INT_LIMIT] = np.inf           # firmware default (0.5.4+)
        C[:, :, C_INPUT_MODE] = INPUT_MODE_PASSTHROUGH
        C[:, :, C_FILTER_BW] = 2.0                  # firmware default input_filter_bandwidth
        C[:, :, C_INT_RESET_TORQUE] = 1.0
        C[:, :, C_CAL_CURRENT] = 10.0               # firmware default calibration_current
        controller_defaults(C, cpr=cfg.cpr)
        # the current controller's R and L as a motor calibration measures them (motor.cpp:
        # 416-509): the motor's own
        C[:, :, C_PHASE_R] = self.motor.phase_resistance
        C[:, :, C_PHASE_L] = self.motor.phase_inductance
        # the board as leglib configures it: brake resistor on, the firmware's bus limits
        C[:, 0, C_BRAKE_ON] = 1.0
        C[:, 0, C_BRAKE_R] = cfg.brake_resistance
        C[:, 0, C_MAX_REGEN] = 0.0
        C[:, 0, C_DC_MAX_POS] = np.inf
        C[:, 0, C_DC_MAX_NEG] = -0.01
        C[:, 0, C_VBUS] = 24.0
        C[:, 0, C_FW_056] = 1.0                     # the firmware the batch follows: 0.5.6
        st = TwinState(X=X, AS=np.zeros((batch, 2, N_AXSTATE)), AI=np.zeros((batch, 2, N_AXINT), np.int64),
                       C=C, RNG=seeds_for(self.seed, [(i,) for i in range(batch)]),
                       ABORT=np.zeros((batch, 2), np.int64))
        return st

    def rest_state(self) -> TwinState:
        """A copy of the state after the idle leg has settled on its stop (cached)."""
        if not hasattr(self, "_rest"):
            st = self._initial_state(1)
            self.run(st, seconds=2.0)
            st.X[:, [X_DQ1, X_DQ2, X_DPHI1, X_DPHI2]] = 0.0
            st.X[:, 4] = 0.0
            # encoder and estimator agree with the settled leg
            self.run(st, ticks=int(0.05 / self.dt))
            st.X[:, 4] = 0.0
            st.X[:, [X_TRAVEL1, X_TRAVEL2]] = 0.0   # a leg fresh from assembly: no use yet
            self._rest = st
        return self._rest.copy()

    def motor_angle(self, st: TwinState, joint: int) -> np.ndarray:
        """Where joint ``joint``'s motor is, on the joint side [rad] (B,): the rotor's angle
        with a compliant belt, the joint's with a rigid one."""
        col = (X_PHI1 if self.plant.belt_compliant else X_Q1) + 2 * joint
        return st.X[:, col].copy()

    def encoder_turns(self, st: TwinState, joint: int) -> np.ndarray:
        """What joint ``joint``'s encoder reads [motor turn from rest] (B,), without noise
        and quantization: the rotor's turns plus the plant's encoder error."""
        turns = self.axes.motor_turns(self.motor_angle(st, joint), joint)
        fr = self.FR[None, :]
        if fr[0, F_ENC_ON] > 0.0:
            turns = turns + np.array([_encoder_error(fr, 0, float(t)) for t in np.atleast_1d(turns)])
        return turns

    # -- running ---------------------------------------------------------------------
    def run(self, st: TwinState, seconds: float | None = None, ticks: int | None = None,
            torque_table: np.ndarray | None = None, table_period: float | None = None,
            record_every: int = 0, record: np.ndarray | None = None, record_offset: int = 0) -> None:
        """Advance ``st`` in place (compiled kernel; no Python per tick)."""
        n = int(ticks) if ticks is not None else int(round(seconds / self.dt))
        if n <= 0:
            return
        B = st.batch
        fixed = self.__dict__.setdefault("_fixed", {})
        if B not in fixed:  # per-batch-size constant arrays, built once (host loops call run often)
            # copies, writable for every B: numba types a read-only array apart, so a view
            # (read-only for B = 1) would compile every kernel a second time
            fixed[B] = (np.broadcast_to(self.P, (B, self.P.size)).copy(),
                        np.broadcast_to(self.FR, (B, self.FR.size)).copy(),
                        np.full(B, self.mech, np.int64), np.zeros((B, 0, 2)), np.zeros((B, 0, 5)))
        P, FR, MECH, no_table, no_rec = fixed[B]
        tt = no_table if torque_table is None else np.ascontiguousarray(torque_table, float)
        tt_period = 1 if table_period is None else max(1, int(round(table_period / self.dt)))
        rec = no_rec if record is None else record
        if B == 1:
            _run_serial(n, self.dt, st.X, st.AS, st.AI, st.C, P, FR, MECH, self.DRV, st.RNG, st.ABORT, tt,
                        tt_period, rec, int(record_every), int(record_offset), 1)
            return
        # blocks of legs handed out one at a time (a dynamic schedule: a core busy with
        # something else takes fewer); whole vectors of legs, two when there are blocks
        # enough to share out evenly
        block = 2 * VECTOR_LEGS if B >= 16 * VECTOR_LEGS * cores() else VECTOR_LEGS
        _run(n, self.dt, st.X, st.AS, st.AI, st.C, P, FR, MECH, self.DRV, st.RNG, st.ABORT, tt, tt_period,
             rec, int(record_every), int(record_offset), block)

    def step_batch(self, gains: np.ndarray, step_turns: float = 0.4, duration: float = 1.5,
                   sample_period: float = 0.002, vel_limit: float | None = None,
                   abort_error_turns: float | None = None, start: TwinState | None = None) -> dict:
        """Position step responses of Listing 7.4 for each row of ``gains``, all at once.

        Parameters
        ----------
        gains : (B, 3) pos_gain [(turn/s)/turn], vel_gain [N*m/(turn/s)],
            vel_integrator_gain [N*m/(turn/s)/s]
        step_turns : motor step; the axis driving q1 gets +step, the other -step [turn]
        duration : response length [s]; sample_period : recording period [s]
        vel_limit : velocity limit during the step [turn/s] (default: config.step_vel_limit)
        abort_error_turns : abort (both axes IDLE) when |input_pos - pos_estimate| exceeds it
            (default 2 * |step|)
        start : the state every leg starts from (default: at rest on its stop). Every
            point starts from this same state, its friction drift (accumulated joint travel,
            X[:, X_TRAVEL1:]) included: a batch's points do not wear the leg for each other,
            whereas a device (:class:`leglib.device.virtual.firmware.VirtualODrive`) carries its
            drift from experiment to experiment.

        Returns
        -------
        dict with ``t`` (n,), ``counts`` (B, n, 2) per axis, ``iq`` (B, n, 2) [A],
        ``abort_tick`` (B,) (-1: completed), ``abort_reason`` (B,), axis errors (B, 2).
        """
        gains = np.atleast_2d(np.asarray(gains, dtype=float))
        B = gains.shape[0]
        base = self.rest_state() if start is None else start
        st = base.take(np.zeros(B, dtype=int))
        st.RNG[:] = seeds_for(self.seed, [tuple(g) + (step_turns, duration) for g in gains])
        st.ABORT[:] = (-1, ABORT_NONE)
        st.X[:, 4] = 0.0
        vl = self.config.step_vel_limit if vel_limit is None else vel_limit
        abort = 2.0 * abs(step_turns) if abort_error_turns is None else abort_error_turns
        a_q1 = self.axes.axis_of_joint[0]
        for a in range(2):
            sign = 1.0 if a == a_q1 else -1.0
            st.C[:, a, C_POS_GAIN] = gains[:, 0]
            st.C[:, a, C_VEL_GAIN] = gains[:, 1]
            st.C[:, a, C_VEL_INT_GAIN] = gains[:, 2]
            st.C[:, a, C_VEL_LIMIT] = vl
            st.C[:, a, C_INPUT_VEL] = 0.0
            st.C[:, a, C_INPUT_TORQUE] = 0.0
            st.C[:, a, C_INPUT_POS] = st.AS[:, a, S_POS_EST] + sign * step_turns
            st.C[:, a, C_ABORT_ERROR] = abort
            st.C[:, a, C_INPUT_MODE] = INPUT_MODE_PASSTHROUGH
            st.C[:, a, C_CONTROL_MODE] = MODE_POSITION
            st.AI[:, a, I_MODE] = MODE_POSITION
            st.AI[:, a, I_CONNECTED] = 1        # closed loop connects the estimates (axis.cpp:270-285)
            # the controller's and the current controller's reset at arming (controller.cpp:12-19,
            # foc.cpp:47-53)
            st.AS[:, a, [S_V_PREV, S_V_INT, S_IQ, S_MECH_P, S_ELEC_P, S_FOC_POWER]] = 0.0
            st.AS[:, a, S_INTEGRATOR] = 0.0
            st.AS[:, a, S_OSC:S_OSC + N_OSC] = 0.0
        every = max(1, int(round(sample_period / self.dt)))
        n_ticks = int(round(duration / self.dt))
        n_rec = (n_ticks + every - 1) // every
        rec = np.zeros((B, n_rec, 5))
        self.run(st, ticks=n_ticks, record_every=every, record=rec)
        # views of the record (no copies of its megabytes): nothing else holds it
        return {"t": rec[0, :, 0], "counts": rec[:, :, 1:3], "iq": rec[:, :, 3:5],
                "abort_tick": np.where(st.ABORT[:, 1] != ABORT_NONE, st.ABORT[:, 0], -1),
                "abort_reason": st.ABORT[:, 1].copy(), "axis_error": st.AI[:, :, I_AXIS_ERR].copy(),
                "final": st}
