"""What the CAN motor drivers declare to the rest of the system (u2sa_hw/ports/declared.py).

Mixins of :class:`u2sa_hw.drivers.can_motor.common.CanMotorService` and its ODrive and VESC
drivers: the one bus a service drives, the mocks that stand in for its controllers, what a
mock node mirrors (actuator names, CAN ids, directions, wheel radii, the motor's limits) and
the node ids ``u2sa check --probe`` listens for. The setting names stay here, with the
drivers; callers get values in their own vocabulary. Each is called with the service's config
with the driver's defaults under it.
"""

from __future__ import annotations

from typing import Any, ClassVar, Mapping

from u2sa_hw.ports.declared import DeviceDeclarations
from u2sa_hw.ports.device_link import device_setting


class CanMotorDeclarations(DeviceDeclarations):
    """One node per controller on one bus: actuator names, CAN ids, directions, wheel radii; the probe's ids."""

    ID_FIELD: ClassVar[str]                # the setting holding the controllers' CAN ids (the driver's)
    PROTOCOL: ClassVar[str] = ""           # what the probe listens for: odrive or vesc

    @classmethod
    def used_devices(cls, service: str, config: Mapping[str, Any]) -> tuple[str, ...]:
        """The one CAN bus the service drives (``device``, else the service's name): a device without a
        ``[devices.NAME]`` address is an error, never a silent ``can0`` (a winch's setpoints must not reach a
        wheel's node)."""
        return (device_setting(config, service),)

    @classmethod
    def mock_wiring(cls, service: str, device: str, config: Mapping[str, Any]) -> dict[str, Any]:
        """Per controller, in order: ``actuators``, ``ids``, ``directions``, ``wheel_radius_m``."""
        return {"actuators": [str(a) for a in config["actuators"]], "ids": list(config[cls.ID_FIELD]),
                "directions": list(config["directions"]), "wheel_radius_m": list(config["wheel_radius_m"])}

    @classmethod
    def probe_expectation(cls, config: Mapping[str, Any]) -> dict[str, Any]:
        """The protocol and the node ids the probe listens for."""
        return {"protocol": cls.PROTOCOL, "nodes": list(config.get(cls.ID_FIELD, []))}


class OdriveDeclarations(CanMotorDeclarations):
    """ODrive CANSimple nodes: the controllers, the firmware, the speed the driver limits its commands to."""

    MOCK_KINDS: ClassVar[tuple[str, ...]] = ("odrive",)
    PROTOCOL = "odrive"

    @classmethod
    def mock_wiring(cls, service: str, device: str, config: Mapping[str, Any]) -> dict[str, Any]:
        """The controllers, ``firmware`` and ``command_limit_turns_per_s`` (``max_turns_per_s``)."""
        return {**super().mock_wiring(service, device, config), "firmware": str(config["firmware"]),
                "command_limit_turns_per_s": float(config["max_turns_per_s"])}


class VescDeclarations(CanMotorDeclarations):
    """VESC nodes: the controllers and the motor's ERPM scale, pole pairs and gearing."""

    MOCK_KINDS: ClassVar[tuple[str, ...]] = ("vesc",)
    PROTOCOL = "vesc"

    @classmethod
    def mock_wiring(cls, service: str, device: str, config: Mapping[str, Any]) -> dict[str, Any]:
        """The controllers, ``max_erpm`` (at 100 %), ``pole_pairs`` and ``gear_ratio``."""
        return {**super().mock_wiring(service, device, config), "max_erpm": float(config["max_erpm"]),
                "pole_pairs": int(config["pole_pairs"]), "gear_ratio": float(config["gear_ratio"])}
