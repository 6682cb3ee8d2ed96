"""Serial port contract: one suite over a real pty, pyserial's loop:// and socket:// (a TCP
serial server), plus the pty-only cases (busy, permission, dangling symlink, garbage)."""

from __future__ import annotations

import grp
import os
import select
import socket
import time
from pathlib import Path
from typing import Callable, Iterator

import pytest

from conftest import wait_until
from u2sa_hw.ports import PortClosed, PortUnavailable, open_serial
from u2sa_hw.ports.serial import port as serial_port
from u2sa_hw.ports.tap import RX, TX


class PtyPeer:
    """A pty pair; the test holds the master like a mock device, the port opens a symlink."""

    def __init__(self, tmp_path: Path) -> None:
        self.master, slave = os.openpty()
        self.slave_path = os.ttyname(slave)
        os.close(slave)
        self.address = str(tmp_path / "gps")
        os.symlink(self.slave_path, self.address)
        self.missing = str(tmp_path / "stopped-mock")
        os.symlink("/dev/pts/999999", self.missing)  # what a stopped mock device leaves behind

    def open(self, tap: Callable[[object], None] | None = None, **options: object) -> serial_port.SerialPort:
        return open_serial(self.address, device="gps", tap=tap, **options)

    def send(self, data: bytes) -> None:
        os.write(self.master, data)

    def receive(self, size: int, timeout: float = 5.0) -> bytes:
        got = b""
        deadline = time.monotonic() + timeout
        while len(got) < size and time.monotonic() < deadline:
            if select.select([self.master], [], [], 0.05)[0]:
                got += os.read(self.master, size - len(got))
        return got

    def lose(self) -> None:
        os.close(self.master)
        self.master = -1
        os.unlink(self.address)

    def cleanup(self) -> None:
        if self.master >= 0:
            os.close(self.master)


class LoopPeer:
    """pyserial's loop://: what the port writes comes back to it, so the peer is the port."""

    address = "loop://"
    missing = "nosuchscheme://gps"

    def __init__(self) -> None:
        self.port: serial_port.SerialPort | None = None

    def open(self, tap: Callable[[object], None] | None = None, **options: object) -> serial_port.SerialPort:
        self.port = open_serial(self.address, device="gps", tap=tap, **options)
        return self.port

    def send(self, data: bytes) -> None:
        assert self.port is not None
        self.port.write(data)

    def receive(self, size: int, timeout: float = 5.0) -> bytes:
        assert self.port is not None
        got = b""
        deadline = time.monotonic() + timeout
        while len(got) < size and time.monotonic() < deadline:
            got += self.port.read(size - len(got))
        return got

    def lose(self) -> None:
        # A loopback cannot be unplugged; a handle closed underneath the port is what a
        # vanished device looks like to pyserial.
        assert self.port is not None
        self.port._serial.close()

    def cleanup(self) -> None:
        pass


class SocketPeer:
    """socket://host:port against a TCP server in the test (how ser2net exposes a device)."""

    def __init__(self) -> None:
        self.server = socket.create_server(("127.0.0.1", 0))
        self.address = f"socket://127.0.0.1:{self.server.getsockname()[1]}"
        free = socket.create_server(("127.0.0.1", 0))
        self.missing = f"socket://127.0.0.1:{free.getsockname()[1]}"
        free.close()
        self.conn: socket.socket | None = None

    def open(self, tap: Callable[[object], None] | None = None, **options: object) -> serial_port.SerialPort:
        port = open_serial(self.address, device="gps", tap=tap, **options)
        self.server.settimeout(5)
        self.conn, _ = self.server.accept()
        self.conn.settimeout(0.05)
        return port

    def send(self, data: bytes) -> None:
        assert self.conn is not None
        self.conn.sendall(data)

    def receive(self, size: int, timeout: float = 5.0) -> bytes:
        assert self.conn is not None
        got = b""
        deadline = time.monotonic() + timeout
        while len(got) < size and time.monotonic() < deadline:
            try:
                got += self.conn.recv(size - len(got))
            except TimeoutError:
                pass
        return got

    def lose(self) -> None:
        assert self.conn is not None
        self.conn.close()

    def cleanup(self) -> None:
        if self.conn is not None:
            self.conn.close()
        self.server.close()


@pytest.fixture(params=["pty", "loop", "socket"])
def peer(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[object]:
    """The device end of each serial backend."""
    made = {"pty": lambda: PtyPeer(tmp_path), "loop": LoopPeer, "socket": SocketPeer}[request.param]()
    yield made
    made.cleanup()


def read_until_closed(port: serial_port.SerialPort, timeout: float = 5.0) -> PortClosed:
    """Keep reading until the port reports the loss; fail if it never does."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            port.read(64)
        except PortClosed as exc:
            return exc
    pytest.fail("reading a lost device never raised PortClosed")


class TestSerialContract:
    """What every serial backend must do."""

    def test_exchange_is_tapped_both_ways(self, peer) -> None:
        records: list = []
        port = peer.open(records.append)
        try:
            assert port.write(b"ping\r\n") == 6
            assert peer.receive(6) == b"ping\r\n"
            peer.send(b"$GPGGA,pong*00\r\n")
            line = wait_until(port.readline, message="a line from the device")
            assert line == b"$GPGGA,pong*00\r\n"
        finally:
            port.close()
        assert all(r.device == "gps" and r.length == len(r.data) for r in records)
        assert b"ping\r\n" in b"".join(r.data for r in records if r.direction == TX)
        assert b"".join(r.data for r in records if r.direction == RX).endswith(b"$GPGGA,pong*00\r\n")

    def test_readline_keeps_a_partial_line_for_later(self, peer) -> None:
        records: list = []
        port = peer.open(records.append, timeout=0.05)
        received = lambda: b"".join(r.data for r in records if r.direction == RX)  # noqa: E731
        try:
            peer.send(b"$GPRMC,1")
            wait_until(lambda: port.readline() == b"" and received() == b"$GPRMC,1",
                       message="the partial line to be read (and kept)")
            peer.send(b"23*00\r\nnext")
            assert wait_until(port.readline, message="the completed line") == b"$GPRMC,123*00\r\n"
            assert port.read(4) == b"next"
            assert port.read(4) == b""
        finally:
            port.close()

    def test_losing_the_device_raises_port_closed(self, peer) -> None:
        port = peer.open()
        peer.lose()
        exc = read_until_closed(port)
        assert exc.device == "gps" and "fix:" in str(exc)
        assert not port.is_open
        with pytest.raises(PortClosed):
            port.write(b"x")

    def test_missing_device_is_unavailable_with_a_fix(self, peer) -> None:
        with pytest.raises(PortUnavailable) as info:
            open_serial(peer.missing, device="gps")
        assert info.value.device == "gps" and info.value.address == peer.missing
        assert "gps" in str(info.value) and info.value.fix

    def test_closed_port_refuses_io(self, peer) -> None:
        port = peer.open()
        port.close()
        port.close()
        with pytest.raises(PortClosed):
            port.read()
        with pytest.raises(PortClosed):
            port.write(b"x")


class TestPtySpecifics:
    """Cases only a device node shows."""

    def test_second_open_is_busy(self, tmp_path: Path) -> None:
        pty = PtyPeer(tmp_path)
        port = pty.open()
        try:
            with pytest.raises(PortUnavailable) as info:
                pty.open()
            assert "busy" in str(info.value) and "fuser" in info.value.fix
        finally:
            port.close()
            pty.cleanup()

    def test_dangling_symlink_says_the_device_is_gone(self, tmp_path: Path) -> None:
        pty = PtyPeer(tmp_path)
        with pytest.raises(PortUnavailable) as info:
            open_serial(pty.missing, device="gps")
        assert "dangling symlink" in info.value.fix
        pty.cleanup()

    def test_no_permission_names_the_group(self, tmp_path: Path) -> None:
        pty = PtyPeer(tmp_path)
        os.chmod(pty.slave_path, 0o600 if os.geteuid() == 0 else 0)
        reader, writer = os.pipe()
        child = os.fork()
        if child == 0:  # root opens anything, so the child drops to nobody first
            fix = "opened"
            try:
                if os.geteuid() == 0:
                    os.setgroups([])
                    os.setgid(65534)
                    os.setuid(65534)
                open_serial(pty.slave_path, device="gps").close()
            except PortUnavailable as exc:
                fix = exc.fix
            finally:
                os.write(writer, fix.encode())
                os._exit(0)
        os.close(writer)
        os.waitpid(child, 0)
        with os.fdopen(reader, "rb") as pipe:
            fix = pipe.read().decode()
        group = grp.getgrgid(os.stat(pty.slave_path).st_gid).gr_name
        pty.cleanup()
        assert fix != "opened", "nobody could open a 0600 root pty"
        expected = "udev rule" if group == "root" else f"group '{group}'"
        assert fix.startswith(f"no permission on {pty.slave_path}") or "belongs to group root" in fix
        assert expected in fix

    def test_write_after_master_closed_raises_port_closed(self, tmp_path: Path) -> None:
        pty = PtyPeer(tmp_path)
        port = pty.open()
        pty.lose()
        with pytest.raises(PortClosed):
            port.write(b"$PMTK220,100*2F\r\n")

    def test_garbage_without_newlines_comes_back_in_bounded_chunks(self, tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
        monkeypatch.setattr(serial_port, "MAX_LINE", 64)
        pty = PtyPeer(tmp_path)
        port = pty.open()
        try:
            pty.send(bytes(range(1, 10)) * 20)  # 180 bytes, no b"\n"
            chunk = wait_until(port.readline, message="a bounded chunk")
            assert len(chunk) == 64 and b"\n" not in chunk
        finally:
            port.close()
            pty.cleanup()

    def test_bad_settings_are_unavailable(self, tmp_path: Path) -> None:
        pty = PtyPeer(tmp_path)
        with pytest.raises(PortUnavailable) as info:
            pty.open(baudrate=-9600)
        assert "baudrate" in info.value.fix
        pty.cleanup()
