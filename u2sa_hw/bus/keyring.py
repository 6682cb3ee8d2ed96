"""The keys a process signs and checks bus messages with, and the role each key speaks for (docs/security.md).

A :class:`Keyring` is built from the bus key file and finds the rest beside it:

    bus.key           the vehicle's HMAC key: role *vehicle* (the services)
    operators/*.key   operator keys (``u2sa key operator NAME``): role *operator*, HMAC too
    pilot.pub         the pilot's Ed25519 public key: checks RC_MODE and MANUAL_CMD (u2sa_hw.bus.pilot)
    pilot.key         the pilot's private key: only the RC mux reads it, and only when it publishes

A process signs with the bus key, or with an operator key when ``$U2SA_OPERATOR_KEY_FILE``
names one (a ground-station tool), and the pilot's channels with the pilot key.
"""

from __future__ import annotations

import hashlib
import logging
import os
import threading
import time
from pathlib import Path
from typing import Any, Callable

from u2sa_hw.bus.key import BusKeyError, key_id, read_key
from u2sa_hw.bus.roles import OPERATOR, VEHICLE

log = logging.getLogger("u2sa_hw.bus.auth")

OPERATOR_KEY_ENV = "U2SA_OPERATOR_KEY_FILE"
OPERATORS_DIR = "operators"
MAX_CACHED_CHANNELS = 1024
OVERLAP_S = 30.0                   # a rotated-out key is still accepted this long
RELOAD_CHECK_S = 1.0               # how often the key files are looked at for a rotation
MAX_OPERATOR_KEYS = 256
MAC_BYTES = 16                     # the MAC is truncated to this (u2sa_hw.bus.auth)


class BusKey:
    """One key with its HMAC inner and outer states precomputed (each message copies them).

    The inner state after a channel's name is kept per channel too, so a message costs one
    copy and one update less; OpenSSL 3's one-shot ``hmac.digest`` fetches its algorithm on
    every call and measured slower than these copies (bench/transport.py, docs/security.md).
    """

    def __init__(self, key: bytes, *, role: str = VEHICLE) -> None:
        self.id = key_id(key)
        self.role = role
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
    """The keys of one bus key file: the current bus key and those it replaced while their overlap
    lasts, the operator keys beside it, the pilot's keys, and the key this process signs with.

    :meth:`poll` (cheap; called on every publish and by the handler thread) re-reads the files
    at most every :data:`RELOAD_CHECK_S` and picks up a rotation or a new operator key without
    a restart. *operator_file* (default ``$U2SA_OPERATOR_KEY_FILE``): sign as that operator.
    """

    def __init__(self, path: Path, *, overlap_s: float = OVERLAP_S, clock: Callable[[], float] = time.monotonic,
                 operator_file: Path | str | None = None) -> None:
        self.path = Path(path)
        self.current = BusKey(read_key(self.path))
        self._overlap_s = overlap_s
        self._clock = clock
        self._previous: list[tuple[BusKey, float]] = []
        self._stamp = _file_stamp(self.path)
        self._next_check = clock() + RELOAD_CHECK_S
        self._lock = threading.Lock()
        self._reload_error_logged = False
        self._operators_dir = self.path.parent / OPERATORS_DIR
        self._operators_stamp: Any = None
        self.operators: dict[bytes, BusKey] = {}
        self._load_operators()
        operator_file = operator_file if operator_file is not None else os.environ.get(OPERATOR_KEY_ENV)
        # The key this process signs its non-pilot messages with: the bus key, or an operator's.
        self.operator = BusKey(read_key(Path(operator_file)), role=OPERATOR) if operator_file else None
        self._pilot_signer: Any = None
        self._pilot_verifier: Any = None
        self.pilot_problem = ""   # why pilot messages cannot be signed or checked here, once found

    @property
    def signing(self) -> BusKey:
        """The key this process signs with (pilot channels aside)."""
        return self.operator or self.current

    def lookup(self, kid: bytes) -> BusKey | None:
        """The key with id *kid*: the bus key, one still in its overlap, or an operator key; None otherwise."""
        current = self.current
        if kid == current.id:
            return current
        for key, until in self._previous:
            if key.id == kid and self._clock() < until:
                return key
        key = self.operators.get(kid)
        if key is None and self.operator is not None and kid == self.operator.id:
            return self.operator   # a tool hears its own commands (and the vehicle, which has it, does too)
        return key

    def pilot_verifier(self) -> Any:
        """The pilot's public key (u2sa_hw.bus.pilot.PilotVerifier), or None when it cannot be read (logged once)."""
        if self._pilot_verifier is None and not self.pilot_problem:
            from u2sa_hw.bus.pilot import pilot_paths, read_verifier
            try:
                self._pilot_verifier = read_verifier(pilot_paths(self.path)[1])
            except BusKeyError as exc:
                self.pilot_problem = str(exc)
                log.error("%s; RC_MODE and MANUAL_CMD are dropped as forged until then", exc)
        return self._pilot_verifier

    def pilot_signer(self) -> Any:
        """The pilot's private key (u2sa_hw.bus.pilot.PilotSigner); BusKeyError when this process may not read it."""
        if self._pilot_signer is None:
            from u2sa_hw.bus.pilot import pilot_paths, read_signer
            self._pilot_signer = read_signer(pilot_paths(self.path)[0])
        return self._pilot_signer

    def poll(self) -> None:
        """Reload the key files if they changed (rate-limited)."""
        now = self._clock()
        if now < self._next_check:
            return
        with self._lock:
            if now < self._next_check:
                return
            self._next_check = now + RELOAD_CHECK_S
            self._reload(now)
            self._load_operators()

    def _load_operators(self) -> None:
        stamp = _file_stamp(self._operators_dir)
        if stamp == self._operators_stamp:
            return
        self._operators_stamp = stamp
        keys: dict[bytes, BusKey] = {}
        try:
            files = sorted(self._operators_dir.glob("*.key"))[:MAX_OPERATOR_KEYS]
        except OSError:
            files = []
        for file in files:
            try:
                key = BusKey(read_key(file), role=OPERATOR)
            except BusKeyError as exc:
                log.error("operator key skipped: %s", exc)
                continue
            keys[key.id] = key
        self.operators = keys

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


_KEYRINGS: dict[tuple[Path, bool], Keyring] = {}
_KEYRINGS_LOCK = threading.Lock()


def keyring_for(path: Path, *, vehicle: bool = False) -> Keyring:
    """The process's one keyring for the key file *path* (BusKeyError when it cannot be read).

    *vehicle*: a service's, which always signs with the bus key, whatever ``$U2SA_OPERATOR_KEY_FILE``
    says (a stack started from a ground station's shell must not sign its health as an operator).
    """
    with _KEYRINGS_LOCK:
        ring = _KEYRINGS.get((path, vehicle))
        if ring is None:
            ring = _KEYRINGS[(path, vehicle)] = Keyring(path, operator_file="" if vehicle else None)
        return ring


def _file_stamp(path: Path) -> tuple[int, int, int] | None:
    """(inode, mtime, size) of *path*, None when it is absent: a change means a reload."""
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_ino, st.st_mtime_ns, st.st_size


