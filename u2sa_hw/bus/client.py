"""A client of the service contract over the bus: discovery, config, stop, listening.

Used by the ``u2sa`` command, the HSM and the tests. It is a plain transport user, not a
service: it answers no discovery and publishes no health.

A command that acts on the vehicle (``u2sa failsafe``, ``u2sa stop``) calls :meth:`BusClient.sync_clock`
before it publishes: a new sender's first packet is refused as a replay by every receiver
when its counter is more than the window (20 s) behind theirs, which a laptop without NTP
easily is; one verified packet heard first moves this process's signing clock to the
vehicle's (docs/security.md, "Replays and the window").
"""

from __future__ import annotations

import os
import threading
import time
import uuid
from pathlib import Path
from typing import Any

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.transport import Transport


class BusClient:
    """Request/response helpers on top of one :class:`Transport`."""

    def __init__(self, url: str | None = None, *, name: str | None = None, system_id: int = 0,
                 security: str | None = None, key_file: Path | str | None = None,
                 interface: str | None = None) -> None:
        self.name = name or f"u2sa-cli-{os.getpid()}"
        self.system_id = system_id
        # The key is found as a service finds it (u2sa_hw.bus.key.key_path); a TransportError says how to get it.
        # With a vehicle's system id (from its profile), another vehicle's messages are dropped as foreign.
        self.transport = Transport(url, name=self.name, security=security, key_file=key_file, interface=interface,
                                   system_id=system_id or None)
        self.transport.start()
        self._seq = 0

    def close(self) -> None:
        """Release the transport."""
        self.transport.stop()

    def __enter__(self) -> "BusClient":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _stamp(self, msg: Any) -> Any:
        self._seq += 1
        msg.header.system_id = self.system_id
        msg.header.timestamp_us = time.time_ns() // 1000
        msg.header.source = self.name
        msg.header.sequence = self._seq
        return msg

    def publish(self, channel: str, msg: Any) -> bool:
        """Publish *msg* with a stamped root header (for types with ``header`` or ``base``)."""
        header = root_header(msg)
        if header is not None:
            self._seq += 1
            header.system_id = header.system_id or self.system_id
            header.timestamp_us = time.time_ns() // 1000
            header.source = header.source or self.name
            header.sequence = self._seq
        return self.transport.publish(channel, msg)

    def _collect(self, reply_channel: str, reply_type: type, request_channel: str, request: Any, *,
                 timeout: float, want: int | None = None, match: Any = None) -> list[Any]:
        replies: list[Any] = []
        done = threading.Event()

        def on_reply(_c: str, msg: Any) -> None:
            if msg.request_id != request.request_id or (match is not None and not match(msg)):
                return
            replies.append(msg)
            if want is not None and len(replies) >= want:
                done.set()

        sub = self.transport.subscribe(reply_channel, reply_type, on_reply)
        try:
            self.transport.publish(request_channel, self._stamp(request))
            done.wait(timeout)
        finally:
            self.transport.unsubscribe(sub)
        return replies

    def discover(self, *, timeout: float = 1.0, name: str = "") -> list[t.DiscoveryResponse]:
        """Every service that answers a discovery request within *timeout* (one answer per name)."""
        req = t.DiscoveryRequest()
        req.request_id = uuid.uuid4().hex
        req.name_filter = name
        replies = self._collect(ch.DISCOVERY_RESPONSE, t.DiscoveryResponse, ch.DISCOVERY_REQUEST, req,
                                timeout=timeout, want=1 if name else None)
        by_name: dict[str, t.DiscoveryResponse] = {}
        for r in replies:
            by_name[r.name] = r
        return [by_name[n] for n in sorted(by_name)]

    def find_service(self, name: str, *, timeout: float = 1.0,
                     resend: float = 0.25) -> tuple[t.DiscoveryResponse | None, list[str]]:
        """Discover until *name* answers or *timeout* passes: ``(its answer or None, every name heard)``.

        One discovery round for everyone (no name filter), so when *name* is not on the bus the
        names that are give a did-you-mean (:func:`unknown_service_text`) instead of a silent wait
        for an answer that cannot come. Returns as soon as *name* answers; the request is sent
        again every *resend* s (a service that was still starting, or a lost datagram).
        """
        req = t.DiscoveryRequest()
        req.request_id = uuid.uuid4().hex
        heard: dict[str, t.DiscoveryResponse] = {}
        found = threading.Event()

        def on_reply(_c: str, msg: t.DiscoveryResponse) -> None:
            if msg.request_id != req.request_id:
                return
            heard[msg.name] = msg
            if msg.name == name:
                found.set()

        sub = self.transport.subscribe(ch.DISCOVERY_RESPONSE, t.DiscoveryResponse, on_reply)
        try:
            deadline = time.monotonic() + timeout
            while True:
                self.transport.publish(ch.DISCOVERY_REQUEST, self._stamp(req))
                left = deadline - time.monotonic()
                if found.wait(max(0.0, min(resend, left))) or left <= resend:
                    break
        finally:
            self.transport.unsubscribe(sub)
        return heard.get(name), sorted(heard)

    def get_config(self, service: str, *, timeout: float = 5.0) -> t.ConfigResponse | None:
        """The config of *service*, or None when it does not answer."""
        req = t.ConfigRequest()
        req.request_id = uuid.uuid4().hex
        req.target = service
        replies = self._collect(ch.CONFIG_RESPONSE, t.ConfigResponse, ch.CONFIG_REQUEST, req,
                                timeout=timeout, want=1, match=lambda m: m.name == service)
        return replies[0] if replies else None

    def set_config(self, service: str, field_name: str, value: str, *, timeout: float = 5.0) -> t.ConfigResponse | None:
        """Change one field of *service*; the response says ok or why not; None when no answer."""
        req = t.ConfigChange()
        req.request_id = uuid.uuid4().hex
        req.target, req.field, req.value = service, field_name, value
        replies = self._collect(ch.CONFIG_RESPONSE, t.ConfigResponse, ch.CONFIG_CHANGE, req,
                                timeout=timeout, want=1, match=lambda m: m.name == service)
        return replies[0] if replies else None

    def stop(self, *, name: str = "", all_services: bool = False) -> None:
        """Send a stop command for one service or all."""
        cmd = t.StopCommand()
        cmd.all, cmd.name = all_services, name
        self.transport.publish(ch.STOP, self._stamp(cmd))

    def sync_clock(self, *, timeout: float = 1.5) -> bool:
        """Wait up to *timeout* s for one verified packet from another sender; True once heard (or on an open bus).

        Verifying it moves this transport's signing clock forward to the sender's, so what this
        client publishes next is inside every receiver's replay window. False: nothing signed
        with our key was heard (an empty bus, another key, no multicast); publishing still works
        for receivers whose clocks are not ahead of ours.
        """
        transport = self.transport
        if transport.auth is None:
            return True
        heard = threading.Event()
        own = transport.sender

        def on_any(_c: str, _data: bytes) -> None:
            if transport.last_sender != own:   # our own packets loop back: they teach us nothing
                heard.set()

        sub = transport.subscribe(".*", None, on_any, raw=True)
        try:
            heard.wait(timeout)
        finally:
            transport.unsubscribe(sub)
        return heard.is_set()

    def wait_for(self, predicate: Any, *, timeout: float, interval: float = 0.05) -> bool:
        """Poll *predicate* until true or *timeout*; True if it became true."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return True
            time.sleep(interval)
        return bool(predicate())


def unknown_service_text(name: str, names: list[str]) -> str:
    """``no service 'pann' on the bus; did you mean 'pan'? (services: ...)`` for a name discovery did not find."""
    from u2sa_hw.config.keys import did_you_mean, known_text

    hint = did_you_mean(name, names)
    return f"no service '{name}' on the bus" + (f"; {hint}" if hint else "") + f" (services: {known_text(names)})"


def root_header(msg: Any) -> t.Header | None:
    """The root ``Header`` of *msg*: its own ``header``, else its ``base``'s (and so on), or None."""
    cur = msg
    while cur is not None:
        header = getattr(cur, "header", None)
        if isinstance(header, t.Header):
            return header
        cur = getattr(cur, "base", None)
    return None
