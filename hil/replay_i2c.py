"""The replay I2C bus: chips answering a driver's register reads with a log's recorded reads, its data
reads paced by the player (the interface of :mod:`u2sa_hw.hil.replay_devices`; made by
:func:`u2sa_hw.hil.replay_buses.make_device`).

I2C is pulled: the driver reads, the chip answers. The recorded reads are loaded before the
replay starts (:meth:`ReplayI2cDevice.preload`) and each read of a register (by chip address)
is answered with the next recorded answer for that register, in order. The driver's reads
of its data register (the most-read one) are paced by the player, as every other device is:
the player feeds the device's records in log order, each recorded read of the data register
*releases* one read, and a read not released yet is held (the I2C analogue is clock
stretching: the chip holds the read until the data exists). The bus's address says
``paced=true``, so the driver reads again as soon as it has published a sample instead of
waiting for its ``rate_hz`` timer (docs/ports.md): its pace is the player's. Other reads
(identification, setup, a magnetometer's) are answered at once. A read the recording has no
answer for left is answered with the register's last value from before the replayed window
(the driver's identification at start, when the window starts later), else refused with
EIO; both are counted. Writes are checked, in order, against the recorded writes to the
same chip, and every difference is counted.

A driver that writes a register differently from the recording (a changed setting) and
reads it back to verify gets its own value back: a
recorded read byte that equals what the recorded driver last wrote to that register is
answered with what the replayed driver wrote there (registers auto-increment, as on the
supported chips). The chip's data registers are never written, so the samples stay as recorded.

A driver held in a read cannot ping a watchdog or see its SIGTERM: the replay runs it without the
launcher's watchdog and stops its bus before stopping it (:func:`held_drivers`,
:func:`release_held_reads`).
"""

from __future__ import annotations

import threading
from collections import deque
from pathlib import Path
from typing import Any, Mapping

from u2sa_hw.ports.address import DeviceAddress, make_address
from u2sa_hw.ports.i2c.wire import OP_READ, OP_WRITE, STATUS_EIO, STATUS_NACK, STATUS_OK
from u2sa_hw.recording.log_reader import LogFile

from u2sa_hw.hil.replay_cut import raw_records
from u2sa_hw.hil.replay_plan import ReplayError

I2C_BACKLOG_READS = 8       # --fast: data reads released ahead of the driver, so it samples beside the player
# The replay bus's client timeout (timeout= in its mock+i2c address). The driver's first data read is held
# from its set-up until the playback starts (the other services' start-up, up to the replay's 30 s readiness
# limit, and the discovery of what they subscribe to), and a later one while the player waits on another
# device (up to its 20 s stall limit); the mock client's default 2 s would drop and reopen the port meanwhile,
# set the chip up again and diverge from the recording.
I2C_CLIENT_TIMEOUT_S = 60.0


class ReplayI2cChip:
    """One chip address on the replay bus (the MockI2cBus chip interface: ``address``, ``handle``)."""

    def __init__(self, address: int, owner: "ReplayI2cDevice") -> None:
        self.address = address
        self.owner = owner

    def handle(self, op: int, register: int, length: int, data: bytes) -> tuple[int, bytes]:
        """Answer a read from the recording (a data read may wait for the player); check a write against it."""
        return self.owner.transact(self.address, op, register, length, data)


def _replay_bus_class() -> type:
    """A MockI2cBus that does not hold its bus lock around a chip's answer (imported when a replay starts)."""
    from u2sa_hw.mocks.i2c_bus import MockI2cBus

    class ReplayI2cBus(MockI2cBus):
        """The replay's bus: a held data read must not keep another chip (an AK8963 on its own connection)
        or another client off the bus; the replay device serialises its chips' answers itself."""

        def transact(self, op: int, address: int, register: int, length: int, data: bytes) -> tuple[int, bytes]:
            chip = self._chips.get(address)
            if chip is None:
                return STATUS_NACK, b""
            return chip.handle(op, register, length, data)

    return ReplayI2cBus


class ReplayI2cDevice:
    """A mock I2C bus whose chips answer with a log's recorded register reads, data reads paced by the player."""

    kind = "i2c"
    streamed = True    # the player feeds its records: each recorded data read releases one read

    def __init__(self, *, name: str, socket_path: Path | str, fast: bool) -> None:
        self.name = name
        self.socket_path = Path(socket_path)
        self.fast = fast
        self.backlog_limit = I2C_BACKLOG_READS           # --fast: the player's wait_taken allowance
        self._lock = threading.Lock()
        self._released_cond = threading.Condition(self._lock)
        self._reads: dict[tuple[int, int], deque[tuple[bool, bytes]]] = {}
        self._before: dict[tuple[int, int], tuple[bool, bytes]] = {}
        self._writes: dict[int, deque[tuple[int, bytes]]] = {}
        self._main: tuple[int, int] | None = None    # the data register: its reads are released by the player
        self._released = 0    # recorded reads of _main fed by the player
        self._asked = 0       # reads of _main the driver has asked for (answered, or held)
        self._stopped = False
        self._recorded_written: dict[tuple[int, int], int] = {}   # (address, register) -> byte, by the recording
        self._replay_written: dict[tuple[int, int], int] = {}     # ... and by the replayed driver
        self._bus: Any = None
        self.counts = {"reads": 0, "from_before_window": 0, "unrecorded_reads": 0, "length_mismatches": 0,
                       "writes": 0, "write_mismatches": 0, "unrecorded_writes": 0, "gated_reads": 0,
                       "refused_at_stop": 0}

    def mock_address(self, real: DeviceAddress | None) -> str:
        """``mock+i2c://<the replay bus socket>/<the recorded chip address>?timeout=<I2C_CLIENT_TIMEOUT_S>&paced=true``.

        ``paced``: the driver reads back to back, as fast as the player releases the reads, whatever the
        replay's rate (``--fast`` or ``--rate X``), instead of on its ``rate_hz`` timer, which would cap a
        ``--fast`` replay at rate_hz / recorded rate and fall behind a ``--rate`` above 1. The data
        register is then the most-read one of that chip (the MPU-9250's burst, not its AK8963's
        read of the same count), when the recording read that chip."""
        if real is None or real.kind != "i2c":
            raise ReplayError(f"RAW.{self.name}: the log's profile gives no I2C address for this device "
                              f"({real.url if real else 'none'}); give the profile with --vehicle FILE")
        self._choose_main(real.chip_address)
        return make_address("i2c", str(self.socket_path), (real.chip_address,), mock=True, device=self.name,
                            params={"timeout": f"{I2C_CLIENT_TIMEOUT_S:g}", "paced": "true"}).url

    def config_changes(self) -> dict[str, Any]:
        """Nothing besides the address: the driver runs with its recorded settings (its sample rate too)."""
        return {}

    def preload(self, log_path: Path, *, start_ns: int, end_ns: int) -> None:
        """Load the device's recorded transactions: reads in the window queued per register, the last
        read of each register before it, and the writes in it (checked)."""
        for log_time_ns, rec in raw_records(LogFile(log_path), self.name, "RawI2c"):
            if log_time_ns > end_ns:
                break
            key = (int(rec.address), int(rec.register_address))
            if rec.op == OP_READ:
                if log_time_ns < start_ns:
                    self._before[key] = (bool(rec.ok), bytes(rec.data))
                else:
                    self._reads.setdefault(key, deque()).append((bool(rec.ok), bytes(rec.data)))
            elif rec.op == OP_WRITE and log_time_ns >= start_ns:
                self._writes.setdefault(key[0], deque()).append((key[1], bytes(rec.data)))
        self._choose_main(None)

    def _choose_main(self, chip: int | None) -> None:
        """The data register: the most-read (address, register), of *chip* when it was read (ties: read
        first); none when no register was read twice (nothing to pace)."""
        keys = [k for k in self._reads if chip is None or k[0] == chip] or list(self._reads)
        main = max(keys, key=lambda k: len(self._reads[k])) if keys else None
        with self._lock:
            if self._released or self._asked:
                return   # the playback has begun: the gate stays where it is
            self._main = main if main is not None and len(self._reads[main]) > 1 else None

    def start(self) -> None:
        """Serve the replay bus with one replay chip per recorded address."""
        self._bus = _replay_bus_class()(socket_path=str(self.socket_path))
        for address in sorted({a for a, _ in self._reads} | {a for a, _ in self._before} | set(self._writes)):
            self._bus.add(ReplayI2cChip(address, self))
        self._bus.start()

    def stop(self) -> None:
        """Refuse every held and later data read (EIO, counted in ``refused_at_stop``), so no driver or
        bus thread waits for a release that will not come, and stop serving (the driver's connection closes)."""
        with self._released_cond:
            self._stopped = True
            self._released_cond.notify_all()
        if self._bus is not None:
            self._bus.stop()
            self._bus = None

    def ready(self, pid: int | None, health: dict[str, str]) -> bool:
        """The driver's port is open: its identification and setup reads were answered. (It cannot run
        ahead of the playback: its first data read is held until the player releases it.)"""
        return health.get("port", "open") == "open"

    def feed(self, record: Any) -> None:
        """A recorded read of the data register releases one read of it; other records were preloaded."""
        if self._main is None or getattr(record, "op", None) != OP_READ:
            return
        if (int(record.address), int(record.register_address)) != self._main:
            return
        with self._released_cond:
            self._released += 1
            self._released_cond.notify_all()

    def pending(self) -> int:
        """Data reads released that the driver has not asked for yet (two counters: cheap, called often)."""
        return max(0, self._released - self._asked)

    def transact(self, address: int, op: int, register: int, length: int, data: bytes) -> tuple[int, bytes]:
        """One transaction from the driver (on the bus's client thread); a data read waits for its release."""
        key = (address, register)
        with self._released_cond:
            if op == OP_WRITE:
                self._check_write(address, register, data)
                return STATUS_OK, b""
            if key == self._main:
                ticket = self._asked
                self._asked += 1
                if ticket >= self._released and not self._stopped:
                    self.counts["gated_reads"] += 1
                    self._released_cond.wait_for(lambda: ticket < self._released or self._stopped)
                if ticket >= self._released:
                    self.counts["refused_at_stop"] += 1
                    return STATUS_EIO, b""
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

    def _check_write(self, address: int, register: int, data: bytes) -> None:
        """Count a write and any difference from the next recorded write to the chip (lock held)."""
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
        """Transactions answered, data reads held for the player, and every kind of difference from the recording."""
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
                                 f"{c['unrecorded_writes']} writes beyond them")
        return out


def held_drivers(devices: Mapping[str, Any], services: Mapping[str, str]) -> set[str]:
    """The services (*services*: device -> its service) whose drivers read a replay I2C bus: they run without
    the launcher's watchdog (``Launcher(unwatched=...)``), because such a driver's loop waits in a data read
    held for the player (start-up, another device's stall, a recorded pause at --rate) and cannot ping; a
    driver that stops taking its reads is the player's stall instead."""
    return {services[name] for name, device in devices.items()
            if isinstance(device, ReplayI2cDevice) and services.get(name)}


def release_held_reads(devices: Mapping[str, Any]) -> None:
    """Stop the replay I2C buses before their drivers: a driver's data read beyond the recording is held
    there, and a driver waiting in it would not see its SIGTERM until the launcher's grace ran out. Its
    read fails, its connection closes and it stops at once."""
    for device in devices.values():
        if isinstance(device, ReplayI2cDevice):
            device.stop()
