"""Mock I2C bus: register-level chip models behind a Unix stream socket.

``MockI2cBus(socket_path=...)`` hosts chip models (subclasses of
:class:`u2sa_hw.mocks.i2c_chip.RegisterChip`) at
7-bit addresses. Drivers reach it through ``open_i2c(bus="mock:<socket_path>", ...)``;
the wire protocol is documented (and its constants defined) in u2sa_hw/ports/i2c/wire.py
and docs/i2c-devices.md. One thread per client; one transaction at a time on the bus, as
on a real I2C bus. An address with no chip NACKs, like an empty address on real hardware.

Run standalone (e.g. from a test in another process, or for a bench session)::

    python -m u2sa_hw.mocks.i2c_bus --socket /tmp/i2c.sock --chip mpu9250@0x68 --chip pca9685@0x40
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import socket
import stat
import threading
import time
from collections import deque

from u2sa_hw.mocks.bno055_chip import Bno055Chip
from u2sa_hw.mocks.i2c_chip import (HISTORY_LIMIT, STANDARD_GRAVITY, I2cChip, I2cTransaction, RegisterChip,
                                   RestingVehicle, Vehicle)
from u2sa_hw.mocks.mpu9250_chip import Mpu9250Chip
from u2sa_hw.mocks.pca9685_chip import Pca9685Chip
from u2sa_hw.ports.i2c.wire import MAX_TRANSFER, OP_READ, OP_WRITE, REQUEST, RESPONSE, STATUS_BAD_REQUEST, STATUS_NACK
from u2sa_hw.ports.i2c.port import MOCK_SCHEME

__all__ = ["HISTORY_LIMIT", "STANDARD_GRAVITY", "I2cChip", "I2cTransaction", "MockI2cBus", "RegisterChip",
           "RestingVehicle", "Vehicle", "build_chip"]   # the chip base is re-exported for existing imports
log = logging.getLogger("u2sa_hw.mocks.i2c_bus")


class MockI2cBus:
    """A mock I2C bus hosting chip models, served on a Unix stream socket."""

    def __init__(self, *, socket_path: str) -> None:
        self.socket_path = os.fspath(socket_path)
        self.history: deque[I2cTransaction] = deque(maxlen=HISTORY_LIMIT)
        self.bad_requests = 0
        self._chips: dict[int, I2cChip] = {}
        self._bus_lock = threading.Lock()
        self._clients: set[socket.socket] = set()
        self._clients_lock = threading.Lock()
        self._listener: socket.socket | None = None
        self._accept_thread: threading.Thread | None = None

    @property
    def address(self) -> str:
        """The bus address a driver config names: ``mock:<socket_path>``."""
        return f"{MOCK_SCHEME}{self.socket_path}"

    def add(self, chip: I2cChip) -> I2cChip:
        """Put *chip* on the bus at its address; returns it."""
        with self._bus_lock:
            if chip.address in self._chips:
                raise ValueError(f"mock I2C bus {self.socket_path}: address 0x{chip.address:02x} is taken")
            self._chips[chip.address] = chip
        return chip

    def remove(self, address: int) -> None:
        """Take the chip at *address* off the bus (it then NACKs, like an unplugged chip)."""
        with self._bus_lock:
            self._chips.pop(address, None)

    def chip(self, address: int) -> I2cChip:
        """The chip model at *address*."""
        return self._chips[address]

    def start(self) -> "MockI2cBus":
        """Listen on the socket and serve clients on threads."""
        if self._listener is not None:
            return self
        self._unlink_stale_socket()
        listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        listener.bind(self.socket_path)
        listener.listen(16)
        self._listener = listener
        self._accept_thread = threading.Thread(target=self._accept_loop, name="mock-i2c-accept", daemon=True)
        self._accept_thread.start()
        return self

    def stop(self) -> None:
        """Stop listening, drop every client (they see the bus go away) and remove the socket."""
        listener, self._listener = self._listener, None
        if listener is None:
            return
        try:
            listener.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        listener.close()
        self.disconnect_clients()
        if self._accept_thread is not None:
            self._accept_thread.join(timeout=5)
        try:
            os.unlink(self.socket_path)
        except FileNotFoundError:
            pass

    def disconnect_clients(self) -> None:
        """Fault: close every client connection (drivers see PortClosed and must reconnect)."""
        with self._clients_lock:
            clients, self._clients = self._clients, set()
        for conn in clients:
            try:
                conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            conn.close()

    def __enter__(self) -> "MockI2cBus":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def transact(self, op: int, address: int, register: int, length: int, data: bytes) -> tuple[int, bytes]:
        """Run one transaction on the bus (what each client request becomes)."""
        with self._bus_lock:
            chip = self._chips.get(address)
            if chip is None:
                status, out = STATUS_NACK, b""
            else:
                status, out = chip.handle(op, register, length, data)
            self.history.append(I2cTransaction(time.monotonic(), address, op, register,
                                               out if op == OP_READ else bytes(data), status))
            return status, out

    def _unlink_stale_socket(self) -> None:
        try:
            mode = os.lstat(self.socket_path).st_mode
        except FileNotFoundError:
            return
        if not stat.S_ISSOCK(mode):
            raise FileExistsError(f"{self.socket_path} exists and is not a socket: choose another path")
        os.unlink(self.socket_path)

    def _accept_loop(self) -> None:
        while True:
            listener = self._listener
            if listener is None:
                return
            try:
                conn, _ = listener.accept()
            except OSError:
                return
            with self._clients_lock:
                self._clients.add(conn)
            threading.Thread(target=self._serve_client, args=(conn,), name="mock-i2c-client", daemon=True).start()

    def _serve_client(self, conn: socket.socket) -> None:
        try:
            while True:
                header = _recv_exact(conn, REQUEST.size)
                if header is None:
                    return
                op, address, register, length = REQUEST.unpack(header)
                if op not in (OP_READ, OP_WRITE) or not 1 <= length <= MAX_TRANSFER or address > 0x7F:
                    # A bad header leaves us unable to find the next request: answer and hang up.
                    self._bad_request(f"op={op} address={address:#x} length={length}")
                    conn.sendall(RESPONSE.pack(STATUS_BAD_REQUEST, 0))
                    return
                data = b""
                if op == OP_WRITE:
                    data = _recv_exact(conn, length)
                    if data is None:
                        return
                status, out = self.transact(op, address, register, length, data)
                conn.sendall(RESPONSE.pack(status, len(out)) + out)
        except OSError:
            return
        finally:
            with self._clients_lock:
                self._clients.discard(conn)
            conn.close()

    def _bad_request(self, what: str) -> None:
        self.bad_requests += 1
        log.warning("mock I2C bus %s: dropped a bad request (%s); %d so far", self.socket_path, what,
                    self.bad_requests)


def _recv_exact(conn: socket.socket, size: int) -> bytes | None:
    """Exactly *size* bytes, or None when the peer closed the connection."""
    buf = bytearray()
    while len(buf) < size:
        chunk = conn.recv(size - len(buf))
        if not chunk:
            return None
        buf += chunk
    return bytes(buf)


def build_chip(spec: str, *, seed: int) -> RegisterChip:
    """A chip model from ``kind@address``: mpu6050, mpu6500, mpu9250, bno055 or pca9685."""
    kind, _, addr_text = spec.partition("@")
    address = int(addr_text, 0) if addr_text else None
    if kind in ("mpu6050", "mpu6500", "mpu9250"):
        return Mpu9250Chip(address=address or 0x68, variant=kind, seed=seed)
    if kind == "bno055":
        return Bno055Chip(address=address or 0x28, seed=seed)
    if kind == "pca9685":
        return Pca9685Chip(address=address or 0x40)
    raise ValueError(f"unknown chip kind {kind!r}: use mpu6050, mpu6500, mpu9250, bno055 or pca9685")


def main(argv: list[str] | None = None) -> int:
    """Serve a mock I2C bus with chips at rest until SIGTERM/SIGINT."""
    parser = argparse.ArgumentParser(prog="python -m u2sa_hw.mocks.i2c_bus", description=main.__doc__)
    parser.add_argument("--socket", required=True, help="Unix socket path to serve on")
    parser.add_argument("--chip", action="append", default=[], metavar="KIND@ADDR",
                        help="chip to host, e.g. mpu9250@0x68 (repeatable)")
    parser.add_argument("--seed", type=int, default=1, help="noise seed of the sensor chips")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    bus = MockI2cBus(socket_path=args.socket)
    for spec in args.chip:
        bus.add(build_chip(spec, seed=args.seed))
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    with bus:
        print(f"mock I2C bus serving {bus.address}", flush=True)
        while not done.wait(1.0):
            pass
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
