"""What install makes of the profile's device addresses: udev rules, CAN bring-up, sysfs PWM drop-ins.

Only device addresses are read (:func:`u2sa_hw.profile.devices.profile_devices`), never a driver's
setting names:

- a real serial address whose path is ``/dev/u2sa/NAME`` and which carries the adapter's USB
  identity (``usb=VID:PID`` and/or ``serial=SERIALNO``) gets one line in
  ``65-u2sa-vehicle.rules`` that makes the link; one without an identity must be made by a
  rule the user installed (``u2sa check`` says so with the line to add, and install refuses
  it without ``--force``: the service would wait for a device node that never appears);
- a real SocketCAN address with ``bitrate=`` gets a line that sets ``U2SA_CAN_BITRATE`` for
  that interface, which ``70-u2sa-can.rules`` applies (``ip link set ... bitrate``, then up)
  whenever the interface appears, at boot and on replug (docs/deployment.md says why udev and
  not systemd-networkd);
- a real sysfs PWM address makes its service's unit a ``50-pwm-sysfs.conf`` drop-in.

Mock addresses (``mock+...``) need nothing on the vehicle and are skipped.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Mapping

from u2sa_hw.profile.devices import DeviceEntry
from u2sa_hw.install.system import InstallError

U2SA_DEV = "/dev/u2sa/"
VEHICLE_RULES = "65-u2sa-vehicle.rules"
LOCAL_RULES = "66-u2sa-local.rules"
_LINK_NAME = re.compile(r"^[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*$")
_HEX4 = re.compile(r"^[0-9a-f]{4}$")
_CAN = re.compile(r"^can[0-9]+$")
_RULE_VALUE = re.compile(r'^[^"\n\\*?\[\]|]*$')   # no quote, newline, escape or udev glob


@dataclass
class DevicePlan:
    """What the device addresses ask install for; *unmade* are ``/dev/u2sa`` links nothing creates."""

    rule_lines: list[str] = field(default_factory=list)
    can_channels: dict[str, int] = field(default_factory=dict)       # interface -> bitrate
    can_without_bitrate: list[str] = field(default_factory=list)     # "device (canN)": left as configured
    pwm_services: dict[str, str] = field(default_factory=dict)       # service -> sysfs chip
    unmade: list[tuple[str, str]] = field(default_factory=list)      # (device, /dev/u2sa/NAME)


def _value(text: str, where: str, what: str) -> str:
    if not _RULE_VALUE.match(text):
        raise InstallError(f"{where}: {what} {text!r} cannot go into a udev rule (quotes, backslashes and "
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


def plan_devices(devices: Mapping[str, DeviceEntry], *, profile_path: Path | str,
                 made_elsewhere: Iterable[str] = ()) -> DevicePlan:
    """The rules, CAN bitrates and PWM drop-ins the real addresses of *devices* need.

    *made_elsewhere*: links (``u2sa/gps``) that an installed rule of the user's already makes.
    """
    plan = DevicePlan()
    elsewhere = set(made_elsewhere)
    for name, entry in sorted(devices.items()):
        address = entry.address
        if address.mock:
            continue
        where = f"{profile_path} [devices.{name}] address"
        if address.kind == "serial" and not address.is_serial_url:
            path = address.serial_path
            if not path.startswith(U2SA_DEV):
                continue
            link = path[len("/dev/"):]
            if not _LINK_NAME.match(link[len("u2sa/"):]):
                raise InstallError(f"{where}: {path} cannot be a udev link; name it /dev/u2sa/NAME with letters, "
                                   "digits, '_', '.' and '-'")
            usb, serial = address.usb_id, address.usb_serial
            if usb is None and not serial:
                if link not in elsewhere:
                    plan.unmade.append((name, path))
                continue
            vendor, product = usb or (None, None)
            if usb is not None and not (_HEX4.match(vendor) and _HEX4.match(product)):
                raise InstallError(f"{where}: usb={vendor}:{product} must be two 4-digit hex ids, e.g. usb=1546:01a7")
            plan.rule_lines.append(serial_rule(link, vendor, product,
                                               _value(serial, where, "serial") if serial else None))
        elif address.kind == "can" and address.can_interface == "socketcan":
            channel = address.can_channel
            if not _CAN.match(channel):
                raise InstallError(f"{where}: SocketCAN interface {channel!r}: install brings up only canN "
                                   "interfaces; rename it or bring it up yourself")
            bitrate = address.bitrate
            if bitrate is None:
                plan.can_without_bitrate.append(f"{name} ({channel})")
                continue
            if not 0 < bitrate <= 8_000_000:
                raise InstallError(f"{where}: bitrate={bitrate} is not a CAN bitrate (bit/s, e.g. 500000)")
            if plan.can_channels.get(channel, bitrate) != bitrate:
                raise InstallError(f"{where}: {channel} at {bitrate} bit/s, but another device has it at "
                                   f"{plan.can_channels[channel]}; one interface has one bitrate")
            plan.can_channels[channel] = bitrate
        elif address.kind == "pwm" and entry.service:
            plan.pwm_services.setdefault(entry.service, address.pwm_chip)
    for channel, bitrate in sorted(plan.can_channels.items()):
        plan.rule_lines.append(f'SUBSYSTEM=="net", KERNEL=="{channel}", ENV{{U2SA_CAN_BITRATE}}="{bitrate}"')
    return plan


def render_rules(plan: DevicePlan, *, profile: str) -> bytes:
    """``65-u2sa-vehicle.rules``: a header, then the plan's lines."""
    lines = [f"# Generated by `u2sa install` from {profile}: do not edit. Edit the device",
             "# addresses in the profile ([devices.NAME] address, usb=VID:PID&serial=... for a serial",
             "# adapter, bitrate=... for CAN) and install again, or write your own rules in another",
             f"# file, e.g. {LOCAL_RULES}, which install never touches. See docs/deployment.md.",
             *plan.rule_lines]
    return ("\n".join(lines) + "\n").encode()


def links_made(rules_dirs: Iterable[Path], *, skip: str = VEHICLE_RULES) -> set[str]:
    """The ``/dev`` links (``u2sa/gps``) that installed rules files other than *skip* make with SYMLINK+=."""
    pattern = re.compile(r'SYMLINK\+?=\s*"([^"]*)"')
    found: set[str] = set()
    for directory in rules_dirs:
        for file in sorted(directory.glob("*.rules")) if directory.is_dir() else ():
            if file.name == skip:
                continue
            try:
                text = file.read_text(errors="replace")
            except OSError:
                continue   # unreadable: udev reads it as root, but we cannot tell what it makes
            for line in text.splitlines():
                if not line.lstrip().startswith("#"):
                    found.update(link for m in pattern.finditer(line) for link in m.group(1).split())
    return found


def unmade_text(plan: DevicePlan) -> list[str]:
    """One line per ``/dev/u2sa`` link nothing creates, with the rule line to add."""
    return [f"device '{name}': nothing creates {path} (its address has no usb=VID:PID or serial= and no "
            f"installed rule makes it); add usb=VID:PID&serial=SERIALNO to the address, or to /etc/udev/rules.d/{LOCAL_RULES}: "
            f"{serial_rule(path[len('/dev/'):], 'VVVV', 'PPPP', 'SERIAL')} (udevadm info -a -n /dev/ttyUSB0 "
            "shows the values)" for name, path in plan.unmade]
