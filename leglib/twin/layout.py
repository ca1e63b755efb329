"""The twin's state layout: what each slot of the kernel's arrays holds.

The kernel (:mod:`leglib.twin.kernel`) works on flat float and int arrays per leg and axis;
these constants name their slots (``C_`` configuration, ``S_`` axis state, ``I_`` integer
state, ``X_`` the leg's mechanical state, ``F_`` plant parameters), the firmware's error
codes and modes, and the rows of a block's working copy (``R_``, ``V_``, ``K_``, ``G_``,
``W_``) used by the vectorized path. Plain Python constants: no numba here.
"""

from __future__ import annotations

from ..abort import N_OSC

TICK_HZ_DEFAULT = 8000.0

# axis modes inside the kernel (control_mode values of the firmware; 0 = not in closed loop;
# MODE_CALIB: armed by a calibration, the rotor locked to an electrical angle that the axis
# state machine of leglib.device.virtual.firmware moves)
MODE_IDLE, MODE_TORQUE, MODE_VELOCITY, MODE_POSITION, MODE_CALIB = 0, 1, 2, 3, 4
# controller.config.input_mode values (firmware enums)
INPUT_MODE_INACTIVE, INPUT_MODE_PASSTHROUGH, INPUT_MODE_POS_FILTER, INPUT_MODE_TRAP_TRAJ = 0, 1, 3, 5

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
N_CFG = 44
# float state per axis: AS[b, axis, k]
S_POS_EST, S_VEL_EST, S_INTEGRATOR, S_IQ, S_WD_TIMER, S_IQ_MEAS = range(6)
S_OSC = 6           # N_OSC slots of the oscillation monitor (see oscillation_update)
S_COUNT_F = S_OSC + N_OSC  # the encoder reading as a float (equal to the counts when quantized)
(S_POS_SP, S_VEL_SP, S_TQ_SP, S_TT_T, S_CAL_POS, S_IBUS_MOTOR, S_CAL_I) = range(S_COUNT_F + 1, S_COUNT_F + 8)
# system state in the slots of axis 0: the reported bus current and the brake current [A]
S_IBUS, S_BRAKE_I = S_COUNT_F + 8, S_COUNT_F + 9
N_AXSTATE = S_COUNT_F + 10
# int state per axis: AI[b, axis, k]; I_SYS_ERR is the board's error (odrv.error), on axis 0
I_MODE, I_AXIS_ERR, I_CTRL_ERR, I_MOTOR_ERR, I_COUNTS, I_TRAJ_DONE, I_SYS_ERR = range(7)
N_AXINT = 7
# firmware error codes (odrive.enums values)
AXIS_ERROR_MOTOR_FAILED = 0x40
AXIS_ERROR_CONTROLLER_FAILED = 0x200
AXIS_ERROR_WATCHDOG_TIMER_EXPIRED = 0x800
CONTROLLER_ERROR_OVERSPEED = 0x1
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
# the leg's state X[b, k]: joints, time, then the unmodeled effects' state (see _run)
X_Q1, X_DQ1, X_Q2, X_DQ2, X_T = range(5)
X_PHI1, X_DPHI1, X_PHI2, X_DPHI2 = range(5, 9)   # rotor angles on the joint side (compliant belt)
X_Z1, X_Z2 = 9, 10                               # LuGre bristle deflections [rad]
X_TRAVEL1, X_TRAVEL2 = 11, 12                    # accumulated joint travel [rad] (friction drift)
N_X = 13
# plant parameters FR[b, k] beyond the joints' friction (k < 14; see _run): the unmodeled
# effects, each off at zero
(F_BELT_K, F_BELT_C, F_BACKLASH_HALF, F_JM, F_BELT_SUB, F_COG_ON, F_COG_PERIODS, F_COG_A1, F_COG_A2,
 F_COG_A3, F_COG_P1, F_COG_P2, F_COG_P3, F_ENC_ON, F_ENC_A1, F_ENC_P1, F_ENC_A2, F_ENC_P2, F_FRIC_EXT,
 F_LUGRE_S0, F_LUGRE_S1, F_ASYM, F_DRIFT, F_DRIFT_TRAVEL) = range(14, 38)
N_FR = 38
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
(V_PE, V_VE, V_INT, V_IQ, V_IQM, V_CNTF, V_PSP, V_VSP, V_TSP, V_IBM) = range(10)
V_OSC = 10
N_V = V_OSC + N_OSC
(K_OFF, K_KP, K_KI, K_VL, K_VTOL, K_IPOS, K_IVEL, K_ITQ, K_KT, K_VG, K_CLIM, K_AE, K_PG, K_VIG,
 K_VIL, K_ALPHA, K_INVKT) = range(17)
N_K = 17
# the configuration rows copied as they are: (K_ row, C_ slot)
K_FROM_C = ((K_OFF, C_COUNT_OFFSET), (K_VL, C_VEL_LIMIT), (K_VTOL, C_VEL_TOL), (K_IPOS, C_INPUT_POS),
            (K_IVEL, C_INPUT_VEL), (K_ITQ, C_INPUT_TORQUE), (K_KT, C_KT), (K_VG, C_VEL_GAIN),
            (K_CLIM, C_CURRENT_LIM), (K_AE, C_ABORT_ERROR), (K_PG, C_POS_GAIN), (K_VIG, C_VEL_INT_GAIN),
            (K_VIL, C_VEL_INT_LIMIT))
(G_BRAKE_ON, G_BRAKE_R, G_MAX_REGEN, G_DCP, G_DCN, G_VBUS, G_STYLE, G_INV_VBUS, G_INV_BRAKE_R, G_IBUS,
 G_BRAKE_I, G_IBUS_AXES) = range(12)
N_G = 12
R_V0, R_V1 = 7, 7 + N_V                       # axis 0, axis 1
R_K0, R_K1 = 7 + 2 * N_V, 7 + 2 * N_V + N_K
R_G = 7 + 2 * N_V + 2 * N_K
N_FROWS = R_G + N_G
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
