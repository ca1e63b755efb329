"""leglib: a research workbench for a five-bar robotic leg driven by an ODrive v3.6.

``import leglib as lg`` gives the workbench's public face, one name per concept, loaded on
first use (``import leglib`` itself costs nothing):

======================  ======================================================================
parameters              :func:`load_leg`, :func:`load_plant`, :func:`load_motor`,
                        :func:`load_odrive_config`
the model               :func:`linearize`, :func:`simulate`, :func:`foot_position`
an ODrive               :func:`connect` (``"virtual"`` or ``"usb"``), :func:`configure`,
                        :func:`calibrate`, :func:`apply_gains`
experiments             :func:`step_response`, :func:`sweep`, :func:`thesis_grid`,
                        :func:`torque_loop`, :func:`play_torque_table`,
                        :func:`friction_experiment`
measurements            :func:`read_measurements`
identification          :func:`second_order`, :func:`fit_friction`, :func:`fit_leg_friction`
design                  :class:`GainMap` (the map from a sweep), :func:`tune` (gains on the leg
                        with few experiments), :func:`place_poles`, :func:`simulate_closed_loop`,
                        :func:`validate`, :func:`save_design`, :func:`load_design`
the twin                :class:`Twin`
errors                  :class:`LeglibError` (every leglib error derives from it)
======================  ======================================================================

The layers below it, one direction only (``tests/test_layers.py``): :mod:`leglib.params`, :mod:`leglib.checks`,
:mod:`leglib.errors` -> :mod:`leglib.model` -> :mod:`leglib.plots` -> :mod:`leglib.twin` ->
:mod:`leglib.device` -> :mod:`leglib.files` -> :mod:`leglib.experiments` ->
:mod:`leglib.identify` -> :mod:`leglib.design` -> :mod:`leglib.thesis`,
:mod:`leglib.evaluation` -> :mod:`leglib.notebook`.
"""

from __future__ import annotations

import importlib

from . import _compat
from ._version import __version__

# public name -> (module, attribute)
_API = {
    "load_leg": ("leglib.params", "load_leg"),
    "load_plant": ("leglib.params", "load_plant"),
    "load_motor": ("leglib.params", "load_motor"),
    "load_odrive_config": ("leglib.params", "load_odrive_config"),
    "linearize": ("leglib.model.linear", "linearize"),
    "simulate": ("leglib.model.dynamics", "simulate"),
    "foot_position": ("leglib.model.kinematics", "foot_position"),
    "connect": ("leglib.device.session", "connect"),
    "configure": ("leglib.device.setup", "configure"),
    "calibrate": ("leglib.device.setup", "calibrate"),
    "apply_gains": ("leglib.device.setup", "apply_gains"),
    "step_response": ("leglib.experiments.step", "step_response"),
    "sweep": ("leglib.experiments.sweep", "sweep"),
    "thesis_grid": ("leglib.experiments.sweep", "thesis_grid"),
    "torque_loop": ("leglib.experiments.torque", "torque_loop"),
    "play_torque_table": ("leglib.experiments.torque", "play_torque_table"),
    "friction_experiment": ("leglib.experiments.torque", "friction_experiment"),
    "read_measurements": ("leglib.files.sweepdir", "read_measurements"),
    "second_order": ("leglib.identify.step", "second_order"),
    "fit_friction": ("leglib.identify.friction", "fit_friction"),
    "fit_leg_friction": ("leglib.identify.friction", "fit_leg_friction"),
    "GainMap": ("leglib.design.gainmap", "GainMap"),
    "tune": ("leglib.design.tuning", "tune"),
    "place_poles": ("leglib.design.statefeedback", "place_poles"),
    "simulate_closed_loop": ("leglib.design.statefeedback", "simulate_closed_loop"),
    "validate": ("leglib.design.validation", "validate"),
    "save_design": ("leglib.design.saved", "save"),
    "load_design": ("leglib.design.saved", "load"),
    "Twin": ("leglib.twin.host", "Twin"),
    "LeglibError": ("leglib.errors", "LeglibError"),
}

__all__ = ["__version__", *_API]

_compat.install()


def __getattr__(name: str):
    target = _API.get(name)
    if target is not None:
        value = getattr(importlib.import_module(target[0]), target[1])
        globals()[name] = value
        return value
    if name in _compat.MOVED:
        return importlib.import_module(f"leglib.{name}")
    raise AttributeError(f"module 'leglib' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_API))
