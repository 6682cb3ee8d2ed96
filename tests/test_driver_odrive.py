"""ODrive CAN driver: the wheel odometry on its own, then the driver as a real ``u2sa service``
process against mock ODrive nodes in a process of their own on a udp_multicast bus."""

from __future__ import annotations

import math
import os
import random
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import pytest
from can_mock_harness import GROUP, Commander, MockCanProcess, stop_driver
from conftest import REPO, ServiceProcesses, wait_until
from serial_driver_harness import DriverProbe, start_driver, write_profile

from u2sa_hw.profile.vehicle import VehicleProfile
from u2sa_hw.drivers.can_motor.diff_drive_odometry import DiffDriveOdometry, WheelTravel, body_motion
from u2sa_hw.drivers.can_motor.odrive.driver import OdriveCanMotor, error_names
from u2sa_hw.mocks import can_adapter
from u2sa_hw.mocks.odrive_config import ENABLE_WATCHDOG_ENDPOINT, MOCK_FW, WATCHDOG_TIMEOUT_ENDPOINT
from u2sa_hw.mocks.odrive_node import OdriveCanNode
from u2sa_hw.mocks.vehicle_sim import SimVehicle
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.config.fields import ConfigError
from u2sa_hw.ports.tap import RX, TX, raw_channel
from u2sa_hw.protocols.odrive_cansimple import (AxisError05, AxisState, Cmd, Heartbeat, OdriveError, ProcedureResult,
                                                arbitration_id, decode_set_axis_state, encode_heartbeat, make_frame)
from u2sa_hw.protocols.odrive_cansimple import decode_set_input_vel as cs_decode_vel
from u2sa_hw.bus.udp_ports import private_udp_port

CIRCUMFERENCE = 2 * math.pi * 0.1  # the mock's default wheel radius
NODES = (3, 4)


# ---------------------------------------------------------------- odometry, pure ---------------
def test_body_motion_is_frd_with_yaw_positive_to_the_right() -> None:
    assert body_motion(1.0, 1.0, 0.5) == (1.0, 0.0)
    speed, yaw_rate = body_motion(1.0, 0.5, 0.5)  # left wheel faster: turning right, psi grows
    assert (speed, yaw_rate) == (0.75, 1.0)
    assert body_motion(-0.5, 0.5, 0.5) == (0.0, -2.0)


def bus_profile(address: str) -> VehicleProfile:
    """A profile (no file) whose device ``motors`` is the CAN bus at *address*."""
    return VehicleProfile(path=None, devices={"motors": {"address": address}})



def test_wheel_travel_uses_deltas_over_the_window_and_restarts_on_a_jump() -> None:
    wheel = WheelTravel(window_s=0.1, max_wheel_speed_mps=5.0)
    assert wheel.add(0.0, 0.0) is None
    speeds = [wheel.add(0.02 * i, 0.02 * i * 1.5) for i in range(1, 20)]
    assert all(s == pytest.approx(1.5) for s in speeds)
    assert wheel.add(0.40, -3.0) is None  # a controller reboot zeroed (here: moved) its position
    assert wheel.resets == 1
    assert wheel.add(0.42, -3.0 + 0.02) == pytest.approx(1.0)
    assert wheel.add(0.42, 7.0) is None and wheel.add(float("nan"), 0.0) is None  # duplicate time, NaN


def test_odometry_pairs_one_fresh_sample_per_side() -> None:
    odo = DiffDriveOdometry(track_width_m=0.5, source="velocity", max_skew_s=0.05)
    assert odo.update("left", 1.00, speed_mps=1.0) is None
    assert odo.update("left", 1.02, speed_mps=1.0) is None  # still waiting for the right side
    motion = odo.update("right", 1.03, speed_mps=0.5)
    assert motion is not None and (motion.t, motion.speed_mps, motion.yaw_rate_rad_s) == (1.03, 0.75, 1.0)
    assert odo.update("right", 1.05, speed_mps=0.5) is None
    assert odo.update("left", 1.20, speed_mps=1.0) is None  # the right sample is too old to pair
    assert odo.unpaired == 1
    positions = DiffDriveOdometry(track_width_m=0.5, source="position", window_s=0.05)
    out = [positions.update(side, 0.01 * i, position_m=0.01 * i * (2.0 if side == "left" else 1.0))
           for i in range(10) for side in ("left", "right")]
    assert [m for m in out if m][-1].speed_mps == pytest.approx(1.5)
    with pytest.raises(ValueError):
        DiffDriveOdometry(track_width_m=0.0)


def test_odometry_refuses_speeds_no_wheel_has_and_counts_them() -> None:
    odo = DiffDriveOdometry(track_width_m=0.5, source="velocity", max_wheel_speed_mps=20.0)
    for t0, speed in ((1.0, 1.9e38), (1.01, float("inf")), (1.02, float("nan")), (1.03, -20.5)):
        assert odo.update("left", t0, speed_mps=speed) is None
    assert odo.rejected == 4
    assert odo.update("left", 1.04, speed_mps=20.0) is None   # the limit itself is a speed a wheel can have
    motion = odo.update("right", 1.05, speed_mps=-20.0)
    assert motion is not None and motion.speed_mps == 0.0 and motion.yaw_rate_rad_s == pytest.approx(80.0)


def test_error_names_decode_both_firmware_lines() -> None:
    bits = int(OdriveError.ESTOP_REQUESTED | OdriveError.DRV_FAULT) | 0x80000000
    assert error_names(bits, firmware="0.6") == "DRV_FAULT|ESTOP_REQUESTED|0x80000000"
    assert error_names(int(AxisError05.MOTOR_FAILED), firmware="0.5") == "MOTOR_FAILED"
    assert error_names(0, firmware="0.6") == "none"


@pytest.mark.parametrize("settings, words", [
    ({"node_ids": [1]}, "one entry per actuator"),
    ({"node_ids": [1, 1]}, "node_ids must be distinct"),
    ({"node_ids": [1, 63]}, "field 'node_ids' item 1 must be >= 0 and <= 62; got 63"),
    ({"watchdog_timeout_endpoint": 70000}, "field 'watchdog_timeout_endpoint' must be >= 0 and <= 65535"),
    ({"directions": [1, 2]}, "field 'directions' item 1 must be >= -1 and <= 1; got 2"),
    ({"directions": [1, 0]}, "1 or -1"),
    ({"max_turns_per_s": 0.0}, "field 'max_turns_per_s' must be > 0 and <= 1000; got 0.0"),
    ({"firmware": "0.4"}, "field 'firmware' must be one of"),
    ({"odometry_left": "port"}, "is not one of the actuators"),
])
def test_a_bad_config_is_refused_with_the_field_named(lcm_url: str, settings: dict, words: str) -> None:
    with pytest.raises(ConfigError, match=words):
        OdriveCanMotor("motors", settings=settings)


class StubbornNode:
    """A CANSimple node on a virtual bus that reports IDLE / NOT_CALIBRATED and ignores arming
    until ``accept`` is set; it records when each Set_Axis_State arrived."""

    def __init__(self, channel: str, node_id: int) -> None:
        import can

        self.bus = can.Bus(interface="virtual", channel=channel)
        self.node_id = node_id
        self.accept = False
        self.state = AxisState.IDLE
        self.arm_requests: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        next_hb = 0.0
        while not self._stop.is_set():
            msg = self.bus.recv(timeout=0.01)
            if msg is not None and msg.arbitration_id == arbitration_id(self.node_id, Cmd.SET_AXIS_STATE):
                self.arm_requests.append(time.monotonic())
                if self.accept:
                    self.state = AxisState.CLOSED_LOOP_CONTROL
            if time.monotonic() >= next_hb:
                next_hb = time.monotonic() + 0.05
                result = ProcedureResult.SUCCESS if self.accept else ProcedureResult.NOT_CALIBRATED
                self.bus.send(make_frame(self.node_id, Cmd.HEARTBEAT, encode_heartbeat(Heartbeat(0, self.state, result))))

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.bus.shutdown()


def test_arming_that_does_not_take_is_retried_with_doubling_waits_and_reported(lcm_url: str) -> None:
    channel = f"odrive-arm-{random.randint(0, 1 << 30)}"
    node = StubbornNode(channel, 5)
    svc = OdriveCanMotor("motors", profile=bus_profile(f"can://virtual/{channel}"), settings={
        "actuators": ["wheel"], "node_ids": [5], "directions": [1],
        "wheel_radius_m": [0.1], "odometry": False, "arm_retry_s": 0.2, "silent_after_s": 1.0})
    runner = threading.Thread(target=svc.run, daemon=True)
    try:
        svc.start()
        runner.start()
        wait_until(lambda: len(node.arm_requests) >= 4, timeout=20, message="four arming attempts")
        with svc.lock:  # the wait before the next attempt doubles from arm_retry_s with every attempt
            axis = svc.axes["wheel"]
            assert axis.arm_attempts >= 4 and axis.backoff == pytest.approx(min(0.2 * 2 ** axis.arm_attempts, 5.0))
        details = svc.health_details()
        assert details["wheel.phase"] == "arming" and details["wheel.arm_failures"] >= 3
        assert "not in closed loop" in svc.last_error and "NOT_CALIBRATED" in svc.last_error
        assert svc.status == "degraded" and "wheel (node 5) not armed (IDLE)" in details["degraded_reason"]
        node.accept = True
        wait_until(lambda: svc.health_details()["wheel.phase"] == "armed", timeout=20, message="armed at last")
        wait_until(lambda: svc.status == "ok", timeout=5, message="status ok once armed")
        assert svc.axes["wheel"].backoff == 0.2  # armed: the next trouble starts from arm_retry_s again
    finally:
        svc.stop()
        runner.join(timeout=10)
        svc.kill()
        svc.transport.stop()
        node.close()


def test_losing_the_can_adapter_is_reported_counted_and_the_bus_reopened(lcm_url: str) -> None:
    interface = can_adapter.register()
    channel = f"odrive-unplug-{random.randint(0, 1 << 30)}"
    vehicle = SimVehicle(origin_lat=0.0, origin_lon=0.0)
    nodes = {side: OdriveCanNode(vehicle, side=side, node_id=node, interface="virtual", channel=channel,
                                 vel_limit=10.0) for side, node in zip(("left", "right"), NODES)}
    svc = OdriveCanMotor("motors", profile=bus_profile(f"can://{interface}/{channel}"), settings={
        "node_ids": list(NODES), "command_timeout_s": 0.0, "rc_gating": False,
        "silent_after_s": 0.5, "status_poll_s": 0.0, "odometry": False})
    runner = threading.Thread(target=svc.run, daemon=True)

    def phases() -> tuple[str, str]:
        d = svc.health_details()
        return d["left.phase"], d["right.phase"]

    try:
        vehicle.start()
        for node in nodes.values():
            node.start()
        svc.start()
        runner.start()
        wait_until(lambda: phases() == ("armed", "armed"), timeout=20, message="both axes armed")
        svc.on_percentage("left", 50.0)
        wait_until(lambda: nodes["left"].wheel_speed_mps == pytest.approx(CIRCUMFERENCE, abs=1e-3),
                   message="the left wheel at 1 rev/s")

        can_adapter.unplug(channel)      # the adapter is gone: the open bus fails, reopening fails
        details = wait_until(lambda: (d := svc.health_details())["bus"] == "down" and d, message="the bus down")
        assert details["bus_losses"] == 1 and "receive failed, bus lost (Network is down" in svc.last_error
        details = wait_until(lambda: (d := svc.health_details())["bus"] == "down" and "cannot open CAN bus" in d["bus_error"]
                             and d, message="a failed reopen in health")
        assert "no CAN adapter" in details["bus_error"] and details["bus_losses"] == 1
        wait_until(lambda: svc.status == "degraded", message="degraded while the bus is down")
        assert svc.health_details()["degraded_reason"].startswith("CAN bus down")
        assert set(phases()) <= {"waiting", "silent"}   # what the axes said went with the bus
        assert runner.is_alive()

        can_adapter.replug(channel)
        wait_until(lambda: svc.health_details()["bus"] == "open", message="the bus reopened")
        wait_until(lambda: phases() == ("armed", "armed"), timeout=20, message="both axes heard and armed again")
        svc.on_percentage("left", -30.0)
        wait_until(lambda: nodes["left"].wheel_speed_mps == pytest.approx(-0.6 * CIRCUMFERENCE, abs=1e-3),
                   message="commands obeyed after the reopen")
        details = svc.health_details()
        assert details["bus_losses"] == 1 and details["bus_error"] == ""
        wait_until(lambda: svc.status == "ok", message="ok again")
    finally:
        can_adapter.replug(channel)
        svc.stop()
        runner.join(timeout=10)
        svc.kill()
        svc.transport.stop()
        for node in nodes.values():
            node.stop()
        vehicle.stop()


# ---------------------------------------------------------------- across processes -------------
@dataclass
class Rig:
    """One mock process (two ODrive axes), the driver process, a probe and a commander."""

    mock: MockCanProcess
    probe: DriverProbe
    driver: object
    commander: Commander
    bus: BusClient

    def wheel(self, side: str) -> float:
        return self.mock.get(side, "wheel_speed_mps")

    def wait_wheels(self, left: float, right: float, *, timeout: float = 15.0, what: str = "") -> None:
        wait_until(lambda: self.wheel("left") == pytest.approx(left, abs=1e-3)
                   and self.wheel("right") == pytest.approx(right, abs=1e-3), timeout=timeout,
                   message=what or f"wheel speeds {left}, {right} m/s")

    def wait_phases(self, left: str, right: str, *, timeout: float = 20.0) -> dict[str, str]:
        return self.probe.wait_health(lambda d, s: d.get("left.phase") == left and d.get("right.phase") == right,
                                      timeout=timeout, message=f"axes {left}/{right}")


@pytest.fixture
def rig(tmp_path: Path, services: ServiceProcesses, bus: BusClient) -> Iterator[Callable[..., Rig]]:
    made: list[Rig] = []

    def make(*, settings: dict | None = None, node: dict | None = None, right: dict | None = None) -> Rig:
        port = private_udp_port()
        nodes = [{"side": "left", "node_id": NODES[0], "vel_limit": 10.0, **(node or {})},
                 {"side": "right", "node_id": NODES[1], "vel_limit": 10.0, **(node or {}), **(right or {})}]
        mock = MockCanProcess({"kind": "odrive", "port": port, "nodes": nodes}, repo=REPO, log=tmp_path / "mock.log")
        config = {"node_ids": list(NODES),
                  "silent_after_s": 0.5, "status_poll_s": 0.2, "rc_gating": False, **(settings or {})}
        profile = write_profile(tmp_path, name="motors", kind="odrive_can", settings=config,
                                devices={config.get("device_name") or "motors":
                                         f"can://udp_multicast/{GROUP}?port={port}"})
        probe = DriverProbe(bus, "motors")
        driver = start_driver(services, profile, "motors")
        made.append(Rig(mock, probe, driver, Commander(bus), bus))
        return made[-1]

    yield make
    for r in made:
        r.commander.close()
        r.mock.stop()


def test_commands_drive_the_wheels_within_limits_and_odometry_matches_the_vehicle(rig, bus: BusClient) -> None:
    raw: list[t.RawCanFrame] = []
    bus.transport.subscribe(raw_channel("can0"), t.RawCanFrame, lambda _c, m: raw.append(m))
    r = rig(settings={"max_turns_per_s": 1.5, "directions": [1, -1], "command_timeout_s": 0.0, "rc_gating": False,
                      "record_raw": True, "device_name": "can0", "speed_sigma_mps": 0.03,
                      "status_poll_s": 0.0},  # only the setpoint re-sends may feed the watchdog
            right={"direction": -1, "watchdog_timeout_s": 0.3}, node={"watchdog_timeout_s": 0.3})
    r.wait_phases("armed", "armed")
    r.commander.hold(left=100.0, right=50.0)
    r.wait_wheels(1.5 * CIRCUMFERENCE, 0.75 * CIRCUMFERENCE, what="100 % -> 1.5 rev/s, 50 % -> 0.75 rev/s")
    assert r.mock.get("right", "input_vel") == pytest.approx(-0.75)  # a mirrored motor turns backwards
    r.commander.hold(left=-250.0)  # beyond the range: limited to -max_turns_per_s
    r.wait_wheels(-1.5 * CIRCUMFERENCE, 0.75 * CIRCUMFERENCE)

    r.commander.hold(left=60.0, right=30.0)
    r.wait_wheels(0.9 * CIRCUMFERENCE, 0.45 * CIRCUMFERENCE)
    since = r.probe.state_count()
    states = r.probe.wait_states(20, since=since + 10, message="odometry at the encoder rate")
    truth = r.mock.truth()
    msg = states[-1][0]
    assert msg.reference_frame == "FRD" and msg.sensor_name == "motors"
    assert (msg.has("x_dot"), msg.has("y_dot"), msg.has("psi_dot"), msg.has("x"), msg.has("psi")) == \
        (True, True, True, False, False)
    assert msg.x_dot == pytest.approx(truth["speed"], rel=0.02)
    assert msg.psi_dot == pytest.approx(truth["yaw_rate"], rel=0.02)
    assert truth["yaw_rate"] == pytest.approx((0.9 - 0.45) * CIRCUMFERENCE / 0.5)
    assert (msg.y_dot, msg.x_dot_sigma, msg.psi_dot_sigma) == (0.0, 0.03, 0.05)

    # no more commands and no command timeout: the driver keeps re-sending the setpoint, which keeps
    # the ODrive's 0.3 s CAN watchdog fed for as long as it runs
    r.commander.release()
    r.probe.health_after(6)
    assert (r.mock.get("left", "axis_error"), r.mock.get("left", "axis_state")) == (0, AxisState.CLOSED_LOOP_CONTROL)
    assert r.wheel("left") == pytest.approx(0.9 * CIRCUMFERENCE, abs=1e-3)

    wait_until(lambda: any(f.direction == RX for f in raw) and any(f.direction == TX for f in raw),
               message="raw frames both ways on RAW.can0")
    set_vel = [f for f in raw if f.direction == TX and f.arbitration_id == NODES[0] << 5 | Cmd.SET_INPUT_VEL]
    assert set_vel and set_vel[-1].dlc == 8 and not set_vel[-1].is_extended_id
    assert any(f.arbitration_id == NODES[1] << 5 | Cmd.HEARTBEAT for f in raw if f.direction == RX)


def test_command_timeout_and_failsafe_go_neutral_and_estop_is_cleared_after(rig, bus: BusClient) -> None:
    r = rig(settings={"command_timeout_s": 0.5})
    r.wait_phases("armed", "armed")
    r.commander.hold(left=50.0, right=50.0)
    r.wait_wheels(CIRCUMFERENCE, CIRCUMFERENCE)
    r.commander.release()
    r.wait_wheels(0.0, 0.0, what="0 rev/s once commands stop for command_timeout_s")
    r.probe.wait_health(lambda d, s: d["command_timed_out"] == "True", message="command_timed_out in health")

    r.commander.hold(left=50.0, right=-50.0)
    r.wait_wheels(CIRCUMFERENCE, -CIRCUMFERENCE)
    r.commander.failsafe(True)
    r.wait_wheels(0.0, 0.0, what="neutral on FAILSAFE")
    details = r.probe.wait_health(lambda d, s: s == "degraded" and int(d["ignored"]) > 2,
                                  message="commands ignored during the failsafe")
    assert "failsafe" in details["degraded_reason"]
    assert r.wheel("left") == 0.0 and r.mock.get("left", "axis_state") == AxisState.CLOSED_LOOP_CONTROL
    r.commander.failsafe(False)
    r.wait_wheels(CIRCUMFERENCE, -CIRCUMFERENCE, what="commands obeyed again after the failsafe")

    reply = bus.set_config("motors", "estop_on_failsafe", "true")
    assert reply is not None and reply.ok, reply
    r.commander.failsafe(True)
    wait_until(lambda: r.mock.get("left", "axis_error") & OdriveError.ESTOP_REQUESTED
               and r.mock.get("right", "axis_error") & OdriveError.ESTOP_REQUESTED, message="Estop on both axes")
    r.wait_wheels(0.0, 0.0)
    r.commander.failsafe(False)
    r.wait_phases("armed", "armed")
    r.wait_wheels(CIRCUMFERENCE, -CIRCUMFERENCE, what="cleared, re-armed and driving after the failsafe")
    assert r.driver.poll() is None


def test_a_silent_node_is_reported_and_recovers_while_the_other_keeps_driving(rig) -> None:
    # the nodes send no cyclic estimates here: the driver polls them by RTR
    r = rig(settings={"command_timeout_s": 0.5, "encoder_poll_hz": 25.0}, node={"encoder_hz": 0})
    r.wait_phases("armed", "armed")
    r.probe.wait_states(5, message="odometry from polled encoder estimates")
    r.commander.hold(left=30.0, right=40.0)
    r.wait_wheels(0.6 * CIRCUMFERENCE, 0.8 * CIRCUMFERENCE)
    r.mock.call("left", "stop_answering", True)
    details = r.wait_phases("silent", "armed")
    assert details["status"] == "degraded" and "left (node 3) node silent" in details["degraded_reason"]
    assert "node silent" in details["last_error"] and details["left.silent_events"] == "1"
    r.commander.hold(right=-40.0)
    r.wait_wheels(0.6 * CIRCUMFERENCE, -0.8 * CIRCUMFERENCE, what="the other axis still obeys")
    assert r.driver.poll() is None

    r.mock.call("left", "stop_answering", False)
    details = r.probe.wait_health(lambda d, s: s == "ok" and d["left.phase"] == "armed", message="recovered")
    assert details["degraded_reason"] == ""
    r.commander.hold(left=-20.0)
    r.wait_wheels(-0.4 * CIRCUMFERENCE, -0.8 * CIRCUMFERENCE, what="the recovered axis obeys again")


@pytest.mark.parametrize("firmware", ["0.6", "0.5"])
def test_an_axis_error_is_reported_and_cleared_by_config(rig, bus: BusClient, firmware: str) -> None:
    r = rig(settings={"firmware": firmware, "command_timeout_s": 0.0, "rc_gating": False}, node={"firmware": firmware})
    r.wait_phases("armed", "armed")
    r.commander.hold(left=25.0, right=25.0)
    r.wait_wheels(0.5 * CIRCUMFERENCE, 0.5 * CIRCUMFERENCE)
    if firmware == "0.6":
        r.mock.call("right", "inject_error", int(OdriveError.CURRENT_LIMIT_VIOLATION))
        expect, detail = "CURRENT_LIMIT_VIOLATION", ("right.active_errors", hex(OdriveError.CURRENT_LIMIT_VIOLATION))
    else:
        r.mock.call("right", "inject_error", 0x1000, kind="motor")
        expect, detail = "MOTOR_FAILED", ("right.motor_error", "0x1000")
    details = r.probe.wait_health(lambda d, s: d.get(detail[0]) == detail[1] and d["right.phase"] == "error",
                                  message=f"right axis error {expect} in health")
    assert expect in details["right.error"] and expect in details["degraded_reason"]
    assert expect in details["last_error"] and "clear_errors" in details["last_error"]
    r.wait_wheels(0.5 * CIRCUMFERENCE, 0.0, what="the failed axis disarmed, the other still driving")
    r.mock.call("left", "inject_garbage", 3)
    details = r.probe.health_after(4)  # no automatic re-arm without rearm_on_error
    assert details["right.phase"] == "error" and int(details["dropped"]) >= 3

    reply = bus.set_config("motors", "clear_errors", "true")
    assert reply is not None and reply.ok, reply
    r.wait_phases("armed", "armed")
    r.wait_wheels(0.5 * CIRCUMFERENCE, 0.5 * CIRCUMFERENCE, what="driving again after clear_errors")
    config = bus.get_config("motors")
    assert config is not None and {f.name: f.value for f in config.fields}["clear_errors"] == "false"
    assert r.driver.poll() is None


@pytest.mark.parametrize(("how", "idle_on_stop"), [("u2sa stop", True), ("SIGTERM", True), ("u2sa stop", False),
                                                    ("SIGTERM", False)])
def test_stop_over_the_bus_and_sigterm_leave_both_axes_at_zero_and_idle(rig, bus: BusClient, how: str,
                                                                         idle_on_stop: bool) -> None:
    r = rig(settings={"command_timeout_s": 0.0, "rc_gating": False, "idle_on_stop": idle_on_stop})   # no watchdog on the nodes
    r.wait_phases("armed", "armed")
    r.commander.hold(left=50.0, right=-50.0)
    r.wait_wheels(CIRCUMFERENCE, -CIRCUMFERENCE)
    r.commander.close()
    marks = {side: len(r.mock.received(side)) for side in ("left", "right")}
    stop_driver(r.driver, bus, how)
    for side, node in zip(("left", "right"), NODES):
        frames = r.mock.received(side)[marks[side]:]
        cmds = [(can_id & 0x1F, data) for can_id, data in frames if can_id >> 5 == node]
        velocities = [cs_decode_vel(data) for cmd, data in cmds if cmd == Cmd.SET_INPUT_VEL]
        assert velocities and velocities[-1] == (0.0, 0.0), f"{side}: the last Set_Input_Vel is 0 rev/s"
        assert r.mock.get(side, "input_vel") == 0.0 and r.wheel(side) == 0.0
        idle = [i for i, (cmd, data) in enumerate(cmds)
                if cmd == Cmd.SET_AXIS_STATE and decode_set_axis_state(data) == AxisState.IDLE]
        if idle_on_stop:   # zero first, then IDLE: the motor stops holding
            last_vel = max(i for i, (cmd, _) in enumerate(cmds) if cmd == Cmd.SET_INPUT_VEL)
            assert idle and idle[-1] > last_vel
            assert r.mock.get(side, "axis_state") == AxisState.IDLE
        else:              # the axis holds 0 rev/s in closed loop
            assert not idle and r.mock.get(side, "axis_state") == AxisState.CLOSED_LOOP_CONTROL


# ---------------------------------------------------------------- the axis watchdog -------------
WATCHDOG_06 = {"watchdog_timeout_endpoint": WATCHDOG_TIMEOUT_ENDPOINT,
               "enable_watchdog_endpoint": ENABLE_WATCHDOG_ENDPOINT, "endpoints_fw": MOCK_FW}


@pytest.mark.parametrize("settings", [{"hw_watchdog_timeout_s": 0.05}, {"hw_watchdog_timeout_s": 0.1},
                                      {"hw_watchdog_timeout_s": 0.3, "command_period_s": 0.2},
                                      {"hw_watchdog_timeout_s": 0.0}])
def test_a_watchdog_timeout_not_above_twice_the_resend_period_is_refused(lcm_url: str, settings: dict) -> None:
    with pytest.raises(ConfigError, match="hw_watchdog_timeout_s") as err:
        OdriveCanMotor("motors", settings=settings)
    assert "service 'motors'" in str(err.value)
    OdriveCanMotor("motors", settings={**settings, "hw_watchdog": False, "hw_watchdog_timeout_s": 0.3})  # off: no check


class InProcess:
    """Two mock ODrive axes on a virtual bus and the driver object running on a thread."""

    def __init__(self, *, settings: dict, firmware: str = "0.6", node: dict | None = None) -> None:
        self.channel = f"odrive-wd-{random.randint(0, 1 << 30)}"
        self.vehicle = SimVehicle(origin_lat=0.0, origin_lon=0.0)
        self.nodes = {side: OdriveCanNode(self.vehicle, side=side, node_id=node_id, interface="virtual",
                                          channel=self.channel, vel_limit=10.0, firmware=firmware, **(node or {}))
                      for side, node_id in zip(("left", "right"), NODES)}
        self.svc = OdriveCanMotor("motors", profile=bus_profile(f"can://virtual/{self.channel}"), settings={
            "node_ids": list(NODES), "firmware": firmware,
            "status_poll_s": 0.0, "odometry": False, "rc_gating": False, "command_timeout_s": 0.5, **settings})
        self.runner = threading.Thread(target=self.svc.run, daemon=True)
        self.killed = False

    def __enter__(self) -> "InProcess":
        self.vehicle.start()
        for node in self.nodes.values():
            node.start()
        self.svc.start()
        self.runner.start()
        return self

    def hang(self) -> None:
        """The driver stops sending anything, as a hung or killed process does (no neutral, no IDLE)."""
        self.svc.stop()
        self.runner.join(timeout=10)
        assert not self.runner.is_alive()

    def __exit__(self, *exc: object) -> None:
        self.svc.stop()
        self.runner.join(timeout=10)
        self.svc.kill()
        self.svc.transport.stop()
        for node in self.nodes.values():
            node.stop()
        self.vehicle.stop()


def test_the_driver_turns_the_axis_watchdog_on_reads_it_back_and_a_hung_driver_stops_the_wheels(lcm_url: str) -> None:
    with InProcess(settings=WATCHDOG_06) as rig:
        details = wait_until(lambda: (d := rig.svc.health_details())["left.phase"] == "armed"
                             and d["right.phase"] == "armed" and d, timeout=20, message="both axes armed")
        assert details["hw_watchdog"] == "on 0.30 s (read back)"
        assert details["left.hw_watchdog"] == details["right.hw_watchdog"] == "on 0.30 s (read back)"
        for node in rig.nodes.values():
            assert (node.config.enable_watchdog, node.config.watchdog_timeout) == (True, pytest.approx(0.3))
            ops = [(op, ep) for _, op, ep, _ in node.sdo_log]   # written, then read back
            assert ops[:4] == [(1, WATCHDOG_TIMEOUT_ENDPOINT), (1, ENABLE_WATCHDOG_ENDPOINT),
                               (0, WATCHDOG_TIMEOUT_ENDPOINT), (0, ENABLE_WATCHDOG_ENDPOINT)]
            arm = [r.t for r in node.history if r.direction == "rx" and r.message.arbitration_id & 0x1F
                   == Cmd.SET_AXIS_STATE]
            enable = [r.t for r in node.history if r.direction == "rx" and r.message.arbitration_id & 0x1F
                      == Cmd.RX_SDO]
            assert arm and enable and enable[0] < arm[0], "the watchdog is on before the axis is armed"
        rig.svc.on_percentage("left", 50.0)
        rig.svc.on_percentage("right", -50.0)
        wait_until(lambda: rig.nodes["left"].wheel_speed_mps == pytest.approx(CIRCUMFERENCE, abs=1e-3)
                   and rig.nodes["right"].wheel_speed_mps == pytest.approx(-CIRCUMFERENCE, abs=1e-3),
                   message="both wheels turning")
        assert not any(node.watchdog_trips for node in rig.nodes.values())   # fed while the driver runs

        rig.hang()
        for side, node in rig.nodes.items():
            wait_until(lambda: node.axis_state == AxisState.IDLE and node.wheel_speed_mps == 0.0, timeout=20,
                       message=f"the {side} axis disarmed by its own watchdog")
            assert node.axis_error == OdriveError.WATCHDOG_TIMER_EXPIRED and len(node.watchdog_trips) == 1
            assert node.input_vel != 0.0   # the last setpoint was still 'drive': only the watchdog stopped it


def test_a_watchdog_read_back_that_disagrees_is_an_error_naming_the_node(lcm_url: str) -> None:
    with InProcess(settings=WATCHDOG_06) as rig:
        rig.nodes["right"].freeze_config(True)   # the writes are acknowledged but do not apply
        details = wait_until(lambda: (d := rig.svc.health_details())["right.hw_watchdog"] != "pending: not heard yet"
                             and d["left.hw_watchdog"].startswith("on") and d, timeout=20, message="read back")
        assert details["right.hw_watchdog"].startswith("read back timeout 0 s, enabled False after writing 0.3 s")
        assert "flat_endpoints.json" in details["right.hw_watchdog"]
        assert "ODrive right (node 4 on motors): watchdog read back" in rig.svc.last_error
        details = wait_until(lambda: (d := rig.svc.health_details())["right.phase"] == "armed" and d, timeout=20,
                             message="armed anyway, degraded")
        assert rig.svc.status == "degraded" and "right (node 4) watchdog read back" in details["degraded_reason"]
        assert details["hw_watchdog"].startswith("left: on 0.30 s (read back); right: read back")


def test_endpoint_ids_of_another_firmware_build_are_not_written(lcm_url: str) -> None:
    with InProcess(settings={**WATCHDOG_06, "endpoints_fw": "0.6.10"}) as rig:
        details = wait_until(lambda: (d := rig.svc.health_details())["left.phase"] == "armed" and d, timeout=20,
                             message="armed")
        assert details["left.hw_watchdog"].startswith(f"not set: the node runs firmware {MOCK_FW} but the endpoint "
                                                      "ids are for 0.6.10")
        assert f"endpoints_fw = '{MOCK_FW}'" in details["left.hw_watchdog"]
        assert not rig.nodes["left"].sdo_log and not rig.nodes["left"].config.enable_watchdog


@pytest.mark.parametrize("firmware, settings, words", [
    ("0.5", {}, "not settable over CAN on fw 0.5: configure with odrivetool (axis.config.watchdog_timeout = 0.3"),
    ("0.6", {}, "not set: endpoint ids unknown"),
    ("0.6", {"hw_watchdog": False}, "off (hw_watchdog = false)"),
])
def test_what_cannot_be_set_over_can_is_said_in_health(lcm_url: str, firmware: str, settings: dict,
                                                        words: str) -> None:
    with InProcess(settings=settings, firmware=firmware) as rig:
        details = wait_until(lambda: (d := rig.svc.health_details())["left.phase"] == "armed"
                             and d["right.phase"] == "armed" and d, timeout=20, message="armed")
        assert details["hw_watchdog"].startswith(words)
        wait_until(lambda: rig.svc.status == "ok", message="not degraded: nothing is wrong with the bus")
        assert not any(node.config.enable_watchdog for node in rig.nodes.values())


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGSTOP])
def test_a_killed_or_frozen_driver_process_is_stopped_by_the_axis_watchdogs(rig, bus: BusClient, sig: int) -> None:
    r = rig(settings={**WATCHDOG_06, "command_timeout_s": 0.5})
    details = r.wait_phases("armed", "armed")
    assert details["hw_watchdog"] == "on 0.30 s (read back)"
    refused = bus.set_config("motors", "hw_watchdog_timeout_s", "0.05")
    assert refused is not None and not refused.ok and "more than twice command_period_s" in refused.error
    r.commander.hold(left=50.0, right=-50.0)
    r.wait_wheels(CIRCUMFERENCE, -CIRCUMFERENCE)
    assert r.mock.get("left", "watchdog_trips") == [] and r.mock.get("right", "watchdog_trips") == []
    try:
        os.kill(r.driver.pid, sig)   # no neutral, no IDLE: only the ODrives' own watchdogs can stop the wheels
        r.wait_wheels(0.0, 0.0, timeout=20, what="both wheels stopped by the axis watchdogs")
        for side in ("left", "right"):
            assert r.mock.get(side, "axis_state") == AxisState.IDLE
            assert r.mock.get(side, "axis_error") == OdriveError.WATCHDOG_TIMER_EXPIRED
            assert len(r.mock.get(side, "watchdog_trips")) == 1
            assert r.mock.get(side, "input_vel") != 0.0   # the driver's last word was still 'drive'
    finally:
        r.commander.close()
        if r.driver.poll() is None:
            r.driver.kill()
            r.driver.wait(timeout=10)


def test_a_node_that_does_not_answer_get_version_is_reported_and_armed_anyway(lcm_url: str) -> None:
    channel = f"odrive-wd-{random.randint(0, 1 << 30)}"
    node = StubbornNode(channel, 5)   # heartbeats only: no Get_Version, no TxSdo
    node.accept = True
    svc = OdriveCanMotor("motors", profile=bus_profile(f"can://virtual/{channel}"), settings={
        "actuators": ["wheel"], "node_ids": [5], "directions": [1],
        "wheel_radius_m": [0.1], "odometry": False, "silent_after_s": 1.0, "rc_gating": False,
        "command_timeout_s": 0.5, **WATCHDOG_06})
    runner = threading.Thread(target=svc.run, daemon=True)
    try:
        svc.start()
        runner.start()
        details = wait_until(lambda: (d := svc.health_details())["wheel.phase"] == "armed" and d, timeout=20,
                             message="armed after the watchdog step gave up")
        assert details["wheel.hw_watchdog"].startswith("no answer to Get_Version after 4 tries")
        assert "ODrive wheel (node 5 on motors): watchdog no answer" in svc.last_error
        assert node.arm_requests   # arming waited for the step, then went ahead
        wait_until(lambda: svc.status == "degraded", message="degraded: the watchdog is not verified")
    finally:
        svc.stop()
        runner.join(timeout=10)
        svc.kill()
        svc.transport.stop()
        node.close()
