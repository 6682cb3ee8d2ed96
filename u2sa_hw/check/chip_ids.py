"""What each I2C chip answers on its identity register, as the drivers expect it.

The register numbers and values come from the protocol modules (the vendors' tables);
this module only says which register identifies which chip for ``u2sa check --probe``.
Reads only: nothing is written to a chip (the AK8963 behind an MPU-9250 is looked at only
when the MPU's bypass is already on).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

from u2sa_hw.protocols import bno055 as bno
from u2sa_hw.protocols import mpu9250 as mpu
from u2sa_hw.protocols import pca9685 as pca

NAMES = {"mpu6050": "MPU-6050", "mpu6500": "MPU-6500", "mpu9250": "MPU-9250"}
OTHER_IDS = {0x73: "MPU-9255", 0x70: "MPU-6500", 0x68: "MPU-6050", 0x71: "MPU-9250"}


@dataclass(frozen=True)
class Identity:
    """A chip's identity register and the values the driver accepts (value -> chip name)."""

    chip: str
    register: int
    register_name: str
    accepted: Mapping[int, str] = field(default_factory=dict)   # empty: any answer (the chip has no id register)
    magnetometer: bool = False   # an MPU-9250: look for its AK8963 too

    def companion(self, port: Any, *, bus: Any, device: str) -> str:
        """Text about the chip's companion (the MPU-9250's AK8963), "" when it has none."""
        if not self.magnetometer:
            return ""
        from u2sa_hw.ports.errors import PortError
        from u2sa_hw.ports.i2c.port import open_i2c

        try:
            mag = open_i2c(device=device, bus=bus, address=mpu.AK8963_ADDRESS)
        except PortError:
            return ""
        try:
            wia = mag.read_byte(mpu.AK8963_WIA)
        except PortError:
            return (f"; AK8963 at 0x{mpu.AK8963_ADDRESS:02x} not visible (the MPU's I2C bypass is off until the "
                    "driver turns it on)")
        finally:
            mag.close()
        if wia == mpu.AK8963_WIA_VALUE:
            return f"; AK8963 WIA 0x{wia:02x} as expected"
        return f"; AK8963 WIA reads 0x{wia:02x}, expected 0x{mpu.AK8963_WIA_VALUE:02x}"


def expected_identity(chip: str, variant: str = "auto") -> Identity:
    """The identity the driver of *chip* (``mpu``, ``bno055``, ``pca9685``) expects; *variant*: the MPU ``chip``
    setting (``auto`` accepts every variant the driver knows)."""
    if chip == "mpu":
        variants = mpu.VARIANTS if variant == "auto" else {variant: mpu.VARIANTS[variant]}
        accepted = {v.who_am_i: NAMES.get(name, name) for name, v in variants.items()}
        return Identity("MPU-60x0/9250" if variant == "auto" else NAMES.get(variant, variant), mpu.WHO_AM_I,
                        "WHO_AM_I", accepted, magnetometer=any(v.has_magnetometer for v in variants.values()))
    if chip == "bno055":
        return Identity("BNO055", bno.CHIP_ID, "CHIP_ID", {bno.CHIP_ID_VALUE: "BNO055"})
    if chip == "pca9685":
        return Identity("PCA9685", pca.MODE1, "MODE1")
    raise ValueError(f"no identity known for chip {chip!r}")


def read_identity(port: Any, expected: Identity) -> tuple[bool, str]:
    """Read *expected*'s register through *port* (an I2cPort): ``(ok, text)``."""
    value = port.read_byte(expected.register)
    if not expected.accepted:
        return True, f"{expected.chip} answers: {expected.register_name} = 0x{value:02x}"
    if value in expected.accepted:
        return True, f"{expected.accepted[value]}: {expected.register_name} 0x{value:02x} as expected"
    known = ", ".join(f"0x{v:02x} ({n})" for v, n in expected.accepted.items())
    what = f" (that is an {OTHER_IDS[value]})" if value in OTHER_IDS else ""
    return False, (f"{expected.register_name} reads 0x{value:02x}{what}; the driver expects {known}: another chip "
                   "at this address, or the wrong chip setting")
