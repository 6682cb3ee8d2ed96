"""What install makes of a real serial address: the udev rule that names its USB adapter ``/dev/u2sa/NAME``.

A real serial address whose path is ``/dev/u2sa/NAME`` and which carries the adapter's USB
identity (``usb=VID:PID`` and/or ``serial=SERIALNO``) gets one line in
``65-u2sa-vehicle.rules`` that makes the link. One without an identity must be made by a rule
the user installed (``u2sa check`` says so with the line to add, and install refuses it
without ``--force``: the service would wait for a device node that never appears). A pyserial
URL needs nothing. :func:`u2sa_hw.install.udev.plan_devices` calls :func:`plan_device` for
each real serial address; *fail* builds its error (an ``InstallError`` naming the line).
"""

from __future__ import annotations

import re
from typing import TYPE_CHECKING, Any, Callable, Collection

if TYPE_CHECKING:
    from u2sa_hw.ports.address import DeviceAddress

U2SA_DEV = "/dev/u2sa/"
_LINK_NAME = re.compile(r"^[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*$")
_HEX4 = re.compile(r"^[0-9a-f]{4}$")
_RULE_VALUE = re.compile(r'^[^"\n\\*?\[\]|]*$')   # no quote, newline, escape or udev glob


def rule_value(text: str, what: str, fail: Callable[[str], Exception]) -> str:
    """*text* when it can go into a udev rule as *what*'s value, else ``fail(problem)``."""
    if not _RULE_VALUE.match(text):
        raise fail(f"{what} {text!r} cannot go into a udev rule (quotes, backslashes and "
                   "glob characters * ? [ ] | are not allowed)")
    return text


def serial_rule(link: str, vendor: str | None, product: str | None, serial: str | None) -> str:
    """The rule line that makes ``/dev/<link>`` for the USB serial adapter *vendor*:*product* and/or *serial*."""
    match = ['SUBSYSTEM=="tty"']
    if vendor and product:
        match += [f'ATTRS{{idVendor}}=="{vendor}"', f'ATTRS{{idProduct}}=="{product}"']
    if serial:
        match.append(f'ATTRS{{serial}}=="{serial}"')
    return ", ".join(match) + f', SYMLINK+="{link}", GROUP="dialout", MODE="0660"'


def plan_device(plan: Any, name: str, address: DeviceAddress, *, service: str | None, elsewhere: Collection[str],
                fail: Callable[[str], Exception]) -> None:
    """Add to *plan* (a ``DevicePlan``) the rule line of device *name*'s real serial *address*, or note its
    ``/dev/u2sa`` link as unmade when nothing identifies the adapter and no rule in *elsewhere* makes it."""
    if address.is_serial_url:
        return
    path = address.serial_path
    if not path.startswith(U2SA_DEV):
        return
    link = path[len("/dev/"):]
    if not _LINK_NAME.match(link[len("u2sa/"):]):
        raise fail(f"{path} cannot be a udev link; name it /dev/u2sa/NAME with letters, digits, '_', '.' and '-'")
    usb, serial = address.usb_id, address.usb_serial
    if usb is None and not serial:
        if link not in elsewhere:
            plan.unmade.append((name, path))
        return
    vendor, product = usb or (None, None)
    if usb is not None and not (_HEX4.match(vendor) and _HEX4.match(product)):
        raise fail(f"usb={vendor}:{product} must be two 4-digit hex ids, e.g. usb=1546:01a7")
    plan.rule_lines.append(serial_rule(link, vendor, product, rule_value(serial, "serial", fail) if serial else None))
