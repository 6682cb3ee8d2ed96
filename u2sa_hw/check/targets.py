"""What ``u2sa check --probe`` looks at: one :class:`Target` per device of each enabled service.

A target is the port kind, the address text shown, the parameters the probe opens it with,
and what the service's driver expects there (the protocol of a serial device, the chip
behind an I2C address, the CAN node ids). Where each device is comes from its address
(:func:`u2sa_hw.profile.devices.profile_devices`); what the driver expects there, the driver declares
(:func:`expectation`: its ``probe_expectation``, :mod:`u2sa_hw.ports.declared`): a protocol,
a chip family and variant, the CAN node ids. Nothing here reads a driver's setting names.

Which probe looks at a device follows its address kind: each port kind names its probe module
(``PortKind.probe``, ``u2sa_hw/ports/<kind>/probe.py``: ``PROBE``, ``target_params``, ``probe``),
and :data:`TARGETS` (kind -> the target of that kind's probe, in
:data:`u2sa_hw.check.probe.PROBES`) is read off the kind table. A device whose kind has
neither is still a target, with no port (``port=""``): ``u2sa check --probe`` says "no
probe for kind X" on its line rather than leave it out unsaid (docs/ports.md, "A new port kind").
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from types import ModuleType
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


def _target_of(probe: ModuleType) -> Callable[[str, str, Any, Mapping[str, Any]], Target]:
    """The target builder of a kind whose probe is *probe* (a ``u2sa_hw/ports/<kind>/probe.py``)."""
    def target(name: str, service: str, address: Any, expect: Mapping[str, Any]) -> Target:
        kind = address.kind if probe.PROBE == "i2c" else ""   # a pca9685 address names its kind on the line
        return Target(name, service, probe.PROBE, address.url, probe.target_params(address, expect), kind=kind)

    return target


def _kind_targets() -> dict[str, Callable[[str, str, Any, Mapping[str, Any]], Target]]:
    from u2sa_hw.ports.kinds import PORT_KINDS

    return {name: _target_of(importlib.import_module(kind.probe)) for name, kind in PORT_KINDS.items()
            if kind.probe is not None}


# address kind -> its probe's target (the probe: u2sa_hw.check.probe.PROBES[target.port]), from the kind table
TARGETS: dict[str, Callable[[str, str, Any, Mapping[str, Any]], Target]] = _kind_targets()


def _from_address(name: str, service: str, address: Any, expect: Mapping[str, Any]) -> Target:
    make = TARGETS.get(address.kind)
    if make is None:   # said on the probe's line: "no probe for kind X"
        return Target(name, service, "", address.url, kind=address.kind)
    return make(name, service, address, expect)


def profile_targets(profile: Any) -> list[Target]:
    """Every device of every enabled service of *profile*; one whose kind has no probe has ``port=""``."""
    from u2sa_hw.profile.devices import effective_config, profile_devices

    entries = profile_devices(profile)   # ProfileError: see u2sa check (offline)
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
