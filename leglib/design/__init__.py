"""Choosing gains and controllers.

- :mod:`~leglib.design.points`: the one classifier of measured steps (``ok`` with its
  numbers, ``unstable``, ``failed`` with the reason);
- :mod:`~leglib.design.gainmap`: the gain map from a sweep and its inverse;
- :mod:`~leglib.design.plantfit`: the leg fitted to a few steps, and its inverse;
- :mod:`~leglib.design.tuning`: tuning on the leg with few experiments (:func:`tune`);
- :mod:`~leglib.design.statefeedback`: state feedback by pole placement;
- :mod:`~leglib.design.saved`: designs as files, with provenance.
"""
