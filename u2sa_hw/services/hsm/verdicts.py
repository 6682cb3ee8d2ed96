"""What the HSM's judgement (:mod:`.monitor`) returns: the actions to carry out and the rows to report."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Restart:
    """Restart *service* now (restart number *attempt* since it was last healthy)."""

    service: str
    reason: str
    attempt: int


@dataclass(frozen=True)
class Failed:
    """*service* is given up."""

    service: str
    reason: str
    required: bool


@dataclass(frozen=True)
class Recovered:
    """*service* is healthy again after a problem."""

    service: str


@dataclass(frozen=True)
class FailsafeChange:
    """The failsafe goes up (active) or down."""

    active: bool
    reason: str
    service: str


@dataclass(frozen=True)
class Cancelled:
    """A problem of *service* was not acted on: it published again before the decision was carried out."""

    service: str
    problem: str
    evidence: str


@dataclass(frozen=True)
class Stalled:
    """The HSM's own judgement stalled for *gap_s*: every service is judged afresh from now."""

    gap_s: float


@dataclass(frozen=True)
class Problem:
    """What is wrong with a service: its state, why, and what would disprove it (heartbeat, data, health)."""

    state: str
    text: str
    evidence: str


@dataclass(frozen=True)
class ServiceView:
    """One row of the system health."""

    name: str
    state: str           # starting, ok, degraded, stale, missing, restarting, stopped, failed
    restarts: int
    last_error: str
    heartbeat_age_s: float   # -1: never heard
    data_age_s: float        # -1: no data channel watched
    required: bool
    watched: bool
