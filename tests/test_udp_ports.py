"""Private UDP ports: below the ephemeral range, never a held one, never one asked to avoid."""

from __future__ import annotations

import random
import socket

from u2sa_hw.bus.udp_ports import LCM_DEFAULT_PORT, LOWEST_PORT, ephemeral_range, private_lcm_url, private_udp_port


def test_ports_come_from_below_the_ephemeral_range_and_skip_the_lcm_default() -> None:
    low, _ = ephemeral_range()
    rng = random.Random(3)
    ports = [private_udp_port(rng=rng, span=3) for _ in range(200)]
    assert all(LOWEST_PORT <= p and p + 2 < low for p in ports)
    assert all(not (p <= LCM_DEFAULT_PORT <= p + 2) for p in ports)
    assert private_lcm_url(options="ttl=0&recv_buf_size=1024").endswith("?ttl=0&recv_buf_size=1024")


def test_a_port_held_without_reuse_or_asked_to_avoid_is_never_handed_out() -> None:
    # The same seed picks the same first candidate; hold it the way a sending socket does.
    first = private_udp_port(rng=random.Random(11))
    for reuse in (False, True):   # a sending socket holds it without SO_REUSEADDR, an LCM receiver with it
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as held:
            if reuse:
                held.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            held.bind(("", first))
            assert private_udp_port(rng=random.Random(11)) != first
    assert private_udp_port(rng=random.Random(11), avoid={first}) != first
    assert private_udp_port(rng=random.Random(11)) == first   # free again once released


def test_ephemeral_range_falls_back_to_linux_defaults(tmp_path) -> None:
    assert ephemeral_range(tmp_path / "missing") == (32768, 60999)
    (tmp_path / "range").write_text("40000\t50000\n")
    assert ephemeral_range(tmp_path / "range") == (40000, 50000)
