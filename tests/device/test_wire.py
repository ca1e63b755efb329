"""The virtual ODrive served by endpoint id to the installed ``odrive`` client.

References: the endpoint tables are the firmware's ``Firmware/odrive-interface.yaml`` of
tags fw-v0.5.1 and fw-v0.5.6 (``leglib/device/virtual/tables/README.md``); the client is odrive 0.6.11
(``runtime_device.py``, ``sync_tree.py``, ``utils.py``, ``legacy.py``).
"""

import pytest

import leglib as lg
from leglib.device.virtual import device_of, find_any
from leglib.device.virtual import firmware as V
from leglib.device.virtual import wire as F
from leglib.device.virtual.tree import UnmodeledError

odrive = pytest.importorskip("odrive")

import odrive.utils  # noqa: E402,F811 - the client's module, after the skip
from odrive.runtime_device import RuntimeDevice  # noqa: E402
from odrive.sync_tree import SyncObject  # noqa: E402


def _node(odrv, path):
    *parents, leaf = path.split(".")
    for p in parents:
        odrv = getattr(odrv, p)
    return odrv, leaf


@pytest.mark.parametrize("firmware, total", [("0.5.6", 762), ("0.5.1", 534)])
def test_every_endpoint_of_the_table_resolves(firmware, total):
    """Every property of the firmware's table reads through the client with its codec's
    type (odrive 0.6.11 runtime_device.py:186-195, codecs.py), answered by the model (its
    own rows and the catalog's) or the firmware identity -- or, for a reading the model
    cannot know (task timings, stack marks), raises UnmodeledError naming it. Every
    writable one takes back the value it reads, as the firmware would."""
    odrv = find_any(seed=101, firmware=firmware)
    cov = F.endpoint_coverage(device_of(odrv), firmware)
    assert sum(len(v) for v in cov.values()) == total
    assert cov["unmodeled"] == [] and len(cov["identity"]) == 4
    flat = F.flatten(F.endpoint_table(firmware))
    python_type = {"float": float, "bool": bool}
    unknown = []
    for path, entry in flat.items():
        node, leaf = _node(odrv, path)
        if entry["type"] == "function":
            assert callable(getattr(node, leaf)), path
            continue
        try:
            value = getattr(node, leaf)
        except UnmodeledError as exc:
            assert path in str(exc) or path.split(".", 1)[-1] in str(exc), (path, exc)
            unknown.append(path)
            continue
        if entry["type"] == "endpoint_ref":
            assert value is None, path            # a null reference by default
        else:
            assert isinstance(value, python_type.get(entry["type"], int)), (path, value)
        if "w" in entry["access"] and path not in ("axis0.requested_state", "axis1.requested_state"):
            setattr(node, leaf, value)
    assert all("task_times" in p or "timing_log" in p or "system_stats" in p for p in unknown), unknown
    assert odrv._dev.fw_version == tuple(int(p) for p in firmware.split("."))


def test_client_object_is_the_usb_kind():
    """find_any returns what odrive.find_any returns: the client's SyncObject over a
    RuntimeDevice (odrive 0.6.11 device_manager.py:639-643), with the serial number the
    client formats as 12 hex digits."""
    odrv = find_any(seed=3)
    assert isinstance(odrv, SyncObject) and isinstance(odrv._dev, RuntimeDevice)
    assert odrv._dev.serial_number == f"{F.serial_for_seed(3):012X}"
    assert odrv.serial_number == F.serial_for_seed(3)
    assert find_any(seed=3) is odrv
    assert find_any(serial_number=f"{F.serial_for_seed(3):012X}") is odrv
    other = find_any(seed=4)
    assert device_of(other) is not device_of(odrv)
    assert device_of(odrv.axis0.controller) is device_of(odrv)   # any node
    assert device_of(object()) is None


def test_reads_and_writes_reach_the_model_as_float32():
    """A float endpoint is float32 on the wire (fibre codecs 'f'): what reads back is the
    float32 of what was written; the model sees the write at once."""
    import struct
    odrv = find_any(seed=5)
    sim = device_of(odrv)
    odrv.axis1.controller.config.pos_gain = 8.27 / 340
    f32 = struct.unpack("<f", struct.pack("<f", 8.27 / 340))[0]
    assert odrv.axis1.controller.config.pos_gain == f32
    assert sim.axis1.controller.config.pos_gain == f32
    n0, t0 = sim.transactions, sim.time
    for _ in range(20):
        odrv.axis0.encoder.pos_estimate
    assert sim.transactions - n0 == 20                # one transaction per endpoint access
    assert sim.time - t0 >= 20 * 0.5 * sim.twin.plant.usb_latency   # each costs (its spread: test_firmware)


def test_settings_are_stored_or_refused_with_the_reason():
    """A setting the model does not act on is stored as the firmware stores it (any value
    of its type) and read back; one that would change the motion in a way the model does
    not simulate accepts only the firmware's default and otherwise raises UnmodeledError
    naming the endpoint and why (catalog.py)."""
    odrv = find_any(seed=6)
    assert odrv.config.uart_a_baudrate == 115200                # odrive_main.h:71
    odrv.config.uart_a_baudrate = 9600                          # nothing wired: stored
    assert odrv.config.uart_a_baudrate == 9600
    odrv.axis0.config.enable_step_dir = False                   # the default: accepted
    with pytest.raises(UnmodeledError, match=r"axis0\.config\.enable_step_dir.*step/dir"):
        odrv.axis0.config.enable_step_dir = True
    assert odrv.axis0.config.enable_step_dir is False
    with pytest.raises(UnmodeledError, match="gpio9_mode.*encoders"):
        odrv.config.gpio9_mode = 0                               # the encoder's A pin


def test_function_calls_follow_the_table():
    """Arguments and results as the client packs them (runtime_device.py:230-248): 0.5.6's
    save_configuration returns its bool (odrive-interface.yaml:205 of fw-v0.5.6), 0.5.1's
    returns nothing (fw-v0.5.1 odrive-interface.yaml:195); test_function's static counter
    counts; a refused action raises naming it; a wrong argument count is the client's
    ValueError."""
    odrv = find_any(seed=7)
    if hasattr(device_of(odrv), "reboot"):     # 0.5.6 resets inside the call: no result
        with pytest.raises(odrive.DeviceLostException):
            odrv.save_configuration()
        odrv = find_any(seed=7)
    else:
        assert odrv.save_configuration() is True
    old = find_any(seed=8, firmware="0.5.1")
    assert old.save_configuration() is None
    assert odrv.test_function(5) == 5 and odrv.test_function(-2) == 3    # odrive_main.h:184-187
    with pytest.raises(NotImplementedError, match="enter_dfu_mode"):     # UnmodeledError
        odrv.enter_dfu_mode()
    with pytest.raises(ValueError, match="expected 1 arguments"):
        odrv.test_function()


def test_dump_errors_shows_the_models_flags(capsys):
    """odrive.utils.dump_errors works on the virtual device as on USB: firmware < 0.6 goes
    to legacy.format_errors (odrive 0.6.11 utils.py:87-89, legacy.py:53-62), which reads
    the model's error flags; odrv.clear_errors() clears them (fw-v0.5.6 main.cpp:236)."""
    odrv = find_any(seed=9)
    odrv.axis0.requested_state = 8               # not calibrated: the axis refuses
    device_of(odrv).sleep(0.002)               # the axis thread takes requests up (axis.cpp:290)
    assert odrv.axis0.error & 0x1
    odrive.utils.dump_errors(odrv)
    out = capsys.readouterr().out
    assert "AxisError.INVALID_STATE" in out and "system" in out and "axis1" in out
    odrv.clear_errors()
    assert odrv.axis0.error == 0
    odrive.utils.dump_errors(odrv)
    assert "INVALID_STATE" not in capsys.readouterr().out


def _reboot(odrv):
    """Reset the device as firmware 0.5.x's reboot() does (main.cpp:194); the model's own
    reboot when it has one, else its boot counter alone."""
    sim = device_of(odrv)
    if hasattr(sim, "reboot"):
        with pytest.raises(odrive.DeviceLostException):
            odrv.reboot()
    else:
        sim.boot_count = getattr(sim, "boot_count", 0) + 1


def test_reboot_loses_the_handle_and_find_any_reconnects():
    """After a reset the old handle raises the client's DeviceLostException on any access
    (as a USB handle whose device vanished, libodrive.py:72-79); find_any with the same seed
    returns a new handle to the same device. Settings come back as saved."""
    odrv = find_any(seed=10)
    sim = device_of(odrv)
    odrv.config.dc_bus_undervoltage_trip_level = 7.0
    try:
        odrv.save_configuration()
    except odrive.DeviceLostException:           # 0.5.6 resets inside the call (main.cpp:180)
        odrv = find_any(seed=10)
    odrv.axis1.motor.config.resistance_calib_max_voltage = 4.0   # not saved
    _reboot(odrv)
    with pytest.raises(odrive.DeviceLostException):
        odrv.config.dc_bus_undervoltage_trip_level
    with pytest.raises(V.DeviceLostError):
        odrv.vbus_voltage
    new = find_any(seed=10)
    assert new is not odrv and device_of(new) is sim
    assert new.config.dc_bus_undervoltage_trip_level == 7.0
    assert new.axis1.motor.config.resistance_calib_max_voltage == 2.0


def test_injected_disconnect_is_the_clients_device_lost():
    """A lost link raises the client's DeviceLostException (also leglib's DeviceLostError);
    find_any again re-plugs: a new handle, the device ran on."""
    odrv = find_any(seed=11)
    sim = device_of(odrv)
    sim.disconnect_after = sim.transactions + 1
    odrv.vbus_voltage
    with pytest.raises(odrive.DeviceLostException):
        odrv.vbus_voltage
    new = find_any(seed=11)
    assert new is not odrv and isinstance(new.vbus_voltage, float)
    with pytest.raises(odrive.DeviceLostException):
        odrv.vbus_voltage


def test_firmware_argument():
    """A v3.6 runs 0.5.x: "0.5" means 0.5.6; 0.6.x (ODrive Pro/S1/Micro) is refused with
    the reason (odrive/README.md item 11); a device keeps its firmware for the process."""
    assert F.normalize_firmware("0.5") == "0.5.6" and F.normalize_firmware("0.5.1") == "0.5.1"
    with pytest.raises(ValueError, match="no 0.6 firmware"):
        find_any(seed=12, firmware="0.6")
    with pytest.raises(ValueError, match="no 0.6 firmware"):
        find_any(seed=12, firmware="0.6.11")
    with pytest.raises(ValueError, match="firmware='0.4.20'"):
        find_any(seed=12, firmware="0.4.20")
    find_any(seed=12, firmware="0.5.1")
    with pytest.raises(ValueError, match="firmware='0.5.6'"):
        find_any(seed=12)
    with pytest.raises(ValueError, match="seed"):
        find_any(seed=-1)
    with pytest.raises(TypeError, match="unknown option"):
        find_any(seed=13, sed=1)


def test_tables_are_package_data():
    """The tables ship inside the package with the firmware's MIT notice."""
    from importlib import resources
    base = resources.files("leglib.device.virtual.tables")
    assert "MIT License" in base.joinpath("LICENSE-ODrive.md").read_text()
    assert len(F.flatten(F.endpoint_table("0.5.6"))) == 762
    assert len(F.flatten(F.endpoint_table("0.5.1"))) == 534


def test_endpoints_start_at_the_firmwares_defaults():
    """Defaults come from the firmware's sources (leglib/device/virtual/tables/defaults_fw-v*.json):
    encoder.hpp:21 ``calib_range = 0.02f``, controller.hpp:48 ``uint8_t axis_to_mirror = -1``
    (reads 255, C's conversion), odrive_main.h:82 ``enable_brake_resistor = false`` and
    :111 ``dc_max_negative_current = -0.01f`` (fw-v0.5.6; 0.5.1 has no such switch)."""
    d56, d51 = F.firmware_defaults("0.5.6"), F.firmware_defaults("0.5.1")
    assert d56["config.enable_brake_resistor"] == {"value": False,
                                                   "source": "Firmware/MotorControl/odrive_main.h:82"}
    assert d56["config.dc_max_negative_current"]["value"] == -0.01
    assert "config.enable_brake_resistor" not in d51                 # 0.5.1: always on
    assert d56["axis*.encoder.config.calib_range"]["source"] == "Firmware/MotorControl/encoder.hpp:21"
    odrv = find_any(seed=14)
    assert odrv.axis1.encoder.config.calib_range == pytest.approx(0.02, rel=1e-7)
    assert odrv.axis0.controller.config.axis_to_mirror == 255


def test_device_reconnect_after_reboot():
    """leglib's Device finds its ODrive again after a reset (fw-v0.5.6 main.cpp:180/194):
    a new client handle on the same model, the old one lost."""
    d = lg.connect("virtual", seed=15)
    old, sim = d.raw, d.sim
    _reboot(d.raw)
    with pytest.raises(odrive.DeviceLostException):
        d.raw.vbus_voltage
    d.reconnect()
    assert d.raw is not old and d.sim is sim and device_of(d.raw) is sim
    assert d.firmware_version == (0, 5, 6) and isinstance(d.raw.vbus_voltage, float)


@pytest.mark.parametrize("option, value, message", [
    ("noise", "no", "virtual ODrive option noise must be True or False, got 'no'"),
    ("noise", 0, "virtual ODrive option noise must be True or False, got 0"),
    ("realtime", "false", "virtual ODrive option realtime must be True or False"),
    ("payload_off_for_calibration", 1, "virtual ODrive option payload_off_for_calibration must be True or False"),
    ("disconnect_after", 2.5, "virtual ODrive option disconnect_after must be an integer, got 2.5"),
])
def test_switches_are_booleans_only(option, value, message):
    from leglib.errors import ParameterError
    # refused before a device is made: the seed is never used
    with pytest.raises(ParameterError, match=message):
        lg.connect("virtual", seed=9771, **{option: value})
    with pytest.raises(ParameterError, match=message):
        find_any(seed=9771, **{option: value})


@pytest.mark.slow
def test_the_virtual_timeline_does_not_depend_on_the_client_threads():
    """The client's device manager rediscovers a rebooted board on its own thread and reads
    its identity when it connects it (odrive 0.6.11 runtime_device.py:81-124). Those reads
    are part of the boot's time and the manager's thread never drives the model's clock
    while a script does: the same script gives the same virtual time, transaction count and
    readings in every run, whatever the threads' timing (here varied by the hash seed)."""
    import os
    import subprocess
    import sys
    from pathlib import Path
    root = Path(__file__).resolve().parents[2]
    script = "\n".join([
        "import odrive",
        "from leglib.device.virtual import device_of, find_any",
        "odrv = find_any(seed=21)",
        "sim = device_of(odrv)",
        "for i in range(3):",
        "    odrv.config.brake_resistance = 1.0 + i",
        "    try:",
        "        odrv.save_configuration()",
        "    except odrive.DeviceLostException:",
        "        pass",
        "    odrv = find_any(seed=21)",
        "    odrv.vbus_voltage",
        "print(repr(sim.time), sim.transactions, repr(odrv.vbus_voltage))",
    ])
    outs = set()
    for hash_seed in ("1", "3", "7", "9"):
        env = {**os.environ, "PYTHONPATH": str(root), "PYTHONHASHSEED": hash_seed}
        run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env,
                             timeout=120, cwd=root)
        assert run.returncode == 0, run.stderr
        outs.add(run.stdout.strip())
    assert len(outs) == 1, outs


def test_a_running_loop_is_left_alone():
    """In a process whose main thread runs an event loop (a Jupyter kernel), connecting to the
    virtual ODrive and rebooting it leave that loop unpatched: the client's device manager
    runs on a thread of its own. A kernel loop patched for nesting from inside a cell crashed
    the kernel in JupyterLab (asyncio's _run_once: "pop from an empty deque", the outer
    iteration popping callbacks a nested run had taken). A new process: the device manager
    is global and made once."""
    import subprocess
    import sys
    import textwrap

    script = textwrap.dedent("""
        import asyncio
        import leglib as lg
        from odrive.device_manager import get_device_manager

        async def cell():
            loop = asyncio.get_running_loop()
            dev = lg.connect("virtual", seed=5)
            try:
                dev.raw.reboot()                    # the device manager finds it again
            except Exception:                       # the reply lost with the link, as on a board
                pass
            dev.reconnect()
            assert get_device_manager().loop is not loop, "the device manager took the kernel's loop"
            assert not hasattr(loop, "_nest_patched"), "the kernel's loop was patched for nesting"
            print("OK", float(dev.raw.vbus_voltage) > 0)

        asyncio.run(cell())
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.split() == ["OK", "True"]


def test_the_json_checksum_is_fibres_bitwise_crc16():
    """The table CRC equals the bitwise definition (fibre's CRC16: polynomial 0x3D65, init
    0x1337, MSB first) on random bytes of several lengths and on the board's own JSON."""
    import numpy as np

    def bitwise(data, crc=0x1337, poly=0x3D65):
        for byte in data:
            crc ^= byte << 8
            for _ in range(8):
                crc = (((crc << 1) ^ poly) if crc & 0x8000 else (crc << 1)) & 0xFFFF
        return crc

    rng = np.random.default_rng(7)
    for n in (0, 1, 2, 3, 255, 4097):
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        assert F._crc16(data) == bitwise(data), n
    for version in F.FIRMWARE_TABLES:
        raw, _ = F._table_raw(version)
        assert F._crc16(raw) == bitwise(raw) != bitwise(raw[:-1]), version
