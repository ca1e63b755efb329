"""The leg's model (thesis chapter 5): kinematics, dynamics, linearization.

The physics lives in small modules: :mod:`~leglib.model.kinematics` (the exact coaxial
five-bar's geometry), :mod:`~leglib.model.dynamics` (mass matrix, gravity, friction,
simulation), :mod:`~leglib.model.linear` (eq. 5.11), :mod:`~leglib.model.derivation` (the
sympy derivation that writes :mod:`~leglib.model._generated`, whose compiled terms are in
:mod:`~leglib.model.terms`), :mod:`~leglib.model.drive` (joint angles <-> motor turns and
encoder counts through the belt) and :mod:`~leglib.model.cascade` (the ODrive's cascade as
linear systems). The functions of the first three are importable from here.
"""

from __future__ import annotations

from .dynamics import (
                         bias_torque,
                         energy,
                         equilibrium_torque,
                         forward_dynamics,
                         friction_vector,
                         gravity_torque,
                         held_torque_stepper,
                         mass_matrix,
                         simulate,
                         simulate_torque_table,
)
from .kinematics import (
                         LISTING_LENGTH,
                         foot_position,
                         inverse_kinematics,
                         leg_length,
                         lower_link_angles,
                         thesis_foot_height,
                         thesis_listing_height,
                         workspace_grid,
                         zeroed_degrees,
)
from .linear import THESIS_A, THESIS_A_PRINTED, THESIS_B, compare_models, linearize
from .terms import COULOMB_VELOCITY, MODELS, STATE_NAMES, param_vector

__all__ = ["MODELS", "STATE_NAMES", "COULOMB_VELOCITY", "param_vector", "lower_link_angles",
           "foot_position", "inverse_kinematics", "thesis_foot_height", "LISTING_LENGTH",
           "thesis_listing_height", "zeroed_degrees", "leg_length", "workspace_grid",
           "friction_vector", "simulate_torque_table", "held_torque_stepper", "mass_matrix", "gravity_torque",
           "bias_torque", "energy", "forward_dynamics", "equilibrium_torque", "simulate",
           "linearize", "THESIS_A_PRINTED", "THESIS_B", "THESIS_A", "compare_models"]
