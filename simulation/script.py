"""Fire a scenario's events on a running simulation (``u2sa sim --scenario FILE``).

:class:`ScriptRunner` acts on what the simulation owns: the mock devices (RC receiver and
its sticks, the GPS), the launcher's processes (signals), and the bus (a forged
``ACTUATOR_CMD``, a ``FAILSAFE`` raised or cleared). It keeps when each event fired
(``time.monotonic_ns()`` just before acting), which :mod:`u2sa_hw.simulation.effects` lines up
with the output log of the mocks.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from typing import Any, Callable, Sequence

from u2sa_hw.simulation.effects import event_effects
from u2sa_hw.simulation.events import Scenario, ScenarioError, ScenarioEvent
from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t

SCRIPT_SOURCE = "scenario"   # header.source of what the scenario runner publishes


def _stamp(msg: Any, source: str, system_id: int, seq: int) -> Any:
    header = msg.header if hasattr(msg, "header") else msg.base.header
    header.system_id, header.source, header.sequence = system_id, source, seq
    header.timestamp_us = time.time_ns() // 1000
    return msg


class ScriptRunner:
    """Fires *scenario*'s events through *run* (a started SimRun) at t0 + at_s."""

    def __init__(self, scenario: Scenario, run: Any) -> None:
        self.scenario = scenario
        self.run = run
        self.fired: list[tuple[ScenarioEvent, int]] = []
        self._seq = 0
        self._threads: list[threading.Thread] = []

    def check(self) -> None:
        """Refuse, before anything moves, an event that names a channel, service or device the run lacks."""
        where = self.scenario.path
        receivers = list(self.run.mocks.context.rc_receivers.values())
        channels = {name for rc in receivers for name in rc.lines}
        for i, event in enumerate(self.scenario.events):
            at = f"{where} event at_s = {event.at_s:g} ({event.action})"
            if event.action in ("rc_loss", "rc_return", "mode", "reengage", "sticks", "centre") and not receivers:
                raise ScenarioError(f"{at}: the profile has no rc_receiver device to act on")
            if event.action == "sticks":
                unknown = sorted(set(event.params) - channels)
                if unknown:
                    raise ScenarioError(f"{at}: RC channel(s) {', '.join(unknown)} not on the receiver "
                                        f"(its channels: {', '.join(sorted(channels))})")
            if event.action == "signal" and event.params["service"] not in self.run.launcher.processes:
                raise ScenarioError(f"{at}: service {event.params['service']!r} is not running "
                                    f"(services: {', '.join(self.run.launcher.processes)})")
            if event.action == "gps_fix" and not self._gps():
                raise ScenarioError(f"{at}: the profile has no nmea_gps device")

    def play(self, t0: float, *, tick: Callable[[str], None]) -> None:
        """Fire every event at t0 + at_s (monotonic s), calling *tick* between them; then wait for the end."""
        for event in self.scenario.events:
            while time.monotonic() < t0 + event.at_s:
                tick(f"next: {event.describe()} at {event.at_s:g} s")
            self.run.progress.event(f"[{time.monotonic() - t0:5.1f} s] scenario: {event.describe()}")
            self.fired.append((event, time.monotonic_ns()))
            self._fire(event, tick)
        while time.monotonic() < t0 + self.scenario.end_s:
            tick(f"scenario '{self.scenario.name}' ends at {self.scenario.end_s:g} s")
        for thread in self._threads:
            thread.join(timeout=5)

    def summary(self, outputs: Any, *, t0: float, end: float, rc_modes: list[tuple[int, str]],
                rc_stalls: Sequence[tuple[int, int]] = ()) -> dict[str, Any]:
        """The summary's ``scenario`` section: the file, and what each fired event did to the outputs."""
        return {"name": self.scenario.name, "file": str(self.scenario.path),
                "description": self.scenario.description,
                "events": event_effects(outputs, self.fired, end_ns=int(end * 1e9), t0_ns=int(t0 * 1e9),
                                        rc_modes=rc_modes, rc_stalls=rc_stalls)}

    # -- the actions ---------------------------------------------------------------------------
    def _gps(self) -> list[Any]:
        return [d.parts[0] for d in self.run.mocks.devices if d.mock == "nmea_gps" and d.parts]

    def _fire(self, event: ScenarioEvent, tick: Callable[[str], None]) -> None:
        mocks, p = self.run.mocks, event.params
        if event.action in ("rc_loss", "rc_return"):
            mocks.signal_loss(event.action == "rc_loss")
        elif event.action == "mode":
            mocks.set_mode_switch(p["value"] == "autonomous")
        elif event.action == "reengage":
            self.run.reengage(tick)
        elif event.action == "sticks":
            mocks.set_sticks(**p)
        elif event.action == "centre":
            for rc in mocks.context.rc_receivers.values():
                rc.centre_sticks()
        elif event.action == "gps_fix":
            for gps in self._gps():
                gps.set_fix(bool(p["fix"]))
        elif event.action == "push":
            self.run.mocks.vehicle.set_push(float(p.get("north_mps", 0.0)), float(p.get("east_mps", 0.0)))
        elif event.action == "signal":
            pid = self.run.launcher.processes[p["service"]].pid
            if pid is not None:
                try:
                    os.kill(pid, getattr(signal, "SIG" + p["signal"]))
                except ProcessLookupError:
                    self.run.progress.event(f"  ! {p['service']} (pid {pid}) was already gone")
        elif event.action == "forge":
            thread = threading.Thread(target=self._forge, args=(p,), name="scenario-forge", daemon=True)
            thread.start()
            self._threads.append(thread)
        elif event.action == "failsafe":
            msg = t.Failsafe()
            msg.active, msg.reason, msg.service = p["active"], p.get("reason", "scenario"), p.get("target", "")
            self._publish(ch.FAILSAFE, msg, p.get("source", "operator"))

    def _forge(self, p: dict[str, Any]) -> None:
        for _ in range(int(p.get("count", 20))):
            cmd = t.PercentageCommand()
            cmd.base.actuator_name, cmd.percentage = p["actuator"], float(p["percent"])
            self._publish(ch.ACTUATOR_CMD, cmd, SCRIPT_SOURCE)
            time.sleep(float(p.get("every_s", 0.05)))

    def _publish(self, channel: str, msg: Any, source: str) -> None:
        self._seq += 1
        self.run.monitor.transport.publish(channel, _stamp(msg, source, self.run.profile.system_id, self._seq))
