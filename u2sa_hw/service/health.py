"""Health reporting (requirement C9): process figures, the Health message of a service, and its reason in words."""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from u2sa_hw import lcmtypes as t

if TYPE_CHECKING:
    from u2sa_hw.bus.transport import Transport

HOSTNAME = socket.gethostname()


_PAGE = os.sysconf("SC_PAGE_SIZE")


def _rss_bytes() -> int:
    """This process's resident set, from ``/proc/self/statm`` (0 where there is none)."""
    try:
        with open("/proc/self/statm", "rb") as f:
            return int(f.read().split()[1]) * _PAGE
    except (OSError, ValueError, IndexError):
        return 0


FALSE_WORDS = {"", "0", "0.0", "false", "no", "none", "off", "n/a"}   # health details read as false


def truthy(value: str | None) -> bool:
    """A health detail read as a boolean ("1", "true", "yes", a non-zero number are true)."""
    return value is not None and value.strip().lower() not in FALSE_WORDS


class ProcessStats:
    """CPU % (since the previous sample) and RSS of this process.

    Read from ``os.times()`` and ``/proc/self/statm`` rather than psutil, which would cost
    every service about 2 MB of memory for two numbers.
    """

    def __init__(self, *, clock: Any = time.monotonic) -> None:
        self._clock = clock
        self.started = clock()
        self._last = (self.started, self._cpu_s())

    @staticmethod
    def _cpu_s() -> float:
        times = os.times()
        return times.user + times.system

    def sample(self) -> tuple[float, int]:
        """``(cpu_percent, rss_bytes)``: CPU % of one core since the previous sample."""
        now, cpu = self._clock(), self._cpu_s()
        wall, used = now - self._last[0], cpu - self._last[1]
        self._last = (now, cpu)
        percent = 100.0 * used / wall if wall > 0 else 0.0
        return round(percent, 1), _rss_bytes()

    @property
    def uptime(self) -> float:
        """Seconds since start."""
        return self._clock() - self.started


def build_health(*, name: str, service_type: str, status: str, stats: ProcessStats, transport: "Transport",
                 last_error: str, details: dict[str, Any]) -> t.Health:
    """Fill a Health message from the process figures and the transport's counters."""
    msg = t.Health()
    msg.name = name
    msg.service_type = service_type
    msg.status = status
    msg.pid = os.getpid()
    msg.host = HOSTNAME
    msg.uptime_s = stats.uptime
    msg.cpu_percent, msg.rss_bytes = stats.sample()
    channels = []
    for direction, table in (("in", transport.rx), ("out", transport.tx)):
        for channel, c in sorted(table.items()):
            cs = t.ChannelStats()
            cs.channel, cs.direction = channel, direction
            cs.messages, cs.malformed, cs.dropped = c.messages, c.malformed, c.dropped
            channels.append(cs)
    msg.channels = channels
    msg.num_channels = len(channels)
    msg.malformed = sum(c.malformed for c in transport.rx.values())
    msg.dropped = sum(c.dropped for c in transport.rx.values()) + sum(c.dropped for c in transport.tx.values())
    msg.last_error = last_error[:500]
    set_details(msg, details)
    return msg


def set_details(msg: t.Health, details: Mapping[str, Any]) -> None:
    """Put *details* (key -> value, values as text) into *msg*'s details list."""
    kvs = []
    for key, value in details.items():
        kv = t.KeyValue()
        kv.key, kv.value = str(key), str(value)
        kvs.append(kv)
    msg.details = kvs
    msg.num_details = len(kvs)


# Health details that say, in words, why a service is not ok. A driver's port puts its error
# (with the fix) in ``port_error`` (a CAN driver in ``bus_error``); drivers and the estimator put their summary in
# ``degraded_reason``; a multi-channel driver reports per channel as ``CHANNEL.last_error``.
REASON_KEYS = ("degraded_reason", "port_error", "bus_error")


def health_reason(details: Mapping[str, str], last_error: str = "") -> str:
    """Why a service is not ok, in words, from its Health *details* and *last_error*; "" when nothing says.

    Parts are joined with "; " and a part already contained in an earlier one is left out
    (``degraded_reason = "port down"`` and the port's own error say the same thing twice otherwise).
    """
    parts: list[str] = [str(details.get(k, "")) for k in REASON_KEYS]
    if details.get("silent_sensors"):
        parts.append(f"silent sensors: {details['silent_sensors']}")
    for key, value in sorted(details.items()):
        if key.endswith((".last_error", ".port_error")) and value:
            parts.append(f"{key.rsplit('.', 1)[0]}: {value}")
    parts.append(last_error)
    return join_reasons(*parts)


def join_reasons(*parts: str) -> str:
    """The non-empty *parts* joined with "; ", each said once (a part inside another is dropped)."""
    kept: list[str] = []
    for part in (p.strip() for p in parts):
        if not part or any(part in k for k in kept):
            continue
        kept = [k for k in kept if k not in part]   # a longer part that says it all replaces a shorter one
        kept.append(part)
    return "; ".join(kept)
