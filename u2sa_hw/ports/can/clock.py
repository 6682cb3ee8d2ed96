"""A device clock for replayed CAN buses: each frame keeps the time it was recorded at.

python-can's ``udp_multicast`` bus stamps a received frame with its own receive time, so a
replayed driver would pair wheel encoder frames and judge a silent node by when the replay
happened to deliver them, which ``u2sa replay --fast`` and a busy machine change. The replay's
CAN device (``u2sa_hw/ports/can/replay.py``) sends each recorded frame with its recorded bus timestamp
on a bus laid out as python-can's (group, port, loopback); :class:`StampedUdpMulticastBus` is
the driver's end of it and keeps that stamp, and :class:`CanDeviceClock` turns the stamps into
the driver's clock.

Only an address that says ``clock=stamped`` opens this bus, and only a ``mock+can`` address on
``udp_multicast`` may say it (the address parser and :func:`u2sa_hw.ports.can.port.open_can`
both refuse it otherwise): a real bus (SocketCAN) can never set the time its driver sees.
"""

from __future__ import annotations

import socket
import struct
import threading
import time
from collections import Counter
from typing import Any, Optional

import can

CAN_CLOCKS = ("stamped",)    # clock=stamped: the replay's frames carry their recorded bus time
DEVICE_CLOCK_GRACE_S = 2.0   # no frame for this long (wall): the clock runs on with the wall clock
OWN_FRAMES_HELD = 1024       # own datagrams awaiting their loopback copy (a lost copy cannot pile up)
CAN_GROUP = "239.74.163.2"   # python-can's default IPv4 group for udp_multicast

# A replay bus's datagram: a tag, then the frame's stamp (s), id, flags and DLC, then its data. A fixed
# layout read with one struct call, where python-can packs and unpacks a msgpack dict per frame and
# receives through select and recvmsg with a kernel timestamp nobody uses here (a replayed ODrive
# driver: about an eighth less CPU). A python-can udp_multicast member's datagram is still understood.
FRAME_TAG = b"U2CF"
FRAME_HEAD = struct.Struct(">4sdIBB")
_EXT, _RTR, _ERR, _FD, _BRS, _ESI = 1, 2, 4, 8, 16, 32
_UNSET = object()            # no socket timeout set yet (0.0 == False, so not False)


def pack_frame(*, timestamp: float, arbitration_id: int, is_extended_id: bool = True, is_remote_frame: bool = False,
               is_error_frame: bool = False, dlc: int, data: bytes, is_fd: bool = False, bitrate_switch: bool = False,
               error_state_indicator: bool = False) -> bytes:
    """A replay bus datagram of one frame (see :data:`FRAME_HEAD`); the defaults are ``can.Message``'s."""
    flags = (_EXT if is_extended_id else 0) | (_RTR if is_remote_frame else 0) | (_ERR if is_error_frame else 0) \
        | (_FD if is_fd else 0) | (_BRS if bitrate_switch else 0) | (_ESI if error_state_indicator else 0)
    return FRAME_HEAD.pack(FRAME_TAG, timestamp, arbitration_id, flags, dlc) + bytes(data)


def unpack_frame(data: bytes) -> can.Message:
    """The frame of a replay bus datagram (ValueError/struct.error when it is not one), or of a python-can
    udp_multicast member's (msgpack) datagram."""
    if not data.startswith(FRAME_TAG):
        from can.interfaces.udp_multicast.utils import unpack_message

        return unpack_message(data, check=True)
    _, stamp, arbitration_id, flags, dlc = FRAME_HEAD.unpack_from(data)
    return can.Message(timestamp=stamp, arbitration_id=arbitration_id, is_extended_id=bool(flags & _EXT),
                       is_remote_frame=bool(flags & _RTR), is_error_frame=bool(flags & _ERR), dlc=dlc,
                       data=data[FRAME_HEAD.size:], is_fd=bool(flags & _FD), bitrate_switch=bool(flags & _BRS),
                       error_state_indicator=bool(flags & _ESI), check=True)


def join_bus(port: int, *, group: str = CAN_GROUP, rcvbuf: int | None = None, hop_limit: int = 1) -> socket.socket:
    """A UDP socket on the multicast bus *group*:*port*, set up as python-can's udp_multicast member (address
    and port reuse, bound to the port, in the group, multicast loopback on, *hop_limit* hops). *rcvbuf*:
    the receive buffer to ask for (forced when root, else up to net.core.rmem_max)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if hasattr(socket, "SO_REUSEPORT"):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        if rcvbuf is not None:
            try:
                sock.setsockopt(socket.SOL_SOCKET, getattr(socket, "SO_RCVBUFFORCE", 33), rcvbuf)
            except OSError:   # not root: as much as net.core.rmem_max allows
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, struct.pack("@I", hop_limit))
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
        sock.bind(("", port))
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                        socket.inet_aton(group) + struct.pack("@I", socket.INADDR_ANY))
    except OSError:
        sock.close()
        raise
    return sock


class StampedUdpMulticastBus(can.BusABC):
    """A replay's CAN bus over UDP multicast (IPv4, python-can's udp_multicast layout: group, port, loopback)
    whose received frames keep the sender's timestamp (the recorded one).

    Frames travel as :func:`pack_frame` datagrams; a python-can udp_multicast member's are understood too
    (their stamp is that sender's). It hears none of its own frames, as a SocketCAN socket does not by
    default and as python-can's ``receive_own_messages=False`` promises (multicast loopback hands every
    datagram back to its sender): each datagram sent is held until its copy comes back, and that copy is
    dropped unread. The replay device's frames never match one (they carry a recorded stamp, the
    driver's do not).
    """

    def __init__(self, channel: str = CAN_GROUP, port: int = 43113, hop_limit: int = 1, fd: bool = True,
                 **kwargs: Any) -> None:
        if ":" in str(channel):
            raise can.CanInitializationError(f"a replay bus is IPv4 multicast; {channel!r} is not an IPv4 group")
        try:
            self._sock = join_bus(int(port), group=str(channel), hop_limit=int(hop_limit))
        except OSError as exc:
            raise can.CanInitializationError(f"could not join the replay bus {channel}:{port} ({exc})") from exc
        self._dest = (str(channel), int(port))
        self._fd = bool(fd)
        self._timeout: Any = _UNSET   # the socket's timeout as last set
        self._own: Counter[bytes] = Counter()
        self._own_lock = threading.Lock()
        self.channel_info = f"replay bus {channel}:{port}"
        super().__init__(channel=channel, **kwargs)

    def fileno(self) -> int:
        """The bus socket's descriptor (as python-can's udp_multicast bus)."""
        return self._sock.fileno()

    def send(self, msg: can.Message, timeout: Optional[float] = None) -> None:
        if msg.is_fd and not self._fd:
            raise can.CanOperationError("cannot send FD message over bus with CAN FD disabled")
        data = pack_frame(timestamp=msg.timestamp, arbitration_id=msg.arbitration_id,
                          is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
                          is_error_frame=msg.is_error_frame, dlc=msg.dlc, data=msg.data, is_fd=msg.is_fd,
                          bitrate_switch=msg.bitrate_switch, error_state_indicator=msg.error_state_indicator)
        with self._own_lock:
            held = len(self._own) < OWN_FRAMES_HELD or data in self._own
            if held:
                self._own[data] += 1
        try:
            # the socket's timeout is the receive path's (set by one thread, the driver's loop); a datagram to
            # the local group does not wait for room, so *timeout* is not applied (setting it here, from
            # another thread, would change a receive already waiting)
            self._sock.sendto(data, self._dest)
        except BaseException as exc:
            if held:
                self._forget(data)
            if isinstance(exc, (TimeoutError, BlockingIOError)):   # no room within the receive path's timeout
                raise can.CanTimeoutError() from None
            if isinstance(exc, OSError):
                raise can.CanOperationError(f"failed to send via socket ({exc})") from exc
            raise

    def _set_timeout(self, timeout: Optional[float]) -> None:
        if self._timeout is _UNSET or timeout != self._timeout:
            self._sock.settimeout(timeout)
            self._timeout = timeout

    def _forget(self, data: bytes) -> bool:
        """Drop one held copy of *data*; True if one was held."""
        with self._own_lock:
            n = self._own.get(data, 0)
            if n > 1:
                self._own[data] = n - 1
            elif n == 1:
                del self._own[data]
            return n > 0

    def _recv_internal(self, timeout: Optional[float]) -> tuple[Optional[can.Message], bool]:
        try:
            self._set_timeout(timeout)
            data = self._sock.recv(4096)
        except (TimeoutError, BlockingIOError):   # nothing within the timeout (0: nothing waiting)
            return None, False
        except OSError as exc:
            raise can.CanOperationError(f"failed to receive from the replay bus ({exc})") from exc
        if self._own and self._forget(data):
            return None, False   # our own frame, back through the loopback
        try:
            msg = unpack_frame(data)
        except Exception as exception:  # noqa: BLE001 - as python-can's own bus: any unpack failure
            raise can.CanOperationError("could not unpack received message") from exception
        # A frame its sender did not stamp (another member's) keeps timestamp 0: it says nothing about
        # the recorded time and must not move the device clock (its receive time would jump the clock
        # from the recording's times to now).
        if msg.is_fd and not self._fd:
            return None, False
        return msg, False

    def shutdown(self) -> None:
        super().shutdown()
        self._sock.close()


class CanDeviceClock:
    """The driver's clock on a stamped bus, in ``time.monotonic()`` seconds.

    Before the first frame it is the wall clock (monotonic). The first frame's stamp is tied to
    the monotonic time it arrived; from then on the clock is the latest frame's stamp on that
    base, so intervals are the recorded ones whatever the replay's speed or the machine's load.
    Fail safe: once no frame has come for :data:`DEVICE_CLOCK_GRACE_S` of wall time, the clock
    runs on with the wall clock from the last stamp, so a silent node still times out.
    """

    def __init__(self, grace_s: float = DEVICE_CLOCK_GRACE_S) -> None:
        self.grace_s = grace_s
        self._lock = threading.Lock()
        self._base: tuple[float, float] | None = None   # (first stamp, monotonic when it arrived)
        self._last: tuple[float, float] | None = None   # (latest stamp on the base, monotonic when it arrived)

    @property
    def started(self) -> bool:
        """True once a stamped frame has arrived."""
        return self._base is not None

    def frame(self, stamp: float) -> float:
        """A frame stamped *stamp* (s) arrived: the clock moves to it (never backwards); its time."""
        wall = time.monotonic()
        with self._lock:
            if self._base is None:
                self._base = (stamp, wall)
            t = self._base[1] + (stamp - self._base[0])
            if self._last is not None and t < self._last[0]:
                t = self._last[0]
            self._last = (t, wall)
            return t

    def now(self) -> float:
        """The device time now (see the class docstring)."""
        wall = time.monotonic()
        with self._lock:
            if self._last is None:
                return wall
            t, arrived = self._last
        quiet = wall - arrived
        return t + quiet if quiet >= self.grace_s else t
