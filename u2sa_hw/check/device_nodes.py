"""The host's serial device nodes: what creates each ``/dev/u2sa/NAME`` link, and adapters told apart.

On the vehicle (the default) a ``/dev/u2sa/NAME`` serial path must be created by something:
a USB id or serial number in the device's address (``u2sa install`` writes the udev rule
from it) or an installed udev rule that makes that link; otherwise the service would wait
for a device node that never appears, and the check prints the rule line to add. Two such
devices whose USB identities do not tell their adapters apart (the same ``usb=VID:PID`` and
no ``serial=`` on one of them, or the same ``serial=``) are an error: both udev rules would
match one adapter, and a link could point at the other device.

These checks are for the vehicle only (not *for_sim*: a simulation's devices are mocks).
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any, Iterable, Mapping

from u2sa_hw.check.problem import Collector

UDEV_RULES_DIRS = (Path("/etc/udev/rules.d"), Path("/run/udev/rules.d"), Path("/lib/udev/rules.d"),
                   Path("/usr/lib/udev/rules.d"))
UDEV_DIRS_ENV = "U2SA_UDEV_RULES_DIRS"   # colon-separated directories instead of the above (tests, staged roots)
U2SA_DEV = "/dev/u2sa/"


def serial_devices(profile: Any, entries: Mapping[str, Any] | None = None) -> list[tuple[str, str, Any]]:
    """``(device name, key, address)`` of every real serial device node of the enabled services
    (*entries*: the profile's device list when already read)."""
    from u2sa_hw.profile.devices import profile_devices

    if entries is None:
        try:
            entries = profile_devices(profile)
        except ValueError:   # ProfileError or a service's ConfigError:
            return []   # reported by the address check (u2sa_hw.check.device_checks)
    found = []
    for name, entry in entries.items():
        spec = profile.services.get(entry.service)
        address = entry.address
        if spec is not None and spec.enabled and address.kind == "serial" and not address.mock \
                and not address.is_serial_url:
            key = f"devices.{name}.address"
            found.append((name, key, address))
    return found


def rules_dirs() -> list[Path]:
    """Where installed udev rules live (``$U2SA_UDEV_RULES_DIRS`` overrides it)."""
    env = os.environ.get(UDEV_DIRS_ENV)
    return [Path(p) for p in env.split(":") if p] if env is not None else list(UDEV_RULES_DIRS)


def rule_creates(link: str, dirs: Iterable[Path]) -> Path | None:
    """The installed rules file with a ``SYMLINK+="<link>"`` for *link* (e.g. ``u2sa/gps``), or None."""
    pattern = re.compile(r'SYMLINK\+?=\s*"([^"]*)"')
    for directory in dirs:
        try:
            files = sorted(directory.glob("*.rules"))
        except OSError:
            continue
        for file in files:
            try:
                text = file.read_text(errors="replace")
            except OSError:
                continue
            for line in text.splitlines():
                if line.lstrip().startswith("#"):
                    continue
                for match in pattern.finditer(line):
                    if link in match.group(1).split():
                        return file
    return None


def udev_line(link: str) -> str:
    """The udev rule line that creates ``/dev/<link>`` for one USB serial adapter (values to fill in)."""
    return (f'SUBSYSTEM=="tty", ATTRS{{idVendor}}=="VVVV", ATTRS{{idProduct}}=="PPPP", '
            f'ATTRS{{serial}}=="SERIAL", SYMLINK+="{link}"')


def check_device_nodes(entries: Mapping[str, Any], profile: Any, out: Collector) -> None:
    """Each ``/dev/u2sa/NAME`` path is created by the address's USB identity or an installed udev rule."""
    dirs = rules_dirs()
    for name, key, address in serial_devices(profile, entries):
        path = address.serial_path
        if not path.startswith(U2SA_DEV):
            continue
        link = path[len("/dev/"):]
        if address.usb_id or address.usb_serial or rule_creates(link, dirs):
            continue
        out.error(key, f"nothing creates {path}: the address has no USB id or serial number and no installed "
                  "udev rule makes that link",
                  f"give the address the adapter's identity, e.g. {address.url}{'&' if '?' in address.url else '?'}"
                  f"usb=VID:PID&serial=SERIAL (u2sa install writes the rule), or add to "
                  f"/etc/udev/rules.d/66-u2sa-local.rules (install rewrites 65-u2sa-vehicle.rules): {udev_line(link)} "
                  "(udevadm info -a -n /dev/ttyUSB0 shows the values)")


SERIAL_NUMBER_HOW = "udevadm info -q property -n /dev/ttyUSB0 | grep ID_SERIAL_SHORT"


def may_be_one_adapter(a: Any, b: Any) -> bool:
    """Whether the udev rules of serial addresses *a* and *b* can both match one adapter: neither their USB
    ids nor their serial numbers tell them apart (one with only ``usb=`` and one with only ``serial=``
    cannot be judged, and are not)."""
    if a.usb_id and b.usb_id and a.usb_id != b.usb_id:
        return False
    if a.usb_serial and b.usb_serial and a.usb_serial != b.usb_serial:
        return False
    if (a.usb_id is None) != (b.usb_id is None) and (a.usb_serial is None) != (b.usb_serial is None):
        return False   # usb= only against serial= only: whether they are one make is not known here
    return True


def identity_text(address: Any) -> str:
    """An address's USB identity as its parameters: ``usb=VID:PID&serial=SERIAL`` (what it has of them)."""
    parts = [f"usb={':'.join(address.usb_id)}"] if address.usb_id else []
    parts += [f"serial={address.usb_serial}"] if address.usb_serial else []
    return "&".join(parts)


def check_usb_identities(entries: Mapping[str, Any], out: Collector) -> None:
    """Two ``/dev/u2sa`` serial devices whose USB identities (``usb=VID:PID``, ``serial=``) do not tell their
    adapters apart: install writes a rule for each (whatever service uses it), both rules match one adapter,
    and either link may then point at the other device (a compass read as the GPS)."""
    found: list[tuple[str, Any]] = []
    for name, entry in entries.items():
        address = entry.address
        if address.kind == "serial" and not address.mock and not address.is_serial_url \
                and address.serial_path.startswith(U2SA_DEV) and (address.usb_id or address.usb_serial):
            found.append((name, address))
    reported: set[str] = set()
    for i, (name, address) in enumerate(found):
        if name in reported:
            continue
        group = [(name, address)] + [(n, a) for n, a in found[i + 1:]
                                     if n not in reported and may_be_one_adapter(address, a)]
        if len(group) < 2:
            continue
        reported.update(n for n, _ in group)
        names = [n for n, _ in group]
        listed = ", ".join(f"'{n}' ({identity_text(a)})" for n, a in group[:-1]) + f" and '{group[-1][0]}' " \
            f"({identity_text(group[-1][1])})"
        links = " and ".join(a.serial_path for _, a in group)
        bare = [n for n, a in group if not a.usb_serial]
        example = next(a for n, a in group if n == (bare or names)[0])
        how = (f"add &serial=SERIAL to the address of {' and '.join(repr(n) for n in bare)}" if bare else
               f"set serial= of {' and '.join(repr(n) for n in names)} to the serial number of each one's own "
               "adapter (one serial number is one adapter)")
        at = (bare or names)[-1]   # the line is on a device to change
        entry = entries[at]
        key = f"devices.{at}.address"
        out.error(key, f"devices {listed} have USB identities that do not tell their adapters apart: the udev "
                  f"rules install writes for {links} {'both' if len(group) == 2 else 'all'} match one adapter, so "
                  f"{'either' if len(group) == 2 else 'any'} link may point at the wrong device",
                  f"give each its adapter's own serial number: {how}, e.g. "
                  f"{example.with_params(serial='SERIAL').url} (the serial of the adapter plugged in as "
                  f"/dev/ttyUSB0: {SERIAL_NUMBER_HOW})")
