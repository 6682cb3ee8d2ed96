"""VESC CAN driver as a real ``u2sa service`` process against mock VESC nodes in a process of
their own on a udp_multicast bus: duty and rpm modes, STATUS in health, odometry, neutral,
silence and faults."""

from __future__ import annotations

import math
import os
import signal
import threading
import uuid
from dataclasses import dataclass
from pathlib import Path
from statistics import mean
from typing import Callable, Iterator

import pytest
from can_mock_harness import GROUP, Commander, MockCanProcess, stop_driver
from conftest import REPO, ServiceProcesses, wait_until
from serial_driver_harness import DriverProbe, start_driver, write_profile

from u2sa_hw.profile.vehicle import VehicleProfile
from u2sa_hw.drivers.can_motor.vesc.driver import VescCanMotor
from u2sa_hw.mocks.vehicle_sim import SimVehicle
from u2sa_hw.mocks.vesc_node import VescCanNode
from u2sa_hw.bus.client import BusClient
from u2sa_hw.config.fields import ConfigError
from u2sa_hw.protocols import vesc_can as vc
from u2sa_hw.protocols.vesc_can import PacketId
from u2sa_hw.bus.udp_ports import private_udp_port

IDS = (10, 11)
POLE_PAIRS = 7
CIRCUMFERENCE = 2 * math.pi * 0.1


def bus_profile(address: str) -> VehicleProfile:
    """A profile (no file) whose device ``motors`` is the CAN bus at *address*."""
    return VehicleProfile(path=None, devices={"motors": {"address": address}})



def wheel_mps(erpm: float) -> float:
    """The mock's wheel surface speed for *erpm* (gear ratio 1)."""
    return erpm / POLE_PAIRS / 60.0 * CIRCUMFERENCE


@pytest.mark.parametrize("settings, words", [
    ({"controller_ids": [10, 255]}, "field 'controller_ids' item 1 must be >= 0 and <= 254; got 255"),
    ({"mode": "current"}, "field 'mode' must be one of"),
    ({"max_duty": 1.5}, "field 'max_duty' must be > 0 and <= 1; got 1.5"),
    ({"neutral": "coast"}, "field 'neutral' must be one of"),
    ({"wheel_radius_m": [0.1, -0.1]}, "field 'wheel_radius_m' item 1 must be > 0 and <= 10; got -0.1"),
    ({"hw_watchdog_timeout_s": 0.1}, "hw_watchdog_timeout_s = 0.1 s must be more than twice command_period_s"),
    ({"hw_watchdog_timeout_s": 0.3, "command_period_s": 0.15}, "more than twice command_period_s"),
    ({"host_id": 1}, "host_id must be a CAN id 0..254 that no VESC uses"),
])
def test_a_bad_config_is_refused_with_the_field_named(lcm_url: str, settings: dict, words: str) -> None:
    with pytest.raises(ConfigError, match=words):
        VescCanMotor("motors", settings=settings)


@dataclass
class Rig:
    """One mock process (two VESCs), the driver process, a probe and a commander."""

    mock: MockCanProcess
    probe: DriverProbe
    driver: object
    commander: Commander

    def wait_outputs(self, left: float, right: float, *, what: str = "", timeout: float = 15.0) -> None:
        wait_until(lambda: self.mock.get("left", "output") == pytest.approx(left, abs=1e-3)
                   and self.mock.get("right", "output") == pytest.approx(right, abs=1e-3), timeout=timeout,
                   message=what or f"wheel speeds {left}, {right} m/s")

    def wait_modes(self, left: tuple[str, float], right: tuple[str, float], *, what: str = "") -> None:
        def now() -> tuple:
            return (self.mock.get("left", "mode"), self.mock.get("left", "command_value"),
                    self.mock.get("right", "mode"), self.mock.get("right", "command_value"))
        wait_until(lambda: now() == (left[0], pytest.approx(left[1]), right[0], pytest.approx(right[1])),
                   timeout=15.0, message=what or f"VESC commands {left}, {right}")

    def wait_ok(self) -> dict[str, str]:
        return self.probe.wait_health(lambda d, s: d.get("left.phase") == "ok" and d.get("right.phase") == "ok",
                                      timeout=20.0, message="both VESCs heard")


@pytest.fixture
def rig(tmp_path: Path, services: ServiceProcesses, bus: BusClient) -> Iterator[Callable[..., Rig]]:
    made: list[Rig] = []

    def make(*, settings: dict | None = None, right: dict | None = None, node: dict | None = None) -> Rig:
        port = private_udp_port()
        nodes = [{"side": "left", "controller_id": IDS[0], "timeout_s": 0.3, **(node or {})},
                 {"side": "right", "controller_id": IDS[1], "timeout_s": 0.3, **(node or {}), **(right or {})}]
        mock = MockCanProcess({"kind": "vesc", "port": port, "nodes": nodes}, repo=REPO, log=tmp_path / "mock.log")
        config = {"controller_ids": list(IDS),
                  "silent_after_s": 0.5, "max_duty": 0.1, "rc_gating": False, **(settings or {})}
        profile = write_profile(tmp_path, name="motors", kind="vesc_can", settings=config,
                                devices={config.get("device_name") or "motors":
                                         f"can://udp_multicast/{GROUP}?port={port}"})
        probe = DriverProbe(bus, "motors")
        driver = start_driver(services, profile, "motors")
        made.append(Rig(mock, probe, driver, Commander(bus)))
        return made[-1]

    yield make
    for r in made:
        r.commander.close()
        r.mock.stop()


def test_duty_commands_status_in_health_and_odometry(rig) -> None:
    r = rig(settings={"directions": [1, -1], "command_timeout_s": 0.0, "rc_gating": False}, right={"direction": -1})
    r.wait_ok()
    r.commander.hold(left=100.0, right=50.0)
    r.wait_modes(("duty", 0.1), ("duty", -0.05), what="100 % -> duty 0.1, 50 % mirrored -> duty -0.05")
    r.wait_outputs(wheel_mps(700), wheel_mps(350))
    r.commander.hold(left=-250.0)  # limited to -100 %
    r.wait_modes(("duty", -0.1), ("duty", -0.05))

    r.commander.hold(left=80.0, right=40.0)
    r.wait_outputs(wheel_mps(560), wheel_mps(280))
    details = r.probe.wait_health(lambda d, s: d["left.erpm"] == "560" and d["right.erpm"] == "-280",
                                  message="STATUS ERPM in health")
    assert (details["left.temp_fet_c"], details["left.temp_motor_c"], details["left.voltage_in_v"]) == \
        ("30.0", "28.0", "24.0")
    assert float(details["left.duty"]) == pytest.approx(0.08, abs=1e-3) and int(details["left.tachometer"]) > 0
    assert details["status"] == "ok" and details["degraded_reason"] == ""
    since = r.probe.state_count()
    msg = r.probe.wait_states(20, since=since + 10, message="odometry from STATUS")[-1][0]
    truth = r.mock.truth()
    assert msg.reference_frame == "FRD" and msg.x_dot == pytest.approx(truth["speed"], rel=0.02)
    assert msg.psi_dot == pytest.approx(truth["yaw_rate"], rel=0.02) and truth["yaw_rate"] > 0.5

    # commands stop, command timeout off: the driver re-sends within the VESCs' 0.3 s timeout
    r.commander.release()
    r.probe.health_after(6)
    assert r.mock.get("left", "mode") == "duty" and r.mock.get("left", "output") == pytest.approx(wheel_mps(560))


def test_rpm_mode_and_tachometer_odometry(rig) -> None:
    r = rig(settings={"mode": "rpm", "max_erpm": 1000.0, "command_timeout_s": 0.0, "rc_gating": False, "odometry_source": "position",
                      "odometry_window_s": 0.5})
    r.wait_ok()
    r.commander.hold(left=100.0, right=60.0)
    r.wait_modes(("rpm", 1000.0), ("rpm", 600.0), what="100 % -> 1000 ERPM, 60 % -> 600 ERPM")
    r.wait_outputs(wheel_mps(1000), wheel_mps(600))
    since = r.probe.state_count()
    states = [m for m, _ in r.probe.wait_states(40, since=since + 40, message="odometry from the tachometer")][-30:]
    truth = r.mock.truth()
    assert mean(m.x_dot for m in states) == pytest.approx(truth["speed"], rel=0.05)
    assert mean(m.psi_dot for m in states) == pytest.approx(truth["yaw_rate"], rel=0.1)


def test_neutral_on_command_timeout_and_failsafe(rig, bus: BusClient) -> None:
    r = rig(settings={"command_timeout_s": 0.5})
    r.wait_ok()
    r.commander.hold(left=50.0, right=50.0)
    r.wait_outputs(wheel_mps(350), wheel_mps(350))
    r.commander.release()
    r.wait_modes(("current", 0.0), ("current", 0.0), what="SET_CURRENT 0 (release) after the command timeout")
    r.wait_outputs(0.0, 0.0)
    r.probe.wait_health(lambda d, s: d["command_timed_out"] == "True", message="command_timed_out in health")

    reply = bus.set_config("motors", "neutral", "zero")
    assert reply is not None and reply.ok, reply
    refused = bus.set_config("motors", "max_duty", "2.0")
    assert refused is not None and not refused.ok and "max_duty" in refused.error
    r.commander.hold(left=50.0, right=-50.0)
    r.wait_outputs(wheel_mps(350), -wheel_mps(350))
    r.commander.failsafe(True)
    r.wait_modes(("duty", 0.0), ("duty", 0.0), what="duty 0 on FAILSAFE with neutral = zero")
    r.probe.wait_health(lambda d, s: s == "degraded" and int(d["ignored"]) > 2 and "failsafe" in d["degraded_reason"],
                        message="commands ignored during the failsafe")
    assert r.mock.get("left", "output") == 0.0
    r.commander.failsafe(False)
    r.wait_outputs(wheel_mps(350), -wheel_mps(350), what="driving again after the failsafe")


def test_silence_and_a_fault_are_reported_and_recovered_from(rig) -> None:
    r = rig(settings={"command_timeout_s": 0.5, "stall_after_s": 0.5})
    r.wait_ok()
    r.commander.hold(left=40.0, right=40.0)
    r.wait_outputs(wheel_mps(280), wheel_mps(280))
    r.mock.call("left", "stop_answering", True)
    details = r.probe.wait_health(lambda d, s: d["left.phase"] == "silent" and d["right.phase"] == "ok",
                                  message="left silent")
    assert details["status"] == "degraded" and "left (id 10) node silent" in details["degraded_reason"]
    r.mock.call("left", "inject_garbage", 2)  # forced onto the bus even while silent
    r.mock.call("left", "stop_answering", False)
    details = r.probe.wait_health(lambda d, s: s == "ok" and d["left.phase"] == "ok", message="left back")
    assert details["left.silent_events"] == "1" and int(details["dropped"]) >= 2
    r.wait_outputs(wheel_mps(280), wheel_mps(280))

    r.mock.call("right", "set_fault", 3)  # DRV fault: motor released, commands ignored, nothing on the bus
    details = r.probe.wait_health(lambda d, s: d["right.phase"] == "stalled", message="right not following")
    assert "right (id 11) not turning" in details["degraded_reason"] and details["left.phase"] == "ok"
    assert details["right.stall_events"] == "1" and details["left.stall_events"] == "0"
    assert "commanded 40 %" in details["last_error"]
    r.mock.call("right", "set_fault", 0)
    r.probe.wait_health(lambda d, s: s == "ok" and d["right.phase"] == "ok", message="right follows again")
    r.wait_outputs(wheel_mps(280), wheel_mps(280))
    assert r.driver.poll() is None


@pytest.mark.parametrize(("how", "neutral"), [("u2sa stop", "release"), ("SIGTERM", "release"), ("u2sa stop", "zero"),
                                              ("SIGTERM", "zero")])
def test_stop_over_the_bus_and_sigterm_leave_the_motors_at_zero(rig, bus: BusClient, how: str, neutral: str) -> None:
    # the VESCs' own command timeout is off here: only the driver's last frames can bring them to zero
    # (hw_watchdog off too: the driver would set the VESCs' timeout over CAN, and on a slow machine the
    # mock's watchdog then releases the motors before the state is read)
    r = rig(settings={"command_timeout_s": 0.0, "rc_gating": False, "neutral": neutral, "hw_watchdog": False},
            node={"timeout_s": 0.0})
    r.wait_ok()
    r.commander.hold(left=50.0, right=-50.0)
    r.wait_modes(("duty", 0.05), ("duty", -0.05), what="duty 5 % both ways")
    r.commander.close()
    marks = {side: len(r.mock.received(side)) for side in ("left", "right")}
    stop_driver(r.driver, bus, how)
    for side, controller in zip(("left", "right"), IDS):
        ids = [(vc.split_ext_id(can_id), data) for can_id, data in r.mock.received(side)[marks[side]:]]
        sent = [(packet, vc.decode_command(packet, data)) for (packet, target), data in ids
                if target == controller and packet in vc.COMMAND_SCALES]
        zero = (PacketId.SET_CURRENT if neutral == "release" else PacketId.SET_DUTY, 0.0)
        assert zero in sent, f"{side}: neutral ({neutral}) sent on the way out"
        assert sent[-1] == (PacketId.SET_CURRENT, 0.0), f"{side}: released last"   # whatever neutral says
        assert (r.mock.get(side, "mode"), r.mock.get(side, "command_value"), r.mock.get(side, "output")) == \
            ("current", 0.0, 0.0)


# ---------------------------------------------------------------- the VESC's own timeout ---------
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGSTOP])
def test_the_driver_sets_timeout_msec_reads_it_back_and_a_dead_driver_is_stopped_by_it(rig, sig: int) -> None:
    r = rig(settings={"command_timeout_s": 0.5}, node={"timeout_s": 1.0})   # VESC Tool's default 1000 ms
    details = r.probe.wait_health(lambda d, s: d.get("hw_watchdog") == "on 0.30 s (read back)", timeout=20,
                                  message="timeout_msec written and read back")
    assert details["left.hw_watchdog"] == details["right.hw_watchdog"] == "on 0.30 s (read back)"
    for side in ("left", "right"):   # written once (it goes to flash), then read back
        assert (r.mock.get(side, "timeout_s"), r.mock.get(side, "appconf_writes")) == (0.3, 1)
    r.commander.hold(left=50.0, right=-50.0)
    r.wait_modes(("duty", 0.05), ("duty", -0.05))
    assert r.mock.get("left", "timeouts") == []   # fed while the driver runs
    try:
        os.kill(r.driver.pid, sig)   # no neutral on the way out: only the VESCs' timeout can stop them
        r.wait_outputs(0.0, 0.0, timeout=20, what="both motors released by timeout_msec")
        for side in ("left", "right"):
            assert r.mock.get(side, "mode") == "released" and len(r.mock.get(side, "timeouts")) == 1
    finally:
        r.commander.close()
        if r.driver.poll() is None:
            r.driver.kill()
            r.driver.wait(timeout=10)


def test_a_timeout_that_does_not_read_back_is_an_error_naming_the_vesc(rig, bus: BusClient) -> None:
    r = rig(settings={"command_timeout_s": 0.5})   # the nodes already have 300 ms: read, nothing written
    r.probe.wait_health(lambda d, s: d.get("hw_watchdog") == "on 0.30 s (read back)", timeout=20,
                        message="timeout_msec read back")
    assert r.mock.get("left", "appconf_writes") == 0
    r.mock.call("right", "freeze_config", True)   # its flash write fails: the old value stays
    reply = bus.set_config("motors", "hw_watchdog_timeout_s", "0.4")
    assert reply is not None and reply.ok, reply
    details = r.probe.wait_health(lambda d, s: d["right.hw_watchdog"].startswith("read back"), timeout=20,
                                  message="the right VESC's read-back error")
    assert details["right.hw_watchdog"].startswith("read back timeout_msec 300 ms after writing 400 ms; set it in "
                                                   "VESC Tool (App Settings > General > Timeout = 400 ms")
    assert "VESC right (id 11 on motors): watchdog read back" in details["last_error"]
    details = r.probe.wait_health(lambda d, s: d["left.hw_watchdog"] == "on 0.40 s (read back)" and s == "degraded",
                                  timeout=20, message="left fine, service degraded")
    assert "right (id 11) watchdog read back timeout_msec 300 ms" in details["degraded_reason"]
    assert r.mock.get("left", "timeout_s") == 0.4 and r.mock.get("right", "timeout_s") == 0.3


def test_a_vesc_that_does_not_answer_configuration_reads_is_an_error_with_the_fix(lcm_url: str) -> None:
    channel = f"vesc-wd-{uuid.uuid4().hex[:8]}"
    vehicle = SimVehicle(origin_lat=0.0, origin_lon=0.0)
    nodes = [VescCanNode(vehicle, side=side, controller_id=i, interface="virtual", channel=channel, timeout_s=0.3)
             for side, i in zip(("left", "right"), IDS)]
    nodes[1].answer_comm = False   # CAN mode not VESC: STATUS frames, but no COMM packets
    svc = VescCanMotor("motors", profile=bus_profile(f"can://virtual/{channel}"),
                       settings={"controller_ids": list(IDS), "odometry": False, "rc_gating": False,
                                 "command_timeout_s": 0.5})
    runner = threading.Thread(target=svc.run, daemon=True)
    try:
        vehicle.start()
        for node in nodes:
            node.start()
        svc.start()
        runner.start()
        details = wait_until(lambda: (d := svc.health_details())["right.hw_watchdog"].startswith("no answer") and d,
                             timeout=30, message="the right VESC reported as not answering")
        assert details["right.hw_watchdog"].startswith("no answer to COMM_GET_APPCONF after 3 tries; check that "
                                                       "App Settings > General > CAN Mode is VESC")
        assert details["left.hw_watchdog"] == "on 0.30 s (read back)"
        assert "VESC right (id 11 on motors): watchdog no answer" in svc.last_error
        wait_until(lambda: svc.status == "degraded"
                   and "right (id 11) watchdog no answer" in svc.health_details()["degraded_reason"],
                   message="degraded with the reason")
    finally:
        svc.stop()
        runner.join(timeout=10)
        svc.kill()
        svc.transport.stop()
        for node in nodes:
            node.stop()
        vehicle.stop()
