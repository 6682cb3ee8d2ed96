"""The launcher's ``$NOTIFY_SOCKET``: the children tell it when they are ready, as they tell systemd.

A service sends ``READY=1`` once it has set up and subscribed, ``STATUS=...`` as it goes
and ``STOPPING=1`` on the way out (:mod:`u2sa_hw.service.sdnotify`). Under systemd these go to
PID 1; under the launcher they come here: a datagram socket in the abstract namespace
with ``SO_PASSCRED``, so each message carries the sender's pid and the launcher knows
which child sent it (systemd does the same).
"""

from __future__ import annotations

import os
import socket
import struct
from dataclasses import dataclass

_UCRED = struct.Struct("3i")   # struct ucred: pid, uid, gid


@dataclass(frozen=True)
class Notification:
    """One datagram: the sender's pid and its ``KEY=value`` fields."""

    pid: int
    fields: dict[str, str]


class NotifyListener:
    """A ``SOCK_DGRAM`` Unix socket in the abstract namespace that reads sd_notify messages with their pid."""

    def __init__(self) -> None:
        self.name = f"u2sa-launcher-{os.getpid()}-{os.urandom(4).hex()}"
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC | socket.SOCK_NONBLOCK)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_PASSCRED, 1)
        self.sock.bind("\0" + self.name)

    @property
    def address(self) -> str:
        """The value for a child's ``NOTIFY_SOCKET`` (``@`` marks the abstract namespace)."""
        return "@" + self.name

    def read(self) -> list[Notification]:
        """Every datagram waiting now (a message without credentials is skipped: its sender is unknown)."""
        out: list[Notification] = []
        while True:
            try:
                data, ancillary, _flags, _addr = self.sock.recvmsg(4096, socket.CMSG_SPACE(_UCRED.size))
            except (BlockingIOError, InterruptedError):
                return out
            except OSError:
                return out
            pid = None
            for level, kind, payload in ancillary:
                if level == socket.SOL_SOCKET and kind == socket.SCM_CREDENTIALS and len(payload) >= _UCRED.size:
                    pid = _UCRED.unpack_from(payload)[0]
            if pid is None:
                continue
            fields = {}
            for line in data.decode(errors="replace").splitlines():
                key, sep, value = line.partition("=")
                if sep:
                    fields[key] = value
            out.append(Notification(pid, fields))

    def close(self) -> None:
        """Close the socket."""
        self.sock.close()
