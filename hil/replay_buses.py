"""Replay devices for the buses: I2C chips answering with recorded register reads, and CAN
frames sent onto a private python-can bus. Serial is in :mod:`hil.replay_devices`; the
interface is the same.

I2C is pulled, not pushed: the driver reads when its own timer says so, so the recorded reads
are loaded before the replay starts and each read of a register (by chip address) is
answered with the next recorded answer for that register, in order, whatever the timing.
A read the recording has no answer for left is answered with the register's last value
from before the replayed window (the driver's identification at start, when the window
starts later), else refused with EIO; both are counted. Writes are checked, in order,
against the recorded writes to the same chip, and every difference is counted.

A driver that writes a register differently from the recording (a changed setting, or
its sample rate raised for --fast, as it declares) and reads it back to verify gets its own value back: a
recorded read byte that equals what the recorded driver last wrote to that register is
answered with what the replayed driver wrote there (registers auto-increment, as on the
supported chips). The chip's data registers are never written, so the samples stay as recorded.
"""

from __future__ import annotations

import os
import re
import threading
from collections import Counter, deque
from pathlib import Path
from typing import Any, Mapping

from u2sa_hw.messages import REGISTRY, MalformedMessage
from u2sa_hw.ports.address import DeviceAddress, make_address
from u2sa_hw.ports.i2c_port import OP_READ, OP_WRITE, STATUS_EIO, STATUS_OK
from u2sa_hw.ports.tap import TX
from u2sa_hw.recording.log_reader import LogFile
from u2sa_hw.udp_ports import private_udp_port

from hil.replay_plan import DevicePlan, ReplayError

CAN_GROUP = "239.74.163.2"  # python-can's default IPv4 group for udp_multicast; the port is the replay's own
CAN_BACKLOG_BYTES = 32_768  # --fast: unread bytes allowed in the driver's CAN socket (its buffer is ~200 kB)


class ReplayI2cChip:
    """One chip address on the replay bus (the MockI2cBus chip interface: ``address``, ``handle``)."""

    def __init__(self, address: int, owner: "ReplayI2cDevice") -> None:
        self.address = address
        self.owner = owner

    def handle(self, op: int, register: int, length: int, data: bytes) -> tuple[int, bytes]:
        """Answer a read from the recording; check a write against it."""
        return self.owner.transact(self.address, op, register, length, data)


class ReplayI2cDevice:
    """A mock I2C bus whose chips answer with a log's recorded register reads."""

    kind = "i2c"
    streamed = False   # loaded before the start (preload); the player does not feed it

    def __init__(self, *, name: str, socket_path: Path | str, fast: bool,
                 fast_settings: Mapping[str, Any] | None = None) -> None:
        self.name = name
        self.socket_path = Path(socket_path)
        self.fast = fast
        self.fast_settings = dict(fast_settings or {})   # the driver's declaration (replay_options)
        self._lock = threading.Lock()
        self._reads: dict[tuple[int, int], deque[tuple[bool, bytes]]] = {}
        self._before: dict[tuple[int, int], tuple[bool, bytes]] = {}
        self._writes: dict[int, deque[tuple[int, bytes]]] = {}
        self._main: tuple[int, int] | None = None    # the most-read register: its queue paces --fast
        self._recorded_written: dict[tuple[int, int], int] = {}   # (address, register) -> byte, by the recording
        self._replay_written: dict[tuple[int, int], int] = {}     # ... and by the replayed driver
        self._bus: Any = None
        self.counts = {"reads": 0, "from_before_window": 0, "unrecorded_reads": 0, "length_mismatches": 0,
                       "writes": 0, "write_mismatches": 0, "unrecorded_writes": 0}

    def mock_address(self, real: DeviceAddress | None) -> str:
        """``mock+i2c://<the replay bus socket>/<the recorded chip address>``."""
        if real is None or real.kind != "i2c":
            raise ReplayError(f"RAW.{self.name}: the log's profile gives no I2C address for this device "
                              f"({real.url if real else 'none'}); give the profile with --vehicle FILE")
        return make_address("i2c", str(self.socket_path), (real.chip_address,), mock=True, device=self.name).url

    def config_changes(self) -> dict[str, Any]:
        """With --fast, the settings the driver declares for it (an IMU: its highest sample rate)."""
        return dict(self.fast_settings) if self.fast else {}

    def preload(self, log_path: Path, *, start_ns: int, end_ns: int) -> None:
        """Load the device's recorded transactions: reads in the window queued per register."""
        for m in LogFile(log_path).messages(rf"RAW\.{re.escape(self.name)}"):
            if m.log_time_ns > end_ns:
                break
            try:
                rec, _ = REGISTRY.decode(m.data)
            except MalformedMessage:
                continue
            if type(rec).__name__ != "RawI2c":
                continue
            key = (int(rec.address), int(rec.register_address))
            if rec.op == OP_READ:
                if m.log_time_ns < start_ns:
                    self._before[key] = (bool(rec.ok), bytes(rec.data))
                else:
                    self._reads.setdefault(key, deque()).append((bool(rec.ok), bytes(rec.data)))
            elif rec.op == OP_WRITE and m.log_time_ns >= start_ns:
                self._writes.setdefault(key[0], deque()).append((key[1], bytes(rec.data)))
        if self._reads:
            self._main = max(self._reads, key=lambda k: len(self._reads[k]))

    def start(self) -> None:
        """Serve the replay bus with one replay chip per recorded address."""
        from mock_devices.i2c_bus import MockI2cBus

        self._bus = MockI2cBus(socket_path=str(self.socket_path))
        for address in sorted({a for a, _ in self._reads} | {a for a, _ in self._before} | set(self._writes)):
            self._bus.add(ReplayI2cChip(address, self))
        self._bus.start()

    def stop(self) -> None:
        """Stop serving."""
        if self._bus is not None:
            self._bus.stop()
            self._bus = None

    def ready(self, pid: int | None, health: dict[str, str]) -> bool:
        """The driver's port is open (its identification and setup reads were answered), or the driver
        has already taken every recorded read of its data register: an I2C driver pulls its reads on its
        own timer from its start (with --fast at the rate its driver declares), so on a loaded machine it can reach
        the end of a short recording, and lose its port to the EIO that follows, before the other
        services are ready; its outputs are captured all the same."""
        with self._lock:
            if self._main is not None and not self._reads.get(self._main) and self.counts["reads"]:
                return True
        return health.get("port", "open") == "open"

    def feed(self, record: Any) -> None:
        """Nothing: the recording was loaded by preload()."""

    def pending(self) -> int:
        """Recorded reads of the most-read register not asked for yet."""
        with self._lock:
            return len(self._reads.get(self._main, ())) if self._main is not None else 0

    def transact(self, address: int, op: int, register: int, length: int, data: bytes) -> tuple[int, bytes]:
        """One transaction from the driver (on the bus's client thread)."""
        key = (address, register)
        with self._lock:
            if op == OP_WRITE:
                self.counts["writes"] += 1
                expected = self._writes.get(address)
                if not expected:
                    self.counts["unrecorded_writes"] += 1
                else:
                    rec_register, rec_data = expected.popleft()
                    if (rec_register, rec_data) != (register, bytes(data)):
                        self.counts["write_mismatches"] += 1
                    for i, b in enumerate(rec_data):
                        self._recorded_written[(address, rec_register + i)] = b
                for i, b in enumerate(data):
                    self._replay_written[(address, register + i)] = b
                return STATUS_OK, b""
            self.counts["reads"] += 1
            queue = self._reads.get(key)
            if queue:
                ok, answer = queue.popleft()
            elif key in self._before:
                self.counts["from_before_window"] += 1
                ok, answer = self._before[key]
            else:
                self.counts["unrecorded_reads"] += 1
                return STATUS_EIO, b""
            if not ok:
                return STATUS_EIO, b""
            if len(answer) != length:
                self.counts["length_mismatches"] += 1
                answer = (answer + bytes(length))[:length]
            return STATUS_OK, self._echo_writes(address, register, answer)

    def _echo_writes(self, address: int, register: int, answer: bytes) -> bytes:
        """*answer* with each byte the recorded driver had written replaced by the replayed driver's."""
        out = bytearray(answer)
        for i, b in enumerate(out):
            key = (address, register + i)
            recorded = self._recorded_written.get(key)
            if recorded is not None and b == recorded and key in self._replay_written:
                out[i] = self._replay_written[key]
        return bytes(out)

    def report(self) -> dict[str, Any]:
        """Transactions answered and every kind of difference from the recording."""
        with self._lock:
            unread = sum(len(q) for q in self._reads.values())
            unwritten = sum(len(q) for q in self._writes.values())
            c = dict(self.counts)
        divergences = c["unrecorded_reads"] + c["length_mismatches"] + c["write_mismatches"] + c["unrecorded_writes"]
        out: dict[str, Any] = {"kind": self.kind, **c, "recorded_reads_left": unread,
                               "recorded_writes_left": unwritten, "divergences": divergences}
        if divergences:
            out["divergence"] = (f"{c['unrecorded_reads']} reads with no recorded answer, {c['length_mismatches']} "
                                 f"of another length, {c['write_mismatches']} writes unlike the recorded ones, "
                                 f"{c['unrecorded_writes']} writes beyond them"
                                 + (f" (--fast replayed with {self._fast_text()})"
                                    if self.fast and self.fast_settings else ""))
        return out


    def _fast_text(self) -> str:
        return ", ".join(f"{k} = {v!r}" for k, v in self.fast_settings.items())


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
        fast_settings = options.get("fast_settings")
        return ReplayI2cDevice(name=dev.name, socket_path=run_dir / f"i2c-{dev.name}.sock", fast=fast,
                               fast_settings=fast_settings if isinstance(fast_settings, Mapping) else None)
    if dev.kind == "can":
        return ReplayCanDevice(name=dev.name, port=private_udp_port())
    raise ReplayError(f"RAW.{dev.name}: replaying {dev.kind or 'unknown'} devices is not supported here; "
                      "leave the device out with --vehicle (a profile without its service)")
