"""What ``u2sa check --probe`` looks at: one :class:`Target` per device of each enabled service.

A target is the port kind, the address text shown, the parameters the probe opens it with,
and what the service's driver expects there (the protocol of a serial device, the chip
behind an I2C address, the CAN node ids). Where each device is comes from its address
(:func:`u2sa_hw.profile.devices.profile_devices`); what the driver expects there, the driver declares
(:func:`expectation`: its ``probe_expectation``, :mod:`u2sa_hw.ports.declared`): a protocol,
a chip family and variant, the CAN node ids. Nothing here reads a driver's setting names.

Which probe looks at a device follows its address kind (:data:`TARGETS`: kind -> the target
of that kind's probe, in :data:`u2sa_hw.check.probe.PROBES`). A device whose kind has
neither is still a target, with no port (``port=""``): ``u2sa check --probe`` says "no
probe for kind X" on its line rather than leave it out unsaid. A new port kind adds its
entry here and its probe there (docs/ports.md, "A new port kind").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Mapping


@dataclass(frozen=True)
class Target:
    """One device to probe."""

    name: str
    service: str
    port: str                 # the probe that looks at it: serial, i2c, can, gpio, pwm ("": none)
    address: str              # as the line shows it
    params: Mapping[str, Any] = field(default_factory=dict)
    kind: str = ""            # the address kind (pca9685 for an i2c probe); "" when it is port


def expectation(kind: str, cfg: Mapping[str, Any]) -> dict[str, Any]:
    """What the driver of *kind* expects at its device, from its effective config *cfg*, as the driver
    declares it (``protocol``, ``chip`` and ``variant``, ``nodes``); empty for a kind that declares nothing."""
    from u2sa_hw.ports.declared import declared_class, probe_expectation

    return probe_expectation(declared_class(kind), cfg)


def _serial(name: str, service: str, address: Any, expect: Mapping[str, Any]) -> Target:
    return Target(name, service, "serial", address.url, {"path": address.serial_path, "baud": address.baud,
                                                         "protocol": expect.get("protocol")})


def _i2c(name: str, service: str, address: Any, expect: Mapping[str, Any]) -> Target:
    chip = "pca9685" if address.kind == "pca9685" else expect.get("chip", "mpu")
    return Target(name, service, "i2c", address.url, {"bus": address.i2c_bus, "address": address.chip_address,
                                                      "chip": chip, "variant": expect.get("variant", "auto")},
                  kind=address.kind)


def _can(name: str, service: str, address: Any, expect: Mapping[str, Any]) -> Target:
    return Target(name, service, "can", address.url, {"interface": address.can_interface,
                                                      "channel": address.can_channel,
                                                      "bus_options": address.bus_options, **expect})


def _gpio(name: str, service: str, address: Any, expect: Mapping[str, Any]) -> Target:
    return Target(name, service, "gpio", address.url, {"chip": address.gpio_chip, "lines": list(address.lines)})


def _pwm(name: str, service: str, address: Any, expect: Mapping[str, Any]) -> Target:
    return Target(name, service, "pwm", address.url, {"chip": address.pwm_chip, "channel": address.pwm_channel})


# address kind -> its probe's target (the probe: u2sa_hw.check.probe.PROBES[target.port])
TARGETS: dict[str, Callable[[str, str, Any, Mapping[str, Any]], Target]] = {
    "serial": _serial, "i2c": _i2c, "pca9685": _i2c, "can": _can, "gpio": _gpio, "pwm": _pwm,
}


def _from_address(name: str, service: str, address: Any, expect: Mapping[str, Any]) -> Target:
    make = TARGETS.get(address.kind)
    if make is None:   # said on the probe's line: "no probe for kind X"
        return Target(name, service, "", address.url, kind=address.kind)
    return make(name, service, address, expect)


def profile_targets(profile: Any) -> list[Target]:
    """Every device of every enabled service of *profile*; one whose kind has no probe has ``port=""``."""
    from u2sa_hw.profile.devices import effective_config, profile_devices

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
        expect = expectation(spec.kind, effective_config(profile, entry.service)) if address.kind in TARGETS else {}
        targets.append(_from_address(entry.name, entry.service, address, expect))
    return targets
