"""One error hierarchy for every port kind (DESIGN.md section 4).

Every error names the device (its configured name and address) and, where one is known,
the fix, so a service's log and health say what to do: ``PortError`` is the root;
``PortUnavailable`` (cannot open: missing, permission, busy), ``PortClosed`` (the device
went away while open: unplug, pty closed, bus down), ``PortTimeout`` (no answer in time)
and ``PortIOError`` (a transaction failed: I2C NACK, EIO) refine it.
"""

from __future__ import annotations


class PortError(Exception):
    """A port failed; ``device`` is its name, ``address`` its address, ``fix`` the advice."""

    def __init__(self, device: str, message: str, *, address: str = "", fix: str = "") -> None:
        self.device = device
        self.address = address
        self.fix = fix
        where = f"{device} ({address})" if address and address != device else device
        text = f"{where}: {message}"
        if fix:
            text += f"; fix: {fix}"
        super().__init__(text)


class PortUnavailable(PortError):
    """The device cannot be opened (missing, no permission, busy, wrong address)."""


class PortClosed(PortError):
    """The device went away while open (unplugged, pty closed, bus down)."""


class PortTimeout(PortError):
    """The device did not answer in time."""


class PortIOError(PortError):
    """A transaction failed on an open device (I2C NACK, EIO, CAN error frame)."""


def fix_for_errno(errno_value: int | None, path: str) -> str:
    """Advice for a common open() failure on a device node."""
    import errno

    if errno_value == errno.ENOENT:
        return (f"{path} does not exist: check the cable, the udev rule, or the device's address "
                "([devices.NAME] address in the vehicle profile)")
    if errno_value in (errno.EACCES, errno.EPERM):
        return f"no permission on {path}: add the service user to the device's group (u2sa install does this)"
    if errno_value == errno.EBUSY:
        return f"{path} is in use by another process: stop it (fuser {path})"
    return "check the device and its address ([devices.NAME] address in the vehicle profile)"
