"""What ``u2sa check --probe`` looks at: one :class:`Target` per device of each enabled service.

A target is the port kind, the address text shown, the parameters the probe opens it with,
and what the service's driver expects there (the protocol of a serial device, the chip
behind an I2C address, the CAN node ids). Where each device is comes from its address
(:func:`u2sa_hw.devices.profile_devices`); what the driver expects there, the driver declares
(:func:`expectation`: its ``probe_expectation``, :mod:`u2sa_hw.ports.declared`): a protocol,
a chip family and variant, the CAN node ids. Nothing here reads a driver's setting names.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping


@dataclass(frozen=True)
class Target:
    """One device to probe."""

    name: str
    service: str
    port: str                 # serial, i2c, can, gpio, pwm
    address: str              # as the line shows it
    params: Mapping[str, Any] = field(default_factory=dict)


def expectation(kind: str, cfg: Mapping[str, Any]) -> dict[str, Any]:
    """What the driver of *kind* expects at its device, from its effective config *cfg*, as the driver
    declares it (``protocol``, ``chip`` and ``variant``, ``nodes``); empty for a kind that declares nothing."""
    from u2sa_hw.ports.declared import declared_class, probe_expectation

    return probe_expectation(declared_class(kind), cfg)


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

    entries = profile_devices(profile, warn=lambda _text: None)   # ProfileError: see u2sa check (offline)
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
