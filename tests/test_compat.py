"""The flat layout's module paths keep working for one release, each with a warning that
names the new home (leglib._compat)."""

import importlib
import sys

import pytest

from leglib._compat import MOVED, LeglibDeprecationWarning


@pytest.fixture(autouse=True)
def _forget_old_modules():
    import leglib
    for old in MOVED:
        sys.modules.pop(f"leglib.{old}", None)
        leglib.__dict__.pop(old, None)
    yield


@pytest.mark.parametrize("old", sorted(MOVED))
def test_every_old_module_imports_with_a_warning_and_its_names_resolve(old):
    with pytest.warns(LeglibDeprecationWarning) as record:
        module = importlib.import_module(f"leglib.{old}")
        homes, renamed = MOVED[old]
        names = [n for n in dir(module) if not n.startswith("_")]
        assert names, old
        for name in names:
            value = getattr(module, name)
            new = renamed.get(name, name)
            assert any(getattr(importlib.import_module(h), new, None) is value for h in homes), (old, name)
    assert f"leglib.{old} is deprecated" in str(record[0].message)


def test_the_readmes_old_examples_still_run():
    with pytest.warns(LeglibDeprecationWarning) as record:
        import leglib as lg
        from leglib import odrive_io as io
        from leglib import statefeedback as SF
        from leglib.gainmap import GainMap
        from leglib.virtual_odrive import find_any
        assert io.connect is lg.connect and io.apply_configuration is lg.configure
        assert GainMap is lg.GainMap and callable(find_any)
    assert any("apply_configuration is now leglib.device.setup.configure" in str(w.message) for w in record)
    with pytest.warns(LeglibDeprecationWarning, match="statefeedback.design is now leglib.design.statefeedback.place_poles"):
        assert SF.design is lg.place_poles


def test_an_unknown_name_of_an_old_module_is_an_attribute_error():
    with pytest.warns(LeglibDeprecationWarning):
        from leglib import dataio
        with pytest.raises(AttributeError, match="has no attribute 'nonsense'"):
            dataio.nonsense
