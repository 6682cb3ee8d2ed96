"""Bus commands: ``services``, ``topics``, ``echo``, ``pub`` and ``stop``."""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from collections import defaultdict
from typing import Any

from u2sa_hw.cli.common import add_timeout_option, add_vehicle_option, bus_client, no_answer_error

ECHO_TIMEOUT_S = 5.0   # echo: how long to wait for a channel's first message
STOP_SYNC_S = 1.5      # stop: how long to listen for a signed packet before sending (clock sync)


def register(sub: Any) -> None:
    """Add the bus subcommands."""
    p = sub.add_parser("services", help="list live services (discovery)",
                       description="Ask every service on the bus to identify itself and list the answers. "
                       "On stderr, per service: where its bus listens when that is not where it belongs, and "
                       "the failsafe raises it accepted outside the replay window or naming another system id "
                       "(how many, the last one's age and sender).")
    add_vehicle_option(p)
    add_timeout_option(p)
    p.add_argument("--json", action="store_true", help="print a JSON list of objects (name, type, status, "
                   "host, pid, bus, rejected counts, listen, raises_accepted, publishes, subscribes)")
    p.set_defaults(func=cmd_services)

    p = sub.add_parser("topics", help="channels seen on the bus: rate, bandwidth, type",
                       description="Listen to every channel for --duration seconds and summarise the traffic.")
    add_vehicle_option(p)
    p.add_argument("--duration", type=float, default=2.0, metavar="S", help="seconds to listen (default 2)")
    p.add_argument("--json", action="store_true", help="print a JSON list")
    p.set_defaults(func=cmd_topics)

    p = sub.add_parser("echo", help="print messages of a channel",
                       description="Print the decoded messages of CHANNEL (a name or a regex such as 'RAW\\..*').")
    p.add_argument("channel")
    add_vehicle_option(p)
    p.add_argument("--count", type=int, default=0, metavar="N", help="exit after N messages (default: run until Ctrl-C)")
    first = p.add_mutually_exclusive_group()
    first.add_argument("--timeout", type=float, default=ECHO_TIMEOUT_S, metavar="S",
                       help="exit 1, naming the channels heard, if no message arrives within S seconds "
                       f"(default {ECHO_TIMEOUT_S:g}); once one has arrived, run until --count or Ctrl-C")
    first.add_argument("--wait", action="store_true", help="wait for the first message as long as it takes")
    p.add_argument("--json", action="store_true", help="one JSON object per line with the fields by name")
    p.set_defaults(func=cmd_echo)

    p = sub.add_parser("pub", help="publish a message built from FIELD=VALUE pairs",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       description="Publish a TYPE message on CHANNEL. Fields are dotted paths "
                       "(base.actuator_name=left); arrays take comma lists. Presence-vector fields "
                       "(StateInformation x, psi, ...) are marked present.",
                       epilog="example:\n  u2sa pub ACTUATOR_CMD PercentageCommand base.actuator_name=left percentage=20 --rate 10")
    p.add_argument("channel")
    p.add_argument("type", help="message type, e.g. StateInformation, PercentageCommand")
    p.add_argument("fields", nargs="*", metavar="FIELD=VALUE")
    add_vehicle_option(p)
    p.add_argument("--rate", type=float, default=0.0, metavar="HZ", help="publish repeatedly at HZ until Ctrl-C")
    p.add_argument("--count", type=int, default=0, metavar="N", help="with --rate, stop after N messages")
    p.set_defaults(func=cmd_pub)

    p = sub.add_parser("stop", help="stop a service by name, or all services",
                       description="Send the contract's stop command and wait until the service(s) are gone. "
                       "It first listens up to 1.5 s for one signed packet (so a laptop whose clock is behind "
                       "the vehicle's is not taken for a replay), and exits 1 when nothing answered. A NAME no "
                       "service on the bus has fails at once, naming the services that answered (with a "
                       "did-you-mean).")
    p.add_argument("name", nargs="?", help="service to stop")
    p.add_argument("--all", action="store_true", help="stop every service on the bus")
    add_vehicle_option(p)
    add_timeout_option(p, 3.0)
    p.set_defaults(func=cmd_stop)


def _channel_list(infos: Any) -> list[dict[str, str]]:
    return [{"channel": i.channel, "type": i.type_name} for i in infos]


def cmd_services(args: Any) -> int:
    """``u2sa services``: who answers discovery, each one's bus (signed or open) and the packets it dropped."""
    from u2sa_hw import channels as ch
    from u2sa_hw import lcmtypes as t
    from u2sa_hw.service.bus_handlers import parse_raises, raise_line

    health: dict[str, Any] = {}
    heard_at: dict[str, float] = {}   # when each service's newest Health arrived (monotonic)

    def on_health(_c: str, msg: Any) -> None:
        health[msg.name] = msg
        heard_at[msg.name] = time.monotonic()

    with bus_client(args) as bus:
        # Health is what says each service's bus, drops and accepted raises; it comes every health_interval_s.
        bus.transport.subscribe(ch.HEALTH, t.Health, on_health)
        found = bus.discover(timeout=args.timeout)
        own_drops = bus.transport.rejected()
    rows = []
    now = time.monotonic()
    for r in found:
        details = {kv.key: kv.value for kv in health[r.name].details} if r.name in health else {}
        dropped = details.get("bus_rejected", "")
        raises = parse_raises(details.get("bus_raises_accepted", ""), older_by_s=now - heard_at.get(r.name, now))
        rows.append({"name": r.name, "type": r.service_type, "status": r.status, "host": r.host, "pid": r.pid,
                     "bus": details.get("bus_security", "?"), "rejected": rejected_total(dropped),
                     "bad_signature": bad_signature_total(dropped), "foreign": rejected_counts(dropped)["foreign"],
                     "denied": rejected_counts(dropped)["denied"],
                     "rejected_by_channel": dropped, "listen": details.get("bus_listen", ""),
                     "raises_accepted": raises,
                     "publishes": _channel_list(r.publishes),
                     "subscribes": _channel_list(r.subscribes)})
    if args.json:
        print(json.dumps(rows, indent=2))
    else:
        if found:
            print(f"{'NAME':22} {'TYPE':18} {'STATUS':9} {'HOST':14} {'PID':>7} {'BUS':8} {'BAD SIG':>7} "
                  f"{'FOREIGN':>7} {'DENIED':>6}  PUBLISHES")
        for row, r in zip(rows, found):
            pubs = ", ".join(i.channel for i in r.publishes)
            print(f"{r.name:22} {r.service_type:18} {r.status:9} {r.host:14} {r.pid:>7} {row['bus'].split()[0]:8} "
                  f"{row['bad_signature']:>7} {row['foreign']:>7} {row['denied']:>6}  {pubs}")
    for row in rows:   # a ttl=0 bus heard beyond the board: never only a log line of the service's
        if row["listen"]:
            print(f"u2sa: {row['name']}: {row['listen']}", file=sys.stderr)
        for entry in row["raises_accepted"]:   # a stale or foreign failsafe raise let through: who and when
            print(f"u2sa: {raise_line(row['name'], entry)}", file=sys.stderr)
    if own_drops:
        from u2sa_hw.service.bus_handlers import rejected_text

        print(f"u2sa: dropped while listening: {rejected_text(own_drops)} (unsigned: a sender without the key; "
              "forged: another key, e.g. a second stack or vehicle on this port; foreign: another vehicle's "
              "system id under this key; denied: a key whose role may not publish that channel, e.g. the bus key "
              "on RC_MODE; u2sa health shows each service's counts)", file=sys.stderr)
    if not found:
        raise no_answer_error(args, f"no service answered discovery within {args.timeout:g} s "
                              "(are services running, and on the same LCM URL and bus key?)")
    return 0


def rejected_counts(text: str) -> dict[str, int]:
    """Packets per reason (every one of ``bus_auth.REJECTIONS``) in a health ``bus_rejected`` text.

    The text is ``CHANNEL: unsigned 2, forged 1; CHANNEL: foreign 3`` (``service_bus.rejected_text``).
    """
    from u2sa_hw.bus.auth import REJECTIONS

    counts = dict.fromkeys(REJECTIONS, 0)
    for part in text.split(";"):
        for item in part.rpartition(":")[2].split(","):
            why, _, n = item.strip().partition(" ")
            if why in counts and n.isdigit():
                counts[why] += int(n)
    return counts


def rejected_total(text: str) -> int:
    """The number of packets in a health ``bus_rejected`` text, whatever the reason."""
    return sum(rejected_counts(text).values())


def bad_signature_total(text: str) -> int:
    """Packets a health ``bus_rejected`` text counts as unsigned, forged or replayed (not foreign)."""
    counts = rejected_counts(text)
    return counts["unsigned"] + counts["forged"] + counts["replayed"]


def cmd_topics(args: Any) -> int:
    """``u2sa topics``."""
    from u2sa_hw.messages import REGISTRY

    stats: dict[str, list[Any]] = defaultdict(lambda: [0, 0, ""])
    lock = threading.Lock()

    def on_raw(channel: str, data: bytes) -> None:
        cls = REGISTRY.by_fingerprint(data[:8])
        with lock:
            s = stats[channel]
            s[0] += 1
            s[1] += len(data)
            s[2] = cls.__name__ if cls else "?"

    with bus_client(args) as bus:
        bus.transport.subscribe(".*", None, on_raw, raw=True)
        start = time.monotonic()
        time.sleep(args.duration)  # listening window, not synchronisation
        elapsed = time.monotonic() - start
    rows = [{"channel": c, "type": s[2], "messages": s[0], "rate_hz": s[0] / elapsed,
             "bandwidth_Bps": s[1] / elapsed} for c, s in sorted(stats.items())]
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    if not rows:
        print(f"no traffic in {elapsed:.1f} s")
        return 0
    print(f"{'CHANNEL':28} {'TYPE':22} {'RATE Hz':>9} {'BANDWIDTH':>12}")
    for r in rows:
        print(f"{r['channel']:28} {r['type']:22} {r['rate_hz']:9.1f} {_human_rate(r['bandwidth_Bps']):>12}")
    return 0


def _human_rate(bps: float) -> str:
    for unit in ("B/s", "kB/s", "MB/s"):
        if bps < 1000:
            return f"{bps:.1f} {unit}"
        bps /= 1000
    return f"{bps:.1f} GB/s"


def cmd_echo(args: Any) -> int:
    """``u2sa echo CHANNEL``."""
    from u2sa_hw.channels import base_type
    from u2sa_hw.cli import CliError
    from u2sa_hw.messages import REGISTRY, MalformedMessage, enumerate_fields, to_dict

    printed = 0
    done = threading.Event()
    first = threading.Event()
    closed = threading.Event()   # our reader went away (| head -3): printed from the transport's thread
    lock = threading.Lock()
    heard: set[str] = set()

    def on_raw(channel: str, data: bytes) -> None:
        nonlocal printed
        first.set()
        try:
            msg, _ = REGISTRY.decode(data, base_type(channel))
        except MalformedMessage as exc:
            print(f"{channel}: malformed message ({exc})", file=sys.stderr)
            return
        with lock:
            if done.is_set():
                return
            try:
                if args.json:   # an absent presence-vector field is null (u2sa_hw/messages/fields.py)
                    print(json.dumps({"channel": channel, **to_dict(msg)}), flush=True)
                else:           # ... and "-" in text
                    print(f"--- {channel} {type(msg).__name__}")
                    for name, value in enumerate_fields(msg):
                        print(f"  {name}: {value}")
                    sys.stdout.flush()
            except BrokenPipeError:   # the main thread ends the command (SIGPIPE convention)
                closed.set()
                first.set()
                done.set()
                return
            printed += 1
            if args.count and printed >= args.count:
                done.set()

    if not args.wait and args.timeout <= 0:
        raise CliError("echo: --timeout must be > 0 seconds (--wait waits for the first message as long as it "
                       "takes)", 2)
    with bus_client(args) as bus:
        bus.transport.subscribe(args.channel, None, on_raw, raw=True)
        others = bus.transport.subscribe(".*", None, lambda c, _d: heard.add(c), raw=True)
        if not first.wait(None if args.wait else args.timeout):
            heard_now = sorted(heard)
            hint = f"; heard: {', '.join(heard_now)} (--wait to wait for it)" if heard_now else ""
            raise CliError(f"no message on {args.channel} within {args.timeout:g} s{hint}")
        bus.transport.unsubscribe(others)
        done.wait()
    if closed.is_set():
        raise BrokenPipeError("stdout closed")
    return 0


def cmd_pub(args: Any) -> int:
    """``u2sa pub CHANNEL TYPE FIELD=VALUE...``."""
    from u2sa_hw.cli import CliError
    from u2sa_hw.messages import REGISTRY, set_field

    try:
        cls = REGISTRY.by_name(args.type)
    except KeyError as exc:
        raise CliError(str(exc.args[0])) from None
    msg = cls()
    for item in args.fields:
        path, sep, text = item.partition("=")
        if not sep:
            raise CliError(f"'{item}' is not FIELD=VALUE", 2)
        try:
            set_field(msg, path, text)
        except (KeyError, ValueError) as exc:
            raise CliError(str(exc.args[0] if exc.args else exc), 2) from None
    with bus_client(args) as bus:
        if args.rate <= 0:
            if not bus.publish(args.channel, msg):
                raise CliError(f"publishing on {args.channel} failed: {bus.transport.last_error}")
            return 0
        period, sent, next_t = 1.0 / args.rate, 0, time.monotonic()
        while not args.count or sent < args.count:
            bus.publish(args.channel, msg)
            sent += 1
            next_t += period
            time.sleep(max(0.0, next_t - time.monotonic()))
    return 0


def cmd_stop(args: Any) -> int:
    """``u2sa stop NAME`` / ``u2sa stop --all``."""
    from u2sa_hw.cli import CliError

    if not args.all and not args.name:
        raise CliError("stop: give a service NAME or --all", 2)
    with bus_client(args) as bus:
        synced = bus.sync_clock(timeout=STOP_SYNC_S)   # else a laptop behind the vehicle's clock is a "replay"
        if args.all:
            before = bus.discover(timeout=min(1.0, args.timeout))
        else:   # everyone is asked, so a name not on the bus gets a did-you-mean from the names that are
            found, on_bus = bus.find_service(args.name, timeout=min(1.0, args.timeout))
            if found is None and on_bus:
                from u2sa_hw.bus.client import unknown_service_text

                raise CliError(f"{unknown_service_text(args.name, on_bus)}; nothing to stop")
            before = [found] if found is not None else []
        if not before:
            target = "no service" if args.all else f"no service '{args.name}'"
            heard = "" if synced else f", and nothing signed with this bus key was heard in {STOP_SYNC_S:g} s"
            raise no_answer_error(args, f"nothing answered: {target} answered discovery within "
                                  f"{min(1.0, args.timeout):g} s{heard}; nothing to stop")
        names = {r.name for r in before}
        bus.stop(name=args.name or "", all_services=args.all)
        deadline = time.monotonic() + args.timeout
        remaining = names
        while remaining and time.monotonic() < deadline:
            live = {r.name for r in bus.discover(timeout=0.3)}
            remaining = names & live
            if remaining:
                bus.stop(name=args.name or "", all_services=args.all)
    if remaining:
        raise CliError(f"still running after {args.timeout:g} s: {', '.join(sorted(remaining))}")
    print(f"stopped {', '.join(sorted(names))}")
    return 0
