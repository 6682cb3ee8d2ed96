"""What ``u2sa install`` deploys from the project and the profile: units, rules, configs.

- The unit files of ``systemd/`` (template, target, HSM, multicast oneshot) go to
  ``/etc/systemd/system``; the rules of ``udev/`` to ``/etc/udev/rules.d``.
- Each enabled service of the profile becomes ``u2sa@NAME.service``, wanted by
  ``u2sa.target``; the service of kind ``hsm`` (it must be called ``hsm``) becomes
  ``u2sa-hsm.service``, which may restart the others.
- Drop-ins by what a service is, whatever its name: every service of kind ``recorder``
  gets ``u2sa@NAME.service.d/10-recorder.conf`` (lower CPU and I/O priority, a longer
  stop), every service that drives PWM through sysfs ``50-pwm-sysfs.conf``.
- The profile is installed as ``/etc/u2sa/vehicle.toml`` with its directories pointed at
  the vehicle's (``/etc/u2sa/config``, ``/var/log/u2sa``, ``/var/lib/u2sa``) and every
  service config as ``/etc/u2sa/config/NAME.toml``.
- ``65-u2sa-vehicle.rules`` is generated from the profile's ``[devices.NAME]`` tables:
  ``usb = { vendor = "1546", product = "01a7", serial = "...", interface = "00" }``
  makes ``/dev/u2sa/NAME``; ``can = { channel = "can0", bitrate = 500000 }`` sets the
  bitrate that ``70-u2sa-can.rules`` brings the interface up at.
"""

from __future__ import annotations

import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tomli_w

from u2sa_hw.install.system import DEVICE_GROUPS, SERVICE_USER, InstallError
from u2sa_hw.registry import RECORDER_KIND
from u2sa_hw.transport import DEFAULT_RECV_BUF_SIZE
from u2sa_hw.vehicle import ServiceSpec, VehicleProfile

UNIT_DIR = "/etc/systemd/system"
UDEV_DIR = "/etc/udev/rules.d"
ETC_DIR = "/etc/u2sa"
CONFIG_DIR = "/etc/u2sa/config"
PROFILE = "/etc/u2sa/vehicle.toml"
LOG_DIR = "/var/log/u2sa"
STATE_DIR = "/var/lib/u2sa"
DOC = "/opt/u2sa/doc/deployment.md"
SYSUSERS = "/etc/sysusers.d/u2sa.conf"
TMPFILES = "/etc/tmpfiles.d/u2sa.conf"
SYSCTL = "/etc/sysctl.d/60-u2sa-lcm.conf"
HSM_LOG = "/var/log/u2sa/hsm.log"
LOG_DIR_MODE = 0o770
VEHICLE_RULES = "65-u2sa-vehicle.rules"
TARGET = "u2sa.target"
TEMPLATE = "u2sa@.service"
HSM_UNIT = "u2sa-hsm.service"
HSM_KIND = "hsm"
HSM_NAME = "hsm"

_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")
_HEX4 = re.compile(r"^[0-9a-fA-F]{4}$")
_CAN = re.compile(r"^can[0-9]+$")
_RULE_VALUE = re.compile(r'^[^"\n\\]*$')


@dataclass(frozen=True)
class ServiceUnit:
    """A profile service and the unit that runs it."""

    name: str
    unit: str
    template: str  # the unit file the wants symlink points at


def service_units(profile: VehicleProfile) -> list[ServiceUnit]:
    """The unit of each enabled service of *profile*; InstallError on a name systemd cannot take."""
    units = []
    for spec in profile.services.values():
        if not spec.enabled:
            continue
        units.append(_unit_for(spec, profile))
    return units


def _unit_for(spec: ServiceSpec, profile: VehicleProfile) -> ServiceUnit:
    where = f"{profile.path} [services.{spec.name}]"
    if spec.kind == HSM_KIND:
        if spec.name != HSM_NAME:
            raise InstallError(f"{where}: the HSM runs as u2sa-hsm.service under the name '{HSM_NAME}'; "
                               f"rename the table to [services.{HSM_NAME}]")
        return ServiceUnit(spec.name, HSM_UNIT, HSM_UNIT)
    if not _NAME.match(spec.name):
        raise InstallError(f"{where}: service name '{spec.name}' cannot be a unit instance; use letters, "
                           "digits, '_', '.' and '-' only")
    return ServiceUnit(spec.name, f"u2sa@{spec.name}.service", TEMPLATE)


RECORDER_DROPIN = """\
# Written by `u2sa install`: {name} is a recorder (kind "recorder"). Recordings go to the
# profile's data_dir, /var/lib/u2sa/recordings on the vehicle (StateDirectory= of the
# template, writable under ProtectSystem=strict; a `directory` elsewhere needs its own
# drop-in with ReadWritePaths=). Disk I/O and CPU yield to the services that drive the vehicle.
[Service]
Nice=5
IOSchedulingClass=best-effort
IOSchedulingPriority=7
# Stopping closes the current file (summary and index): a large last chunk may need more
# than the template's 5 s.
TimeoutStopSec=15s
"""

PWM_SYSFS = "/sys/class/pwm"
PWM_DROPIN = """\
# Written by `u2sa install`: this service drives PWM through sysfs ({path}), whose files
# udev gives to group gpio (60-u2sa-permissions.rules). The template's
# ProtectKernelTunables=yes makes all of /sys read-only, so it is off for this unit only.
[Service]
ProtectKernelTunables=no
"""


def _strings(value: Any) -> list[str]:
    if isinstance(value, str):
        return [value]
    if isinstance(value, dict):
        return [s for v in value.values() for s in _strings(v)]
    if isinstance(value, list):
        return [s for v in value for s in _strings(v)]
    return []


AFTER_RECORDER_DROPIN = """\
# Written by `u2sa install`: the vehicle has a recorder, so {name} starts once the recorder
# is ready (READY=1 after it subscribed): the recording then holds this service's start-up
# I/O (an IMU's identification reads, a motor controller's arming), which replay needs.
# u2sa run does the same. Only ordering: a recorder that fails to start holds nobody back.
[Unit]
After={recorders}
"""


def unit_dropins(profile: VehicleProfile) -> dict[str, bytes]:
    """Per-service drop-ins the profile calls for: a recorder's priorities, the others ordered after it,
    sysfs PWM's writable /sys."""
    dropins = {}
    units = service_units(profile)
    recorders = [u.unit for u in units if profile.services[u.name].kind == RECORDER_KIND]
    for unit in units:
        spec = profile.services[unit.name]
        if spec.kind == RECORDER_KIND:
            dropins[f"{UNIT_DIR}/{unit.unit}.d/10-recorder.conf"] = RECORDER_DROPIN.format(name=unit.unit).encode()
        elif recorders:
            dropins[f"{UNIT_DIR}/{unit.unit}.d/20-after-recorder.conf"] = AFTER_RECORDER_DROPIN.format(
                name=unit.unit, recorders=" ".join(recorders)).encode()
        pwm = [s for s in _strings(spec.settings) if s.startswith(PWM_SYSFS)]
        if pwm and unit.unit != HSM_UNIT:
            dropins[f"{UNIT_DIR}/{unit.unit}.d/50-pwm-sysfs.conf"] = PWM_DROPIN.format(path=pwm[0]).encode()
    return dropins


def unit_sources(source: Path) -> dict[str, bytes]:
    """Every file under the project's ``systemd/``, keyed by its path in /etc/systemd/system."""
    base = source / "systemd"
    return {f"{UNIT_DIR}/{p.relative_to(base)}": p.read_bytes()
            for p in sorted(base.rglob("*")) if p.is_file()}


def udev_sources(source: Path) -> dict[str, bytes]:
    """The project's ``udev/*.rules``, keyed by their path in /etc/udev/rules.d."""
    return {f"{UDEV_DIR}/{p.name}": p.read_bytes() for p in sorted((source / "udev").glob("*.rules"))}


def wants_links(units: list[ServiceUnit]) -> dict[str, str]:
    """The enable symlinks (what ``systemctl enable`` would make): path -> target."""
    links = {f"{UNIT_DIR}/multi-user.target.wants/{TARGET}": f"{UNIT_DIR}/{TARGET}"}
    for u in units:
        links[f"{UNIT_DIR}/{TARGET}.wants/{u.unit}"] = f"{UNIT_DIR}/{u.template}"
    return links


def render_profile(profile: VehicleProfile) -> bytes:
    """The profile as installed: same content, directories pointed at the vehicle's."""
    assert profile.path is not None
    data: dict[str, Any] = tomllib.loads(profile.path.read_text())
    vehicle = data.setdefault("vehicle", {})
    vehicle.update(config_dir=CONFIG_DIR, log_dir=LOG_DIR, data_dir=STATE_DIR)
    for table in data.get("services", {}).values():
        if isinstance(table, dict):
            table.pop("config", None)  # every config is <config_dir>/<name>.toml on the vehicle
    header = (f"# Vehicle profile installed by `u2sa install` from {profile.path.resolve()}.\n"
              "# Edit it here if you like: install never overwrites a profile or config you changed\n"
              "# (a newer default lands beside it as vehicle.toml.new). Directories point at the\n"
              f"# vehicle's: configs {CONFIG_DIR}, logs {LOG_DIR}, data {STATE_DIR}.\n\n")
    return (header + tomli_w.dumps(data)).encode()


def service_configs(profile: VehicleProfile) -> dict[str, bytes]:
    """Each service config file that exists next to the profile, keyed by its vehicle path."""
    configs = {}
    for spec in profile.services.values():
        if spec.config_path.is_file():
            data = spec.config_path.read_bytes()
            try:
                tomllib.loads(data.decode())
            except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
                raise InstallError(f"{spec.config_path}: config of service '{spec.name}' is not valid TOML "
                                   f"({exc}); fix it before installing") from None
            configs[f"{CONFIG_DIR}/{spec.name}.toml"] = data
    return configs


def sysusers_conf() -> bytes:
    """systemd-sysusers declaration of the service user and device groups (for images and packages)."""
    lines = ["# u2sa-hw: the service user and the device groups (written by u2sa install).",
             *(f"g {g} -" for g in DEVICE_GROUPS),
             f'u {SERVICE_USER} - "U2SA vehicle services" {STATE_DIR} /usr/sbin/nologin',
             *(f"m {SERVICE_USER} {g}" for g in DEVICE_GROUPS)]
    return ("\n".join(lines) + "\n").encode()


def tmpfiles_conf() -> bytes:
    """systemd-tmpfiles declaration of the log directory, made (again) before any unit starts.

    Shared by the services (User=u2sa, its LogsDirectory=) and the HSM (uid 0, group u2sa,
    which may not declare it: systemd would chown it to root at each HSM start).
    """
    return (f"# u2sa-hw: the services' and the HSM's log directory (written by u2sa install).\n"
            f"d {LOG_DIR} {LOG_DIR_MODE:04o} {SERVICE_USER} {SERVICE_USER} -\n").encode()


def sysctl_conf() -> bytes:
    """The kernel's cap on a socket's receive buffer, raised so LCM's receive buffers get what they ask for.

    u2sa's transport asks for a 4 MiB UDP receive buffer (``recv_buf_size``); the kernel
    grants at most ``net.core.rmem_max``, 208 KiB by default, which a burst at 20,000 msg/s
    overflows in a few milliseconds (LCM's own setup guide recommends raising it).
    """
    return ("# u2sa-hw: let LCM's UDP receive buffers grow to 4 MiB (written by u2sa install;\n"
            "# see docs/deployment.md). The default cap, 208 KiB, drops packets in bursts.\n"
            f"net.core.rmem_max = {DEFAULT_RECV_BUF_SIZE}\n").encode()


def _rule_value(value: Any, where: str, *, pattern: re.Pattern[str] = _RULE_VALUE, hint: str = "") -> str:
    if not isinstance(value, (str, int)) or isinstance(value, bool) or not pattern.match(str(value)):
        raise InstallError(f"{where}: {value!r} is not usable in a udev rule{hint}")
    return str(value)


def render_vehicle_rules(profile: VehicleProfile) -> bytes:
    """``65-u2sa-vehicle.rules`` from the profile's ``[devices.NAME]`` usb/can tables."""
    lines = [f"# Generated by `u2sa install` from {PROFILE}: do not edit, edit the profile's",
             "# [devices.NAME] tables and install again (or write your own rules in another file,",
             "# e.g. 66-u2sa-local.rules, which install never touches). See docs/deployment.md."]
    for name, table in sorted(profile.devices.items()):
        where = f"{profile.path} [devices.{name}]"
        usb, can = table.get("usb"), table.get("can")
        if usb is not None:
            if not isinstance(usb, dict):
                raise InstallError(f'{where}: usb must be a table like usb = {{ vendor = "1546", product = "01a7" }}')
            _rule_value(name, where, pattern=_NAME, hint=" as /dev/u2sa/NAME; use letters, digits, '_', '.', '-'")
            vendor = _rule_value(usb.get("vendor"), f"{where} usb.vendor", pattern=_HEX4,
                                 hint=' (4 hex digits, e.g. "1546")')
            product = _rule_value(usb.get("product"), f"{where} usb.product", pattern=_HEX4,
                                  hint=' (4 hex digits, e.g. "01a7")')
            match = ['SUBSYSTEM=="tty"', f'ATTRS{{idVendor}}=="{vendor.lower()}"',
                     f'ATTRS{{idProduct}}=="{product.lower()}"']
            if "serial" in usb:
                match.append(f'ATTRS{{serial}}=="{_rule_value(usb["serial"], f"{where} usb.serial")}"')
            if "interface" in usb:
                match.append(f'ATTRS{{bInterfaceNumber}}=="{_rule_value(usb["interface"], f"{where} usb.interface")}"')
            lines.append(", ".join(match) + f', SYMLINK+="u2sa/{name}", GROUP="dialout", MODE="0660"')
        if can is not None:
            if not isinstance(can, dict):
                raise InstallError(f'{where}: can must be a table like can = {{ channel = "can0", bitrate = 500000 }}')
            channel = _rule_value(can.get("channel"), f"{where} can.channel", pattern=_CAN, hint=" (canN)")
            bitrate = can.get("bitrate")
            if not isinstance(bitrate, int) or isinstance(bitrate, bool) or not 0 < bitrate <= 8_000_000:
                raise InstallError(f"{where}: can.bitrate must be an integer in bit/s, e.g. 500000; got {bitrate!r}")
            lines.append(f'SUBSYSTEM=="net", KERNEL=="{channel}", ENV{{U2SA_CAN_BITRATE}}="{bitrate}"')
    return ("\n".join(lines) + "\n").encode()
