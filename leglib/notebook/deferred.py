"""jsonschema's IRI format checks, loaded on their first use instead of at import.

Every process that runs a notebook imports papermill, so nbformat, so jsonschema, whose format
checkers import ``rfc3987_syntax`` when it is installed (it is: jupyter-events asks for
``jsonschema[format-nongpl]``). That module builds its Earley parsers (lark) as it is
imported: 1.2 s of the 1.4 s that ``import nbformat`` takes on a 2-core machine, and more in
a process that holds much already (the test suite's collection: 12 to 14 CPU seconds with
it, 7 without), in every process that runs notebooks (``make run``'s, a batch's Dask
workers, the test workers), for the formats "iri" and "iri-reference", which no notebook
schema uses (python-jsonschema/jsonschema#1428).

:func:`install` (run when :mod:`leglib.notebook` is imported) puts a finder first on
``sys.meta_path`` that answers ``import rfc3987_syntax`` with a stand-in whose
``is_valid_syntax`` -- the one name jsonschema imports from it -- imports the real module
on its first call and hands every call on; any other name imports the real module at once.
Where rfc3987_syntax is not installed, or was imported before, nothing changes.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys
import threading
import types

NAME = "rfc3987_syntax"
_LOCK = threading.RLock()


def real_module() -> types.ModuleType:
    """rfc3987_syntax itself, imported now if it was not (it then replaces the stand-in in
    ``sys.modules``)."""
    with _LOCK:
        module = sys.modules.get(NAME)
        if module is not None and not getattr(module, "_leglib_stand_in", False):
            return module
        _FINDER.active = False
        stand_in = sys.modules.pop(NAME, None)
        try:
            return importlib.import_module(NAME)
        except BaseException:
            if stand_in is not None:
                sys.modules[NAME] = stand_in
            raise


def is_valid_syntax(term: str, value: str) -> bool:
    """rfc3987_syntax.is_valid_syntax, the real module imported on the first call."""
    return real_module().is_valid_syntax(term, value)


def _any_other_name(name: str):
    if name.startswith("__"):   # the import system's questions (``from ... import`` asks for __path__)
        raise AttributeError(name)
    return getattr(real_module(), name)


class _Finder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    active = True

    def find_spec(self, name, path=None, target=None):
        real = importlib.machinery.PathFinder.find_spec(name) if name == NAME and self.active else None
        if real is None:
            return None
        spec = importlib.util.spec_from_loader(name, self, is_package=True)
        spec.submodule_search_locations = list(real.submodule_search_locations or [])   # its submodules as they are
        return spec

    def create_module(self, spec):
        return None   # the default module

    def exec_module(self, module):
        module._leglib_stand_in = True
        module.is_valid_syntax = is_valid_syntax
        module.__getattr__ = _any_other_name


_FINDER = _Finder()


def install() -> None:
    """Answer the next ``import rfc3987_syntax`` with the stand-in (once; nothing when it
    was imported already)."""
    with _LOCK:
        if NAME not in sys.modules and _FINDER not in sys.meta_path and _FINDER.active:
            sys.meta_path.insert(0, _FINDER)
