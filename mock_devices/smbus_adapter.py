"""Linux I2C adapters (``/dev/i2c-N``) backed by mock I2C buses, for smbus2 in this process.

This machine has no ``/dev/i2c-*``, so the smbus2 backend of the I2C port
(``u2sa_hw.ports.i2c.port.SmbusI2cPort``) cannot reach a kernel adapter. ``SmbusAdapters``
stands in for the kernel's i2c-dev: attach a :class:`~u2sa_hw.mocks.i2c_bus.MockI2cBus` as
adapter N, and the class from :meth:`SmbusAdapters.smbus_class` (put in place of
``smbus2.SMBus``) answers ``open(N)``, ``read_i2c_block_data``, ``write_i2c_block_data`` and
``i2c_rdwr`` (with smbus2's own ``i2c_msg`` objects) from that bus's chip models, with the
errnos i2c-dev gives:

- no adapter N: ``open`` fails with ENOENT (``/dev/i2c-N`` does not exist);
- a chip that does not acknowledge (absent, or ``nack(True)``): ENXIO;
- a chip's EIO fault: EIO;
- an adapter unplugged while open (:meth:`SmbusAdapters.unplug`): ENODEV, and ENOENT on
  the next ``open``, until :meth:`SmbusAdapters.replug`;
- more than 32 bytes in an SMBus block call: ValueError, as smbus2 raises.

Only the port's own code above smbus2 runs for real; the chips are the same models the
mock bus serves over its socket, so one contract suite can run over both.
"""

from __future__ import annotations

import ctypes
import errno
import os
import threading
from typing import Any

from u2sa_hw.mocks.i2c_bus import MockI2cBus
from u2sa_hw.ports.i2c.wire import OP_READ, OP_WRITE, STATUS_EIO, STATUS_NACK, STATUS_OK

SMBUS_BLOCK_MAX = 32
I2C_M_RD = 0x0001  # i2c_msg flag: a read


class SmbusAdapters:
    """Adapter numbers -> mock buses, and the SMBus stand-in that reaches them."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._buses: dict[int, MockI2cBus] = {}
        self._unplugged: set[int] = set()
        self.opened = 0  # successful open() calls, all SMBus objects together

    def attach(self, number: int, bus: MockI2cBus) -> None:
        """Make *bus* (started or not: its chips are called directly) adapter ``/dev/i2c-<number>``."""
        with self._lock:
            self._buses[number] = bus

    def unplug(self, number: int) -> None:
        """Remove adapter *number* (a USB I2C adapter pulled out): open SMBus objects fail with ENODEV."""
        with self._lock:
            self._unplugged.add(number)

    def replug(self, number: int) -> None:
        """Put adapter *number* back: it can be opened again."""
        with self._lock:
            self._unplugged.discard(number)

    def _bus(self, number: int, *, opening: bool) -> MockI2cBus:
        with self._lock:
            bus = self._buses.get(number)
            gone = number in self._unplugged
        if bus is None or gone:
            if opening:
                raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), f"/dev/i2c-{number}")
            raise OSError(errno.ENODEV, os.strerror(errno.ENODEV))
        return bus

    def smbus_class(self) -> type:
        """A class to put in place of ``smbus2.SMBus``, reaching these adapters."""
        adapters = self

        class MockAdapterSMBus:
            """What the port uses of smbus2.SMBus, on a mock adapter."""

            def __init__(self, bus: int | None = None) -> None:
                self.number: int | None = None
                if bus is not None:
                    self.open(bus)

            def open(self, bus: int) -> None:
                adapters._bus(bus, opening=True)
                self.number = bus
                with adapters._lock:
                    adapters.opened += 1

            def close(self) -> None:
                self.number = None

            def _transact(self, op: int, address: int, register: int, length: int, data: bytes) -> bytes:
                if self.number is None:
                    raise OSError(errno.EBADF, os.strerror(errno.EBADF))
                status, out = adapters._bus(self.number, opening=False).transact(op, address, register, length, data)
                if status == STATUS_NACK:
                    raise OSError(errno.ENXIO, os.strerror(errno.ENXIO))
                if status == STATUS_EIO:
                    raise OSError(errno.EIO, os.strerror(errno.EIO))
                if status != STATUS_OK:
                    raise OSError(errno.EINVAL, os.strerror(errno.EINVAL))
                return out

            def read_i2c_block_data(self, i2c_addr: int, register: int, length: int,
                                    force: bool | None = None) -> list[int]:
                if length > SMBUS_BLOCK_MAX:
                    raise ValueError(f"Desired block length over {SMBUS_BLOCK_MAX} bytes")
                return list(self._transact(OP_READ, i2c_addr, register, length, b""))

            def write_i2c_block_data(self, i2c_addr: int, register: int, data: list[int],
                                     force: bool | None = None) -> None:
                if len(data) > SMBUS_BLOCK_MAX:
                    raise ValueError(f"Data length cannot exceed {SMBUS_BLOCK_MAX} bytes")
                self._transact(OP_WRITE, i2c_addr, register, len(data), bytes(data))

            def i2c_rdwr(self, *messages: Any) -> None:
                """A register write followed by a read (repeated start), or one write of register + data."""
                if len(messages) == 2 and not messages[0].flags & I2C_M_RD and messages[1].flags & I2C_M_RD:
                    write, read = messages
                    register = bytes(write)[0]
                    data = self._transact(OP_READ, read.addr, register, read.len, b"")
                    ctypes.memmove(read.buf, data, len(data))
                elif len(messages) == 1 and not messages[0].flags & I2C_M_RD:
                    payload = bytes(messages[0])
                    self._transact(OP_WRITE, messages[0].addr, payload[0], len(payload) - 1, payload[1:])
                else:
                    raise OSError(errno.EOPNOTSUPP, "the mock adapter does register reads and writes only")

        return MockAdapterSMBus
