"""The sysfs PWM kind's probe (``u2sa check --probe``): the chip and the channel exist.

A PCA9685 output is probed as an I2C chip (:mod:`u2sa_hw.ports.i2c.probe`). Nothing is exported or written.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

if TYPE_CHECKING:
    from u2sa_hw.check.targets import Target
    from u2sa_hw.ports.address import DeviceAddress

PROBE = "pwm"             # the probe's name (a target's ``port``)


def target_params(address: DeviceAddress, expect: Mapping[str, Any]) -> dict[str, Any]:
    """The chip directory and channel of a sysfs PWM *address*."""
    return {"chip": address.pwm_chip, "channel": address.pwm_channel}


def probe(target: Target, seconds: float) -> tuple[bool, str, dict[str, Any]]:
    """The chip and the channel exist (an exported channel is said to be in use)."""
    chip = Path(str(target.params["chip"]))
    channel = int(target.params["channel"])
    if not chip.is_dir():
        return False, f"no PWM chip at {chip} (enable the PWM overlay, e.g. dtoverlay=pwm-2chan)", {}
    try:
        npwm = int((chip / "npwm").read_text().strip())
    except (OSError, ValueError):
        return False, f"{chip}/npwm cannot be read", {}
    if not 0 <= channel < npwm:
        return False, f"channel {channel} does not exist ({chip.name} has {npwm}: 0..{npwm - 1})", {}
    exported = (chip / f"pwm{channel}").is_dir()
    return True, f"channel {channel} of {npwm} exists" + (" (exported: in use)" if exported else ""), {}
