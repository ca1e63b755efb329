"""leglib: a research workbench for a five-bar robotic leg driven by an ODrive.

Modules: :mod:`params` (TOML -> dataclasses), :mod:`derivation` (sympy), :mod:`model`
(kinematics, dynamics, linearization), :mod:`plots`, :mod:`nbtools`, :mod:`notebooks`.
"""

__version__ = "0.1.0"
