"""Where a transport listens and sends: the vehicle's own interface, not every network the board is on.

LCM joins the multicast group on the interface of the default route, and a socket bound to
the group's port hears the group on every interface any socket joined it on (Linux's
IP_MULTICAST_ALL). A single-board vehicle (``ttl=0``) would hear the whole LAN. So, once LCM
has made its sockets, this module re-joins the receive socket on one interface only, with
IP_MULTICAST_ALL off, and points the send socket at the same interface (IP_MULTICAST_IF):

* ``ttl=0``: loopback. Nothing from another host reaches the transport;
* ``ttl`` >= 1 with the profile's ``bus_interface`` (e.g. ``"eth0"``): that interface;
* ``ttl`` >= 1 without it: LCM's default (the default route's interface), unchanged; not refused,
  but a service with the vehicle's key says so in its health (:func:`default_route_note`).

Only the sockets LCM made for this transport are touched (the fds that appeared while it
opened). LCM's own self test, when the receiver opens, sends on the default route: the send
socket is pointed back there for it.

Linux's ``lo`` has no MULTICAST flag by default. :func:`prepare_interface` sets it
(``SIOCSIFFLAGS``, what ``ip link set lo multicast on`` does) when the process may (root, or
CAP_NET_ADMIN: ``u2sa run`` as root; the ``u2sa-multicast-lo`` unit does it for installed
units). When it may not, the transport stays on LCM's default interface and
:func:`prepare_interface` says so in one line (``bus listens on eth0, not lo: sudo ip link
set lo multicast on``): the transport keeps it as ``listen_problem``, every service's health
carries it (``bus_listen``), and a service signed with the vehicle's key refuses to start
(``u2sa_hw.service.bus_handlers.listen_refusal``, docs/security.md "Where the vehicle listens").
"""

from __future__ import annotations

import errno
import fcntl
import logging
import os
import socket
import struct
from urllib.parse import parse_qs, urlsplit

log = logging.getLogger("u2sa_hw.bus.listen")

IP_MULTICAST_ALL = getattr(socket, "IP_MULTICAST_ALL", 49)
IFF_MULTICAST = 0x1000
SIOCGIFFLAGS = 0x8913
SIOCSIFFLAGS = 0x8914
_IFREQ_FLAGS = struct.Struct("16sH22x")          # struct ifreq: the name, then ifr_flags (40 bytes in all)
ROUTE_FILE = "/proc/net/route"
ANY_INTERFACE_ENV = "U2SA_BUS_ANY_INTERFACE"   # set: LCM's default interface even for ttl=0 (diagnosis)
_warned: set[str] = set()
_UNKNOWN_ROUTE = "the default route's interface"   # route_interface's answer when no route matches


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


def is_local(url: str) -> bool:
    """True for a ``udpm://`` URL with ``ttl=0`` (or none): a bus that must stay on this board."""
    if not url.startswith("udpm://"):
        return False
    return parse_qs(urlsplit(url).query).get("ttl", ["0"])[0].strip() in ("", "0")


def listen_interface(url: str, interface: str | None) -> str | None:
    """The interface a transport on *url* should use: ``lo`` for ttl=0, *interface* otherwise (None: LCM's)."""
    if not url.startswith("udpm://") or os.environ.get(ANY_INTERFACE_ENV):
        return None
    return "lo" if is_local(url) else interface


def forced_default_problem(url: str) -> str:
    """The line health carries when ``$U2SA_BUS_ANY_INTERFACE`` keeps a ttl=0 bus on LCM's default ("" otherwise)."""
    if not os.environ.get(ANY_INTERFACE_ENV) or not is_local(url):
        return ""
    return f"bus listens on {route_interface(url)}, not lo: ${ANY_INTERFACE_ENV} is set (diagnosis only); unset it"


def default_route_note(url: str, interface: str | None) -> str:
    """Where a ``ttl`` >= 1 bus listens when no interface keeps it on the vehicle's network ("" otherwise).

    Without the profile's ``bus_interface`` (or with ``$U2SA_BUS_ANY_INTERFACE``) LCM joins the
    group on the default route's interface, which on many boards is the WiFi. Not refused (a
    multi-board vehicle may mean it), but said: a service with the vehicle's key puts this line in
    its health (``bus_listen``) and logs it at start (``u2sa_hw.service.bus_handlers.listen_state``).
    """
    if not url.startswith("udpm://") or is_local(url):
        return ""
    forced = bool(os.environ.get(ANY_INTERFACE_ENV))
    if interface and not forced:
        return ""
    where = route_interface(url)
    if where != _UNKNOWN_ROUTE:
        where += ", the default route's interface"
    ttl = parse_qs(urlsplit(url).query).get("ttl", ["?"])[0].strip()
    if forced:
        return f"bus listens on {where}: ${ANY_INTERFACE_ENV} is set (diagnosis only); unset it"
    return (f"bus listens on {where} (ttl={ttl} without bus_interface): every host on that network that has the "
            "key can command this vehicle; name the vehicle's own network in [vehicle], e.g. bus_interface = \"eth0\"")


def _group_and_port(url: str) -> tuple[bytes, int]:
    where = urlsplit(url)
    return socket.inet_aton(where.hostname or "239.255.76.67"), where.port or 7667


def bus_port(url: str) -> int:
    """The UDP port of a ``udpm://`` URL (LCM's 7667 when it names none)."""
    return _group_and_port(url)[1]


def interface_flags(interface: str) -> int | None:
    """The kernel's flags of *interface* in this network namespace (SIOCGIFFLAGS), None when unknown."""
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            reply = fcntl.ioctl(sock.fileno(), SIOCGIFFLAGS, _IFREQ_FLAGS.pack(interface.encode()[:15], 0))
    except OSError:
        return None
    return _IFREQ_FLAGS.unpack(reply)[1]


def set_multicast_flag(interface: str) -> None:
    """Turn *interface*'s MULTICAST flag on (``ip link set IF multicast on``); OSError (EPERM) without CAP_NET_ADMIN."""
    flags = interface_flags(interface)
    if flags is None:
        raise OSError(errno.ENODEV, f"no interface {interface}")
    if flags & IFF_MULTICAST:
        return
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        fcntl.ioctl(sock.fileno(), SIOCSIFFLAGS, _IFREQ_FLAGS.pack(interface.encode()[:15], flags | IFF_MULTICAST))


def route_interface(url: str, *, route_file: str = ROUTE_FILE) -> str:
    """The interface the kernel routes *url*'s multicast group to (where LCM joins it), or a description."""
    group = struct.unpack("<I", _group_and_port(url)[0])[0]   # /proc/net/route is in host (little-endian) order
    best: tuple[int, str] | None = None
    try:
        with open(route_file) as f:
            next(f, None)
            for line in f:
                fields = line.split()
                if len(fields) < 8:
                    continue
                dest, mask = int(fields[1], 16), int(fields[7], 16)
                if group & mask == dest and (best is None or bin(mask).count("1") > best[0]):
                    best = (bin(mask).count("1"), fields[0])
    except (OSError, ValueError):
        pass
    return best[1] if best else _UNKNOWN_ROUTE


def prepare_interface(url: str, interface: str) -> tuple[int | None, str]:
    """``(index, "")`` when the bus can be kept on *interface*; ``(None, why and the fix)`` when it cannot.

    ``lo`` without its MULTICAST flag gets it when this process may set it (root); otherwise the
    transport stays on LCM's default interface and the second item says so in one line, logged
    once per interface. OSError when *interface* does not exist.
    """
    try:
        index = socket.if_nametoindex(interface)
    except OSError:
        raise OSError(f"bus_interface {interface!r}: no such network interface "
                      f"(the interfaces here: {', '.join(n for _i, n in socket.if_nameindex())})") from None
    flags = interface_flags(interface)
    if flags is not None and not flags & IFF_MULTICAST and interface == "lo":
        try:
            set_multicast_flag(interface)
        except OSError as exc:
            log.debug("cannot set %s's MULTICAST flag: %s", interface, exc)
        else:
            log.info("set %s's MULTICAST flag (ip link set %s multicast on): the bus stays on %s",
                     interface, interface, interface)
            flags = interface_flags(interface)
    if flags is not None and flags & IFF_MULTICAST:
        return index, ""
    problem = (f"bus listens on {route_interface(url)}, not {interface}: sudo ip link set {interface} multicast on "
               f"({interface} has no MULTICAST flag and this process may not set it)")
    if interface not in _warned:
        _warned.add(interface)
        log.warning("%s", problem)
    return None, problem


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
