"""What a service says about its bus, and the checks that refuse a start (issue 11).

* :func:`bus_text` and :func:`rejected_text` fill the ``bus_security`` and ``bus_rejected``
  details of every Health message (``u2sa services`` and ``u2sa health`` show them); the
  transport's ``listen_problem`` fills ``bus_listen``.
* :func:`raises_text` fills ``bus_raises_accepted``: the failsafe raises the transport let
  through though outside the replay window or from another system id (they fail safe), each
  kind with its count, last sender and that one's age. :func:`parse_raises` reads it back and
  :func:`raise_line` says it in the words ``u2sa health`` and ``u2sa services`` print
  (:func:`raise_note`, shorter, in the reason column of ``u2sa health --watch``).
* :func:`listen_state` fills ``bus_listen``: the transport's ``listen_problem``, or a ``ttl`` >= 1
  bus with the vehicle's key on the default route's interface.
* :class:`DuplicateWatch` runs as a service process starts, before ``setup()`` opens any
  device (:meth:`DuplicateWatch.probe`), and says why it must not start, in one line; the
  service then exits :data:`DUPLICATE_EXIT` (3), which neither ``u2sa run`` nor systemd
  (``RestartPreventExitStatus=3``) restarts, since a restart would find the same:

  - :func:`listen_refusal`: a ``ttl=0`` bus that cannot be kept on ``lo`` (its MULTICAST flag
    is off and the service may not set it) with a key other hosts may hold (the installed
    ``/etc/u2sa/bus.key`` or the profile's ``bus_key``) or on an open bus: any host on the
    network that has the key (or, open, any host) could command it. A key the run made for
    itself (``$U2SA_BUS_KEY_FILE``: ``u2sa sim``, ``u2sa run`` without an installed key, the
    tests) is held by no other host: the service starts and its health says where it listens.
  - a live service of the same name that answers discovery (or sends its Health) on this
    bus: the line names the other's pid and host and the fix. Only a process with the bus key
    can answer, so another stack signed with another key is no duplicate. The probe lasts
    :data:`DUPLICATE_PROBE_S`, its request sent again every :data:`PROBE_RESEND_S`
    (``$U2SA_DUPLICATE_PROBE_S`` to change it; 0 skips it).

  Two that start together cannot see each other in the probe (neither answers before it
  runs), and a loaded board may answer after it: for :data:`DUPLICATE_WATCH_S` after its start
  the service watches the Health of others of its name, and the newer of two
  (:class:`Instance`: the later start, then the larger stack pid, then the larger sender id)
  stops with the same line and the same exit status; the older runs on.
"""

from __future__ import annotations

import math
import os
import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.service.health import HOSTNAME

if TYPE_CHECKING:
    from collections.abc import Iterable

    from u2sa_hw.service.contract import U2SAService
    from u2sa_hw.bus.transport import Transport
    from u2sa_hw.bus.guard import AcceptedRaise

# How long a starting service listens for another of its name, sending its discovery request again
# every PROBE_RESEND_S (one may be lost or answered late). A live service answers in milliseconds;
# the probe is short because every restart waits for it (a killed service must publish again within
# 1.5 s, issue 27), and the watch after start catches an answer later than the probe.
DUPLICATE_PROBE_S = 0.3
PROBE_RESEND_S = 0.1
PROBE_ENV = "U2SA_DUPLICATE_PROBE_S"
DUPLICATE_WATCH_S = 10.0   # after start, how long it watches Health for another of its name (started together)
RUN_ID_ENV = "U2SA_RUN_ID"   # set by the launcher (u2sa run, u2sa sim) for its children
_STARTED_US = time.time_ns() // 1000   # when /proc cannot say when this process started
DUPLICATE_EXIT = 3         # exit status of a service that refused to start (a duplicate, a bus off the board)


def bus_text(transport: "Transport") -> str:
    """``signed (key 1a2b3c4d)`` or ``open``."""
    return f"signed (key {transport.key_id()})" if transport.auth is not None else "open"


def rejected_text(rejected: dict[str, dict[str, int]]) -> str:
    """``CHANNEL: unsigned 2, replayed 1; ...`` from :meth:`Transport.rejected` (health's ``bus_rejected``)."""
    return "; ".join(f"{channel}: " + ", ".join(f"{why} {n}" for why, n in counts.items() if n)
                     for channel, counts in rejected.items())


# The transport's counter of each kind of accepted raise, the word the health detail uses for it,
# and what such a raise is likely to be (said by u2sa health and u2sa services).
RAISE_KINDS = {"raise_stale": "stale", "raise_foreign": "foreign"}
RAISE_WHAT = {"stale": ("outside the replay window", "a sender whose clock is behind, or a replay"),
              "foreign": ("naming another system id", "a ground station or an operator's u2sa with another "
                          "vehicle's profile, or another vehicle under this key")}
_RAISE_PART = re.compile(r"^(?P<channel>[^:;]+): (?P<count>\d+) (?P<kind>\w+), last from sender (?P<sender>\S*) "
                         r"(?P<age>\d+(?:\.\d+)?) s ago$")


def raises_text(raises: Iterable[AcceptedRaise]) -> str:
    """``FAILSAFE: 2 stale, last from sender 1a2b3c4d5e6f7a8b 12.3 s ago; FAILSAFE: 1 foreign, ...``.

    From :meth:`Transport.accepted_raise_log` (health's ``bus_raises_accepted``); "" when none.
    """
    return "; ".join(f"{r.channel}: {r.count} {RAISE_KINDS.get(r.kind, r.kind)}, last from sender "
                     f"{r.last_sender or '-'} {r.last_age_s:.1f} s ago" for r in raises)


def parse_raises(text: str, *, older_by_s: float = 0.0) -> list[dict[str, Any]]:
    """The entries of a ``bus_raises_accepted`` text: channel, kind, count, last_sender, last_age_s.

    *older_by_s* is added to each age: how long ago the Health carrying the text arrived. A
    part that does not parse is left out.
    """
    out: list[dict[str, Any]] = []
    for part in text.split(";") if text else ():
        m = _RAISE_PART.match(part.strip())
        if m:
            out.append({"channel": m["channel"], "kind": m["kind"], "count": int(m["count"]),
                        "last_sender": "" if m["sender"] == "-" else m["sender"],
                        "last_age_s": round(float(m["age"]) + max(0.0, older_by_s), 1)})
    return out


def raise_note(entry: dict[str, Any]) -> str:
    """One :func:`parse_raises` entry, short: ``accepted 2 failsafe raises outside the replay window (last 12.3 s
    ago, from sender 1a2b3c4d5e6f7a8b)`` (the reason column of ``u2sa health --watch`` and Foxglove's /health)."""
    where = RAISE_WHAT.get(entry["kind"], (f"({entry['kind']})", ""))[0]
    n = entry["count"]
    on = "" if entry["channel"] == ch.FAILSAFE else f" on {entry['channel']}"
    return (f"accepted {n} failsafe raise{'' if n == 1 else 's'}{on} {where} (last {entry['last_age_s']:.1f} s ago, "
            f"from sender {entry['last_sender'] or 'unknown'})")


def raise_line(service: str, entry: dict[str, Any]) -> str:
    """One :func:`parse_raises` entry in words, as ``u2sa health`` and ``u2sa services`` print it:

    ``hsm: accepted 2 failsafe raises outside the replay window (last 12.3 s ago, from sender
    1a2b3c4d5e6f7a8b): a raise always fails safe; a sender whose clock is behind, or a replay``.
    """
    likely = RAISE_WHAT.get(entry["kind"], ("", "an unknown kind"))[1]
    return f"{service}: {raise_note(entry)}: a raise always fails safe; {likely}"


def run_key(key_file: Path, profile_key: Path | None, *, env: dict[str, str] | None = None) -> bool:
    """True when *key_file* is a key this run chose (``$U2SA_BUS_KEY_FILE``), not the vehicle's.

    The vehicle's key is the installed ``/etc/u2sa/bus.key`` or the profile's ``bus_key``: the
    key a ground station or another board may hold.
    """
    from u2sa_hw.bus.key import KEY_ENV, SYSTEM_KEY

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
    (:func:`~u2sa_hw.bus.listen.default_route_note`): not refused, as a multi-board vehicle may mean
    it, but visible in ``u2sa services`` and ``u2sa health``. A run's own key (:func:`run_key`) is
    held by no other host: nothing to say then.
    """
    from u2sa_hw.bus.listen import default_route_note

    transport = service.transport
    if transport.listen_problem:
        return transport.listen_problem
    note = default_route_note(transport.url, service.profile.bus_interface)
    auth = transport.auth
    if not note or auth is not None and run_key(auth.keyring.path, service.profile.bus_key):
        return ""
    return note


def probe_seconds(default: float = DUPLICATE_PROBE_S) -> float:
    """How long the duplicate probe listens: ``$U2SA_DUPLICATE_PROBE_S`` if set (a number >= 0), else *default*.

    0 skips the probe (a start a second quicker): the watch after start still finds a duplicate.
    """
    try:
        value = float(os.environ.get(PROBE_ENV, ""))
    except ValueError:
        return default
    return value if value >= 0 and math.isfinite(value) else default


@dataclass(frozen=True, order=True)
class Instance:
    """What orders two live services of one name: the later start, then the larger stack pid, then sender id.

    *started_us* is the wall-clock start of the process, or of the ``u2sa run``/``u2sa sim``
    launcher that started it (``$U2SA_RUN_ID`` set, the launcher its parent): every service of
    one run then has the run's start, and of two runs of one profile the whole newer run gives
    way, not half of each (the launcher stops a run when one of its services exits 3). Each
    side compares the values both report (Health details ``started_us`` and ``stack_pid``, the
    verified sender id), so both reach the same verdict, whatever their clocks.
    """

    started_us: int
    stack_pid: int
    sender: str
    host: str = field(compare=False, default="")
    pid: int = field(compare=False, default=0)


def own_instance(transport: "Transport") -> Instance:
    """This process's :class:`Instance`."""
    sender = getattr(transport, "sender", "")   # "" on an open bus: no sender ids
    ppid = os.getppid()
    if os.environ.get(RUN_ID_ENV) and ppid > 1:   # a child of the launcher: the run's start
        started = process_start_us(ppid)
        if started is not None:
            return Instance(started, ppid, sender, HOSTNAME, os.getpid())
    started = process_start_us(os.getpid())
    return Instance(_STARTED_US if started is None else started, os.getpid(), sender, HOSTNAME, os.getpid())


def process_start_us(pid: int) -> int | None:
    """When process *pid* started (wall clock, µs; 10 ms resolution), from /proc; None when unknown."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            ticks = int(f.read().rsplit(")", 1)[1].split()[19])   # field 22, starttime, after "(comm)"
        with open("/proc/stat") as f:
            btime = next(int(line.split()[1]) for line in f if line.startswith("btime "))
        return btime * 1_000_000 + ticks * 1_000_000 // os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return None


def health_instance(msg: t.Health, sender: str) -> Instance:
    """The :class:`Instance` a Health reports (its ``started_us`` and ``stack_pid`` details)."""
    details = {kv.key: kv.value for kv in msg.details}
    try:
        started, stack = int(details["started_us"]), int(details["stack_pid"])
    except (KeyError, ValueError):   # a sender that does not say: its start from its uptime
        started, stack = msg.header.timestamp_us - int(msg.uptime_s * 1e6), msg.pid
    return Instance(started, stack, sender, msg.host, msg.pid)


def instance_details(me: Instance) -> dict[str, str]:
    """The Health details that let another of this name order itself against *me*."""
    return {"started_us": str(me.started_us), "stack_pid": str(me.stack_pid)}


class DuplicateWatch:
    """Finds a live service of the same name on this bus: before start (:meth:`probe`) and for a while after.

    * :meth:`probe` (before ``setup()``): the transport's handler thread has not started, so
      this thread pumps it. It sends a discovery request, again every :data:`PROBE_RESEND_S`,
      for :func:`probe_seconds`; a discovery answer or a Health of the name from another
      process (not one stopping) is a service already running: the line why this one must not
      start. A loaded board may answer late; two that start together cannot see each other
      here (neither answers before it runs): hence the watch.
    * the watch (from the probe to :data:`DUPLICATE_WATCH_S` after :meth:`arm`, which the
      service calls once started): the Health of every other live service of this name and
      vehicle, signed by another sender, with another pid. Of the two, the newer (the larger
      :class:`Instance`) stops: it calls ``service.stop()`` and :attr:`refusal` says why, in the
      line the service logs and exits :data:`DUPLICATE_EXIT` with. The older says nothing and
      runs on, so exactly one of the two stays (an actuator that stops drops its device to
      neutral; the HSM is never left without one).
    """

    def __init__(self, service: "U2SAService", *, watch_s: float = DUPLICATE_WATCH_S) -> None:
        self.service = service
        self.transport = service.transport
        self.watch_s = watch_s
        self.me = own_instance(self.transport)
        self.refusal: str | None = None     # set: this one must not run (the line, with the other and the fix)
        self._probing = False
        self._found: list[tuple[str, int, str]] = []   # (service type, pid, host) answering during the probe
        self._lock = threading.Lock()
        self._health_sub: Any = None
        self._timer: threading.Timer | None = None

    def details(self) -> dict[str, str]:
        """This service's ``started_us`` and ``stack_pid`` for its Health."""
        return instance_details(self.me)

    def probe(self, timeout: float | None = None) -> str | None:
        """Why the service must not start, in one line (:func:`listen_refusal`, or another answers), or None."""
        refused = listen_refusal(self.service)
        if refused is not None:
            return refused
        timeout = probe_seconds() if timeout is None else timeout
        transport, service = self.transport, self.service
        self._probing = True
        self._health_sub = transport.subscribe(ch.HEALTH, t.Health, self._on_health)
        if timeout <= 0:
            self._probing = False
            return None
        sub = transport.subscribe(ch.DISCOVERY_RESPONSE, t.DiscoveryResponse, self._on_response)
        try:
            start = time.monotonic()
            deadline, resend = start + timeout, start
            while not self._found and (left := deadline - time.monotonic()) > 0:
                if time.monotonic() >= resend:
                    self._request()
                    resend += PROBE_RESEND_S
                try:
                    transport.handle_once(min(left, max(0.0, resend - time.monotonic())))
                except OSError:   # a signal (SIGINT, SIGTERM) interrupted the wait: stop() was asked
                    break
        finally:
            transport.unsubscribe(sub)
            self._probing = False
        if not self._found:
            return None
        self.close()
        kind, pid, host = self._found[0]
        return duplicate_line(service.name, kind, pid, host)

    def arm(self) -> None:
        """The service started: watch for :attr:`watch_s` more, then stop listening to Health."""
        if self._health_sub is None or self.watch_s <= 0:
            self.close()
            return
        self._timer = threading.Timer(self.watch_s, self.close)
        self._timer.daemon = True
        self._timer.start()

    def close(self) -> None:
        """Stop watching (idempotent; from any thread but the transport's handler thread)."""
        with self._lock:
            sub, self._health_sub = self._health_sub, None
            timer, self._timer = self._timer, None
        if timer is not None and timer is not threading.current_thread():
            timer.cancel()
        if sub is not None:
            self.transport.unsubscribe(sub)

    def _request(self) -> None:
        service = self.service
        req = t.DiscoveryRequest()
        req.request_id, req.name_filter = f"dup-{os.getpid()}-{time.monotonic_ns()}", service.name
        req.header.system_id, req.header.source = service.profile.system_id, service.name
        req.header.timestamp_us = time.time_ns() // 1000
        self.transport.publish(ch.DISCOVERY_REQUEST, req)

    def _on_response(self, _c: str, r: t.DiscoveryResponse) -> None:
        if r.name == self.service.name and (r.host, r.pid) != (HOSTNAME, os.getpid()):
            self._found.append((r.service_type, r.pid, r.host))

    def _on_health(self, _c: str, msg: t.Health) -> None:
        service = self.service
        if (msg.name != service.name or msg.status == "stopping" or self.refusal is not None
                or (msg.host, msg.pid) == (HOSTNAME, os.getpid())
                or msg.header.system_id != service.profile.system_id):
            return
        sender = self.transport.last_sender
        if sender and sender == self.transport.sender:
            return
        if self._probing:   # it runs and this one has not started: this one gives way
            self._found.append((msg.service_type, msg.pid, msg.host))
            return
        if not service.running:
            return          # stopping anyway
        other = health_instance(msg, sender)
        if other > self.me:
            return          # the other is the newer: it stops (it hears this one's Health)
        self.refusal = duplicate_line(service.name, msg.service_type, msg.pid, msg.host, after_start=True)
        service.logger.error("%s", self.refusal)
        service.stop()


def duplicate_line(name: str, kind: str, pid: int, host: str, *, after_start: bool = False) -> str:
    """The one line a duplicate logs before it exits :data:`DUPLICATE_EXIT`."""
    when = (", heard after this one started (of the two, the one started later stops: this one)" if after_start
            else "")
    return (f"another '{name}' ({kind}) already runs on this bus: pid {pid} on host {host}{when}; stop it first "
            f"('u2sa stop {name}'), or give this one another name or another lcm_url (u2sa sim and the tests pick "
            "a private port)")
