"""Replay devices for the buses: the I2C bus (:mod:`hil.replay_i2c`: chips answering with recorded
register reads, data reads paced by the player), and CAN frames sent onto a private python-can bus.
Serial is in :mod:`hil.replay_devices`; the interface is the same. :func:`make_device` makes either.
"""

from __future__ import annotations

import os
import threading
from collections import Counter
from pathlib import Path
from typing import Any, Mapping

from u2sa_hw.ports.address import DeviceAddress, make_address
from u2sa_hw.ports.tap import TX
from u2sa_hw.udp_ports import private_udp_port

from hil.replay_i2c import I2C_BACKLOG_READS, I2C_CLIENT_TIMEOUT_S, ReplayI2cChip, ReplayI2cDevice
from hil.replay_plan import DevicePlan, ReplayError

__all__ = ["CAN_BACKLOG_BYTES", "CAN_GROUP", "I2C_BACKLOG_READS", "I2C_CLIENT_TIMEOUT_S", "ReplayCanDevice",
           "ReplayI2cChip", "ReplayI2cDevice", "make_device", "socket_inodes", "udp_backlog"]

CAN_GROUP = "239.74.163.2"  # python-can's default IPv4 group for udp_multicast; the port is the replay's own
CAN_BACKLOG_BYTES = 32_768  # --fast: unread bytes allowed in the driver's CAN socket (its buffer is ~200 kB)


class ReplayCanDevice:
    """A private udp_multicast CAN bus: recorded RX frames are sent to the driver, its frames are counted.

    Frames the recorded driver received are sent in order, each with its recorded bus timestamp
    (the driver's port, ``clock=stamped``, keeps it: its clock and its odometry's pairing run on the
    recorded times, not on when the replay delivered them), except the echoes of its own
    frames (on udp_multicast a node hears what it sends; the replayed driver hears its own
    again). What the driver sends depends on its timers (setpoints re-sent every
    ``command_period_s``), so its frames are counted, not compared frame by frame.
    """

    kind = "can"

    def __init__(self, *, name: str, port: int) -> None:
        self.name = name
        self.port = port
        self.backlog_limit = CAN_BACKLOG_BYTES
        self._bus: Any = None
        self._pid: int | None = None
        self._inodes: set[str] = set()
        self._reader: threading.Thread | None = None
        self._stop = threading.Event()
        self._recorded_tx: Counter[tuple[int, bool, bytes]] = Counter()
        self._sent: Counter[tuple[int, bool, bytes]] = Counter()
        self._lock = threading.Lock()
        self.counts = {"fed": 0, "echoes_skipped": 0, "recorded_tx": 0, "driver_tx": 0}

    def mock_address(self, real: DeviceAddress | None) -> str:
        """``mock+can://udp_multicast/<group>?port=<the private port>&clock=stamped``."""
        return make_address("can", CAN_GROUP, params={"port": self.port, "clock": "stamped"}, mock=True, backend="udp_multicast",
                            device=self.name).url

    def config_changes(self) -> dict[str, Any]:
        """Nothing besides the address."""
        return {}

    def start(self) -> None:
        """Join the bus and count what the driver sends."""
        import can

        self._bus = can.Bus(interface="udp_multicast", channel=CAN_GROUP, port=self.port)
        self._reader = threading.Thread(target=self._read_loop, name=f"replay-{self.name}", daemon=True)
        self._reader.start()

    def stop(self) -> None:
        """Leave the bus."""
        self._stop.set()
        if self._reader is not None:
            self._reader.join(timeout=2.0)
            self._reader = None
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None

    def ready(self, pid: int | None, health: dict[str, str]) -> bool:
        """The driver's bus is open (frames sent before it joined the group would be lost)."""
        self._pid = pid
        return health.get("bus") == "open"

    def feed(self, record: Any) -> None:
        """Send a recorded RX frame (not an echo of the recorded driver's own); note a TX frame."""
        import can

        key = (int(record.arbitration_id), bool(record.is_remote_frame), bytes(record.data))
        if record.direction == TX:
            self._recorded_tx[key] += 1
            self.counts["recorded_tx"] += 1
            return
        if self._recorded_tx[key] > 0:
            self._recorded_tx[key] -= 1
            self.counts["echoes_skipped"] += 1
            return
        msg = can.Message(arbitration_id=key[0], is_extended_id=bool(record.is_extended_id),
                          is_remote_frame=key[1], is_error_frame=bool(record.is_error_frame),
                          dlc=int(record.dlc), data=key[2], timestamp=float(record.bus_timestamp or 0.0))
        with self._lock:
            self._sent[key] += 1
        self._bus.send(msg)
        self.counts["fed"] += 1

    def pending(self) -> int:
        """Bytes waiting unread in the driver's socket on the replay bus's port (Linux /proc)."""
        if self._pid and not self._inodes:
            self._inodes = socket_inodes(self._pid)
        return udp_backlog(self._pid, self.port, self._inodes)

    def _read_loop(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self._bus.recv(0.1)
            except Exception:  # noqa: BLE001 - the bus was shut down under us
                return
            if msg is None:
                continue
            key = (int(msg.arbitration_id), bool(msg.is_remote_frame), bytes(msg.data))
            with self._lock:
                if self._sent[key] > 0:   # our own frame, heard back
                    self._sent[key] -= 1
                    continue
            self.counts["driver_tx"] += 1

    def report(self) -> dict[str, Any]:
        """Frames fed, echoes left out, and the driver's frames against the recording's."""
        return {"kind": self.kind, **self.counts, "divergences": 0}


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


def make_device(dev: DevicePlan, run_dir: Path, *, fast: bool, options: Mapping[str, Any]) -> Any:
    """The replay device for a bus device (*options*: what its driver declares a replay needs)."""
    if dev.kind == "i2c":
        return ReplayI2cDevice(name=dev.name, socket_path=run_dir / f"i2c-{dev.name}.sock", fast=fast)
    if dev.kind == "can":
        return ReplayCanDevice(name=dev.name, port=private_udp_port())
    raise ReplayError(f"RAW.{dev.name}: replaying {dev.kind or 'unknown'} devices is not supported here; "
                      "leave the device out with --vehicle (a profile without its service)")
