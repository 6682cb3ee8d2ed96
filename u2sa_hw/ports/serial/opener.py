"""``open_serial``: a serial device path or pyserial URL opened as a :class:`~u2sa_hw.ports.serial.port.SerialPort`.

A path opens with ``serial.Serial(..., exclusive=True)``, a URL with ``serial.serial_for_url``;
an address that says ``clock=stamped`` (a replay's pty) opens a
:class:`~u2sa_hw.ports.serial.clock.StampedSerialPort`. The two port classes live in their own
modules, and only this one chooses between them, so neither imports the other's chooser.
"""

from __future__ import annotations

import errno
import grp
import logging
import os

import serial

from u2sa_hw.ports.errors import PortUnavailable, fix_for_errno
from u2sa_hw.ports.serial.clock import StampedSerialPort
from u2sa_hw.ports.serial.port import SerialPort, is_serial_url
from u2sa_hw.ports.tap import Tap

log = logging.getLogger(__name__)

_BUSY_ERRNOS = {errno.EBUSY, errno.EAGAIN, errno.EWOULDBLOCK}


def _os_errno(exc: BaseException) -> int | None:
    """The errno behind a pyserial exception (pyserial often keeps it only in the context)."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        if isinstance(current, OSError) and isinstance(current.errno, int):
            return current.errno
        current = current.__cause__ or current.__context__
    return None


def _group_fix(path: str) -> str:
    """Advice for EACCES on *path*, naming the device node's group when it can be read."""
    try:
        group = grp.getgrgid(os.stat(path).st_gid).gr_name
    except (OSError, KeyError):
        return fix_for_errno(errno.EACCES, path)
    if group == "root":
        return (f"{path} belongs to group root: give it group 'dialout' with a udev rule "
                "(like udev/60-u2sa-permissions.rules, installed by u2sa install) and add the "
                "service user to that group")
    return (f"no permission on {path}: add the service user to group '{group}' "
            f"(usermod -aG {group} <user>; u2sa install does this)")


def _open_fix(address: str, exc: BaseException, *, pyserial_url: bool) -> str:
    """The advice for an open failure of *address* (a pyserial URL or a device path)."""
    code = _os_errno(exc)
    if pyserial_url:
        if isinstance(exc, ValueError):
            return ("the URL scheme or its options are not known to pyserial: use a device path "
                    "or loop://, socket://host:port, rfc2217://host:port, spy://<path>")
        if code == errno.ECONNREFUSED:
            return f"nothing listens at {address}: start the serial server (e.g. ser2net) or fix the URL"
        return f"check that {address} is reachable and the URL is right"
    if code in (errno.EACCES, errno.EPERM):
        return _group_fix(address)
    if code in _BUSY_ERRNOS:
        return f"{address} is in use by another process: stop it (fuser -v {address})"
    if code == errno.ENOENT and os.path.islink(address):
        return (f"{address} is a dangling symlink: the device (or the mock device's pty) is gone; "
                "plug it in / start the mock device, or fix the udev rule")
    return fix_for_errno(code, address)


def open_serial(address: str, *, device: str, baudrate: int = 9600, bytesize: int = 8, parity: str = "N",
                stopbits: float = 1, timeout: float = 0.1, tap: Tap | None = None,
                device_clock: bool = False, pyserial_url: bool | None = None) -> SerialPort:
    """Open the serial device at *address* (a path or a pyserial URL) as *device*.

    *pyserial_url*: *address* is a pyserial URL (from a parsed address: ``DeviceAddress.is_serial_url``);
    None decides it from the text (``scheme://``), for a caller that holds only the text.

    *device_clock*: the other end writes stamped frames (a replay's pty, ``clock=stamped`` on a
    ``mock+serial`` address; :mod:`u2sa_hw.ports.serial.clock`).

    Raises PortUnavailable naming the device, the address and the fix when it cannot be
    opened (missing, no permission, busy, unknown URL scheme).
    """
    url = is_serial_url(address) if pyserial_url is None else pyserial_url
    options = dict(baudrate=baudrate, bytesize=bytesize, parity=parity, stopbits=stopbits, timeout=timeout)
    try:
        if url:
            handle = serial.serial_for_url(address, **options)
        else:
            handle = serial.Serial(address, exclusive=True, **options)
    except (serial.SerialException, OSError, ValueError) as exc:
        code = _os_errno(exc)
        if isinstance(exc, ValueError) and not url:
            reason = f"bad serial settings ({exc})"
            fix = (f"check the framing in the service config: baudrate {baudrate!r} (e.g. 4800-115200), "
                   f"bytesize {bytesize!r} (5, 6, 7, 8), parity {parity!r} (N, E, O, M, S), "
                   f"stopbits {stopbits!r} (1, 1.5, 2)")
        else:
            reason = f"cannot open ({exc})"
            fix = _open_fix(address, exc, pyserial_url=url)
        if code in _BUSY_ERRNOS:
            reason = f"busy: another process holds it ({exc})"
        raise PortUnavailable(device, reason, address=address, fix=fix) from exc
    log.debug("%s: opened %s%s", device, address, " (stamped frames: device clock)" if device_clock else "")
    if device_clock:
        return StampedSerialPort(handle, device=device, address=address, tap=tap, timeout=timeout)
    return SerialPort(handle, device=device, address=address, tap=tap, pyserial_url=url)
