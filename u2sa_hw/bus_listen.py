"""Where a transport listens and sends: the vehicle's own interface, not every network the board is on.

LCM joins the multicast group on the interface of the default route, and a socket bound to
the group's port hears the group on every interface any socket joined it on (Linux's
IP_MULTICAST_ALL). A single-board vehicle (``ttl=0``) would hear the whole LAN. So, once LCM
has made its sockets, this module re-joins the receive socket on one interface only, with
IP_MULTICAST_ALL off, and points the send socket at the same interface (IP_MULTICAST_IF):

* ``ttl=0``: loopback. Nothing from another host reaches the transport;
* ``ttl`` >= 1 with the profile's ``bus_interface`` (e.g. ``"eth0"``): that interface;
* ``ttl`` >= 1 without it: LCM's default (the default route's interface), unchanged.

Only the sockets LCM made for this transport are touched (the fds that appeared while it
opened). LCM's own self test, when the receiver opens, sends on the default route: the send
socket is pointed back there for it. When the interface cannot carry multicast (``lo``
without its MULTICAST flag), the transport keeps LCM's default and says once how to fix it.
"""

from __future__ import annotations

import errno
import logging
import os
import socket
import struct
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

log = logging.getLogger("u2sa_hw.bus_listen")

IP_MULTICAST_ALL = getattr(socket, "IP_MULTICAST_ALL", 49)
IFF_MULTICAST = 0x1000
ANY_INTERFACE_ENV = "U2SA_BUS_ANY_INTERFACE"   # set: LCM's default interface even for ttl=0 (diagnosis)
_warned: set[str] = set()


def socket_fds() -> set[int]:
    """This process's open socket file descriptors."""
    fds = set()
    for name in os.listdir("/proc/self/fd"):
        try:
            if os.readlink(f"/proc/self/fd/{name}").startswith("socket:"):
                fds.add(int(name))
        except OSError:
            continue
    return fds


def listen_interface(url: str, interface: str | None) -> str | None:
    """The interface a transport on *url* should use: ``lo`` for ttl=0, *interface* otherwise (None: LCM's)."""
    if not url.startswith("udpm://") or os.environ.get(ANY_INTERFACE_ENV):
        return None
    ttl = parse_qs(urlsplit(url).query).get("ttl", ["0"])[0]
    return "lo" if ttl.strip() in ("", "0") else interface


def _group_and_port(url: str) -> tuple[bytes, int]:
    where = urlsplit(url)
    return socket.inet_aton(where.hostname or "239.255.76.67"), where.port or 7667


def _multicast_capable(interface: str) -> bool:
    try:
        return int(Path(f"/sys/class/net/{interface}/flags").read_text(), 16) & IFF_MULTICAST != 0
    except (OSError, ValueError):
        return False


def interface_index(interface: str) -> int | None:
    """The index of *interface*, or None when it cannot carry multicast (said once); OSError when unknown."""
    try:
        index = socket.if_nametoindex(interface)
    except OSError:
        raise OSError(f"bus_interface {interface!r}: no such network interface "
                      f"(the interfaces here: {', '.join(n for _i, n in socket.if_nameindex())})") from None
    if not _multicast_capable(interface):
        if interface not in _warned:
            _warned.add(interface)
            log.warning("%s has no MULTICAST flag: the bus listens on the default route's interface too; "
                        "'sudo ip link set %s multicast on' (the u2sa-multicast-lo unit does it for lo)",
                        interface, interface)
        return None
    return index


def _inet_dgram(fds: set[int]) -> list[socket.socket]:
    out = []
    for fd in fds:
        try:
            sock = socket.socket(fileno=os.dup(fd))
        except OSError:
            continue
        if sock.family == socket.AF_INET and sock.type == socket.SOCK_DGRAM:
            out.append(sock)
        else:
            sock.close()
    return out


def send_via(url: str, fds: set[int], index: int) -> None:
    """Send multicast from the sockets among *fds* (not the receive one) on interface *index* (0: the route's)."""
    _group, port = _group_and_port(url)
    for sock in _inet_dgram(fds):
        with sock:
            if sock.getsockname()[1] != port:
                sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, struct.pack("4s4si", b"", b"", index))


def receive_on(url: str, fds: set[int], index: int) -> None:
    """Make the receive socket among *fds* a member of the group on interface *index* only."""
    group, port = _group_and_port(url)
    for sock in _inet_dgram(fds):
        with sock:
            if sock.getsockname()[1] != port:
                continue
            try:
                sock.setsockopt(socket.IPPROTO_IP, socket.IP_DROP_MEMBERSHIP, struct.pack("4s4si", group, b"", 0))
            except OSError:
                pass   # LCM joined nowhere (no route), or it was dropped already
            sock.setsockopt(socket.IPPROTO_IP, IP_MULTICAST_ALL, 0)
            try:
                sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, struct.pack("4s4si", group, b"", index))
            except OSError as exc:
                if exc.errno != errno.EADDRINUSE:   # joined there already
                    raise
