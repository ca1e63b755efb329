"""The ODrive boundary: joint units (rad, rad/s, N*m) <-> motor units (turns, counts).

ODrive-native units exist only here and in the code that talks to a device. The wiring
comes from the leg file's ``[drive]`` section: which axis drives which joint, the belt
ratio, the encoder resolution, and the sign relating motor turns to joint angles. ``zero`` holds the motor positions [turn]
read at the rest pose (the operating point): the encoders are incremental and the firmware
re-references their counts during calibration (fw-v0.5.6 encoder.cpp:344), so joint angles
are defined by a zeroing step (:func:`leglib.device.setup.zero_joints`, Listing 7.4's "zero the
angles at the start"), not by the counts themselves. Before zeroing, ``zero`` is (0, 0): the
rest pose where the encoders powered up.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ..params import LegParams


@dataclass(frozen=True)
class AxisMap:
    """Conversions between joint and motor quantities for one leg.

    Attributes
    ----------
    gear_ratio : motor turns per joint turn (3 for the 16:48 belt)
    cpr : encoder counts per motor turn
    direction : +1/-1, sign of motor turns per joint angle
    axis_of_joint : (axis driving q1, axis driving q2)
    q_rest : (q1, q2) [rad] at the rest pose
    zero : (turns of the motor driving q1, of the motor driving q2) [turn] read at the rest
        pose; (0, 0) until a zeroing step sets it
    """

    gear_ratio: float
    cpr: int
    direction: int
    axis_of_joint: tuple[int, int]
    q_rest: tuple[float, float]
    zero: tuple[float, float] = (0.0, 0.0)

    @classmethod
    def from_leg(cls, leg: LegParams) -> "AxisMap":
        return cls(gear_ratio=leg.gear_ratio, cpr=leg.encoder_cpr, direction=leg.direction,
                   axis_of_joint=(leg.axis_of_q1, leg.axis_of_q2), q_rest=leg.q0)

    def joint_of_axis(self, axis: int) -> int:
        """Joint index (0 for q1, 1 for q2) that ``axis`` drives."""
        return self.axis_of_joint.index(axis)

    def motor_turns(self, q, joint: int):
        """Motor position [turn] for joint angle ``q`` [rad] of joint 0 (q1) or 1 (q2)."""
        return (self.direction * (np.asarray(q) - self.q_rest[joint]) * self.gear_ratio / (2 * math.pi)
                + self.zero[joint])

    def joint_angle(self, turns, joint: int):
        """Joint angle [rad] for motor position ``turns`` [turn]."""
        return self.q_rest[joint] + self.direction * (np.asarray(turns, dtype=float) - self.zero[joint]) \
            * 2 * math.pi / self.gear_ratio

    def zeroed(self, turns_at_rest) -> "AxisMap":
        """A copy whose rest pose is where the motors read ``turns_at_rest`` (joint 0's
        motor, joint 1's motor) [turn]."""
        z = tuple(float(x) for x in turns_at_rest)
        if len(z) != 2 or not all(math.isfinite(x) for x in z):
            raise ValueError(f"turns_at_rest must be two finite motor positions [turn], got {turns_at_rest!r}")
        return dataclasses.replace(self, zero=z)

    def counts_to_joint(self, counts, joint: int):
        """Joint angle [rad] for encoder ``counts``."""
        return self.joint_angle(np.asarray(counts, dtype=float) / self.cpr, joint)

    def joint_velocity(self, turns_per_s):
        """Joint velocity [rad/s] for motor velocity [turn/s]."""
        return self.direction * np.asarray(turns_per_s, dtype=float) * 2 * math.pi / self.gear_ratio

    def joint_torque(self, motor_torque):
        """Joint torque [N*m] for motor torque [N*m] (belt: times the ratio)."""
        return self.direction * self.gear_ratio * np.asarray(motor_torque, dtype=float)

    def motor_torque(self, joint_torque):
        """Motor torque [N*m] that gives ``joint_torque`` [N*m] at the joint."""
        return np.asarray(joint_torque, dtype=float) / (self.direction * self.gear_ratio)

    def motor_step_to_joint_step(self, step_turns: float) -> tuple[float, float]:
        """Joint angle changes (dq1, dq2) [rad] of Listing 7.4's step: the axis driving q1
        moves +step, the other -step [turn]."""
        return (self.direction * step_turns * 2 * math.pi / self.gear_ratio,
                -self.direction * step_turns * 2 * math.pi / self.gear_ratio)
