"""A device clock for replayed CAN buses: each frame keeps the time it was recorded at.

python-can's ``udp_multicast`` bus packs the sender's ``Message.timestamp`` into every
datagram but stamps a received frame with its own receive time, so a replayed driver would
pair wheel encoder frames and judge a silent node by when the replay happened to deliver them,
which ``u2sa replay --fast`` and a busy machine change. The replay's CAN device
(``hil/replay_buses.py``) sends each recorded frame with its recorded bus timestamp;
:class:`StampedUdpMulticastBus` keeps that stamp, and :class:`CanDeviceClock` turns the stamps
into the driver's clock.

Only an address that says ``clock=stamped`` opens this bus, and only a ``mock+can`` address on
``udp_multicast`` may say it (the address parser and :func:`u2sa_hw.ports.can_port.open_can`
both refuse it otherwise): a real bus (SocketCAN) can never set the time its driver sees.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from typing import Any, Optional

import can
from can.interfaces.udp_multicast import UdpMulticastBus
from can.interfaces.udp_multicast.utils import pack_message, unpack_message

CAN_CLOCKS = ("stamped",)    # clock=stamped: the replay's frames carry their recorded bus time
DEVICE_CLOCK_GRACE_S = 2.0   # no frame for this long (wall): the clock runs on with the wall clock
OWN_FRAMES_HELD = 1024       # own datagrams awaiting their loopback copy (a lost copy cannot pile up)


class StampedUdpMulticastBus(UdpMulticastBus):
    """A ``udp_multicast`` bus whose received frames keep the sender's timestamp (the recorded one).

    It hears none of its own frames, as a SocketCAN socket does not by default and as python-can's
    ``receive_own_messages=False`` promises (multicast loopback hands every datagram back to its
    sender): each datagram sent is held until its copy comes back, and that copy is dropped unread.
    The replay device's frames never match one (they carry a recorded stamp, the driver's do not).
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._own: Counter[bytes] = Counter()
        self._own_lock = threading.Lock()

    def send(self, msg: can.Message, timeout: Optional[float] = None) -> None:
        if self._can_protocol is not can.CanProtocol.CAN_FD and msg.is_fd:
            raise can.CanOperationError("cannot send FD message over bus with CAN FD disabled")
        data = pack_message(msg)
        with self._own_lock:
            held = len(self._own) < OWN_FRAMES_HELD or data in self._own
            if held:
                self._own[data] += 1
        try:
            self._multicast.send(data, timeout)
        except BaseException:
            if held:
                self._forget(data)
            raise

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
        result = self._multicast.recv(timeout)
        if not result:
            return None, False
        data, _, _received = result
        if self._own and self._forget(data):
            return None, False   # our own frame, back through the loopback
        try:
            msg = unpack_message(data, check=True)
        except Exception as exception:  # noqa: BLE001 - as python-can's own bus: any unpack failure
            raise can.CanOperationError("could not unpack received message") from exception
        # A frame its sender did not stamp (another member's) keeps timestamp 0: it says nothing about
        # the recorded time and must not move the device clock (its receive time would jump the clock
        # from the recording's times to now).
        if msg.is_fd and not self.protocol == can.CanProtocol.CAN_FD:
            return None, False
        return msg, False


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
