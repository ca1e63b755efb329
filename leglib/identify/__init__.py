"""Identification from measurements: second-order dynamics of step responses (thesis 6.4)
and friction (thesis 5.2).

:mod:`~leglib.identify.step` (the true measure, least squares over the compiled kernel of
:mod:`~leglib.identify.fastfit`), :mod:`~leglib.identify.listing77` (the thesis's own
measure, exactly), :mod:`~leglib.identify.friction`.
"""

from __future__ import annotations

from ..errors import IdentificationError
from .friction import (
                       FRICTION_MODELS,
                       MIN_DIRECTION_SAMPLES,
                       FrictionFit,
                       LegFrictionFit,
                       RunSimulator,
                       choose_friction_model,
                       compare_friction_models,
                       derivative,
                       effective_samples,
                       fit_friction,
                       fit_leg_friction,
                       friction_table,
                       load_identified,
                       simulate_run,
)
from .listing77 import ThesisReading, matlab_findpeaks, matlab_smooth
from .step import METHODS, MIN_R2, SecondOrderFit, second_order, standard_errors

__all__ = ["IdentificationError", "MIN_R2", "SecondOrderFit", "METHODS", "second_order", "standard_errors",
           "ThesisReading", "matlab_smooth", "matlab_findpeaks", "effective_samples", "derivative",
           "FrictionFit", "MIN_DIRECTION_SAMPLES", "fit_friction", "FRICTION_MODELS",
           "LegFrictionFit", "compare_friction_models", "RunSimulator", "simulate_run",
           "fit_leg_friction", "friction_table", "choose_friction_model", "load_identified"]
