"""CAN ports over python-can: ``socketcan``/``can0`` on a vehicle, ``virtual``/<name> in one
process, ``udp_multicast``/<group> across processes (python-can's own test doubles).

``open_can`` builds ``can.Bus(interface=..., channel=..., bitrate=...)`` and maps
python-can's errors to the port hierarchy: failing to open is ``PortUnavailable`` with the
SocketCAN fix (bring the interface up, load the kernel module), a bus that went away
(interface down, adapter unplugged, bus shut down) is ``PortClosed``, and any other failed
send or receive (transmit queue full, undecodable datagram) is ``PortIOError``.

Every frame sent is tapped as a ``RawCanFrame`` TX record, every frame received as RX.

``clock=stamped`` (a ``mock+can`` udp_multicast address only: a replay's bus) keeps each
frame's sender stamp (its recorded bus time) and gives the port a device clock
(:mod:`u2sa_hw.ports.can.clock`); :meth:`CanPort.now` is then that clock, else
``time.monotonic()``. A real bus never takes a foreign clock.
"""

from __future__ import annotations

import errno
import logging
import threading
import time
from typing import TYPE_CHECKING, Any

from u2sa_hw.messages import RawCanFrame
from u2sa_hw.ports.errors import PortClosed, PortIOError, PortUnavailable
from u2sa_hw.ports.tap import RX, TX, Tap, call_tap, tapping

# python-can (about 11 MB of memory) is imported when a bus opens, not with this module: the RC
# mux imports the CAN motor drivers only to read their actuator names, and must not pay for it.
if TYPE_CHECKING:
    import can

    from u2sa_hw.ports.can.clock import CanDeviceClock

log = logging.getLogger(__name__)

# errnos that mean the bus itself is gone rather than one frame failing
_LOST_ERRNOS = {errno.ENETDOWN, errno.ENODEV, errno.ENXIO, errno.EBADF, errno.ENETUNREACH}


def bring_up_hint(channel: str, bitrate: int | None) -> str:
    """The command that brings a SocketCAN interface up (what udev/70-u2sa-can.rules runs)."""
    return f"ip link set {channel} up type can bitrate {bitrate or 500000}"


def _error_code(exc: BaseException) -> int | None:
    """The errno behind a python-can or socket error, following the exception chain."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        code = getattr(current, "error_code", None) or getattr(current, "errno", None)
        if isinstance(code, int):
            return code
        current = current.__cause__ or current.__context__
    return None


def _open_fix(interface: str, channel: str, bitrate: int | None, exc: BaseException) -> str:
    """Advice for a failure to open the bus."""
    import can

    code = _error_code(exc)
    if isinstance(exc, can.CanInterfaceNotImplementedError):
        return (f"interface '{interface}' is not usable here: use one python-can knows "
                "(socketcan on a vehicle, virtual or udp_multicast for tests) and install its driver")
    if interface == "socketcan":
        if code == errno.EAFNOSUPPORT:
            return "this kernel has no SocketCAN loaded: modprobe can can_raw (and the adapter's driver)"
        if code in (errno.ENODEV, errno.ENXIO):
            return (f"no CAN interface '{channel}': plug in the adapter, then `{bring_up_hint(channel, bitrate)}` "
                    "(udev/70-u2sa-can.rules, installed by u2sa install, does this when the adapter appears)")
        if code in (errno.EACCES, errno.EPERM):
            return "no permission to open a CAN socket: run the service with CAP_NET_RAW or as root"
    if interface == "udp_multicast":
        return (f"cannot join multicast group '{channel}': check the group address, the port option "
                "and that the host has a multicast route (ip route add 224.0.0.0/4 dev lo for one host)")
    return f"check interface '{interface}' and channel '{channel}' in the device's address (can://INTERFACE/CHANNEL)"


def _record(device: str, direction: int, msg: can.Message) -> RawCanFrame:
    record = RawCanFrame()
    record.device = device
    record.direction = direction
    record.arbitration_id = int(msg.arbitration_id)
    record.is_extended_id = bool(msg.is_extended_id)
    record.is_remote_frame = bool(msg.is_remote_frame)
    record.is_error_frame = bool(msg.is_error_frame)
    record.dlc = int(msg.dlc)
    record.data = bytes(msg.data or b"")
    record.length = len(record.data)
    record.bus_timestamp = float(msg.timestamp or 0.0)
    return record


class CanPort:
    """An open CAN bus: ``send`` and ``recv`` frames (``can.Message``), tapped, errors mapped."""

    def __init__(self, bus: can.BusABC, *, device: str, interface: str, channel: str,
                 bitrate: int | None = None, tap: Tap | None = None,
                 clock: CanDeviceClock | None = None) -> None:
        import can

        self._errors = (can.CanError, OSError, ValueError)
        self.device = device
        self.interface = interface
        self.channel = channel
        self.bitrate = bitrate
        self.address = f"{interface}:{channel}"
        self._bus = bus
        self._tap = tap
        self._closed = False
        self._close_lock = threading.Lock()
        self.clock = clock   # the replay's device clock (clock=stamped), else None

    def now(self) -> float:
        """The driver's time (s, ``time.monotonic()`` base): the device clock on a stamped bus."""
        return self.clock.now() if self.clock is not None else time.monotonic()

    @property
    def is_open(self) -> bool:
        """True until the port is closed or the bus is lost."""
        return not self._closed

    def _check_open(self) -> None:
        if self._closed:
            raise PortClosed(self.device, "port is closed", address=self.address,
                             fix="open the port again (ReconnectingPort does this)")

    def _is_loss(self, exc: BaseException) -> bool:
        # A bus shut down underneath us (python-can's own flag) or a socket error that
        # means the interface is gone; anything else is one failed frame.
        if getattr(self._bus, "_is_shutdown", False):
            return True
        return _error_code(exc) in _LOST_ERRNOS

    def _fail(self, exc: BaseException, action: str) -> PortClosed | PortIOError:
        """Map a python-can/socket error to PortClosed (bus gone) or PortIOError (one frame)."""
        if self._is_loss(exc):
            self.close()
            fix = (f"bring the bus back: `{bring_up_hint(self.channel, self.bitrate)}`, check the adapter"
                   if self.interface == "socketcan" else "restart the bus peer; ReconnectingPort reopens it")
            return PortClosed(self.device, f"{action} failed, bus lost ({exc})", address=self.address, fix=fix)
        fix = ("check bus wiring, termination and bitrate (ip -details -statistics link show "
               f"{self.channel})" if self.interface == "socketcan" else "check the peers on this bus")
        return PortIOError(self.device, f"{action} failed ({exc})", address=self.address, fix=fix)

    def send(self, msg: can.Message, *, timeout: float | None = None) -> None:
        """Send one frame (tapped as TX once the bus accepted it)."""
        self._check_open()
        try:
            self._bus.send(msg, timeout=timeout)
        except self._errors as exc:
            raise self._fail(exc, "send") from exc
        if tapping(self._tap):
            call_tap(self._tap, _record(self.device, TX, msg))

    def recv(self, timeout: float) -> can.Message | None:
        """The next frame, or None if none arrives within *timeout* seconds (tapped as RX)."""
        self._check_open()
        try:
            msg = self._bus.recv(timeout)
        except self._errors as exc:
            raise self._fail(exc, "receive") from exc
        if msg is not None:
            if self.clock is not None and msg.timestamp:   # an unstamped frame (another member's) leaves it
                self.clock.frame(float(msg.timestamp))
            if tapping(self._tap):
                call_tap(self._tap, _record(self.device, RX, msg))
        return msg

    def close(self) -> None:
        """Shut the bus down (idempotent)."""
        with self._close_lock:
            self._closed = True
            try:
                self._bus.shutdown()
            except Exception as exc:  # noqa: BLE001 - python-can backends may raise anything on shutdown
                log.debug("%s: shutting down %s: %s", self.device, self.address, exc)

    def __enter__(self) -> CanPort:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<CanPort {self.device} {self.address} {'open' if self.is_open else 'closed'}>"


def open_can(*, device: str, interface: str, channel: str, bitrate: int | None = None,
             tap: Tap | None = None, **bus_options: Any) -> CanPort:
    """Open the CAN bus ``interface``/``channel`` as *device*.

    *bus_options* go to ``can.Bus`` unchanged (e.g. ``port=`` for udp_multicast,
    ``receive_own_messages=`` for virtual). Raises PortUnavailable naming the device and
    the fix when the bus cannot be opened. ``clock="stamped"`` (udp_multicast only: a replay's bus)
    keeps the senders' stamps and gives the port a device clock; any other interface refuses it.
    """
    import can

    from u2sa_hw.ports.can.clock import CAN_CLOCKS, CanDeviceClock, StampedUdpMulticastBus

    kwargs = dict(bus_options)
    clock = kwargs.pop("clock", None)
    address = f"{interface}:{channel}"
    if clock is not None and (clock not in CAN_CLOCKS or interface != "udp_multicast"):
        raise PortUnavailable(device, f"clock={clock!r} is not for this bus", address=address,
                              fix="clock=stamped is only for a replay's mock+can udp_multicast bus; remove clock=")
    if bitrate is not None:
        kwargs["bitrate"] = bitrate
    try:
        bus = StampedUdpMulticastBus(channel=channel, **kwargs) if clock else \
            can.Bus(interface=interface, channel=channel, **kwargs)
    except (can.CanError, OSError, ValueError) as exc:
        raise PortUnavailable(device, f"cannot open CAN bus ({exc})", address=address,
                              fix=_open_fix(interface, channel, bitrate, exc)) from exc
    log.debug("%s: opened %s", device, address)
    return CanPort(bus, device=device, interface=interface, channel=channel, bitrate=bitrate, tap=tap,
                   clock=CanDeviceClock() if clock else None)
