"""What the HSM's health monitor (:mod:`.monitor`) keeps per service: one :class:`ServiceTrack` each.

The record only: its times are on the monitor's clock (every input carries it), and the monitor
alone reads and changes them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from u2sa_hw.services.hsm.rules import WatchRule
from u2sa_hw.services.hsm.senders import ServiceSenders
from u2sa_hw.services.hsm.stamps import SenderClock


@dataclass
class ServiceTrack:
    """What the monitor knows of one service: what it heard, what it judged, what it did about it."""

    rule: WatchRule | None
    watch_since: float
    last_heartbeat: float | None = None   # when the newest heartbeat was sent (our clock, from its stamp)
    last_received: float | None = None    # when the HSM received anything from it (heartbeat or data)
    clock: SenderClock = field(default_factory=SenderClock)
    pending_since: float | None = None    # a problem first seen then, not acted on yet
    confirmed: bool = False               # the current problem outlasted confirm_s
    cancelled: str = ""                   # why a pending problem was dropped (reported once)
    problem_evidence: str = ""            # what would disprove the current problem
    pid: int | None = None
    senders: ServiceSenders = field(default_factory=ServiceSenders)   # whose signed Health speaks for it
    status: str = ""
    health_error: str = ""
    incarnation: float | None = None
    last_data: float | None = None
    details_bad_since: float | None = None
    degraded_since: float | None = None
    restarts: int = 0
    attempts: int = 0
    last_restart: float | None = None
    healthy_since: float | None = None
    failed: bool = False
    state: str = "starting"
    problem: str = ""
    restart_error: str = ""
    details: dict[str, str] = field(default_factory=dict)
