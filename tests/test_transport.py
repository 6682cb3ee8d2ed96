"""The LCM transport over real multicast: URL order, threads, errors, counters, extension decoding."""

from __future__ import annotations

import logging
import socket
import subprocess
import sys
import textwrap
import threading
from pathlib import Path
from typing import Any

import pytest
from conftest import wait_until

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw import message_codegen
from u2sa_hw.service.contract import U2SAService
from u2sa_hw.bus.transport import Transport, resolve_url
from u2sa_hw.bus.lcm_url import DEFAULT_LCM_URL, DEFAULT_RECV_BUF_SIZE, with_receive_buffer
from u2sa_hw.bus.multicast_check import check_multicast
from u2sa_hw.bus.lcm_open import TransportError
from u2sa_hw.bus.udp_ports import private_lcm_url
from u2sa_hw.profile.vehicle import VehicleProfile


def _port(url: str) -> int:
    return int(url.split("?", 1)[0].rsplit(":", 1)[1])


def test_url_comes_from_the_profile_then_the_environment_then_the_default(monkeypatch: pytest.MonkeyPatch,
                                                                        tmp_path: Path) -> None:
    profile_url, env_url = private_lcm_url(), private_lcm_url()
    monkeypatch.delenv("U2SA_LCM_URL", raising=False)
    assert resolve_url(None) == DEFAULT_LCM_URL
    monkeypatch.setenv("U2SA_LCM_URL", env_url)
    assert resolve_url(None) == env_url
    assert resolve_url(profile_url) == profile_url
    svc = U2SAService("urls", profile=VehicleProfile(path=None, lcm_url=profile_url), config_path=tmp_path / "u.toml")
    try:
        assert svc.transport.url == profile_url
    finally:
        svc.transport.stop()
    tr = Transport(None)
    try:
        assert tr.url == env_url
    finally:
        tr.stop()


def test_a_udpm_url_gets_a_receive_buffer_the_kernel_allows(tmp_path: Path) -> None:
    rmem_max = tmp_path / "rmem_max"
    rmem_max.write_text("212992\n")   # Debian's default cap: asking for more makes LCM warn on stderr
    url = "udpm://239.255.76.67:7667?ttl=0"
    assert with_receive_buffer(url, rmem_max_file=str(rmem_max)) == url + "&recv_buf_size=212992"
    rmem_max.write_text(f"{DEFAULT_RECV_BUF_SIZE * 4}\n")
    assert with_receive_buffer("udpm://239.255.76.67:7667", rmem_max_file=str(rmem_max)) == \
        f"udpm://239.255.76.67:7667?recv_buf_size={DEFAULT_RECV_BUF_SIZE}"
    mine = url + "&recv_buf_size=65536"
    assert with_receive_buffer(mine, rmem_max_file=str(rmem_max)) == mine            # the user's own wins
    assert with_receive_buffer("memq://", rmem_max_file=str(rmem_max)) == "memq://"   # not a socket
    assert with_receive_buffer(url, rmem_max_file=str(tmp_path / "missing")) == url   # no /proc: kernel default


def test_opening_from_several_threads_at_once_leaves_stderr_where_it_was() -> None:
    """Each open catches what the LCM C library prints on fd 2; interleaved, they used to leave fd 2 on a
    deleted temp file, and every later log line and traceback was lost."""
    import os

    before = os.fstat(2)
    start = threading.Barrier(8)
    opened: list[Transport] = []

    def open_one() -> None:
        start.wait()
        opened.append(Transport("memq://", name="many"))

    threads = [threading.Thread(target=open_one) for _ in range(8)]
    for th in threads:
        th.start()
    for th in threads:
        th.join(timeout=30)
    for tr in opened:
        tr.stop()
    after = os.fstat(2)
    assert len(opened) == 8 and (after.st_dev, after.st_ino) == (before.st_dev, before.st_ino)


def test_publishing_from_several_threads_delivers_every_message_intact(lcm_url: str) -> None:
    threads, per_thread = 4, 300
    received: list[bytes] = []
    rx = Transport(lcm_url, name="rx")
    rx.subscribe(ch.STATE_INFO, None, lambda _c, data: received.append(data), raw=True)
    rx.start()
    tx = Transport(lcm_url, name="tx")
    start = threading.Barrier(threads)
    sent = [0]
    sent_lock = threading.Lock()

    def publisher(k: int) -> None:
        start.wait()
        for i in range(per_thread):
            msg = t.StateInformation().set(x=float(k), y=float(i), psi=k + i / 1000)
            msg.sensor_name = f"thread-{k}-" + "x" * (i % 50)  # varying lengths
            tx.publish(ch.STATE_INFO, msg)
            with sent_lock:
                sent[0] += 1
            if i % 20 == 19:  # flow control: a socket buffer's worth in flight at most, so UDP loses nothing
                wait_until(lambda: len(received) >= sent[0] - 100, timeout=30, interval=0.001,
                           message="the receiver to catch up")

    workers = [threading.Thread(target=publisher, args=(k,)) for k in range(threads)]
    try:
        for w in workers:
            w.start()
        for w in workers:
            w.join(60)
        wait_until(lambda: len(received) >= threads * per_thread, timeout=30, message="every message")
        seen = set()
        for data in received:
            msg = t.StateInformation.decode(data)  # raises on a corrupted message
            k, i = int(msg.x), int(msg.y)
            assert msg.sensor_name == f"thread-{k}-" + "x" * (i % 50) and msg.psi == k + i / 1000
            seen.add((k, i))
        assert seen == {(k, i) for k in range(threads) for i in range(per_thread)}
        assert tx.tx[ch.STATE_INFO].messages == threads * per_thread
    finally:
        tx.stop()
        rx.stop()


def test_a_bad_url_or_provider_is_one_line_naming_the_url_and_what_lcm_said(capfd: pytest.CaptureFixture) -> None:
    for url, said in (("foo://bar", 'LCM provider "foo" not found'),
                      ("udpm://300.1.2.3:7667", 'Bad multicast IP address "300.1.2.3"')):
        with pytest.raises(TransportError) as err:
            Transport(url)
        text = str(err.value)
        assert "\n" not in text and text.startswith(f"cannot open LCM at {url}: {said}; check the URL"), text
    assert capfd.readouterr().err == ""  # the C library's own lines were caught, not printed


def test_no_multicast_route_is_one_line_with_the_fix(tmp_path: Path) -> None:
    if subprocess.run(["unshare", "-rn", "true"], capture_output=True).returncode != 0:
        pytest.skip("unshare -rn (a network namespace without routes) is not allowed here")
    code = "from u2sa_hw.bus.transport import Transport\nTransport('udpm://239.255.76.67:7667?ttl=0')\n"
    r = subprocess.run(["unshare", "-rn", sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                       cwd=Path(__file__).resolve().parent.parent)
    last = r.stderr.strip().splitlines()[-1]
    assert r.returncode != 0 and "LCM requires a valid multicast route" not in r.stderr, r.stderr
    assert "TransportError: cannot open LCM at udpm://239.255.76.67:7667?ttl=0: " in last
    assert "multicast does not work on this machine" in last and "ip route add 224.0.0.0/4 dev lo" in last
    assert "Traceback" in r.stderr.splitlines()[0]  # nothing of LCM's printed before Python's report


def test_a_port_held_without_sharing_is_a_transport_error_naming_it(lcm_url: str) -> None:
    holder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    holder.bind(("0.0.0.0", _port(lcm_url)))  # no SO_REUSEADDR: LCM cannot bind beside it
    tr = Transport(lcm_url)
    try:
        with pytest.raises(TransportError) as err:
            tr.subscribe(ch.NAV_POINT, t.NavigationPoint, lambda _c, _m: None)
        text = str(err.value)
        assert "Address already in use" in text and f"UDP port {_port(lcm_url)}" in text and "\n" not in text
    finally:
        tr.stop()
        holder.close()


def test_check_multicast_passes_here(lcm_url: str) -> None:
    check_multicast(lcm_url)


def test_counters_count_packets_once_and_malformed_ones_are_logged_once(lcm_url: str,
                                                                        caplog: pytest.LogCaptureFixture) -> None:
    got: list[Any] = []
    rx = Transport(lcm_url, name="rx")
    rx.subscribe(ch.STATE_INFO, t.StateInformation, lambda _c, m: got.append(("exact", m)))
    rx.subscribe("STATE_I.*", t.StateInformation, lambda _c, m: got.append(("regex", m)))
    rx.start()
    tx = Transport(lcm_url, name="tx")
    good = t.StateInformation().set(x=1.0).encode()
    packets = [b"\x00garbage", good[:30], t.Health().encode(), good, good]
    try:
        with caplog.at_level(logging.WARNING, logger="u2sa_hw.bus.transport"):
            for data in packets:
                tx.publish_bytes(ch.STATE_INFO, data)
            wait_until(lambda: len(got) >= 4, message="both subscriptions to get both good messages")
        counters = rx.rx[ch.STATE_INFO]
        assert (counters.messages, counters.malformed) == (2, 3)
        assert counters.bytes == sum(len(p) for p in packets)
        assert sum("dropping malformed message on STATE_INFO" in r.getMessage() for r in caplog.records) == 1
        assert rx.last_error.startswith("malformed message on STATE_INFO")
        assert (tx.tx[ch.STATE_INFO].messages, tx.tx[ch.STATE_INFO].bytes) == (5, sum(len(p) for p in packets))
    finally:
        tx.stop()
        rx.stop()


BUOY_PUBLISHER = """\
import sys
sys.path.insert(0, sys.argv[1])
from buoyext import Buoy
from u2sa_hw.bus.transport import Transport
tx = Transport(sys.argv[2], name="buoys")   # signed with the session's key ($U2SA_BUS_KEY_FILE)
for i in range(3):
    b = Buoy(); b.base.uid = f"red-{i}"; b.base.object_type = "buoy"; b.base.x = 4.0 + i; b.colour = "red"
    tx.publish_bytes("OBJECTS", b.encode())
"""


def test_an_unknown_child_from_another_process_arrives_as_its_base_and_is_logged_once(
        lcm_url: str, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A Buoy (an ObjectDescription child) that this process has no code for, published by another."""
    (tmp_path / "buoy.lcm").write_text(textwrap.dedent("""\
        package buoyext;
        struct Buoy { u2sa_hw.lcmtypes.ObjectDescription base; string colour; double height; }
        """))
    subprocess.run([message_codegen.find_lcm_gen(), "-p", "--ppath", str(tmp_path), str(tmp_path / "buoy.lcm")],
                   check=True)
    got: list[Any] = []
    rx = Transport(lcm_url, name="world")
    rx.subscribe(ch.OBJECTS, t.ObjectDescription, lambda _c, m: got.append(m))
    rx.start()
    try:
        with caplog.at_level(logging.INFO, logger="u2sa_hw.bus.transport"):
            subprocess.run([sys.executable, "-c", BUOY_PUBLISHER, str(tmp_path), lcm_url], check=True, timeout=60)
            wait_until(lambda: len(got) >= 3, timeout=20, message="three buoys")
        assert all(type(m) is t.ObjectDescription for m in got)
        assert [(m.uid, m.object_type, m.x) for m in got] == [(f"red-{i}", "buoy", 4.0 + i) for i in range(3)]
        unknown = [r for r in caplog.records if "decoded as its base ObjectDescription" in r.getMessage()]
        assert len(unknown) == 1 and "on OBJECTS" in unknown[0].getMessage()
        assert rx.rx[ch.OBJECTS].messages == 3 and rx.rx[ch.OBJECTS].malformed == 0
    finally:
        rx.stop()


def test_raw_lcm_is_the_transports_own_lcm_unsigned_and_on_its_sockets(lcm_url: str) -> None:
    """What bench/transport.py measures as plain LCM: the transport's own LCM, which neither signs nor verifies."""
    rx = Transport(lcm_url, name="rx")
    tx = Transport(lcm_url, name="tx")
    plain: list[bytes] = []
    try:
        lc = rx.raw_lcm()
        assert lc is rx.raw_lcm()   # one LCM, its receive socket opened once
        lc.subscribe(ch.STATE_INFO, lambda _c, data: plain.append(data))
        verified: list[Any] = []
        rx.subscribe(ch.STATE_INFO, t.StateInformation, lambda _c, m: verified.append(m))
        rx.start()
        msg = t.StateInformation().set(x=1.5)
        tx.raw_lcm().publish(ch.STATE_INFO, msg.encode())   # bypasses signing: the bytes as they are
        tx.publish(ch.STATE_INFO, msg)                      # signed: the payload then the trailer
        wait_until(lambda: len(plain) >= 2, timeout=10, message="both packets on the raw subscription")
        assert plain[0] == msg.encode() and plain[1].startswith(msg.encode()) and len(plain[1]) > len(plain[0])
        # the transport's own subscribers verify: the unsigned one is dropped and counted
        wait_until(lambda: rx.rx[ch.STATE_INFO].unsigned == 1 and verified, timeout=10,
                   message="the unsigned packet counted, the signed one delivered")
        assert len(verified) == 1 and verified[0].x == 1.5
    finally:
        tx.stop()
        rx.stop()
    with pytest.raises(TransportError, match="stopped"):
        rx.raw_lcm()
