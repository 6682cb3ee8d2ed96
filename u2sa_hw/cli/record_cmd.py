"""``u2sa record`` and ``u2sa log info|echo|recover``: MCAP logs of the bus."""

from __future__ import annotations

import argparse
import json
import re
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

from u2sa_hw.cli.common import add_vehicle_option, profile_from
from u2sa_hw.recording.mcap_log import BUS_METADATA, SIGNERS_METADATA

RECORD_HELP = """\
Record the bus into an MCAP log until Ctrl-C (or --duration). The LCM bytes of every
verified packet are stored (without the signature trailer: the log replays with any
key), each with its signer (an MCAP channel per channel and signer); packets dropped as
unsigned, forged, replayed or foreign are counted in the log (u2sa log info), with each
type's .lcm definition as its schema, plus the vehicle profile and
service configs, so the log says everything about the run. Chunks are closed every
second: a kill or power cut loses at most the last second (u2sa log recover repairs it).
Below --min-free-mb of free disk space in the log's directory the recording stops, the
file is finished and the command exits 1 saying so. A message that finds the queue to
the disk full is dropped and counted ("dropped" in the final line), never waited for.
See docs/recording.md.
"""


def register(sub: Any) -> None:
    """Add ``record`` and ``log``."""
    p = sub.add_parser("record", help="record the bus to an MCAP file", description=RECORD_HELP,
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       epilog="examples:\n  u2sa record -o run1.mcap --duration 60\n"
                       "  u2sa record --exclude 'RAW\\..*'          (everything but raw device I/O)")
    p.add_argument("-o", "--output", metavar="FILE", help="log file (default: u2sa-<date>-<time>.mcap here)")
    p.add_argument("--include", default=".*", metavar="RE", help="record channels fully matching RE (default all)")
    p.add_argument("--exclude", default="", metavar="RE", help="skip channels fully matching RE")
    p.add_argument("--duration", type=float, default=0.0, metavar="S", help="stop after S seconds")
    p.add_argument("--compression", choices=["zstd", "lz4", "none"], default="zstd",
                   help="chunk compression (default zstd)")
    p.add_argument("--rotate-size-mb", type=float, default=0.0, metavar="MB",
                   help="start a new file past MB (names: <name>-YYYYmmdd-HHMMSS.mcap)")
    p.add_argument("--rotate-duration", type=float, default=0.0, metavar="S", help="start a new file every S seconds")
    p.add_argument("--min-free-mb", type=float, default=50.0, metavar="MB",
                   help="stop (and finish the file) below MB of free disk (default 50)")
    p.add_argument("--queue-size", type=int, default=20000, metavar="N",
                   help="messages buffered between the bus and the disk; beyond, drops are counted (default 20000)")
    add_vehicle_option(p)
    p.set_defaults(func=cmd_record)

    lp = sub.add_parser("log", help="inspect, print, repair and export MCAP logs",
                        description="Work with MCAP logs written by u2sa record or the recorder service.")
    lsub = lp.add_subparsers(dest="log_command", metavar="ACTION", required=True)
    ip = lsub.add_parser("info", help="duration, channels, types, counts, rates, devices, vehicle",
                         description="Summarise a log: vehicle, duration, whether it is complete (a killed "
                         "recorder leaves it incomplete: u2sa log recover), devices with raw I/O, attachments, "
                         "and per channel its type, message count and rate.")
    ip.add_argument("file", help="an MCAP log (complete or truncated)")
    ip.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    ip.set_defaults(func=cmd_info)
    ep = lsub.add_parser("echo", help="print the decoded messages of a channel",
                         description="Print the messages of the channels fully matching CHANNEL, decoded from "
                         "their LCM bytes, in log order.")
    ep.add_argument("file", help="an MCAP log (complete or truncated)")
    ep.add_argument("channel", help="channel name or regex (RAW\\..*)")
    ep.add_argument("--json", action="store_true", help="one JSON object per line")
    ep.add_argument("--count", type=int, default=0, metavar="N", help="stop after N messages")
    ep.set_defaults(func=cmd_echo)
    rp = lsub.add_parser("recover", help="rewrite a truncated log (killed recorder) as a valid indexed one")
    rp.add_argument("file", help="the truncated (or complete) log")
    rp.add_argument("-o", "--output", metavar="FILE", help="output (default: <file>.recovered.mcap)")
    rp.set_defaults(func=cmd_recover)
    xp = lsub.add_parser("export", help="write a copy Foxglove can open (map, 3D scene, health, logs, every channel)",
                         description="Foxglove cannot decode LCM: this writes every message as JSON with a JSON "
                         "schema per (channel, type), plus the well-known messages of u2sa foxglove's live view: "
                         "foxglove.LocationFix (map), FrameTransform/PoseInFrame and SceneUpdate (3D), the "
                         "health table and the service log lines (foxglove.Log). See docs/foxglove.md.")
    xp.add_argument("file", help="an MCAP log written by u2sa")
    xp.add_argument("--foxglove", required=True, metavar="OUT.mcap", help="output file")
    xp.add_argument("--logs", metavar="DIR", help="the run's service log directory for /log (default: a logs/ "
                    "directory beside the log's directory, as u2sa sim writes, if there is one)")
    xp.set_defaults(func=cmd_export)
    pp = lsub.add_parser("plot", help="PNG of the run: map with waypoints, obstacles and the geofence, heading, "
                        "speed, commands, RC mode and failsafes")
    pp.add_argument("file", help="an MCAP log written by u2sa")
    pp.add_argument("-o", "--output", metavar="PNG", help="output (default: <file>.png)")
    pp.add_argument("--channel", default="STATE_ESTIMATE", help="state channel to plot (default STATE_ESTIMATE)")
    pp.set_defaults(func=cmd_plot)


def cmd_record(args: Any) -> int:
    """Record until Ctrl-C or --duration."""
    from u2sa_hw.cli import CliError
    from u2sa_hw.recording.mcap_log import McapLogWriter
    from u2sa_hw.services.recorder.capture import BusCapture
    from u2sa_hw.services.recorder.service import run_info
    from u2sa_hw.bus.transport import Transport
    from u2sa_hw.bus.lcm_open import TransportError

    profile = profile_from(args)
    out = Path(args.output) if args.output else None
    try:
        transport = Transport(profile.lcm_url, name="u2sa-record", security=profile.bus_security,
                              key_file=profile.bus_key, interface=profile.bus_interface,
                              system_id=profile.system_id if profile.path else None)
    except TransportError as exc:
        raise CliError(str(exc)) from None
    if args.queue_size < 1 or args.min_free_mb < 0:
        raise CliError("--queue-size must be at least 1 and --min-free-mb at least 0", 2)
    writer = McapLogWriter(out.parent if out else Path("."), compression=args.compression,
                           rotate_size_mb=args.rotate_size_mb, rotate_duration_s=args.rotate_duration,
                           run=run_info(profile, transport.url), path=out)
    try:
        capture = BusCapture(transport, writer, include=args.include, exclude=args.exclude,
                             min_free_mb=args.min_free_mb, queue_size=args.queue_size)
    except ValueError as exc:
        raise CliError(str(exc), 2) from None
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    capture.start()
    transport.start()
    start = time.monotonic()
    tty = sys.stderr.isatty()
    try:
        while not stop.wait(0.5):
            elapsed = time.monotonic() - start
            s = capture.stats
            line = f"recording {elapsed:6.1f} s  {s.written} messages  {len(s.per_channel)} channels  {s.dropped} dropped"
            if tty:
                print("\r" + line, end="", file=sys.stderr, flush=True)
            if s.stopped_reason or (args.duration and elapsed >= args.duration):
                break
    finally:
        capture.stop()
        transport.stop()
    if tty:
        print(file=sys.stderr)
    s = capture.stats
    files = ", ".join(str(p) for p in writer.files) or "nothing (no traffic)"
    print(f"wrote {s.written} messages on {len(s.per_channel)} channels to {files}; {s.dropped} dropped")
    if s.stopped_reason:
        raise CliError(s.stopped_reason)
    return 0


def _open(path: str) -> Any:
    from u2sa_hw.cli import CliError
    from u2sa_hw.recording.log_reader import LogError, LogFile

    try:
        return LogFile(path)
    except LogError as exc:
        raise CliError(str(exc)) from None


def cmd_info(args: Any) -> int:
    """``u2sa log info``."""
    log = _open(args.file)
    summary = log.scan()
    c = summary.contents
    meta = c.metadata.get("u2sa", {})
    bus = bus_summary(meta, c.metadata.get(BUS_METADATA))
    bus["signers"] = c.metadata.get(SIGNERS_METADATA, {})
    bus["pilot"] = pilot_summary(meta, c)
    rows = [{"channel": s.channel, "type": s.type_name, "count": s.count,
             "rate_hz": s.count / summary.duration_s if summary.duration_s else 0.0} for s in summary.channels]
    if args.json:
        print(json.dumps({"file": str(log.path), "complete": c.complete, "problem": c.problem,
                          "duration_s": summary.duration_s, "messages": summary.messages, "vehicle": meta,
                          "bus": bus,
                          "devices": summary.devices, "attachments": sorted(c.attachments), "channels": rows},
                         indent=2))
        return 0
    print(f"file:        {log.path}")
    print(f"vehicle:     {meta.get('vehicle', '?')} (system id {meta.get('system_id', '?')}) on "
          f"{meta.get('host', '?')}, started {meta.get('started', '?')}")
    print(f"duration:    {summary.duration_s:.1f} s, {summary.messages} messages")
    print(f"bus:         {bus['text']}")
    print(f"pilot:       {bus['pilot']['text']}")
    if bus["signers"]:
        print(f"signers:     {len(bus['signers'])} (" + "; ".join(f"{sig} {who or '?'}" for sig, who in
                                                        bus["signers"].items()) + ")")
    print(f"state:       {'complete' if c.complete else 'NOT COMPLETE: ' + (c.problem or 'no summary')}"
          + ("" if c.complete else f" (u2sa log recover {log.path})"))
    print(f"devices:     {', '.join(summary.devices) or 'none (no RAW.* channels)'}")
    print(f"attachments: {', '.join(sorted(c.attachments)) or 'none'}")
    print(f"{'CHANNEL':28} {'TYPE':22} {'COUNT':>8} {'RATE Hz':>9}")
    for r in rows:
        print(f"{r['channel']:28} {r['type']:22} {r['count']:>8} {r['rate_hz']:9.1f}")
    return 0


def bus_summary(meta: dict[str, str], record: dict[str, str] | None) -> dict[str, Any]:
    """Whether the recorded bus was signed, and the packets the recorder dropped, from the log's metadata."""
    security = (record or {}).get("security") or meta.get("bus_security") or ""
    dropped = {why: int((record or {}).get(why, "0") or 0) for why in ("unsigned", "forged", "replayed", "foreign")}
    if not security:
        text = "not recorded (a log from before the bus was signed)"
    elif security == "open":
        text = "open: nothing was verified (bus_security = \"open\")"
    else:
        key = (record or {}).get("key_id") or meta.get("bus_key_id", "?")
        counts = ", ".join(f"{why} {n}" for why, n in dropped.items())
        text = (f"signed (key {key}); the log holds verified payloads; dropped {sum(dropped.values())} packets "
                f"({counts})" if record else f"signed (key {key}); drop counts not written (log cut short)")
        if record and record.get("by_channel"):
            text += f": {record['by_channel']}"
    return {"security": security or None, "dropped": dropped, "by_channel": (record or {}).get("by_channel", ""),
            "text": text}


def pilot_summary(meta: dict[str, str], contents: Any) -> dict[str, Any]:
    """The pilot's recorded public key and the channels whose messages keep its signature trailer."""
    from u2sa_hw.recording.log_reader import trailer_length
    from u2sa_hw.recording.pilot_check import PILOT_KEY, PILOT_KEY_ID, recorded_verifier

    kept = sorted({ch.topic for ch in contents.channels.values() if trailer_length(ch)})
    key_id = meta.get(PILOT_KEY_ID, "")
    if meta.get(PILOT_KEY):
        text = f"key {key_id or '?'}; " + (f"messages of {', '.join(kept)} kept with their signatures "
                                            "(u2sa replay checks them)" if kept else
                                            "no pilot message recorded with its signature")
    else:
        text = recorded_verifier({"u2sa": meta})[1]
    return {"key": meta.get(PILOT_KEY, "") or None, "key_id": key_id or None, "signed_channels": kept, "text": text}


def cmd_echo(args: Any) -> int:
    """``u2sa log echo``: decoded LCM messages; JSON-encoded channels of other tools as their JSON;
    anything else named with its encoding and size. A channel pattern that matches nothing lists
    the log's channels and exits 1; so does a log in which no matching message could be decoded."""
    from u2sa_hw.channels import base_type
    from u2sa_hw.cli import CliError
    from u2sa_hw.messages import REGISTRY, MalformedMessage, enumerate_fields, to_dict

    log = _open(args.file)
    try:
        re.compile(args.channel or "")
    except re.error as exc:
        raise CliError(f"{args.channel!r} is not a valid regular expression ({exc}); "
                       "quote it, e.g. 'STATE_.*'") from None
    n = undecodable = 0
    encodings: dict[str, str] = {}
    for msg in log.messages(args.channel):
        if msg.channel not in encodings:   # channels are read as the file goes
            encodings = {ch.topic: ch.message_encoding for ch in log.contents.channels.values()}
        encoding = encodings.get(msg.channel, "lcm")
        if encoding.lower() not in ("lcm", ""):
            print_foreign(msg, encoding, json_out=args.json)
        else:
            try:
                decoded, _ = REGISTRY.decode(msg.data, base_type(msg.channel))
            except MalformedMessage as exc:
                print(f"{msg.channel} @{msg.log_time_ns}: undecodable as LCM ({exc})", file=sys.stderr)
                undecodable += 1
                continue
            if args.json:
                print(json.dumps({"channel": msg.channel, "log_time_ns": msg.log_time_ns, **to_dict(decoded)}))
            else:
                print(f"--- {msg.channel} {type(decoded).__name__} @ {msg.log_time_ns / 1e9:.6f}")
                for name, value in enumerate_fields(decoded):
                    print(f"  {name}: {value}")
        n += 1
        if args.count and n >= args.count:
            break
    if log.contents.problem:
        print(f"u2sa: warning: {log.path}: {log.contents.problem}", file=sys.stderr)
    if n == 0 and args.channel:
        topics = sorted({ch.topic for ch in log.contents.channels.values()})
        if not any(re.fullmatch(args.channel, t) for t in topics):
            raise CliError(f"{log.path}: no channel matches {args.channel!r}; the log's channels: "
                           f"{', '.join(topics) or 'none'}")
    if n == 0 and undecodable:
        raise CliError(f"{log.path}: none of the {undecodable} messages on {args.channel} could be decoded as LCM "
                       "(a type this build does not know, or bytes that are not LCM)")
    return 0


def print_foreign(msg: Any, encoding: str, *, json_out: bool) -> None:
    """A message of another tool's encoding: JSON printed as JSON, anything else by encoding and size."""
    if encoding.lower() == "json":
        try:
            body = json.loads(msg.data)
        except (UnicodeDecodeError, ValueError) as exc:
            print(f"{msg.channel} @{msg.log_time_ns}: invalid JSON ({exc})", file=sys.stderr)
            return
        if json_out:
            print(json.dumps({"channel": msg.channel, "log_time_ns": msg.log_time_ns, "json": body}))
        else:
            print(f"--- {msg.channel} {msg.type_name} (json) @ {msg.log_time_ns / 1e9:.6f}")
            print(f"  {json.dumps(body)}")
        return
    text = f"{len(msg.data)} bytes of {encoding} (u2sa decodes LCM and JSON only)"
    if json_out:
        print(json.dumps({"channel": msg.channel, "log_time_ns": msg.log_time_ns, "encoding": encoding,
                          "bytes": len(msg.data), "hex": msg.data[:64].hex()}))
    else:
        print(f"--- {msg.channel} {msg.type_name} @ {msg.log_time_ns / 1e9:.6f}: {text}")


def cmd_recover(args: Any) -> int:
    """``u2sa log recover``: exit 1 when nothing could be recovered."""
    from u2sa_hw.cli import CliError
    from u2sa_hw.recording.log_reader import LogError, recover

    src = Path(args.file)
    dst = Path(args.output) if args.output else src.with_suffix(".recovered.mcap")
    try:
        count, problem = recover(src, dst)
    except LogError as exc:
        raise CliError(str(exc)) from None
    print(f"wrote {count} messages to {dst}" + (f" ({src}: {problem})" if problem else f" ({src} was complete)"))
    if count == 0:
        print(f"u2sa: no message could be recovered from {src}; {dst} holds only its metadata and attachments",
              file=sys.stderr)
        return 1
    return 0


def cmd_export(args: Any) -> int:
    """``u2sa log export --foxglove``: exit 1, writing nothing, when nothing in the log could be exported."""
    import os
    import tempfile

    from u2sa_hw.cli import CliError
    from u2sa_hw.recording.foxglove import export_foxglove

    _open(args.file)  # clear error for a missing or foreign file
    log_dir = Path(args.logs) if args.logs else Path(args.file).resolve().parent.parent / "logs"
    if args.logs and not log_dir.is_dir():
        raise CliError(f"{log_dir}: no such directory (--logs names the run's service log directory)")
    out = Path(args.foxglove)
    if not out.parent.is_dir():
        raise CliError(f"{out}: the directory {out.parent} does not exist")
    fd, tmp_name = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".part", dir=out.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:   # written beside OUT and renamed when there is something in it: a failure never touches OUT
        report = export_foxglove(args.file, tmp, log_dir=log_dir if log_dir.is_dir() else None)
        if not any(n for topic, n in report.counts.items() if topic != "/log"):   # service log lines alone: no
            raise CliError(f"{args.file}: nothing to export: {_unexported(report)}")
        umask = os.umask(0)
        os.umask(umask)
        tmp.chmod(0o666 & ~umask)   # a new file's usual mode, not mkstemp's 0600
        tmp.replace(out)
    finally:
        tmp.unlink(missing_ok=True)
    total = sum(report.counts.values())
    fixes = sum(n for c, n in report.counts.items() if c.startswith("/location/"))
    print(f"wrote {total} JSON messages on {len(report.counts)} topics to {out} ({fixes} location fixes, "
          f"{report.counts.get('/log', 0)} log lines" + (f" from {log_dir}" if log_dir.is_dir() else "") + ")")
    for note in report.notes:
        print(f"note: {note}")
    if report.undecodable or report.skipped:
        print(f"note: not exported: {_unexported(report)}")
    return 0


def _unexported(report: Any) -> str:
    """What an export left out and why, in one line: LCM it could not decode, encodings it cannot convert."""
    parts = []
    if report.undecodable:
        parts.append(f"{report.undecodable} LCM messages could not be decoded (a type this build does not know, "
                     "or damaged bytes)")
    for encoding in sorted({e for e, _topic in report.skipped}):
        where = {topic: n for (e, topic), n in sorted(report.skipped.items()) if e == encoding}
        parts.append(f"{sum(where.values())} {encoding} messages (" + ", ".join(f"{n} on {topic}" for topic, n in
                     where.items()) + f"): u2sa turns LCM into JSON and copies JSON, it cannot convert {encoding} "
                     "(Foxglove opens such a file directly)")
    return "; ".join(parts) or "the log holds no messages (u2sa log info shows what it holds)"


def cmd_plot(args: Any) -> int:
    """``u2sa log plot``."""
    from u2sa_hw.cli import CliError
    from u2sa_hw.recording.plot import plot_log

    _open(args.file)
    out = Path(args.output) if args.output else Path(args.file).with_suffix(".png")
    try:
        counts = plot_log(args.file, out, channel=args.channel)
    except ModuleNotFoundError as exc:
        raise CliError(f"plotting needs {exc.name}: pip install 'u2sa-hw[sim]'") from None
    if not any(counts.values()):
        raise CliError(f"{args.file}: nothing to plot (no {args.channel} positions or actuator commands)")
    fence = f", {counts['fence_areas']} geofence areas" if counts["fence_areas"] else ""
    print(f"wrote {out} ({counts['track']} track points, {counts['waypoints']} waypoints, {counts['obstacles']} "
          f"obstacles{fence}, {counts['commands']} commands, {counts['failsafes']} failsafes)")
    return 0
