"""The kernel channel filter on a transport's receive socket (u2sa_hw.bus.filter): a process hears
only the channels it subscribed to, and never misses one of them."""

from __future__ import annotations

import os
import socket
import threading

import pytest
from conftest import wait_until

from u2sa_hw.bus import filter as bus_filter
from u2sa_hw.bus.filter import FilterTooLarge, lcm_packet, program
from u2sa_hw.bus.transport import Transport
from u2sa_hw.bus.lcm_sockets import FILTER_ENV


def _kernel_run(channels: list[str], packets: list[bytes]) -> list[bytes]:
    """The packets a loopback socket carrying the filter for *channels* lets through, in order."""
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    with rx, tx:
        rx.bind(("127.0.0.1", 0))
        rx.setblocking(False)
        assert bus_filter.apply([rx.fileno()], rx.getsockname()[1], channels)
        for data in packets:
            tx.sendto(data, rx.getsockname())
        got = []
        while True:
            try:
                got.append(rx.recv(70_000))
            except BlockingIOError:
                return got


def test_the_program_passes_exactly_the_subscribed_channels_and_everything_not_a_channel_header() -> None:
    wanted = ["ACTUATOR_CMD", "FAILSAFE", "U2SA_HEALTH", "A", "AB", "ABC", "RAW.gps", "RAW.rc", "X"]
    keep = [lcm_packet(c) for c in wanted] + [
        lcm_packet("LCM_SELF_TEST"),                  # LCM's own probe always passes
        lcm_packet("FAILSAFE", long=True),            # fragment 0 of a large message on a wanted channel
        lcm_packet("", long=True, fragment=1),        # later fragments carry no channel: they pass
        b"garbage that is not an LCM header",
    ]
    keep += [lcm_packet(c, payload=b"") for c in ("A", "AB", "RAW.rc", "FAILSAFE", "X")]   # nothing after the name:
    # a packet shorter than an earlier name in the program must not end it with a drop
    drop = [lcm_packet(c) for c in ("FAILSAFE_X", "FAILSAF", "STATE_INFO", "ACTUATOR_CMDX", "RAW.r", "RAW.rcc",
                                     "B", "failsafe")] + [lcm_packet("STATE_INFO", long=True), b"LC0", b"",
                                                          lcm_packet("C", payload=b"")]
    packets = [p for pair in zip(keep, drop) for p in pair] + keep[len(drop):] + drop[len(keep):] + [b"LC02"]
    got = _kernel_run(wanted, packets)
    assert got == [p for p in packets if p in keep], [p[:24] for p in got]


def test_too_many_channels_for_one_program_is_refused_and_then_the_socket_hears_everything() -> None:
    with pytest.raises(FilterTooLarge):
        program([f"CHANNEL_NUMBER_{i:04d}_WITH_A_LONG_NAME" for i in range(400)])
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    with rx:
        rx.bind(("127.0.0.1", 0))
        assert not bus_filter.apply([rx.fileno()], rx.getsockname()[1],
                                    [f"CHANNEL_NUMBER_{i:04d}_WITH_A_LONG_NAME" for i in range(400)])


def _socket_drops(inodes: set[str]) -> int:
    """The kernel's drop count (filtered packets included) of this process's UDP sockets *inodes*."""
    total = 0
    with open("/proc/self/net/udp") as fh:
        for row in fh.read().splitlines()[1:]:
            f = row.split()
            if f[9] in inodes:
                total += int(f[12])
    return total


def _inodes(fds: set[int]) -> set[str]:
    return {os.readlink(f"/proc/self/fd/{fd}")[8:-1] for fd in fds}


def test_a_transport_hears_its_channels_and_the_kernel_drops_the_rest(lcm_url: str) -> None:
    got: dict[str, int] = {"WANTED": 0, "LARGE": 0}
    big = bytes(range(256)) * 400          # 100 kB: LCM sends it in fragments
    large: list[bytes] = []
    rx = Transport(lcm_url, name="rx")
    tx = Transport(lcm_url, name="tx")
    try:
        rx.subscribe("WANTED", None, lambda c, _d: got.__setitem__(c, got[c] + 1), raw=True)
        rx.subscribe("LARGE", None, lambda _c, d: large.append(d), raw=True)
        rx.start()
        assert rx.filtered
        inodes = _inodes(rx._sockets.recv_fds)
        before = _socket_drops(inodes)
        for i in range(200):
            tx.publish_bytes("UNWANTED", b"x" * 100)
            if i % 20 == 0:
                tx.publish_bytes("WANTED", b"y" * 100)
        tx.publish_bytes("LARGE", big)
        wait_until(lambda: got["WANTED"] == 10 and large, timeout=20, message="the wanted channels")
        assert large == [big]
        # the 200 unwanted packets never reached LCM: the kernel dropped them at the socket
        assert _socket_drops(inodes) - before >= 200
        assert "UNWANTED" not in rx.rx
    finally:
        tx.stop()
        rx.stop()


def test_a_regex_subscription_removes_the_filter_and_each_transport_filters_its_own_socket(lcm_url: str) -> None:
    heard_a: list[str] = []
    heard_all: list[str] = []
    a = Transport(lcm_url, name="a")
    everything = Transport(lcm_url, name="all")
    tx = Transport(lcm_url, name="tx")
    opened = threading.Barrier(2)

    def open_all() -> None:   # two transports of one process open their receivers at once
        opened.wait()
        everything.subscribe("CHAN_.*", None, lambda c, _d: heard_all.append(c), raw=True)

    other = threading.Thread(target=open_all)
    other.start()
    opened.wait()
    a.subscribe("CHAN_A", None, lambda c, _d: heard_a.append(c), raw=True)
    other.join(10)
    try:
        assert a.filtered and not everything.filtered
        a.start()
        everything.start()
        for name in ("CHAN_B", "CHAN_A", "CHAN_C"):
            tx.publish_bytes(name, b"z")
        wait_until(lambda: len(heard_all) == 3 and heard_a, timeout=20, message="both listeners")
        assert heard_a == ["CHAN_A"] and sorted(heard_all) == ["CHAN_A", "CHAN_B", "CHAN_C"]
        # a channel subscribed later is added before LCM takes it
        a.subscribe("CHAN_D", None, lambda c, _d: heard_a.append(c), raw=True)
        tx.publish_bytes("CHAN_D", b"z")
        wait_until(lambda: heard_a == ["CHAN_A", "CHAN_D"], timeout=20, message="the later channel")
        # a regex subscription on the filtered transport: it hears everything from then on
        a.subscribe("CHAN_[BC]", None, lambda c, _d: heard_a.append(c), raw=True)
        assert not a.filtered
        tx.publish_bytes("CHAN_B", b"z")
        wait_until(lambda: heard_a[-1:] == ["CHAN_B"], timeout=20, message="the regex channel")
    finally:
        for t in (tx, a, everything):
            t.stop()


def test_the_filter_can_be_turned_off_from_the_environment(lcm_url: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(FILTER_ENV, "off")
    rx = Transport(lcm_url, name="rx")
    try:
        rx.subscribe("WANTED", None, lambda _c, _d: None, raw=True)
        assert not rx.filtered
    finally:
        rx.stop()


def test_a_filter_that_cannot_be_widened_is_removed_so_nothing_subscribed_is_dropped(
        monkeypatch: pytest.MonkeyPatch) -> None:
    group = "239.255.76.99"
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2)]
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        port = 0
        for s in socks:   # two members of one group on one port, as two LCM receivers would be
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind(("", port))
            port = s.getsockname()[1]
            s.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                         socket.inet_aton(group) + socket.inet_aton("127.0.0.1"))
            s.setblocking(False)
        tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
        fds = [s.fileno() for s in socks]
        assert bus_filter.apply(fds, port, ["A"])
        calls = []
        real = bus_filter._attach

        def second_fails(sock: socket.socket, insns: list) -> None:
            calls.append(sock.fileno())
            if len(calls) == 2:
                raise OSError(12, "Cannot allocate memory")
            real(sock, insns)

        monkeypatch.setattr(bus_filter, "_attach", second_fails)
        assert not bus_filter.apply(fds, port, ["A", "B"])
        for channel in ("B", "C"):   # neither socket keeps a narrower filter: both hear everything now
            tx.sendto(lcm_packet(channel), (group, port))
        got = []
        for s in socks:
            while True:
                try:
                    got.append(s.recv(100))
                except BlockingIOError:
                    break
        assert got == [lcm_packet("B"), lcm_packet("C")] * 2
    finally:
        for s in (*socks, tx):
            s.close()


def test_two_threads_subscribing_first_on_one_transport_both_hear_their_channels(lcm_url: str) -> None:
    for _trial in range(5):
        rx = Transport(lcm_url, name="rx")
        tx = Transport(lcm_url, name="tx")
        got = {"CHAN_X": 0, "CHAN_Y": 0}
        both = threading.Barrier(2)

        def subscribe(channel: str) -> None:
            both.wait()   # each thread's subscribe is the transport's first: both open its receiver at once
            rx.subscribe(channel, None, lambda c, _d: got.__setitem__(c, got[c] + 1), raw=True)

        threads = [threading.Thread(target=subscribe, args=(c,)) for c in got]
        try:
            for th in threads:
                th.start()
            for th in threads:
                th.join(10)
            rx.start()
            for _ in range(5):
                tx.publish_bytes("CHAN_X", b"x")
                tx.publish_bytes("CHAN_Y", b"y")
            wait_until(lambda: got == {"CHAN_X": 5, "CHAN_Y": 5}, timeout=20, message=f"both channels ({got})")
            assert rx.filtered
        finally:
            tx.stop()
            rx.stop()
