"""CAN port contract: one suite over python-can's virtual and udp_multicast buses, the
unpluggable adapter (u2sa_hw.mocks.can_adapter) and SocketCAN on a vcan interface when one
exists (skipped with the reason otherwise: this machine has no vcan module), plus
udp_multicast across processes, bad datagrams, and the SocketCAN open hints."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import uuid
from pathlib import Path
from typing import Iterator

import can
import pytest

from u2sa_hw.mocks import can_adapter
from u2sa_hw.ports import PortClosed, PortIOError, PortUnavailable, open_can
from u2sa_hw.ports.address import AddressError, parse_address
from u2sa_hw.ports.can.clock import CanDeviceClock
from u2sa_hw.ports.can.port import CanPort
from u2sa_hw.ports.tap import RX, TX
from u2sa_hw.bus.udp_ports import private_udp_port

GROUP = "239.74.163.2"  # python-can's default IPv4 group


VCAN = os.environ.get("U2SA_TEST_VCAN", "vcan0")


def socketcan_missing(channel: str) -> str:
    """Why SocketCAN on *channel* cannot be tested here ("" when it can)."""
    if not hasattr(socket, "AF_CAN"):
        return "this Python has no AF_CAN"
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except OSError as exc:
        return f"this kernel has no SocketCAN ({exc.strerror}): modprobe can can_raw vcan"
    if not Path(f"/sys/class/net/{channel}").exists():
        return (f"no CAN interface {channel}: `ip link add dev {channel} type vcan && ip link set {channel} up` "
                "(modprobe vcan first), or name another one in U2SA_TEST_VCAN")
    return ""


class CanBackend:
    """How to reach one python-can interface from a test: options, a missing device, and a loss."""

    def __init__(self, interface: str) -> None:
        self.interface = interface
        self.options: dict = {}
        self.missing: dict | None = None
        if interface == "virtual":
            self.channel = f"u2sa-test-{uuid.uuid4().hex[:8]}"  # a virtual channel always exists
        elif interface == can_adapter.INTERFACE:
            self.channel = f"u2sa-test-{uuid.uuid4().hex[:8]}"
        elif interface == "socketcan":
            self.channel = VCAN
            self.missing = {"channel": "u2sa-none0"}
        else:
            self.channel = GROUP
            self.options = {"port": private_udp_port()}
            self.missing = {"channel": "no-such-group.invalid"}

    def open(self, device: str, **kwargs) -> CanPort:
        return open_can(device=device, interface=self.interface, channel=self.channel, **self.options, **kwargs)

    def lose(self, port: CanPort) -> None:
        """Take the bus away under *port*: unplug the adapter, or shut the python-can bus down
        underneath the port (what a vanished interface looks like to a double that cannot be unplugged)."""
        if self.interface == can_adapter.INTERFACE:
            can_adapter.unplug(self.channel)
        else:
            port._bus.shutdown()

    def cleanup(self) -> None:
        if self.interface == can_adapter.INTERFACE:
            can_adapter.replug(self.channel)


@pytest.fixture(params=["virtual", "udp_multicast", can_adapter.register(), "socketcan"])
def backend(request: pytest.FixtureRequest) -> Iterator[CanBackend]:
    """Each CAN test double python-can ships, the unpluggable adapter, and SocketCAN where a vcan exists."""
    if request.param == "socketcan" and (why := socketcan_missing(VCAN)):
        pytest.skip(f"SocketCAN contract not run: {why}")
    b = CanBackend(request.param)
    yield b
    b.cleanup()


@pytest.fixture
def pair(backend: CanBackend) -> Iterator[tuple[CanPort, CanPort, list, list]]:
    """A driver port and a device port on one bus, each with its tap records."""
    driver_taps: list = []
    device_taps: list = []
    driver = backend.open("motor", tap=driver_taps.append)
    device = backend.open("odrive-mock", tap=device_taps.append)
    yield driver, device, driver_taps, device_taps
    driver.close()
    device.close()


def recv_id(port: CanPort, arbitration_id: int, timeout: float = 5.0) -> can.Message:
    """The next frame with *arbitration_id* (udp_multicast also hands a port its own frames)."""
    for _ in range(1000):
        msg = port.recv(timeout)
        assert msg is not None, f"no frame 0x{arbitration_id:x} within {timeout} s"
        if msg.arbitration_id == arbitration_id:
            return msg
    pytest.fail(f"frame 0x{arbitration_id:x} never came")


class TestCanContract:
    """What every CAN backend must do."""

    def test_frames_cross_both_ways_and_are_tapped(self, pair) -> None:
        driver, device, driver_taps, _ = pair
        driver.send(can.Message(arbitration_id=0x00C, data=b"\x01\x02\x03\x04", is_extended_id=False))
        got = recv_id(device, 0x00C)
        assert bytes(got.data) == b"\x01\x02\x03\x04" and not got.is_extended_id
        device.send(can.Message(arbitration_id=0x1ABCDE0, data=b"\xff" * 8, is_extended_id=True))
        reply = recv_id(driver, 0x1ABCDE0)
        assert reply.is_extended_id and bytes(reply.data) == b"\xff" * 8

        tx = [r for r in driver_taps if r.direction == TX]
        rx = [r for r in driver_taps if r.direction == RX and r.arbitration_id == 0x1ABCDE0]
        assert len(tx) == 1 and tx[0].device == "motor"
        assert (tx[0].arbitration_id, tx[0].is_extended_id, tx[0].dlc, tx[0].data) == (0x00C, False, 4, b"\x01\x02\x03\x04")
        assert len(rx) == 1
        assert (rx[0].is_extended_id, rx[0].dlc, rx[0].length, rx[0].data) == (True, 8, 8, b"\xff" * 8)
        assert rx[0].bus_timestamp > 0

    def test_remote_frames_are_tapped_as_remote(self, pair) -> None:
        driver, device, driver_taps, device_taps = pair
        driver.send(can.Message(arbitration_id=0x009, is_remote_frame=True, dlc=8, is_extended_id=False))
        got = recv_id(device, 0x009)
        assert got.is_remote_frame
        assert driver_taps[-1].is_remote_frame and driver_taps[-1].dlc == 8 and driver_taps[-1].length == 0
        assert device_taps[-1].is_remote_frame and device_taps[-1].direction == RX

    def test_recv_timeout_returns_none(self, backend: CanBackend) -> None:
        port = backend.open("motor")
        try:
            assert port.recv(0.05) is None
        finally:
            port.close()

    def test_losing_the_bus_raises_port_closed(self, backend: CanBackend, pair) -> None:
        driver, _, _, _ = pair
        backend.lose(driver)
        with pytest.raises(PortClosed) as info:
            driver.recv(0.05)
        assert info.value.device == "motor" and info.value.fix
        assert not driver.is_open
        with pytest.raises(PortClosed):
            driver.send(can.Message(arbitration_id=1, data=b"\x00", is_extended_id=False))

    def test_missing_device_is_unavailable_with_a_fix(self, backend: CanBackend) -> None:
        if backend.interface == can_adapter.INTERFACE:
            can_adapter.unplug(backend.channel)
            missing = {"channel": backend.channel}
        elif backend.missing is None:
            pytest.skip("a virtual channel cannot be missing: python-can creates it on first use")
        else:
            missing = backend.missing
        with pytest.raises(PortUnavailable) as info:
            open_can(device="motor", interface=backend.interface, **missing)
        assert info.value.device == "motor" and "motor" in str(info.value) and info.value.fix

    def test_closed_port_refuses_io(self, backend: CanBackend) -> None:
        port = backend.open("motor")
        port.close()
        port.close()
        with pytest.raises(PortClosed):
            port.recv(0.01)


class TestUdpMulticastSpecifics:
    """The cross-process bus: real datagrams from other processes, good and bad."""

    def test_frames_from_another_process_arrive(self) -> None:
        backend = CanBackend("udp_multicast")
        port = backend.open("motor")
        code = ("import can\n"
                f"bus = can.Bus(interface='udp_multicast', channel={GROUP!r}, port={backend.options['port']})\n"
                "bus.send(can.Message(arbitration_id=0x321, data=b'\\x05\\x06', is_extended_id=False))\n"
                "bus.shutdown()\n")
        try:
            subprocess.run([sys.executable, "-c", code], check=True, timeout=30)
            got = recv_id(port, 0x321)
            assert bytes(got.data) == b"\x05\x06"
        finally:
            port.close()

    def test_undecodable_datagram_is_an_io_error_and_the_port_lives_on(self) -> None:
        backend = CanBackend("udp_multicast")
        port = backend.open("motor")
        sender = backend.open("peer")
        raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            raw.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
            raw.sendto(b"\x00garbage\xff", (GROUP, backend.options["port"]))
            with pytest.raises(PortIOError) as info:
                port.recv(5.0)
            assert "motor" in str(info.value)
            sender.send(can.Message(arbitration_id=0x42, data=b"\x01", is_extended_id=False))
            assert recv_id(port, 0x42).data == bytearray(b"\x01")
        finally:
            raw.close()
            port.close()
            sender.close()

    def test_fd_frame_on_a_classic_bus_is_an_io_error(self) -> None:
        backend = CanBackend("udp_multicast")
        port = backend.open("motor", fd=False)
        try:
            with pytest.raises(PortIOError):
                port.send(can.Message(arbitration_id=0x42, data=bytes(12), is_fd=True, is_extended_id=False))
            assert port.is_open
        finally:
            port.close()


class TestStampedClock:
    """clock=stamped (a replay's mock bus): frames keep their senders' stamps and the port's clock follows them."""

    def test_frames_keep_the_recorded_stamps_and_the_clock_follows_them(self) -> None:
        udp_port = private_udp_port()
        port = open_can(device="wheels", interface="udp_multicast", channel=GROUP, port=udp_port, clock="stamped")
        plain = open_can(device="other", interface="udp_multicast", channel=GROUP, port=udp_port)
        sender = can.Bus(interface="udp_multicast", channel=GROUP, port=udp_port)
        try:
            for stamp in (1000.0, 1000.25):
                sender.send(can.Message(arbitration_id=0x9, data=bytes(8), is_extended_id=False, timestamp=stamp))
            assert port.clock is not None
            port.clock = CanDeviceClock(grace_s=1e9)   # no wall-clock run-on, however slow this machine is
            first = recv_id(port, 0x9)
            at_first = port.now()
            second = recv_id(port, 0x9)
            assert (first.timestamp, second.timestamp) == (1000.0, 1000.25)
            # the clock moves by the stamps' interval, whatever time the frames took to arrive
            assert port.now() - at_first == pytest.approx(0.25)
            # a frame its sender did not stamp (the driver's own, heard back) keeps 0 and leaves the clock
            at_second = port.now()
            sender.send(can.Message(arbitration_id=0x9, data=bytes(8), is_extended_id=False))
            assert recv_id(port, 0x9).timestamp == 0.0
            assert port.now() == at_second
            assert recv_id(plain, 0x9).timestamp != 1000.0   # a plain bus stamps its receive time
            assert plain.clock is None
        finally:
            sender.shutdown()
            port.close()
            plain.close()

    def test_a_silent_device_clock_runs_on_with_the_wall_clock(self) -> None:
        held, running = CanDeviceClock(grace_s=1e9), CanDeviceClock(grace_s=0.0)
        t0 = held.frame(50.0)
        assert held.frame(50.5) - t0 == pytest.approx(0.5)
        assert held.now() == held.frame(50.5)             # held at the last stamp while frames keep coming
        assert held.frame(49.0) == held.now()             # never backwards
        t1 = running.frame(50.0)
        assert running.now() >= t1                         # past its grace: the wall clock moves it on

    def test_only_a_mock_udp_multicast_address_takes_a_device_clock(self) -> None:
        assert parse_address(f"mock+can://udp_multicast/{GROUP}?clock=stamped", device="w").bus_options["clock"] \
            == "stamped"
        for url in ("can://socketcan/can0?clock=stamped", f"can://udp_multicast/{GROUP}?clock=stamped",
                    "mock+can://virtual/x?clock=stamped", f"mock+can://udp_multicast/{GROUP}?clock=wall"):
            with pytest.raises(AddressError, match="clock"):
                parse_address(url, device="w")
        with pytest.raises(PortUnavailable, match="clock"):
            open_can(device="w", interface="socketcan", channel="can0", clock="stamped")


def test_socketcan_without_the_interface_says_how_to_bring_it_up() -> None:
    with pytest.raises(PortUnavailable) as info:
        open_can(device="motor", interface="socketcan", channel="u2sa-none0", bitrate=250000)
    fix = info.value.fix
    # This machine has no SocketCAN module (EAFNOSUPPORT); a vehicle without the adapter has ENODEV.
    assert "modprobe can" in fix or "ip link set u2sa-none0 up type can bitrate 250000" in fix
    assert info.value.address == "socketcan:u2sa-none0"


def test_unknown_interface_is_unavailable() -> None:
    with pytest.raises(PortUnavailable) as info:
        open_can(device="motor", interface="no-such-interface", channel="can0")
    assert "socketcan" in info.value.fix
