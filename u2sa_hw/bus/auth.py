"""Signing and verifying bus messages: the trailer after the LCM payload (DESIGN.md 5b, docs/security.md).

Every signed packet is ``payload | trailer``; the trailer is 40 bytes::

    sender (8)   random per transport: a restarted process is a new sender
    counter (8)  big-endian µs of the sender's signing clock, strictly growing per sender
    key id (4)   names the key that signed (rotation keeps the old one for a short overlap)
    mac (16)     HMAC-SHA256(key, channel NUL payload sender counter key-id), first 16 bytes
    tag (4)      b"U2S1"

The key id names the signer's role too (u2sa_hw.bus.keyring, u2sa_hw.bus.roles): the bus
key speaks for the vehicle, an operator key for a ground station. The pilot's channels,
RC_MODE and MANUAL_CMD, carry another trailer, 88 bytes: sender, counter and key id as above,
then an Ed25519 signature (64) of channel NUL payload sender counter key-id, then b"U2P1".
Only the RC mux holds the pilot's private key (u2sa_hw.bus.pilot); every receiver checks it
with the public key, so no holder of the bus key can speak for the pilot. A packet whose
signer's role may not publish its channel is DENIED.

LCM decoders read the payload and ignore what follows, so LCM's own tools still decode.

Replays: a receiver keeps the last counter of every sender it heard. A packet from a known
sender must carry a larger counter; the first packet of a sender it never heard must be no
older than :data:`WINDOW_US` on the receiver's signing clock. The signing clock is the wall
clock, moved forward to the largest counter of any verified packet (MAVLink 2's rule), so a
board that booted without an RTC adopts the vehicle's time from the first packet it verifies.
A restarted service is a new sender with a current counter: accepted at once. A packet
captured and replayed a minute later is either not above its sender's last counter or,
for a receiver that never heard that sender, outside the window.

Restarts: a receiver's window never starts below the signing time the board saved before a
reboot (``u2sa_hw.bus.clock``; the transport calls :meth:`BusAuth.adopt`), so a board that
boots without a real-time clock does not accept a packet captured before it went down.

Failsafe raises: a packet refused as REPLAYED only for its counter's age or range (its MAC
checked, its counter above its sender's last) may still be accepted by the transport through
:meth:`BusAuth.admit_stale` when it is a signed ``Failsafe`` with ``active = true``: a replayed
raise can only make the vehicle safer, and an operator's laptop whose clock is behind must
never lose one. Everything else, a failsafe clear included, stays refused.
"""

from __future__ import annotations

import hmac
import logging
import os
import struct
import time
from typing import Any, Callable

from u2sa_hw.bus.key import BusKeyError
from u2sa_hw.bus.keyring import BusKey, Keyring, keyring_for
from u2sa_hw.bus.roles import PILOT_CHANNELS, VEHICLE, may_publish

__all__ = ["BusAuth", "BusKey", "Keyring", "check_pilot_packet", "keyring_for", "resolve_security", "strip_trailer"]

log = logging.getLogger("u2sa_hw.bus.auth")

TAG = b"U2S1"
SENDER_BYTES = 8
MAC_BYTES = 16
KEY_ID_BYTES = 4
TRAILER_LEN = SENDER_BYTES + 8 + KEY_ID_BYTES + MAC_BYTES + len(TAG)
_TAIL = struct.Struct(">8sQ4s")                   # the signed part of the trailer: sender, counter, key id
_SENDER_COUNTER = struct.Struct(">8sQ")          # read once the MAC is checked
SIGNED_TAIL = _TAIL.size
# The pilot's trailer (RC_MODE, MANUAL_CMD): sender, counter, key id as above, then an Ed25519
# signature of channel NUL payload sender counter key-id, then its own tag.
PILOT_TAG = b"U2P1"
SIGNATURE_BYTES = 64
PILOT_TRAILER_LEN = SIGNED_TAIL + SIGNATURE_BYTES + len(PILOT_TAG)
MAX_STALE_RAISERS = 1024           # senders of admitted stale failsafe raises remembered (BusAuth.admit_stale)

WINDOW_US = 20_000_000             # a sender never heard before: its first counter at most 20 s old
PRUNE_EVERY_US = 10_000_000
SANE_CLOCK_US = 1_704_067_200_000_000   # 2024-01-01: a wall clock before this has no RTC behind it
MAX_AHEAD_US = 366 * 86_400_000_000     # with a sane clock, a counter further ahead is out of range
MAX_COUNTER = 2 ** 53                   # about the year 2255: anything above is out of range

# Verification results (also the names of the drop counters).
OK, UNSIGNED, FORGED, REPLAYED = "ok", "unsigned", "forged", "replayed"
# A verified (or, on an open bus, any) message whose header names another vehicle's system id.
FOREIGN = "foreign"
# Signed by a key whose role may not publish the channel (u2sa_hw.bus.roles).
DENIED = "denied"
REJECTIONS = (UNSIGNED, FORGED, REPLAYED, FOREIGN, DENIED)

LCM_SELF_TEST = "LCM_SELF_TEST"
REJECTION_WHY = {
    "unsigned": "no valid signature trailer: a sender without the bus key, or one with bus_security = \"open\"",
    "forged": "signed with another key: another vehicle or simulation, or a forgery",
    "replayed": "its counter is not newer than the sender's last or is outside the window: a replay",
    "foreign": "its header names another vehicle's system id: another stack sharing this bus and key",
    "denied": "signed by a key whose role may not publish this channel (docs/security.md): the bus key or an "
              "operator key on the pilot's RC_MODE or MANUAL_CMD, or an operator key on a vehicle channel",
}

SECURITY_ENV = "U2SA_BUS_SECURITY"
SIGNED, OPEN = "signed", "open"
SECURITY_MODES = (SIGNED, OPEN)


def resolve_security(profile_value: str | None = None) -> str:
    """``signed`` or ``open``: the profile's ``bus_security``, else ``$U2SA_BUS_SECURITY``, else signed."""
    value = profile_value or os.environ.get(SECURITY_ENV) or SIGNED
    if value not in SECURITY_MODES:
        raise BusKeyError(f"bus_security must be \"signed\" or \"open\", not {value!r} (the vehicle profile's "
                          f"[vehicle] bus_security or ${SECURITY_ENV})")
    return value


class BusAuth:
    """Signs what one transport publishes and verifies what it receives.

    :meth:`sign` runs under the transport's publish lock, :meth:`verify` on its one handler
    thread; the signing clock's offset is the only state both touch (an int, replaced whole).
    """

    def __init__(self, keyring: Keyring, *, sender: bytes | None = None,
                 wall_us: Callable[[], int] | None = None) -> None:
        self.keyring = keyring
        self.sender = sender or os.urandom(SENDER_BYTES)
        self.last_sender = b""          # the verified sender of the packet being dispatched
        self.last_counter = 0           # ... its signing time (µs)
        self.end = 0                    # ... where its payload ends
        # The wall clock in ns: time.time_ns itself unless a test gives its own (in µs).
        self._wall_ns: Callable[[], int] = time.time_ns if wall_us is None else (lambda: wall_us() * 1000)
        self._offset = 0
        self._last_sent = 0
        self._peers: dict[bytes, int] = {}
        self._prune_at = 0
        self._stale: tuple[bytes, int] | None = None   # sender and counter of the last packet refused as too old
        # The last counter of each sender whose raise was admitted though stale: kept apart from
        # _peers, so that admitting a raise never makes its sender's other packets acceptable.
        self._stale_raises: dict[bytes, int] = {}

    def now(self) -> int:
        """The signing clock in µs: the wall clock, moved forward to the newest verified counter."""
        return self._wall_ns() // 1000 + self._offset

    def high_water(self) -> int:
        """The highest signing time this sender reached: its clock, or its last counter if that is larger."""
        return max(self.now(), self._last_sent)

    def adopt(self, at_least_us: int) -> bool:
        """Move the signing clock forward to *at_least_us* (a saved time, ``u2sa_hw.bus.clock``); True if it moved.

        Refused (False) like a counter out of range: above :data:`MAX_COUNTER`, or more than
        :data:`MAX_AHEAD_US` ahead of a wall clock that is set. Never moves the clock back.
        """
        now = self.now()
        if at_least_us <= now:
            return False
        if at_least_us > MAX_COUNTER or (at_least_us > now + MAX_AHEAD_US and now >= SANE_CLOCK_US):
            log.warning("ignoring a saved bus clock of %d µs: out of range for this clock (%d µs)", at_least_us, now)
            return False
        self._offset += at_least_us - now
        return True

    def sign(self, channel: str, payload: bytes) -> bytes:
        """*payload* with its trailer: the pilot's on RC_MODE and MANUAL_CMD, the HMAC one otherwise.

        BusKeyError when this process may not sign *channel* (the pilot's channels without the
        pilot's private key: every process but the RC mux).
        """
        ring = self.keyring
        if ring._clock() >= ring._next_check:
            ring.poll()
        counter = self._wall_ns() // 1000 + self._offset
        if counter <= self._last_sent:
            counter = self._last_sent + 1
        if channel in PILOT_CHANNELS:
            return self._sign_pilot(channel, payload, counter)
        self._last_sent = counter
        key = ring.operator or ring.current
        tail = _TAIL.pack(self.sender, counter, key.id)
        inner = (key._by_channel.get(channel) or key.inner_after(channel)).copy()
        inner.update(payload)
        inner.update(tail)
        outer = key._outer.copy()
        outer.update(inner.digest())
        return b"".join((payload, tail, outer.digest()[:MAC_BYTES], TAG))

    def _sign_pilot(self, channel: str, payload: bytes, counter: int) -> bytes:
        signer = self.keyring.pilot_signer()
        self._last_sent = counter
        tail = _TAIL.pack(self.sender, counter, signer.id)
        signature = signer.sign(b"".join((channel.encode(), b"\0", payload, tail)))
        return b"".join((payload, tail, signature, PILOT_TAG))

    def verify(self, channel: str, data: bytes) -> str:
        """OK, or why *data* is dropped: UNSIGNED, FORGED, DENIED or REPLAYED. Never raises.

        The MAC (or the pilot's signature) is checked, the MAC in constant time, before anything
        of the trailer is believed; then the signer's role (u2sa_hw.bus.roles), then the counter.
        On OK, ``end`` is where the payload ends and ``last_counter`` its signing time.
        A packet REPLAYED only for its counter's age or range can be admitted with :meth:`admit_stale`.
        """
        end = len(data) - TRAILER_LEN
        if end < 0 or not data.endswith(TAG):
            if data.endswith(PILOT_TAG):
                return self._verify_pilot(channel, data)
            return UNSIGNED
        key = self.keyring.current
        mac_at = end + SIGNED_TAIL
        if data[mac_at - KEY_ID_BYTES:mac_at] != key.id:
            key = self.keyring.lookup(data[mac_at - KEY_ID_BYTES:mac_at])
            if key is None:
                return FORGED
        inner = (key._by_channel.get(channel) or key.inner_after(channel)).copy()
        inner.update(memoryview(data)[:mac_at])
        outer = key._outer.copy()
        outer.update(inner.digest())
        if not hmac.compare_digest(outer.digest()[:MAC_BYTES], data[mac_at:mac_at + MAC_BYTES]):
            return FORGED
        if (key.role is not VEHICLE or channel in PILOT_CHANNELS) and not may_publish(key.role, channel):
            return DENIED
        return self._fresh(data, end)

    def _verify_pilot(self, channel: str, data: bytes) -> str:
        verdict = check_pilot_packet(channel, data, self.keyring.pilot_verifier())
        if verdict is not OK:
            return verdict
        if channel not in PILOT_CHANNELS:
            return DENIED
        return self._fresh(data, len(data) - PILOT_TRAILER_LEN)

    def _fresh(self, data: bytes, end: int) -> str:
        """The counter rules, on a packet whose signature and role are checked; OK sets ``end``."""
        sender, counter = _SENDER_COUNTER.unpack_from(data, end)
        now = self._wall_ns() // 1000 + self._offset
        if counter > MAX_COUNTER or (counter > now + MAX_AHEAD_US and now >= SANE_CLOCK_US):
            return self._outside(sender, counter)
        last = self._peers.get(sender)
        if last is None:
            if counter < now - WINDOW_US:
                return self._outside(sender, counter)
            if now >= self._prune_at:
                self._prune(now)
        elif counter <= last:
            return REPLAYED
        self._peers[sender] = counter
        self.last_sender = sender
        self.last_counter = counter
        self.end = end
        if counter > now:
            self._offset += counter - now
        return OK

    def _outside(self, sender: bytes, counter: int) -> str:
        # Not above the sender's last counter (in the window, or of an admitted raise): a replay whatever it carries.
        if counter <= max(self._peers.get(sender, -1), self._stale_raises.get(sender, -1)):
            return REPLAYED
        self._stale = (sender, counter)
        return REPLAYED

    def admit_stale(self, data: bytes) -> str:
        """OK: accept *data*, just refused as REPLAYED, if only its counter's age or range refused it; else REPLAYED.

        The caller (the transport) has found it a failsafe raise.

        Its counter becomes the last of its sender's admitted raises, so the same packet sent
        again is REPLAYED while that is remembered (up to :data:`MAX_STALE_RAISERS` senders; a
        raise replayed after that only holds a failsafe again). The sender does not become
        known: its other packets still meet the window. The signing clock is never moved by it.
        """
        stale, self._stale = self._stale, None
        if len(data) < TRAILER_LEN or stale != _SENDER_COUNTER.unpack_from(data, len(data) - TRAILER_LEN):
            return REPLAYED
        sender, counter = stale
        if len(self._stale_raises) >= MAX_STALE_RAISERS and sender not in self._stale_raises:
            self._stale_raises.clear()
        self._stale_raises[sender] = counter
        self.last_sender, self.last_counter, self.end = sender, counter, len(data) - TRAILER_LEN
        return OK

    def _prune(self, now: int) -> None:
        # A sender whose last counter left the window can be forgotten: anything it sent
        # before is then older than the window too, and refused as a new sender's would be.
        self._prune_at = now + PRUNE_EVERY_US
        horizon = now - WINDOW_US
        for sender in [s for s, c in self._peers.items() if c < horizon]:
            del self._peers[sender]


def check_pilot_packet(channel: str, data: bytes, verifier: Any) -> str:
    """OK when *data* ends in a pilot trailer signed by *verifier*'s key for *channel*; UNSIGNED or FORGED.

    Only the signature: no counter, no role. A replay checks recorded pilot messages so, with
    the public key the recording names (u2sa_hw.bus.pilot.PilotVerifier; None: FORGED).
    """
    end = len(data) - PILOT_TRAILER_LEN
    if end < 0 or not data.endswith(PILOT_TAG):
        return UNSIGNED
    sig_at = end + SIGNED_TAIL
    if verifier is None or data[sig_at - KEY_ID_BYTES:sig_at] != verifier.id:
        return FORGED
    signed = b"".join((channel.encode(), b"\0", memoryview(data)[:sig_at]))
    if not verifier.check(data[sig_at:sig_at + SIGNATURE_BYTES], signed):
        return FORGED
    return OK


def strip_trailer(data: bytes) -> bytes:
    """*data* without a trailer if it has one (open mode: nothing is verified)."""
    if len(data) >= TRAILER_LEN and data[-4:] == TAG:
        return data[:-TRAILER_LEN]
    if len(data) >= PILOT_TRAILER_LEN and data[-4:] == PILOT_TAG:
        return data[:-PILOT_TRAILER_LEN]
    return data

