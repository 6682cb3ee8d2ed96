"""What ``u2sa install`` deploys from the project and the profile: units, rules, configs.

- The unit files of ``systemd/`` (template, target, HSM, multicast oneshot) go to
  ``/etc/systemd/system``; the rules of ``udev/`` to ``/etc/udev/rules.d``.
- Each enabled service of the profile becomes ``u2sa@NAME.service``, wanted by
  ``u2sa.target``; the service of kind ``hsm`` (it must be called ``hsm``) becomes
  ``u2sa-hsm.service``, which may restart the others.
- Drop-ins by what a service is, whatever its name: every service of kind ``recorder``
  gets ``u2sa@NAME.service.d/10-recorder.conf`` (lower CPU and I/O priority, a longer
  stop), every service whose device address is a sysfs PWM chip ``50-pwm-sysfs.conf``, every
  service of the safety chain ``30-realtime.conf`` (``CPUSchedulingPolicy=fifo``, the priority
  of :mod:`u2sa_hw.realtime`) and every command source ``31-command-source.conf``
  (``WatchdogSignal=SIGKILL``: never resumed to print stacks); the RC mux (kind ``rc_mux``)
  alone gets ``32-pilot-key.conf``: the group u2sa-pilot, so it reads /etc/u2sa/pilot.key,
  which the template and the HSM's unit make inaccessible to every other service.
- The profile is installed as ``/etc/u2sa/vehicle.toml`` with its directories pointed at
  the vehicle's (``/etc/u2sa/config``, ``/var/log/u2sa``, ``/var/lib/u2sa``) and every
  service config as ``/etc/u2sa/config/NAME.toml``.
- ``65-u2sa-vehicle.rules`` and the sysfs PWM drop-ins come from the device addresses
  (:mod:`u2sa_hw.install.udev`); the files the services' settings name (missions, objects)
  are found by :mod:`u2sa_hw.install.referenced`.
"""

from __future__ import annotations

import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import tomli_w

from u2sa_hw.bus.pilot import PILOT_GROUP
from u2sa_hw.install.system import DEVICE_GROUPS, SERVICE_USER, UNIT_ONLY_GROUPS, InstallError
from u2sa_hw.realtime import unit_directives
from u2sa_hw.registry import COMMAND_SOURCE_KINDS, RECORDER_KIND   # command sources: their watchdog kills
from u2sa_hw.bus.lcm_url import DEFAULT_RECV_BUF_SIZE
from u2sa_hw.profile.vehicle import ServiceSpec, VehicleProfile

UNIT_DIR = "/etc/systemd/system"
UDEV_DIR = "/etc/udev/rules.d"
ETC_DIR = "/etc/u2sa"
CONFIG_DIR = "/etc/u2sa/config"
PROFILE = "/etc/u2sa/vehicle.toml"
LOG_DIR = "/var/log/u2sa"
STATE_DIR = "/var/lib/u2sa"
HSM_STATE_DIR = "/var/lib/u2sa-hsm"   # u2sa-hsm.service's StateDirectory= (its saved signing time)
DOC = "/opt/u2sa/doc/deployment.md"
SYSUSERS = "/etc/sysusers.d/u2sa.conf"
TMPFILES = "/etc/tmpfiles.d/u2sa.conf"
SYSCTL = "/etc/sysctl.d/60-u2sa-lcm.conf"
HSM_LOG = "/var/log/u2sa/hsm.log"
LOG_DIR_MODE = 0o770
TARGET = "u2sa.target"
TEMPLATE = "u2sa@.service"
HSM_UNIT = "u2sa-hsm.service"
HSM_KIND = "hsm"
HSM_NAME = "hsm"

_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")


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

PWM_DROPIN = """\
# Written by `u2sa install`: this service drives PWM through sysfs ({path}), whose files
# udev gives to group gpio (60-u2sa-permissions.rules). The template's
# ProtectKernelTunables=yes makes all of /sys read-only, so it is off for this unit only.
[Service]
ProtectKernelTunables=no
"""


AFTER_RECORDER_DROPIN = """\
# Written by `u2sa install`: the vehicle has a recorder, so {name} starts once the recorder
# is ready (READY=1 after it subscribed): the recording then holds this service's start-up
# I/O (an IMU's identification reads, a motor controller's arming), which replay needs.
# u2sa run does the same. Only ordering: a recorder that fails to start holds nobody back.
[Unit]
After={recorders}
"""


REALTIME_DROPIN = """\
# Written by `u2sa install`: {name} is in the safety chain (kind "{kind}"), so it runs
# real-time (u2sa_hw/realtime.py; u2sa run does the same): a board saturated by normal work
# cannot delay it. Its threads inherit the policy (no CPUSchedulingResetOnFork=, which would
# put every thread the service starts back at normal priority). Kernel RT throttling
# (sched_rt_runtime_us) keeps 5 % of each CPU for normal tasks, systemd among them, so a
# service that spins is still killed by its watchdog. See docs/safety.md.
[Service]
{directives}"""

COMMAND_SOURCE_DROPIN = """\
# Written by `u2sa install`: {name} commands actuators (kind "{kind}"). A hang ends in
# SIGKILL, not the template's SIGABRT: systemd sends SIGCONT with SIGABRT, and a frozen
# command source resumed to print its stacks publishes commands again until it dies.
# The stack dump is lost; the journal still says "Watchdog timeout". See docs/safety.md.
[Service]
WatchdogSignal=SIGKILL
"""


PILOT_KIND = "rc_mux"   # the one service that signs the pilot's channels (RC_MODE, MANUAL_CMD)
PILOT_DROPIN_NAME = "32-pilot-key.conf"
PILOT_DROPIN = f"""\
# Written by `u2sa install`: {{name}} is the RC mux (kind "{PILOT_KIND}"), the only service that
# signs the pilot's channels (RC_MODE, MANUAL_CMD) with /etc/u2sa/pilot.key (root:{PILOT_GROUP}
# 0040). It alone gets the group {PILOT_GROUP}, added to the template's SupplementaryGroups=
# (a list: this adds, an empty assignment would reset it); the user u2sa is not a member.
# The template makes the key inaccessible to every service (InaccessiblePaths=); the empty
# assignment below resets that list for this unit only. See docs/security.md.
[Service]
SupplementaryGroups={PILOT_GROUP}
InaccessiblePaths=
"""


def pilot_dropins(unit: str, kind: str) -> dict[str, bytes]:
    """The drop-in that lets *unit* read the pilot's private key: only for the RC mux (kind ``rc_mux``)."""
    if kind != PILOT_KIND or unit == HSM_UNIT:
        return {}
    return {f"{UNIT_DIR}/{unit}.d/{PILOT_DROPIN_NAME}": PILOT_DROPIN.format(name=unit).encode()}


def safety_dropins(unit: str, kind: str) -> dict[str, bytes]:
    """The real-time and watchdog-signal drop-ins of *unit* running a service of *kind* (none for most kinds)."""
    dropins = {}
    directives = unit_directives(kind)
    if directives is not None:
        dropins[f"{UNIT_DIR}/{unit}.d/30-realtime.conf"] = REALTIME_DROPIN.format(
            name=unit, kind=kind, directives=directives).encode()
    if kind in COMMAND_SOURCE_KINDS:
        dropins[f"{UNIT_DIR}/{unit}.d/31-command-source.conf"] = COMMAND_SOURCE_DROPIN.format(
            name=unit, kind=kind).encode()
    return dropins


def unit_dropins(profile: VehicleProfile, *, pwm_services: Mapping[str, str]) -> dict[str, bytes]:
    """Per-service drop-ins the profile calls for: a recorder's priorities, the others ordered after it,
    a writable /sys for each service in *pwm_services* (service -> the sysfs PWM chip its address names),
    real-time priority for the safety chain and SIGKILL on a watchdog timeout for command sources, and the
    pilot's key for the RC mux."""
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
        dropins.update(safety_dropins(unit.unit, spec.kind))
        dropins.update(pilot_dropins(unit.unit, spec.kind))
        chip = pwm_services.get(unit.name)
        if chip and unit.unit != HSM_UNIT:
            dropins[f"{UNIT_DIR}/{unit.unit}.d/50-pwm-sysfs.conf"] = PWM_DROPIN.format(path=chip).encode()
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


CONFIG_DIR_NAME = "config"   # config_dir in the installed profile: /etc/u2sa/config, relative to it


def render_profile(profile: VehicleProfile, *, settings: Mapping[str, Mapping[str, str]] | None = None) -> bytes:
    """The profile as installed: same content, directories pointed at the vehicle's, and each setting
    in *settings* (service -> {setting: value}) naming its installed file.

    ``config_dir`` stays relative (``config``, i.e. /etc/u2sa/config) so that a staged tree is
    a profile that ``u2sa check`` reads as it will be on the vehicle; a ``bus_key`` path is
    dropped, since the vehicle's key is /etc/u2sa/bus.key (made by install or ``u2sa key import``).
    """
    assert profile.path is not None
    data: dict[str, Any] = tomllib.loads(profile.path.read_text())
    vehicle = data.setdefault("vehicle", {})
    vehicle.update(config_dir=CONFIG_DIR_NAME, log_dir=LOG_DIR, data_dir=STATE_DIR)
    vehicle.pop("bus_key", None)
    for name, table in data.get("services", {}).items():
        if isinstance(table, dict):
            table.pop("config", None)  # every config is <config_dir>/<name>.toml on the vehicle
            for key, value in (settings or {}).get(name, {}).items():
                table.setdefault("settings", {})[key] = value
    header = (f"# Vehicle profile installed by `u2sa install` from {profile.path.resolve()}.\n"
              "# Edit it here if you like: install never overwrites a profile or config you changed\n"
              "# (a newer default lands beside it as vehicle.toml.new). Directories point at the\n"
              f"# vehicle's: configs {CONFIG_DIR}, logs {LOG_DIR}, data {STATE_DIR}; files the\n"
              "# services name are beside this profile.\n\n")
    return (header + tomli_w.dumps(data)).encode()


def service_configs(profile: VehicleProfile, *, rewrites: Mapping[str, Mapping[str, str]] | None = None
                    ) -> dict[str, bytes]:
    """Each service config file that exists next to the profile, keyed by its vehicle path; a config with
    settings in *rewrites* (service -> {setting: value}) is rewritten to name the installed files.

    A config that is not TOML is the offline check's error (install refuses it without ``--force``);
    forced, it is installed as it is, and the service says what is wrong with it when it starts."""
    configs = {}
    for spec in profile.services.values():
        if spec.config_path.is_file():
            data = spec.config_path.read_bytes()
            try:
                table = tomllib.loads(data.decode())
            except (tomllib.TOMLDecodeError, UnicodeDecodeError):
                configs[f"{CONFIG_DIR}/{spec.name}.toml"] = data
                continue
            changes = {k: v for k, v in (rewrites or {}).get(spec.name, {}).items() if table.get(k) != v}
            if changes:
                table.update(changes)
                data = (f"# Config of {spec.name}, installed by `u2sa install` from {spec.config_path.resolve()}\n"
                        f"# ({', '.join(sorted(changes))} now naming the installed copies).\n\n"
                        + tomli_w.dumps(table)).encode()
            configs[f"{CONFIG_DIR}/{spec.name}.toml"] = data
    return configs


def sysusers_conf() -> bytes:
    """systemd-sysusers declaration of the service user, the device groups and u2sa-pilot (for images and packages).

    The user is a member of the device groups, not of u2sa-pilot (only the RC mux's unit gets it)."""
    lines = ["# u2sa-hw: the service user and the device groups (written by u2sa install); u2sa-pilot, the",
             "# group of /etc/u2sa/pilot.key, is the RC mux's unit's alone: u2sa is not a member.",
             *(f"g {g} -" for g in (*DEVICE_GROUPS, *UNIT_ONLY_GROUPS)),
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
