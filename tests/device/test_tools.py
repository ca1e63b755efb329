"""The odrive client's own tools on the virtual ODrive, as on a board on USB.

References: the client is odrive 0.6.11 (``legacy_config.py`` backup/restore,
``utils.py`` dump_errors / call_rebooting_function / the dump_* tools / the liveplotter,
``recorder.py`` the liveplotter's data source, ``shell.py`` odrivetool's shell,
``device_manager.py``); the firmware is fw-v0.5.6 unless marked.
"""

import asyncio
import contextlib
import io
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from leglib.device.virtual import device_of, find_any
from leglib.device.virtual import firmware as V
from leglib.device.virtual.tree import UnmodeledError
from leglib.params import load_plant

odrive = pytest.importorskip("odrive")

import odrive.utils as U  # noqa: E402 - the client's module, after the skip
from odrive._internal_utils import run_on_loop  # noqa: E402
from odrive.device_manager import get_device_manager  # noqa: E402
from odrive.legacy_config import backup_config, backup_config_ui, restore_config, restore_config_ui  # noqa: E402
from odrive.recorder import Recorder  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
_ANSI = re.compile(r"\x1b\[[0-9;]*m")


def _printed(fn, *args, **kwargs) -> str:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        fn(*args, **kwargs)
    return _ANSI.sub("", buf.getvalue())


def _listing_7_1(odrv):
    """A part of the thesis's Listing 7.1 and some more: configuration away from defaults."""
    odrv.config.brake_resistance = 2.05
    odrv.config.enable_brake_resistor = True
    odrv.config.dc_max_negative_current = -1.0
    for ax in (odrv.axis0, odrv.axis1):
        ax.motor.config.pole_pairs = 11
        ax.motor.config.torque_constant = 8.27 / 150
        ax.motor.config.current_lim = 20.0
        ax.encoder.config.cpr = 4000
        ax.controller.config.vel_limit = 2.0
        ax.controller.config.pos_gain = 35.0
        ax.config.watchdog_timeout = 0.2


def _same(a, b) -> bool:
    """legacy_config.py:28-35: floats compare as their float32 bytes."""
    if isinstance(a, float) or isinstance(b, float):
        return np.float32(a).tobytes() == np.float32(b).tobytes()
    return a == b


# -- backup_config / restore_config (odrivetool backup-config / restore-config) ----------

def test_backup_restore_round_trips_between_two_virtual_boards():
    """legacy_config.py:120-135 reads every property with ".config." in its path;
    apply_config (50-117) writes them back. On a real board the only members it cannot
    write are the read-only ones under config (odrive-interface.yaml:1149-1154, the three
    anticogging members per axis): the same six errors here, and every other value
    arrives bit for bit."""
    a, b = find_any(seed=401), find_any(seed=402)
    _listing_7_1(a)
    cfg = backup_config(a)
    assert len(cfg) > 350
    before = backup_config(b)
    assert not _same(before["axis0.encoder.config.cpr"], cfg["axis0.encoder.config.cpr"])
    errors = restore_config(b, cfg)
    assert len(errors) == 6 and all("anticogging" in e and "cannot be written" in e for e in errors)
    after = backup_config(b)
    assert after.keys() == cfg.keys()
    assert [k for k in cfg if not _same(cfg[k], after[k])] == []


def test_restore_config_ui_saves_and_the_client_finds_the_board_again(tmp_path):
    """legacy_config.py:165-188: restore, then save_configuration through
    call_rebooting_function (utils.py:290-321): the board resets inside the call
    (main.cpp:176-180), the client's device manager drops it and waits for it by serial
    number; the returned object is the rebooted board with the configuration loaded
    (user_config_loaded, main.cpp:664-672)."""
    a, c = find_any(seed=403), find_any(seed=404)
    _listing_7_1(a)
    path = tmp_path / "odrive-config.json"
    out = _printed(backup_config_ui, a, str(path))
    assert "Configuration saved" in out
    assert json.loads(path.read_text())["axis1.encoder.config.cpr"] == 4000
    boots = device_of(c).boot_count
    new = restore_config_ui(c, str(path)).sync_wrapper   # (the RuntimeDevice it returns)
    assert device_of(new) is device_of(c) and device_of(c).boot_count == boots + 1
    assert new.user_config_loaded and new.axis1.encoder.config.cpr == 4000
    assert new.config.brake_resistance == pytest.approx(2.05)
    with pytest.raises(odrive.DeviceLostException):       # the old object is the lost boot's
        c.vbus_voltage


def test_call_rebooting_function_reboot_and_find_any_agree():
    """utils.py:290-321 with reboot() (odrive_main.h:175, NVIC_SystemReset): a new object for
    the next boot; find_any returns that same boot's object."""
    odrv = find_any(seed=405)
    dm = get_device_manager()
    new = run_on_loop(U.call_rebooting_function(odrv._dev, "reboot"), dm.loop).sync_wrapper
    assert device_of(new) is device_of(odrv)
    assert new.axis0.current_state in (V.AXIS_STATE_UNDEFINED, V.AXIS_STATE_IDLE)
    again = find_any(seed=405)
    assert again.serial_number == new.serial_number and isinstance(again.vbus_voltage, float)


# -- dump_errors (utils.py:82-176) ---------------------------------------------------------

def test_dump_errors_names_the_errors_on_both_firmwares():
    """format_errors reads each axis's, motor's, encoder's, controller's error and the
    board's (fw 0.5.6 odrive-interface.yaml: odrv.error); fw 0.5.1 has no board error and
    no DRV fault reading, which the client reports as "not found" there as on a 0.5.1
    board. clear=True clears them through clear_errors (0.5.6) or the members (0.5.1)."""
    odrv = find_any(seed=406)
    odrv.axis0.config.watchdog_timeout = 0.1
    odrv.axis0.watchdog_feed()
    odrv.axis0.config.enable_watchdog = True
    device_of(odrv).sleep(0.3)
    out = _printed(U.dump_errors, odrv)
    assert "system: no error" in out and "AxisError.WATCHDOG_TIMER_EXPIRED" in out
    assert out.count("no error") == 10              # every other member of both axes
    odrv.axis0.config.enable_watchdog = False      # else it expires again at once
    _printed(U.dump_errors, odrv, True)
    assert odrv.axis0.error == 0

    old = find_any(seed=407, firmware="0.5.1")
    old.axis0.requested_state = V.AXIS_STATE_CLOSED_LOOP_CONTROL   # uncalibrated: invalid
    device_of(old).sleep(0.1)
    out = _printed(U.dump_errors, old)
    assert "system: not found" in out and "AxisError.INVALID_STATE" in out
    assert "DRV fault: not found" in out


# -- the liveplotter's data path (plotting.py:79-130, recorder.py) -----------------------

def test_the_liveplotters_recorder_samples_the_board_through_the_device_manager():
    """The liveplotter reads its properties with a Recorder (recorder.py:113-270)
    subscribed to the client's device manager: read_multiple every 10 ms. On the twin in
    real time the samples are the board's: vbus near the battery's 24 V, the control-loop
    counter advancing at 8 kHz (n_evt_control_loop, main.cpp:366) against the host's
    clock. (The window itself needs a GUI backend; odrive.utils.start_liveplotter from a
    plain script fails in the client 0.6.11 -- run_sync_on_loop passes the coroutine
    function, _internal_utils.py:80-82 -- it works in odrivetool's shell: see
    test_odrivetool_shell_in_ipython.)"""
    odrv = find_any(seed=408, realtime=True)
    aodrv = U.to_async(odrv)
    props = [aodrv.vbus_voltage, aodrv.axis0.encoder.pos_estimate, aodrv.n_evt_control_loop]
    dev = props[0]._dev
    rec = Recorder([(dev.serial_number, [(dev.path_of(p._info), p._info.codec_name) for p in props])])
    dm = get_device_manager()
    task = asyncio.run_coroutine_threadsafe(rec.run(dm), dm.loop)
    time.sleep(1.0)
    task.cancel()
    (data,) = rec.get_data(10.0)
    assert len(data) > 30
    assert np.all(np.abs(data["vbus_voltage"] - 24.0) < 1.0)
    rate = np.diff(data["n_evt_control_loop"][[0, -1]].astype(float)) / (np.diff(data["timestamp"][[0, -1]]) / 1e9)
    assert rate[0] == pytest.approx(8000.0, rel=0.1)


# -- the client's dump tools (utils.py:525-776) ---------------------------------------------

def test_the_clients_dump_tools_on_the_twin():
    """dump_dma (utils.py:663-727) prints the board's DMA table (main.cpp:487-505: the
    streams the 0.5.6 board configures). What the twin cannot know raises at its use,
    naming it, where a real board answers: dump_interrupts stops at the first
    event-driven interrupt's count (main.cpp:470-484), dump_threads at the stack
    high-water marks (main.cpp:261-288), dump_timing -- which arms the task timers and
    waits for the firmware to disarm them (utils.py:729-760, task_timer.hpp) -- returns
    from its wait and raises at the first task time."""
    odrv = find_any(seed=409)
    out = _printed(U.dump_dma, odrv)
    assert "DMA1_Stream0" in out and "SPI3_RX" in out and "ADC1" in out
    with pytest.raises(UnmodeledError, match="event-driven"):
        _printed(U.dump_interrupts, odrv)
    with pytest.raises(UnmodeledError, match="stack"):
        _printed(U.dump_threads, odrv)
    with pytest.raises(UnmodeledError, match="task_times"):
        _printed(U.dump_timing, odrv, n_samples=2, path=os.devnull)
    assert odrv.task_timers_armed is False


# -- function calls as the protocol costs them ----------------------------------------------

def test_a_function_call_costs_a_transaction_per_argument_trigger_and_result():
    """The legacy protocol (fibre legacy_object_client.cpp:668-685) writes each input
    argument to its endpoint, triggers the function, then reads each output: n_in + 1 +
    n_out request-responses. At usb_jitter 0 each costs exactly the plant's usb_latency."""
    odrv = find_any(seed=410, plant=load_plant("default", usb_jitter=0.0))
    sim = device_of(odrv)
    lat, tick = sim.twin.plant.usb_latency, sim.twin.dt

    def cost(call):
        t0, n0 = sim.time, sim.transactions
        call()
        return sim.transactions - n0, sim.time - t0

    for call, n in ((lambda: odrv.test_function(3), 3),            # 1 in, trigger, 1 out
                    (lambda: odrv.get_adc_voltage(1), 3),         # GPIO1: UART TX, high
                    (lambda: odrv.oscilloscope.get_val(7), 3),
                    (lambda: odrv.clear_errors(), 1),               # trigger only
                    (lambda: odrv.axis0.watchdog_feed(), 1),
                    (lambda: odrv.axis0.encoder.config.cpr, 1)):    # a property: one
        count, dt = cost(call)
        assert count == n
        assert dt == pytest.approx(n * lat, abs=tick)


# -- python -m leglib odrivetool ---------------------------------------------------------

def _odrivetool(args: list[str], script: str, timeout: float = 120.0) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg"}
    return subprocess.run([sys.executable, "-m", "leglib", "odrivetool", *args], input=script, text=True,
                          capture_output=True, timeout=timeout, cwd=ROOT, env=env)


@pytest.mark.slow
def test_odrivetool_shell_in_ipython():
    """odrivetool's shell (shell.py launch_shell) on a virtual board: odrv0 is there with
    the board's identity; after a reboot the device manager reports it lost and finds it
    again as odrv0 (shell.py:320-345) while the shell's loop runs (an awaited sleep: a
    blocking time.sleep holds the loop, as in odrivetool on a real board); the
    liveplotter starts and stops; dump_errors prints."""
    script = "\n".join([
        "import asyncio",
        "print('ID', hex(odrv0.serial_number), odrv0.hw_version_major, odrv0.hw_version_minor,"
        " odrv0.hw_version_variant, odrv0.fw_version_revision)",
        "odrv0.reboot()",
        "await asyncio.sleep(4)",
        "print('AFTER', odrv0.axis0.current_state, round(odrv0.vbus_voltage))",
        "start_liveplotter([to_async(odrv0).vbus_voltage])",
        "await asyncio.sleep(1.0)",
        "stop_liveplotter()",
        "await asyncio.sleep(0.2)",
        "dump_errors(odrv0)",
        ""])
    run = _odrivetool(["--seed", "411"], script)
    out = _ANSI.sub("", run.stdout)
    assert run.returncode == 0, run.stderr
    assert "Connected to ODrive v3.6-56V 3A7F1E2D4" in out and "as odrv0" in out
    assert "ID 0x3a7f1e2d4" in out and " 3 6 56 6" in out
    assert "odrv0 disappeared" in out and "Reconnected to ODrive" in out
    assert "AFTER 1 24" in out
    assert "stopped liveplotter" in out and "liveplotter failed" not in out
    assert "system: no error" in out
    assert "Traceback" not in out + run.stderr


def test_odrivetool_plain_console_on_firmware_051():
    """--no-ipython: the plain Python console of shell.py; --firmware 0.5.1 presents
    fw-v0.5.1's tree (no odrv.error, motor.config.direction)."""
    script = "\n".join([
        "print('FW', odrv0.fw_version_minor, odrv0.fw_version_revision)",
        "print('DIR', odrv0.axis0.motor.config.direction)",       # motor.hpp:49 (0.5.1): 0
        "print('ERR', hasattr(odrv0, 'error'))",
        ""])
    run = _odrivetool(["--seed", "412", "--firmware", "0.5.1", "--no-ipython"], script)
    assert run.returncode == 0, run.stderr
    out = run.stdout + run.stderr
    assert "FW 5 1" in out and "DIR 0" in out and "ERR False" in out


def test_odrivetool_command_rejects_bad_arguments():
    """Bad arguments: argparse's one line and exit code 2."""
    run = _odrivetool(["--firmware", "0.4.12"], "")
    assert run.returncode == 2 and "invalid choice" in run.stderr
    run = _odrivetool(["--seed", "-1"], "")
    assert run.returncode == 2 and "seed" in run.stderr
