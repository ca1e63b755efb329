"""Measure the spread and tail of the ``odrive`` Python client's cost per USB transaction
into ``usb_client_latency.json`` (maintainer tool; the JSON file ships with leglib).

Usage: ``python -m leglib.device.virtual.tables.measure_client [N]``

Method: the installed ``odrive`` client (its ``RuntimeDevice`` and ``SyncObject``, on its
own event-loop thread, as ``odrive.find_any`` gives them) over a device that answers every
endpoint read at once with fixed bytes; ``N`` reads of one float property in a plain loop,
each timed with ``time.perf_counter_ns``, after 1000 reads of warm-up. What this measures
is the host's share of a transaction -- Python, the thread hop, the scheduler -- whose
shape (spread, tail) a real transaction has too; the device and the bus add a nearly
constant part. The virtual ODrive takes the mean of a transaction from a cited measurement
of the Python client on a v3.x (``plant_*.toml``: usb_latency) and its spread and tail from
this file: a transaction costs the mean plus a draw of the host's cost less its mean
(:func:`leglib.device.virtual.transport.latency`). The load of the machine
at the time is recorded: the tail is the scheduler's, and grows with it.
"""

from __future__ import annotations

import asyncio
import json
import os
import platform
import sys
import threading
import time
from pathlib import Path

import numpy as np

QUANTILES = (0.0, 0.001, 0.01, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95, 0.98, 0.99, 0.995,
             0.999, 0.9999, 1.0)


class _EchoDevice:
    """A device for the client that answers at once (no model behind it)."""

    def __init__(self, raw_json: bytes, crc: int):
        from odrive.libodrive import DeviceType, DiscoveryInfo  # load time: the maintainer tool only
        self._raw, self._crc = raw_json, crc
        self.info = DiscoveryInfo(device_type=DeviceType.RUNTIME, serial_number="000000000000")
        self.interface = type("I", (), {"interface_type": 0})()
        self.hw_version = None
        self.on_disconnected = None

    async def connect(self, node_id=None, baudrate=None):
        return None

    async def get_json(self):
        return self._raw, self._crc

    async def get_json_id(self):
        return (self._crc << 16) | len(self._raw) & 0xFFFF

    async def read_endpoints(self, endpoint_ids, sizes, transient=False):
        return bytes(sum(sizes))


def measure(n: int) -> np.ndarray:
    """Per-read cost [s] of ``n`` reads through the client."""
    from odrive.runtime_device import RuntimeDevice  # load time: the maintainer tool only

    from ..wire import _crc16, _table_raw  # load time: the maintainer tool only
    raw, _ = _table_raw("0.5.6")
    loop = asyncio.new_event_loop()
    threading.Thread(target=loop.run_forever, daemon=True).start()
    device = _EchoDevice(raw, _crc16(raw))
    odrv = asyncio.run_coroutine_threadsafe(RuntimeDevice.from_device(device, json_cache=None), loop).result().sync_wrapper
    for _ in range(1000):
        odrv.axis0.encoder.pos_estimate
    out = np.empty(n)
    clock = time.perf_counter_ns
    for i in range(n):
        t0 = clock()
        odrv.axis0.encoder.pos_estimate
        out[i] = clock() - t0
    loop.call_soon_threadsafe(loop.stop)
    return out * 1e-9


def main(argv):
    n = int(argv[0]) if argv else 20000
    costs = measure(n)
    mean = float(np.mean(costs))
    q = np.quantile(costs, QUANTILES)
    data = {
        "_comment": "the odrive Python client's cost per transaction on the host: the spread and tail of the "
                    "virtual ODrive's USB latency (measure_client.py)",
        "method": "odrive 0.6.11 RuntimeDevice/SyncObject over a device answering at once; "
                  f"{n} timed reads of a float after 1000 of warm-up (time.perf_counter_ns)",
        "host": f"{platform.python_implementation()} {platform.python_version()}, {platform.machine()}, "
                f"{platform.system()} {platform.release()}",
        "date": time.strftime("%Y-%m-%d"),
        "load_average_1_5_15min": [round(x, 2) for x in os.getloadavg()],
        "cpus": os.cpu_count(),
        "n": n,
        "mean_s": mean,
        "std_s": float(np.std(costs)),
        "quantiles": list(QUANTILES),
        "seconds": [float(x) for x in q],
    }
    out = Path(__file__).parent / "usb_client_latency.json"
    out.write_text(json.dumps(data, indent=1) + "\n")
    print(f"{out.name}: mean {mean * 1e6:.1f} us, median {q[8] * 1e6:.1f} us, p99 {q[15] * 1e6:.0f} us, "
          f"p99.9 {q[17] * 1e6:.0f} us, max {q[-1] * 1e6:.0f} us (load {os.getloadavg()[0]:.1f})")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
