"""LCM transport: one LCM instance per process, one thread handling, publishing from any thread.

LCM's Python binding allows one thread in ``handle``; publishing from several Python
threads at once is known to corrupt data, so every publish takes a lock. Subscriptions
are typed: a callback gets a decoded message of the channel's base type or of a known
extension of it. Malformed packets (wrong type, truncated, garbage) are counted per
channel and logged once per channel; they never reach or break the service. Counters
count packets: a packet that several subscriptions receive counts once.

Every packet is signed with the vehicle's bus key and verified on receipt (``u2sa_hw.bus.auth``,
docs/security.md): unsigned, forged and replayed packets are counted per channel, logged
once per channel and reason, and never reach a callback. Raw subscribers get the verified
payload without its trailer. ``security="open"`` (a bench) signs and verifies nothing.

What happens to a packet before a callback sees it (verification, the signer's role, a command
signed before this process started, the system id, a failsafe raise that fails safe) is
``u2sa_hw.bus.guard``.

The LCM C library reports a failure to open (no multicast route, a bad URL, a port held by
another program) with many lines on stderr; those are caught and folded into the one-line
``TransportError`` (``u2sa_hw.bus.lcm_open``). The sockets under the LCM instance (the bus's
interface, the receive socket bound early, the kernel's channel filter) are ``u2sa_hw.bus.lcm_sockets``;
``u2sa_hw.bus.multicast_check`` checks that multicast works at all.
"""

from __future__ import annotations

import functools
import logging
import re
import threading
import time
from collections import defaultdict, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from u2sa_hw.bus.auth import OK, OPEN, WINDOW_US, BusAuth, keyring_for, resolve_security
from u2sa_hw.bus.guard import AcceptedRaise, ChannelCounters, ReceiveGuard
from u2sa_hw.bus.clock import ClockStore, store_from_env
from u2sa_hw.bus.key import BusKeyError, key_path
from u2sa_hw.bus.lcm_open import TransportError
from u2sa_hw.bus.lcm_sockets import LcmSockets, is_regex
from u2sa_hw.bus.lcm_url import resolve_url
from u2sa_hw.bus.threads import name_native_thread
from u2sa_hw.messages import REGISTRY, MalformedMessage

# LCM queues at most 30 messages per subscription by default and drops the rest without a
# word; a burst (a log replay, a recorder catching up, 50 Hz from several sensors while the
# handler thread is busy) needs more.
DEFAULT_QUEUE_CAPACITY = 10_000

Callback = Callable[[str, Any], None]
log = logging.getLogger("u2sa_hw.bus.transport")


@dataclass
class _Subscription:
    channel: str
    base: type | None
    callback: Callback
    raw: bool
    handle: Any = None
    unknown_logged: set[bytes] = field(default_factory=set)
    active: bool = True


class Transport:
    """One LCM instance with a handler thread, a publish lock, signing and per-channel counters.

    *security* is ``signed`` or ``open`` (None: ``$U2SA_BUS_SECURITY``, else signed); the key
    comes from ``$U2SA_BUS_KEY_FILE``, else *key_file* (the profile's ``bus_key``), else
    /etc/u2sa/bus.key. A key that cannot be used is a one-line :class:`TransportError`.
    With *system_id* (the vehicle's), a message whose header carries another non-zero system
    id is dropped and counted as ``foreign``: a second stack sharing the bus and the key.
    A failsafe raise is the exception to both the replay window and the system id check
    (module docstring). A tool signs with the operator key ``$U2SA_OPERATOR_KEY_FILE`` names,
    if any; a service's transport (*vehicle*) always with the bus key.

    ``listen_problem`` is "" when the bus stays where the URL and *interface* say (ttl=0: ``lo``),
    else one line saying where it listens instead and the fix (``u2sa_hw.bus.listen``).
    With ``$STATE_DIRECTORY`` (*clock_store*), the signing clock starts no lower than the
    board's saved one and is saved every minute and at stop (``u2sa_hw.bus.clock``).
    """

    def __init__(self, url: str | None = None, *, name: str = "u2sa", security: str | None = None,
                 key_file: Path | str | None = None, interface: str | None = None,
                 system_id: int | None = None, clock_store: ClockStore | None = None, vehicle: bool = False) -> None:
        self.url = resolve_url(url)
        self.name = name
        try:
            self.security = resolve_security(security)
            self.auth = BusAuth(keyring_for(key_path(key_file), vehicle=vehicle)) if self.security != OPEN else None
        except BusKeyError as exc:
            raise TransportError(str(exc)) from None
        self._clock_store = (clock_store or store_from_env()) if self.auth is not None else None
        self._clock_saving: threading.Thread | None = None
        if self._clock_store is not None:
            start = self._clock_store.start_at(WINDOW_US)
            if start is not None and self.auth.adopt(start):
                log.info("%s: signing clock starts at the saved %d µs (%s)", name, start, self._clock_store.path)
        self._verdict = OK
        self.system_id = system_id
        self._pending_unsubscribe: deque[Any] = deque()
        self._sign_logged: set[str] = set()
        # ttl=0: loopback only; ttl>=1: the profile's bus_interface, if any (u2sa_hw.bus.listen).
        self._sockets = LcmSockets(self.url, interface)
        self._lc = self._sockets.open()
        self.interface, self.listen_problem = self._sockets.interface, self._sockets.listen_problem
        self._publish_lock = threading.Lock()
        self._subs: list[_Subscription] = []
        self._subs_lock = threading.Lock()
        self.rx: dict[str, ChannelCounters] = defaultdict(ChannelCounters)
        self._guard = ReceiveGuard(name=name, auth=self.auth, system_id=system_id, rx=self.rx)
        self.started_us = self._guard.started_us   # the signing clock at start: older commands are not obeyed
        self.tx: dict[str, ChannelCounters] = defaultdict(ChannelCounters)
        self._malformed_logged: set[str] = set()
        # One handle() call dispatches one packet to every matching subscription: the
        # generation below tells a packet's first dispatch (which counts it) from the others.
        self._generation = 0
        self._bytes_counted = self._messages_counted = self._malformed_counted = -1
        self.last_error = ""
        self._thread: threading.Thread | None = None
        self._running = False

    # -- publishing ---------------------------------------------------------------
    def publish(self, channel: str, msg: Any) -> bool:
        """Encode and publish *msg* on *channel*; True on success (thesis ``publish``)."""
        try:
            data = msg.encode()
        except Exception as exc:  # noqa: BLE001 - a bad field value is the caller's error, reported
            self._error(f"cannot encode {type(msg).__name__} for {channel}: {exc}")
            self.tx[channel].dropped += 1
            return False
        return self.publish_bytes(channel, data, type_name=type(msg).__name__)

    def publish_bytes(self, channel: str, data: bytes, *, type_name: str = "") -> bool:
        """Publish already-encoded bytes (signed unless the bus is open); True on success."""
        with self._publish_lock:
            c = self.tx[channel]
            try:
                wire = self.auth.sign(channel, data) if self.auth is not None else data
            except BusKeyError as exc:   # the pilot's channels, from a process without the pilot's key
                c.dropped += 1
                if channel not in self._sign_logged:
                    self._sign_logged.add(channel)
                    self._error(f"cannot sign {channel}: {exc}")
                self.last_error = f"cannot sign {channel}: {exc}"
                return False
            try:
                if self._lc is None:
                    raise OSError("the transport is stopped")
                self._lc.publish(channel, wire)
            except (OSError, IOError) as exc:
                c.dropped += 1
                failure = exc
            else:
                c.messages += 1
                c.bytes += len(data)
                if type_name:
                    c.type_name = type_name
                return True
        self._error(f"publish on {channel} failed: {failure}")
        return False

    # -- subscribing --------------------------------------------------------------
    def subscribe(self, channel: str, base: type | None, callback: Callback, *, raw: bool = False,
                  queue_capacity: int = DEFAULT_QUEUE_CAPACITY) -> _Subscription:
        """Deliver messages on *channel* (an exact name, or a regex) to ``callback(channel, msg)``.

        *base* is the channel's base type: known extensions decode to their own type, unknown
        ones as *base*. With ``raw=True`` the callback gets the bytes undecoded. Callbacks run
        on the handler thread; an exception in one is logged and counted, never raised.
        *queue_capacity* is how many messages LCM holds for this subscription before dropping.
        """
        sub = _Subscription(channel, base, callback, raw)
        pattern = channel if is_regex(channel) else re.escape(channel)
        handler = functools.partial(self._dispatch, sub)   # no Python frame of its own per packet
        if self._lc is None:
            raise TransportError(f"cannot subscribe to {channel}: the transport on {self.url} is stopped")
        self._sockets.open_receiver(self._lc)
        self._sockets.widen_filter(channel)   # before LCM takes the channel: nothing of it is dropped after subscribe
        sub.handle = self._lc.subscribe(pattern, handler)
        if sub.handle is None:
            raise TransportError(f"cannot subscribe to {channel} on LCM at {self.url}")
        sub.handle.set_queue_capacity(queue_capacity)
        with self._subs_lock:
            self._subs.append(sub)
        return sub

    @property
    def filtered(self) -> bool:
        """True while the kernel drops the channels this transport does not take (u2sa_hw.bus.filter)."""
        return self._sockets.filtered

    def unsubscribe(self, sub: _Subscription) -> None:
        """Stop delivering to *sub* (at once; LCM lets go of it between two packets)."""
        with self._subs_lock:
            if sub not in self._subs:
                return
            self._subs.remove(sub)
        sub.active = False
        thread = self._thread
        if thread is None or not thread.is_alive() or thread is threading.current_thread():
            if self._lc is not None:
                self._lc.unsubscribe(sub.handle)
            return
        # LCM's Python binding crashes when a subscription goes while another thread is in
        # handle() (lcm-proj/lcm#616): the handler thread unsubscribes after its current handle.
        self._pending_unsubscribe.append(sub.handle)

    def _dispatch(self, sub: _Subscription, channel: str, data: bytes) -> None:
        if not sub.active:
            return
        generation = self._generation
        if self._bytes_counted != generation:   # the packet's first dispatch: verify it once
            self._bytes_counted = generation
            self._verdict = self._guard.verify(channel, data)
        if self._verdict is not OK:
            return
        data = self._guard.payload
        counters = self.rx[channel]
        if sub.raw:
            if self._messages_counted != generation:
                self._messages_counted = generation
                counters.messages += 1
            self._call(sub, channel, data)
            return
        try:
            msg, known = REGISTRY.decode(data, sub.base)
        except MalformedMessage as exc:
            if self._malformed_counted != generation:
                self._malformed_counted = generation
                counters.malformed += 1
            if channel not in self._malformed_logged:
                self._malformed_logged.add(channel)
                log.warning("%s: dropping malformed message on %s (%s); further ones are only counted",
                            self.name, channel, exc)
            self.last_error = f"malformed message on {channel}: {exc}"
            return
        if not known and data[:8] not in sub.unknown_logged:
            sub.unknown_logged.add(data[:8])
            log.info("%s: unknown type %s on %s decoded as its base %s",
                     self.name, data[:8].hex(), channel, sub.base.__name__)
        if self._messages_counted != generation:
            self._messages_counted = generation
            counters.messages += 1
        counters.type_name = type(msg).__name__
        try:   # _call, inlined on the path of every message
            sub.callback(channel, msg)
        except Exception as exc:  # noqa: BLE001 - a failing callback must not kill the handler thread
            counters.dropped += 1
            self._error(f"callback for {channel} failed: {type(exc).__name__}: {exc}", exc_info=True)

    def raw_lcm(self) -> Any:
        """The ``lcm.LCM`` under this transport, its receive socket open on the bus's interface.

        For tools that measure plain LCM on exactly the sockets a transport uses (bench/transport.py):
        what is published or received on it directly is neither signed nor verified, and the
        transport hears every channel from then on (no kernel filter, u2sa_hw.bus.filter).
        """
        if self._lc is None:
            raise TransportError(f"the transport on {self.url} is stopped")
        self._sockets.open_receiver(self._lc)
        self._sockets.widen_filter(".*")   # what is subscribed on it directly must not meet the kernel filter
        return self._lc

    @property
    def sender(self) -> str:
        """This transport's sender id in the trailers it signs (hex; empty on an open bus)."""
        return self.auth.sender.hex() if self.auth else ""

    def accepted_raises(self) -> dict[str, dict[str, int]]:
        """``{channel: {"raise_stale": n, "raise_foreign": n}}`` for channels where a raise was let through."""
        return self._guard.accepted_raises()

    def accepted_raise_log(self) -> list[AcceptedRaise]:
        """Every kind of raise let through though stale or foreign: its count, its last sender and that one's age."""
        return self._guard.accepted_raise_log()

    def rejected(self) -> dict[str, dict[str, int]]:
        """``{channel: {"unsigned": n, "forged": n, "replayed": n, "foreign": n, "denied": n}}`` for channels with drops."""
        return self._guard.rejected()

    @property
    def packet(self) -> bytes:
        """The whole packet being dispatched, its signature trailer included; call from a callback.

        The recorder keeps the pilot's trailers with RC_MODE and MANUAL_CMD so that a replay
        can check them with the recorded public key.
        """
        return self._guard.packet

    @property
    def last_sender(self) -> str:
        """The verified sender id (hex) of the message being dispatched; call from a callback."""
        return self.auth.last_sender.hex() if self.auth else ""

    def key_id(self) -> str:
        """The id of the key this transport signs with (hex; empty on an open bus)."""
        return self.auth.keyring.current.id.hex() if self.auth else ""

    def _call(self, sub: _Subscription, channel: str, payload: Any) -> None:
        try:
            sub.callback(channel, payload)
        except Exception as exc:  # noqa: BLE001 - a failing callback must not kill the handler thread
            self.rx[channel].dropped += 1
            self._error(f"callback for {channel} failed: {type(exc).__name__}: {exc}", exc_info=True)

    def _error(self, text: str, *, exc_info: bool = False) -> None:
        self.last_error = text
        log.error("%s: %s", self.name, text, exc_info=exc_info)

    # -- handling -----------------------------------------------------------------
    def handle_once(self, timeout: float) -> bool:
        """Handle at most one message, waiting up to *timeout* s; True if one was handled."""
        if self._lc is None:
            return False
        try:
            return self._lc.handle_timeout(max(0, int(timeout * 1000))) > 0
        finally:
            self._generation += 1

    def start(self) -> None:
        """Start the one handler thread (idempotent)."""
        if self._thread is not None:
            return
        self._sockets.open_receiver(self._lc)
        self._running = True
        self._thread = threading.Thread(target=self._loop, name=f"lcm-{self.name}", daemon=True)
        self._thread.start()
        name_native_thread(self._thread, f"bus {self.name}")   # top -H and bench/stack.py tell it apart

    def _loop(self) -> None:
        # handle_timeout releases the GIL while it waits in C; a short timeout bounds stop().
        while self._running:
            if self.auth is not None:
                self.auth.keyring.poll()
            try:
                self._lc.handle_timeout(200)
            except Exception as exc:  # noqa: BLE001 - keep handling; LCM reports socket trouble here
                self._error(f"LCM handle failed: {exc}")
                time.sleep(0.01)
            self._generation += 1
            self._unsubscribe_pending()
            if self._clock_store is not None and self._clock_store.due():
                self._save_clock_soon()
        self._unsubscribe_pending()

    def _save_clock_soon(self) -> None:
        """Save the signing clock on a thread of its own: an fsync on an SD card must not hold up handling."""
        if self._clock_saving is not None and self._clock_saving.is_alive():
            return
        self._clock_saving = threading.Thread(target=self._clock_store.save, args=(self.auth.high_water(),),
                                              name=f"bus-clock-{self.name}", daemon=True)
        self._clock_saving.start()

    def _unsubscribe_pending(self) -> None:
        while self._pending_unsubscribe:
            handle = self._pending_unsubscribe.popleft()
            try:
                self._lc.unsubscribe(handle)
            except Exception:  # noqa: BLE001 - LCM forgot it already
                pass

    def stop(self) -> None:
        """Stop the handler thread and release the LCM instance."""
        self._running = False
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=2.0)
        still_handling = thread is not None and thread.is_alive()
        self._thread = None
        with self._subs_lock:
            for sub in self._subs:
                sub.active = False
                if still_handling:
                    continue   # a callback outlived the join: unsubscribing now could crash LCM (see unsubscribe)
                try:
                    self._lc.unsubscribe(sub.handle)
                except Exception:  # noqa: BLE001 - tearing down
                    pass
            self._subs.clear()
        if self._clock_store is not None and self._lc is not None:
            self._clock_store.save(self.auth.high_water())   # the latest time, for a restart or a reboot
        if not still_handling and self._lc is not None:
            self._unsubscribe_pending()
            # LCM holds our handlers and we hold LCM: a cycle the garbage collector cannot see through
            # LCM's C type, so without this every stopped transport kept its sockets and pipes open
            # until the process ended (a long test run passed 1024 fds and LCM's select() crashed).
            self._lc = None

    def __enter__(self) -> "Transport":
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
