"""What a service says about its bus, and the checks that refuse a start (issue 11).

* :func:`bus_text` and :func:`rejected_text` fill the ``bus_security`` and ``bus_rejected``
  details of every Health message (``u2sa services`` and ``u2sa health`` show them); the
  transport's ``listen_problem`` fills ``bus_listen``.
* :func:`find_duplicate` runs as a service process starts, before ``setup()`` opens any
  device, and says why it must not start, in one line; the service then exits
  :data:`DUPLICATE_EXIT` (3), which neither ``u2sa run`` nor systemd
  (``RestartPreventExitStatus=3``) restarts, since a restart would find the same:

  - :func:`listen_refusal`: a ``ttl=0`` bus that cannot be kept on ``lo`` (its MULTICAST flag
    is off and the service may not set it) with a key other hosts may hold (the installed
    ``/etc/u2sa/bus.key`` or the profile's ``bus_key``) or on an open bus: any host on the
    network that has the key (or, open, any host) could command it. A key the run made for
    itself (``$U2SA_BUS_KEY_FILE``: ``u2sa sim``, ``u2sa run`` without an installed key, the
    tests) is held by no other host: the service starts and its health says where it listens.
  - a live service of the same name that answers discovery on this bus: the line names the
    other's pid and host and the fix. Only a process with the bus key can answer, so another
    stack signed with another key is no duplicate. The probe lasts :data:`DUPLICATE_PROBE_S`
    (``$U2SA_DUPLICATE_PROBE_S`` to wait longer, e.g. on a loaded test machine).
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import TYPE_CHECKING

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.health import HOSTNAME

if TYPE_CHECKING:
    from u2sa_hw.service import U2SAService
    from u2sa_hw.transport import Transport

DUPLICATE_PROBE_S = 0.25   # how long a starting service listens for another of its name
PROBE_ENV = "U2SA_DUPLICATE_PROBE_S"
DUPLICATE_EXIT = 3         # exit status of a service that refused to start (a duplicate, a bus off the board)


def bus_text(transport: "Transport") -> str:
    """``signed (key 1a2b3c4d)`` or ``open``."""
    return f"signed (key {transport.key_id()})" if transport.auth is not None else "open"


def rejected_text(rejected: dict[str, dict[str, int]]) -> str:
    """``CHANNEL: unsigned 2, replayed 1; ...`` from :meth:`Transport.rejected` (health's ``bus_rejected``)."""
    return "; ".join(f"{channel}: " + ", ".join(f"{why} {n}" for why, n in counts.items() if n)
                     for channel, counts in rejected.items())


def run_key(key_file: Path, profile_key: Path | None, *, env: dict[str, str] | None = None) -> bool:
    """True when *key_file* is a key this run chose (``$U2SA_BUS_KEY_FILE``), not the vehicle's.

    The vehicle's key is the installed ``/etc/u2sa/bus.key`` or the profile's ``bus_key``: the
    key a ground station or another board may hold.
    """
    from u2sa_hw.bus_key import KEY_ENV, SYSTEM_KEY

    if not (os.environ if env is None else env).get(KEY_ENV):
        return False
    vehicle_keys = {SYSTEM_KEY.resolve(), *([Path(profile_key).resolve()] if profile_key else [])}
    return Path(key_file).resolve() not in vehicle_keys


def listen_refusal(service: "U2SAService") -> str | None:
    """Why *service* must not start because its bus cannot be kept where it belongs, or None.

    Only a bus the transport could not keep on its interface (``lo`` for ``ttl=0``, else the
    profile's ``bus_interface``) is refused, and only when a host on the network could command
    the service: with the vehicle's key, or on an open bus.
    """
    transport = service.transport
    problem = transport.listen_problem
    if not problem or transport.interface is None:   # fine, or $U2SA_BUS_ANY_INTERFACE asked for it
        return None
    auth = transport.auth
    if auth is not None and run_key(auth.keyring.path, service.profile.bus_key):
        return None   # a key no other host has: it starts, and its health says where it listens
    who = ("any host on that network (the bus is open)" if auth is None else
           f"any host on that network that has the vehicle's key {auth.keyring.path}")
    return (f"refusing to start '{service.name}': {problem}; until then {who} could command it "
            "(docs/security.md, 'Where the vehicle listens'); 'u2sa run' as root sets the flag itself")


def listen_state(service: "U2SAService") -> str:
    """The ``bus_listen`` line of *service*'s health: where its bus listens when that is not where it belongs.

    The transport's ``listen_problem`` (a ``ttl=0`` bus off ``lo``), else, for a ``ttl`` >= 1 bus
    without ``bus_interface`` signed with the vehicle's key (or open), the default route's interface
    (:func:`~u2sa_hw.bus_listen.default_route_note`): not refused, as a multi-board vehicle may mean
    it, but visible in ``u2sa services`` and ``u2sa health``. A run's own key (:func:`run_key`) is
    held by no other host: nothing to say then.
    """
    from u2sa_hw.bus_listen import default_route_note

    transport = service.transport
    if transport.listen_problem:
        return transport.listen_problem
    note = default_route_note(transport.url, service.profile.bus_interface)
    auth = transport.auth
    if not note or auth is not None and run_key(auth.keyring.path, service.profile.bus_key):
        return ""
    return note


def probe_seconds(default: float = DUPLICATE_PROBE_S) -> float:
    """How long the duplicate probe listens: ``$U2SA_DUPLICATE_PROBE_S`` if set (and a number > 0), else *default*."""
    try:
        value = float(os.environ.get(PROBE_ENV, ""))
    except ValueError:
        return default
    return value if value > 0 else default


def find_duplicate(service: "U2SAService", *, timeout: float | None = None) -> str | None:
    """Why *service* must not start, in one line, or None: :func:`listen_refusal`, or another of its name answers.

    The transport's handler thread has not started yet, so this thread pumps it.
    """
    refused = listen_refusal(service)
    if refused is not None:
        return refused
    timeout = probe_seconds() if timeout is None else timeout
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
