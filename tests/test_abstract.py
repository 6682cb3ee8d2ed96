"""Sensor and Actuator base classes over a real LCM transport (in one process)."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

from conftest import wait_until

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.abstract import Actuator, ExteroceptiveSensor, ProprioceptiveSensor
from u2sa_hw.bus.client import BusClient


class RecordingActuator(Actuator):
    """An actuator that records what it was told to do."""

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.outputs: list[tuple[str, float]] = []

    def on_percentage(self, actuator: str, percent: float) -> None:
        self.outputs.append((actuator, percent))

    def neutral(self) -> None:
        self.outputs.append(("neutral", 0.0))

    def run(self) -> None:
        while self.wait(0.02):
            self.check_command_timeout()


def _command(name: str, pct: float) -> t.PercentageCommand:
    cmd = t.PercentageCommand()
    cmd.base.actuator_name = name
    cmd.percentage = pct
    return cmd


def _run(service: Any) -> threading.Thread:
    service.start()
    thread = threading.Thread(target=service.run, daemon=True)
    thread.start()
    return thread


def test_actuator_acts_only_on_its_name_clamps_and_times_out(tmp_path: Path, lcm_url: str, bus: BusClient) -> None:
    act = RecordingActuator("left", config_path=tmp_path / "left.toml", settings={"command_timeout_s": 0.3, "rc_gating": False})
    thread = _run(act)
    try:
        bus.publish(ch.ACTUATOR_CMD, _command("right", 50))
        bus.publish(ch.ACTUATOR_CMD, _command("left", 150))
        wait_until(lambda: ("left", 100.0) in act.outputs, message="the clamped command")
        assert not any(name == "right" for name, _ in act.outputs)
        wait_until(lambda: act.outputs[-1] == ("neutral", 0.0), message="neutral after the command timeout")
        assert act.health_details()["command_timed_out"] is True
    finally:
        act.stop()
        thread.join(5)
        act.kill()
        act.transport.stop()


def test_failsafe_forces_neutral_and_blocks_commands(tmp_path: Path, lcm_url: str, bus: BusClient) -> None:
    act = RecordingActuator("thruster", config_path=tmp_path / "t.toml", settings={"command_timeout_s": 0.0, "rc_gating": False})
    thread = _run(act)
    try:
        fs = t.Failsafe()
        fs.active, fs.reason = True, "test"
        bus.publish(ch.FAILSAFE, fs)
        wait_until(lambda: act.failsafe_active and act.outputs[-1:] == [("neutral", 0.0)], message="the failsafe")
        bus.publish(ch.ACTUATOR_CMD, _command("thruster", 40))
        wait_until(lambda: act.commands_ignored >= 1, message="the command to be ignored")
        assert ("thruster", 40.0) not in act.outputs
        estop = t.Failsafe()
        estop.active, estop.reason, estop.header.source = True, "e-stop pressed", "estop"
        bus.publish(ch.FAILSAFE, estop)
        wait_until(lambda: "estop" in act.failsafe_sources, message="the second source")
        fs.active = False
        bus.publish(ch.FAILSAFE, fs)  # one source clears; the e-stop still holds
        wait_until(lambda: len(act.failsafe_sources) == 1, message="the first source to clear")
        assert act.failsafe_active
        estop.active = False
        bus.publish(ch.FAILSAFE, estop)
        wait_until(lambda: not act.failsafe_active, message="the failsafe to clear")
        bus.publish(ch.ACTUATOR_CMD, _command("thruster", 40))
        wait_until(lambda: ("thruster", 40.0) in act.outputs, message="commands after the failsafe")
    finally:
        act.stop()
        thread.join(5)
        act.kill()
        act.transport.stop()


def test_sensors_publish_with_their_name(tmp_path: Path, lcm_url: str, bus: BusClient) -> None:
    states: list[t.StateInformation] = []
    objects: list[Any] = []
    bus.transport.subscribe(ch.STATE_INFO, t.StateInformation, lambda _c, m: states.append(m))
    bus.transport.subscribe(ch.OBJECTS, t.ObjectDescription, lambda _c, m: objects.append(m))
    compass = ProprioceptiveSensor("compass", config_path=tmp_path / "c.toml")
    sonar = ExteroceptiveSensor("sonar", config_path=tmp_path / "s.toml")
    for s in (compass, sonar):
        s.start()
    try:
        compass.publish_state(t.StateInformation().set(psi=0.7))
        circle = t.Circle()
        circle.base.base.uid, circle.radius = "rock", 1.0
        sonar.publish_object(circle)
        wait_until(lambda: states and objects, message="the sensor messages")
        assert states[0].sensor_name == "compass" and states[0].present_fields() == ["psi"]
        assert isinstance(objects[0], t.Circle) and objects[0].base.base.source == "sonar"
        assert objects[0].base.base.header.source == "sonar"
    finally:
        for s in (compass, sonar):
            s.kill()
            s.transport.stop()


def test_check_config_refuses_a_change_before_it_is_written(tmp_path: Path, lcm_url: str) -> None:
    from u2sa_hw.config.fields import ConfigError, field
    from u2sa_hw.service.contract import U2SAService

    class RateService(U2SAService):
        CONFIG = (field("rate_hz", 10.0, le=1000), field("burst", 2, le=100))

        def check_config(self) -> None:
            if self.config["rate_hz"] * self.config["burst"] > 100:
                raise ConfigError("rate_hz * burst must stay <= 100")

    svc = RateService("rates", config_path=tmp_path / "rates.toml")
    try:
        assert svc.config.set("burst", 5)
        before = (tmp_path / "rates.toml").read_bytes()
        ok, reason = svc.config.try_set("rate_hz", 50.0)
        assert not ok and "rate_hz * burst must stay <= 100" in reason
        assert svc.config["rate_hz"] == 10.0 and (tmp_path / "rates.toml").read_bytes() == before
        assert svc.config.set("rate_hz", 20.0)
    finally:
        svc.transport.stop()


def test_no_command_is_obeyed_after_the_final_neutral_of_kill(tmp_path: Path, lcm_url: str) -> None:
    act = RecordingActuator("esc", config_path=tmp_path / "esc.toml", settings={"rc_gating": False})
    act.kill()
    assert act.outputs[-1] == ("neutral", 0.0)
    # a command the transport delivers in the window between kill() and the transport's stop
    act._on_autonomous_command(_command("esc", 55.0))
    assert act.outputs[-1] == ("neutral", 0.0) and ("esc", 55.0) not in act.outputs
    act.transport.stop()
