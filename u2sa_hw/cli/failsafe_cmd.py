"""``u2sa failsafe``: the operator raises, clears and inspects failsafes.

Failsafes are held per source (u2sa_hw/failsafe.py). This command is the source
``operator``: ``raise`` holds the operator's failsafe, ``clear`` lowers it, and ``clear
--source NAME`` (or ``--all``) lowers another source's, the operator's override. A source
whose condition still holds (the HSM seeing a failed service, a pressed e-stop) raises it
again at its next repeat, within a second, and ``status`` shows that.

``status`` listens for ``--timeout`` seconds: to ``FAILSAFE`` (active failsafes are
re-sent every second by their holders), to the services' health (each actuator, the RC mux,
control and the HSM report the sources they hold) and to ``RC_MODE`` (why autonomy is not
granted).

``raise`` and ``clear`` first listen (up to :data:`SYNC_S`) for one signed packet, which moves
this process's signing clock to the vehicle's: a laptop whose clock is behind would otherwise
send a packet every receiver takes for a replay (receivers accept a raise even then, but not
a clear; docs/security.md). ``raise`` then waits for evidence that the failsafe is held (the
HSM's relay, or a service's health listing ``operator``), sends it again up to
:data:`RAISE_SENDS` times, and exits 1 naming what did not answer when nothing confirms it.
"""

from __future__ import annotations

import argparse
import json
import threading
import time
from typing import Any

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.cli.common import add_vehicle_option, bus_client, no_answer_error
from u2sa_hw.failsafe import ALL_SOURCES, OPERATOR_SOURCE

SYNC_S = 1.5        # how long raise/clear listen for a signed packet to sync the signing clock
RAISE_SENDS = 3     # raise: sends, each followed by up to --timeout s of waiting for evidence

HELP = """\
Raise, clear or show failsafes. Every actuator goes neutral and autonomy drops while any
source holds one; each source clears only its own, and the operator (this command) may
clear any.

  status                     who holds a failsafe now (listens --timeout seconds)
  raise [--reason TEXT]      hold the operator's failsafe: every actuator neutral now
  clear                      lower the operator's failsafe
  clear --source NAME        lower NAME's failsafe (e.g. hsm, an e-stop service); it comes
                             back within a second if NAME's condition still holds
  clear --all                lower every source's failsafe

The HSM (kind "hsm") re-sends the operator's failsafe every second until the operator
clears it, so a service that restarts, or missed the one packet, still hears it; without
an HSM in the profile only the services that heard the raise hold it. See docs/safety.md.

raise confirms: it waits up to --timeout seconds for the HSM's relay or a service's health
listing the operator's failsafe, sends again (3 sends in all), and exits 1 naming what did
not answer if nothing confirmed it. Before sending, raise and clear listen up to 1.5 s for
one signed packet, so a laptop whose clock is behind the vehicle's is heard.
"""


def register(sub: Any) -> None:
    """Add the ``failsafe`` subcommand."""
    p = sub.add_parser("failsafe", help="raise, clear or show failsafes (the operator's override)",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter,
                       epilog="examples:\n  u2sa failsafe raise --reason 'swimmer near the boat'\n"
                       "  u2sa failsafe status\n  u2sa failsafe clear\n  u2sa failsafe clear --source hsm")
    p.add_argument("action", choices=("status", "raise", "clear"), help="what to do (see above)")
    p.add_argument("--reason", default="raised by the operator", help="raise: the reason every service logs")
    who = p.add_mutually_exclusive_group()
    who.add_argument("--source", metavar="NAME", help="clear: the source whose failsafe to lower")
    who.add_argument("--all", action="store_true", help="clear: lower every source's failsafe")
    p.add_argument("--json", action="store_true", help="status: print JSON")
    add_vehicle_option(p)
    p.add_argument("--timeout", type=float, default=1.5, metavar="S",
                   help="status: seconds to listen; raise: seconds to wait for confirmation after each of "
                   "its 3 sends (default 1.5)")
    p.set_defaults(func=cmd_failsafe)


class FailsafeListener:
    """What the bus says about failsafes: active messages by source, holders by service, the RC's view."""

    def __init__(self, bus: Any) -> None:
        self.active: dict[str, str] = {}          # source -> reason, from FAILSAFE
        self.held_by_service: dict[str, str] = {}  # service -> "src1,src2" from its health
        self.rc_blocked: str | None = None
        self._lock = threading.Lock()
        self._bus = bus
        self._subs = [bus.transport.subscribe(ch.FAILSAFE, t.Failsafe, self._on_failsafe),
                      bus.transport.subscribe(ch.HEALTH, t.Health, self._on_health),
                      bus.transport.subscribe(ch.RC_MODE, t.RcMode, self._on_rc)]

    def close(self) -> None:
        """Stop listening."""
        for sub in self._subs:
            self._bus.transport.unsubscribe(sub)

    def _on_failsafe(self, _c: str, msg: t.Failsafe) -> None:
        with self._lock:
            if msg.active:
                self.active[msg.header.source or "?"] = msg.reason
            else:
                self.active.pop(msg.header.source or "?", None)

    def _on_health(self, _c: str, msg: t.Health) -> None:
        details = {kv.key: kv.value for kv in msg.details}
        if "failsafe_sources" in details:
            with self._lock:
                self.held_by_service[msg.name or msg.header.source] = details["failsafe_sources"]

    def _on_rc(self, _c: str, msg: t.RcMode) -> None:
        with self._lock:
            self.rc_blocked = msg.blocked_by

    def snapshot(self) -> dict[str, Any]:
        """JSON-ready: ``active`` (source -> reason), ``held_by`` (service -> sources), ``rc_blocked_by``."""
        with self._lock:
            return {"active": dict(self.active),
                    "held_by": {s: [x for x in v.split(",") if x] for s, v in sorted(self.held_by_service.items())},
                    "rc_blocked_by": self.rc_blocked}


def status_lines(snap: dict[str, Any]) -> list[str]:
    """The status for people."""
    holders = set(snap["active"]) | {src for srcs in snap["held_by"].values() for src in srcs}
    lines = [f"failsafe HELD by {', '.join(sorted(holders))}" if holders else "no failsafe held"]
    for source, reason in sorted(snap["active"].items()):
        lines.append(f"  {source}: {reason or 'no reason given'}")
    for service, sources in snap["held_by"].items():
        lines.append(f"  {service} holds: {', '.join(sources) or 'none'}")
    if snap["rc_blocked_by"] is not None:
        lines.append(f"  autonomy: {snap['rc_blocked_by'] or 'granted'}")
    if not snap["held_by"] and snap["rc_blocked_by"] is None:
        lines.append("  (no service reported within the timeout; u2sa services lists the live ones)")
    return lines


def cmd_failsafe(args: Any) -> int:
    """Run ``u2sa failsafe ACTION``."""
    from u2sa_hw.cli import CliError

    if args.timeout <= 0:
        raise CliError("failsafe: --timeout must be > 0 seconds", 2)
    if args.action != "clear" and (args.source or args.all):
        raise CliError(f"failsafe {args.action}: --source and --all go with clear", 2)
    with bus_client(args) as bus:
        if args.action == "status":
            listener = FailsafeListener(bus)
            try:
                time.sleep(args.timeout)  # a listening window: holders re-send and report every second
                snap = listener.snapshot()
            finally:
                listener.close()
            print(json.dumps(snap, indent=2) if args.json else "\n".join(status_lines(snap)))
            return 1 if snap["active"] or any(snap["held_by"].values()) else 0
        synced = bus.sync_clock(timeout=SYNC_S)
        msg = t.Failsafe()
        msg.header.source = OPERATOR_SOURCE
        if args.action == "raise":
            msg.active, msg.reason = True, args.reason
            print(raise_confirmed(bus, msg, args, synced=synced))
            return 0
        msg.active, msg.reason = False, "cleared by the operator"
        msg.service = ALL_SOURCES if args.all else (args.source or "")
        if not bus.publish(ch.FAILSAFE, msg):
            raise CliError(f"failsafe {args.action}: could not publish on {bus.transport.url}")
        # the HSM relays the operator's failsafe every second: a relay already in flight when the
        # first clear lands would raise it again, so the clear goes out once more after it
        time.sleep(0.3)
        bus.publish(ch.FAILSAFE, msg)
    target = "every source's" if args.all else (f"{args.source}'s" if args.source else "the operator's")
    print(f"cleared {target} failsafe (u2sa failsafe status shows who still holds one)")
    return 0


class RaiseEvidence:
    """Listens for proof that the operator's failsafe is held: the HSM's relay or a holder's health."""

    def __init__(self, bus: Any) -> None:
        self.confirmed_by: list[str] = []         # e.g. "the HSM's relay", "drive's health"
        self.not_holding: set[str] = set()        # holders whose health did not list the operator
        self.event = threading.Event()
        self._bus, self._own = bus, bus.transport.sender
        self._subs = [bus.transport.subscribe(ch.FAILSAFE, t.Failsafe, self._on_failsafe),
                      bus.transport.subscribe(ch.HEALTH, t.Health, self._on_health)]

    def close(self) -> None:
        """Stop listening."""
        for sub in self._subs:
            self._bus.transport.unsubscribe(sub)

    def _on_failsafe(self, _c: str, msg: t.Failsafe) -> None:
        # our own packet loops back to us: it proves nothing; another sender's copy is the HSM's relay
        if msg.active and msg.header.source == OPERATOR_SOURCE and self._bus.transport.last_sender != self._own:
            self._confirm("the HSM's relay on FAILSAFE")

    def _on_health(self, _c: str, msg: t.Health) -> None:
        details = {kv.key: kv.value for kv in msg.details}
        if "failsafe_sources" not in details:
            return
        name = msg.name or msg.header.source
        if OPERATOR_SOURCE in details["failsafe_sources"].split(","):
            self.not_holding.discard(name)
            self._confirm(f"{name}'s health")
        elif not self.event.is_set():
            self.not_holding.add(name)

    def _confirm(self, what: str) -> None:
        if what not in self.confirmed_by:
            self.confirmed_by.append(what)
        self.event.set()


def raise_confirmed(bus: Any, msg: t.Failsafe, args: Any, *, synced: bool) -> str:
    """Send the raise until something confirms it is held; the line to print, or CliError naming who did not answer."""
    from u2sa_hw.cli import CliError

    evidence = RaiseEvidence(bus)
    try:
        for _ in range(RAISE_SENDS):
            if not bus.publish(ch.FAILSAFE, msg):
                raise CliError(f"failsafe raise: could not publish on {bus.transport.url}: {bus.transport.last_error}")
            if evidence.event.wait(args.timeout):
                break
    finally:
        evidence.close()
    if evidence.event.is_set():
        return (f"failsafe raised by the operator: every actuator neutral, autonomy off "
                f"(confirmed by {', '.join(evidence.confirmed_by)})")
    waited = f"{RAISE_SENDS} sends over {RAISE_SENDS * args.timeout:g} s"
    text = (f"failsafe raise NOT confirmed after {waited}: the HSM did not relay it on FAILSAFE and no actuator, "
            "RC mux or control service reported holding it in its health")
    if evidence.not_holding:
        raise CliError(f"{text} ({', '.join(sorted(evidence.not_holding))} answered without it: their bus drops "
                       "show why, u2sa services); treat the vehicle as NOT safe")
    if not synced:
        raise no_answer_error(args, f"{text}, and nothing signed with this bus key was heard "
                              f"(no service running, another key or LCM URL); treat the vehicle as NOT safe")
    raise CliError(f"{text} (services are on the bus, but none holds failsafes: is the HSM or an actuator "
                   "running?); treat the vehicle as NOT safe")
