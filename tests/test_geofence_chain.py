"""The geofence in the safety chain, real processes: a mock RC receiver, the rc_mux service and a pwm_servo
actuator on sysfs PWM (as tests/test_safety_chain.py), with a fence in the profile and this test standing in
for the estimator on STATE_ESTIMATE. Pre-arm refuses autonomy outside the fence naming it; in autonomy a
breach takes the outputs to neutral (on_check_lost "neutral") or holds them ("hold"); the pilot's manual
control still works outside the fence; autonomy never comes back by itself."""

from __future__ import annotations

import shutil
import tempfile
import threading
import tomllib
from pathlib import Path
from typing import Any, Iterator

import pytest
import tomli_w
from can_mock_harness import Commander
from conftest import ServiceProcesses
from gpio_driver_harness import BusCollector
from serial_driver_harness import start_driver
from test_safety_chain import MIXER, RC_LINES, Chain, write_vehicle

from u2sa_hw.mocks.gpio_chip import MockGpioChip
from u2sa_hw.mocks.rc_receiver import RcReceiverMock
from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.service.health import set_details
from u2sa_hw.bus.client import BusClient
from u2sa_hw.cli.health_cmd import autonomy_line, autonomy_report
from u2sa_hw.messages import STATE_FIELDS  # noqa: F401 - installs the presence setters

FENCE = {"circles": [{"name": "yard", "local_center": [0, 0], "radius_m": 20}]}
BREACH = "geofence: outside inclusion circle 'yard'"


def as_health(details: dict[str, str]) -> t.Health:
    """A Health message carrying *details* (what u2sa health reads them from)."""
    msg = t.Health()
    set_details(msg, details)
    return msg


class Estimator:
    """Publishes STATE_ESTIMATE as the profile's estimator, at the position last set, every 50 ms."""

    def __init__(self, bus: BusClient) -> None:
        self.bus, self.at = bus, (0.0, 0.0)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="estimator", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.05):
            msg = t.StateInformation()
            msg.header.source = msg.sensor_name = "estimator"
            msg.set(x=self.at[0], y=self.at[1], psi=0.0, x_sigma=0.3, y_sigma=0.3, psi_sigma=0.01)
            self.bus.publish(ch.STATE_ESTIMATE, msg)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)


@pytest.fixture(params=["neutral", "hold"])
def fenced(request: Any, tmp_path: Path, services: ServiceProcesses,
           bus: BusClient) -> Iterator[tuple[Chain, Estimator, str]]:
    sockets = Path(tempfile.mkdtemp(prefix="u2sa-gf-", dir="/tmp"))
    chip = MockGpioChip(socket_path=str(sockets / "gpio.sock")).start()
    rc = RcReceiverMock(chip, lines=RC_LINES, frame_hz=50).start()
    from u2sa_hw.ports.pwm.port import make_sysfs_pwm_tree

    pwm = make_sysfs_pwm_tree(tmp_path / "pwmchip0", npwm=2)
    path = write_vehicle(tmp_path, safety={"manual_mixer": MIXER, "rc_mode_timeout_ms": 250,
                                           "on_check_lost": request.param,
                                           "prearm": {"estimator": False}}, socket=chip.socket_path, pwm=pwm)
    profile = tomllib.loads(path.read_text())
    profile["services"]["estimator"] = {"kind": "state_estimator", "required": False}   # stood in for by the test
    profile["geofence"] = FENCE
    path.write_text(tomli_w.dumps(profile))
    col = BusCollector(bus).listen(ch.RC_MODE, t.RcMode).listen(ch.HEALTH, t.Health)
    estimator = Estimator(bus)
    procs = {"drive": start_driver(services, path, "drive"), "rc": start_driver(services, path, "rc")}
    try:
        yield Chain(rc=rc, pwm=pwm, procs=procs, col=col, bus=bus), estimator, request.param
    finally:
        estimator.close()
        services.stop_all()
        rc.stop()
        chip.stop()
        shutil.rmtree(sockets, ignore_errors=True)


def test_the_fence_refuses_autonomy_outside_and_stops_or_holds_on_a_breach(
        fenced: tuple[Chain, Estimator, str]) -> None:
    chain, estimator, action = fenced
    estimator.at = (30.0, 0.0)                                  # outside: pre-arm refuses, naming the fence
    chain.mode(lambda m: m.mode == 0 and BREACH in m.blocked_by, "the geofence check failing in manual")
    chain.rc.set_mode_switch(True)
    refused = chain.mode(lambda m: m.mode == 1 and not m.armed, "autonomy refused outside the fence")
    assert not refused.autonomy_enabled and BREACH in refused.blocked_by

    chain.rc.set_mode_switch(False)                             # the pilot drives back in by hand
    chain.rc.set_pulse("throttle", 1000)
    chain.wait_duty(1, 1000.0, "the pilot's stick drives the ESC in manual, outside the fence")
    chain.rc.set_pulse("throttle", 1500)
    estimator.at = (0.0, 0.0)
    chain.mode(lambda m: m.mode == 0 and m.armed and not m.blocked_by.startswith("pre-arm"), "inside: armed")

    control = Commander(chain.bus, period=0.05)
    try:
        control.hold(esc=40.0)
        chain.rc.set_mode_switch(True)
        chain.mode(lambda m: m.mode == 1 and m.autonomy_enabled and not m.blocked_by, "autonomy granted inside")
        chain.wait_duty(1, 1700.0, "the control system drives in autonomy")

        since = chain.col.count(ch.HEALTH)
        estimator.at = (25.0, 0.0)                              # the breach, while autonomous
        chain.wait_duty(1, 1500.0, "neutral on the breach, though autonomous commands keep coming")
        # neutral: disarmed, RC_MODE names the breach; hold: RC_MODE says hold, the rc service's health names it
        lost = chain.mode(lambda m: m.mode == 1 and (m.hold or BREACH in m.blocked_by), "the breach acted on")
        details = chain.col.health_of("rc", lambda d: BREACH in d["prearm_failed"] and d["checks_lost"] == "1",
                                      since=since, message="the breach, a check lost while autonomous, in health")
        line = autonomy_line(autonomy_report({"rc": as_health(details)})[0])   # what u2sa health prints
        assert BREACH in line and ("GRANTED, but HOLD" in line if action == "hold" else "refused" in line), line
        if action == "hold":
            assert lost.hold and lost.autonomy_enabled, f"not held: {lost}"
        else:
            assert not lost.armed and not lost.autonomy_enabled and not lost.hold, f"not disarmed: {lost}"

        estimator.at = (0.0, 0.0)                               # back inside: autonomy waits for the pilot
        chain.mode(lambda m: m.mode == 1 and BREACH not in m.blocked_by, "the check holding again")
        later = chain.mode(lambda m: m.mode == 1, "another RC_MODE")
        assert not (later.autonomy_enabled and not later.hold), "autonomy came back by itself"
        assert chain.duty_us(1) == pytest.approx(1500.0, abs=1.0)
    finally:
        control.close()
