"""What the RC mux driver declares to the rest of the system (u2sa_hw/ports/declared.py).

A mixin of :class:`u2sa_hw.drivers.rc_mux.driver.RcMuxDriver`: the one GPIO device whose
lines carry the receiver's pulse trains and the mux's enable and select lines, the mock that
stands in for it (an RC receiver) and what that mock mirrors. The setting names stay here,
with the driver; each declaration is called with the service's config with the driver's
defaults under it.
"""

from __future__ import annotations

from typing import Any, ClassVar, Mapping

from u2sa_hw.drivers.gpio.lines import parse_line_map
from u2sa_hw.ports.declared import DeviceDeclarations
from u2sa_hw.ports.device_link import device_setting


class RcMuxDeclarations(DeviceDeclarations):
    """An RC receiver's pulse trains on the service's lines, and the mux on its enable line."""

    MOCK_KINDS: ClassVar[tuple[str, ...]] = ("rc_receiver",)

    @classmethod
    def used_devices(cls, service: str, config: Mapping[str, Any]) -> tuple[str, ...]:
        """The GPIO device of the receiver's and the mux's lines (``device``, else the service's name)."""
        return (device_setting(config, service),)

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
