"""systemd notification (sd_notify protocol) without libsystemd.

Sends READY=1, WATCHDOG=1, STATUS=..., STOPPING=1 to ``$NOTIFY_SOCKET`` (a path, or an
abstract-namespace socket when it starts with ``@``). Does nothing when not under systemd.
"""

from __future__ import annotations

import os
import socket


class SystemdNotifier:
    """A datagram connection to systemd's notify socket, if there is one."""

    def __init__(self, socket_path: str | None = None) -> None:
        addr = socket_path if socket_path is not None else os.environ.get("NOTIFY_SOCKET", "")
        self._sock: socket.socket | None = None
        self._addr = ""
        if addr:
            self._addr = "\0" + addr[1:] if addr.startswith("@") else addr
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)

    @property
    def enabled(self) -> bool:
        """True when running under systemd with a notify socket."""
        return self._sock is not None

    def notify(self, state: str) -> bool:
        """Send *state* (e.g. ``READY=1``); True if sent."""
        if self._sock is None:
            return False
        try:
            self._sock.sendto(state.encode(), self._addr)
            return True
        except OSError:
            return False

    def close(self) -> None:
        """Close the socket."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def watchdog_interval() -> float | None:
    """Half of ``$WATCHDOG_USEC`` in seconds (how often to ping), if the watchdog is on for us."""
    usec = os.environ.get("WATCHDOG_USEC")
    pid = os.environ.get("WATCHDOG_PID")
    if not usec or (pid and pid.isdigit() and int(pid) != os.getpid()):
        return None
    try:
        return int(usec) / 2e6
    except ValueError:
        return None
