"""What a USB transaction costs the host on the virtual ODrive's clock.

The ODrive's protocol (fibre's legacy protocol of firmware 0.5.x) is one request-response
per endpoint (legacy_protocol.cpp:456-497): a property read or write is one transaction, a
function call one per input argument, one for the trigger and one per output
(legacy_object_client.cpp:668-685); the wire counts them (:mod:`.wire`).

One transaction's cost: its mean is a cited measurement of the Python client on an ODrive
v3.x -- ``plant.usb_latency``, 0.36 ms: 4 x 200 reads with odrive's Python library took
0.353-0.366 ms each on average (discourse.odriverobotics.com/t/decreasing-latency/1463,
2018) -- and its spread and tail are the host's: the odrive 0.6.11 client's own cost per
transaction measured here (``tables/usb_client_latency.json``, ``measure_client.py``: the
method, the host and its load). A transaction costs the mean plus ``plant.usb_jitter``
times a draw of the host's cost less its mean (1: the measured spread and tail; 0: a
constant latency).
"""

from __future__ import annotations

import functools
import json
from importlib import resources

import numpy as np


@functools.lru_cache(maxsize=1)
def client_cost() -> dict:
    """The measured host cost per transaction (``tables/usb_client_latency.json``)."""
    raw = resources.files("leglib.device.virtual.tables").joinpath("usb_client_latency.json").read_text()
    data = json.loads(raw)
    data["quantiles"] = np.asarray(data["quantiles"], float)
    data["seconds"] = np.asarray(data["seconds"], float)
    return data


def latency(mean: float, jitter: float, u: float) -> float:
    """One transaction's latency [s] for the uniform draw ``u`` in [0, 1): ``mean`` plus
    ``jitter`` times the host's cost at quantile ``u`` less its mean (never negative)."""
    if jitter == 0.0:
        return mean
    c = client_cost()
    host = float(np.interp(u, c["quantiles"], c["seconds"]))
    return max(mean + jitter * (host - c["mean_s"]), 0.0)
