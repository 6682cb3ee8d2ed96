"""The LCM URL a transport opens: the profile's, the environment's or the default, with a receive buffer.

Split from ``u2sa_hw.bus.transport`` (which re-exports these names).
"""

from __future__ import annotations

import os

DEFAULT_LCM_URL = "udpm://239.255.76.67:7667?ttl=0"
LCM_URL_ENV = "U2SA_LCM_URL"
# The kernel's default UDP receive buffer (about 208 KiB) holds a few hundred packets: a
# receiver that loses the CPU for a few ms at 20,000 msg/s drops packets before LCM sees
# them. A udpm URL without its own recv_buf_size asks for this much, capped at what the
# kernel allows (net.core.rmem_max: LCM warns on stderr when it gets less than it asked).
DEFAULT_RECV_BUF_SIZE = 4 * 1024 * 1024
RMEM_MAX_FILE = "/proc/sys/net/core/rmem_max"


def resolve_url(profile_url: str | None = None) -> str:
    """The LCM URL: the vehicle profile's, else ``$U2SA_LCM_URL``, else the default (ttl=0)."""
    return profile_url or os.environ.get(LCM_URL_ENV) or DEFAULT_LCM_URL


def with_receive_buffer(url: str, *, rmem_max_file: str = RMEM_MAX_FILE) -> str:
    """*url* with ``recv_buf_size`` added when it is a udpm URL without one (see DEFAULT_RECV_BUF_SIZE)."""
    if not url.startswith("udpm://") or "recv_buf_size=" in url:
        return url
    try:
        with open(rmem_max_file) as f:
            size = min(DEFAULT_RECV_BUF_SIZE, int(f.read()))
    except (OSError, ValueError):
        return url   # not Linux, or no /proc: leave the kernel's default
    return f"{url}{'&' if '?' in url else '?'}recv_buf_size={size}"
