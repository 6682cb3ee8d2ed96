"""What ``u2sa check --probe`` looks at: one :class:`Target` per device of each enabled service.

A target is the port kind, the address text shown, the parameters the probe opens it with,
and what the service's driver expects there (the protocol of a serial device, the chip
behind an I2C address, the CAN node ids). Where each device is comes from its address
(:func:`u2sa_hw.devices.profile_devices`); what the driver expects there from the service
kind (``EXPECT``: a compass's ``format``, an MPU's ``chip``, the CAN node ids). A profile
whose device addresses cannot be listed (reported by the offline check) falls back to the
service settings of the old form (``KIND_TARGETS``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

from u2sa_hw.ports.pwm_port import is_real_sysfs

PCA9685_PREFIX = "pca9685:"


@dataclass(frozen=True)
class Target:
    """One device to probe."""

    name: str
    service: str
    port: str                 # serial, i2c, can, gpio, pwm
    address: str              # as the line shows it
    params: Mapping[str, Any] = field(default_factory=dict)


def _lines(text: Any) -> list[int]:
    """The line numbers of a ``name=line,...`` value."""
    found = []
    for item in str(text or "").split(","):
        _name, sep, line = item.partition("=")
        if sep and line.strip().isdigit():
            found.append(int(line))
    return found


def _serial(name: str, kind: str, cfg: Mapping[str, Any]) -> list[Target]:
    protocol = "OS5000" if kind == "compass_serial" and str(cfg.get("format", "")).lower() == "os5000" else "NMEA"
    path, baud = str(cfg["port"]), int(cfg["baudrate"])
    return [Target(name, name, "serial", f"{path}?baud={baud}", {"path": path, "baud": baud, "protocol": protocol})]


def _imu(name: str, kind: str, cfg: Mapping[str, Any]) -> list[Target]:
    chip = "bno055" if kind == "imu_bno055" else "mpu"
    bus, address = str(cfg["bus"]), int(cfg["address"])
    params = {"bus": bus, "address": address, "chip": chip, "variant": str(cfg.get("chip", "auto"))}
    return [Target(name, name, "i2c", f"{bus}/0x{address:02x}", params)]


def _pwm(name: str, kind: str, cfg: Mapping[str, Any]) -> list[Target]:
    targets, seen = [], set()
    for index, table in enumerate(cfg.get("channels", [])):
        if not isinstance(table, dict):
            continue
        address = str(table.get("address", ""))
        label = f"{name}.{table.get('name', index)}"
        if address.startswith(PCA9685_PREFIX):
            bus, _, chip = address[len(PCA9685_PREFIX):].rpartition(":")
            key = (bus, chip)
            if key not in seen:
                seen.add(key)
                targets.append(Target(label, name, "i2c", f"{bus}/{chip}",
                                      {"bus": bus, "address": int(chip, 0), "chip": "pca9685"}))
        elif address:
            channel = int(table.get("channel", 0))
            targets.append(Target(label, name, "pwm", f"{address}/{channel}", {"chip": address, "channel": channel,
                                                                                "real": is_real_sysfs(address)}))
    return targets


def _gpio(name: str, kind: str, cfg: Mapping[str, Any]) -> list[Target]:
    if kind == "rc_mux":
        lines = _lines(cfg.get("channels")) + [int(cfg[k]) for k in ("enable_line", "select_line")
                                               if isinstance(cfg.get(k), int) and cfg[k] >= 0]
    else:
        lines = _lines(cfg.get("outputs" if kind == "gpio_output" else "inputs"))
    chip = str(cfg["chip"])
    return [Target(name, name, "gpio", f"{chip}/{','.join(map(str, lines))}", {"chip": chip, "lines": lines})]


def _can(name: str, kind: str, cfg: Mapping[str, Any]) -> list[Target]:
    interface, channel = str(cfg["interface"]), str(cfg["channel"])
    options = {"port": int(cfg["udp_port"])} if interface == "udp_multicast" and cfg.get("udp_port") else {}
    odrive = kind == "odrive_can"
    protocol, ids = ("odrive", cfg.get("node_ids", [])) if odrive else ("vesc", cfg.get("controller_ids", []))
    return [Target(name, name, "can", f"{interface}/{channel}", {"interface": interface, "channel": channel,
                                                                 "bus_options": options, "protocol": protocol,
                                                                 "nodes": list(ids)})]


KIND_TARGETS: dict[str, Callable[[str, str, Mapping[str, Any]], list[Target]]] = {
    "gps_nmea": _serial, "compass_serial": _serial, "imu_mpu9250": _imu, "imu_bno055": _imu, "pwm_servo": _pwm,
    "rc_mux": _gpio, "gpio_input": _gpio, "gpio_output": _gpio, "odrive_can": _can, "vesc_can": _can,
}


def expectation(kind: str, cfg: Mapping[str, Any]) -> dict[str, Any]:
    """What the driver of *kind* expects at its device, from its effective config *cfg*."""
    if kind in ("gps_nmea", "compass_serial"):
        os5000 = kind == "compass_serial" and str(cfg.get("format", "")).lower() == "os5000"
        return {"protocol": "OS5000" if os5000 else "NMEA"}
    if kind in ("imu_mpu9250", "imu_bno055"):
        return {"chip": "bno055" if kind == "imu_bno055" else "mpu", "variant": str(cfg.get("chip", "auto"))}
    if kind == "pwm_servo":
        return {"chip": "pca9685"}
    if kind in ("odrive_can", "vesc_can"):
        ids = cfg.get("node_ids" if kind == "odrive_can" else "controller_ids", [])
        return {"protocol": "odrive" if kind == "odrive_can" else "vesc", "nodes": list(ids)}
    return {}


def _from_address(name: str, service: str, address: Any, expect: Mapping[str, Any]) -> Target | None:
    kind = address.kind
    if kind == "serial":
        return Target(name, service, "serial", address.url, {"path": address.serial_path, "baud": address.baud,
                                                             "protocol": expect.get("protocol")})
    if kind in ("i2c", "pca9685"):
        chip = "pca9685" if kind == "pca9685" else expect.get("chip", "mpu")
        return Target(name, service, "i2c", address.url, {"bus": address.i2c_bus, "address": address.chip_address,
                                                          "chip": chip, "variant": expect.get("variant", "auto")})
    if kind == "can":
        return Target(name, service, "can", address.url, {"interface": address.can_interface,
                                                          "channel": address.can_channel,
                                                          "bus_options": address.bus_options, **expect})
    if kind == "gpio":
        return Target(name, service, "gpio", address.url, {"chip": address.gpio_chip, "lines": list(address.lines)})
    if kind == "pwm":
        return Target(name, service, "pwm", address.url, {"chip": address.pwm_chip, "channel": address.pwm_channel})
    return None


def profile_targets(profile: Any) -> list[Target]:
    """Every device of every enabled service of *profile* that a probe knows how to look at."""
    from u2sa_hw.devices import effective_config, profile_devices
    from u2sa_hw.vehicle import ProfileError

    try:
        entries = profile_devices(profile, warn=lambda _text: None)
    except ProfileError:
        return _legacy_targets(profile)
    targets, seen = [], set()
    for entry in entries.values():
        spec = profile.services.get(entry.service)
        if spec is None or not spec.enabled:
            continue
        address = entry.address
        if address.kind == "pca9685":   # one identity read per chip, whatever the number of channels on it
            key = (address.i2c_bus, address.chip_address)
            if key in seen:
                continue
            seen.add(key)
        target = _from_address(entry.name, entry.service, address,
                               expectation(spec.kind, effective_config(profile, entry.service)))
        if target is not None:
            targets.append(target)
    return targets


def _legacy_targets(profile: Any) -> list[Target]:
    from u2sa_hw.devices import effective_config

    targets = []
    for name, spec in profile.services.items():
        build = KIND_TARGETS.get(spec.kind)
        if spec.enabled and build is not None:
            targets.extend(build(name, spec.kind, effective_config(profile, name)))
    return targets
