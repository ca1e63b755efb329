"""The real ODrive on USB: ``odrive.find_any`` on a worker thread, with a timeout.
"""

from __future__ import annotations

import threading

from ..errors import DeviceNotFoundError


def _find_usb(timeout: float, serial_number: str | None):
    try:
        import odrive  # load time: the odrive client (needs libusb), only on USB
    except Exception as exc:  # the native part needs libusb-1.0
        raise DeviceNotFoundError(f"cannot import the odrive package ({exc}); on Debian install "
                                  f"libusb-1.0-0") from exc
    result: dict = {}

    def worker():
        try:
            kwargs = {"timeout": timeout}
            if serial_number:
                kwargs["serial_number"] = serial_number
            result["odrv"] = odrive.find_any(**kwargs)
        except BaseException as exc:  # noqa: BLE001 - reported to the caller below
            result["error"] = exc

    # ipykernel 7 + find_any on the kernel's thread hangs a live JupyterLab kernel: run it
    # on a worker thread and give up ourselves after the timeout.
    th = threading.Thread(target=worker, name="odrive-find-any", daemon=True)
    th.start()
    th.join(timeout + 2.0)
    if "odrv" in result and result["odrv"] is not None:
        return result["odrv"]
    err = result.get("error")
    detail = f" ({type(err).__name__}: {err})" if err is not None else ""
    raise DeviceNotFoundError(f"no ODrive answered on USB within {timeout:g} s{detail}. Check power, "
                              f"the cable, USB permissions (udev rules) and that no other program "
                              f"(odrivetool) holds the device.")
