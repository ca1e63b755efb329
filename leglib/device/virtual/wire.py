"""The virtual ODrive on the wire: endpoint ids of the firmware's own table, served to the
installed ``odrive`` client.

A real ODrive v3.6 describes itself with a JSON table (endpoint 0) and then answers reads,
writes and function calls by endpoint id. :class:`VirtualUSBDevice` does the same for a
:class:`leglib.device.virtual.firmware.VirtualODrive`, with the tables of firmware 0.5.1 and 0.5.6
shipped in :mod:`leglib.device.virtual.tables`; the ``odrive`` package then builds its usual object tree
over it (``odrive.runtime_device.RuntimeDevice``, ``odrive.sync_tree.SyncObject``), so a
virtual and a USB ODrive are the same kind of Python object: ``odrv.axis0.controller.config.
pos_gain``, ``odrv.save_configuration()`` and ``odrive.utils.dump_errors(odrv)`` behave alike.

Every endpoint of the table resolves onto the firmware model's tree: its own rows
(:data:`leglib.device.virtual.firmware.ENDPOINTS`) and, for every other endpoint, the
catalog's (:mod:`leglib.device.virtual.catalog`: settings stored as the firmware stores them,
derived readings, and what the model refuses, with the reason); the firmware identity
(``fw_version_*``) is that of the table served. :func:`endpoint_coverage` lists them.

Each endpoint operation costs what the firmware's protocol costs (fibre's legacy protocol,
legacy_protocol.cpp:456-497: one request-response per endpoint): a property read or write
is one USB transaction, a function call one per input argument, one for the trigger and one
per output (legacy_object_client.cpp:668-685).

:func:`find_any` (exported as :func:`leglib.device.virtual.wire.find_any`) keeps one virtual
device per serial number for the life of the process. When the device reboots (its
``boot_count`` grows), every old handle raises :class:`VirtualDeviceLost` (an
``odrive.DeviceLostException``) on its next access, as a USB handle does; ``find_any`` with
the same seed returns a new handle to the same device.

The client runs its coroutines on one background event loop (a daemon thread), as
``odrive.find_any`` does from a plain script; each blocking access hops to that thread.
"""

from __future__ import annotations

import asyncio
import json
import struct
import threading
import time as _time
from dataclasses import dataclass, field
from functools import lru_cache
from importlib import resources

from odrive.async_tree import AsyncObject
from odrive.hw_version import HwVersion
from odrive.libodrive import Device, DeviceLostException, DeviceType, DiscoveryInfo, Interface, InterfaceType
from odrive.runtime_device import RuntimeDevice
from odrive.sync_tree import SyncObject

from ... import checks
from ...errors import DeviceLostError, ParameterError
from ...params import PlantParams, load_plant
from .board import HW_VERSION as _HW_VERSION
from .firmware import BOOT_TIME, VirtualODrive
from .tree import Endpoint, Leaf, UnmodeledError, model_paths

FIRMWARE_TABLES = {"0.5.1": "endpoints_fw-v0.5.1.json", "0.5.6": "endpoints_fw-v0.5.6.json"}
FIRMWARE_ALIASES = {"0.5": "0.5.6"}
SERIAL_BASE = 0x3A7F1E2D4B00  # the model's serial_number is SERIAL_BASE + seed

# struct format of each codec of the table (as odrive.codecs)
_FORMATS = {"int8": "b", "uint8": "B", "int16": "h", "uint16": "H", "int32": "i", "uint32": "I",
            "int64": "q", "uint64": "Q", "bool": "?", "float": "f", "endpoint_ref": "I"}

# the firmware identity endpoints, answered from the table served
_IDENTITY = ("fw_version_major", "fw_version_minor", "fw_version_revision", "fw_version_unreleased")


class VirtualDeviceLost(DeviceLostException, DeviceLostError):
    """The virtual ODrive went away (reboot, injected disconnect): the old handle is dead.

    It is the client's own ``odrive.DeviceLostException``, as on USB, and leglib's
    :class:`leglib.errors.DeviceLostError`.
    """

    def __init__(self, device, reason: str = ""):
        DeviceLostException.__init__(self, device)
        if reason:
            self.args = (f"{self.args[0]} ({reason})",)


# ---------------------------------------------------------------------------------------
# the tables
# ---------------------------------------------------------------------------------------

def normalize_firmware(firmware: str) -> str:
    """The table version for a ``firmware`` argument: "0.5.1" or "0.5.6" ("0.5" is 0.5.6).

    Raises ValueError naming the parameter for anything else; 0.6.x gets its own message,
    since an ODrive v3.6 has no 0.6 firmware.
    """
    fw = str(firmware).strip().lstrip("v")
    fw = FIRMWARE_ALIASES.get(fw, fw)
    if fw in FIRMWARE_TABLES:
        return fw
    parts = fw.split(".")
    if len(parts) >= 2 and parts[0].isdigit() and parts[1].isdigit() and (int(parts[0]), int(parts[1])) >= (0, 6):
        raise ValueError(f"firmware={firmware!r}: an ODrive v3.6 has no 0.6 firmware (0.6.x is for ODrive "
                         f"Pro, S1 and Micro); use '0.5.6' or '0.5.1'")
    raise ValueError(f"firmware={firmware!r}: the virtual ODrive v3.6 has the endpoint tables of "
                     f"{sorted(FIRMWARE_TABLES)} ('0.5' means '0.5.6')")


_TABLE_CACHE: dict[str, tuple[bytes, list]] = {}


def endpoint_table(firmware: str = "0.5.6") -> list:
    """The firmware's interface description (nested JSON list) for ``firmware``."""
    return _table_raw(normalize_firmware(firmware))[1]


def _table_raw(version: str) -> tuple[bytes, list]:
    if version not in _TABLE_CACHE:
        raw = resources.files("leglib.device.virtual.tables").joinpath(FIRMWARE_TABLES[version]).read_bytes()
        _TABLE_CACHE[version] = (raw, json.loads(raw))
    return _TABLE_CACHE[version]


_DEFAULTS_CACHE: dict[str, dict] = {}


def firmware_defaults(firmware: str = "0.5.6") -> dict:
    """``{"axis*.motor.config.calibration_current": {"value": 10.0, "source":
    "Firmware/MotorControl/motor.hpp:20"}, ...}``: the configuration defaults of
    ``firmware``, from its sources (ODrive v3.6, 56 V: the board presented). Defaults that
    differ by axis carry ``"axes": [axis0, axis1]``."""
    version = normalize_firmware(firmware)
    if version not in _DEFAULTS_CACHE:
        raw = resources.files("leglib.device.virtual.tables").joinpath(f"defaults_fw-v{version}.json").read_text()
        _DEFAULTS_CACHE[version] = json.loads(raw)["defaults"]
    return _DEFAULTS_CACHE[version]


def flatten(table: list, prefix: str = "") -> dict:
    """``{"axis0.controller.config.pos_gain": entry, ...}``: every property and function."""
    out = {}
    for item in table:
        path = f"{prefix}{item['name']}"
        if item["type"] == "object":
            out.update(flatten(item["members"], path + "."))
        elif item["type"] != "json":
            out[path] = item
    return out


def _generic(path: str) -> str:
    """``axis1.motor.config.x`` -> ``axis*.motor.config.x`` (the keys of the defaults)."""
    head, _, rest = path.partition(".")
    return "axis*." + rest if head.startswith("axis") and head[4:].isdigit() else path


def _crc16_table(poly: int) -> tuple:
    """The byte-at-a-time table of the CRC16 below (the bitwise loop over the eight bits of
    each possible top byte)."""
    table = []
    for top in range(256):
        crc = top << 8
        for _ in range(8):
            crc = (((crc << 1) ^ poly) if crc & 0x8000 else (crc << 1)) & 0xFFFF
        table.append(crc)
    return tuple(table)


_CRC16_TABLE = _crc16_table(0x3D65)


@lru_cache(maxsize=8)
def _crc16(data: bytes, init: int = 0x1337) -> int:
    """Fibre's canonical CRC16 (polynomial 0x3D65, MSB first, no reflection; the JSON's
    checksum the client folds into endpoint refs), a table lookup per byte. Every connect
    computes it over the endpoint JSON (tens of kilobytes; the same bytes for the same
    board): the bitwise loop cost a fifth of a twin connect's CPU, hence the table and the
    cache."""
    crc, table = init, _CRC16_TABLE
    for byte in data:
        crc = ((crc << 8) & 0xFFFF) ^ table[(crc >> 8) ^ byte]
    return crc


# ---------------------------------------------------------------------------------------
# resolution of endpoints onto the model
# ---------------------------------------------------------------------------------------

@dataclass
class _Endpoint:
    path: str
    id: int
    kind: str            # "property" or "function"
    codec: str           # property codec, or "function"
    writable: bool
    source: str          # "model", "identity" or "unmodeled" (no row: an error at use)
    node: object = None  # the model's _Node holding it (source "model")
    leaf: str = ""
    row: Endpoint = None  # the model's row (source "model")
    outputs: tuple = ()
    n_inputs: int = 0


def _build_endpoints(leaves: dict, version: str) -> dict[int, _Endpoint]:
    """The table of ``version`` resolved onto the model's endpoints ``leaves`` (``{name:
    Leaf(node, name, row)}``, as :func:`leglib.device.virtual.tree.build_tree` gives)."""
    eps = {}
    for path, e in flatten(_table_raw(version)[1]).items():
        kind = "function" if e["type"] == "function" else "property"
        ep = _Endpoint(path=path, id=e["id"], kind=kind, codec=e["type"],
                       writable="w" in e.get("access", ""), source="unmodeled",
                       outputs=tuple(o["type"] for o in e.get("outputs", ())),
                       n_inputs=len(e.get("inputs", ())))
        if kind == "property" and path in _IDENTITY:
            ep.source = "identity"
        else:
            hit = leaves.get(path)
            if hit is not None and hit.row.function == (kind == "function"):
                ep.source, ep.node, ep.leaf, ep.row = "model", hit.node, hit.name, hit.row
        eps[ep.id] = ep
    return eps


def endpoint_coverage(sim=None, firmware: str = "0.5.6") -> dict:
    """How the table of ``firmware`` maps onto the firmware model: that of ``sim`` (a
    :class:`VirtualODrive`), else the rows of :data:`VirtualODrive.endpoints`.

    Returns
    -------
    dict with lists of endpoint paths: ``"model"`` (answered by the model: its own rows and
    the catalog's), ``"identity"`` (firmware version, from the table), ``"unmodeled"`` (no
    row: empty when the catalog covers the table).
    """
    from .catalog import fill  # load time: the catalog reads these tables
    version = normalize_firmware(firmware)
    if sim is not None:
        leaves = sim._leaves
    else:
        own = VirtualODrive.endpoints
        rows = model_paths(tuple(own) + fill(own, _model_firmware(version)), _model_firmware(version))
        leaves = {path: Leaf(None, path.rpartition(".")[2], row) for path, (_, row) in rows.items()}
    out = {"model": [], "identity": [], "unmodeled": []}
    for ep in _build_endpoints(leaves, version).values():
        out[ep.source].append(ep.path)
    return {k: sorted(v) for k, v in out.items()}


def _model_firmware(version: str) -> str:
    """The firmware model's own version string (the model runs each version as itself)."""
    return version


def _version_tuple(version: str) -> tuple[int, int, int]:
    return tuple(int(p) for p in version.split("."))


def _boot_count(sim) -> int:
    return int(getattr(sim, "boot_count", 0))


# ---------------------------------------------------------------------------------------
# the device record (lives for the process) and the USB-like device (one per boot)
# ---------------------------------------------------------------------------------------

@dataclass
class _Record:
    """One virtual ODrive of the process: the model and its table."""

    sim: object
    version: str
    serial: int
    args: dict
    handle: object = None                           # the client object of the current boot
    handle_boot: int = -1
    link: int = 0                                   # re-plugs after a lost link
    handle_link: int = -1
    lock: threading.RLock = field(default_factory=threading.RLock)


class VirtualInterface(Interface):
    """The virtual ODrives' "USB port": an interface of the client's device manager
    (``odrive.device_manager``) on which every virtual ODrive of the process is discovered
    as a USB ODrive is on libusb's -- found when it answers, lost when it resets (a save, a
    reboot, an erase), found again once it has booted. So the client's own discovery and
    connection paths run on it: ``device_manager.wait_for``, odrivetool's
    ``call_rebooting_function`` (restore_config), the liveplotter's recorder.

    All its methods run on the device manager's event loop."""

    def __init__(self):
        super().__init__(None, InterfaceType.USB, "virtual ODrive")
        self._handle = 1          # always open: there is no libusb handle behind it
        self._devices: dict[int, VirtualUSBDevice] = {}
        self._records: dict[int, _Record] = {}

    def __repr__(self):
        return "Interface(virtual ODrive)"

    def close(self):
        self._delegate = None     # the device manager released it; it stays usable

    def start_discovery(self, delegate):
        self._delegate = delegate
        for record in list(self._records.values()):
            self.sync(record)

    def stop_discovery(self):
        self._delegate = None

    def _known(self, dev) -> bool:
        return dev in getattr(self._delegate, "_device_metadata", {})

    def sync(self, record: _Record):
        """Bring the device manager up to date with ``record``'s device: its old boot lost,
        its current boot found once the board answers."""
        self._records[record.serial] = record
        dev = self._devices.get(record.serial)
        if dev is not None and not dev.is_present:
            del self._devices[record.serial]
            known = self._known(dev)
            dev._on_lost()
            if known and self._delegate is not None:
                self._delegate.on_lost_device(self, dev)
            dev = None
        if dev is None and _answers(record):
            dev = self._devices[record.serial] = VirtualUSBDevice(record, self)
        if dev is not None and self._delegate is not None and not self._known(dev):
            self._delegate.on_found_device(self, dev)

    def forget(self, serial: int):
        self._records.pop(serial, None)
        dev = self._devices.pop(serial, None)
        if dev is not None and self._known(dev) and self._delegate is not None:
            dev._on_lost()
            self._delegate.on_lost_device(self, dev)

    async def booted(self, record: _Record):
        """After a reset: let the board boot (its virtual time; real time too when paced)
        and report it found again, as libusb reports a board that re-enumerates."""
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(None, _boot_wait, record)
        self.sync(record)


def _answers(record: _Record) -> bool:
    """Whether ``record``'s board answers on USB now (booted, link up)."""
    sim = record.sim
    if getattr(sim, "lost", False):
        return False
    booted = getattr(sim, "_booted_at", None)
    return booted is None or sim.time >= booted + BOOT_TIME


# [s] of wall time without the virtual clock moving after which the device manager's
# thread lets a rebooting board's boot pass itself (nobody else is driving the model)
_IDLE_BOOT_WAIT = 0.5


def _boot_wait(record: _Record):
    """Wait (on an executor thread) until ``record``'s board answers again after a reset.
    Whoever drives the model -- a script's own calls, ``find_any``'s reconnect -- moves its
    clock through the boot; this thread only watches, so the virtual timeline does not
    depend on thread timing. Only if the clock stands still for a while (the script waits
    on the device manager: ``call_rebooting_function``, ``restore_config_ui``, odrivetool's
    shell) does it let the boot pass itself, under the device's lock."""
    sim = record.sim
    still_since, last = _time.monotonic(), sim.time
    while not getattr(sim, "lost", False) and not _answers(record):
        now = _time.monotonic()
        if sim.time != last:
            still_since, last = now, sim.time
        elif now - still_since > _IDLE_BOOT_WAIT:
            with record.lock:
                if not getattr(sim, "lost", False) and not _answers(record) and sim.time == last:
                    sim.reconnect()
            still_since, last = _time.monotonic(), sim.time
        _time.sleep(0.002)


# what the client reads when it connects a device (odrive 0.6.11 runtime_device.py:81-124,
# attach_metadata; commit_hash and otp_valid are not in a 0.5.x table): the enumeration's
# own reads, inside the boot's time
_ATTACH_READS = frozenset({"hw_version_major", "hw_version_minor", "hw_version_variant",
                           "fw_version_major", "fw_version_minor", "fw_version_revision"})


class VirtualUSBDevice(Device):
    """A ``odrive.libodrive.Device`` that answers endpoint ids from the firmware model of
    one boot of a virtual ODrive (the client's own device class, its libodrive calls
    replaced by the model).

    Parameters
    ----------
    record : the device record (model, table version)
    interface : the interface it is found on
    """

    def __init__(self, record: _Record, interface: VirtualInterface | None = None):
        info = DiscoveryInfo(device_type=DeviceType.RUNTIME, serial_number=f"{record.serial:012X}")
        Device.__init__(self, None, 1, info, interface)
        self._record = record
        self._sim = record.sim
        self._boot = _boot_count(record.sim)
        self._link = record.link
        self._endpoints = _build_endpoints(record.sim._leaves, record.version)
        self._raw_json, _ = _table_raw(record.version)
        self._crc = _crc16(self._raw_json)

    def __repr__(self):
        return f"VirtualUSBDevice(serial_number={self.info.serial_number}, firmware={self._record.version})"

    # -- link ----------------------------------------------------------------------------
    @property
    def sim(self):
        """The firmware model behind this device."""
        return self._sim

    @property
    def is_present(self) -> bool:
        return (bool(self._handle) and _boot_count(self._sim) == self._boot and self._link == self._record.link
                and not getattr(self._sim, "lost", False))

    def drop(self):
        self._handle = 0

    def _alive(self):
        if _boot_count(self._sim) != self._boot:
            raise VirtualDeviceLost(self, "the virtual ODrive rebooted")
        if getattr(self._sim, "lost", False) or self._link != self._record.link:
            raise VirtualDeviceLost(self, "link lost")

    def _model(self, op):
        """Run ``op`` on the model; the model's own DeviceLostError becomes the client's."""
        try:
            return op()
        except DeviceLostError as exc:
            if isinstance(exc, VirtualDeviceLost):
                raise
            raise VirtualDeviceLost(self, str(exc)) from exc

    async def connect(self, node_id=None, baudrate=None) -> None:
        self._alive()
        self._connected = True
        self.hw_version = HwVersion(*_HW_VERSION)
        # The client's connection reads the identity once (attach_metadata). The device
        # manager may run it on its own thread while the script runs on (after a reboot,
        # rediscovery is asynchronous), so charging it to the virtual clock would make the
        # numbers depend on thread timing: those reads are free, part of the boot's time.
        self._attach_pending = set(_ATTACH_READS)

    def disconnect(self):
        self._connected = False

    async def get_json(self) -> tuple[bytes, int]:
        self._alive()
        return self._raw_json, self._crc

    async def get_json_id(self) -> int:
        return (self._crc << 16) | len(self._raw_json) & 0xFFFF

    # -- endpoint operations -------------------------------------------------------------
    def _endpoint(self, eid: int, kind: str) -> _Endpoint:
        ep = self._endpoints.get(eid)
        if ep is None or ep.kind != kind:
            raise ValueError(f"virtual ODrive (firmware {self._record.version}): no {kind} with "
                             f"endpoint id {eid}")
        return ep

    def _read_one(self, ep: _Endpoint):
        pending = getattr(self, "_attach_pending", ())
        if ep.path in pending:
            pending.discard(ep.path)
            if ep.source == "model":
                return self._model(lambda: ep.node._props[ep.leaf].get())
            v = _version_tuple(self._record.version)
            return {"fw_version_major": v[0], "fw_version_minor": v[1], "fw_version_revision": v[2]}[ep.path]
        if ep.source == "model":
            return self._model(lambda: getattr(ep.node, ep.leaf))
        if ep.source == "identity":
            self._transaction()
            v = _version_tuple(self._record.version)
            return {"fw_version_major": v[0], "fw_version_minor": v[1], "fw_version_revision": v[2],
                    "fw_version_unreleased": 0}[ep.path]
        raise UnmodeledError(f"virtual ODrive (firmware {self._record.version}): {ep.path} has no row")

    def _write_one(self, ep: _Endpoint, value):
        if ep.source == "model":
            if not ep.row.writable:
                raise AttributeError(f"{ep.path} is read-only")
            return self._model(lambda: setattr(ep.node, ep.leaf, value))
        if ep.source == "identity":
            raise AttributeError(f"{ep.path} is read-only")
        raise UnmodeledError(f"virtual ODrive (firmware {self._record.version}): {ep.path} has no row")

    def _transaction(self):
        tx = getattr(self._sim, "_transaction", None)
        if tx is not None:
            self._model(tx)

    @staticmethod
    def _to_wire(codec: str, value):
        if codec == "float":
            return float(value)
        if codec == "bool":
            return bool(value)
        return int(value)

    async def read_endpoints(self, endpoint_ids, sizes, transient=False) -> bytes:
        with self._record.lock:
            self._alive()
            out = bytearray()
            for eid, size in zip(endpoint_ids, sizes):
                ep = self._endpoint(eid, "property")
                fmt = "<" + _FORMATS[ep.codec]
                if struct.calcsize(fmt) != size:
                    raise ValueError(f"virtual ODrive: {ep.path} is {ep.codec}, read asked for {size} bytes")
                out += struct.pack(fmt, self._to_wire(ep.codec, self._read_one(ep)))
            return bytes(out)

    async def write_endpoints(self, endpoint_ids, sizes, buf: bytes) -> None:
        with self._record.lock:
            self._alive()
            pos = 0
            for eid, size in zip(endpoint_ids, sizes):
                ep = self._endpoint(eid, "property")
                fmt = "<" + _FORMATS[ep.codec]
                (value,) = struct.unpack_from(fmt, buf, pos)
                pos += size
                if not ep.writable:
                    raise AttributeError(f"{ep.path} is read-only")
                self._write_one(ep, value)

    async def call_function(self, endpoint_id, in_format: str, out_format: str, args):
        with self._record.lock:
            self._alive()
            ep = self._endpoint(endpoint_id, "function")
            args = struct.unpack(in_format, struct.pack(in_format, *args))  # the wire's conversions
            n_out = len(struct.unpack(out_format, bytes(struct.calcsize(out_format))))
            if ep.source != "model":
                raise UnmodeledError(f"virtual ODrive (firmware {self._record.version}): {ep.path}() has no row")
            # legacy_object_client.cpp:668-685: each input argument is written to its own
            # endpoint, then the trigger (the model's call, one transaction), then each
            # output is read from its own endpoint
            for _ in range(ep.n_inputs):
                self._transaction()
            result = self._model(lambda: getattr(ep.node, ep.leaf)(*args))
            if _boot_count(self._sim) != self._boot:
                # the firmware resets inside the call (NVIC_SystemReset): no response comes back
                raise VirtualDeviceLost(self, f"{ep.path}() rebooted the virtual ODrive")
            for _ in range(n_out):
                self._transaction()
            if n_out == 0:
                return ()
            values = result if isinstance(result, tuple) else (result,)
            if len(values) != n_out:
                raise ValueError(f"virtual ODrive: {ep.path}() returned {len(values)} values, the "
                                 f"table declares {n_out}")
            values = [self._to_wire(c, v) for c, v in zip(ep.outputs, values)]
            return struct.unpack(out_format, struct.pack(out_format, *values))


# ---------------------------------------------------------------------------------------
# the client's device manager, the registry and find_any
# ---------------------------------------------------------------------------------------

_REGISTRY: dict[int, _Record] = {}
_REGISTRY_LOCK = threading.RLock()
_INTERFACES: dict[int, VirtualInterface] = {}     # id(device manager) -> its virtual interface


def _manager():
    """The client's global device manager (``odrive.device_manager.get_device_manager``:
    a background thread with its event loop in a script, the shell's loop in IPython) and
    the virtual interface registered with it."""
    from odrive._internal_utils import get_current_loop  # load time: the client's device manager
    from odrive.device_manager import get_device_manager  # load time: the client's device manager
    # a thread and loop of its own, also where this thread runs a loop: a Jupyter kernel's
    # loop, patched for nesting from inside a cell (its outer _run_once already counted the
    # ready callbacks a nested run takes), crashes the kernel ("pop from an empty deque")
    dm = get_device_manager(force_background_thread=True)
    loop = get_current_loop()
    if loop is not None and dm.loop is loop and not hasattr(loop, "_nest_patched"):
        # a device manager bound to this loop before (odrivetool's shell made it there):
        # the synchronous calls below run on it nested, as odrive.find_sync does
        import odrive._nest_asyncio  # load time: only in a shell's running loop (as odrive.find_sync does)
        odrive._nest_asyncio.apply(loop)
    intf = _INTERFACES.get(id(dm))
    if intf is None:
        intf = _INTERFACES[id(dm)] = VirtualInterface()
    return dm, intf


def _register(dm, intf: VirtualInterface):
    """Register the interface with the device manager (again, after it released it when
    its last device was lost: the client closes an unused interface)."""
    if intf not in dm._interface_metadata:
        dm._add_intf(intf, "virtual", lambda i: i.close())


def _on_loop(dm, make_coro):
    from odrive._internal_utils import run_on_loop  # load time: the client's device manager

    async def run():
        return await make_coro()
    return run_on_loop(run(), dm.loop)


def _on_reset(sim):
    """The model's reset hook: tell the device manager, on its loop, that the board went
    away, and bring it back once it has booted."""
    with _REGISTRY_LOCK:
        record = next((r for r in _REGISTRY.values() if r.sim is sim), None)
    if record is None:
        return
    for dm_id, intf in list(_INTERFACES.items()):
        dm = _dm_alive(dm_id)
        if dm is None:
            continue
        def schedule(intf=intf):
            intf.sync(record)
            asyncio.ensure_future(intf.booted(record))
        try:
            dm.loop.call_soon_threadsafe(schedule)
        except RuntimeError:     # the device manager was closed
            pass


def _dm_alive(dm_id: int):
    import odrive.device_manager as m  # load time: the client's device manager
    dm = m._global_device_manager
    return dm if dm is not None and id(dm) == dm_id else None


def _connect_client(record: _Record):
    """The client's object over the current boot of ``record``'s device, as the client's
    device manager finds and connects it."""
    from odrive.device_manager import RuntimeDevice as _RD  # load time: the client's device manager
    dm, intf = _manager()
    hooks = record.sim.__dict__.setdefault("_reset_hooks", [])
    if _on_reset not in hooks:
        hooks.append(_on_reset)

    async def connect():
        intf.sync(record)           # (a lost device's bookkeeping may release the interface)
        _register(dm, intf)
        return await dm.wait_for(interfaces=[intf], serial_number=f"{record.serial:012X}", return_type=_RD)
    runtime = _on_loop(dm, connect)
    record.handle = runtime.sync_wrapper
    record.handle_boot = runtime.device._boot
    record.handle_link = runtime.device._link
    return record.handle



def serial_for_seed(seed: int) -> int:
    """The serial number of the virtual ODrive made with ``seed``."""
    return SERIAL_BASE + int(seed)


def _parse_serial(serial_number) -> int:
    if isinstance(serial_number, int) and not isinstance(serial_number, bool):
        return serial_number
    if isinstance(serial_number, str):
        try:
            return int(serial_number, 16)
        except ValueError:
            pass
    raise ValueError(f"serial_number={serial_number!r}: expected the hex string the client reports "
                     f"(e.g. '{SERIAL_BASE:012X}') or an int")


def find_any(*, seed: int = 0, plant="default", firmware: str = "0.5.6", realtime: bool = False,
             timeout: float | None = None, serial_number=None, **options):
    """The virtual ODrive of ``seed`` as the ``odrive`` client's object: a drop-in for
    ``odrive.find_any()``. See :func:`leglib.device.virtual.wire.find_any`."""
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed={seed!r}: expected a non-negative int")
    if timeout is not None and (isinstance(timeout, bool) or not isinstance(timeout, (int, float))
                                or not timeout > 0):
        raise ValueError(f"timeout={timeout!r}: expected a positive number of seconds or None")
    if not isinstance(plant, (str, PlantParams)) and not hasattr(plant, "__fspath__"):
        raise ValueError(f"plant={plant!r}: expected a plant name, a path or PlantParams")
    version = normalize_firmware(firmware)
    serial = serial_for_seed(seed)
    if serial_number is not None:
        wanted = _parse_serial(serial_number)
        if seed != 0 and wanted != serial:
            raise ValueError(f"serial_number={serial_number!r} is not the device of seed={seed} "
                             f"({serial:012X})")
        if wanted < SERIAL_BASE:
            raise ValueError(f"serial_number={serial_number!r}: no virtual ODrive has this serial number "
                             f"(they are {SERIAL_BASE:012X} + seed)")
        serial, seed = wanted, wanted - SERIAL_BASE
    allowed = {"config", "noise", "disconnect_after", "payload_off_for_calibration"}
    unknown = set(options) - allowed
    if unknown:
        raise TypeError(f"find_any: unknown option(s) {sorted(unknown)}; allowed: seed, plant, firmware, "
                        f"realtime, timeout, serial_number, {', '.join(sorted(allowed))}")
    # switches are booleans only: bool("no") is True
    realtime = checks.boolean(realtime, "virtual ODrive option realtime", ParameterError)
    for name in ("noise", "payload_off_for_calibration"):
        if name in options:
            options[name] = checks.boolean(options[name], f"virtual ODrive option {name}", ParameterError)
    if options.get("disconnect_after") is not None:
        checks.integer(options["disconnect_after"], "virtual ODrive option disconnect_after", ParameterError, low=0)
    args = {"plant": load_plant(plant) if isinstance(plant, str) else plant, "firmware": version,
            **{k: v for k, v in options.items() if k != "disconnect_after"}}
    with _REGISTRY_LOCK:
        record = _REGISTRY.get(serial)
        if record is None:
            sim = VirtualODrive(plant=plant, seed=seed, realtime=bool(realtime),
                                  firmware=_model_firmware(version), **options)
            record = _Record(sim=sim, version=version, serial=serial, args=args)
            _REGISTRY[serial] = record
        else:
            for key, value in args.items():
                if key in record.args and record.args[key] != value:
                    raise ValueError(f"{key}={value!r}: the virtual ODrive {serial:012X} (seed {seed}) "
                                     f"exists with {key}={record.args[key]!r} for this process; use "
                                     f"another seed for another device")
            if getattr(record.sim, "lost", False):
                # the link was lost (injected disconnect): finding the device re-plugs it;
                # old handles stay dead, the device itself ran on (its watchdog acted)
                record.sim.lost = False
                record.sim.disconnect_after = None
                record.link += 1
            if "disconnect_after" in options:
                record.sim.disconnect_after = options["disconnect_after"]
            _set_realtime(record.sim, bool(realtime))
        # (the client's loop thread takes record.lock for each operation: not held here)
        if record.handle is not None and record.handle_boot == _boot_count(record.sim) \
                and record.handle_link == record.link and not getattr(record.sim, "lost", False):
            return record.handle
        if record.handle is not None and record.handle_boot != _boot_count(record.sim):
            # a rebooting board enumerates again only after its boot time (as find_any on
            # USB waits for it): the model lets that virtual time pass
            record.sim.reconnect()
        return _connect_client(record)


def connect_options(sim) -> dict:
    """The :func:`find_any` arguments that find ``sim``'s device again (seed, plant,
    firmware and the options it was made with); {} for a model not in the registry."""
    with _REGISTRY_LOCK:
        for record in _REGISTRY.values():
            if record.sim is sim:
                return {"seed": record.serial - SERIAL_BASE, **record.args}
    return {}


def _set_realtime(sim, realtime: bool) -> None:
    """Switch pacing; entering real time re-bases the wall clock on the virtual one."""
    if realtime and not sim.realtime and hasattr(sim, "_t0_wall"):
        sim._t0_wall = _time.monotonic() - sim.time
    sim.realtime = realtime


def device_of(odrv):
    """The :class:`~leglib.device.virtual.firmware.VirtualODrive` behind a client object (a
    ``SyncObject``/``AsyncObject``/``RuntimeDevice`` from :func:`find_any`, any node of its
    tree, or a :class:`leglib.device.session.Device`); None for a USB device or anything else."""
    if isinstance(odrv, VirtualODrive):
        return odrv
    sim = getattr(odrv, "sim", None) if not _is_client_object(odrv) else None
    if isinstance(sim, VirtualODrive):
        return sim
    runtime = odrv if _is_runtime(odrv) else getattr(odrv, "_dev", None)
    device = getattr(runtime, "device", None)
    return device.sim if isinstance(device, VirtualUSBDevice) else None


def _is_client_object(obj) -> bool:
    return isinstance(obj, (SyncObject, AsyncObject))


def _is_runtime(obj) -> bool:
    return isinstance(obj, RuntimeDevice)


def forget(serial_number=None) -> None:
    """Drop virtual devices from the process registry (all, or one serial number): the
    next :func:`find_any` builds a fresh one. Their client objects are lost, as a board's
    when it is unplugged (the client's device manager forgets them)."""
    with _REGISTRY_LOCK:
        if serial_number is None:
            serials = list(_REGISTRY)
            _REGISTRY.clear()
        else:
            serial = _parse_serial(serial_number)
            serials = [serial] if _REGISTRY.pop(serial, None) is not None else []
    for dm_id, intf in list(_INTERFACES.items()):
        dm = _dm_alive(dm_id)
        if dm is None or not serials:
            continue

        async def retire(intf=intf):
            for serial in serials:
                intf.forget(serial)
        _on_loop(dm, retire)
