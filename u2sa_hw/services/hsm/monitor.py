"""The HSM's judgement, as pure logic: every input carries the time, so tests use a fake clock.

Feed it heartbeats (:meth:`HealthMonitor.on_health`) and data sightings
(:meth:`HealthMonitor.on_data`); call :meth:`HealthMonitor.evaluate` periodically. It
returns what to do (:class:`Restart`, :class:`Failed`, :class:`Recovered`,
:class:`FailsafeChange`); the service carries that out. Rules, in order, for a service:

1. no heartbeat within ``startup_grace_s`` of the watch starting or of a restart, or none
   for ``heartbeat_timeout_s`` -> *missing*; if its last word was ``stopping`` it stopped
   on purpose -> *stopped* (never restarted);
2. its own health says ``failed``; its data (``data_channel``) silent for ``stale_after_s``;
   a required health detail false for ``require_grace_s`` -> *stale*;
   ``degraded`` for ``degraded_restart_s`` (when set) -> *degraded*;
3. a problem is met by a restart, then judgement pauses for ``startup_grace_s``; restart k+1
   waits ``restart_backoff_s * 2**(k-1)`` after restart k; after ``max_restarts`` without
   recovery (or at once with ``restart = false``) the service is *failed*;
4. ``recovery_s`` of health forgives the restarts; a failed service that comes back recovers;
5. a *failed* or *stopped* required service raises the failsafe. Without ``failsafe_latch``
   the HSM lowers it once every required service is ok again; with it (the default) it stays
   up until an operator clears it (:meth:`HealthMonitor.operator_clear`) while every
   required service is ok. The HSM never lowers a failsafe it did not raise.

Doing no harm:

- a heartbeat counts from when the service *sent* it (its header stamp, read by
  :class:`~u2sa_hw.services.hsm.stamps.SenderClock`), not from when the HSM got to read it;
- a problem is acted on (restart, failed, stopped) only once it has lasted ``confirm_s``, and a
  heartbeat (or data) received meanwhile cancels it (:class:`Cancelled`): the HSM never acts on
  a service that is publishing, even when its own reading lags behind;
- a gap between two judgements longer than ``stall_s`` means the HSM itself was stalled
  (SIGSTOP, a frozen machine): every pending decision is dropped (:class:`Stalled`) and a
  service is judged again only once something arrived from it after the wake, or once its
  heartbeat timeout has passed since; time the HSM could not watch never counts against a
  service's data, details or degraded timers.
"""

from __future__ import annotations

from typing import Any

from u2sa_hw.service.health import health_reason, join_reasons, truthy
from u2sa_hw.services.hsm.rules import MonitorPolicy, WatchRule
from u2sa_hw.services.hsm.track import ServiceTrack
from u2sa_hw.services.hsm.verdicts import (Cancelled, Failed, FailsafeChange, Problem, Recovered, Restart,
                                           ServiceView, Stalled)

UNWATCHED_FORGET_S = 60.0


class HealthMonitor:
    """Judges expected services from their heartbeats and data (see the module docstring)."""

    def __init__(self, rules: list[WatchRule], *, policy: MonitorPolicy, now: float,
                 default_timeout_s: float = 3.0) -> None:
        self.policy = policy
        self.default_timeout_s = default_timeout_s
        self._tracks: dict[str, ServiceTrack] = {r.name: ServiceTrack(rule=r, watch_since=now) for r in rules}
        self.failsafe_active = False
        self.failsafe_reason = ""
        self.failsafe_service = ""
        self._last_evaluate: float | None = None
        self._rebased_at: float | None = None

    # -- inputs ------------------------------------------------------------------------------
    def data_channels(self) -> dict[str, set[str]]:
        """Channel -> the services whose data is watched on it."""
        out: dict[str, set[str]] = {}
        for name, tr in self._tracks.items():
            if tr.rule is not None and tr.rule.data_channel:
                out.setdefault(tr.rule.data_channel, set()).add(name)
        return out

    def unwatch(self, names: set[str], reason: str) -> None:
        """Stop expecting *names* (e.g. not started by the launcher); they stay visible if they talk."""
        for name in names:
            tr = self._tracks.get(name)
            if tr is None:
                continue
            if tr.last_heartbeat is None:
                del self._tracks[name]
            else:
                tr.rule, tr.problem = None, reason

    def on_health(self, msg: Any, now: float, *, sender: str = "") -> None:
        """A Health message arrived (``name``, ``pid``, ``status``, ``last_error``, ``details``).

        *sender* is the verified sender id of its signature (``Transport.last_sender``; empty
        on an open bus): a restart is counted only when the service's own sender is replaced.
        """
        tr = self._tracks.get(msg.name)
        if tr is None:
            tr = self._tracks[msg.name] = ServiceTrack(rule=None, watch_since=now)
        if sender and not tr.senders.admit(sender, msg, now, self._timeout(tr)):
            return
        if tr.pid is not None and msg.pid != tr.pid:
            if tr.last_restart is None or now - tr.last_restart > self._grace(tr):
                tr.restarts += 1   # restarted by systemd or the launcher on its own
            tr.incarnation = now
            tr.clock.reset()
        elif tr.incarnation is None:
            tr.incarnation = now
        sent = tr.clock.sent_at(stamp_us=msg.header.timestamp_us, sequence=msg.header.sequence, received=now)
        if sent is None:
            return   # a duplicate or reordered heartbeat: older than what we know
        tr.pid = msg.pid
        tr.last_heartbeat = max(sent, tr.last_heartbeat or sent)
        tr.last_received = now
        self._disproved(tr, "heartbeat")
        tr.status = msg.status
        tr.health_error = msg.last_error
        tr.details = {kv.key: kv.value for kv in msg.details}
        if tr.rule is not None and tr.rule.require_details:
            if all(truthy(tr.details.get(k)) for k in tr.rule.require_details):
                tr.details_bad_since = None
            elif tr.details_bad_since is None:
                tr.details_bad_since = now
        if msg.status == "degraded":
            tr.degraded_since = tr.degraded_since if tr.degraded_since is not None else now
        else:
            tr.degraded_since = None

    def on_data(self, source: str, channel: str, now: float) -> None:
        """A message from *source* was seen on *channel*."""
        tr = self._tracks.get(source)
        if tr is not None and tr.rule is not None and tr.rule.data_channel == channel:
            tr.last_data = now
            tr.last_received = now
            self._disproved(tr, "data")

    def _disproved(self, tr: ServiceTrack, evidence: str) -> None:
        """*evidence* arrived from a service: it cancels a problem that it contradicts, not yet acted on."""
        if tr.pending_since is None and not tr.confirmed:
            return
        # A heartbeat or data disproves "missing"/"stopped"; data disproves "no data". A problem
        # read from the health's content is judged again from the new content instead.
        if tr.problem_evidence == "heartbeat" or tr.problem_evidence == evidence:
            if tr.pending_since is not None:
                tr.cancelled = f"{evidence} received"   # not acted on yet: say so once
            tr.pending_since, tr.confirmed = None, False

    def heard_ago(self, service: str, now: float) -> float | None:
        """Seconds since anything (heartbeat or data) was received from *service*; None if never."""
        tr = self._tracks.get(service)
        return None if tr is None or tr.last_received is None else now - tr.last_received

    def restart_result(self, service: str, ok: bool, text: str) -> None:
        """The restarter's outcome for *service* (shown as its last error when it failed)."""
        tr = self._tracks.get(service)
        if tr is not None:
            tr.restart_error = "" if ok else f"restart failed: {text}"

    # -- judgement ---------------------------------------------------------------------------
    def _grace(self, tr: ServiceTrack) -> float:
        return tr.rule.startup_grace_s if tr.rule is not None else self.default_timeout_s

    def _timeout(self, tr: ServiceTrack) -> float:
        return tr.rule.heartbeat_timeout_s if tr.rule is not None else self.default_timeout_s

    def _watched(self, t: float) -> float:
        """*t*, or the end of the HSM's last stall if later: time the HSM could not watch does not count."""
        return t if self._rebased_at is None else max(t, self._rebased_at)

    def _data_age(self, tr: ServiceTrack, now: float, *, judging: bool = False) -> float | None:
        if tr.rule is None or not tr.rule.data_channel or tr.incarnation is None:
            return None
        since = max(tr.last_data or tr.incarnation, tr.incarnation)
        return now - (self._watched(since) if judging else since)

    def _problem(self, tr: ServiceTrack, now: float) -> Problem | None:
        rule = tr.rule
        timeout = self._timeout(tr)
        # A stall rebases the judgement of what might have come meanwhile, but a service already given up
        # on recovers only on its own evidence (a heartbeat, data, a good health), never on the HSM's pause.
        watched = (lambda t: t) if tr.failed else self._watched
        if tr.last_heartbeat is None:
            waited = now - watched(tr.watch_since)
            if waited > self._grace(tr):
                return Problem("missing", f"no heartbeat in {waited:.1f} s", "heartbeat")
            return None
        age = now - tr.last_heartbeat
        if age > timeout:
            if tr.status == "stopping":
                return Problem("stopped", f"stopped on purpose {age:.1f} s ago", "heartbeat")
            return Problem("missing", f"no heartbeat for {age:.1f} s (timeout {timeout:g} s)", "heartbeat")
        if rule is None:
            return None
        if tr.status == "failed":
            return Problem("stale", f"reports failed: {tr.health_error or 'no reason given'}", "health")
        data_age = self._data_age(tr, now, judging=not tr.failed)
        if rule.stale_after_s > 0 and data_age is not None and data_age > rule.stale_after_s:
            return Problem("stale", f"no data on {rule.data_channel} for {data_age:.1f} s "
                           f"(limit {rule.stale_after_s:g} s)", "data")
        if tr.details_bad_since is not None and now - watched(tr.details_bad_since) > rule.require_grace_s:
            bad = [k for k in rule.require_details if not truthy(tr.details.get(k))]
            shown = ", ".join(f"{k}={tr.details.get(k, 'absent')}" for k in bad)
            return Problem("stale", f"{shown} for {now - tr.details_bad_since:.1f} s (required: {', '.join(bad)})",
                           "health")
        if rule.degraded_restart_s > 0 and tr.degraded_since is not None \
                and now - watched(tr.degraded_since) > rule.degraded_restart_s:
            return Problem("degraded", f"degraded for {now - tr.degraded_since:.1f} s: "
                           f"{tr.health_error or 'no reason given'}", "health")
        return None

    def _stalled(self, now: float) -> Stalled | None:
        """Notice a gap in the judgements: the HSM itself was not running (see the module docstring)."""
        last, self._last_evaluate = self._last_evaluate, now
        if last is None or now - last <= self.policy.stall_s:
            return None
        self._rebased_at = now
        for tr in self._tracks.values():
            tr.pending_since = None
        return Stalled(now - last)

    def _blind(self, tr: ServiceTrack, now: float) -> bool:
        """True while a service is not judged after a stall: nothing from it since, and within its timeout."""
        if self._rebased_at is None or (tr.last_received is not None and tr.last_received >= self._rebased_at):
            return False
        limit = self._timeout(tr) if tr.last_heartbeat is not None else self._grace(tr)
        return now - self._rebased_at <= limit

    def evaluate(self, now: float) -> list[Any]:
        """Judge every service at *now*; return the actions to carry out, in order."""
        actions: list[Any] = []
        stall = self._stalled(now)
        if stall is not None:
            actions.append(stall)
        for name, tr in list(self._tracks.items()):
            if self._blind(tr, now):
                continue
            problem = self._problem(tr, now)
            if tr.cancelled:
                actions.append(Cancelled(name, tr.problem, tr.cancelled))
                tr.cancelled = ""
            if tr.rule is None:
                tr.state = problem.state if problem else ("degraded" if tr.status == "degraded" else "ok")
                if problem and tr.last_heartbeat is not None and now - tr.last_heartbeat > UNWATCHED_FORGET_S:
                    del self._tracks[name]
                continue
            if problem is None:
                tr.pending_since, tr.confirmed, tr.problem_evidence = None, False, ""
                self._healthy(tr, now, actions)
                continue
            tr.healthy_since = None
            if tr.failed:
                tr.state = "failed"   # keeps the reason it failed with
                continue
            if tr.last_restart is not None and now - tr.last_restart < tr.rule.startup_grace_s:
                tr.state = "restarting"
                continue
            tr.state, tr.problem, tr.problem_evidence = problem.state, problem.text, problem.evidence
            if not self._confirm(tr, now):
                continue
            if tr.state == "stopped":
                continue
            if not tr.rule.restart or tr.attempts >= self.policy.max_restarts:
                tr.failed, tr.state = True, "failed"
                how = "restarts are off for it" if not tr.rule.restart else f"after {tr.attempts} restarts"
                tr.problem = f"{tr.problem} ({how})"
                actions.append(Failed(name, tr.problem, tr.rule.required))
                continue
            if tr.last_restart is None or now - tr.last_restart >= self.policy.backoff(tr.attempts):
                tr.attempts += 1
                tr.restarts += 1
                tr.last_restart = now
                tr.watch_since = now
                tr.state = "restarting"
                tr.confirmed = False
                actions.append(Restart(name, tr.problem, tr.attempts))
        actions.extend(self._failsafe(now))
        return actions

    def _confirm(self, tr: ServiceTrack, now: float) -> bool:
        """True once the problem has lasted ``confirm_s`` with nothing from the service disproving it."""
        if tr.confirmed:
            return True
        if tr.pending_since is None:
            tr.pending_since = now
        if now - tr.pending_since < self.policy.confirm_s:
            return False
        tr.pending_since, tr.confirmed = None, True
        return True

    def _healthy(self, tr: ServiceTrack, now: float, actions: list[Any]) -> None:
        assert tr.rule is not None
        was_bad = tr.failed or tr.state in ("missing", "stale", "restarting", "stopped")
        if tr.last_heartbeat is None:
            tr.state = "starting"
            return
        tr.state = "degraded" if tr.status == "degraded" else "ok"
        tr.problem = ""
        if tr.healthy_since is None:
            tr.healthy_since = now
        if tr.attempts and now - tr.healthy_since >= self.policy.recovery_s:
            tr.attempts = 0
            tr.last_restart = None
        if was_bad:
            tr.failed = False
            tr.restart_error = ""
            actions.append(Recovered(tr.rule.name))

    def _causes(self) -> list[ServiceTrack]:
        return [tr for tr in self._tracks.values() if tr.rule is not None and tr.rule.required
                and (tr.failed or (tr.state == "stopped" and tr.confirmed))]

    def _all_required_ok(self) -> bool:
        return all(tr.state in ("ok", "degraded") for tr in self._tracks.values()
                   if tr.rule is not None and tr.rule.required)

    def _failsafe(self, now: float) -> list[FailsafeChange]:
        causes = self._causes()
        if causes and not self.failsafe_active:
            first = causes[0]
            self.failsafe_active = True
            self.failsafe_service = first.rule.name if first.rule else ""
            self.failsafe_reason = f"required service {self.failsafe_service} {first.state}: {first.problem}"
            return [FailsafeChange(True, self.failsafe_reason, self.failsafe_service)]
        if self.failsafe_active and not self.policy.failsafe_latch and not causes and self._all_required_ok():
            self.failsafe_active, self.failsafe_reason, self.failsafe_service = False, "", ""
            return [FailsafeChange(False, "every required service is ok again", "")]
        return []

    def operator_clear(self) -> str:
        """An operator cleared the HSM's failsafe (a clear from ``operator`` naming ``hsm`` or ``*``).

        Returns "" when the HSM's failsafe is now down (or was not up), else why it stays up
        (the HSM then asserts it again at once).
        """
        if not self.failsafe_active:
            return ""
        causes = self._causes()
        if causes:
            return f"{causes[0].rule.name if causes[0].rule else '?'} is still {causes[0].state}"
        if not self._all_required_ok():
            bad = [tr.rule.name for tr in self._tracks.values() if tr.rule is not None and tr.rule.required
                   and tr.state not in ("ok", "degraded")]
            return f"{', '.join(bad)} not ok yet"
        self.failsafe_active, self.failsafe_reason, self.failsafe_service = False, "", ""
        return ""

    # -- reports -------------------------------------------------------------------------------
    def views(self, now: float) -> list[ServiceView]:
        """One row per known service, expected ones first."""
        rows = []
        for name, tr in self._tracks.items():
            data_age = self._data_age(tr, now)
            error = tr.restart_error or (tr.problem if tr.state not in ("ok", "degraded", "starting")
                                         else "") or tr.health_error
            if tr.state not in ("ok", "starting"):
                # The service's own words from its latest Health, kept after it died: the silent
                # sensor, the missing device and its fix.
                error = join_reasons(error, health_reason(tr.details, tr.health_error))
            error = join_reasons(error, tr.senders.note(now, self._timeout(tr)))
            rows.append(ServiceView(
                name=name, state=tr.state, restarts=tr.restarts, last_error=error,
                heartbeat_age_s=now - tr.last_heartbeat if tr.last_heartbeat is not None else -1.0,
                data_age_s=data_age if data_age is not None else -1.0,
                required=bool(tr.rule and tr.rule.required), watched=tr.rule is not None))
        return sorted(rows, key=lambda v: (not v.watched, v.name))

    def summary(self, now: float) -> str:
        """One line: FAILSAFE and why, or the services that are not ok, or all ok."""
        rows = self.views(now)
        if self.failsafe_active:
            return f"FAILSAFE: {self.failsafe_reason}"
        bad = [f"{v.name} {v.state}" for v in rows if v.watched and v.state not in ("ok", "starting")]
        ok = sum(v.state == "ok" for v in rows if v.watched)
        if bad:
            return f"degraded: {', '.join(bad)} ({ok} of {sum(v.watched for v in rows)} ok)"
        return f"ok: {ok} of {sum(v.watched for v in rows)} services ok"
