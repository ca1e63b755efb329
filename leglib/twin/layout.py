"""The twin's state layout: what each slot of the kernel's arrays holds.

The kernel (:mod:`leglib.twin.kernel`) works on flat float and int arrays per leg and axis;
these constants name their slots (``C_`` configuration, ``S_`` axis state, ``I_`` integer
state, ``X_`` the leg's mechanical state, ``F_`` plant parameters), the firmware's error
codes and modes, and the rows of a block's working copy (``R_``, ``V_``, ``K_``, ``G_``,
``W_``) used by the vectorized path. Plain Python constants: no numba here.

numba compiles these constants into each kernel function as it finds them, and its on-disk
cache of a function is renewed only when that function's own file changes. So a constant
that a compiled module uses (``mechanics.py``, ``effects.py``) keeps its value: new slots
and rows are appended, never inserted before existing ones.
"""

from __future__ import annotations

from ..abort import N_OSC

TICK_HZ_DEFAULT = 8000.0

# axis modes inside the kernel (control_mode values of the firmware; 0 = not in closed loop;
# MODE_CALIB: armed by a calibration, the rotor locked to an electrical angle that the axis
# state machine of leglib.device.virtual.firmware moves)
MODE_IDLE, MODE_TORQUE, MODE_VELOCITY, MODE_POSITION, MODE_CALIB = 0, 1, 2, 3, 4
# controller.config.control_mode values (firmware enums; VOLTAGE_CONTROL is "not used
# internally", odrive-interface.yaml:1607-1609: the controller treats it as torque control)
CONTROL_MODE_VOLTAGE, CONTROL_MODE_TORQUE, CONTROL_MODE_VELOCITY, CONTROL_MODE_POSITION = 0, 1, 2, 3
# controller.config.input_mode values (firmware enums)
INPUT_MODE_INACTIVE, INPUT_MODE_PASSTHROUGH, INPUT_MODE_VEL_RAMP, INPUT_MODE_POS_FILTER = 0, 1, 2, 3
INPUT_MODE_MIX_CHANNELS, INPUT_MODE_TRAP_TRAJ, INPUT_MODE_TORQUE_RAMP, INPUT_MODE_MIRROR = 4, 5, 6, 7
INPUT_MODE_TUNING = 8      # 0.5.6 (not in fw-v0.5.1)

# float config per axis: C[b, axis, k]
(C_POS_GAIN, C_VEL_GAIN, C_VEL_INT_GAIN, C_VEL_LIMIT, C_VEL_TOL, C_CURRENT_LIM, C_KT,
 C_INPUT_POS, C_INPUT_VEL, C_INPUT_TORQUE, C_WD_TIMEOUT, C_CURRENT_BW, C_ENCODER_BW,
 C_ABORT_ERROR, C_WD_ENABLE, C_COUNT_OFFSET, C_VEL_INT_LIMIT, C_INPUT_MODE, C_FILTER_BW,
 C_TT_XI, C_TT_XF, C_TT_VI, C_TT_AR, C_TT_VR, C_TT_DR, C_TT_TA, C_TT_TV, C_TT_TD, C_TT_YACC,
 C_CAL_VEL, C_CAL_CURRENT, C_INT_RESET_TORQUE, C_CAL_RAMP) = range(33)
# system (board) configuration, kept in the slots of axis 0: C[b, 0, k]
(C_BRAKE_ON, C_BRAKE_R, C_MAX_REGEN, C_DC_MAX_POS, C_DC_MAX_NEG, C_VBUS, C_REGEN_ERR_STYLE) = range(33, 40)
# appended for the board's power supply (read only by kernel._board_checks; slots of axis 0):
# the supply's source resistance [ohm], config.dc_bus_undervoltage_trip_level and
# config.dc_bus_overvoltage_trip_level [V], and whether the board checks them (1: a virtual
# ODrive's board, main.cpp:300-305; 0: a bare Twin, whose C array starts at zero)
C_VBUS_R, C_UV_TRIP, C_OV_TRIP, C_VBUS_CHECKS = 40, 41, 42, 43
# the controller's and the motor's further settings, per axis (controller.hpp:23-56,
# motor.hpp:18-50): the configured control mode (the kernel's I_MODE says whether the axis
# is armed and how), the enable flags, ramps, circular setpoints, mirroring, tuning, the
# torque limit, the current-limit margin, the configured cpr (what the encoder's counts are
# divided by), the motor's largest measurable current (requested_current_range)
(C_CONTROL_MODE, C_EN_VEL_LIMIT, C_EN_TQ_VEL_LIMIT, C_EN_OVERSPEED, C_EN_GAIN_SCHED, C_GAIN_SCHED_WIDTH,
 C_VEL_RAMP_RATE, C_TORQUE_RAMP_RATE, C_CIRCULAR, C_CIRC_RANGE, C_INERTIA, C_MIRROR_AXIS, C_MIRROR_RATIO,
 C_TORQUE_MIRROR_RATIO, C_TUNE_FREQ, C_TUNE_POS_AMP, C_TUNE_VEL_AMP, C_TUNE_TQ_AMP, C_TORQUE_LIM,
 C_CURRENT_LIM_MARGIN, C_CPR, C_MAX_CURRENT) = range(44, 66)
# the firmware's generation, a board slot on axis 0: 1 for 0.5.6 (the controller updates
# every tick in every state and its failure is an axis error, main.cpp:438-446; the
# setpoint clamps of controller.cpp:285-290), 0 for 0.5.1 (the controller runs only in
# closed loop, fw-v0.5.1 axis.cpp:344-355)
C_FW_056 = 66
# the current controller's settings per axis: the configured phase resistance and
# inductance its gains come from (motor.cpp:297-302), its feed-forwards (motor.cpp:567-586),
# the motor's bus-current trip (motor.cpp:728-730)
(C_PHASE_R, C_PHASE_L, C_BEMF_FF, C_RWL_FF, C_IBUS_MIN, C_IBUS_MAX) = range(67, 73)
# the controller's spinout check (controller.cpp:422-441): the power filters' bandwidths
# [rad/s] and the thresholds [W]
(C_MECH_BW, C_ELEC_BW, C_SPIN_MECH, C_SPIN_ELEC) = range(73, 77)
N_CFG = 77
# float state per axis: AS[b, axis, k]
S_POS_EST, S_VEL_EST, S_INTEGRATOR, S_IQ, S_WD_TIMER, S_IQ_MEAS = range(6)
S_OSC = 6           # N_OSC slots of the oscillation monitor (see oscillation_update)
S_COUNT_F = S_OSC + N_OSC  # the encoder reading as a float (equal to the counts when quantized)
(S_POS_SP, S_VEL_SP, S_TQ_SP, S_TT_T, S_CAL_POS, S_IBUS_MOTOR, S_CAL_I) = range(S_COUNT_F + 1, S_COUNT_F + 8)
# system state in the slots of axis 0: the reported bus current and the brake current [A]
S_IBUS, S_BRAKE_I = S_COUNT_F + 8, S_COUNT_F + 9
# the controller's further state: the tuning sine's phase (autotuning_phase), the
# encoder's circular position (pos_circular) and the controller's torque output [N*m]
S_TUNE_PHASE, S_POS_CIRC, S_TQ_OUT = S_COUNT_F + 10, S_COUNT_F + 11, S_COUNT_F + 12
# the current loop: Iq's setpoint [A], the q voltage of the previous tick (still applied for
# half a period) and the PI's integrator (v_current_control_integral_q) [V]
S_IQ_SP, S_V_PREV, S_V_INT = S_COUNT_F + 13, S_COUNT_F + 14, S_COUNT_F + 15
# the spinout check's filtered mechanical and electrical power and the current controller's
# last power (foc.cpp:175-179: kept while disarmed) [W]
S_MECH_P, S_ELEC_P, S_FOC_POWER = S_COUNT_F + 16, S_COUNT_F + 17, S_COUNT_F + 18
N_AXSTATE = S_COUNT_F + 19
# int state per axis: AI[b, axis, k]; I_SYS_ERR is the board's error (odrv.error), on axis 0
I_MODE, I_AXIS_ERR, I_CTRL_ERR, I_MOTOR_ERR, I_COUNTS, I_TRAJ_DONE, I_SYS_ERR = range(7)
# 1 once the controller's estimate inputs are connected to the encoder (the first
# closed-loop entry of a boot, axis.cpp:270-285); before that they read 0 (component.hpp:
# an unconnected InputPort holds a default-constructed value)
I_CONNECTED = 7
# 1 when this tick's controller produced a torque (its torque_output_ is "present",
# component.hpp:72-79): what an axis mirroring it needs (controller.cpp:223-241)
I_TQ_PRESENT = 8
N_AXINT = 9
# firmware error codes (odrive.enums values)
AXIS_ERROR_MOTOR_FAILED = 0x40
AXIS_ERROR_CONTROLLER_FAILED = 0x200
AXIS_ERROR_WATCHDOG_TIMER_EXPIRED = 0x800
CONTROLLER_ERROR_OVERSPEED = 0x1
CONTROLLER_ERROR_INVALID_INPUT_MODE = 0x2
CONTROLLER_ERROR_INVALID_MIRROR_AXIS = 0x8
CONTROLLER_ERROR_INVALID_ESTIMATE = 0x20
CONTROLLER_ERROR_SPINOUT_DETECTED = 0x80
MOTOR_ERROR_UNKNOWN_TORQUE = 0x10000000             # 0.5.6: motor.update without a torque
MOTOR_ERROR_UNKNOWN_VOLTAGE_COMMAND = 0x100000000   # 0.5.6: the FOC without a voltage command
MOTOR_ERROR_I_BUS_OUT_OF_RANGE = 0x400000           # 0.5.2+: motor.cpp:728-730
MOTOR_ERROR_MODULATION_IS_NAN = 0x10000             # foc.cpp:31-32
# foc.cpp:144: the modulation's magnitude is held to 0.8 sqrt(3)/2, of 2/3 vbus in volts
V_MAX_PER_VBUS = 0.8 * (3.0 ** 0.5 / 2.0) * (2.0 / 3.0)
MOTOR_ERROR_CURRENT_LIMIT_VIOLATION = 0x1000
MOTOR_ERROR_DC_BUS_OVER_REGEN_CURRENT = 0x4000      # 0.5.1: the bus faults land on the motors
MOTOR_ERROR_DC_BUS_OVER_CURRENT = 0x8000
MOTOR_ERROR_SYSTEM_LEVEL = 0x1000000                # 0.5.2+: motors disarmed by a board fault
ODRIVE_ERROR_DC_BUS_UNDER_VOLTAGE = 0x2             # 0.5.2+: odrv.error (odrive-interface.yaml ODrive.Error)
ODRIVE_ERROR_DC_BUS_OVER_VOLTAGE = 0x4
ODRIVE_ERROR_DC_BUS_OVER_REGEN_CURRENT = 0x8
ODRIVE_ERROR_DC_BUS_OVER_CURRENT = 0x10
AXIS_ERROR_DC_BUS_UNDER_VOLTAGE = 0x2                # 0.5.1: the axes' own errors (fw-v0.5.1 axis.cpp:173-176)
AXIS_ERROR_DC_BUS_OVER_VOLTAGE = 0x4
CURRENT_LIM_MARGIN = 8.0  # A, firmware default motor.config.current_lim_margin
# motor.cpp:312-330 Motor::setup: the largest current the shunt amplifier measures at the
# gain requested_current_range asks for (its default 60 A gives gain 40, 0.9 * 1.35 V *
# 2000 S / 40 = 60.75 A); effective_current_lim is current_lim capped by it (motor.cpp:365-381)
MAX_UNITY_GAIN_CURRENT = 0.9 * 1.35 * 2000.0     # A at amplifier gain 1 (v3.x shunt 0.5 mOhm)
DRV_GAINS = (10.0, 20.0, 40.0, 80.0)               # the DRV8301's current-sense gains [V/V]
# the leg's state X[b, k]: joints, time, then the unmodeled effects' state (see _run)
X_Q1, X_DQ1, X_Q2, X_DQ2, X_T = range(5)
X_PHI1, X_DPHI1, X_PHI2, X_DPHI2 = range(5, 9)   # rotor angles on the joint side (compliant belt)
X_Z1, X_Z2 = 9, 10                               # LuGre bristle deflections [rad]
X_TRAVEL1, X_TRAVEL2 = 11, 12                    # accumulated joint travel [rad] (friction drift)
N_X = 13
# plant parameters FR[b, k] beyond the joints' friction (k < 14; see _run): the unmodeled
# effects, each off at zero. The cogging's and the encoder error's phases are kept as their
# cosines and sines (F_COG_C1, F_COG_S1, ...: the host computes them once; each harmonic is
# the sine of the angle plus its phase, by angle addition)
(F_BELT_K, F_BELT_C, F_BACKLASH_HALF, F_JM, F_BELT_SUB, F_COG_ON, F_COG_PERIODS, F_COG_A1, F_COG_A2,
 F_COG_A3, F_COG_C1, F_COG_S1, F_COG_C2, F_COG_S2, F_COG_C3, F_COG_S3, F_ENC_ON, F_ENC_A1, F_ENC_C1,
 F_ENC_S1, F_ENC_A2, F_ENC_C2, F_ENC_S2, F_FRIC_EXT, F_LUGRE_S0, F_LUGRE_S1, F_ASYM, F_DRIFT,
 F_DRIFT_TRAVEL) = range(14, 43)
N_FR = 43
# legs per vector of the plain mechanics (see _run_block): 8 doubles fill an AVX-512
# register, two AVX2 ones; a block of legs is one or two of these (a block that is not a
# multiple leaves legs to the slower scalar remainder of the loop; more legs than 16 leave
# the L1 cache)
VECTOR_LEGS = 8
# a compliant belt is sub-stepped so that its mode advances at most this many radians a step
BELT_PHASE_PER_STEP = 0.3


# ---------------------------------------------------------------------------------------
# a block's working copy of its legs' state, laid out by leg (structure of arrays): FB
# (float) and IB (int) hold rows of LANES entries, one per leg of the block, at rows fixed
# at compile time, so the compiler sees that the rows do not overlap and vectorizes the
# loops over the legs without run-time checks
# ---------------------------------------------------------------------------------------

LANES = 2 * VECTOR_LEGS   # the most legs in a block
# float rows: the joints and time, the motor torques, then (vectorized block only) per axis
# its state (V_) and configuration (K_), and the board's (G_)
R_Q = 0                   # q1, dq1, q2, dq2, t (the X_ order)
R_TAU = 5                 # joint 0, joint 1 [N*m] on the joint side
(V_PE, V_VE, V_INT, V_IQ, V_IQM, V_CNTF, V_PSP, V_VSP, V_TSP, V_IBM, V_TQOUT, V_IQSP, V_VPREV,
 V_VINT, V_MECHP, V_ELECP, V_FOCP) = range(17)
V_OSC = 17
N_VS = V_OSC + N_OSC      # the rows copied from the float state AS, in this order
# the controller's flags, estimates connected and torque output present (the int state
# I_CONNECTED, I_TQ_PRESENT), as floats: more int rows in the axes' loop would add run-time
# overlap checks between FB and IB, past what the compiler vectorizes
V_CONN, V_TQP = N_VS, N_VS + 1
N_V = N_VS + 2
(K_OFF, K_KP, K_KI, K_VL, K_VTOL, K_IPOS, K_IVEL, K_ITQ, K_KT, K_VG, K_CLIM, K_AE, K_PG, K_VIG,
 K_VIL, K_CCKP, K_INVKT, K_TLIM, K_MAXI, K_MARGIN, K_INVCPR, K_CCKI, K_VMAX, K_MECHBW, K_ELECBW,
 K_SPINM, K_SPINE, K_PHR) = range(28)
N_K = 28
# the configuration rows copied as they are: (K_ row, C_ slot)
K_FROM_C = ((K_OFF, C_COUNT_OFFSET), (K_VL, C_VEL_LIMIT), (K_VTOL, C_VEL_TOL), (K_IPOS, C_INPUT_POS),
            (K_IVEL, C_INPUT_VEL), (K_ITQ, C_INPUT_TORQUE), (K_KT, C_KT), (K_VG, C_VEL_GAIN),
            (K_CLIM, C_CURRENT_LIM), (K_AE, C_ABORT_ERROR), (K_PG, C_POS_GAIN), (K_VIG, C_VEL_INT_GAIN),
            (K_VIL, C_VEL_INT_LIMIT), (K_TLIM, C_TORQUE_LIM), (K_MAXI, C_MAX_CURRENT),
            (K_MARGIN, C_CURRENT_LIM_MARGIN), (K_MECHBW, C_MECH_BW), (K_ELECBW, C_ELEC_BW),
            (K_SPINM, C_SPIN_MECH), (K_SPINE, C_SPIN_ELEC), (K_PHR, C_PHASE_R))
(G_BRAKE_ON, G_BRAKE_R, G_MAX_REGEN, G_DCP, G_DCN, G_VBUS, G_STYLE, G_INV_VBUS, G_INV_BRAKE_R, G_IBUS,
 G_BRAKE_I, G_IBUS_AXES, G_FW056, G_TAU_AXIS0) = range(14)
N_G = 14
R_V0, R_V1 = 7, 7 + N_V                       # axis 0, axis 1
R_K0, R_K1 = 7 + 2 * N_V, 7 + 2 * N_V + N_K
R_G = 7 + 2 * N_V + 2 * N_K
# the encoder's reading error of axis 0 and axis 1 this tick [turn] (plant [encoder_error];
# 0 without one), computed before the axes' loops: a library call inside them would keep
# them from vectorizing
R_ENC_ERR = R_G + N_G
N_FROWS = R_ENC_ERR + 2
# int rows: per axis (W_), then per leg
W_MODE, W_AXERR, W_CTRLERR, W_MOTERR, W_COUNTS = range(5)
N_W = 5
R_W0, R_W1 = 0, N_W
R_DEAD = 2 * N_W          # 1: stopped for good (non-finite mechanics)
R_NF = R_DEAD + 1         # set by the mechanics: non-finite this tick
R_SYS = R_DEAD + 2        # the board's error
R_AB = R_DEAD + 3         # abort tick, abort reason
R_RNG = R_DEAD + 5        # the noise stream's state (its bits)
R_CODE = R_DEAD + 6       # the abort code the axes raised this tick
N_IROWS = R_CODE + 1
