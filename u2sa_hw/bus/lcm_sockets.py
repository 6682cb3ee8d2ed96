"""The sockets under one transport's LCM instance: opened on the bus's interface, the receive one found and
bound before any handler thread, and the kernel's channel filter on it.

:class:`LcmSockets` opens LCM (its C library's complaints folded into one :class:`TransportError`,
u2sa_hw.bus.lcm_open), keeps a ttl >= 1 bus's sends on the profile's ``bus_interface`` (u2sa_hw.bus.listen),
has LCM bind its receive socket early (:meth:`LcmSockets.open_receiver`: LCM binds lazily, and a bind
that fails there prints to stderr and can leave a handling thread and a subscribing one blocked on each
other), and narrows what the kernel passes up to the channels subscribed (:meth:`LcmSockets.widen_filter`,
u2sa_hw.bus.filter; ``$U2SA_BUS_FILTER=off`` hears the whole bus).
"""

from __future__ import annotations

import os
import threading
from typing import Any

import lcm

from u2sa_hw.bus import filter as bus_filter
from u2sa_hw.bus.lcm_open import TransportError, captured_c_stderr, open_error, reemit
from u2sa_hw.bus.lcm_url import with_receive_buffer
from u2sa_hw.bus.listen import (bus_port, forced_default_problem, listen_interface, prepare_interface, receive_on,
                                send_via, socket_fds)

FILTER_ENV = "U2SA_BUS_FILTER"   # "off": every transport hears the whole bus (u2sa_hw.bus.filter)
_RECEIVER_OPENING = threading.Lock()   # one transport at a time finds its new receive socket among the process's


def is_regex(channel: str) -> bool:
    """True when *channel* is a pattern (LCM subscribes it as a regex), not one channel's name."""
    return any(ch in channel for ch in "*+?[]()|\\^$")


class LcmSockets:
    """The sockets of one LCM instance on *url*; *interface*: the profile's ``bus_interface`` (None: the
    default for the URL, u2sa_hw.bus.listen). ``listen_problem`` is "" when the bus stays where the URL
    and the interface say, else where it listens instead and the fix."""

    def __init__(self, url: str, interface: str | None) -> None:
        self.url = url
        self.interface = listen_interface(url, interface)
        self.listen_problem = forced_default_problem(url)
        self.if_index: int | None = None
        self.send_fds: set[int] = set()
        self.receiving = False   # set once open_receiver had LCM bind its receive socket
        self._receiver_lock = threading.Lock()
        self.recv_fds: set[int] = set()   # LCM's receive socket (found as it opens), for the channel filter
        # The exact channels subscribed, which the kernel filter passes; None: a regex subscription, hear everything.
        self.filter_channels: set[str] | None = (set() if url.startswith("udpm://")
                                                 and os.environ.get(FILTER_ENV, "").lower() != "off" else None)
        self._filter_lock = threading.Lock()
        self.filtered = False   # True while the kernel drops the channels this transport does not take

    def open(self) -> Any:
        """A new ``lcm.LCM`` on the URL, sending on the interface only when one is set; TransportError with the
        fix when it cannot open. The caller holds the only reference (see Transport.stop)."""
        sockets_before = socket_fds() if self.interface else set()
        with captured_c_stderr() as printed:
            try:
                lc = lcm.LCM(with_receive_buffer(self.url))
                failure = None
            except (RuntimeError, OSError) as exc:
                failure = exc
        if failure is not None:
            raise TransportError(open_error(self.url, f"cannot open LCM at {self.url}", failure, printed[0]))
        reemit(printed[0])
        self.send_fds = socket_fds() - sockets_before if self.interface else set()
        if self.interface:
            try:
                self.if_index, problem = prepare_interface(self.url, self.interface)
                self.listen_problem = problem or self.listen_problem
                if self.if_index is not None:
                    send_via(self.url, self.send_fds, self.if_index)
            except OSError as exc:
                raise TransportError(f"cannot send on {self.interface} only: {exc}") from None
        return lc

    def open_receiver(self, lc: Any) -> None:
        """Have LCM bind its receive socket now, before any handler thread, so a failure is one clear error.

        LCM binds lazily (at the first subscribe or handle); a bind that fails there prints to
        stderr and can leave a handling thread and a subscribing one blocked on each other.
        """
        if self.receiving:
            return
        with self._receiver_lock:   # two threads subscribing first at once: one opens, the other waits for it
            if self.receiving:
                return
            if self.if_index is not None:
                send_via(self.url, self.send_fds, 0)   # LCM's self test, as the receiver opens, sends on the route
            with _RECEIVER_OPENING, captured_c_stderr() as printed:
                sockets_before = socket_fds()
                fd = lc.fileno()
                recv_fds = socket_fds() - sockets_before
            if fd < 0:
                raise TransportError(open_error(self.url, f"cannot receive on LCM at {self.url}", None, printed[0]))
            reemit(printed[0])
            if self.if_index is not None:
                try:
                    receive_on(self.url, recv_fds, self.if_index)
                    send_via(self.url, self.send_fds, self.if_index)
                except OSError as exc:
                    raise TransportError(f"cannot listen on {self.interface} only: {exc}") from None
            self.recv_fds = recv_fds
            self.receiving = True

    def widen_filter(self, channel: str) -> None:
        """Let the kernel pass *channel* too (all channels once a subscription is a regex).

        Filters only narrow what a process hears to what it subscribed to; an unsubscribed channel
        stays in the filter (a few packets more, never one fewer).
        """
        with self._filter_lock:
            wanted = self.filter_channels
            if wanted is None or channel in wanted:
                return
            port = bus_port(self.url)
            if is_regex(channel):
                self.filter_channels = None
                bus_filter.apply(self.recv_fds, port, None)
                self.filtered = False
                return
            wanted.add(channel)
            self.filtered = bus_filter.apply(self.recv_fds, port, wanted)
            if not self.filtered:
                self.filter_channels = None   # not available here (apply removed any filter): stop trying
