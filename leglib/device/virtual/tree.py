"""The virtual ODrive's object tree: nodes and properties with the firmware's endpoint names.

A tree belongs to one boot of the device: after a reboot every access raises
:class:`leglib.errors.DeviceLostError`, as the USB object of a real ODrive does. Every
property read or write is one USB transaction on the device's clock.
"""

from __future__ import annotations

import math

import numpy as np

from ...errors import DeviceLostError


class _Prop:
    """One property of the tree: getter, optional setter, value type."""

    def __init__(self, get, set=None, kind=float):
        self.get, self.set, self.kind = get, set, kind


class _Node:
    """A node of the object tree with a fixed set of properties, children and methods.

    A tree belongs to one boot of the device: after a reboot every access raises
    :class:`DeviceLostError`, as the USB object of a real ODrive does.
    """

    def __init__(self, dev, path, props=None, children=None, methods=None):
        object.__setattr__(self, "_dev", dev)
        object.__setattr__(self, "_path", path)
        object.__setattr__(self, "_props", props or {})
        object.__setattr__(self, "_children", children or {})
        object.__setattr__(self, "_methods", methods or {})
        object.__setattr__(self, "_boot", dev.boot_count)

    def _alive(self):
        if self._boot != self._dev.boot_count:
            raise DeviceLostError(f"'{self._path}': the ODrive rebooted (boot {self._dev.boot_count}); "
                                  f"this handle is from boot {self._boot}: reconnect")

    def __getattr__(self, name):
        if name in self._children:
            self._alive()
            return self._children[name]
        if name in self._props:
            self._alive()
            self._dev._transaction()
            return self._props[name].get()
        if name in self._methods:
            fn = self._methods[name]

            def call(*args, **kwargs):
                self._alive()
                self._dev._transaction()
                return fn(*args, **kwargs)
            return call
        raise AttributeError(f"'{self._path}' has no attribute '{name}'")

    def __setattr__(self, name, value):
        prop = self._props.get(name)
        if prop is None:
            if name in self._children or name in self._methods:
                raise AttributeError(f"'{self._path}.{name}' cannot be assigned")
            raise AttributeError(f"'{self._path}' has no attribute '{name}'")
        if prop.set is None:
            raise AttributeError(f"'{self._path}.{name}' is read-only")
        if prop.kind is bool:
            if not isinstance(value, (bool, int, np.integer)):
                raise TypeError(f"'{self._path}.{name}' expects a bool, got {value!r}")
            value = bool(value)
        elif prop.kind is int:
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise TypeError(f"'{self._path}.{name}' expects an integer, got {value!r}")
            value = int(value)
        else:
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
                raise TypeError(f"'{self._path}.{name}' expects a number, got {value!r}")
            value = float(value)
            if math.isnan(value):
                raise ValueError(f"'{self._path}.{name}' must be a number, got {value!r}")
        self._alive()
        self._dev._transaction()
        prop.set(value)

    def __dir__(self):
        return sorted(set(self._props) | set(self._children) | set(self._methods))

    def __repr__(self):
        return f"<virtual ODrive node {self._path}>"
