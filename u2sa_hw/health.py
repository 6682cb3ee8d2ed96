"""Health reporting (requirement C9): process figures and the Health message of a service."""

from __future__ import annotations

import os
import socket
import time
from typing import TYPE_CHECKING, Any

import psutil

from u2sa_hw import lcmtypes as t

if TYPE_CHECKING:
    from u2sa_hw.transport import Transport

HOSTNAME = socket.gethostname()


class ProcessStats:
    """CPU % (since the previous sample) and RSS of this process."""

    def __init__(self) -> None:
        self._proc = psutil.Process(os.getpid())
        self._proc.cpu_percent(None)
        self.started = time.monotonic()

    def sample(self) -> tuple[float, int]:
        """``(cpu_percent, rss_bytes)``."""
        try:
            return self._proc.cpu_percent(None), self._proc.memory_info().rss
        except psutil.Error:
            return 0.0, 0

    @property
    def uptime(self) -> float:
        """Seconds since start."""
        return time.monotonic() - self.started


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
    kvs = []
    for key, value in details.items():
        kv = t.KeyValue()
        kv.key, kv.value = str(key), str(value)
        kvs.append(kv)
    msg.details = kvs
    msg.num_details = len(kvs)
    return msg
