"""``u2sa health --watch``: a live table of every service's state, reason, rates and restarts.

The table is built from the bus as Foxglove's ``/health`` topic is
(``u2sa_hw.foxglove.health_table``): the HSM's ``SystemHealth`` for states, restarts and
reasons, each service's own ``Health`` for status, message rates, CPU and drops. On a
terminal it is redrawn in place every ``--interval``; when stdout is not a terminal (a
pipe, a file, journald) each refresh is a block of plain lines with a time header and no
escape codes. Without an HSM it still lists every service heard from itself.

Below the table, one line per RC mux says who drives, in the words of the one-shot
``u2sa health`` (``autonomy (rc, RC autonomous, armed): GRANTED``, or ``refused:`` and why):
from the mux's ``RC_MODE`` (20 Hz, and at once on a change), or its ``Health`` when that is
newer. A view older than :data:`RC_STALE_S` is marked with its age: a silent mux drives nothing.
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
RC_STALE_S = 1.5   # RC_MODE comes at 20 Hz, the mux's Health every second: older than this, the view is stale
COLUMNS = (("SERVICE", 18, "<"), ("STATE", 10, "<"), ("STATUS", 9, "<"), ("RESTARTS", 8, ">"), ("RX/s", 7, ">"),
           ("TX/s", 7, ">"), ("CPU%", 5, ">"), ("DROPS", 6, ">"))


def add_options(parser: Any) -> None:
    """The ``--watch`` options of ``u2sa health``."""
    parser.add_argument("--watch", action="store_true",
                        help="a live table (state, reason, rates, restarts) and the autonomy line (who drives, "
                             "from RC_MODE) refreshed until Ctrl-C; plain text blocks when stdout is not a terminal")
    parser.add_argument("--interval", type=float, default=1.0, metavar="S", help="--watch refresh period (default 1)")
    parser.add_argument("--count", type=int, default=0, metavar="N", help="--watch: stop after N refreshes")


def _cell(value: Any) -> str:
    if value is None:
        return "-"
    return f"{value:.1f}" if isinstance(value, float) else str(value)


class AutonomyView:
    """Each RC mux's latest view of autonomy: from its RC_MODE or its Health, whichever came last."""

    def __init__(self) -> None:
        self._views: dict[str, tuple[dict[str, Any], float]] = {}   # service -> (report, monotonic time heard)
        self._lock = threading.Lock()

    def _take(self, report: dict[str, Any], at: float) -> None:
        with self._lock:
            self._views[report["service"]] = (report, at)

    def on_rc_mode(self, msg: Any, at: float) -> None:
        """An ``RcMode`` heard on ``RC_MODE`` at *at* (time.monotonic)."""
        from u2sa_hw.cli.health_cmd import autonomy_from_rc_mode

        self._take(autonomy_from_rc_mode(msg), at)

    def on_health(self, msg: Any, at: float) -> None:
        """A service's ``Health``: an RC mux's says mode, armed and why autonomy is refused."""
        from u2sa_hw.cli.health_cmd import autonomy_report

        for report in autonomy_report({msg.name: msg}):
            self._take(report, at)

    def lines(self, now: float) -> list[str]:
        """One line per mux, as ``u2sa health`` prints it; a stale one says how long it has been silent."""
        from u2sa_hw.cli.health_cmd import autonomy_line

        with self._lock:
            views = sorted(self._views.items())
        out = []
        for _name, (report, at) in views:
            line = autonomy_line(report)
            if now - at > RC_STALE_S:
                line += f" (nothing from it for {now - at:.1f} s)"
            out.append(line)
        return out


def _cut(line: str, width: int) -> str:
    return line if len(line) <= width else line[:max(width - 3, 10)] + "..."


def render(message: dict[str, Any], *, width: int, now: str, autonomy: list[str] | tuple[str, ...] = ()) -> list[str]:
    """The table's lines for one HealthTable message, the reason column cut to *width*, then the *autonomy*
    lines (:class:`AutonomyView`)."""
    failsafe = {True: "FAILSAFE ACTIVE", False: "failsafe off"}.get(message["failsafe"], "failsafe unknown")
    head = f"{now}  {failsafe} -- {message['summary']}"
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
    lines.extend(_cut(line, width) for line in autonomy)
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
    autonomy = AutonomyView()
    lock = threading.Lock()
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())

    def on_health(_c: str, msg: Any) -> None:
        with lock:
            table.on_health(msg)
        autonomy.on_health(msg, time.monotonic())

    def on_rc_mode(_c: str, msg: Any) -> None:
        autonomy.on_rc_mode(msg, time.monotonic())

    def on_system(_c: str, msg: Any) -> None:
        with lock:
            table.on_system(msg)

    shown = 0
    with bus_client(args) as bus:
        bus.transport.subscribe(ch.HEALTH, t.Health, on_health)
        bus.transport.subscribe(ch.SYSTEM_HEALTH, t.SystemHealth, on_system)
        bus.transport.subscribe(ch.RC_MODE, t.RcMode, on_rc_mode)
        while not stop.wait(args.interval):
            with lock:
                message = table.message()
            width = shutil.get_terminal_size((120, 24)).columns if tty else 200
            lines = render(message, width=width, now=time.strftime("%H:%M:%S"),
                           autonomy=autonomy.lines(time.monotonic()))
            if tty:
                out.write(CLEAR + "\n".join(lines) + "\n")
            else:
                out.write("\n".join(lines) + "\n\n")
            out.flush()
            shown += 1
            if args.count and shown >= args.count:
                break
    return 0
