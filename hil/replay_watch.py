"""What ``u2sa replay`` hears of the services it replays, and when the replay may end.

:class:`ReplayWatch` takes every message of the replay bus (:meth:`ReplayWatch.on_message`):
the replayed services' health (their details, and how many messages they took and published
per channel), how many of their outputs reached the replay, the newest replayed state of the
``ORDERED_CHANNELS`` (hil/player.py), and when one of them last published an output. An output
is a message on a channel of its own, or a raw record of what a driver drives (``RawPwmWrite``,
``RawGpioWrite`` on ``RAW.<device>``, the same records ``--compare`` compares): a servo driver's
last write follows its last command, and on a loaded machine it may come more than the quiet
time after the driver's health counted that command.

:meth:`ReplayWatch.settle` is the end of the play: it waits until every service's health counts
the recorded messages republished to it, then for ``settle_s`` (from that count at the earliest)
without a new output.
:func:`listeners` reads which replayed service takes which channel from the bus (their
discovery answers), which is what the first of those waits counts.
"""

from __future__ import annotations

import threading
import time
import uuid
from typing import Any, Callable, Container, Iterable, Mapping

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.channels import base_type
from u2sa_hw.messages import REGISTRY, MalformedMessage
from u2sa_hw.recording.mcap_log import header_source

from u2sa_hw.hil.compare_values import OUTPUT_RAW_TYPES, STATE_CHANNELS
from u2sa_hw.hil.player import ORDERED_CHANNELS, authority_key
from u2sa_hw.hil.replay_plan import ReplayError

CONTRACT_PREFIX = "U2SA_"
HEALTH_CHANNEL = "U2SA_HEALTH"
#: the LCM fingerprints (an encoded message's first 8 bytes) of the raw records of what a driver drives
OUTPUT_FINGERPRINTS = frozenset(getattr(t, name)._get_packed_fingerprint() for name in OUTPUT_RAW_TYPES)
GIVE_UP_S = 10.0   # the settle's longest wait


class ReplayWatch:
    """The replayed services as the replay bus shows them (see the module docstring).

    *services*: the names of the replayed services; *clock*: seconds, monotonic (a test passes its own).
    """

    def __init__(self, services: Container[str], *, clock: Callable[[], float] = time.monotonic) -> None:
        self.services = services
        self.clock = clock
        self.clocked = False   # a GPIO replay chip with edges: the drivers' timers stop with its clock
        self.health: dict[str, dict[str, str]] = {}   # service -> its latest health details
        self.received: dict[str, int] = {}    # service -> its outputs the replay bus delivered here
        self.replayed_state: dict[str, tuple[Any, ...]] = {}  # ORDERED_CHANNELS: the replayed services' newest
        self.published: dict[str, int] = {}   # service -> its outputs by its own count (latest health)
        self.heard: dict[str, dict[str, int]] = {}   # service -> messages it took per channel (latest health)
        self.listeners: dict[str, set[str]] = {}     # republished channel -> the services that take it from the bus
        self.last_output = clock()

    def on_message(self, channel: str, data: bytes) -> None:
        """One message of the replay bus (a raw subscription's callback)."""
        if channel.startswith(CONTRACT_PREFIX):
            if channel == HEALTH_CHANNEL:
                self._note_health(data)
            return
        if channel == "LCM_SELF_TEST":
            return
        if channel.startswith("RAW."):
            # a driver's tap of what it drives is its output too (not counted in received: health's counts leave
            # RAW out); the input records of the replay devices are not
            if data[:8] in OUTPUT_FINGERPRINTS and header_source(data) in self.services:
                self.last_output = self.clock()
            return
        source = header_source(data)
        if source in self.services:
            self.received[source] = self.received.get(source, 0) + 1
            if channel in ORDERED_CHANNELS:
                self._note_ordered(channel, data)
            # state channels are published on a timer too, so they are waited for only when that timer
            # runs on a replay chip's clock, which stops with the recorded edges (GPIO logs)
            if channel not in STATE_CHANNELS or self.clocked:
                self.last_output = self.clock()

    def _note_ordered(self, channel: str, data: bytes) -> None:
        """A replayed message on an ORDERED_CHANNELS channel: its deciding fields are the replayed state now."""
        try:
            msg, _ = REGISTRY.decode(data, base_type(channel))
        except MalformedMessage:
            return
        self.replayed_state[channel] = authority_key(channel, msg)

    def _note_health(self, data: bytes) -> None:
        try:
            msg = t.Health.decode(data)
        except Exception:  # noqa: BLE001 - a malformed health message is not our concern here
            return
        if msg.name in self.services:
            self.health[msg.name] = {kv.key: kv.value for kv in msg.details}
            self.heard[msg.name] = {c.channel: c.messages for c in msg.channels if c.direction == "in"}
            self.published[msg.name] = sum(c.messages for c in msg.channels if c.direction == "out" and not
                                           c.channel.startswith((CONTRACT_PREFIX, "RAW.")))

    def behind(self, republished_on: Mapping[str, int]) -> list[tuple[str, str]]:
        """(service, channel) pairs where the service's latest health counts fewer messages taken on the channel
        than were republished on it (at least: it may also hear the live services there)."""
        return [(service, channel) for channel, sent in republished_on.items()
                for service in sorted(self.listeners.get(channel, ()))
                if self.heard.get(service, {}).get(channel, 0) < sent]

    def settle(self, republished_on: Mapping[str, int], settle_s: float, *, abort: threading.Event,
               reason: Callable[[], str], sleep: Callable[[float], None] = time.sleep) -> None:
        """Wait until every service has taken the recorded messages republished to it (*republished_on*: how many
        per channel; by the counts in its health) and then published nothing new for *settle_s* (at most
        GIVE_UP_S); ReplayError with ``reason()`` when *abort* is set meanwhile.

        Without the first, a loaded machine could stop a driver before the last recorded command reached it
        (a servo driver's last write, its only output, was lost so). The quiet time starts when the counts are
        complete at the earliest, and a driver's raw output tap (its write) restarts it like any output: the
        write a command makes may follow the health that counted the command."""
        self.last_output = max(self.last_output, self.clock())
        give_up = self.clock() + GIVE_UP_S
        counted = False
        while self.clock() < give_up:
            behind = self.behind(republished_on)
            if not behind and not counted:
                # the quiet time runs from the count at the earliest: what a command makes a driver do (its write)
                # comes after the driver took it, and its health may count the command before that
                counted = True
                self.last_output = max(self.last_output, self.clock())
            if not behind and self.clock() - self.last_output >= settle_s:
                return
            if abort.is_set():
                raise ReplayError(reason())
            sleep(0.05)


def discover(url: str, services: Iterable[str], *, timeout: float = 1.5,
             resend: float = 0.25) -> dict[str, Any]:
    """The replayed *services*' discovery answers (name -> DiscoveryResponse): done as soon as every one has
    answered (the request is sent again every *resend* s), else what answered within *timeout*. They are all
    up (their health was heard), so this takes a round trip, not a fixed wait for stragglers."""
    wanted = list(services)
    found: dict[str, Any] = {}
    everyone = threading.Event()
    with BusClient(url, name="u2sa-replay") as client:
        req = t.DiscoveryRequest()
        req.request_id = uuid.uuid4().hex

        def on_reply(_c: str, msg: Any) -> None:
            if msg.request_id == req.request_id:
                found[msg.name] = msg
                if all(n in found for n in wanted):
                    everyone.set()

        sub = client.transport.subscribe(ch.DISCOVERY_RESPONSE, t.DiscoveryResponse, on_reply)
        try:
            deadline = time.monotonic() + timeout
            while True:
                client.publish(ch.DISCOVERY_REQUEST, req)
                left = deadline - time.monotonic()
                if everyone.wait(max(0.0, min(resend, left))) or left <= resend:
                    break
        finally:
            client.transport.unsubscribe(sub)
    return dict(found)


def listeners(found: Mapping[str, Any], services: Container[str],
              from_device: Mapping[str, set[str]]) -> dict[str, set[str]]:
    """Republishable channel -> the replayed services that take it from the bus, from their discovery answers
    *found*; a service whose replay device hands it a channel (*from_device*: channel -> such services; the RC
    mux's replay chip hands it the recorded Health, FAILSAFE and STATE_ESTIMATE in order with the edges, and
    it ignores the bus on them) does not count for that channel."""
    taken: dict[str, set[str]] = {}
    for r in found.values():
        if r.name in services:
            for c in r.subscribes:
                taken.setdefault(c.channel, set()).add(r.name)
    # Health is contract traffic, but the RC mux's pre-arm checks judge the other services by it
    return {c: who - from_device.get(c, set()) for c, who in taken.items()
            if (c == HEALTH_CHANNEL or not c.startswith(CONTRACT_PREFIX)) and not c.startswith("RAW.")}
