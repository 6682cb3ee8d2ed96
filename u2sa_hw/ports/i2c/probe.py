"""The I2C kind's probe (``u2sa check --probe``): the chip's identity register against what the driver expects.

The identities are :mod:`u2sa_hw.check.chip_ids`'s; a PCA9685 address is probed here too (one
identity read per chip). Nothing is written to the chip.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Mapping

if TYPE_CHECKING:
    from u2sa_hw.check.targets import Target
    from u2sa_hw.ports.address import DeviceAddress

PROBE = "i2c"             # the probe's name (a target's ``port``), for i2c and pca9685 addresses


def target_params(address: DeviceAddress, expect: Mapping[str, Any]) -> dict[str, Any]:
    """The bus and chip of an I2C or PCA9685 *address*, and the chip family and variant the driver expects."""
    chip = "pca9685" if address.kind == "pca9685" else expect.get("chip", "mpu")
    return {"bus": address.i2c_bus, "address": address.chip_address, "chip": chip,
            "variant": expect.get("variant", "auto")}


def probe(target: Target, seconds: float) -> tuple[bool, str, dict[str, Any]]:
    """Read the chip's identity register (and its companion's, e.g. an MPU-9250's AK8963)."""
    from u2sa_hw.check.chip_ids import expected_identity, read_identity
    from u2sa_hw.ports.i2c.port import open_i2c

    chip = target.params["chip"]
    address = int(target.params["address"])
    expected = expected_identity(chip, target.params.get("variant", "auto"))
    port = open_i2c(device=target.name, bus=target.params["bus"], address=address)
    try:
        ok, text = read_identity(port, expected)
        extra = expected.companion(port, bus=target.params["bus"], device=target.name) if ok else ""
    finally:
        port.close()
    return ok, text + extra, {"chip": chip, "address": address}
