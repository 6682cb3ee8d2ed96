"""Pre-arm checks: autonomy is earned (docs/safety.md, "Pre-arm checks").

Pure logic, time passed in, no bus access: the service that hosts it (the RC mux) feeds
what arrives on the bus and asks before every grant of autonomy, and while autonomous,
whether the checks still hold::

    checks = PrearmChecks.from_profile(profile)              # ProfileError on a bad [safety.prearm]
    checks.on_health(health_msg, now)                        # every Health on U2SA_HEALTH
    if checks.needs_estimate:
        checks.on_estimate(estimate_msg, now)                # every STATE_ESTIMATE
    failures = checks.evaluate(now, rc_link_ok=..., failsafe_reason=...)
    if failures:
        refuse(failures[0].reason)                           # "gps: no 3D fix (fix type 2D, 7 satellites)"

The evidence, per check (the table and its defaults are in :mod:`.prearm_table`):

- ``no_failsafe``: *failsafe_reason* is empty (the host holds the failsafes, per source);
- ``rc_link``: *rc_link_ok* (the host measures the RC signal);
- ``gps``: the GPS service's Health: ``data`` fresh, ``fix_type`` 3D, ``h_sigma_m`` under the
  bound (the driver publishes its health at once when the fix type or the data's freshness
  changes);
- ``imu``: each IMU service's Health: ``calibrated`` true;
- ``estimator``: its Health, STATE_ESTIMATE younger than ``max_estimate_age_s``, and the
  estimate's position and heading sigmas (from the newest STATE_ESTIMATE, else the Health
  details ``position_sigma_m`` and ``heading_sigma_deg``) under their bounds;
- ``geofence`` (on whenever the profile has a ``[geofence]``): the estimator's newest position is
  fresh and inside the fence (:mod:`.prearm_geofence`);
- ``required_services``: every other required service's Health is fresh and says ``ok``.

A ``degraded`` reason ends with the service's ``to_clear`` health detail when it gives one (a latched
motor controller error: ``to clear: u2sa param set wheels clear_errors true``, or the pilot's re-arm
for a watchdog trip of the driver's own stall), so the refusal names what clears it.

Every service a check names must have sent a Health within ``health_timeout_s`` and must not
say ``starting``, ``failed`` or ``stopping``; after its own evidence, ``degraded`` fails too.
Times are the host's monotonic clock at receipt: service clocks are never compared.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Any, Callable, NamedTuple

from u2sa_hw.messages import STATE_FIELDS  # noqa: F401 - installs the presence getters on StateInformation
from u2sa_hw.profile.vehicle import VehicleProfile
from u2sa_hw.service.health import truthy
from u2sa_hw.safety.prearm_geofence import Position, age_limit, geofence_problem, position_of
from u2sa_hw.safety.prearm_table import PrearmTable, parse_prearm


@dataclass(frozen=True)
class CheckFailure:
    """One check that does not hold: its name in the table, one line a pilot understands, and the service
    it judged ("" for ``no_failsafe`` and ``rc_link``).

    Ages in a reason are the configured limits ("no health for over 3 s"), so the text of a lasting
    failure stays the same from one evaluation to the next; a sigma is shown as measured.
    """

    check: str
    reason: str
    service: str = ""


@dataclass(frozen=True)
class _Heard:
    """The newest Health of one service, as received."""

    at: float
    status: str
    last_error: str
    details: dict[str, str]


@dataclass(frozen=True)
class _Estimate:
    """What the checks read from the newest STATE_ESTIMATE."""

    at: float
    position_sigma_m: float | None   # None: no position; nan: a position without a sigma
    heading_sigma_deg: float | None


class _Verdict(NamedTuple):
    """A verdict and what it was judged on: it stands for another question with the same inputs while
    ``holds_from <= now < holds_until`` (no age limit between: time is the only other input)."""

    evidence: int           # PrearmChecks._evidence when judged
    rc_link_ok: bool
    failsafe_reason: str
    holds_from: float
    holds_until: float
    failures: tuple[CheckFailure, ...]


def _float(text: str | None) -> float | None:
    try:
        return float(text) if text not in (None, "") else None
    except ValueError:
        return None


def _sigma(text: str | None) -> float | None:
    """A sigma health detail: None when empty (not estimated), nan when it is there but no number."""
    if text in (None, ""):
        return None
    value = _float(text)
    return math.nan if value is None else value


def _degraded_why(heard: _Heard) -> str:
    """Why a service says degraded, and what clears it when it says (its ``to_clear`` detail: a latched
    motor controller error names the command or the re-arm, so the refusal the pilot reads names the fix)."""
    d = heard.details
    why = (d.get("degraded_reason") or d.get("port_error") or (f"silent sensors: {d['silent_sensors']}"
           if d.get("silent_sensors") else "") or heard.last_error or "no reason given")
    fix = (d.get("to_clear") or "").strip()
    return f"{why}; to clear: {fix}" if fix else why


class PrearmChecks:
    """The pre-arm checks of one vehicle (see the module docstring); thread-safe."""

    def __init__(self, table: PrearmTable) -> None:
        self.table = table
        self._lock = threading.Lock()
        self._heard: dict[str, _Heard] = {}
        self._estimate: _Estimate | None = None
        self._position: Position | None = None
        self._last: list[CheckFailure] | None = None
        self._evidence = 0   # counts what arrived: a verdict holds only for the evidence it judged
        self._memo: _Verdict | None = None
        watched: set[str] = set()
        if table.gps:
            watched.add(table.gps.service)
        if table.estimator:
            watched.add(table.estimator.service)
        if table.imu:
            watched.update(table.imu.services)
        if table.required_services:
            watched.update(table.required_services.services)
        self.watched = frozenset(watched)

    @classmethod
    def from_profile(cls, profile: VehicleProfile) -> "PrearmChecks":
        """The checks of *profile*'s ``[safety.prearm]`` table (ProfileError names the file, key and fix)."""
        return cls(parse_prearm(profile))

    @property
    def needs_estimate(self) -> bool:
        """True when the estimator check judges STATE_ESTIMATE freshness: feed :meth:`on_estimate`."""
        return (self.table.estimator is not None and self.table.estimator.max_estimate_age_s > 0) \
            or self.table.geofence is not None

    # -- evidence ---------------------------------------------------------------------------
    def on_health(self, msg: Any, now: float) -> None:
        """A Health message (U2SA_HEALTH) arrived at *now*; services no check names are ignored."""
        name = msg.name or msg.header.source
        if name not in self.watched:
            return
        heard = _Heard(at=now, status=msg.status, last_error=msg.last_error,
                       details={kv.key: kv.value for kv in msg.details})
        with self._lock:
            self._heard[name] = heard
            self._evidence += 1

    def on_estimate(self, msg: Any, now: float) -> None:
        """A STATE_ESTIMATE arrived at *now* (from the estimator a check names; others are ignored)."""
        check, fence = self.table.estimator, self.table.geofence
        source = msg.header.source or msg.sensor_name
        if fence is not None and source == fence.service:
            with self._lock:
                self._position = position_of(msg, now)
                self._evidence += 1
        if check is None or source != check.service:
            return
        position = heading = None
        if msg.has("x") and msg.has("y"):
            sx, sy = msg.get("x_sigma"), msg.get("y_sigma")
            position = math.hypot(sx, sy) if sx is not None and sy is not None else math.nan
        if msg.has("psi"):
            sp = msg.get("psi_sigma")
            heading = math.degrees(sp) if sp is not None else math.nan
        with self._lock:
            self._estimate = _Estimate(at=now, position_sigma_m=position, heading_sigma_deg=heading)
            self._evidence += 1

    # -- judgement ----------------------------------------------------------------------------
    def evaluate(self, now: float, *, rc_link_ok: bool, failsafe_reason: str) -> list[CheckFailure]:
        """Every check that does not hold at *now*, in table order (empty: autonomy may be granted).

        The RC mux asks after every edge; the verdict changes only when evidence arrives, the RC link or a
        failsafe changes, or an age limit passes, so a verdict is kept until one of those (exactly the
        verdict a fresh judgement would give: :meth:`_holds`)."""
        return list(self.verdict(now, rc_link_ok=rc_link_ok, failsafe_reason=failsafe_reason))

    def verdict(self, now: float, *, rc_link_ok: bool, failsafe_reason: str) -> tuple[CheckFailure, ...]:
        """:meth:`evaluate` as a tuple that is the very same object for as long as the verdict is kept, so a
        caller asking many times a second can tell "nothing changed" by identity, without a copy."""
        # without the lock first: the memo is immutable and both reads are atomic, so a hit is the verdict as
        # of the evidence count read (evidence arriving just after is judged at the next question)
        memo = self._memo
        if (memo is not None and memo.evidence == self._evidence and memo.rc_link_ok == rc_link_ok
                and memo.failsafe_reason == failsafe_reason and memo.holds_from <= now < memo.holds_until):
            return memo.failures
        with self._lock:
            memo = self._memo
            if (memo is not None and memo.evidence == self._evidence and memo.rc_link_ok == rc_link_ok
                    and memo.failsafe_reason == failsafe_reason and memo.holds_from <= now < memo.holds_until):
                return memo.failures
            out = tuple(self._judge_all(now, rc_link_ok=rc_link_ok, failsafe_reason=failsafe_reason))
            self._memo = _Verdict(self._evidence, rc_link_ok, failsafe_reason, *self._holds(now), out)
            self._last = list(out)
            return out

    def _judge_all(self, now: float, *, rc_link_ok: bool, failsafe_reason: str) -> list[CheckFailure]:
        t = self.table
        out: list[CheckFailure] = []
        if t.no_failsafe and failsafe_reason:
            out.append(CheckFailure("no_failsafe", f"failsafe held: {failsafe_reason}"))
        if t.rc_link and not rc_link_ok:
            out.append(CheckFailure("rc_link", "rc_link: no valid RC signal"))
        if t.gps:
            self._judge(out, "gps", t.gps.service, now, self._gps_problem)
        if t.imu:
            for name in t.imu.services:
                self._judge(out, "imu", name, now, self._imu_problem)
        if t.estimator:
            self._judge(out, "estimator", t.estimator.service, now, self._estimator_problem)
        if t.geofence and (problem := geofence_problem(t.geofence, self._position, now)):
            out.append(CheckFailure("geofence", f"geofence: {problem}", t.geofence.service))
        if t.required_services:
            for name in t.required_services.services:
                self._judge(out, "required_services", name, now, lambda _h, _n: "",
                            allow_degraded=name in t.required_services.allow_degraded)
        return out

    def _holds(self, now: float) -> tuple[float, float]:
        """When a verdict judged at *now* stands on the same evidence, ``[from, until)``: between the last age
        limit passed and the first still ahead (a Health's ``health_timeout_s``, the estimate's
        ``max_estimate_age_s``), each a microsecond in so float rounding at a limit is judged afresh. Time is
        the only other input; the RC mux asks at edge stamps a little before its loop's last look, so
        the span reaches back too."""
        limits = [heard.at + self.table.health_timeout_s for heard in self._heard.values()]
        check = self.table.estimator
        if check is not None and check.max_estimate_age_s > 0 and self._estimate is not None:
            limits.append(self._estimate.at + check.max_estimate_age_s)
        if self.table.geofence is not None and (limit := age_limit(self.table.geofence, self._position)) is not None:
            limits.append(limit)
        ahead = [limit for limit in limits if limit >= now]
        behind = [limit for limit in limits if limit < now]
        since, until = (max(behind) + 1e-6 if behind else -math.inf), (min(ahead) - 1e-6 if ahead else math.inf)
        # judged within a microsecond of a limit: rounding may have decided it, so it stands for nothing else
        return (since, until) if since <= now < until else (math.inf, -math.inf)

    def _judge(self, out: list[CheckFailure], check: str, service: str, now: float,
               specific: Callable[[_Heard, float], str], *, allow_degraded: bool = False) -> None:
        heard = self._heard.get(service)
        problem = ""
        if heard is None:
            problem = "no health yet (is it running?)"
        elif now - heard.at > self.table.health_timeout_s:
            problem = f"no health for over {self.table.health_timeout_s:g} s"
        elif heard.status == "stopping":
            problem = "stopped"
        elif heard.status == "failed":
            problem = f"failed ({heard.last_error or 'no reason given'})"
        elif heard.status == "starting":
            problem = "starting"
        else:
            problem = specific(heard, now)
            if not problem and heard.status == "degraded" and not allow_degraded:
                problem = f"degraded ({_degraded_why(heard)})"
            elif not problem and heard.status not in ("ok", "degraded"):
                problem = f"status {heard.status!r}"
        if check == "estimator" and not problem:
            problem = self._estimate_problem(now)
        if problem:
            if check == "required_services":
                label = f"required service {service}"
            else:
                label = check if service == check else f"{check} {service}"
            out.append(CheckFailure(check, f"{label}: {problem}", service))

    def _gps_problem(self, heard: _Heard, _now: float) -> str:
        check = self.table.gps
        assert check is not None
        d = heard.details
        if d.get("data") == "none yet":
            return "no data from the receiver yet"
        if d.get("data") == "stale":
            return "no data from the receiver (stale)"
        sats = d.get("satellites", "")
        with_sats = f", {sats} satellites" if sats else ""
        fix_type = d.get("fix_type", "")
        if fix_type != "3D":
            what = f"fix type {fix_type}" if fix_type in ("2D",) else (fix_type or "fix type not reported")
            return f"no 3D fix ({what}{with_sats})"
        sigma = _float(d.get("h_sigma_m"))
        if sigma is None:
            return "horizontal sigma unknown (the receiver sends neither GST nor HDOP)"
        if sigma > check.max_sigma_m:
            return f"horizontal sigma {sigma:.1f} m > {check.max_sigma_m:g} m ({sats or '?'} satellites)"
        return ""

    @staticmethod
    def _imu_problem(heard: _Heard, _now: float) -> str:
        if truthy(heard.details.get("calibrated")):
            return ""
        state = heard.details.get("calibration") or "the driver reports no calibration"
        if "no rest found" in state:   # the driver's bounded fallback: it says what it waits for itself
            hint = "; keep the vehicle still, then it passes"
        elif "rest" in state or "calibrating" in state:
            hint = "; keep the vehicle still"
        elif "mag" in state:
            hint = "; turn the vehicle slowly through a figure eight"
        else:
            hint = ""
        return f"not calibrated ({state}{hint})"

    def _estimator_problem(self, heard: _Heard, _now: float) -> str:
        check = self.table.estimator
        assert check is not None
        est = self._estimate
        if est is not None:
            position, heading = est.position_sigma_m, est.heading_sigma_deg
        else:
            d = heard.details
            position = _sigma(d.get("position_sigma_m"))
            heading = _sigma(d.get("heading_sigma_deg"))
        if position is None:
            return "not converged (no position yet)"
        if math.isnan(position) or position > check.max_position_sigma_m:
            shown = "unknown" if math.isnan(position) else f"{position:.1f} m"
            return f"not converged (position sigma {shown} > {check.max_position_sigma_m:g} m)"
        if heading is None:
            return "not converged (no heading yet)"
        if math.isnan(heading) or heading > check.max_heading_sigma_deg:
            shown = "unknown" if math.isnan(heading) else f"{heading:.1f} deg"
            return f"not converged (heading sigma {shown} > {check.max_heading_sigma_deg:g} deg)"
        return ""

    def _estimate_problem(self, now: float) -> str:
        check = self.table.estimator
        if check is None or check.max_estimate_age_s <= 0:
            return ""
        if self._estimate is None:
            return "no STATE_ESTIMATE yet"
        age = now - self._estimate.at
        return f"no STATE_ESTIMATE for over {check.max_estimate_age_s:g} s" if age > check.max_estimate_age_s else ""

    # -- reporting ------------------------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        """Health details from the latest :meth:`evaluate`: ``prearm`` (ok, or the first failure's reason),
        ``prearm_failed`` (the failing checks' names) and ``prearm_checks`` (those that run)."""
        with self._lock:
            last = self._last
        if last is None:
            verdict = "not evaluated yet"
        else:
            verdict = last[0].reason if last else "ok"
        failed = ",".join(dict.fromkeys(f.check for f in last or ()))
        return {"prearm": verdict, "prearm_failed": failed, "prearm_checks": ",".join(self.table.enabled())}

    def describe(self) -> str:
        """One line for the log at start: each check that runs and on what."""
        t = self.table
        parts = []
        if t.no_failsafe:
            parts.append("no_failsafe")
        if t.rc_link:
            parts.append("rc_link")
        if t.gps:
            parts.append(f"gps ({t.gps.service}: 3D fix, sigma <= {t.gps.max_sigma_m:g} m)")
        if t.imu:
            parts.append(f"imu ({', '.join(t.imu.services)}: calibrated)")
        if t.estimator:
            e = t.estimator
            parts.append(f"estimator ({e.service}: sigma <= {e.max_position_sigma_m:g} m, "
                         f"<= {e.max_heading_sigma_deg:g} deg)")
        if t.geofence:
            parts.append(f"geofence ({t.geofence.service}'s position inside {t.geofence.fence.names()})")
        if t.required_services:
            parts.append(f"required_services ({', '.join(t.required_services.services) or 'none'})")
        return "pre-arm checks: " + ("; ".join(parts) or "none (every check is off)")
