"""Whether LCM multicast works here: one packet sent to ourselves must come back (``u2sa`` commands and
``u2sa replay`` check before they start, so "multicast does not work" is one line with the fix)."""

from __future__ import annotations

import os
import threading
import time

from u2sa_hw.bus.auth import OPEN
from u2sa_hw.bus.lcm_open import MULTICAST_FIX, TransportError
from u2sa_hw.bus.lcm_url import resolve_url
from u2sa_hw.bus.transport import Transport


def check_multicast(url: str | None = None, *, timeout: float = 1.0) -> None:
    """Send one packet to ourselves; raise TransportError with the fix if it never arrives.

    Only ``udpm://`` URLs are probed: other providers do not loop packets back the same way.
    """
    if not resolve_url(url).startswith("udpm://"):
        return
    probe = f"U2SA_PROBE_{os.getpid()}_{time.monotonic_ns()}"
    t = Transport(url, name="probe", security=OPEN)   # it hears only itself: nothing to verify
    got = threading.Event()
    t.subscribe(probe, None, lambda ch, data: got.set(), raw=True)
    try:
        t.start()
        deadline = time.monotonic() + timeout
        while not got.is_set() and time.monotonic() < deadline:
            t.publish_bytes(probe, b"probe")
            got.wait(0.1)
    finally:
        t.stop()
    if not got.is_set():
        raise TransportError(f"no LCM packet came back on {t.url} within {timeout:.1f} s: {MULTICAST_FIX}")
