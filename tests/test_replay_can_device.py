"""The replay CAN device (hil/replay_buses.py) over a real UDP multicast bus: recorded RX frames reach a
member of the bus (as the replayed driver's, ``clock=stamped``) in order with their recorded times,
every field of a frame survives the replay's datagram, a python-can udp_multicast member is still
understood, a datagram that is no frame is an error of one receive, echoes of the recorded driver's own frames are left out,
the device counts the other members' frames but never its own, and the --fast pacing keeps the
driver's socket well under its receive buffer.
"""

from __future__ import annotations

import socket
import struct
from typing import Iterator

import pytest
from conftest import wait_until

from u2sa_hw.hil.replay_buses import CAN_BACKLOG_BYTES, CAN_CHECK_EVERY, CAN_GROUP, ReplayCanDevice
from u2sa_hw.lcmtypes import RawCanFrame
from u2sa_hw.ports.can.clock import StampedUdpMulticastBus, pack_frame, unpack_frame
from u2sa_hw.ports.tap import RX, TX
from u2sa_hw.bus.udp_ports import private_udp_port

SO_MEMINFO = 55   # Linux: struct sk_meminfo, [0] bytes queued (truesize), [1] the receive buffer


def frame(arbitration_id: int, data: bytes, *, direction: int = RX, stamp: float = 0.0) -> RawCanFrame:
    """A recorded CAN frame as the player hands it to the device."""
    rec = RawCanFrame()
    rec.direction, rec.arbitration_id, rec.dlc, rec.length = direction, arbitration_id, len(data), len(data)
    rec.data, rec.bus_timestamp = data, stamp
    return rec


@pytest.fixture
def bus_pair() -> Iterator[tuple[ReplayCanDevice, StampedUdpMulticastBus]]:
    """The replay device and a member of its bus opened as the replayed driver opens it."""
    port = private_udp_port()
    device = ReplayCanDevice(name="wheels", port=port)
    device.start()
    driver = StampedUdpMulticastBus(channel=CAN_GROUP, port=port)
    try:
        yield device, driver
    finally:
        driver.shutdown()
        device.stop()


def meminfo(bus: StampedUdpMulticastBus) -> tuple[int, ...]:
    """The kernel's memory counters of *bus*'s socket."""
    with socket.socket(fileno=socket.dup(bus.fileno())) as sock:
        return struct.unpack("9I", sock.getsockopt(socket.SOL_SOCKET, SO_MEMINFO, 36))


def test_frames_reach_the_driver_in_order_with_their_recorded_times(bus_pair) -> None:
    device, driver = bus_pair
    sent = [(0x9 + (n << 5), bytes((n, 1, 2, 3, 4, 5, 6, 7)), 1000.0 + n / 100) for n in range(5)]
    for arbitration_id, data, stamp in sent:
        device.feed(frame(arbitration_id, data, stamp=stamp))
    got = [driver.recv(5.0) for _ in sent]
    assert [(m.arbitration_id, bytes(m.data), m.timestamp, m.dlc, m.is_extended_id) for m in got] == \
        [(a, d, s, 8, False) for a, d, s in sent]
    assert device.report()["fed"] == 5


def test_echoes_of_the_recorded_driver_are_left_out(bus_pair) -> None:
    device, driver = bus_pair
    device.feed(frame(0x0C, b"\x01\x02", direction=TX))      # the recorded driver sent it ...
    device.feed(frame(0x0C, b"\x01\x02", stamp=5.0))         # ... and heard it back: not sent again
    device.feed(frame(0x0C, b"\x01\x02", stamp=6.0))         # the same frame again: a node's, sent
    assert driver.recv(5.0).timestamp == 6.0
    report = device.report()
    assert (report["recorded_tx"], report["echoes_skipped"], report["fed"]) == (1, 1, 1), report


def test_counts_the_other_members_frames_not_its_own(bus_pair) -> None:
    device, driver = bus_pair
    import can

    for n in range(4):
        device.feed(frame(0x29, bytes((n,)), stamp=float(n)))
    assert [driver.recv(5.0).data[0] for _ in range(4)] == [0, 1, 2, 3]
    for n in range(3):
        driver.send(can.Message(arbitration_id=0x2C, data=bytes((n,)), is_extended_id=False))
    wait_until(lambda: device.report()["driver_tx"] >= 3, message="the driver's frames counted")
    for n in range(4, 8):                                     # ours after theirs: still not counted
        device.feed(frame(0x29, bytes((n,)), stamp=float(n)))
    assert [driver.recv(5.0).data[0] for _ in range(4)] == [4, 5, 6, 7]   # (the driver never hears its own)
    report = device.report()
    assert (report["driver_tx"], report["fed"], report["driver_tx_lost"]) == (3, 8, 0), report


def test_backlog_is_checked_every_so_many_frames_sent(bus_pair) -> None:
    device, _driver = bus_pair
    device.feed(frame(0x0C, b"\x00", direction=TX))            # recorded TX: not sent, not counted
    for n in range(CAN_CHECK_EVERY - 1):
        device.feed(frame(0x29, bytes((n % 256,))))
    assert not device.backlog_due()
    device.feed(frame(0x29, b"\xff"))
    assert device.backlog_due()
    assert device.pending() == 0 and not device.backlog_due()  # no driver pid: nothing to measure; looked


def test_the_worst_backlog_stays_well_under_the_drivers_buffer(bus_pair) -> None:
    """At a check at most CAN_BACKLOG_BYTES wait; CAN_CHECK_EVERY more frames may come before the next."""
    device, driver = bus_pair
    device.feed(frame(0x7FF, bytes(8), stamp=1764255379.123456))   # the longest frame the device sends
    truesize = wait_until(lambda: meminfo(driver)[0], message="the frame queued at the driver")
    rcvbuf = meminfo(driver)[1]
    assert CAN_BACKLOG_BYTES + CAN_CHECK_EVERY * truesize <= rcvbuf // 2, (truesize, rcvbuf)


def test_the_replayed_driver_never_hears_its_own_frames_but_hears_every_other(bus_pair) -> None:
    """As a SocketCAN socket (and python-can's receive_own_messages=False): multicast loopback returns each
    datagram to its sender, and the stamped bus drops those copies, even of a frame sent twice unchanged."""
    import can

    device, driver = bus_pair
    other = StampedUdpMulticastBus(channel=CAN_GROUP, port=device.port)
    try:
        setpoint = can.Message(arbitration_id=0x0D, data=b"\x00\x00\x80\x3f\x00\x00\x00\x00", is_extended_id=False)
        driver.send(setpoint)
        driver.send(setpoint)
        other.send(can.Message(arbitration_id=0x0D, data=b"\x01" * 8, is_extended_id=False))
        device.feed(frame(0x29, b"\x02" * 8, stamp=5.0))
        got = [driver.recv(5.0) for _ in range(2)]
        assert sorted((m.arbitration_id, bytes(m.data)) for m in got) == [(0x0D, b"\x01" * 8), (0x29, b"\x02" * 8)]
        assert driver.recv(0.2) is None and not driver._own   # both copies of its own frame came back and went
        heard = [other.recv(5.0) for _ in range(3)]   # the other member hears the driver's two frames and the device's
        assert sorted(m.arbitration_id for m in heard) == [0x0D, 0x0D, 0x29]
    finally:
        other.shutdown()


@pytest.mark.parametrize("fields", [
    dict(arbitration_id=0x1FFFFFFF, is_extended_id=True, dlc=8, data=bytes(range(8))),
    dict(arbitration_id=0x7FF, is_remote_frame=True, dlc=4, data=b""),
    dict(arbitration_id=0x080, is_extended_id=True, is_error_frame=True, dlc=8, data=bytes(8)),
    dict(arbitration_id=0x123, is_fd=True, bitrate_switch=True, error_state_indicator=True, dlc=64, data=bytes(range(64))),
    dict(arbitration_id=0, dlc=0, data=b""),
])
def test_every_field_of_a_frame_survives_the_replay_datagram(fields) -> None:
    import can

    sent = can.Message(timestamp=1764255379.123456, **fields)
    got = unpack_frame(pack_frame(timestamp=sent.timestamp, **fields))
    assert got.equals(sent, timestamp_delta=0.0), (got, sent)
    for name in ("is_extended_id", "is_remote_frame", "is_error_frame", "is_fd", "bitrate_switch",
                 "error_state_indicator"):
        assert getattr(got, name) == getattr(sent, name), name


def test_a_python_can_member_is_heard_and_garbage_is_one_failed_receive(bus_pair) -> None:
    import can

    device, driver = bus_pair
    assert driver.recv(0.0) is None and driver.recv(0.01) is None   # nothing waiting: none, not an error
    member = can.Bus(interface="udp_multicast", channel=CAN_GROUP, port=device.port)
    try:
        member.send(can.Message(timestamp=42.5, arbitration_id=0x0A, data=b"\x07", is_extended_id=False))
        got = driver.recv(5.0)
        assert (got.arbitration_id, bytes(got.data), got.timestamp) == (0x0A, b"\x07", 42.5)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw:
            raw.sendto(b"U2CF" + b"\x01\x02", (CAN_GROUP, device.port))   # truncated head
        with pytest.raises(can.CanOperationError, match="could not unpack"):
            driver.recv(5.0)
        device.feed(frame(0x29, b"\x05", stamp=7.0))                    # the bus goes on
        assert driver.recv(5.0).timestamp == 7.0
    finally:
        member.shutdown()
