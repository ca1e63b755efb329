"""leglib's errors: one family.

Every error leglib raises on purpose derives from :class:`LeglibError` and from the
builtin it has always been (``ValueError``, ``RuntimeError``, ``ConnectionError``), so
``except leglib.LeglibError`` catches them all and ``except ValueError`` keeps working.

===========================  ===================  ============================================
error                        also a               raised when
===========================  ===================  ============================================
:class:`ParameterError`      ``ValueError``       a parameter file or override is invalid
:class:`NotebookParameterError` ``ValueError``    a notebook parameter is of the wrong type or range
:class:`SpecError`           ``ValueError``       a batch spec is malformed
:class:`MeasurementError`    ``ValueError``       a measurement file is malformed
:class:`ProvenanceError`     ``ValueError``       a directory holds another leg's measurements
:class:`DesignFileError`     ``ValueError``       a design file is malformed
:class:`IdentificationError` ``ValueError``       a response cannot be identified
:class:`OutsideRegionError`  ``ValueError``       a target is outside a gain map's region
:class:`PoleError`           ``ValueError``       poles cannot be placed
:class:`ExperimentError`     ``RuntimeError``     an experiment cannot run or failed on the device
:class:`BenchLimitError`     ``RuntimeError``     a run on the leg would take longer than its limit
:class:`DeviceNotFoundError` ``RuntimeError``     no ODrive answered on USB
:class:`DeviceLostError`     ``ConnectionError``  the link to the ODrive was lost
===========================  ===================  ============================================
"""

from __future__ import annotations

__all__ = ["LeglibError", "ArgumentError", "ParameterError", "NotebookParameterError", "SpecError", "MeasurementError",
           "ProvenanceError", "DesignFileError", "IdentificationError", "OutsideRegionError", "PoleError",
           "ExperimentError", "BenchLimitError", "DeviceNotFoundError", "DeviceLostError"]


class LeglibError(Exception):
    """Base of every error leglib raises on purpose."""


class ArgumentError(LeglibError, ValueError):
    """A function was called with an argument it cannot use (the message names it)."""


class ParameterError(LeglibError, ValueError):
    """A parameter file is missing, malformed, or holds an invalid value."""


class NotebookParameterError(LeglibError, ValueError):
    """A notebook parameter has the wrong type or is out of range."""


class SpecError(LeglibError, ValueError):
    """A batch spec is malformed."""


class MeasurementError(LeglibError, ValueError):
    """A measurement file is malformed; the message names the file (and line, field)."""


class ProvenanceError(LeglibError, ValueError):
    """A directory holds measurements of another leg or experiment."""


class DesignFileError(LeglibError, ValueError):
    """A design file is missing a field or holds a value of the wrong form."""


class IdentificationError(LeglibError, ValueError):
    """The data cannot be identified (flat, NaN, too short, not a step)."""


class OutsideRegionError(LeglibError, ValueError):
    """A requested (zeta, fn) is outside the achievable region of a gain map.

    Attributes
    ----------
    target : (zeta, fn [Hz]) that was asked for
    nearest : :class:`leglib.design.gainmap.Choice`, the nearest achievable point (its
        gains, zeta, fn)
    tolerance : the relative distance in zeta and fn that counts as achievable
    """

    def __init__(self, target, nearest, tolerance):
        self.target = tuple(float(x) for x in target)
        self.nearest = nearest
        self.tolerance = tolerance
        g = ", ".join(f"{x:.4g}" for x in nearest.gains)
        super().__init__(
            f"target (zeta {target[0]:.3g}, fn {target[1]:.3g} Hz) is outside the achievable region "
            f"(no achievable point within {tolerance:.0%} in zeta and fn); the nearest achievable point is "
            f"(zeta {nearest.zeta:.3g}, fn {nearest.fn:.3g} Hz) with gains (pos_gain, vel_gain, "
            f"vel_integrator_gain) = ({g})")


class PoleError(LeglibError, ValueError):
    """The requested poles cannot be placed."""


class ExperimentError(LeglibError, RuntimeError):
    """An experiment could not run (calibration failed, axis error, ...)."""


class BenchLimitError(LeglibError, RuntimeError):
    """A run on the real leg would take longer than the limit it was given; the message gives
    the estimate and names the limit's parameter (:mod:`leglib.device.bench`)."""


class DeviceNotFoundError(LeglibError, RuntimeError):
    """No ODrive answered on USB."""


class DeviceLostError(LeglibError, ConnectionError):
    """The connection to the ODrive was lost."""
