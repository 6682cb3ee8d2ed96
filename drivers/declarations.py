"""Device declarations of the driver families whose modules are full: CAN motors and the RC mux.

Mixins of :class:`u2sa_hw.drivers.can_motor.common.CanMotorService`, :class:`u2sa_hw.drivers.can_motor.odrive.driver.OdriveCanMotor`,
:class:`u2sa_hw.drivers.can_motor.vesc.driver.VescCanMotor` and :class:`u2sa_hw.drivers.rc_mux.driver.RcMuxDriver`: what each
declares to the mock catalog and ``u2sa check --probe`` (``MOCK_KINDS``, ``mock_wiring``,
``probe_expectation``; u2sa_hw/ports/declared.py). The setting names stay with the drivers;
callers get values in their own vocabulary. Each is called with the service's config with
the driver's defaults under it.
"""

from __future__ import annotations

from typing import Any, ClassVar, Mapping

from u2sa_hw.drivers.gpio.lines import parse_line_map


class CanMotorDeclarations:
    """One node per controller: actuator names, CAN ids, directions, wheel radii; the probe's node ids."""

    ID_FIELD: ClassVar[str]                # the setting holding the controllers' CAN ids (the driver's)
    PROTOCOL: ClassVar[str] = ""           # what the probe listens for: odrive or vesc

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


class RcMuxDeclarations:
    """An RC receiver's pulse trains on the service's lines, and the mux on its enable line."""

    MOCK_KINDS: ClassVar[tuple[str, ...]] = ("rc_receiver",)

    @classmethod
    def mock_wiring(cls, service: str, device: str, config: Mapping[str, Any]) -> dict[str, Any]:
        """``lines`` (channel -> line), ``mode_channel``, ``enable_line`` and ``select_line`` (None: no such line);
        a ConfigError names the setting and the fix."""
        enable, select = int(config["enable_line"]), int(config["select_line"])
        return {"lines": parse_line_map(str(config["channels"]), service=service, key="channels"),
                "mode_channel": str(config["mode_channel"]),
                "enable_line": enable if enable >= 0 else None, "select_line": select if select >= 0 else None}

    @classmethod
    def probe_expectation(cls, config: Mapping[str, Any]) -> dict[str, Any]:
        """Nothing: a GPIO chip has no identity to read."""
        return {}
