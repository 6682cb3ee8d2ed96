"""The CAN kind's replay device: a private UDP multicast bus that plays a log's ``RawCanFrame`` records to a driver.

:class:`ReplayCanDevice` sends the recorded RX frames onto a bus laid out as python-can's
``udp_multicast`` (the kind's wire end, :func:`u2sa_hw.ports.can.clock.pack_frame`), each with its
recorded bus timestamp, and counts the driver's frames; :func:`udp_backlog` tells the player how
much waits unread in the driver's socket (``--fast`` pacing). It needs nothing from ``hil``, so it
lives in its kind's package; the replay (``hil/``) makes it through the kind's ``replay`` part
(``u2sa_hw.hil.replay_buses.make_can_device``) and plays into it.
"""

from __future__ import annotations

import os
import socket
import struct
import threading
from collections import Counter
from typing import Any

from u2sa_hw.ports.address import DeviceAddress, make_address
from u2sa_hw.ports.can.clock import CAN_GROUP, join_bus, pack_frame
from u2sa_hw.ports.tap import TX

__all__ = ["CAN_BACKLOG_BYTES", "CAN_CHECK_EVERY", "CAN_DRAIN_PERIOD_S", "CAN_GROUP", "ReplayCanDevice",
           "socket_inodes", "udp_backlog"]

# --fast pacing of the driver's CAN socket (its receive buffer: net.core.rmem_default, 212,992 bytes here; a
# frame's datagram takes ~830 bytes of it, its truesize): the player checks the unread bytes every
# CAN_CHECK_EVERY frames sent and waits while they exceed CAN_BACKLOG_BYTES, so at most
# CAN_BACKLOG_BYTES plus CAN_CHECK_EVERY datagrams (~73 kB) ever wait there (tests/test_replay_can_device.py)
CAN_BACKLOG_BYTES = 32_768
CAN_CHECK_EVERY = 48
CAN_DRAIN_PERIOD_S = 0.02     # the counting thread reads the bus in batches this often
CAN_RCVBUF_BYTES = 4 << 20    # its socket's receive buffer asked for (granted up to net.core.rmem_max unless root)
_SO_MEMINFO = 55              # Linux: getsockopt -> struct sk_meminfo (u32 x 9), [8] the datagrams dropped


class ReplayCanDevice:
    """A private udp_multicast CAN bus: recorded RX frames are sent to the driver, its frames are counted.

    Frames the recorded driver received are sent in order, each with its recorded bus timestamp
    (the driver's port, ``clock=stamped``, keeps it: its clock and its odometry's pairing run on the
    recorded times, not on when the replay delivered them), except the echoes of its own
    frames (on udp_multicast a node hears what it sends; the replayed driver hears its own
    again). What the driver sends depends on its timers (setpoints re-sent every
    ``command_period_s``), so its frames are counted, not compared frame by frame.

    The frames go out as :func:`u2sa_hw.ports.can.clock.pack_frame` datagrams from a socket of their own
    (not bound to the bus's port), so the bus socket that counts tells them from every other member's
    (sent from the port, as python-can's and the driver's bus send) by the sender's port, without
    decoding; a thread reads it in
    batches (:data:`CAN_DRAIN_PERIOD_S`) rather than waking for every datagram.
    """

    kind = "can"

    def __init__(self, *, name: str, port: int) -> None:
        self.name = name
        self.port = port
        self.backlog_limit = CAN_BACKLOG_BYTES
        self._tx: socket.socket | None = None        # sends the recorded frames
        self._rx: socket.socket | None = None        # a member of the bus: hears the driver's frames (and ours)
        self._tx_port = 0                            # the port the recorded frames come from
        self._pid: int | None = None
        self._inodes: set[str] = set()
        self._unchecked = 0                          # frames sent since pending() last looked
        self._reader: threading.Thread | None = None
        self._stop = threading.Event()
        self._recorded_tx: Counter[tuple[int, bool, bytes]] = Counter()
        self._drain_lock = threading.Lock()
        self.counts = {"fed": 0, "echoes_skipped": 0, "recorded_tx": 0, "driver_tx": 0}

    def mock_address(self, real: DeviceAddress | None) -> str:
        """``mock+can://udp_multicast/<group>?port=<the private port>&clock=stamped``."""
        return make_address("can", CAN_GROUP, params={"port": self.port, "clock": "stamped"}, mock=True, backend="udp_multicast",
                            device=self.name).url

    def config_changes(self) -> dict[str, Any]:
        """Nothing besides the address."""
        return {}

    def start(self) -> None:
        """Join the bus (as python-can does) and count what the driver sends."""
        self._rx = join_bus(self.port, rcvbuf=CAN_RCVBUF_BYTES)
        self._tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, struct.pack("@I", 1))  # python-can's hop limit
        self._tx.bind(("", 0))
        self._tx_port = int(self._tx.getsockname()[1])
        self._reader = threading.Thread(target=self._read_loop, name=f"replay-{self.name}", daemon=True)
        self._reader.start()

    def stop(self) -> None:
        """Leave the bus."""
        self._stop.set()
        if self._reader is not None:
            self._reader.join(timeout=2.0)
            self._reader = None
        with self._drain_lock:
            for sock in (self._tx, self._rx):
                if sock is not None:
                    sock.close()
            self._tx = self._rx = None

    def ready(self, pid: int | None, health: dict[str, str]) -> bool:
        """The driver's bus is open (frames sent before it joined the group would be lost)."""
        self._pid = pid
        return health.get("bus") == "open"

    def feed(self, record: Any) -> None:
        """Send a recorded RX frame (not an echo of the recorded driver's own); note a TX frame."""
        key = (int(record.arbitration_id), bool(record.is_remote_frame), bytes(record.data))
        if record.direction == TX:
            self._recorded_tx[key] += 1
            self.counts["recorded_tx"] += 1
            return
        if self._recorded_tx[key] > 0:
            self._recorded_tx[key] -= 1
            self.counts["echoes_skipped"] += 1
            return
        data = pack_frame(timestamp=float(record.bus_timestamp or 0.0), arbitration_id=key[0],
                          is_extended_id=bool(record.is_extended_id), is_remote_frame=key[1],
                          is_error_frame=bool(record.is_error_frame), dlc=int(record.dlc), data=key[2])
        assert self._tx is not None, "feed() before start()"
        self._tx.sendto(data, (CAN_GROUP, self.port))
        self._unchecked += 1
        self.counts["fed"] += 1

    def backlog_due(self) -> bool:
        """--fast: whether the player should look at the driver's backlog now (each CAN_CHECK_EVERY frames sent)."""
        return self._unchecked >= CAN_CHECK_EVERY

    def pending(self) -> int:
        """Bytes waiting unread in the driver's socket on the replay bus's port (Linux /proc)."""
        self._unchecked = 0
        if self._pid and not self._inodes:
            self._inodes = socket_inodes(self._pid)
        return udp_backlog(self._pid, self.port, self._inodes)

    def _read_loop(self) -> None:
        while not self._stop.wait(CAN_DRAIN_PERIOD_S):
            self._drain()

    def _drain(self) -> None:
        """Count the driver's frames waiting in the bus socket (ours, heard back, are left out by their sender)."""
        with self._drain_lock:
            rx, ours = self._rx, self._tx_port
            if rx is None:
                return
            theirs = 0
            try:
                while True:
                    _, sender = rx.recvfrom(4096, socket.MSG_DONTWAIT)
                    if sender[1] != ours:
                        theirs += 1
            except BlockingIOError:   # all read
                pass
            self.counts["driver_tx"] += theirs

    def report(self) -> dict[str, Any]:
        """Frames fed, echoes left out, and the driver's frames against the recording's (and any the count missed)."""
        self._drain()
        return {"kind": self.kind, **self.counts, "driver_tx_lost": _dropped(self._rx), "divergences": 0}


def _dropped(sock: socket.socket | None) -> int:
    """Datagrams the kernel dropped on *sock* for a full buffer (0 when unknown: not Linux, or closed)."""
    if sock is None:
        return 0
    try:
        return int(struct.unpack("9I", sock.getsockopt(socket.SOL_SOCKET, _SO_MEMINFO, 36))[8])
    except (OSError, struct.error):
        return 0


def socket_inodes(pid: int) -> set[str]:
    """The inodes of the sockets process *pid* holds (Linux /proc)."""
    inodes: set[str] = set()
    try:
        for entry in os.scandir(f"/proc/{pid}/fd"):
            try:
                target = os.readlink(entry.path)
            except OSError:
                continue
            if target.startswith("socket:["):
                inodes.add(target[8:-1])
    except OSError:
        pass
    return inodes


def udp_backlog(pid: int | None, port: int, inodes: set[str]) -> int:
    """Unread bytes in those of *inodes* (sockets of process *pid*) bound to UDP *port* (0 when unknown)."""
    if not pid or not inodes:
        return 0
    try:
        with open(f"/proc/{pid}/net/udp") as fh:
            rows = fh.read().splitlines()[1:]
    except OSError:
        return 0
    total = 0
    for row in rows:
        f = row.split()
        if len(f) > 9 and f[9] in inodes and int(f[1].rsplit(":", 1)[1], 16) == port:
            total += int(f[4].split(":")[1], 16)
    return total
