"""The AK8963 magnetometer inside an MPU-9250, reached through the MPU's I2C bypass.

Set-up (after every MPU set-up, since the MPU's reset clears its bypass bit): the MPU's
INT_PIN_CFG.BYPASS_EN connects the AK8963 (0x0C) to the main bus; WIA must read 0x48; a
soft reset; fuse-ROM mode to read the factory sensitivity adjustment ASA (one byte per
axis, ``H_adj = H * ((ASA - 128) / 256 + 1)``); power-down; then continuous measurement
mode 2 (100 Hz) with 16-bit output (0.15 µT/LSB). Each sample is one 8-byte read of ST1,
HXL..HZH and ST2 (reading ST2 ends the read cycle). A sample without ST1.DRDY is not new
(the previous one is kept); one with ST2.HOFL (field beyond +-4912 µT: a magnet next to the
board) is dropped and counted.

Axes: the AK8963's axes are not the MPU's. With the MPU's chip axes x, y, z, the
magnetometer's x is chip y, its y is chip x and its z is -chip z (MPU-9250 product
specification, section 9.1); :func:`to_chip_axes` turns a reading into chip axes, after
which the driver's ``mounting`` applies as to the accel and gyro.

Address: the AK8963 sits on the MPU's own bus, so its address is the MPU device's with chip
address 0x0c (:func:`mag_address`: ``i2c://1/0x68`` -> ``i2c://1/0x0c``, and the same for a
mock or replay bus socket), opened through ``open_port`` like every device. It is set up
again on every open of the MPU, from the MPU device's address at that moment, so it follows
an address change. Its transactions go to the tap the driver gives (the MPU device's
``RAW.<device>``, where the chip address 0x0c tells them apart), so they are recorded and a
replay answers them like the MPU's (docs/replay.md).
"""

from __future__ import annotations

import time
from typing import Callable

from u2sa_hw.ports.address import DeviceAddress
from u2sa_hw.ports.errors import PortError, PortIOError
from u2sa_hw.ports.i2c.port import I2cPort
from u2sa_hw.ports.opener import open_port
from u2sa_hw.ports.tap import Tap
from u2sa_hw.protocols import mpu9250 as mpu

Vector = tuple[float, float, float]


def to_chip_axes(mag: Vector) -> Vector:
    """An AK8963-axes vector in the MPU's chip axes (x<->y swapped, z inverted)."""
    return mag[1], mag[0], -mag[2]


def mag_address(mpu_address: DeviceAddress) -> DeviceAddress:
    """The AK8963's address beside the MPU at *mpu_address*: the same adapter or bus socket, chip 0x0c."""
    return mpu_address.with_chip_address(mpu.AK8963_ADDRESS)


class Ak8963:
    """The magnetometer's own port, set-up and sample reads; every fault is counted, none raised.

    *tap* gets every transaction (the driver's ``RAW.<device>`` tap); *retries* gives the
    number of immediate retries of a failed transaction.
    """

    def __init__(self, *, retries: Callable[[], int], tap: Tap | None = None) -> None:
        self._retries = retries
        self._tap = tap
        self.device = ""
        self.address: DeviceAddress | None = None   # where the latest set-up opened it
        self.port: I2cPort | None = None
        self.adjust: Vector = (1.0, 1.0, 1.0)
        self.asa: tuple[int, int, int] | None = None
        self.state = "not set up"
        self.samples = 0
        self.overflows = 0
        self.errors = 0
        self.last: Vector | None = None      # µT, AK8963 axes, ASA applied
        self.last_at = 0.0

    def setup(self, mpu_port: object, *, device: str, mpu_address: DeviceAddress) -> bool:
        """Enable the bypass through *mpu_port* (a RetryingI2c), open the AK8963 beside the MPU at
        *mpu_address* as *device* (closing the one opened before), identify and start it; False if absent."""
        self.close()
        self.device, self.address = device, mag_address(mpu_address)
        try:
            mpu_port.write_byte(mpu.INT_PIN_CFG, mpu.INT_PIN_CFG_BYPASS_EN)  # type: ignore[attr-defined]
            port: I2cPort = open_port(self.address, device=device, tap=self._tap)
            self.port = port
            who = self._call(lambda: port.read_byte(mpu.AK8963_WIA))
            if who != mpu.AK8963_WIA_VALUE:
                self.state = f"no AK8963 at {self.address} (WIA 0x{who:02x}, expected 0x48)"
                self.close()
                return False
            self._call(lambda: port.write_byte(mpu.AK8963_CNTL2, mpu.AK8963_CNTL2_SRST))
            self._mode(port, mpu.AK8963_MODE_FUSE_ROM)
            asa = self._call(lambda: port.read_block(mpu.AK8963_ASAX, 3))
            self.asa = (asa[0], asa[1], asa[2])
            self.adjust = tuple(mpu.ak8963_adjustment(a) for a in self.asa)  # type: ignore[assignment]
            self._mode(port, mpu.AK8963_MODE_POWER_DOWN)
            self._mode(port, mpu.AK8963_CNTL1_BIT_16 | mpu.AK8963_MODE_CONTINUOUS_2)
        except PortError as exc:
            self.errors += 1
            self.state = f"not answering ({exc})"
            self.close()
            return False
        self.state = "continuous 100 Hz, 16-bit"
        return True

    def _call(self, fn: Callable[[], object]) -> object:
        """*fn* retried ``retries()`` times after an I/O error (counted in ``errors``, not the MPU's counters)."""
        tries = self._retries() + 1
        while True:
            try:
                return fn()
            except PortIOError:
                tries -= 1
                if tries <= 0:
                    raise
                self.errors += 1

    def _mode(self, port: I2cPort, mode: int) -> None:
        self._call(lambda: port.write_byte(mpu.AK8963_CNTL1, mode))
        time.sleep(mpu.AK8963_MODE_WAIT_S)

    def read(self) -> Vector | None:
        """The newest field (µT, AK8963 axes), or None when there is none new and valid."""
        port = self.port
        if port is None:
            return None
        try:
            raw = mpu.decode_mag(self._call(lambda: port.read_block(mpu.AK8963_SAMPLE_START,  # type: ignore[arg-type]
                                                                    mpu.AK8963_SAMPLE_LENGTH)))
        except PortError as exc:
            self.errors += 1
            self.state = f"lost ({exc}); set up again with the MPU"
            self.close()
            return None
        if not raw.ready:
            return None
        if raw.overflow:
            self.overflows += 1
            return None
        scale = mpu.AK8963_UT_PER_LSB_16BIT if raw.sixteen_bit else mpu.AK8963_UT_PER_LSB_14BIT
        self.last = (raw.hx * scale * self.adjust[0], raw.hy * scale * self.adjust[1], raw.hz * scale * self.adjust[2])
        self.last_at = time.monotonic()
        self.samples += 1
        return self.last

    def close(self, why: str = "") -> None:
        """Release the magnetometer's port (set up again by the next ``setup``); *why*, if given, is its state."""
        if why:
            self.state = why
        if self.port is not None:
            try:
                self.port.close()
            except (OSError, PortError):
                pass
            self.port = None
