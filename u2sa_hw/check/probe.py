"""``u2sa check --probe``: open each device of a profile and look at it, one line per device.

Each port kind's probe is in its package (``u2sa_hw/ports/<kind>/probe.py``, named by
``PortKind.probe``). Serial: line rate, protocol, good checksums, the baud that works. I2C
(and PCA9685): the chip's identity register against what the driver expects
(:mod:`u2sa_hw.check.chip_ids`). CAN: the interface's state, bitrate and error counters
(socketcan: ``/sys/class/net`` and ``ip -details -statistics link``; a python-can
``udp_multicast``/``virtual`` bus is said to be simulated) and the node ids heard in the
window. GPIO: the lines exist and no one holds them. PWM: the channel exists. A device whose
address kind has no probe (:data:`PROBES`, chosen through :data:`u2sa_hw.check.targets.TARGETS`)
gets a ``probe skip`` line saying so: never probed without a word, and not a failure.

Nothing is written to a device: a probe only reads (an I2C identity register, the GPIO
lines' info) and listens. A device held by a running service is reported busy; stop the
service (or probe before starting it) to look at it.
"""

from __future__ import annotations

import importlib
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Mapping

from u2sa_hw.check.targets import Target, profile_targets


@dataclass(frozen=True)
class ProbeResult:
    """What a probe of one device found: ``ok`` False when it cannot work as configured."""

    device: str
    port: str
    address: str
    ok: bool
    text: str
    details: Mapping[str, Any] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()      # it works, but not as well as it could (an uncalibrated sensor)
    probed: bool = True                 # False: no probe for the device's kind (ok, since nothing was found wrong)

    def __str__(self) -> str:
        status = "ok  " if self.ok else "FAIL"
        line = f"probe {status if self.probed else 'skip'} {self.device}: {self.port} {self.address}: {self.text}"
        return "\n".join([line, *(f"probe warn {self.device}: {w}" for w in self.warnings)])

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready."""
        data = asdict(self)
        data["details"] = dict(self.details)
        return data


def probe_profile(profile: Any, *, seconds: float = 3.0) -> list[ProbeResult]:
    """Probe every device of every enabled service of *profile*, all at once (each listens *seconds*).

    The devices are independent, so they are probed on threads: the wall time is about one
    window, not one per device. The results keep the profile's device order.
    """
    from concurrent.futures import ThreadPoolExecutor

    targets = profile_targets(profile)
    if not targets:
        return []
    with ThreadPoolExecutor(max_workers=len(targets), thread_name_prefix="probe") as pool:
        results = list(pool.map(lambda target: probe_target(target, seconds=seconds), targets))
    from u2sa_hw.check.probe_calibration import with_calibration_warnings

    return [with_calibration_warnings(profile, target, result) for target, result in zip(targets, results)]


def probe_target(target: Target, *, seconds: float) -> ProbeResult:
    """One device: the probe of its port kind (none: a "no probe for kind" line); a port error becomes a failed
    line with its fix."""
    from u2sa_hw.ports.errors import PortError

    probe = PROBES.get(target.port)
    if probe is None:
        kind = target.kind or target.port
        return ProbeResult(target.name, kind, target.address, True,
                           f"no probe for kind {kind}: not looked at (check it by hand; a probe for the kind goes in "
                           f"u2sa_hw/ports/{kind}/probe.py, see docs/adding-a-device.md, 'A port kind')", probed=False)
    try:
        ok, text, details = probe(target, seconds)
    except PortError as exc:
        ok, text, details = False, str(exc).replace(f"{target.name} ({target.address}): ", ""), {}
    except OSError as exc:
        ok, text, details = False, f"{exc.strerror or exc}", {}
    return ProbeResult(target.name, target.port, target.address, ok, text, details)


def _kind_probes() -> dict[str, Callable[[Target, float], tuple[bool, str, dict[str, Any]]]]:
    from u2sa_hw.ports.kinds import PORT_KINDS

    modules = [importlib.import_module(kind.probe) for kind in PORT_KINDS.values() if kind.probe is not None]
    return {module.PROBE: module.probe for module in modules}


# probe name (a target's port) -> the probe, each in its kind's package (u2sa_hw/ports/<kind>/probe.py)
PROBES: dict[str, Callable[[Target, float], tuple[bool, str, dict[str, Any]]]] = _kind_probes()
