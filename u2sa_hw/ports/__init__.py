"""Ports: the one seam between drivers and hardware (DESIGN.md section 4).

Drivers never open ``/dev/...`` themselves; they ask this package for a port by the
device's address (``address``: one URL per device, real or mock; ``opener.open_port``
opens it through its kind, one line of the table in ``kinds``; ``device_link.DeviceLink`` is
the lifecycle a driver holds). Each port kind is a package (``serial``, ``can``, ``i2c``,
``gpio``, ``pwm``) implementing ``port_kind.PortKind``. See ``errors`` for the one error
hierarchy and ``tap`` for how raw I/O is published for recording and replay.

The openers are imported on first use (``from u2sa_hw.ports import open_serial``), so a
service pays for pyserial or python-can only when it opens such a port.
"""

from __future__ import annotations

import importlib
from typing import Any

from u2sa_hw.ports.errors import PortClosed, PortError, PortIOError, PortTimeout, PortUnavailable

# public name -> module that defines it, imported lazily by __getattr__
_LAZY = {
    "open_serial": "u2sa_hw.ports.serial.opener",
    "SerialPort": "u2sa_hw.ports.serial.port",
    "open_can": "u2sa_hw.ports.can.port",
    "CanPort": "u2sa_hw.ports.can.port",
    "open_pwm": "u2sa_hw.ports.pwm.port",
    "PwmChannel": "u2sa_hw.ports.pwm.port",
    "SysfsPwmChannel": "u2sa_hw.ports.pwm.port",
    "make_sysfs_pwm_tree": "u2sa_hw.ports.pwm.port",
    "ReconnectingPort": "u2sa_hw.ports.reconnect",
    "open_port": "u2sa_hw.ports.opener",
    "PORT_KINDS": "u2sa_hw.ports.kinds",
    "PortKind": "u2sa_hw.ports.port_kind",
    "parse_address": "u2sa_hw.ports.address",
    "make_address": "u2sa_hw.ports.address",
    "DeviceAddress": "u2sa_hw.ports.address",
    "AddressError": "u2sa_hw.ports.address",
    "DeviceLink": "u2sa_hw.ports.device_link",
}

__all__ = ["PortError", "PortUnavailable", "PortClosed", "PortTimeout", "PortIOError", *_LAZY]


def __getattr__(name: str) -> Any:
    """Import the module behind a lazily exported name on first access."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value
