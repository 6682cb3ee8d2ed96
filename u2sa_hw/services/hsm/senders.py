"""Which signed sender speaks for a watched service (issue 11, docs/security.md).

Every transport signs with a random sender id, new for each process, and the HSM hears the
verified one of each Health (``Transport.last_sender``). A new sender replacing the old one
is a restart; a second sender talking beside the old one is another process of the same
name (another stack sharing the bus and key, or an impostor holding the key): its Health is
ignored and shown, never counted as a restart.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

MAX_RETIRED = 64


@dataclass
class ServiceSenders:
    """The sender of one service's Health, and any other sender naming it."""

    sender: str = ""                  # the verified sender id of its Health (empty: none yet, or an open bus)
    heard: float = 0.0                # when that sender's last Health arrived
    interval: float = 0.0             # its usual gap between Healths (the largest lately: an extra one is no beat)
    retired: set[str] = field(default_factory=set)   # senders it replaced: a dead process never speaks again
    candidate: str = ""               # another sender naming this service, not adopted (yet)
    candidate_heard: float = 0.0
    other: str = ""                   # what that other sender says

    def admit(self, sender: str, msg: Any, now: float, timeout: float) -> bool:
        """Whether a Health signed by *sender* speaks for the service (*timeout*: its heartbeat timeout).

        Its current sender does. Another one replaces it only once the current one has been
        silent for *timeout*, or since the other's previous Health and for more than 1.5 of
        its own intervals (a restart: the old process is gone). While both talk, the other's
        Health is ignored; a replaced sender that speaks again was not dead and stays ignored.
        """
        if not self.sender or sender == self.sender:
            if self.heard:
                self.interval = max(now - self.heard, 0.9 * self.interval)
            self.sender, self.heard = sender, now
            return True
        silent = now - self.heard
        replaced = sender not in self.retired and (silent > timeout or (
            self.candidate == sender and self.heard < self.candidate_heard and silent > 1.5 * self.interval))
        if replaced:
            if len(self.retired) < MAX_RETIRED:
                self.retired.add(self.sender)
            self.sender, self.heard, self.interval = sender, now, 0.0
            self.candidate, self.other = "", ""
            return True
        self.candidate, self.candidate_heard = sender, now
        self.other = (f"another process also sends Health as '{msg.name}' (pid {msg.pid} on {msg.host}): "
                      "ignored, not counted as a restart")
        return False

    def note(self, now: float, timeout: float) -> str:
        """What to show about another sender while it keeps talking ("" otherwise)."""
        return self.other if self.other and now - self.candidate_heard <= timeout else ""
