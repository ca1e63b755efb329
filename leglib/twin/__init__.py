"""The twin: the virtual leg and its ODrive's control loop, compiled, at 8 kHz.

:class:`Twin` advances a batch of legs; its kernel is split into the state layout
(:mod:`~leglib.twin.layout`), the noise (:mod:`~leglib.twin.rng`), the plant's unmodeled
effects (:mod:`~leglib.twin.effects`), the mechanics (:mod:`~leglib.twin.mechanics`), the
reference tick (:mod:`~leglib.twin.kernel`) and the vectorized path
(:mod:`~leglib.twin.vector`). The ODrive's object tree on top of it is
:mod:`leglib.device.virtual`.
"""

from __future__ import annotations

from .host import Twin, TwinState, effect_parameters, reflected_rotor_inertia, true_leg
from .layout import TICK_HZ_DEFAULT
from .rng import seeds_for

__all__ = ["Twin", "TwinState", "true_leg", "reflected_rotor_inertia", "effect_parameters",
           "seeds_for", "TICK_HZ_DEFAULT"]
