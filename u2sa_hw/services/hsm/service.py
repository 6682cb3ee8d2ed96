"""The Health and Status Monitor service (requirements H1, H2; DESIGN.md section 5).

Listens to every service's Health on ``U2SA_HEALTH`` and, for services whose data is
watched, to their data channels (only the header's ``source`` is read). A
:class:`HealthMonitor` judges them; this service carries out its verdicts: restarts
(through systemd or the local launcher, on a worker thread so the loop never blocks),
the failsafe on ``FAILSAFE`` (re-sent every second while active, so a restarted actuator
learns it), and the system health on ``U2SA_SYSTEM_HEALTH`` at 1 Hz. Its loop is
``while self.wait(...)``, so systemd's (or ``u2sa run``'s) watchdog restarts a hung HSM.

Failsafes follow the one model of :mod:`u2sa_hw.failsafe`: the HSM's own is held under its
name; a clear from any other source leaves it up; an operator clear (source ``operator``)
naming the HSM or ``*`` lowers it only while every required service is ok, else the HSM
says why and asserts it again at once. Every source holding a failsafe is reported in the
system health (summary) and the HSM's health details (``failsafe_sources``, as every holder
reports them, and ``failsafe_reasons``), which ``u2sa failsafe status`` reads.
"""

from __future__ import annotations

import queue
import struct
import threading
import time
from io import BytesIO
from typing import Any, ClassVar

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.config.fields import MAX_TIMEOUT_S, field
from u2sa_hw.failsafe import ALL_SOURCES, OPERATOR_SOURCE, FailsafeSources
from u2sa_hw.services.hsm.monitor import HealthMonitor
from u2sa_hw.services.hsm.restarters import (DEFAULT_UNIT_TEMPLATE, LauncherRestarter, Restarter, RestartError,
                                             choose_restarter)
from u2sa_hw.services.hsm.rules import MonitorPolicy, rules_from_profile
from u2sa_hw.services.hsm.verdicts import Cancelled, Failed, FailsafeChange, Recovered, Restart, Stalled
from u2sa_hw.service.contract import U2SAService

FAILSAFE_REPEAT_S = 1.0
FAILSAFE_HELD = "FAILSAFE held by"


class HealthStatusMonitor(U2SAService):
    """Watches every expected service, restarts the ones in trouble, raises the failsafe."""

    SERVICE_TYPE: ClassVar[str] = "hsm"
    CONFIG = (
        field("missed_heartbeats", 3, "heartbeats a service may miss before it counts as missing", ge=1, le=1000),
        field("startup_grace_s", 10.0, "time to the first heartbeat after the HSM starts or a restart", ge=0, le=MAX_TIMEOUT_S),
        field("max_restarts", 3, "restarts without recovery before a service is marked failed", ge=0, le=1000),
        field("restart_backoff_s", 2.0, "wait after the first restart before another; doubles each time", ge=0, le=MAX_TIMEOUT_S),
        field("max_backoff_s", 30.0, "cap of the wait between restarts", ge=0, le=MAX_TIMEOUT_S),
        field("recovery_s", 30.0, "healthy this long -> the restart count starts over", ge=0, le=MAX_TIMEOUT_S),
        field("failsafe_latch", True, "true: the failsafe stays up until someone clears it while all is ok; "
              "false: the HSM lowers it when every required service is ok again"),
        field("system_health_interval_s", 1.0, "seconds between SystemHealth messages", gt=0, le=60),
        field("check_interval_s", 0.1, "seconds between judgements", gt=0, le=10),
        field("confirm_s", 0.5, "a problem must last this long, with nothing from the service meanwhile, "
              "before the HSM restarts it or marks it failed", ge=0, le=MAX_TIMEOUT_S),
        field("restarter", "auto", "auto, systemd, launcher or none (see docs/supervision.md)"),
        field("unit_template", DEFAULT_UNIT_TEMPLATE, "systemd unit of a service; {name} is its name"),
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        cfg = self.config
        self.rules = rules_from_profile(self.profile, own_name=name, missed_heartbeats=int(cfg["missed_heartbeats"]),
                                        startup_grace_s=float(cfg["startup_grace_s"]))
        self.policy = self._policy()
        self.monitor = HealthMonitor(self.rules, policy=self.policy, now=time.monotonic(),
                                     default_timeout_s=int(cfg["missed_heartbeats"]) * 1.0)
        self.restarter: Restarter | None = None
        self._lock = threading.Lock()
        self._restarts: queue.Queue[tuple[str, str] | None] = queue.Queue()
        self._worker: threading.Thread | None = None
        self._summary = ""
        self._reassert = threading.Event()
        self.failsafes = FailsafeSources()   # every source's, the HSM's own included
        self.register_subscriber(ch.HEALTH, t.Health, self._on_health)
        self.register_subscriber(ch.FAILSAFE, t.Failsafe, self._on_failsafe)
        for channel in self.monitor.data_channels():
            self.transport.subscribe(channel, None, self._on_data, raw=True)
            self._subscribers[channel] = "(header only)"
        self.register_publisher(ch.SYSTEM_HEALTH, t.SystemHealth)
        self.register_publisher(ch.FAILSAFE, t.Failsafe)

    def _policy(self) -> MonitorPolicy:
        cfg = self.config
        # A loop gap of 5 periods (at least 1 s) is no scheduling hiccup: the HSM itself was stalled.
        return MonitorPolicy(max_restarts=int(cfg["max_restarts"]), restart_backoff_s=float(cfg["restart_backoff_s"]),
                             max_backoff_s=float(cfg["max_backoff_s"]), recovery_s=float(cfg["recovery_s"]),
                             failsafe_latch=bool(cfg["failsafe_latch"]), confirm_s=float(cfg["confirm_s"]),
                             stall_s=max(1.0, 5 * float(cfg["check_interval_s"])))

    # -- inputs (LCM handler thread) -----------------------------------------------------------
    def _on_health(self, msg: t.Health) -> None:
        if msg.name == self.name:
            return
        with self._lock:
            self.monitor.on_health(msg, time.monotonic(), sender=self.transport.last_sender)

    def _on_failsafe(self, msg: t.Failsafe) -> None:
        source = msg.header.source or "?"
        if source == self.name:
            return   # our own, back from the bus: self.failsafes already holds what we sent
        self.failsafes.apply_message(msg)
        aimed_at_us = source == OPERATOR_SOURCE and msg.service in (self.name, ALL_SOURCES)
        if msg.active or not aimed_at_us:
            if not msg.active and self.monitor.failsafe_active:
                self.logger.info("failsafe clear from %s%s leaves the HSM's own up (only an operator clear naming "
                                 "'%s' or '*' lowers it)", source, f" for {msg.service}" if msg.service else "",
                                 self.name)
            return
        with self._lock:
            was_active = self.monitor.failsafe_active
            refusal = self.monitor.operator_clear()
        if refusal:
            self.logger.warning("failsafe clear from %s refused: %s; asserting it again", source, refusal)
            self.failsafes.apply(source=self.name, active=True, reason=self.monitor.failsafe_reason)
            self._reassert.set()
        elif was_active:
            self.logger.info("failsafe cleared by %s (%s); every required service is ok", source, msg.reason or "-")
            self._publish_failsafe(False, f"clear from {source} accepted: every required service is ok", "")

    def _on_data(self, channel: str, data: bytes) -> None:
        try:
            source = t.Header._decode_one(BytesIO(data[8:])).source   # every U2SA type starts with its header
        except (struct.error, UnicodeDecodeError, ValueError, MemoryError):
            self.transport.rx[channel].malformed += 1
            return
        with self._lock:
            self.monitor.on_data(source, channel, time.monotonic())

    # -- lifecycle --------------------------------------------------------------------------------
    def setup(self) -> None:
        """Choose the restarter; under a launcher, watch only the services it runs."""
        names = [r.name for r in self.rules]
        self.restarter = choose_restarter(str(self.config["restarter"]), profile=self.profile, services=names,
                                          unit_template=str(self.config["unit_template"]))
        if isinstance(self.restarter, LauncherRestarter):
            supervised = self.restarter.supervised()
            absent = set(names) - supervised if supervised is not None else set()
            if absent:
                self.logger.info("not watching %s: the launcher does not run them (--only)", ", ".join(sorted(absent)))
                self.monitor.unwatch(absent, "not run by the launcher")
                names = [n for n in names if n not in absent]
        self.logger.info("watching %s; restarts via %s", ", ".join(names) or "no services",
                         self.restarter.describe())
        self._worker = threading.Thread(target=self._restart_worker, name="hsm-restarts", daemon=True)
        self._worker.start()

    def run(self) -> None:
        """Judge, act, report; the loop's wait() pings systemd's watchdog."""
        next_report = 0.0
        next_failsafe = 0.0
        while self.wait(float(self.config["check_interval_s"])):
            now = time.monotonic()
            with self._lock:
                actions = self.monitor.evaluate(now)
            for action in actions:
                self._act(action)
            if self._reassert.is_set():
                self._reassert.clear()
                next_failsafe = 0.0
            if now >= next_failsafe:
                if self.monitor.failsafe_active:
                    self._publish_failsafe(True, self.monitor.failsafe_reason, self.monitor.failsafe_service)
                self._relay_operator_failsafe()
                next_failsafe = now + FAILSAFE_REPEAT_S
            if now >= next_report:
                self.publish_system_health(now)
                next_report = now + float(self.config["system_health_interval_s"])

    def on_config_change(self, name: str, value: Any) -> None:
        """Apply a new restart/failsafe policy live; rule and restarter fields apply at the next start."""
        if name in ("max_restarts", "restart_backoff_s", "max_backoff_s", "recovery_s", "failsafe_latch", "confirm_s",
                    "check_interval_s"):
            policy = self._policy()
            with self._lock:
                self.policy = self.monitor.policy = policy
            self.logger.info("%s is now %r", name, value)
        elif name in ("missed_heartbeats", "startup_grace_s", "restarter", "unit_template"):
            self.logger.info("%s changed to %r: takes effect when the HSM restarts", name, value)

    def kill(self) -> None:
        """Stop the restart worker, then release."""
        self._restarts.put(None)
        super().kill()

    # -- actions ------------------------------------------------------------------------------------
    def _act(self, action: Any) -> None:
        if isinstance(action, Stalled):
            self.logger.warning("the HSM itself was stalled for %.1f s (it judges every %g s): no verdict from "
                                "before; each service is judged again once it is heard from, or after its timeout",
                                action.gap_s, float(self.config["check_interval_s"]))
        elif isinstance(action, Cancelled):
            self.logger.info("%s: not acting on '%s': %s since", action.service, action.problem, action.evidence)
        elif isinstance(action, Restart):
            self.logger.warning("restarting %s (restart %d of %d): %s", action.service, action.attempt,
                                self.policy.max_restarts, action.reason)
            self._restarts.put((action.service, action.reason))
        elif isinstance(action, Failed):
            what = "required -> failsafe" if action.required else "not required -> system degraded"
            self.error(f"{action.service} FAILED ({what}): {action.reason}")
        elif isinstance(action, Recovered):
            self.logger.info("%s is healthy again", action.service)
        elif isinstance(action, FailsafeChange):
            if action.active:
                self.error(f"FAILSAFE raised: {action.reason}")
            else:
                self.logger.info("failsafe clear: %s", action.reason)
            self._publish_failsafe(action.active, action.reason, action.service)

    def _restart_worker(self) -> None:
        while True:
            item = self._restarts.get()
            if item is None:
                return
            service, reason = item
            ok, text = self.restart_unless_restarted(service, reason)
            with self._lock:
                self.monitor.restart_result(service, ok, text)

    def restart_unless_restarted(self, service: str, reason: str) -> tuple[bool, str]:
        """Restart *service*, unless its supervisor started it again since the HSM last heard from it.

        Returns ``(ok, account)``. A service killed by systemd's (or the launcher's) watchdog is
        being restarted already: a second restart would only kill the new process as it starts.
        """
        assert self.restarter is not None
        with self._lock:
            heard = self.monitor.heard_ago(service, time.monotonic())
        if heard is not None and self.restarter.started_within(service, heard):
            account = f"not restarting {service}: it was started again since the HSM last heard from it " \
                      f"{heard:.1f} s ago (by {self.restarter.kind})"
            self.logger.info("%s", account)
            return True, account
        try:
            account = self.restarter.restart(service, reason=f"HSM: {reason}")
        except RestartError as exc:
            self.error(str(exc))
            return False, str(exc)
        self.logger.info("%s", account)
        return True, account

    def _relay_operator_failsafe(self) -> None:
        """Re-send the operator's failsafe every second while it is held: ``u2sa failsafe raise`` sends it
        once, and an actuator that restarts (or lost that packet) must still hear it. The operator's clear
        ends it here as everywhere (the CLI sends its clear twice, so a relay in flight cannot outlive it)."""
        reason = self.failsafes.held().get(OPERATOR_SOURCE)
        if reason is None:
            return
        msg = t.Failsafe()
        msg.active, msg.reason = True, reason
        msg.header.system_id, msg.header.source = self.profile.system_id, OPERATOR_SOURCE
        msg.header.timestamp_us = time.time_ns() // 1000
        self.transport.publish(ch.FAILSAFE, msg)

    def _publish_failsafe(self, active: bool, reason: str, service: str) -> None:
        self.failsafes.apply(source=self.name, active=active, reason=reason)
        msg = t.Failsafe()
        msg.active, msg.reason, msg.service = active, reason, service
        self.publish(ch.FAILSAFE, msg)

    def publish_system_health(self, now: float | None = None) -> None:
        """Publish one SystemHealth now."""
        now = time.monotonic() if now is None else now
        with self._lock:
            views = self.monitor.views(now)
            summary = self.monitor.summary(now)
        held = self.failsafes.held()
        failsafe = bool(held)
        if held:
            summary = failsafe_summary(held, services=summary)
        msg = t.SystemHealth()
        msg.failsafe, msg.summary = failsafe, summary
        for v in views:
            s = t.ServiceState()
            s.name, s.state, s.restarts, s.last_error = v.name, v.state, v.restarts, v.last_error[:500]
            s.heartbeat_age_s, s.data_age_s = v.heartbeat_age_s, v.data_age_s
            msg.services.append(s)
        msg.num_services = len(msg.services)
        self.publish(ch.SYSTEM_HEALTH, msg)
        if summary != self._summary:
            self._summary = summary
            self.notify_status(summary)
            self.status = "degraded" if failsafe else "ok"

    def health_details(self) -> dict[str, Any]:
        """Restarter, the HSM's own failsafe, every source holding one, and the number of watched services."""
        return {"restarter": self.restarter.kind if self.restarter else "?", "failsafe": self.monitor.failsafe_active,
                "failsafe_sources": ",".join(sorted(self.failsafes.held())),
                "failsafe_reasons": self.failsafes.reason(), "watched": len(self.rules)}


def failsafe_summary(held: dict[str, str], *, services: str) -> str:
    """The system health's summary while sources hold failsafes: ``FAILSAFE held by A, B -- A: why; B: why``.

    *services* (the HSM's own summary) follows in brackets when the HSM holds none itself.
    """
    text = (f"{FAILSAFE_HELD} {', '.join(sorted(held))} -- "
            + "; ".join(f"{src}: {why or 'no reason given'}" for src, why in sorted(held.items())))
    return text if services.startswith("FAILSAFE") else f"{text} [{services}]"
