"""Pick a UDP port for a private multicast bus (a replay, a simulation's CAN bus, a test).

A port inside the kernel's ephemeral range can already be held by another socket: every
unconnected UDP socket that sends (LCM's own send socket among them) is given one from that
range, without SO_REUSEADDR, and a multicast receiver that then binds the same port fails
with "Address already in use". So private ports come from below the ephemeral range and
are tried with a bind before they are handed out.
"""

from __future__ import annotations

import random
import socket
from pathlib import Path

EPHEMERAL_RANGE_FILE = Path("/proc/sys/net/ipv4/ip_local_port_range")
LOWEST_PORT = 10_000
LCM_DEFAULT_PORT = 7667


def ephemeral_range(path: Path = EPHEMERAL_RANGE_FILE) -> tuple[int, int]:
    """The kernel's ephemeral port range (Linux's default 32768-60999 where it cannot be read)."""
    try:
        low, high = (int(v) for v in path.read_text().split())
        return low, high
    except (OSError, ValueError):
        return 32768, 60999


def _bindable(port: int) -> bool:
    # Without SO_REUSEADDR: a port an LCM receiver (which shares with SO_REUSEADDR) or a sending
    # socket holds fails this bind, so a bus in use is never handed out again.
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.bind(("", port))
        except OSError:
            return False
    return True


def private_udp_port(*, avoid: set[int] | frozenset[int] = frozenset(), span: int = 1,
                     rng: random.Random | None = None) -> int:
    """A free UDP port (and the *span* - 1 after it) outside the ephemeral range and *avoid*.

    *span* > 1 asks for consecutive ports (a simulation gives each CAN bus the next one).
    """
    rng = rng or random.Random()
    low, _high = ephemeral_range()
    top = max(LOWEST_PORT + span, low) - span
    for _ in range(200):
        port = rng.randint(LOWEST_PORT, top)
        ports = range(port, port + span)
        if LCM_DEFAULT_PORT in ports or any(p in avoid for p in ports):
            continue
        if all(_bindable(p) for p in ports):
            return port
    raise OSError(f"no free UDP port between {LOWEST_PORT} and {top + span - 1} after 200 tries")


def private_lcm_url(*, avoid: set[int] | frozenset[int] = frozenset(), options: str = "ttl=0") -> str:
    """``udpm://239.255.76.67:<private port>?<options>``: a bus of its own on this machine."""
    return f"udpm://239.255.76.67:{private_udp_port(avoid=avoid)}?{options}"
