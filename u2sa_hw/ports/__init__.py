"""Ports: the one seam between drivers and hardware (DESIGN.md section 4).

Drivers never open ``/dev/...`` themselves; they ask this package for a port by the
device address in their config, real or mock. See ``errors`` for the one error
hierarchy and ``tap`` for how raw I/O is published for recording and replay.
"""

from u2sa_hw.ports.errors import PortClosed, PortError, PortIOError, PortTimeout, PortUnavailable

__all__ = ["PortError", "PortUnavailable", "PortClosed", "PortTimeout", "PortIOError"]
