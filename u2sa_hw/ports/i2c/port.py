"""I2C port: register transactions with one chip, on a real bus (smbus2) or the mock bus.

``open_i2c(device=..., bus=1, address=0x68)`` talks to ``/dev/i2c-1`` through smbus2;
``bus="mock:/run/u2sa/i2c.sock"`` talks to the mock I2C bus server
(mock_devices/i2c_bus.py) over a Unix stream socket. Both raise the same errors:
``PortUnavailable`` when the bus cannot be opened, ``PortIOError`` when a transaction
fails (no ACK, EIO), ``PortClosed`` when the bus goes away, ``PortTimeout`` when the mock
server does not answer. Every transaction is handed to the tap as a ``RawI2c`` record
(op 0 read / 1 write, ok flag, data).

The mock bus's wire protocol is :mod:`u2sa_hw.ports.i2c.wire`.
"""

from __future__ import annotations

import errno
import socket
import threading
from u2sa_hw.messages import RawI2c
from u2sa_hw.ports.errors import PortClosed, PortError, PortIOError, PortTimeout, PortUnavailable
from u2sa_hw.ports.i2c.wire import (MAX_TRANSFER, MOCK_BUS_NUMBER, OP_READ, OP_WRITE, REQUEST, RESPONSE, STATUS_NAMES,
                                    STATUS_EIO, STATUS_NACK, STATUS_OK)
from u2sa_hw.ports.tap import Tap, call_tap, tapping

MOCK_SCHEME = "mock:"
SMBUS_BLOCK_MAX = 32  # SMBus I2C-block limit; longer reads/writes use I2C_RDWR
MOCK_TIMEOUT_S = 2.0  # a mock bus client's wait for an answer, unless its address says timeout=

_NO_ACK_ERRNOS = {errno.ENXIO, errno.EREMOTEIO, errno.EIO}
_GONE_ERRNOS = {errno.ENODEV, errno.EBADF, errno.ESHUTDOWN}


class I2cPort:
    """One chip on one I2C bus: byte and block register reads/writes, tapped.

    Subclasses provide ``_read(register, length)`` and ``_write(register, data)`` and
    raise port errors; this class validates arguments, serialises callers from several
    threads and records every transaction.
    """

    def __init__(self, *, device: str, address: str, bus_number: int, i2c_address: int, tap: Tap | None) -> None:
        self.device = device
        self.address = address
        self.i2c_address = i2c_address
        self._bus_number = bus_number
        self._tap = tap
        self._lock = threading.Lock()
        self._open = True

    @property
    def is_open(self) -> bool:
        """False once closed or once the bus has gone away."""
        return self._open

    def read_byte(self, register: int) -> int:
        """Read one register."""
        return self.read_block(register, 1)[0]

    def write_byte(self, register: int, value: int) -> None:
        """Write one register."""
        if not 0 <= value <= 0xFF:
            raise ValueError(f"{self.device}: I2C byte must be 0..255, got {value}")
        self.write_block(register, bytes((value,)))

    def read_block(self, register: int, length: int) -> bytes:
        """Read *length* bytes starting at *register* in one transaction (auto-increment is the chip's)."""
        self._check_register(register)
        if not 1 <= length <= MAX_TRANSFER:
            raise ValueError(f"{self.device}: I2C read length must be 1..{MAX_TRANSFER}, got {length}")
        return self._transact(OP_READ, register, length, b"")

    def write_block(self, register: int, data: bytes) -> None:
        """Write *data* starting at *register* in one transaction."""
        self._check_register(register)
        data = bytes(data)
        if not 1 <= len(data) <= MAX_TRANSFER:
            raise ValueError(f"{self.device}: I2C write must carry 1..{MAX_TRANSFER} bytes, got {len(data)}")
        self._transact(OP_WRITE, register, len(data), data)

    def close(self) -> None:
        """Release the bus; further calls raise PortClosed."""
        with self._lock:
            if self._open:
                self._open = False
                self._release()

    def __enter__(self) -> "I2cPort":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _check_register(self, register: int) -> None:
        if not 0 <= register <= 0xFF:
            raise ValueError(f"{self.device}: I2C register must be 0..255, got {register}")

    def _transact(self, op: int, register: int, length: int, data: bytes) -> bytes:
        with self._lock:
            if not self._open:
                raise PortClosed(self.device, "I2C port is closed", address=self.address,
                                 fix="open the port again")
            try:
                if op == OP_READ:
                    result = self._read(register, length)
                else:
                    self._write(register, data)
                    result = b""
            except PortError:
                self._record(op, register, data, ok=False)
                raise
            self._record(op, register, result if op == OP_READ else data, ok=True)
            return result

    def _record(self, op: int, register: int, data: bytes, *, ok: bool) -> None:
        if not tapping(self._tap):
            return
        rec = RawI2c()
        rec.device = self.device
        rec.bus = self._bus_number
        rec.address = self.i2c_address
        rec.register_address = register
        rec.op = op
        rec.ok = ok
        rec.data = bytes(data)
        rec.length = len(rec.data)
        call_tap(self._tap, rec)

    def _no_ack(self, where: str) -> PortIOError:
        return PortIOError(self.device, f"no ACK from 0x{self.i2c_address:02x} on {where}", address=self.address,
                           fix="check the wiring, the chip's power and its address (i2cdetect lists what answers)")

    def _read(self, register: int, length: int) -> bytes:
        raise NotImplementedError

    def _write(self, register: int, data: bytes) -> None:
        raise NotImplementedError

    def _release(self) -> None:
        raise NotImplementedError


class SmbusI2cPort(I2cPort):
    """A chip on a Linux I2C adapter ``/dev/i2c-N``, through smbus2."""

    def __init__(self, *, device: str, bus: int, i2c_address: int, tap: Tap | None) -> None:
        import smbus2

        path = f"/dev/i2c-{bus}"
        super().__init__(device=device, address=f"{path}:0x{i2c_address:02x}", bus_number=bus,
                         i2c_address=i2c_address, tap=tap)
        self._smbus2 = smbus2
        self._bus = smbus2.SMBus()
        try:
            self._bus.open(bus)
        except OSError as exc:
            self._bus.close()
            raise open_error(device, self.address, bus, exc) from exc

    def _read(self, register: int, length: int) -> bytes:
        try:
            if length <= SMBUS_BLOCK_MAX:
                return bytes(self._bus.read_i2c_block_data(self.i2c_address, register, length))
            write = self._smbus2.i2c_msg.write(self.i2c_address, [register])
            read = self._smbus2.i2c_msg.read(self.i2c_address, length)
            self._bus.i2c_rdwr(write, read)
            return bytes(read)
        except OSError as exc:
            raise transaction_error(self, exc) from exc

    def _write(self, register: int, data: bytes) -> None:
        try:
            if len(data) <= SMBUS_BLOCK_MAX:
                self._bus.write_i2c_block_data(self.i2c_address, register, list(data))
            else:
                self._bus.i2c_rdwr(self._smbus2.i2c_msg.write(self.i2c_address, bytes((register,)) + data))
        except OSError as exc:
            raise transaction_error(self, exc) from exc

    def _release(self) -> None:
        self._bus.close()


def transaction_error(port: I2cPort, exc: OSError) -> PortError:
    """The port error for an OSError from an smbus2 transaction on *port*."""
    bus = port.address.split(":")[0]
    if exc.errno in _NO_ACK_ERRNOS:
        return port._no_ack(bus)
    if exc.errno == errno.ETIMEDOUT:
        return PortTimeout(port.device, f"I2C transaction with 0x{port.i2c_address:02x} timed out on {bus}",
                           address=port.address, fix="check for a chip holding SDA low; power-cycle the bus")
    if exc.errno == errno.EBUSY:
        return PortIOError(port.device, f"0x{port.i2c_address:02x} on {bus} is claimed by a kernel driver",
                           address=port.address, fix="unbind the kernel driver or remove its device-tree overlay")
    if exc.errno in _GONE_ERRNOS:
        port._open = False
        return PortClosed(port.device, f"{bus} went away ({exc.strerror})", address=port.address,
                          fix="check the I2C adapter (USB adapters can be unplugged)")
    return PortIOError(port.device, f"I2C transaction failed: {exc}", address=port.address,
                       fix="check the wiring and the chip's address")


def open_error(device: str, address: str, bus: int, exc: OSError) -> PortUnavailable:
    """The PortUnavailable for an OSError raised while opening ``/dev/i2c-<bus>``."""
    path = f"/dev/i2c-{bus}"
    if exc.errno == errno.ENOENT:
        return PortUnavailable(device, f"{path} does not exist", address=address,
                               fix="enable I2C (raspi-config / dtparam=i2c_arm=on) or check the bus number")
    if exc.errno in (errno.EACCES, errno.EPERM):
        return PortUnavailable(device, f"no permission to open {path}", address=address,
                               fix="add the service user to group i2c and install the udev rule that makes "
                                   "/dev/i2c-* group i2c (u2sa install does both)")
    return PortUnavailable(device, f"cannot open {path}: {exc.strerror or exc}", address=address,
                           fix="check that the bus number names an I2C adapter (ls /dev/i2c-*)")


class MockI2cPort(I2cPort):
    """A chip on the mock I2C bus server, reached over its Unix socket."""

    def __init__(self, *, device: str, socket_path: str, i2c_address: int, tap: Tap | None,
                 timeout: float = MOCK_TIMEOUT_S) -> None:
        super().__init__(device=device, address=f"{MOCK_SCHEME}{socket_path}:0x{i2c_address:02x}",
                         bus_number=MOCK_BUS_NUMBER, i2c_address=i2c_address, tap=tap)
        self._where = f"{MOCK_SCHEME}{socket_path}"
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._sock.settimeout(timeout)
        try:
            self._sock.connect(socket_path)
        except OSError as exc:
            self._sock.close()
            why = exc.strerror or exc
            raise PortUnavailable(device, f"cannot connect to the mock I2C bus at {socket_path} ({why})",
                                  address=self.address,
                                  fix="start the mock I2C bus server (python -m u2sa_hw.mocks.i2c_bus) "
                                      "or check the socket path in the service config") from exc

    def _read(self, register: int, length: int) -> bytes:
        return self._exchange(REQUEST.pack(OP_READ, self.i2c_address, register, length), expect=length)

    def _write(self, register: int, data: bytes) -> None:
        self._exchange(REQUEST.pack(OP_WRITE, self.i2c_address, register, len(data)) + data, expect=0)

    def _exchange(self, request: bytes, *, expect: int) -> bytes:
        try:
            self._sock.sendall(request)
            # one recv for the whole answer (the server writes it at once): a syscall fewer per transaction
            reply = self._sock.recv(RESPONSE.size + expect)
            if len(reply) < RESPONSE.size:
                reply += self._recv_exact(RESPONSE.size - len(reply))
            status, length = RESPONSE.unpack_from(reply)
            payload = reply[RESPONSE.size:]
            if len(payload) < length:
                payload += self._recv_exact(length - len(payload))
            elif len(payload) > length:   # more than the answer says: the stream is out of step
                raise ConnectionError(f"the mock I2C bus answered {len(payload)} bytes after announcing {length}")
        except socket.timeout as exc:
            # The stream may now hold a late answer; drop the connection rather than misread it.
            self._gone()
            raise PortTimeout(self.device, f"mock I2C bus {self._where} did not answer", address=self.address,
                              fix="check that the mock I2C bus server is running") from exc
        except (ConnectionError, OSError) as exc:
            self._gone()
            raise self._closed(str(exc)) from exc
        if status == STATUS_OK and len(payload) == expect:
            return payload
        if status == STATUS_NACK:
            raise self._no_ack(self._where)
        if status == STATUS_EIO:
            raise PortIOError(self.device, f"I/O error (EIO) talking to 0x{self.i2c_address:02x} on {self._where}",
                              address=self.address, fix="check the wiring and pull-ups; retry the transaction")
        raise PortIOError(self.device, f"mock I2C bus answered {STATUS_NAMES.get(status, status)} with "
                                       f"{len(payload)} bytes", address=self.address,
                          fix="client and mock server disagree on the protocol: update both")

    def _recv_exact(self, size: int) -> bytes:
        chunks = bytearray()
        while len(chunks) < size:
            chunk = self._sock.recv(size - len(chunks))
            if not chunk:
                raise ConnectionResetError("the mock I2C bus server closed the connection")
            chunks += chunk
        return bytes(chunks)

    def _gone(self) -> None:
        self._open = False
        self._sock.close()

    def _closed(self, why: str) -> PortClosed:
        return PortClosed(self.device, f"mock I2C bus {self._where} went away ({why})", address=self.address,
                          fix="restart the mock I2C bus server; the driver reconnects")

    def _release(self) -> None:
        self._sock.close()


def parse_bus(bus: int | str, *, device: str) -> int | str:
    """Normalise a configured bus: an adapter number (int or digit string) or a mock socket path."""
    if isinstance(bus, bool):
        bus = str(bus)
    if isinstance(bus, int) and bus >= 0:
        return bus
    if isinstance(bus, str):
        text = bus.strip()
        if text.isdigit():
            return int(text)
        if text.startswith(MOCK_SCHEME) and len(text) > len(MOCK_SCHEME):
            return text
    raise PortUnavailable(device, f"unknown I2C bus {bus!r}", address=str(bus),
                          fix='use an adapter number (1 for /dev/i2c-1) or "mock:/path/to/bus.sock"')


def open_i2c(*, device: str, bus: int | str, address: int, tap: Tap | None = None,
             timeout: float | None = None) -> I2cPort:
    """Open the chip at 7-bit *address* on *bus* (int N -> /dev/i2c-N, "mock:/path" -> mock server).

    *timeout* (mock bus only; None: :data:`MOCK_TIMEOUT_S`) is how long the client waits for the
    server's answer before it drops the connection (``PortTimeout``); a replay's bus holds a data
    read until its player releases it, so its addresses carry a longer one (``timeout=`` in a
    ``mock+i2c`` address). A real adapter's timeout is its kernel driver's: giving one is a ValueError.
    """
    where = parse_bus(bus, device=device)
    if timeout is not None and (isinstance(where, int) or not timeout > 0):
        raise ValueError(f"{device}: an I2C client timeout is for a mock bus and must be > 0 s, got {timeout!r} "
                         f"on bus {bus!r}")
    if isinstance(address, bool) or not isinstance(address, int) or not 0x03 <= address <= 0x77:
        raise PortUnavailable(device, f"I2C address {address!r} is not a 7-bit device address (0x03..0x77)",
                              address=f"{bus}:{address}", fix="use the chip's address from its datasheet, e.g. 0x68")
    return open_i2c_chip(device=device, bus=where if isinstance(where, int) else where[len(MOCK_SCHEME):],
                         chip=address, tap=tap, timeout=timeout)


def open_i2c_chip(*, device: str, bus: int | str, chip: int, tap: Tap | None = None,
                  timeout: float | None = None) -> I2cPort:
    """Open *chip* (a checked 7-bit address) on *bus*: an adapter number (int: ``/dev/i2c-N`` through smbus2)
    or the mock bus server's socket path (str). The typed parts of a parsed address go here as they are;
    *timeout* is the mock client's wait for an answer (None: :data:`MOCK_TIMEOUT_S`)."""
    if isinstance(bus, int):
        return SmbusI2cPort(device=device, bus=bus, i2c_address=chip, tap=tap)
    return MockI2cPort(device=device, socket_path=bus, i2c_address=chip, tap=tap,
                       timeout=MOCK_TIMEOUT_S if timeout is None else timeout)

