"""Signing and verifying bus messages: the trailer after the LCM payload (DESIGN.md 5b, docs/security.md).

Every signed packet is ``payload | trailer``; the trailer is 40 bytes::

    sender (8)   random per transport: a restarted process is a new sender
    counter (8)  big-endian µs of the sender's signing clock, strictly growing per sender
    key id (4)   names the key that signed (rotation keeps the old one for a short overlap)
    mac (16)     HMAC-SHA256(key, channel NUL payload sender counter key-id), first 16 bytes
    tag (4)      b"U2S1"

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
reboot (``u2sa_hw.bus_clock``; the transport calls :meth:`BusAuth.adopt`), so a board that
boots without a real-time clock does not accept a packet captured before it went down.

Failsafe raises: a packet refused as REPLAYED only for its counter's age or range (its MAC
checked, its counter above its sender's last) may still be accepted by the transport through
:meth:`BusAuth.admit_stale` when it is a signed ``Failsafe`` with ``active = true``: a replayed
raise can only make the vehicle safer, and an operator's laptop whose clock is behind must
never lose one. Everything else, a failsafe clear included, stays refused.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import os
import struct
import threading
import time
from pathlib import Path
from typing import Any, Callable

from u2sa_hw.bus_key import BusKeyError, key_id, read_key

log = logging.getLogger("u2sa_hw.bus_auth")

TAG = b"U2S1"
SENDER_BYTES = 8
MAC_BYTES = 16
KEY_ID_BYTES = 4
TRAILER_LEN = SENDER_BYTES + 8 + KEY_ID_BYTES + MAC_BYTES + len(TAG)
_TAIL = struct.Struct(">8sQ4s")                   # the signed part of the trailer: sender, counter, key id
_SENDER_COUNTER = struct.Struct(">8sQ")          # read once the MAC is checked
SIGNED_TAIL = _TAIL.size
MAX_CACHED_CHANNELS = 1024
MAX_STALE_RAISERS = 1024           # senders of admitted stale failsafe raises remembered (BusAuth.admit_stale)

WINDOW_US = 20_000_000             # a sender never heard before: its first counter at most 20 s old
OVERLAP_S = 30.0                   # a rotated-out key is still accepted this long
RELOAD_CHECK_S = 1.0               # how often the key file is looked at for a rotation
PRUNE_EVERY_US = 10_000_000
SANE_CLOCK_US = 1_704_067_200_000_000   # 2024-01-01: a wall clock before this has no RTC behind it
MAX_AHEAD_US = 366 * 86_400_000_000     # with a sane clock, a counter further ahead is out of range
MAX_COUNTER = 2 ** 53                   # about the year 2255: anything above is out of range

# Verification results (also the names of the drop counters).
OK, UNSIGNED, FORGED, REPLAYED = "ok", "unsigned", "forged", "replayed"
# A verified (or, on an open bus, any) message whose header names another vehicle's system id.
FOREIGN = "foreign"
REJECTIONS = (UNSIGNED, FORGED, REPLAYED, FOREIGN)

LCM_SELF_TEST = "LCM_SELF_TEST"
REJECTION_WHY = {
    "unsigned": "no valid signature trailer: a sender without the bus key, or one with bus_security = \"open\"",
    "forged": "signed with another key: another vehicle or simulation, or a forgery",
    "replayed": "its counter is not newer than the sender's last or is outside the window: a replay",
    "foreign": "its header names another vehicle's system id: another stack sharing this bus and key",
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


class BusKey:
    """One key with its HMAC inner and outer states precomputed (each message copies them).

    The inner state after a channel's name is kept per channel too, so a message costs one
    copy and one update less; OpenSSL 3's one-shot ``hmac.digest`` fetches its algorithm on
    every call and measured slower than these copies (bench/transport.py, docs/security.md).
    """

    def __init__(self, key: bytes) -> None:
        self.id = key_id(key)
        block = key.ljust(64, b"\0")   # a 32-byte key is shorter than SHA-256's block: HMAC pads it
        self._inner = hashlib.sha256(bytes(b ^ 0x36 for b in block))
        self._outer = hashlib.sha256(bytes(b ^ 0x5C for b in block))
        self._by_channel: dict[str, Any] = {}

    def inner_after(self, channel: str) -> Any:
        """The inner hash state having absorbed *channel* NUL (do not update it: copy it)."""
        state = self._by_channel.get(channel)
        if state is None:
            state = self._inner.copy()
            state.update(channel.encode() + b"\0")
            if len(self._by_channel) < MAX_CACHED_CHANNELS:   # a flood of invented names cannot grow it
                self._by_channel[channel] = state
        return state

    def mac(self, channel: bytes, signed: bytes | memoryview) -> bytes:
        """The truncated HMAC-SHA256 of *channel* (NUL-terminated) and *signed*."""
        inner = self._inner.copy()
        inner.update(channel)
        inner.update(signed)
        outer = self._outer.copy()
        outer.update(inner.digest())
        return outer.digest()[:MAC_BYTES]


class Keyring:
    """The current key from a file, and the keys it replaced while their overlap lasts.

    :meth:`poll` (cheap; called on every publish and by the handler thread) re-reads the file
    at most every :data:`RELOAD_CHECK_S` and picks up a rotation without a restart.
    """

    def __init__(self, path: Path, *, overlap_s: float = OVERLAP_S, clock: Callable[[], float] = time.monotonic) -> None:
        self.path = Path(path)
        self.current = BusKey(read_key(self.path))
        self._overlap_s = overlap_s
        self._clock = clock
        self._previous: list[tuple[BusKey, float]] = []
        self._stamp = _file_stamp(self.path)
        self._next_check = clock() + RELOAD_CHECK_S
        self._lock = threading.Lock()
        self._reload_error_logged = False

    def lookup(self, kid: bytes) -> BusKey | None:
        """The key with id *kid*: the current one or one still in its overlap; None otherwise."""
        current = self.current
        if kid == current.id:
            return current
        for key, until in self._previous:
            if key.id == kid and self._clock() < until:
                return key
        return None

    def poll(self) -> None:
        """Reload the key file if it changed (rate-limited)."""
        now = self._clock()
        if now < self._next_check:
            return
        with self._lock:
            if now < self._next_check:
                return
            self._next_check = now + RELOAD_CHECK_S
            self._reload(now)

    def _reload(self, now: float) -> None:
        stamp = _file_stamp(self.path)
        if stamp == self._stamp:
            return
        try:
            key = BusKey(read_key(self.path))
        except BusKeyError as exc:
            if not self._reload_error_logged:
                self._reload_error_logged = True
                log.error("%s; still signing with the key loaded before (id %s)", exc, self.current.id.hex())
            return
        self._stamp, self._reload_error_logged = stamp, False
        if key.id == self.current.id:
            return
        self._previous = [(k, u) for k, u in self._previous if u > now] + [(self.current, now + self._overlap_s)]
        self.current = key
        log.info("bus key %s changed: now signing with key %s; the previous key is accepted for %g s",
                 self.path, key.id.hex(), self._overlap_s)


_KEYRINGS: dict[Path, Keyring] = {}
_KEYRINGS_LOCK = threading.Lock()


def keyring_for(path: Path) -> Keyring:
    """The process's one keyring for the key file *path* (BusKeyError when it cannot be read)."""
    with _KEYRINGS_LOCK:
        ring = _KEYRINGS.get(path)
        if ring is None:
            ring = _KEYRINGS[path] = Keyring(path)
        return ring


def _file_stamp(path: Path) -> tuple[int, int, int] | None:
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_ino, st.st_mtime_ns, st.st_size


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
        """Move the signing clock forward to *at_least_us* (a saved time, ``u2sa_hw.bus_clock``); True if it moved.

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
        """*payload* with its trailer."""
        ring = self.keyring
        if ring._clock() >= ring._next_check:
            ring.poll()
        key = ring.current
        counter = self._wall_ns() // 1000 + self._offset
        if counter <= self._last_sent:
            counter = self._last_sent + 1
        self._last_sent = counter
        tail = _TAIL.pack(self.sender, counter, key.id)
        inner = (key._by_channel.get(channel) or key.inner_after(channel)).copy()
        inner.update(payload)
        inner.update(tail)
        outer = key._outer.copy()
        outer.update(inner.digest())
        return b"".join((payload, tail, outer.digest()[:MAC_BYTES], TAG))

    def verify(self, channel: str, data: bytes) -> str:
        """OK, or why *data* is dropped: UNSIGNED, FORGED or REPLAYED. Never raises.

        The MAC is checked (in constant time) before anything of the trailer is believed.
        A packet REPLAYED only for its counter's age or range can be admitted with :meth:`admit_stale`.
        """
        end = len(data) - TRAILER_LEN
        if end < 0 or not data.endswith(TAG):
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
        self.last_sender = sender
        return OK

    def _prune(self, now: int) -> None:
        # A sender whose last counter left the window can be forgotten: anything it sent
        # before is then older than the window too, and refused as a new sender's would be.
        self._prune_at = now + PRUNE_EVERY_US
        horizon = now - WINDOW_US
        for sender in [s for s, c in self._peers.items() if c < horizon]:
            del self._peers[sender]


def strip_trailer(data: bytes) -> bytes:
    """*data* without a trailer if it has one (open mode: nothing is verified)."""
    if len(data) >= TRAILER_LEN and data[-4:] == TAG:
        return data[:-TRAILER_LEN]
    return data


def payload_of(data: bytes) -> bytes:
    """The payload of a verified packet."""
    return data[:-TRAILER_LEN]
