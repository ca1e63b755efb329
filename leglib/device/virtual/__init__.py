"""The virtual ODrive v3.6: firmware 0.5.6 or 0.5.1 over the twin, served to the ``odrive``
client.

- :mod:`~leglib.device.virtual.firmware`: what the firmware does (states, calibration as
  motion, the watchdog, save and reboot, the DC bus, errors) over a batch of one of
  :class:`leglib.twin.host.Twin`, with :mod:`~leglib.device.virtual.board` (the v3.6 56 V
  board), :mod:`~leglib.device.virtual.readings` and
  :mod:`~leglib.device.virtual.procedures` (the axis thread's procedures);
- :mod:`~leglib.device.virtual.tree`: its object tree with the firmware's endpoint names,
  built from a table of one row per endpoint (``firmware.ENDPOINTS``) and, for every other
  endpoint of the firmware's table, :mod:`~leglib.device.virtual.catalog`;
- :mod:`~leglib.device.virtual.wire`: the endpoint ids of the firmware's own tables
  (:mod:`~leglib.device.virtual.tables`) answered to the installed ``odrive`` client, so
  :func:`find_any` gives the same kind of object as ``odrive.find_any()``.
"""

from __future__ import annotations

from .firmware import FIRMWARES, VirtualODrive
from .wire import device_of, find_any, forget

__all__ = ["FIRMWARES", "VirtualODrive", "find_any", "device_of", "forget"]
