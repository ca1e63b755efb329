"""The module paths of leglib 0.1's flat layout, kept for one release as thin re-exports.

``import leglib.odrive_io`` (and ``from leglib import gainmap``, ...) still works: the old
module is made on first import from the new modules that hold its names, and warns once
(:class:`LeglibDeprecationWarning`, a ``FutureWarning``, so it shows in notebooks and
scripts alike) with the new place of each name as it is used. Renamed names map to their new
names. One table, :data:`MOVED`; delete this module and its one line in ``leglib/__init__``
to drop them.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import types
import warnings

# old module -> (the modules that hold its names now, {old name: new name})
MOVED: dict[str, tuple[tuple[str, ...], dict[str, str]]] = {
    "odrive_io": (("leglib.device.session", "leglib.device.setup", "leglib.experiments.step",
                   "leglib.experiments.sweep", "leglib.experiments.torque", "leglib.errors"),
                  {"apply_configuration": "configure"}),
    "virtual_odrive": (("leglib.device.virtual", "leglib.device.virtual.firmware", "leglib.errors"), {}),
    "fibre_device": (("leglib.device.virtual.wire",), {}),
    "dataio": (("leglib.files.measurements", "leglib.files.sweepdir", "leglib.files.atomic", "leglib._version",
                "leglib.errors"), {}),
    "gainmap": (("leglib.design.points", "leglib.design.gainmap", "leglib.design.plantfit", "leglib.design.tuning",
                 "leglib.errors"), {"design": "tune", "Design": "Tuning"}),
    "autotune": (("leglib.design.tuning", "leglib.errors"), {"design": "tune", "Design": "Tuning"}),
    "statefeedback": (("leglib.design.statefeedback", "leglib.errors"),
                      {"design": "place_poles", "Design": "StateFeedback"}),
    "designs": (("leglib.design.saved", "leglib.errors"), {}),
    "fastfit": (("leglib.identify.fastfit",), {}),
    "derivation": (("leglib.model.derivation",), {}),
    "cascade": (("leglib.model.cascade",), {}),
    "drive": (("leglib.model.drive",), {}),
    "robustness": (("leglib.evaluation.robustness",), {}),
    "notebooks": (("leglib.notebook.run",), {}),
    "nbtools": (("leglib.notebook.setup", "leglib.files.atomic", "leglib.errors"), {}),
    "widgets": (("leglib.notebook.widgets",), {}),
    "liveview": (("leglib.notebook.liveview",), {}),
    "batch": (("leglib.notebook.batch", "leglib.errors"), {}),
}


class LeglibDeprecationWarning(FutureWarning):
    """An old leglib module path or name was used; the message names the new one."""


class _Moved(types.ModuleType):
    """An old module: its names looked up in the new modules, each use pointed to its new home."""

    def __init__(self, name: str, homes: tuple[str, ...], renamed: dict[str, str]):
        super().__init__(name, f"Deprecated: {name} moved; its names live in {', '.join(homes)}.")
        self.__homes, self.__renamed, self.__told = homes, renamed, set()

    def __getattr__(self, attr: str):
        if attr.startswith("__"):
            raise AttributeError(attr)
        new = self.__renamed.get(attr, attr)
        for home in self.__homes:
            module = importlib.import_module(home)
            if hasattr(module, new):
                if new != attr and attr not in self.__told:
                    self.__told.add(attr)
                    warnings.warn(f"{self.__name__}.{attr} is now {home}.{new}; the old path goes in the "
                                  f"next release", LeglibDeprecationWarning, stacklevel=2)
                return getattr(module, new)
        raise AttributeError(f"module {self.__name__!r} (moved to {', '.join(self.__homes)}) has no attribute "
                             f"{attr!r}")

    def __dir__(self):
        names = set()
        for home in self.__homes:
            names.update(n for n in dir(importlib.import_module(home)) if not n.startswith("_"))
        return sorted(names | set(self.__renamed))


class _Finder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    def find_spec(self, fullname, path=None, target=None):
        prefix, _, leaf = fullname.rpartition(".")
        if prefix == "leglib" and leaf in MOVED:
            return importlib.util.spec_from_loader(fullname, self)
        return None

    def create_module(self, spec):
        homes, renamed = MOVED[spec.name.rpartition(".")[2]]
        warnings.warn(f"{spec.name} is deprecated: its names moved to {', '.join(homes)} (use "
                      f"'import leglib as lg' for the public API); the old path goes in the next release",
                      LeglibDeprecationWarning, stacklevel=_caller_level())
        return _Moved(spec.name, homes, renamed)

    def exec_module(self, module):
        pass


def _caller_level() -> int:
    """The stack level of the code that imported the old module (past importlib's frames)."""
    frame, level = sys._getframe(1), 1
    while frame is not None and (frame.f_code.co_filename.startswith("<frozen importlib")
                                 or frame.f_code.co_filename == __file__):
        frame, level = frame.f_back, level + 1
    return level


def install() -> None:
    if not any(isinstance(f, _Finder) for f in sys.meta_path):
        sys.meta_path.append(_Finder())
