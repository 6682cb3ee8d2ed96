"""The mock I2C bus's wire protocol, shared by the port's mock client and the bus server the mock devices run.

Mock wire protocol (one request, one response, in order, on a stream socket; big-endian):
  request  = op:u8 (0 read, 1 write) | address:u8 (7-bit) | register:u8 | length:u16
             | data[length] (write only; for a read, length is the number of bytes wanted)
  response = status:u8 (0 OK, 1 NACK, 2 EIO, 3 BAD_REQUEST) | length:u16 | data[length]
A read answers OK with exactly the bytes asked for; every other answer carries no data.

The client end is :class:`~u2sa_hw.ports.i2c.port.MockI2cPort`; the end the mock devices serve
is ``u2sa_hw.mocks.i2c_bus`` (and ``hil/replay_i2c.py``'s replay bus).
"""

from __future__ import annotations

import struct

OP_READ = 0
OP_WRITE = 1
STATUS_OK = 0
STATUS_NACK = 1
STATUS_EIO = 2
STATUS_BAD_REQUEST = 3
STATUS_NAMES = {STATUS_OK: "OK", STATUS_NACK: "NACK", STATUS_EIO: "EIO", STATUS_BAD_REQUEST: "BAD_REQUEST"}
REQUEST = struct.Struct(">BBBH")
RESPONSE = struct.Struct(">BH")
MAX_TRANSFER = 1024  # bytes per transaction; far above any chip's register file
MOCK_BUS_NUMBER = -1  # the RawI2c.bus value recorded for a mock bus
