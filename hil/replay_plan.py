"""What a replay runs: the log's vehicle profile and configs, which service drives each device,
the ``--set`` overrides, and the private run directory the services are started from.

A log says everything about its run: ``vehicle.toml`` and ``config/<service>.toml`` are
attachments, and every tapped device has a ``RAW.<device>`` channel. A service *claims* a
device when its driver says it uses it (the driver's ``used_devices``: its ``device``
setting, default the service's name; a PWM servo service one device per channel), or when
the device has the service's own name. The device's recorded address is its ``[devices.NAME]
address`` in the log's profile; the replay gives the device a ``mock+`` address of the same
kind and changes nothing else. Claims and addresses come from the one resolver of a profile's
devices (:func:`u2sa_hw.profile.devices.resolve_devices`, reading the recorded profile's data).

Each device must be claimed by exactly one service of the profile; a device nobody claims
is left out (and said so), two claimants are an error.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tomli_w

from u2sa_hw.config.fields import ConfigError, parse_text
from u2sa_hw.ports.address import DeviceAddress
from u2sa_hw.ports.kinds import PORT_KINDS
from u2sa_hw.recording.log_reader import LogFile, LogSummary
from u2sa_hw.profile.devices import resolve_devices
from u2sa_hw.registry import resolve_kind

from u2sa_hw.hil.replay_cut import autonomy_armed_at_start, i2c_setup_recorded, identity_register, service_kind

RAW_KINDS = {"RawSerial": "serial", "RawCanFrame": "can", "RawI2c": "i2c", "RawGpioEdge": "gpio",
             "RawGpioWrite": "gpio", "RawGpioClockRead": "gpio", "RawPwmWrite": "pwm"}
# device kinds with a replay device: the port kinds whose replay part names one (u2sa_hw.ports.kinds)
REPLAYABLE = frozenset(name for name, kind in PORT_KINDS.items() if kind.replay)
OUTPUT_TAPPED = {"gpio", "pwm"}   # kinds whose driver's outputs are its raw taps: record_raw stays on in a replay


HEALTH_INTERVAL_S = 0.2


class ReplayError(ValueError):
    """A log cannot be replayed as asked; the message names the file or service and the fix."""


@dataclass
class DevicePlan:
    """One device seen in the log."""

    name: str
    kind: str                      # serial, can, i2c, gpio, pwm
    records: int
    service: str = ""              # the service that claims it ("" when none)
    types: set[str] = field(default_factory=set)   # raw record types in the log (RawGpioEdge, ...)
    address: DeviceAddress | None = None   # the recorded (real) address, when the profile gives one


@dataclass
class ServicePlan:
    """One service the replay starts, with the config it is started with."""

    name: str
    kind: str
    config: dict[str, Any]
    devices: list[str] = field(default_factory=list)
    overrides: dict[str, Any] = field(default_factory=dict)


@dataclass
class ReplayPlan:
    """Everything decided before anything starts."""

    log: Path
    summary: LogSummary
    vehicle: dict[str, Any]                        # the [vehicle] table of the log's profile
    services: dict[str, ServicePlan]
    devices: dict[str, DevicePlan]
    notes: list[str] = field(default_factory=list)  # what is left out, and why
    # The rest of the log's profile, written into the replay's profile but never started: the
    # RC mux checks its [safety] table against every service's actuators, and its pre-arm checks
    # judge the other services by their health, which the replay republishes from the log.
    safety: dict[str, Any] = field(default_factory=dict)
    others: dict[str, dict[str, Any]] = field(default_factory=dict)   # name -> kind, enabled, required, config
    start_ns: int = 0                              # the replayed window, log time (ns)
    end_ns: int = 0

    def held_windows(self) -> dict[str, list[Any]]:
        """service -> where the recording machine held it up (hil/held_up.py): what differs
        there, ``--compare`` reports as a note."""
        from u2sa_hw.hil.held_up import plan_windows

        gpio = {d.name: d.service for d in self.devices.values() if d.service and d.kind == "gpio"}
        return plan_windows(self.log, kinds={name: sp.kind for name, sp in self.services.items()}, devices=gpio,
                            start_ns=self.start_ns, end_ns=self.end_ns)

    @property
    def duration_s(self) -> float:
        """Seconds of log time replayed."""
        return max(0.0, (self.end_ns - self.start_ns) / 1e9)


def _toml(data: bytes, where: str) -> dict[str, Any]:
    try:
        return tomllib.loads(data.decode())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ReplayError(f"{where} is not valid TOML ({exc})") from None


def read_profile(log: LogFile, vehicle: Path | None) -> tuple[dict[str, Any], dict[str, dict[str, Any]]]:
    """The profile (as a TOML dict) and each service's effective config (profile settings, then its file).

    With *vehicle*, that profile and its config files are used instead of the log's attachments.
    """
    attachments = log.contents.attachments
    if vehicle is not None:
        try:
            profile = _toml(vehicle.read_bytes(), str(vehicle))
        except OSError as exc:
            raise ReplayError(f"{vehicle}: cannot read ({exc.strerror})") from None
        from u2sa_hw.profile.vehicle import ProfileError
        from u2sa_hw.profile.loader import load_profile

        try:
            parsed = load_profile(vehicle)
        except ProfileError as exc:
            raise ReplayError(str(exc)) from None
        files = {n: s.config_path.read_bytes() for n, s in parsed.services.items() if s.config_path.exists()}
    elif "vehicle.toml" in attachments:
        profile = _toml(attachments["vehicle.toml"], f"{log.path}: attachment vehicle.toml")
        files = {name[len("config/"):-len(".toml")]: data for name, data in attachments.items()
                 if name.startswith("config/") and name.endswith(".toml")}
    else:
        raise ReplayError(f"{log.path}: the log carries no vehicle.toml (it was recorded without a vehicle "
                          "profile), so replay cannot tell which service drives each device; give the profile "
                          "with --vehicle FILE")
    configs: dict[str, dict[str, Any]] = {}
    for name, table in (profile.get("services") or {}).items():
        if not isinstance(table, dict):
            continue
        settings = table.get("settings") if isinstance(table.get("settings"), dict) else {}
        config = dict(settings)
        if name in files:
            config.update(_toml(files[name], f"{log.path}: config of service '{name}'"))
        configs[name] = config
    return profile, configs


def parse_overrides(items: list[str]) -> dict[str, dict[str, str]]:
    """``["gps.uere_m=9", ...]`` -> ``{"gps": {"uere_m": "9"}}``; ReplayError on a malformed item."""
    out: dict[str, dict[str, str]] = {}
    for item in items:
        target, sep, text = item.partition("=")
        service, dot, name = target.strip().partition(".")
        if not sep or not dot or not service or not name:
            raise ReplayError(f"--set {item!r}: expected SERVICE.FIELD=VALUE, e.g. --set gps.uere_m=9")
        out.setdefault(service, {})[name] = text.strip()
    return out


def typed_overrides(service: str, kind: str, texts: dict[str, str]) -> dict[str, Any]:
    """The override texts of *service* parsed with its kind's declared field types."""
    try:
        fields = {f.name: f for f in resolve_kind(kind).config_fields()}
    except (LookupError, ImportError) as exc:
        raise ReplayError(f"service '{service}': cannot load kind '{kind}' ({exc})") from None
    values: dict[str, Any] = {}
    for name, text in texts.items():
        f = fields.get(name)
        if f is None:
            raise ReplayError(f"--set {service}.{name}: '{kind}' has no config field '{name}' "
                              f"(fields: {', '.join(sorted(fields))})")
        try:
            values[name] = parse_text(f, text)
        except ConfigError as exc:
            raise ReplayError(f"--set {service}.{name}={text}: {exc}") from None
    return values


def build_plan(path: Path | str, *, extra_services: list[str] = (), overrides: list[str] = (),
               start_s: float = 0.0, end_s: float | None = None, vehicle: Path | str | None = None) -> ReplayPlan:
    """Read the log once and decide what to replay (ReplayError says why something cannot be)."""
    from u2sa_hw.recording.log_reader import LogError

    try:
        log = LogFile(path)
    except LogError as exc:
        raise ReplayError(str(exc)) from None
    summary = log.scan()
    if log.contents.problem:
        raise ReplayError(f"{log.path}: {log.contents.problem}; repair it first with "
                          f"u2sa log recover {log.path}, then replay the recovered file")
    if not summary.messages:
        raise ReplayError(f"{log.path}: the log holds no messages; nothing to replay")
    profile, configs = read_profile(log, Path(vehicle) if vehicle else None)
    services_table = profile.get("services") or {}
    devices: dict[str, DevicePlan] = {}
    for ch in summary.channels:
        if not ch.channel.startswith("RAW."):
            continue
        name = ch.channel[4:]
        kind = RAW_KINDS.get(ch.type_name, "")
        dev = devices.get(name)
        if dev is None:
            dev = devices[name] = DevicePlan(name, kind, ch.count)
        else:
            dev.records += ch.count
            dev.kind = dev.kind or kind
        dev.types.add(ch.type_name)
    plan = ReplayPlan(Path(path), summary, dict(profile.get("vehicle") or {}), {}, devices)
    # the one resolver of a profile's devices, reading the recorded profile (claims, addresses) leniently
    resolved = resolve_devices(profile, configs=configs, strict=False)
    blocked: set[str] = set()   # services that drive a device replay cannot stand in for
    for dev in devices.values():
        owners = list(resolved.users.get(dev.name, ()))
        if len(owners) > 1:
            raise ReplayError(f"{log.path}: device '{dev.name}' is claimed by services {', '.join(owners)}; "
                              "give each service its own device (device = \"...\")")
        if not owners:
            plan.notes.append(f"RAW.{dev.name}: no service of the profile names device '{dev.name}' "
                              "(as its name, its device setting or a channel's device); not replayed")
            continue
        entry = resolved.entries.get(dev.name)   # None: no address, or one that does not parse
        dev.address = entry.address if entry is not None else None
        if dev.kind not in REPLAYABLE:
            what = f"{dev.kind} devices cannot be replayed yet" if dev.kind else "unknown raw type"
            plan.notes.append(f"RAW.{dev.name}: {what}; service '{owners[0]}' is not replayed")
            blocked.add(owners[0])
            continue
        if dev.kind == "i2c" and not i2c_setup_recorded(log, dev.name,
                                                        identity_register=identity_register(services_table, owners[0])):
            plan.notes.append(f"RAW.{dev.name}: the recording began after '{owners[0]}' set its chip up, or inside "
                              "that set-up (the log lacks its identification, and so its configuration and "
                              f"calibration samples), so what it published depends on what came before the cut; service "
                              f"'{owners[0]}' is not replayed and its messages are not compared")
            blocked.add(owners[0])
            continue
        if dev.kind == "gpio" and service_kind(services_table, owners[0]) == "rc_mux" and autonomy_armed_at_start(
                log, owners[0], start_ns=summary.start_ns + int(max(0.0, start_s) * 1e9)):
            plan.notes.append(f"RAW.{dev.name}: the recording began with '{owners[0]}' armed in autonomous mode (the "
                              "pilot armed it through manual, and it judged the services' health, before the cut): "
                              "a replayed mux never saw that and could not grant autonomy, so what follows from it "
                              f"(its enable line, every actuator's output) would differ; service '{owners[0]}' is not "
                              "replayed and its messages are not compared; the actuators get its recorded RC_MODE")
            blocked.add(owners[0])
            continue
        dev.service = owners[0]
    for dev in devices.values():
        if dev.service in blocked:
            plan.notes.append(f"RAW.{dev.name}: its service '{dev.service}' also drives a device that cannot be "
                              "replayed; not replayed")
            dev.service = ""
        elif dev.service:
            _add_service(plan, dev.service, services_table, configs).devices.append(dev.name)
    for name in extra_services:
        if name not in services_table:
            raise ReplayError(f"--services {name}: the log's profile has no service '{name}' "
                              f"(services: {', '.join(services_table) or 'none'})")
        _add_service(plan, name, services_table, configs)
    for service, texts in parse_overrides(list(overrides)).items():
        sp = plan.services.get(service)
        if sp is None:
            raise ReplayError(f"--set {service}.…: service '{service}' is not replayed "
                              f"(replayed: {', '.join(plan.services) or 'none'}; add it with --services)")
        sp.overrides = typed_overrides(service, sp.kind, texts)
    if not plan.services:
        raise ReplayError(f"{log.path}: nothing to replay: no RAW.<device> channel belongs to a service of the "
                          "profile (record with record_raw = true in the driver configs) and no --services given")
    plan.safety = dict(profile.get("safety") or {})
    for name, table in services_table.items():
        if name not in plan.services and isinstance(table, dict) and isinstance(table.get("kind"), str):
            plan.others[name] = {"kind": table["kind"], "enabled": table.get("enabled", True) is not False,
                                 "required": table.get("required", True) is not False,
                                 "config": dict(configs.get(name, {}))}
    first, last = summary.start_ns, summary.end_ns
    plan.start_ns = first + int(max(0.0, start_s) * 1e9)
    plan.end_ns = last if end_s is None else min(last, first + int(end_s * 1e9))
    if plan.end_ns <= plan.start_ns:
        raise ReplayError(f"--start {start_s:g} / --end {end_s}: empty window; the log lasts "
                          f"{summary.duration_s:.1f} s")
    return plan


def _add_service(plan: ReplayPlan, name: str, table: dict[str, Any], configs: dict[str, dict[str, Any]]) -> ServicePlan:
    sp = plan.services.get(name)
    if sp is None:
        kind = table[name].get("kind") if isinstance(table.get(name), dict) else None
        if not isinstance(kind, str) or not kind:
            raise ReplayError(f"{plan.log}: service '{name}' in the log's profile has no kind")
        sp = plan.services[name] = ServicePlan(name, kind, dict(configs.get(name, {})))
    return sp


def write_run_profile(plan: ReplayPlan, run_dir: Path, *, lcm_url: str,
                      changes: dict[str, dict[str, Any]], addresses: dict[str, str] | None = None) -> Path:
    """Write ``vehicle.toml`` and ``config/<service>.toml`` for the replay into *run_dir*.

    Each config is the recorded one with ``record_raw`` off (on for GPIO and PWM drivers, whose
    taps are their outputs), the ``--set`` overrides, and then *changes* (what a replay device
    needs besides its address, e.g. a faster rate). *addresses* (device -> replay address) become
    the profile's ``[devices.NAME] address`` tables, which win over any address in a service's
    settings, so no override moves a device back to real hardware; the profile points every
    directory into *run_dir* and the LCM URL at the private replay bus.
    """
    (run_dir / "config").mkdir(parents=True, exist_ok=True)
    vehicle = {**plan.vehicle, "lcm_url": lcm_url, "config_dir": "config", "log_dir": "logs", "data_dir": "data"}
    services: dict[str, Any] = {}
    for name, sp in plan.services.items():
        # health often, so the replay learns quickly that a driver has opened its device
        config = {**sp.config, "health_interval_s": HEALTH_INTERVAL_S}
        if "record_raw" in declared_fields(sp.kind):
            # the replay's input is the log, re-tapping it only doubles the traffic; but a GPIO or PWM
            # driver's outputs are its taps (RawGpioWrite, RawPwmWrite), which --compare compares
            config["record_raw"] = any(plan.devices[d].kind in OUTPUT_TAPPED for d in sp.devices)
        config.update(sp.overrides)
        config.update(changes.get(name, {}))   # last: a device address always points at the replay device
        (run_dir / "config" / f"{name}.toml").write_text(tomli_w.dumps(config))
        services[name] = {"kind": sp.kind, "config": f"config/{name}.toml"}
    for name, other in plan.others.items():   # listed as recorded, never started (see ReplayPlan.others)
        (run_dir / "config" / f"{name}.toml").write_text(tomli_w.dumps(other["config"]))
        services[name] = {"kind": other["kind"], "config": f"config/{name}.toml", "enabled": other["enabled"],
                          "required": other["required"]}
    path = run_dir / "vehicle.toml"
    devices = {name: {"address": address} for name, address in (addresses or {}).items()}
    path.write_text(tomli_w.dumps({"vehicle": vehicle, "services": services,
                                   **({"devices": devices} if devices else {}),
                                   **({"safety": plan.safety} if plan.safety else {})}))
    return path


def declared_fields(kind: str) -> set[str]:
    """The config field names service kind *kind* declares (empty when it cannot be loaded)."""
    try:
        return {f.name for f in resolve_kind(kind).config_fields()}
    except (LookupError, ImportError):
        return set()
