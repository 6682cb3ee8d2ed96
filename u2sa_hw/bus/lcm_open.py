"""Opening LCM: what its C library prints on stderr, folded into one line with the fix.

The LCM C library reports a failure to open (no multicast route, a bad URL, a port held by
another program) with many lines on stderr; :func:`captured_c_stderr` catches them and
:func:`open_error` makes the one line of the transport's ``TransportError``.
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
from typing import Iterator

MULTICAST_FIX = (
    "multicast does not work on this machine. If it has no network (a vehicle on the bench), "
    "enable multicast on loopback: 'sudo ip link set lo multicast on && "
    "sudo ip route add 224.0.0.0/4 dev lo' (u2sa install adds a oneshot unit that does this), "
    "or set U2SA_LCM_URL / lcm_url in the vehicle profile to another provider"
)


URL_HELP = ("check the URL: udpm://GROUP:PORT?ttl=N with a multicast group (224.0.0.0/4) and a port "
            "1-65535, or another LCM provider (memq://, file://PATH?mode=w)")


_STDERR_LOCK = threading.Lock()   # fd 2 is the process's: one capture at a time


class TransportError(RuntimeError):
    """The LCM transport cannot start; the message says why and how to fix it."""


@contextlib.contextmanager
def captured_c_stderr() -> Iterator[list[str]]:
    """Redirect file descriptor 2 (where C code prints) to a temp file for the block.

    The yielded list gets one item after the block: the text printed meanwhile ("" when
    fd 2 could not be redirected). Python's own stderr writes meanwhile are caught too;
    :func:`reemit` gives them back.
    """
    printed: list[str] = []
    with _STDERR_LOCK:   # two threads interleaving dup/dup2 would leave fd 2 on a deleted temp file
        try:
            sys.stderr.flush()
            saved = os.dup(2)
        except (OSError, ValueError, AttributeError):  # no fd 2 (a daemon), or sys.stderr closed
            printed.append("")
            yield printed
            return
        # an anonymous in-memory file: tempfile (and the modules it pulls in) would cost every
        # service process memory for this one use
        with open(os.memfd_create("u2sa-lcm-stderr"), "w+b") as tmp:
            os.dup2(tmp.fileno(), 2)
            try:
                yield printed
            finally:
                os.dup2(saved, 2)
                os.close(saved)
                tmp.seek(0)
                printed.append(tmp.read().decode(errors="replace"))


def reemit(text: str) -> None:
    """Write back to stderr what a successful call printed while stderr was captured."""
    if text:
        try:
            os.write(2, text.encode())
        except OSError:
            pass


def fold(printed: str, *, limit: int = 300) -> str:
    """The C library's lines as one: its own multicast advice (ours replaces it) left out."""
    lines = []
    for line in printed.splitlines():
        line = line.strip()
        if line.startswith("LCM requires"):
            break
        if line:
            lines.append(line.removeprefix("Error: "))
    text = "; ".join(lines)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def open_error(url: str, what: str, exc: BaseException | None, printed: str) -> str:
    """One line: what failed, what LCM said, and the fix that fits the cause."""
    said = fold(printed)
    detail = ": ".join(p for p in (said, str(exc) if exc and not said else "") if p) or "LCM gave no reason"
    low = said.lower()
    if "address already in use" in low:
        port = url.split("?", 1)[0].rsplit(":", 1)[-1]
        fix = (f"another program holds UDP port {port} without sharing it (find it with 'ss -ulpn sport = :{port}'), "
               "or choose another port in U2SA_LCM_URL / the profile's lcm_url")
    elif "provider" in low or "bad multicast" in low or not url.startswith("udpm://"):
        fix = URL_HELP
    else:
        fix = MULTICAST_FIX
    return f"{what}: {detail}; {fix}"
