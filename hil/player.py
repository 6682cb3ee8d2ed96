"""The replay clock: walks a log in order and hands each recorded record to its replay device
(or republishes it on the replay bus) at its time.

Timing:

- ``rate`` (``--rate X``, default 1): a record recorded *t* seconds into the window goes out
  *t / X* seconds after the playback started. Silences are scaled too, so a driver that ends
  a burst on silence (``epoch_gap_s``) sees the same bursts as long as X times its gap stays
  above a few milliseconds.
- fast (``--fast``, ``rate=None``): no clock. A device's next record goes out as soon as its
  driver has taken the previous one (the pty is empty), each burst of a device (records closer
  than its driver's ``epoch_gap_s``) is written at once, and silences between bursts are not
  reproduced in wall time: a serial device carries each chunk's recorded read time and a tick
  after each recorded silence in the pty (the serial device clock, u2sa_hw/ports/serial/replay.py), and
  a GPIO replay chip its edges' kernel stamps (hil/replay_gpio.py), so the drivers group and
  time by the recorded times at any speed (see docs/replay.md).

A device may also take recorded bus messages as its input (``bus_inputs``: the channels; a GPIO
replay chip hands its driver the recorded Health and FAILSAFE the RC mux decides by): they reach
it as :class:`RecordedBusMessage` records, in log order with its raw records, whatever their
source (republishing, above, is a separate matter).

The player streams the log (a long one is never loaded whole) and stops early when the
``abort`` event is set, raising the reason the orchestration stored.
"""

from __future__ import annotations

import heapq
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator

from u2sa_hw.channels import base_type
from u2sa_hw.messages import REGISTRY, MalformedMessage
from u2sa_hw.recording.log_reader import LogFile
from u2sa_hw.bus.transport import Transport

from u2sa_hw.hil.replay_devices import ReplayDevice
from u2sa_hw.ports.serial.replay import ReplayStalled


@dataclass
class PlayStats:
    """What the player did."""

    records: int = 0          # device records fed
    republished_on: dict[str, int] = field(default_factory=dict)   # bus messages republished, by channel
    malformed: int = 0        # records that did not decode (skipped)
    late_s: float = 0.0       # the largest lag behind the clock (rate mode)
    wall_s: float = 0.0       # playback time
    started_ns: int = 0       # wall clock (ns) when the playback began: log time start_ns was played then
    order_waits: int = 0      # republished messages held until the replayed state was the recorded one
    order_timeouts: int = 0   # ... that went out after ORDER_WAIT_S without it (the replay never got there)

    @property
    def republished(self) -> int:
        """Bus messages republished, on every channel."""
        return sum(self.republished_on.values())


# Channels a replayed service publishes that decide what another replayed service does with a republished
# message, with the fields that do: the RC mux's RC_MODE admits or refuses an actuator's ACTUATOR_CMD by its
# mode and autonomy_enabled (u2sa_hw.safety.gate). Recorded, the mode change came before the first obeyed
# command; replayed --fast, the player would republish that command while the replayed mux was still decoding
# the edges before it, and the driver refused it. So a republished message waits until the replayed state
# (those fields of the replayed service's newest message) is the recorded one as of the message: a state,
# not a count, because a loaded recording machine may have made the mux flap more or less often than a
# replay does where it was held up (hil/held_up.py).
ORDERED_CHANNELS: dict[str, tuple[str, ...]] = {"RC_MODE": ("mode", "autonomy_enabled")}
# How long a republished message waits for it before it goes out anyway (counted, and that state is not
# waited for again): well under the replay devices' clock grace (2 s), or a state the replay never reaches
# would starve every replayed driver meanwhile.
ORDER_WAIT_S = 0.5


def authority_key(channel: str, msg: Any) -> tuple[Any, ...]:
    """The values of *channel*'s deciding fields (ORDERED_CHANNELS) in *msg*."""
    return tuple(getattr(msg, name, None) for name in ORDERED_CHANNELS[channel])


class RecordedBusMessage:
    """A recorded bus message for a device that takes it as input: its channel, its LCM bytes and its log time."""

    __slots__ = ("channel", "data", "log_time_ns")

    def __init__(self, channel: str, data: bytes, log_time_ns: int) -> None:
        self.channel, self.data, self.log_time_ns = channel, data, log_time_ns


def header_source(msg: Any) -> str:
    """The source service in a message's root header ('' if it has none)."""
    cur = msg
    while cur is not None:
        header = getattr(cur, "header", None)
        if header is not None and hasattr(header, "source"):
            return header.source
        cur = getattr(cur, "base", None)
    return ""


def _targeted(target: str, items: Iterator[tuple[int, Any]]) -> Iterator[tuple[int, str, Any]]:
    """``(t, payload)`` items as ``(t, target, payload)`` events."""
    for t_ns, payload in items:
        yield t_ns, target, payload


def _open_bounds(open_: dict[str, list[Any]], gaps: dict[str, int]) -> tuple[int | None, int | None]:
    """Of the open bursts (device -> [first t, last t, ...]): the earliest time one closes, the earliest first record."""
    if not open_:
        return None, None
    return min(b[1] + gaps[d] for d, b in open_.items()), min(b[0] for b in open_.values())


class Player:
    """Plays the window [start_ns, end_ns] of a log into devices and onto the replay bus."""

    def __init__(self, log_path: Any, *, devices: dict[str, ReplayDevice], transport: Transport | None,
                 republish: set[str], replayed_services: set[str], start_ns: int, end_ns: int,
                 rate: float | None, abort: threading.Event, abort_reason: Callable[[], str],
                 progress: Callable[[float], None] = lambda _s: None, stall_timeout_s: float = 20.0,
                 replayed_state: Callable[[str], tuple[Any, ...] | None] | None = None) -> None:
        if rate is not None and not rate > 0:
            raise ValueError(f"--rate must be > 0, got {rate!r}")
        self.log_path = log_path
        self.devices = devices
        self.transport = transport
        self.republish = republish
        self.replayed = replayed_services
        self.start_ns, self.end_ns = start_ns, end_ns
        self.rate = rate
        self.abort = abort
        self.abort_reason = abort_reason
        self.progress = progress
        self.stall_timeout_s = stall_timeout_s
        self.stats = PlayStats()
        # ORDERED_CHANNELS: the replayed services' newest state on each, as the replay bus carried it (None:
        # not watched); the recorded state as of the next republished message; states given up waiting for
        self.replayed_state = replayed_state
        self._want_state: dict[str, tuple[Any, ...]] = {}
        self._given_up: dict[str, tuple[Any, ...]] = {}
        self.bus_inputs: dict[str, list[str]] = {}   # channel -> devices that take its recorded messages
        for name, device in devices.items():
            for channel in getattr(device, "bus_inputs", ()):
                self.bus_inputs.setdefault(channel, []).append(name)

    # -- the recorded stream -------------------------------------------------------------------
    def events(self) -> Iterator[tuple[int, str, Any]]:
        """``(log time ns, target, payload)`` in log order: target a device name, or ``"bus:<channel>"``
        with the recorded bytes; a device's clock ticks (a GPIO replay chip's, through recorded
        silences) are merged in at their log times."""
        ticks = [_targeted(name, device.clock_ticks()) for name, device in self.devices.items()
                 if hasattr(device, "clock_ticks")]
        if not ticks:
            return self._recorded()
        return heapq.merge(self._recorded(), *ticks, key=lambda e: e[0])

    def _wanted(self, channel: str) -> bool:
        """Whether the player needs *channel*'s messages (asked once per channel of the log)."""
        if channel.startswith("RAW."):
            device = channel[4:]
            return bool(getattr(self.devices.get(device), "streamed", device in self.devices))
        return channel in self.bus_inputs or channel in self.republish or self._ordered(channel)

    def _ordered(self, channel: str) -> bool:
        return self.replayed_state is not None and channel in ORDERED_CHANNELS

    def _recorded(self) -> Iterator[tuple[int, str, Any]]:
        start_ns, end_ns = self.start_ns, self.end_ns
        for channel, log_time_ns, data in LogFile(self.log_path).selected(self._wanted):
            if log_time_ns < start_ns:
                continue
            if log_time_ns > end_ns:
                break
            if channel.startswith("RAW."):
                try:
                    record, _ = REGISTRY.decode(data)
                except MalformedMessage:
                    self.stats.malformed += 1
                    continue
                yield log_time_ns, channel[4:], record
                continue
            for device in self.bus_inputs.get(channel, ()):
                yield log_time_ns, device, RecordedBusMessage(channel, data, log_time_ns)
            ordered = self._ordered(channel)
            if channel in self.republish or ordered:
                try:
                    msg, _ = REGISTRY.decode(data, base_type(channel))
                except MalformedMessage:
                    self.stats.malformed += 1
                    continue
                replayed = header_source(msg) in self.replayed
                if not replayed and channel in self.republish:
                    yield log_time_ns, f"bus:{channel}", data
                elif replayed and ordered:
                    yield log_time_ns, f"order:{channel}", authority_key(channel, msg)

    def _bursts(self) -> Iterator[tuple[int, str, Any]]:
        """Fast mode: each device's bursts written whole.

        A burst is a run of one device's records with recorded gaps shorter than the device's
        ``burst_gap_s`` (its driver's ``epoch_gap_s``: no silence its driver could have noticed).
        Records of other devices recorded in between go out after it, so no stall on another
        device can put a silence into the middle of a burst. Items leave in the order of their
        first record's time.
        """
        held: list[tuple[int, int, str, Any]] = []       # finished items, a heap by first time
        open_: dict[str, list[Any]] = {}                 # device -> [first t, last t, payload, order]
        merges = {name: getattr(d, "merge", None) for name, d in self.devices.items()}
        gaps = {name: self._gap_ns(name) for name in self.devices}
        push, pop = heapq.heappush, heapq.heappop
        order = 0
        # while a burst is open: the earliest time one can close (its last record + its gap) and the earliest
        # first record (nothing later leaves before it); kept as bursts change, not sought per record
        close_at: int | None = None
        horizon: int | None = None
        for t_ns, target, payload in self.events():
            if close_at is not None and t_ns >= close_at:
                for dev in [d for d, b in open_.items() if t_ns - b[1] >= gaps[d]]:
                    b = open_.pop(dev)
                    push(held, (b[0], b[3], dev, b[2]))
                close_at, horizon = _open_bounds(open_, gaps)
            merge = merges.get(target)
            if merge is None:
                if horizon is None and not held:   # nothing waits for a burst: straight out, in order
                    order += 1
                    yield t_ns, target, payload
                    continue
                push(held, (t_ns, order, target, payload))
            else:
                b = open_.get(target)
                joined = merge(b[2], payload) if b is not None else None
                if joined is not None:
                    b[1], b[2] = t_ns, joined
                else:
                    if b is not None:
                        push(held, (b[0], b[3], target, b[2]))
                    open_[target] = [t_ns, t_ns, payload, order]
                close_at, horizon = _open_bounds(open_, gaps)
            order += 1
            while held and (horizon is None or held[0][0] < horizon):
                first, _, dev, item = pop(held)
                yield first, dev, item
        for dev, b in open_.items():
            push(held, (b[0], b[3], dev, b[2]))
        while held:
            first, _, dev, item = pop(held)
            yield first, dev, item

    def _gap_ns(self, device: str) -> int:
        return int(getattr(self.devices.get(device), "burst_gap_s", 0.0) * 1e9)

    # -- playing ---------------------------------------------------------------------------------
    def run(self) -> PlayStats:
        """Play the window; returns the stats (ReplayStalled or the abort reason as RuntimeError on failure)."""
        started = time.monotonic()
        self.stats.started_ns = time.time_ns()
        stream = self._bursts() if self.rate is None else self.events()
        for t_ns, target, payload in stream:
            if self.abort.is_set():
                raise RuntimeError(self.abort_reason())
            offset_s = (t_ns - self.start_ns) / 1e9
            if self.rate is not None:
                due = started + offset_s / self.rate
                delay = due - time.monotonic()
                if delay > 0 and self.abort.wait(delay):
                    raise RuntimeError(self.abort_reason())
                self.stats.late_s = max(self.stats.late_s, -delay)
            if target.startswith("order:"):
                if self.replayed_state is not None:
                    self._want_state[target[6:]] = payload
                continue
            if target.startswith("bus:"):
                channel = target[4:]
                if self._want_state:
                    self._wait_ordered()
                if self.transport is not None:
                    self.transport.publish_bytes(channel, payload)
                self.stats.republished_on[channel] = self.stats.republished_on.get(channel, 0) + 1
            else:
                device = self.devices[target]
                limit = getattr(device, "backlog_limit", 0)
                if self.rate is None and (not limit or self._backlog_due(device)):
                    self.wait_taken(device, limit=limit)
                device.feed(payload)
                self.stats.records += 1
            self.progress(offset_s)
        if self.rate is None:
            for device in self.devices.values():
                self.wait_taken(device)
        else:  # the window's end, so timer-driven services get the whole window and the speed is honest
            rest = started + (self.end_ns - self.start_ns) / 1e9 / self.rate - time.monotonic()
            if rest > 0 and self.abort.wait(rest):
                raise RuntimeError(self.abort_reason())
        self.progress((self.end_ns - self.start_ns) / 1e9)
        self.stats.wall_s = time.monotonic() - started
        return self.stats

    def _wait_ordered(self) -> None:
        """Hold a republished message until the replayed state on every ORDERED_CHANNELS channel is the
        recorded one as of it (at most ORDER_WAIT_S; then it goes out, counted, and that state is not waited
        for again)."""
        assert self.replayed_state is not None
        state = self.replayed_state

        def behind() -> list[str]:
            return [c for c, want in self._want_state.items() if self._given_up.get(c) != want and state(c) != want]

        waiting = behind()
        if not waiting:
            return
        self.stats.order_waits += 1
        deadline = time.monotonic() + ORDER_WAIT_S
        pause = 0.0002
        while waiting:
            if self.abort.is_set():
                raise RuntimeError(self.abort_reason())
            if time.monotonic() > deadline:
                self.stats.order_timeouts += 1
                for c in waiting:
                    self._given_up[c] = self._want_state[c]
                return
            time.sleep(pause)
            pause = min(0.002, pause * 2)
            waiting = behind()

    def _backlog_due(self, device: ReplayDevice) -> bool:
        """Whether to check the backlog of *device* (one with a backlog allowance) before its next record: when
        it says so (``backlog_due()``: the CAN device, every so many frames it sent, as its pending() reads
        /proc), else every 16 records."""
        due = getattr(device, "backlog_due", None)
        return bool(due()) if due is not None else self.stats.records % 16 == 0

    def wait_taken(self, device: ReplayDevice, *, limit: int = 0) -> None:
        """Wait until *device*'s driver has taken everything fed so far (all but *limit*)."""
        left = device.pending()
        if left <= limit:
            return
        deadline = time.monotonic() + self.stall_timeout_s
        pause = 0.0002
        while left > limit:
            if self.abort.is_set():
                raise RuntimeError(self.abort_reason())
            if time.monotonic() > deadline:
                raise ReplayStalled(f"{device.name}: its driver has not taken any of its input for "
                                    f"{self.stall_timeout_s:g} s; is the service still running?")
            time.sleep(pause)
            pause = min(0.002, pause * 2)
            now_left = device.pending()
            if now_left < left:   # progress: a long input (reads at the driver's pace) may take a while
                deadline = time.monotonic() + self.stall_timeout_s
            left = now_left
