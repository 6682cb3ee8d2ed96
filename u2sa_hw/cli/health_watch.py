"""``u2sa health --watch``: a live table of every service's state, reason, rates and restarts.

The table is built from the bus as Foxglove's ``/health`` topic is
(``u2sa_hw.foxglove.health_table``): the HSM's ``SystemHealth`` for states, restarts and
reasons, each service's own ``Health`` for status, message rates, CPU and drops. On a
terminal it is redrawn in place every ``--interval``; when stdout is not a terminal (a
pipe, a file, journald) each refresh is a block of plain lines with a time header and no
escape codes. Without an HSM it still lists every service heard from itself.
"""

from __future__ import annotations

import shutil
import signal
import sys
import threading
import time
from typing import Any, TextIO

from u2sa_hw.cli.common import bus_client

CLEAR = "\x1b[H\x1b[J"   # cursor home, clear to the end of the screen
COLUMNS = (("SERVICE", 18, "<"), ("STATE", 10, "<"), ("STATUS", 9, "<"), ("RESTARTS", 8, ">"), ("RX/s", 7, ">"),
           ("TX/s", 7, ">"), ("CPU%", 5, ">"), ("DROPS", 6, ">"))


def add_options(parser: Any) -> None:
    """The ``--watch`` options of ``u2sa health``."""
    parser.add_argument("--watch", action="store_true",
                        help="a live table (state, reason, rates, restarts) refreshed until Ctrl-C; plain text "
                             "blocks when stdout is not a terminal")
    parser.add_argument("--interval", type=float, default=1.0, metavar="S", help="--watch refresh period (default 1)")
    parser.add_argument("--count", type=int, default=0, metavar="N", help="--watch: stop after N refreshes")


def _cell(value: Any) -> str:
    if value is None:
        return "-"
    return f"{value:.1f}" if isinstance(value, float) else str(value)


def render(message: dict[str, Any], *, width: int, now: str) -> list[str]:
    """The table's lines for one HealthTable message, the reason column cut to *width*."""
    head = f"{now}  {'FAILSAFE ACTIVE' if message['failsafe'] else 'failsafe off'} -- {message['summary']}"
    fixed = " ".join(f"{name:{align}{w}}" for name, w, align in COLUMNS)
    lines = [head[:width], f"{fixed}  REASON"[:width]]
    keys = ("name", "state", "status", "restarts", "rx_hz", "tx_hz", "cpu_percent", "dropped")
    for row in message["services"]:
        cells = " ".join(f"{_cell(row[k])[:w]:{align}{w}}" for k, (_n, w, align) in zip(keys, COLUMNS))
        room = max(width - len(cells) - 2, 10)
        reason = row["reason"] if len(row["reason"]) <= room else row["reason"][:room - 3] + "..."
        lines.append(f"{cells}  {reason}".rstrip())
    if not message["services"]:
        lines.append("(no service heard yet)")
    return lines


def watch(args: Any, *, out: TextIO | None = None) -> int:
    """Refresh the table until Ctrl-C, SIGTERM or ``--count`` refreshes."""
    from u2sa_hw import channels as ch
    from u2sa_hw import lcmtypes as t
    from u2sa_hw.cli import CliError
    from u2sa_hw.foxglove.health_table import HealthTable

    out = out or sys.stdout
    if args.interval <= 0:
        raise CliError("--interval must be above 0", 2)
    tty = out.isatty()
    table = HealthTable()
    lock = threading.Lock()
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())

    def on_health(_c: str, msg: Any) -> None:
        with lock:
            table.on_health(msg)

    def on_system(_c: str, msg: Any) -> None:
        with lock:
            table.on_system(msg)

    shown = 0
    with bus_client(args) as bus:
        bus.transport.subscribe(ch.HEALTH, t.Health, on_health)
        bus.transport.subscribe(ch.SYSTEM_HEALTH, t.SystemHealth, on_system)
        while not stop.wait(args.interval):
            with lock:
                message = table.message()
            width = shutil.get_terminal_size((120, 24)).columns if tty else 200
            lines = render(message, width=width, now=time.strftime("%H:%M:%S"))
            if tty:
                out.write(CLEAR + "\n".join(lines) + "\n")
            else:
                out.write("\n".join(lines) + "\n\n")
            out.flush()
            shown += 1
            if args.count and shown >= args.count:
                break
    return 0
