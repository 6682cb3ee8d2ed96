"""What a transport does with a packet before any callback sees it (u2sa_hw.bus.transport, docs/security.md).

:class:`ReceiveGuard` verifies the signature and the signer's role (``u2sa_hw.bus.auth``),
drops a command signed before this process started (a restarted service must not obey a stop
captured before its restart), checks the header's system id, and counts and logs once per
channel and reason what it drops. A failsafe raise (a signed ``Failsafe`` with ``active = true``
on ``FAILSAFE``) fails safe, so it is accepted where anything else is dropped: outside the
replay window, from another non-zero system id, or signed before this process started; each
such acceptance is counted (``raise_stale``, ``raise_foreign``), logged once and remembered
with its sender and time (:meth:`ReceiveGuard.accepted_raise_log`, shown in health).
"""

from __future__ import annotations

import logging
import struct
import time
from dataclasses import dataclass
from typing import Any

from u2sa_hw.bus.auth import FOREIGN, LCM_SELF_TEST, OK, REJECTION_WHY, REJECTIONS, REPLAYED, TRAILER_LEN, BusAuth, strip_trailer
from u2sa_hw.bus.roles import COMMAND_CHANNELS
from u2sa_hw.channels import FAILSAFE as FAILSAFE_CHANNEL
from u2sa_hw.lcmtypes import Failsafe
from u2sa_hw.messages import REGISTRY, MalformedMessage

log = logging.getLogger("u2sa_hw.bus.transport")

_SYSTEM_ID = struct.Struct(">i")
_ANY_SYSTEM = _SYSTEM_ID.pack(0)   # unset (a tool without a profile): not another vehicle
_FAILSAFE_FP = Failsafe._get_packed_fingerprint()


@dataclass
class ChannelCounters:
    """Traffic counters of one channel in one direction."""

    messages: int = 0
    malformed: int = 0
    dropped: int = 0
    bytes: int = 0
    type_name: str = ""
    unsigned: int = 0    # received only: dropped by verification (bus_auth.REJECTIONS)
    forged: int = 0
    replayed: int = 0
    foreign: int = 0     # received only: another vehicle's system id in the header
    denied: int = 0      # received only: signed by a key whose role may not publish the channel
    raise_stale: int = 0     # received only: failsafe raises accepted though outside the replay window
    raise_foreign: int = 0   # received only: failsafe raises accepted though from another system id

    def rejected(self) -> int:
        """Packets verification (or the system id check) dropped on this channel."""
        return self.unsigned + self.forged + self.replayed + self.foreign + self.denied


@dataclass(frozen=True)
class AcceptedRaise:
    """Failsafe raises of one kind let through on one channel (``raise_stale``: outside the replay
    window; ``raise_foreign``: another system id), with the last one's sender (hex) and age."""

    channel: str
    kind: str
    count: int
    last_sender: str
    last_age_s: float


class ReceiveGuard:
    """Verifies, checks and counts each received packet of one transport, on its handler thread.

    *rx* is the transport's per-channel receive counters (shared: the transport counts messages,
    this counts drops). *auth* None: an open bus, nothing verified. Every u2sa message starts
    with its Header (extensions with their base, which does): the system id is the big-endian
    int32 right after the 8-byte fingerprint. A packet of an unknown fingerprint is not checked
    (it is malformed, or a raw subscriber's bytes).
    """

    def __init__(self, *, name: str, auth: BusAuth | None, system_id: int | None, rx: Any) -> None:
        self.name = name
        self.auth = auth
        self.rx = rx
        self._own_system = None if system_id is None else _SYSTEM_ID.pack(system_id)
        # The signing clock at start: a command signed before it is not obeyed.
        self.started_us = auth.now() if auth is not None else 0
        self.payload = b""
        self.packet = b""   # the whole verified packet being dispatched, trailer included
        self._rejection_logged: set[tuple[str, str]] = set()
        self._last_raises: dict[tuple[str, str], tuple[str, float]] = {}   # (channel, kind) -> (sender, monotonic)

    def verify(self, channel: str, data: bytes) -> str:
        """OK (the payload is in ``payload``, the whole packet in ``packet``) or why *data* is dropped,
        counted and logged once."""
        auth = self.auth
        if auth is None:
            payload = strip_trailer(data)
            verdict = OK
        else:
            verdict = auth.verify(channel, data)
            if verdict is REPLAYED and channel == FAILSAFE_CHANNEL:
                verdict = self._admit_stale_raise(auth, channel, data)
            payload = data[:auth.end]
            if verdict is OK and channel in COMMAND_CHANNELS and auth.last_counter < self.started_us:
                verdict = self._before_start(channel, payload)
        if verdict is OK:
            own = self._own_system
            # Only a u2sa type's bytes 8..12 are its system id: anything else is left to decoding (malformed).
            if own is None or payload[8:12] in (own, _ANY_SYSTEM) or REGISTRY.by_fingerprint(payload[:8]) is None:
                self.payload = payload
                self.packet = data
                self.rx[channel].bytes += len(payload)
                return OK
            if _is_failsafe_raise(channel, payload):
                self._accepted_raise(channel, "raise_foreign", "from another system id than this vehicle's")
                self.payload = payload
                self.packet = data
                self.rx[channel].bytes += len(payload)
                return OK
            verdict = FOREIGN
        counters = self.rx[channel]
        counters.bytes += len(data)
        if channel == LCM_SELF_TEST:   # LCM's own probe at start-up, never ours: not a rejection
            return verdict
        setattr(counters, verdict, getattr(counters, verdict) + 1)
        if (channel, verdict) not in self._rejection_logged:
            self._rejection_logged.add((channel, verdict))
            log.warning("%s: dropping %s message on %s (%s); further ones are only counted", self.name, verdict,
                        channel, REJECTION_WHY[verdict])
        return verdict

    def _before_start(self, channel: str, payload: bytes) -> str:
        """REPLAYED for a command signed before this transport started (a restarted service must not obey a
        stop captured before its restart); OK for a failsafe raise, which fails safe whenever it was signed."""
        if _is_failsafe_raise(channel, payload):
            return OK
        if (channel, "before start") not in self._rejection_logged:
            self._rejection_logged.add((channel, "before start"))
            log.warning("%s: dropping a command on %s signed before this service started (a replay, or a sender "
                        "whose clock is behind); further ones are only counted as replayed", self.name, channel)
        return REPLAYED

    def _admit_stale_raise(self, auth: BusAuth, channel: str, data: bytes) -> str:
        """OK for a failsafe raise refused only for its age (it fails safe), REPLAYED for anything else."""
        if not _is_failsafe_raise(channel, data[:-TRAILER_LEN]):
            return REPLAYED
        verdict = auth.admit_stale(data)
        if verdict is OK:
            self._accepted_raise(channel, "raise_stale", "outside the replay window (a sender whose clock is behind, "
                                 "or a replay)")
        return verdict

    def _accepted_raise(self, channel: str, counter: str, why: str) -> None:
        counters = self.rx[channel]
        setattr(counters, counter, getattr(counters, counter) + 1)
        sender = self.auth.last_sender.hex() if self.auth is not None else ""
        self._last_raises[(channel, counter)] = (sender, time.monotonic())
        if (channel, counter) not in self._rejection_logged:
            self._rejection_logged.add((channel, counter))
            log.warning("%s: accepting a failsafe raise on %s %s: a raise fails safe, so it is never dropped for "
                        "that; further ones are only counted", self.name, channel, why)

    def accepted_raises(self) -> dict[str, dict[str, int]]:
        """``{channel: {"raise_stale": n, "raise_foreign": n}}`` for channels where a raise was let through."""
        return {ch: {"raise_stale": c.raise_stale, "raise_foreign": c.raise_foreign}
                for ch, c in sorted(self.rx.items()) if c.raise_stale or c.raise_foreign}

    def accepted_raise_log(self) -> list[AcceptedRaise]:
        """Every kind of raise let through though stale or foreign: its count, its last sender and that one's age."""
        now = time.monotonic()
        out = []
        for (channel, kind), (sender, at) in sorted(self._last_raises.items()):
            out.append(AcceptedRaise(channel=channel, kind=kind, count=getattr(self.rx[channel], kind),
                                     last_sender=sender, last_age_s=now - at))
        return out

    def rejected(self) -> dict[str, dict[str, int]]:
        """``{channel: {"unsigned": n, "forged": n, "replayed": n, "foreign": n}}`` for channels with drops."""
        return {ch: {r: getattr(c, r) for r in REJECTIONS} for ch, c in sorted(self.rx.items()) if c.rejected()}


def _is_failsafe_raise(channel: str, payload: bytes) -> bool:
    """True for a Failsafe with ``active = true`` on FAILSAFE (only read on the rare paths that drop otherwise)."""
    if channel != FAILSAFE_CHANNEL or payload[:8] != _FAILSAFE_FP:
        return False
    try:
        msg, _ = REGISTRY.decode(payload, Failsafe)
    except MalformedMessage:
        return False
    return bool(msg.active)
