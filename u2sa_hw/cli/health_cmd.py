"""``u2sa health``: the HSM's view of the system (its SystemHealth on ``U2SA_SYSTEM_HEALTH``)."""

from __future__ import annotations

import json
import sys
import threading
import time
from typing import Any

from u2sa_hw.cli.common import add_vehicle_option, bus_client

HELP = """\
Wait for the HSM's next system health message and show each service's state
(ok, degraded, stale, missing, restarting, stopped, failed, starting), its restarts,
heartbeat age and data age, and for every service not ok the reason in words (the silent
sensor of an estimator, the missing device of a driver and its fix; for an ok one its last
error), with the failsafe state, and whether the RC mux
grants autonomy (if not, why: the failed pre-arm check, the failsafe, the mode), and one
line per service that accepted failsafe raises outside the replay window or naming another
system id (a raise always fails safe): how many, the last one's age and sender. Exits 1
when no HSM answers within --timeout (is a service of kind "hsm" in the profile and running?).
"""


def register(sub: Any) -> None:
    """Add the ``health`` subcommand."""
    p = sub.add_parser("health", help="the HSM's view: each service's state, restarts, last error, data age",
                       description=HELP)
    add_vehicle_option(p)
    p.add_argument("--json", action="store_true",
                   help="print one JSON object (failsafe, summary, services, autonomy, raises_accepted)")
    p.add_argument("--timeout", type=float, default=3.0, metavar="S",
                   help="seconds to wait for the HSM (default 3; it publishes every second)")
    from u2sa_hw.cli.health_watch import add_options

    add_options(p)   # --watch: a live table (u2sa_hw/cli/health_watch.py)
    p.set_defaults(func=cmd_health)


def _age(seconds: float) -> str:
    return "-" if seconds < 0 else f"{seconds:.1f}s"


def as_dict(msg: Any) -> dict[str, Any]:
    """A SystemHealth message as plain values."""
    return {
        "source": msg.header.source,
        "failsafe": msg.failsafe,
        "summary": msg.summary,
        "services": [{"name": s.name, "state": s.state, "restarts": s.restarts, "last_error": s.last_error,
                      "heartbeat_age_s": None if s.heartbeat_age_s < 0 else round(s.heartbeat_age_s, 3),
                      "data_age_s": None if s.data_age_s < 0 else round(s.data_age_s, 3)} for s in msg.services],
    }


def cmd_health(args: Any) -> int:
    """Print the next SystemHealth; exit 1 naming the problem when no HSM answers."""
    if args.watch:
        from u2sa_hw.cli.health_watch import watch

        return watch(args)
    from u2sa_hw import channels as ch
    from u2sa_hw import lcmtypes as t
    from u2sa_hw.cli import CliError
    from u2sa_hw.cli.bus_cmds import bad_signature_total, rejected_counts, rejected_total

    got: list[Any] = []
    arrived = threading.Event()

    def on_message(_c: str, msg: Any) -> None:
        if not arrived.is_set():
            got.append(msg)
            arrived.set()

    health: dict[str, Any] = {}
    heard_at: dict[str, float] = {}   # when each service's newest Health arrived (monotonic)

    def on_health(_c: str, msg: Any) -> None:
        health[msg.name] = msg
        heard_at[msg.name] = time.monotonic()

    with bus_client(args) as bus:
        # Each service's own Health says its bus (signed/open), the packets it dropped, the raises it let through.
        bus.transport.subscribe(ch.HEALTH, t.Health, on_health)
        bus.transport.subscribe(ch.SYSTEM_HEALTH, t.SystemHealth, on_message)
        arrived.wait(max(0.0, args.timeout))
        if got:
            # the HSM's own Health too: it is not among the services it watches, and it says the raises it let through
            names = {s.name for s in got[0].services} | ({got[0].header.source} if got[0].header.source else set())
            deadline = time.monotonic() + min(1.5, max(0.0, args.timeout))
            while not names <= set(health) and time.monotonic() < deadline:
                arrived.wait(0.05)   # polls the callbacks' dict; SystemHealth already arrived
        url = bus.transport.url
        own_drops = bus.transport.rejected()
    if own_drops:
        from u2sa_hw.service.bus_handlers import rejected_text

        print(f"u2sa: dropped while listening: {rejected_text(own_drops)}", file=sys.stderr)
    if not got:
        raise CliError(f"no HSM answered: nothing on {ch.SYSTEM_HEALTH} within {args.timeout:g} s on {url} "
                       "(add a service with kind = \"hsm\" to the vehicle profile and start it, "
                       "e.g. 'u2sa run' or 'systemctl start u2sa@hsm')")
    report = as_dict(got[0])
    for s in report["services"]:
        details = {kv.key: kv.value for kv in health[s["name"]].details} if s["name"] in health else {}
        s["bus"] = details.get("bus_security", "?")
        s["rejected_by_channel"] = details.get("bus_rejected", "")
        s["rejected"] = rejected_total(s["rejected_by_channel"])
        s["bad_signature"] = bad_signature_total(s["rejected_by_channel"])
        s["foreign"] = rejected_counts(s["rejected_by_channel"])["foreign"]
        s["denied"] = rejected_counts(s["rejected_by_channel"])["denied"]
        s["reason"] = service_reason(s, health.get(s["name"]))
        s["bus_listen"] = details.get("bus_listen", "")   # a ttl=0 bus heard beyond the board
    report["autonomy"] = autonomy_report(health)
    report["raises_accepted"] = raises_report(health, heard_at)
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    print(f"{'FAILSAFE ACTIVE' if report['failsafe'] else 'failsafe off'} -- {report['summary']} "
          f"(from {report['source'] or 'hsm'})")
    if report["services"]:
        print(f"{'SERVICE':22} {'STATE':11} {'RESTARTS':>8} {'HEARTBEAT':>9} {'DATA AGE':>8} {'BAD SIG':>7} "
              f"{'FOREIGN':>7} {'DENIED':>6}  "
              "REASON / LAST ERROR")
    for s, row in zip(got[0].services, report["services"]):
        print(f"{s.name:22} {s.state:11} {s.restarts:>8} {_age(s.heartbeat_age_s):>9} {_age(s.data_age_s):>8} "
              f"{row['bad_signature']:>7} {row['foreign']:>7} {row['denied']:>6}  "
              f"{'; '.join(x for x in (row['reason'] or s.last_error, row['bus_listen']) if x)}")
    for rc in report["autonomy"]:
        print(autonomy_line(rc))
    if report["raises_accepted"]:
        from u2sa_hw.service.bus_handlers import raise_line

        for entry in report["raises_accepted"]:
            print(raise_line(entry["service"], entry))
    return 0


def raises_report(health: dict[str, Any], heard_at: dict[str, float] | None = None) -> list[dict[str, Any]]:
    """Every service's accepted failsafe raises (its Health's ``bus_raises_accepted``), the HSM's own included.

    One entry per service and kind: service, channel, kind (stale, foreign), count, last_sender and
    last_age_s, the age counted to now when *heard_at* says when that Health arrived.
    """
    from u2sa_hw.service.bus_handlers import parse_raises

    now = time.monotonic()
    out = []
    for name, msg in sorted(health.items()):
        text = next((kv.value for kv in msg.details if kv.key == "bus_raises_accepted"), "")
        if text:
            older = now - heard_at[name] if heard_at and name in heard_at else 0.0
            out.extend({"service": name, **entry} for entry in parse_raises(text, older_by_s=older))
    return out


def service_reason(row: dict[str, Any], health: Any | None) -> str:
    """Why a service the HSM does not call ``ok`` is not, in words ("" for an ok one).

    The HSM's words (its problem, a restart error, what the service said before it died) come
    first, then the service's own latest Health (the silent sensor, the port's error and fix).
    """
    from u2sa_hw.service.health import health_reason, join_reasons

    if row["state"] == "ok":
        return ""
    own = health_reason({kv.key: kv.value for kv in health.details}, health.last_error) if health else ""
    fallback = "no heartbeat yet" if row["state"] == "starting" else "no reason given by the service or the HSM"
    return join_reasons(row["last_error"], own) or fallback


def autonomy_report(health: dict[str, Any]) -> list[dict[str, Any]]:
    """Each RC mux's view of autonomy from its Health: granted, and if not why (the failed pre-arm check)."""
    out = []
    for name, msg in sorted(health.items()):
        details = {kv.key: kv.value for kv in msg.details}
        if "enable_blocked_by" not in details:
            continue
        out.append({"service": name, "granted": details.get("autonomy_enabled") == "True",
                    "blocked_by": details["enable_blocked_by"], "mode": details.get("mode", "?"),
                    "armed": details.get("armed") == "True", "hold": details.get("hold") == "True",
                    "prearm_failed": details.get("prearm_failed", "")})
    return out


def autonomy_from_rc_mode(msg: Any) -> dict[str, Any]:
    """The same view from an ``RcMode`` on ``RC_MODE`` (the mux sends it at 20 Hz and at once on a change)."""
    return {"service": msg.header.source or "RC_MODE", "granted": bool(msg.autonomy_enabled),
            "blocked_by": msg.blocked_by, "mode": msg.mode_name or "?", "armed": bool(msg.armed),
            "hold": bool(msg.hold), "prearm_failed": ""}


def autonomy_line(rc: dict[str, Any]) -> str:
    """``autonomy (rc, RC autonomous, armed): GRANTED``, or ``refused:`` and why; the one-shot's and the watch's.

    Granted with ``hold`` (a pre-arm check was lost with action "hold") keeps the outputs neutral: said so.
    """
    if rc["granted"] and rc.get("hold"):
        # the check that was lost, when the RC mux's health says which (RC_MODE alone does not)
        lost = f"pre-arm check lost: {rc['prearm_failed']}" if rc.get("prearm_failed") else "a pre-arm check was lost"
        state = f"GRANTED, but HOLD: outputs neutral ({lost})"
    elif rc["granted"]:
        state = "GRANTED"
    else:
        state = f"refused: {rc['blocked_by'] or 'unknown'}"
    return f"autonomy ({rc['service']}, RC {rc['mode']}, {'armed' if rc['armed'] else 'not armed'}): {state}"
