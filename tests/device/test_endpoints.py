"""The virtual ODrive's object tree is a table, one row per endpoint
(leglib/device/virtual/firmware.py ENDPOINTS, row kinds in leglib/device/virtual/tree.py).

Every row is checked against the firmware's own endpoint table of each version it is
marked for (tables/endpoints_fw-v0.5.x.json, from the firmware's odrive-interface.yaml of
tags fw-v0.5.1 and fw-v0.5.6): a typo in a path, a wrong type, a write the firmware does not
take or a version the endpoint does not have fails here. A row added to the table appears
in the tree and on the wire with nothing else written.
"""

import inspect

import pytest

from leglib.device.virtual import catalog, device_of, find_any, forget
from leglib.device.virtual import firmware as V
from leglib.device.virtual import tree as T
from leglib.device.virtual import wire as F
from leglib.twin import layout as L

INT_CODECS = {"int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64", "endpoint_ref"}
CODECS = {float: {"float"}, bool: {"bool"}, int: INT_CODECS}
TABLES = sorted(F.FIRMWARE_TABLES)


def _fits(method: str, n: int) -> bool:
    """Whether VirtualODrive.<method> takes ``n`` positional arguments after self."""
    try:
        inspect.signature(getattr(V.VirtualODrive, method)).bind(None, *range(n))
    except (AttributeError, TypeError):
        return False
    return True


def all_rows(firmware: str) -> tuple:
    """The device's rows on ``firmware``: its own and the catalog's."""
    return tuple(V.ENDPOINTS) + catalog.fill(V.ENDPOINTS, firmware)


def row_problems(rows, version: str) -> list[str]:
    """What is wrong with ``rows`` against the firmware table of ``version``."""
    flat = F.flatten(F.endpoint_table(version))
    problems = []
    for path, (a, row) in T.model_paths(rows, version).items():
        entry = flat.get(path)
        if entry is None:
            problems.append(f"{path}: not an endpoint of firmware {version} ({row!r})")
            continue
        n_axis = 0 if a is None else 1
        if row.function:
            if entry["type"] != "function":
                problems.append(f"{path}: a {entry['type']} property on {version}, the row is a function")
            elif not _fits(row.store.method, n_axis + len(row.store.bound) + len(entry["inputs"])):
                problems.append(f"{path}: {row.store.method} does not take the table's "
                                f"{len(entry['inputs'])} argument(s)")
            continue
        if entry["type"] == "function":
            problems.append(f"{path}: a function on {version}, the row is a property")
            continue
        if entry["type"] not in CODECS[row.kind]:
            problems.append(f"{path}: {entry['type']} on {version}, the row is {row.kind.__name__}")
        if row.writable and "w" not in entry["access"]:
            problems.append(f"{path}: read-only on {version}, the row takes writes")
        if row.setter is not None and not _fits(row.setter, n_axis + 1):
            problems.append(f"{path}: setter {row.setter} does not take (axis, value)")
        if isinstance(row.store, T.Get) and not _fits(row.store.method, n_axis + len(row.store.args)):
            problems.append(f"{path}: getter {row.store.method} does not take the axis")
    return problems


@pytest.mark.parametrize("version", TABLES)
def test_every_row_is_an_endpoint_of_the_firmwares_table(version):
    """Each row marked for ``version`` -- the model's own and the catalog's -- names an
    endpoint of that version's table, with a compatible type (float / bool / an integer
    codec / a function taking the table's arguments), writable only where the firmware's
    is, and names device methods that exist with the right arguments."""
    assert row_problems(V.ENDPOINTS, version) == []
    assert row_problems(all_rows(version), version) == []


@pytest.mark.parametrize("version", TABLES)
def test_every_endpoint_of_the_table_has_a_row(version):
    """The whole tree: every endpoint of the firmware's table (but its version numbers,
    answered from the table) has a row, and every catalog row comes from a rule (none
    falls to the strict default)."""
    flat = F.flatten(F.endpoint_table(version))
    paths = T.model_paths(all_rows(version), version)
    identity = {"fw_version_major", "fw_version_minor", "fw_version_revision", "fw_version_unreleased"}
    assert set(paths) <= set(flat) and set(flat) - set(paths) <= identity
    kinds = catalog.disposition(version)
    assert "strict" not in kinds, kinds.get("strict")
    assert F.endpoint_coverage(firmware=version)["unmodeled"] == []


def test_every_row_is_checked_against_a_table():
    """A row marked only for releases without a shipped table could not be checked: an
    error. So is a release that does not exist."""
    unchecked = [r.path for r in V.ENDPOINTS if not any(r.active(v) for v in TABLES)]
    assert unchecked == []
    with pytest.raises(ValueError, match="not a release"):
        T.Endpoint("axis*.controller.config.pos_gain", T.C(L.C_POS_GAIN), since="0.5.16")
    with pytest.raises(ValueError, match="before since"):
        T.Endpoint("axis*.controller.config.pos_gain", T.C(L.C_POS_GAIN), since="0.5.6", until="0.5.1")


def test_the_check_finds_wrong_rows():
    """The check above bites: a typo in a path, a type the firmware does not have, a
    writable row on a read-only endpoint, a row for a version without the endpoint, a
    setter that does not exist."""
    bad = (
        T.Endpoint("axis*.controller.config.pos_gian", T.C(L.C_POS_GAIN)),
        T.Endpoint("axis*.encoder.config.cpr", T.Key("cpr"), bool),
        T.Endpoint("axis*.encoder.pos_estimate", T.S(L.S_POS_EST, writable=True)),
        T.Endpoint("axis*.motor.is_armed", T.Get("_is_armed"), bool),              # 0.5.2+
        T.Endpoint("axis*.controller.input_vel", T.C(L.C_INPUT_VEL), setter="_set_input_vel"),
        T.Endpoint("save_configuration", T.C(L.C_POS_GAIN)),
    )
    found = row_problems(bad, "0.5.1")
    for text in ("axis0.controller.config.pos_gian: not an endpoint", "axis1.encoder.config.cpr: int32",
                 "axis0.encoder.pos_estimate: read-only", "axis0.motor.is_armed: not an endpoint of firmware 0.5.1",
                 "setter _set_input_vel", "save_configuration: a function"):
        assert any(p.startswith(text) or text in p for p in found), (text, found)


def test_malformed_rows_are_refused():
    with pytest.raises(ValueError, match="axis\\*"):
        T.Endpoint("axis0.controller.config.pos_gain", T.C(L.C_POS_GAIN))
    with pytest.raises(ValueError, match="axis\\*"):
        T.Endpoint("config.axis*.pos_gain", T.C(L.C_POS_GAIN))
    with pytest.raises(ValueError, match="per axis"):
        T.Endpoint("config.cpr", T.Key("cpr"), int)
    with pytest.raises(ValueError, match="read-only"):
        T.Endpoint("axis*.encoder.pos_estimate", T.S(L.S_POS_EST), check=T.positive)
    with pytest.raises(TypeError, match="kind"):
        T.Endpoint("axis*.encoder.pos_estimate", T.S(L.S_POS_EST), str)
    twice = V.ENDPOINTS + (T.Endpoint("axis*.controller.config.pos_gain", T.C(L.C_VEL_GAIN)),)
    with pytest.raises(ValueError, match="two rows for axis0.controller.config.pos_gain"):
        T.model_paths(twice, "0.5.6")
    inside = (T.Endpoint("axis*.motor", T.Const(1), int), T.Endpoint("axis*.motor.error", T.Err(L.I_MOTOR_ERR), int))
    with pytest.raises(ValueError, match="endpoint of its own"):
        T.model_paths(inside, "0.5.6")


@pytest.mark.parametrize("firmware", V.FIRMWARES)
def test_the_tree_is_the_table(firmware):
    """The device's tree holds exactly the rows of its firmware, each where its path says,
    a property or a method as the row says; the firmware versions differ where the rows do
    (fw-v0.5.1: clear_errors per axis, no odrv.error, no enable_brake_resistor)."""
    dev = V.VirtualODrive(firmware=firmware)
    paths = T.model_paths(all_rows(firmware), firmware)
    assert set(dev._leaves) == set(paths)
    for path, (_, row) in paths.items():
        node = dev._tree
        *parents, name = path.split(".")
        for p in parents:
            node = getattr(node, p)
        assert dev._leaves[path].node is node and name in dir(node)
        assert (name in node._methods) == row.function and (name in node._props) != row.function
        if not row.function:
            assert (node._props[name].set is not None) == row.writable
    new = firmware != "0.5.1"
    assert ("clear_errors" in dir(dev)) == new and ("clear_errors" in dir(dev.axis0)) != new
    assert ("error" in dir(dev)) == new and ("enable_brake_resistor" in dir(dev.config)) == new


EXTRA = (
    # a reading of the kernel the table does not expose yet: the motor's bus current, renamed
    # in 0.5.2 (fw-v0.5.1 odrive-interface.yaml: motor.current_control.Ibus; 0.5.2: motor.I_bus)
    T.Endpoint("axis*.motor.current_control.Ibus", T.S(L.S_IBUS_MOTOR), until="0.5.1"),
    T.Endpoint("axis*.motor.I_bus", T.S(L.S_IBUS_MOTOR), since="0.5.2"),
    # a writable setting with a check (any kernel slot the tree does not show will do)
    T.Endpoint("axis*.motor.config.acim_autoflux_attack_gain", T.C(L.C_INT_RESET_TORQUE), check=T.positive),
)


def test_a_new_row_appears_in_the_tree_and_on_the_wire(monkeypatch):
    """Adding rows is all it takes: a model row replaces the catalog's for its endpoint
    (read, written, checked, one transaction each, in the tree and on the wire)."""
    assert all(row_problems(EXTRA, v) == [] for v in TABLES)
    before = F.endpoint_coverage(firmware="0.5.6")["model"]
    old = V.VirtualODrive(seed=131)._leaves["axis0.motor.I_bus"].row
    assert old.path == "axis*.motor.I_bus" and old not in EXTRA          # the catalog's
    monkeypatch.setattr(V.VirtualODrive, "endpoints", V.ENDPOINTS + EXTRA)
    assert F.endpoint_coverage(firmware="0.5.6")["model"] == before      # the same endpoints ...
    assert V.VirtualODrive(seed=131)._leaves["axis0.motor.I_bus"].row in EXTRA   # ... from the new rows
    assert "axis0.motor.current_control.Ibus" in F.endpoint_coverage(firmware="0.5.1")["model"]
    # the model's tree
    sim = V.VirtualODrive(seed=132)
    t0 = sim.transactions
    value = sim.axis1.motor.I_bus              # read after the transaction's ticks
    assert value == float(sim.st.AS[0, 1, L.S_IBUS_MOTOR]) and type(value) is float
    assert sim.transactions == t0 + 1
    assert "current_control" in dir(sim.axis1.motor) and "Ibus" not in dir(sim.axis1.motor.current_control)
    sim.axis0.motor.config.acim_autoflux_attack_gain = 3
    assert sim.st.C[0, 0, L.C_INT_RESET_TORQUE] == 3.0
    with pytest.raises(ValueError, match="odrv.axis0.motor.config.acim_autoflux_attack_gain must be positive"):
        sim.axis0.motor.config.acim_autoflux_attack_gain = -1.0
    with pytest.raises(AttributeError, match="read-only"):
        sim.axis0.motor.I_bus = 1.0
    # the wire
    serial = F.serial_for_seed(133)
    try:
        odrv = find_any(seed=133)
        model = device_of(odrv)
        cov = F.endpoint_coverage(model)
        assert "axis1.motor.I_bus" in cov["model"]
        assert "axis1.motor.config.acim_autoflux_attack_gain" in cov["model"]
        t0 = model.transactions
        assert odrv.axis1.motor.I_bus == float(model.st.AS[0, 1, L.S_IBUS_MOTOR])
        assert model.transactions == t0 + 1     # one transaction
        odrv.axis1.motor.config.acim_autoflux_attack_gain = 2.5
        assert model.st.C[0, 1, L.C_INT_RESET_TORQUE] == 2.5
        assert odrv.axis1.motor.config.acim_autoflux_attack_gain == 2.5
        with pytest.raises(ValueError, match="must be positive"):
            odrv.axis1.motor.config.acim_autoflux_attack_gain = 0.0
    finally:
        forget(serial)
