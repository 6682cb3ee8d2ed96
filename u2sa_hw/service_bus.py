"""What a service says about its bus, and the check that keeps two of one name apart (issue 11).

* :func:`bus_text` and :func:`rejected_text` fill the ``bus_security`` and ``bus_rejected``
  details of every Health message (``u2sa services`` and ``u2sa health`` show them).
* :func:`find_duplicate` runs as a service process starts, before ``setup()`` opens any
  device: a live service of the same name that answers discovery on this bus means this
  one refuses to start (exit :data:`DUPLICATE_EXIT`) with one line naming the other's pid
  and host and the fix. Only a process with the bus key can answer, so another stack
  signed with another key is no duplicate.
"""

from __future__ import annotations

import os
import time
from typing import TYPE_CHECKING

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.health import HOSTNAME

if TYPE_CHECKING:
    from u2sa_hw.service import U2SAService
    from u2sa_hw.transport import Transport

DUPLICATE_PROBE_S = 0.25   # how long a starting service listens for another of its name
DUPLICATE_EXIT = 3         # exit status of a service that refused to start beside its duplicate


def bus_text(transport: "Transport") -> str:
    """``signed (key 1a2b3c4d)`` or ``open``."""
    return f"signed (key {transport.key_id()})" if transport.auth is not None else "open"


def rejected_text(rejected: dict[str, dict[str, int]]) -> str:
    """``CHANNEL: unsigned 2, replayed 1; ...`` from :meth:`Transport.rejected` (health's ``bus_rejected``)."""
    return "; ".join(f"{channel}: " + ", ".join(f"{why} {n}" for why, n in counts.items() if n)
                     for channel, counts in rejected.items())


def find_duplicate(service: "U2SAService", *, timeout: float = DUPLICATE_PROBE_S) -> str | None:
    """Why *service* must not start (another of its name answers discovery), or None.

    The transport's handler thread has not started yet, so this thread pumps it.
    """
    found: list[t.DiscoveryResponse] = []
    me = (HOSTNAME, os.getpid())

    def on_response(_c: str, r: t.DiscoveryResponse) -> None:
        if r.name == service.name and (r.host, r.pid) != me:
            found.append(r)

    transport = service.transport
    sub = transport.subscribe(ch.DISCOVERY_RESPONSE, t.DiscoveryResponse, on_response)
    try:
        req = t.DiscoveryRequest()
        req.request_id, req.name_filter = f"dup-{os.getpid()}-{time.monotonic_ns()}", service.name
        req.header.system_id, req.header.source = service.profile.system_id, service.name
        req.header.timestamp_us = time.time_ns() // 1000
        transport.publish(ch.DISCOVERY_REQUEST, req)
        deadline = time.monotonic() + timeout
        while not found and (left := deadline - time.monotonic()) > 0:
            try:
                transport.handle_once(left)
            except OSError:   # a signal (SIGINT, SIGTERM) interrupted the wait: stop() was asked
                break
    finally:
        transport.unsubscribe(sub)
    if not found:
        return None
    other = found[0]
    return (f"another '{service.name}' ({other.service_type}) already runs on this bus: pid {other.pid} on host "
            f"{other.host}; stop it first ('u2sa stop {service.name}'), or give this one another name or another "
            "lcm_url (u2sa sim and the tests pick a private port)")
