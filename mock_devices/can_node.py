"""What every mock CAN node shares: a python-can bus participant on its own thread.

A mock CAN node is the device, so it opens a python-can ``Bus`` itself (``virtual`` within
one process, ``udp_multicast`` across processes, ``socketcan`` on a vcan interface if one
exists) and meets the driver only on that channel. :class:`MockCanNode` runs one thread
that receives frames, hands those the device accepts to ``_handle`` and calls ``_tick`` at a
fixed rate for the device's control loop and cyclic messages; it keeps the history and the
faults every node has (``stop_answering``, ``inject_garbage``, ``send_error_frames``).

The device's time (what its handlers and ticks are given: timeouts, watchdogs, cyclic
messages, history stamps) comes from its *clock*, ``time.monotonic`` unless a test injects
one it steps itself: the thread still ticks at ``tick_hz`` of real time, but what the device
sees as the gap between two frames is then the test's, whatever the machine's load.

python-can's ``udp_multicast`` bus delivers a process's own datagrams back to it (the
socket joins the group with multicast loop on), unlike a real CAN controller. The node
therefore remembers what it sent for a second and drops the matching echoes, so its own
heartbeats never reach its handlers or its history as received frames.
"""

from __future__ import annotations

import argparse
import logging
import math
import signal
import struct
import threading
import time
from abc import ABC, abstractmethod
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import can

from u2sa_hw.mocks.vehicle_sim import SimVehicle

log = logging.getLogger(__name__)

TX = "tx"  # node -> bus
RX = "rx"  # bus -> node
ECHO_WINDOW_S = 1.0
# SocketCAN error class CAN_ERR_BUSERROR, what a controller reports for a corrupted frame
BUS_ERROR_ID = 0x080


@dataclass(frozen=True)
class FrameRecord:
    """One frame the node sent (tx) or accepted (rx); ``t`` is the node's clock, ``note`` e.g. "garbage"."""

    t: float
    direction: str
    message: can.Message
    note: str = ""


class PeriodicSchedule:
    """Says when a cyclic message is due at *hz* (0 = never), without bursts after a stall; the first
    time is *start* (the owner's clock now; default time.monotonic())."""

    def __init__(self, hz: float, *, start: float | None = None) -> None:
        self.period = 1.0 / hz if hz > 0 else math.inf
        self._next = time.monotonic() if start is None else start

    def due(self, now: float) -> bool:
        """True once per period; the next deadline is kept on the grid unless we fell a period behind."""
        if now < self._next:
            return False
        self._next = self._next + self.period if now - self._next < self.period else now + self.period
        return True


class WheelOdometer:
    """One side's wheel travel and speed from the vehicle's odometer, in simulation time.

    The speed is the odometer difference over the simulation time between two samples that
    straddle at least one vehicle step, so it is exact for a constant speed whatever the
    threads' timing.
    """

    def __init__(self, vehicle: SimVehicle, side: str) -> None:
        if side not in ("left", "right"):
            raise ValueError(f"side must be 'left' or 'right', got {side!r}")
        self.vehicle = vehicle
        self.side = side
        t, odo = self._read()
        self._origin = odo
        self._last = (t, odo)
        self._speed = 0.0

    def _read(self) -> tuple[float, float]:
        truth = self.vehicle.snapshot()
        return truth.t, truth.wheel_left_m if self.side == "left" else truth.wheel_right_m

    def rebase(self) -> None:
        """Make the current odometer reading distance 0 (a device reboot)."""
        self._origin = self._read()[1]

    def sample(self) -> tuple[float, float]:
        """(distance in m since start or rebase, speed in m/s) of this side's wheel surface."""
        t, odo = self._read()
        t0, odo0 = self._last
        if t > t0:
            self._speed = (odo - odo0) / (t - t0)
            self._last = (t, odo)
        return odo - self._origin, self._speed


def _frame_key(msg: can.Message) -> tuple:
    return (msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame, msg.is_error_frame, msg.dlc,
            bytes(msg.data))


class MockCanNode(ABC):
    """A device on a python-can bus: receive loop, control tick, history and common faults.

    *clock*: the device's time in seconds (module docstring); ``time.monotonic`` by default.
    """

    def __init__(self, *, name: str, interface: str, channel: str, bus_options: Mapping[str, Any] | None = None,
                 tick_hz: float = 100.0, history_size: int = 10_000,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if tick_hz <= 0:
            raise ValueError(f"{name}: tick_hz must be > 0, got {tick_hz!r}")
        self.name = name
        self.interface = interface
        self.channel = channel
        self.bus_options: dict[str, Any] = dict(bus_options or {})
        self.tick_period = 1.0 / tick_hz
        self.clock = clock
        self.rx_errors = 0  # receive failures (undecodable datagrams, bus errors)
        self.dropped = 0  # accepted frames the device could not use (bad length, bad value)
        self._history: deque[FrameRecord] = deque(maxlen=history_size)
        self._lock = threading.RLock()
        self._silent = False
        self.config_frozen = False  # freeze_config(True): configuration writes acknowledged, not applied
        self._echoes: deque[tuple[float, tuple]] = deque()
        self._filter_echoes = interface == "udp_multicast"
        self._bus: can.BusABC | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    # ---- life cycle ------------------------------------------------------------------
    @property
    def address(self) -> str:
        """``interface:channel`` as a driver config names it (bus_options such as a udp port aside)."""
        return f"{self.interface}:{self.channel}"

    def start(self) -> None:
        """Open the bus and run the node's thread."""
        if self._thread is not None:
            raise RuntimeError(f"{self.name}: already started")
        try:
            self._bus = can.Bus(interface=self.interface, channel=self.channel, **self.bus_options)
        except (can.CanError, OSError, ValueError) as exc:
            raise RuntimeError(f"{self.name}: cannot open CAN bus {self.address} {self.bus_options or ''}: {exc}; "
                               f"check the interface name and channel (python-can 'virtual' or "
                               f"'udp_multicast' for mocks)") from exc
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the thread, release the motor and close the bus."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        with self._lock:
            self._on_stop()
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None

    def __enter__(self) -> "MockCanNode":
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ---- history and faults ----------------------------------------------------------
    @property
    def history(self) -> list[FrameRecord]:
        """Frames sent (tx) and accepted (rx), oldest first, up to history_size records."""
        return list(self._history)

    def stop_answering(self, on: bool) -> None:
        """Cut the node off the bus (on=True): it neither sends nor hears frames, but keeps running."""
        with self._lock:
            self._silent = bool(on)

    def freeze_config(self, on: bool) -> None:
        """Acknowledge configuration writes but keep the old values (a read-only endpoint, a failed
        flash write): what a driver then reads back disagrees with what it wrote."""
        with self._lock:
            self.config_frozen = bool(on)

    @property
    def answering(self) -> bool:
        """False while stop_answering(True) is in force."""
        return not self._silent

    def inject_garbage(self, count: int = 1) -> None:
        """Send *count* frames on the node's own ids with payloads too short to decode."""
        with self._lock:
            for _ in range(count):
                self._send(self._garbage_frame(), note="garbage", force=True)

    def send_error_frames(self, count: int = 1) -> None:
        """Put *count* error frames (SocketCAN CAN_ERR_BUSERROR) on the bus, as a disturbed bus does."""
        with self._lock:
            for _ in range(count):
                frame = can.Message(arbitration_id=BUS_ERROR_ID, is_error_frame=True, dlc=8, data=bytes(8))
                self._send(frame, note="error frame", force=True)

    # ---- for subclasses --------------------------------------------------------------
    @abstractmethod
    def _handle(self, msg: can.Message, now: float) -> bool:
        """Act on a received frame; return True if the device accepted it (it then enters history)."""

    @abstractmethod
    def _tick(self, now: float) -> None:
        """Run the control loop and send due cyclic frames; called every tick with the lock held."""

    @abstractmethod
    def _garbage_frame(self) -> can.Message:
        """A frame on the node's own id with a payload the protocol cannot decode."""

    def _on_stop(self) -> None:
        """Power-off hook (release the motor)."""

    def _send(self, msg: can.Message, *, note: str = "", force: bool = False) -> None:
        """Send *msg* unless the node is cut off (force: fault injection sends anyway)."""
        if (self._silent and not force) or self._bus is None:
            return
        now = self.clock()
        if self._filter_echoes:
            self._echoes.append((now, _frame_key(msg)))
        try:
            self._bus.send(msg)
        except can.CanError as exc:
            log.warning("%s: send on %s failed: %s", self.name, self.address, exc)
            return
        self._history.append(FrameRecord(now, TX, msg, note))

    # ---- the thread ------------------------------------------------------------------
    def _is_echo(self, msg: can.Message, now: float) -> bool:
        while self._echoes and now - self._echoes[0][0] > ECHO_WINDOW_S:
            self._echoes.popleft()
        key = _frame_key(msg)
        for i, (_, sent) in enumerate(self._echoes):
            if sent == key:
                del self._echoes[i]
                return True
        return False

    def _receive(self, msg: can.Message) -> None:
        now = self.clock()
        with self._lock:
            if self._filter_echoes and self._is_echo(msg, now):
                return
            if self._silent or msg.is_error_frame:
                return
            try:
                accepted = self._handle(msg, now)
            except (ValueError, struct.error) as exc:  # the protocol modules' decode errors
                self.dropped += 1
                log.info("%s: dropped %s: %s", self.name, msg, exc)
                accepted = True
            if accepted:
                self._history.append(FrameRecord(now, RX, msg))

    def _run(self) -> None:
        bus = self._bus
        assert bus is not None
        next_tick = time.monotonic()
        while not self._stop.is_set():
            try:
                msg = bus.recv(timeout=max(0.0, next_tick - time.monotonic()))
            except (can.CanError, OSError, ValueError) as exc:
                self.rx_errors += 1
                log.info("%s: receive on %s failed: %s", self.name, self.address, exc)
                msg = None
                self._stop.wait(0.01)  # a broken socket must not spin the CPU
            if msg is not None:
                self._receive(msg)
            now = time.monotonic()   # the thread's schedule is real time; the device's time is its clock
            if now >= next_tick:
                with self._lock:
                    try:
                        self._tick(self.clock())
                    except Exception:  # the device must keep running; the log says what broke
                        log.exception("%s: control tick failed", self.name)
                next_tick = next_tick + self.tick_period if now - next_tick < 1.0 else now + self.tick_period


# ---- running a node as its own process (tests across processes, manual bench work) --------
def add_bus_arguments(parser: argparse.ArgumentParser) -> None:
    """The options every node's ``python -m`` entry point takes: bus, udp port and vehicle side."""
    parser.add_argument("--interface", default="udp_multicast", help="python-can interface (default udp_multicast)")
    parser.add_argument("--channel", default="239.74.163.2", help="python-can channel (default the IPv4 group)")
    parser.add_argument("--port", type=int, default=None, help="udp_multicast port (python-can default 43113)")
    parser.add_argument("--side", choices=("left", "right"), default="left")


def bus_options(args: argparse.Namespace) -> dict[str, Any]:
    """python-can Bus keyword options from the parsed arguments."""
    return {"port": args.port} if args.port is not None else {}


def serve(node: MockCanNode, vehicle: SimVehicle) -> None:
    """Run *vehicle* and *node* until SIGTERM or SIGINT; print "ready" once the bus is open."""
    done = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: done.set())
    vehicle.start()
    node.start()
    print(f"ready {node.name} on {node.address}", flush=True)
    try:
        done.wait()
    finally:
        node.stop()
        vehicle.stop()
