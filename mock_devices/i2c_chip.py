"""The register-level chip model base the mock I2C bus hosts, and what sensor chips sample.

:class:`RegisterChip` is a register file with auto-increment, faults and a history;
the chip models (:mod:`u2sa_hw.mocks.mpu9250_chip`, :mod:`u2sa_hw.mocks.bno055_chip`,
:mod:`u2sa_hw.mocks.pca9685_chip`) subclass it and :class:`u2sa_hw.mocks.i2c_bus.MockI2cBus`
hosts them. This module imports neither, so the bus can import the chip models and the
chip models this base without an import circle.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any, Protocol

from u2sa_hw.ports.i2c.wire import OP_READ, STATUS_EIO, STATUS_NACK, STATUS_OK

STANDARD_GRAVITY = 9.80665
HISTORY_LIMIT = 10_000


@dataclass(frozen=True)
class I2cTransaction:
    """One transaction as the bus or a chip saw it: t is time.monotonic()."""

    t: float
    address: int
    op: int
    register: int
    data: bytes
    status: int


class Vehicle(Protocol):
    """What motion-sensing chips need from the simulated vehicle (SimVehicle satisfies it)."""

    def snapshot(self) -> Any:
        """The current truth: roll/pitch/yaw, body rates, FRD specific force."""


class I2cChip(Protocol):
    """What the bus needs from a chip model."""

    address: int

    def handle(self, op: int, register: int, length: int, data: bytes) -> tuple[int, bytes]:
        """Run one transaction; return (status, data read)."""


class RegisterChip:
    """Base of register-level chip models: a register file, auto-increment, faults, history.

    Subclasses set ``reset_values`` (register -> power-on value), ``read_only`` registers
    (writes ignored, as the silicon does), ``write_only`` registers (read as 0), and
    override ``read_register`` / ``write_register`` / ``next_register`` /
    ``begin_transaction`` for behaviour beyond plain memory.
    """

    size = 256
    reset_values: dict[int, int] = {}
    read_only: frozenset[int] = frozenset()
    write_only: frozenset[int] = frozenset()

    def __init__(self, *, address: int) -> None:
        if not 0x03 <= address <= 0x77:
            raise ValueError(f"I2C chip address must be 0x03..0x77, got {address:#x}")
        self.address = address
        self.history: deque[I2cTransaction] = deque(maxlen=HISTORY_LIMIT)
        self._lock = threading.RLock()
        self._regs = bytearray(self.size)
        self._nack = False
        self._eio_every = 0
        self._count = 0
        self.reset()

    def reset(self) -> None:
        """Return every register to its power-on value."""
        with self._lock:
            self._regs[:] = bytes(self.size)
            for reg, value in self.reset_values.items():
                self._regs[reg] = value

    def nack(self, on: bool) -> None:
        """Fault: refuse every transaction with a NACK (as a chip that lost power or hangs)."""
        self._nack = bool(on)

    def eio_every(self, n: int) -> None:
        """Fault: fail every *n*-th transaction with EIO (0 turns it off)."""
        if n < 0:
            raise ValueError(f"eio_every needs n >= 0, got {n}")
        with self._lock:
            self._eio_every = n
            self._count = 0

    def peek(self, register: int) -> int:
        """The raw register value, bypassing read semantics (for tests and the simulation)."""
        with self._lock:
            return self._regs[register]

    def poke(self, register: int, value: int) -> None:
        """Set a raw register value, bypassing write semantics."""
        with self._lock:
            self._regs[register] = value & 0xFF

    def handle(self, op: int, register: int, length: int, data: bytes) -> tuple[int, bytes]:
        """Run one bus transaction against the register file, with faults and history."""
        with self._lock:
            status, out = self._handle(op, register, length, data)
            self.history.append(I2cTransaction(time.monotonic(), self.address, op, register,
                                               out if op == OP_READ else bytes(data), status))
            return status, out

    def _handle(self, op: int, register: int, length: int, data: bytes) -> tuple[int, bytes]:
        if self._nack:
            return STATUS_NACK, b""
        self._count += 1
        if self._eio_every and self._count % self._eio_every == 0:
            return STATUS_EIO, b""
        self.begin_transaction(op, register, length)
        reg = register
        if op == OP_READ:
            out = bytearray()
            for _ in range(length):
                out.append(0 if reg in self.write_only else self.read_register(reg) & 0xFF)
                reg = self.next_register(reg)
            return STATUS_OK, bytes(out)
        for value in data:
            if reg not in self.read_only:
                self.write_register(reg, value)
            reg = self.next_register(reg)
        self.end_write(register, len(data))
        return STATUS_OK, b""

    def begin_transaction(self, op: int, register: int, length: int) -> None:
        """Hook run before each transaction (e.g. latch a fresh sample into data registers)."""

    def end_write(self, register: int, length: int) -> None:
        """Hook run after a write transaction's STOP."""

    def read_register(self, register: int) -> int:
        """The value a read of *register* returns."""
        return self._regs[register]

    def write_register(self, register: int, value: int) -> None:
        """Store a written byte (read-only registers never get here)."""
        self._regs[register] = value

    def next_register(self, register: int) -> int:
        """The register the chip's pointer moves to after one byte (auto-increment)."""
        return (register + 1) % self.size


class RestingVehicle:
    """The vehicle sensor chips sample when given none: level, heading north, at rest."""

    def snapshot(self) -> SimpleNamespace:
        """A VehicleTruth-shaped record with the fields the chip models read."""
        return SimpleNamespace(t=time.monotonic(), roll=0.0, pitch=0.0, yaw=0.0, roll_rate=0.0, pitch_rate=0.0,
                               yaw_rate=0.0, accel_x=0.0, accel_y=0.0, accel_z=-STANDARD_GRAVITY)
