"""The mock ODrive and VESC nodes on real python-can buses: virtual in one process, udp_multicast across processes.

The test talks to a node only through a python-can Bus on the node's channel, as a driver would,
and checks the wheel through the SimVehicle the node drives.
"""

from __future__ import annotations

import math
import subprocess
import sys
import time
import uuid
from pathlib import Path
from typing import Callable, Iterator

import can
import pytest

from conftest import REPO, wait_until
from u2sa_hw.mocks.can_node import RX
from u2sa_hw.mocks.odrive_node import OdriveCanNode
from u2sa_hw.mocks.vehicle_sim import SimVehicle
from u2sa_hw.mocks.vesc_node import VescCanNode
from u2sa_hw.protocols import odrive_cansimple as cs
from u2sa_hw.protocols import vesc_can as vc
from u2sa_hw.protocols.odrive_cansimple import AxisState, Cmd, ControlMode, InputMode
from u2sa_hw.protocols.vesc_can import FaultCode, PacketId
from u2sa_hw.bus.udp_ports import private_udp_port

CIRCUMFERENCE = 2 * math.pi * 0.1  # the nodes' default wheel radius
GROUP = "239.74.163.2"


class Client:
    """The test's end of the bus, with a way to wait for a frame."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus

    def send(self, msg: can.Message) -> None:
        self.bus.send(msg)

    def wait_for(self, match: Callable[[can.Message], object], *, timeout: float = 5.0,
                 what: str = "a frame") -> can.Message:
        """The first frame from now on for which *match* is truthy; fails the test after *timeout*."""
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            msg = self.bus.recv(timeout=left)
            if msg is not None and match(msg):
                return msg
        pytest.fail(f"no {what} within {timeout:g} s")

    def drain(self) -> None:
        """Forget the frames already queued (sent before the moment that matters)."""
        while self.bus.recv(timeout=0) is not None:
            pass

    def none_within(self, match: Callable[[can.Message], object], seconds: float) -> bool:
        """True if no matching frame arrives for *seconds* (to show a node went quiet)."""
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            msg = self.bus.recv(timeout=left)
            if msg is not None and match(msg):
                return False
        return True

    # ODrive helpers
    def odrive(self, node: int, cmd: int, payload: bytes = b"") -> None:
        self.send(cs.make_frame(node, cmd, payload))

    def odrive_reply(self, node: int, cmd: int, *, timeout: float = 5.0) -> bytes:
        arb = cs.arbitration_id(node, cmd)
        msg = self.wait_for(lambda m: m.arbitration_id == arb and not m.is_remote_frame and not m.is_extended_id
                            and m.dlc == 8, timeout=timeout, what=f"{cs.command_name(cmd)} from node {node}")
        return bytes(msg.data)

    def request(self, node: int, cmd: int) -> bytes:
        self.send(cs.make_request(node, cmd))
        return self.odrive_reply(node, cmd)

    def heartbeat(self, node: int, *, firmware: str = "0.6",
                  until: Callable[[cs.Heartbeat], bool] = lambda hb: True, timeout: float = 5.0) -> cs.Heartbeat:
        arb = cs.arbitration_id(node, Cmd.HEARTBEAT)
        msg = self.wait_for(lambda m: m.arbitration_id == arb and m.dlc == 8
                            and until(cs.decode_heartbeat(m.data, firmware=firmware)),
                            timeout=timeout, what=f"a matching heartbeat from node {node}")
        return cs.decode_heartbeat(msg.data, firmware=firmware)

    def encoder(self, node: int, *, until: Callable[[float, float], bool] = lambda p, v: True,
                timeout: float = 5.0) -> tuple[float, float]:
        arb = cs.arbitration_id(node, Cmd.GET_ENCODER_ESTIMATES)
        msg = self.wait_for(lambda m: m.arbitration_id == arb and not m.is_remote_frame
                            and until(*cs.decode_encoder_estimates(m.data)),
                            timeout=timeout, what=f"matching encoder estimates from node {node}")
        return cs.decode_encoder_estimates(msg.data)

    def arm_velocity(self, node: int, vel: float) -> None:
        self.odrive(node, Cmd.SET_CONTROLLER_MODE, cs.encode_set_controller_mode(ControlMode.VELOCITY_CONTROL,
                                                                                 InputMode.PASSTHROUGH))
        self.odrive(node, Cmd.SET_AXIS_STATE, cs.encode_set_axis_state(AxisState.CLOSED_LOOP_CONTROL))
        self.odrive(node, Cmd.SET_INPUT_VEL, cs.encode_set_input_vel(vel))

    # VESC helpers
    def vesc(self, controller: int, packet: int, value: float) -> None:
        self.send(vc.make_frame(controller, packet, vc.encode_command(packet, value)))

    def status(self, controller: int, packet: int, *, until: Callable[[object], bool] = lambda s: True,
               timeout: float = 5.0):
        arb = vc.ext_id(packet, controller)
        msg = self.wait_for(lambda m: m.arbitration_id == arb and m.is_extended_id and m.dlc == 8
                            and until(vc.decode_status(packet, m.data)),
                            timeout=timeout, what=f"a matching {PacketId(packet).name} from VESC {controller}")
        return vc.decode_status(packet, msg.data)


@pytest.fixture
def vehicle() -> Iterator[SimVehicle]:
    sim = SimVehicle(origin_lat=52.0, origin_lon=5.0)
    sim.start()
    yield sim
    sim.stop()


@pytest.fixture
def channel() -> str:
    return f"can-test-{uuid.uuid4().hex[:8]}"


@pytest.fixture
def client(channel: str) -> Iterator[Client]:
    bus = can.Bus(interface="virtual", channel=channel)
    yield Client(bus)
    bus.shutdown()


@pytest.fixture
def start_node() -> Iterator[Callable]:
    nodes: list = []

    def start(node):
        node.start()
        nodes.append(node)
        return node

    yield start
    for node in nodes:
        node.stop()


class SteppedClock:
    """A node's clock that stands still until the test advances it (the node's thread still runs), then,
    after :meth:`run`, goes on with real time from where it stood."""

    def __init__(self) -> None:
        self._at = 1000.0
        self._since: float | None = None

    def __call__(self) -> float:
        return self._at if self._since is None else self._at + time.monotonic() - self._since

    def advance(self, seconds: float) -> None:
        assert self._since is None, "the clock runs with real time now"
        self._at += seconds

    def run(self) -> None:
        self._since = time.monotonic()


def received(node) -> int:
    """Frames the node has taken from the bus."""
    return sum(1 for r in node.history if r.direction == RX)


def odrive(vehicle: SimVehicle, channel: str, **options) -> OdriveCanNode:
    options = {"side": "left", "node_id": 1, **options}
    return OdriveCanNode(vehicle, interface="virtual", channel=channel, **options)


def vesc(vehicle: SimVehicle, channel: str, **options) -> VescCanNode:
    options = {"side": "left", "controller_id": 5, **options}
    return VescCanNode(vehicle, interface="virtual", channel=channel, **options)


# ==== ODrive ==============================================================================
def test_odrive_boots_idle_and_drives_the_wheel_only_in_closed_loop(vehicle, channel, client, start_node) -> None:
    node = start_node(odrive(vehicle, channel))
    assert client.heartbeat(1) == cs.Heartbeat(0, AxisState.IDLE, trajectory_done=True)
    client.odrive(1, Cmd.SET_CONTROLLER_MODE, cs.encode_set_controller_mode(ControlMode.VELOCITY_CONTROL,
                                                                            InputMode.PASSTHROUGH))
    client.odrive(1, Cmd.SET_INPUT_VEL, cs.encode_set_input_vel(1.0))
    client.heartbeat(1)
    client.heartbeat(1)  # two heartbeats later the idle axis still has not moved
    assert node.wheel_speed_mps == 0.0 and vehicle.snapshot().wheel_left_m == 0.0

    client.odrive(1, Cmd.SET_AXIS_STATE, cs.encode_set_axis_state(AxisState.CLOSED_LOOP_CONTROL))
    assert client.heartbeat(1, until=lambda hb: hb.axis_state == AxisState.CLOSED_LOOP_CONTROL).axis_error == 0
    assert node.wheel_speed_mps == pytest.approx(CIRCUMFERENCE)
    # the velocity estimate is the odometer's rate: exactly the commanded 1 rev/s
    client.encoder(1, until=lambda pos, vel: vel == pytest.approx(1.0, abs=1e-4) and pos > 0.2)

    client.odrive(1, Cmd.SET_INPUT_VEL, cs.encode_set_input_vel(0.0))
    pos, _ = client.encoder(1, until=lambda pos, vel: vel == 0.0)
    assert pos == pytest.approx(vehicle.snapshot().wheel_left_m / CIRCUMFERENCE, abs=1e-5)


def test_odrive_direction_limits_and_ramp(vehicle, channel, client, start_node) -> None:
    node = start_node(odrive(vehicle, channel, side="right", node_id=2, direction=-1))
    client.arm_velocity(2, 0.5)
    client.encoder(2, until=lambda pos, vel: vel == pytest.approx(0.5, abs=1e-4))
    assert node.wheel_speed_mps == pytest.approx(-0.5 * CIRCUMFERENCE)  # a mirrored motor turns the wheel back
    assert vehicle.snapshot().wheel_right_m < 0

    client.odrive(2, Cmd.SET_LIMITS, cs.encode_set_limits(0.75, 10.0))
    client.odrive(2, Cmd.SET_INPUT_VEL, cs.encode_set_input_vel(3.0))
    client.encoder(2, until=lambda pos, vel: vel == pytest.approx(0.75, abs=1e-4))
    assert node.config.vel_limit == 0.75

    client.odrive(2, Cmd.SET_INPUT_VEL, cs.encode_set_input_vel(0.0))
    client.encoder(2, until=lambda pos, vel: vel == 0.0)
    client.odrive(2, Cmd.SET_CONTROLLER_MODE, cs.encode_set_controller_mode(ControlMode.VELOCITY_CONTROL,
                                                                            InputMode.VEL_RAMP))
    client.odrive(2, Cmd.SET_INPUT_VEL, cs.encode_set_input_vel(0.75))  # ramps at 1 rev/s^2
    client.encoder(2, until=lambda pos, vel: 0.1 < vel < 0.6)  # on the way up
    client.encoder(2, until=lambda pos, vel: vel == pytest.approx(0.75, abs=1e-4))


def test_odrive_position_control_reaches_the_target(vehicle, channel, client, start_node) -> None:
    node = start_node(odrive(vehicle, channel))  # boots in POSITION_CONTROL / PASSTHROUGH like the firmware
    client.odrive(1, Cmd.SET_AXIS_STATE, cs.encode_set_axis_state(AxisState.CLOSED_LOOP_CONTROL))
    client.odrive(1, Cmd.SET_INPUT_POS, cs.encode_set_input_pos(0.5))
    client.encoder(1, until=lambda pos, vel: abs(pos - 0.5) < 0.005 and abs(vel) < 0.05, timeout=10)

    client.odrive(1, Cmd.SET_CONTROLLER_MODE, cs.encode_set_controller_mode(ControlMode.POSITION_CONTROL,
                                                                            InputMode.TRAP_TRAJ))
    client.odrive(1, Cmd.SET_TRAJ_VEL_LIMIT, cs.encode_floats(0.5))
    client.odrive(1, Cmd.SET_INPUT_POS, cs.encode_set_input_pos(1.5))
    client.heartbeat(1, until=lambda hb: not hb.trajectory_done)
    client.encoder(1, until=lambda pos, vel: vel == pytest.approx(0.5, abs=1e-4))  # at the trajectory's limit
    client.encoder(1, until=lambda pos, vel: abs(pos - 1.5) < 0.005 and abs(vel) < 0.05, timeout=10)
    client.heartbeat(1, until=lambda hb: hb.trajectory_done)
    assert node.config.traj_vel_limit == 0.5


def test_odrive_watchdog_is_fed_by_any_frame_and_disarms_when_starved(vehicle, channel, client, start_node) -> None:
    clock = SteppedClock()   # the node's time moves only when the test moves it: load cannot starve the watchdog
    node = start_node(odrive(vehicle, channel, watchdog_timeout_s=0.4, clock=clock))
    client.arm_velocity(1, 1.0)
    wait_until(lambda: node.axis_state == AxisState.CLOSED_LOOP_CONTROL, message="the axis armed")
    # as in can_simple.cpp, RTR requests feed it too: one every 0.35 s for over twice the timeout, still armed
    for _ in range(3):
        client.drain()
        clock.advance(0.35)
        client.encoder(1)   # a cyclic frame: the control tick (watchdog first) ran 0.35 s after the last feed
        assert node.axis_state == AxisState.CLOSED_LOOP_CONTROL and node.axis_error == 0
        client.request(1, Cmd.GET_BUS_VOLTAGE_CURRENT)   # an RTR, answered: the node has taken it
    wait_until(lambda: vehicle.snapshot().wheel_left_m > 0, message="the wheel driven")
    client.drain()
    clock.advance(0.41)   # then nothing for just over the timeout
    hb = client.heartbeat(1, until=lambda hb: hb.axis_state == AxisState.IDLE)
    assert hb.axis_error == cs.OdriveError.WATCHDOG_TIMER_EXPIRED
    assert node.watchdog_trips == [clock()] and node.wheel_speed_mps == 0.0
    clock.run()
    client.encoder(1, until=lambda pos, vel: vel == 0.0)


def test_odrive_watchdog_set_over_rxsdo_reads_back_and_trips_when_starved(vehicle, channel, client,
                                                                           start_node) -> None:
    from u2sa_hw.mocks.odrive_config import ENABLE_WATCHDOG_ENDPOINT as ENABLE, WATCHDOG_TIMEOUT_ENDPOINT as TIMEOUT
    node = start_node(odrive(vehicle, channel))   # boots with the watchdog off, as the factory config has it

    def read(endpoint: int, kind: str):
        client.odrive(1, Cmd.RX_SDO, cs.encode_sdo_read(endpoint))
        got, raw = cs.decode_tx_sdo(client.wait_for(lambda m: m.arbitration_id == cs.arbitration_id(1, Cmd.TX_SDO),
                                                    what="TxSdo").data)
        assert got == endpoint
        return cs.sdo_value(kind, raw)

    assert (read(TIMEOUT, "float"), read(ENABLE, "bool")) == (0.0, False)
    client.odrive(1, Cmd.RX_SDO, cs.encode_sdo_write(TIMEOUT, "float", 0.3))
    client.odrive(1, Cmd.RX_SDO, cs.encode_sdo_write(ENABLE, "bool", True))
    assert (read(TIMEOUT, "float"), read(ENABLE, "bool")) == (pytest.approx(0.3), True)
    client.odrive(1, Cmd.RX_SDO, cs.encode_sdo_read(0x7777))   # no such endpoint in this build: counted
    wait_until(lambda: node.dropped == 1, message="the unknown endpoint to be dropped")

    client.arm_velocity(1, 1.0)
    client.heartbeat(1, until=lambda hb: hb.axis_state == AxisState.CLOSED_LOOP_CONTROL)
    hb = client.heartbeat(1, until=lambda hb: hb.axis_error != 0, timeout=10)   # nobody feeds it
    assert (hb.axis_error, hb.axis_state) == (cs.OdriveError.WATCHDOG_TIMER_EXPIRED, AxisState.IDLE)
    assert node.wheel_speed_mps == 0.0 and len(node.watchdog_trips) == 1

    node.freeze_config(True)   # a write that does not apply: the read-back shows the old value
    client.odrive(1, Cmd.RX_SDO, cs.encode_sdo_write(TIMEOUT, "float", 0.8))
    assert read(TIMEOUT, "float") == pytest.approx(0.3)
    assert [op for _, op, _, _ in node.sdo_log].count(cs.SDO_WRITE) == 3


def test_odrive_estop_clear_errors_and_rearm(vehicle, channel, client, start_node) -> None:
    node = start_node(odrive(vehicle, channel))
    client.arm_velocity(1, 1.0)
    client.heartbeat(1, until=lambda hb: hb.axis_state == AxisState.CLOSED_LOOP_CONTROL)
    client.odrive(1, Cmd.ESTOP)
    hb = client.heartbeat(1, until=lambda hb: hb.axis_error != 0)
    assert (hb.axis_error, hb.axis_state) == (cs.OdriveError.ESTOP_REQUESTED, AxisState.IDLE)
    assert node.wheel_speed_mps == 0.0
    assert cs.decode_get_error(client.request(1, Cmd.GET_ERROR)) == (0x2000000, 0x2000000)

    client.odrive(1, Cmd.SET_AXIS_STATE, cs.encode_set_axis_state(AxisState.CLOSED_LOOP_CONTROL))
    hb = client.heartbeat(1, until=lambda hb: hb.procedure_result == cs.ProcedureResult.DISARMED)
    assert hb.axis_state == AxisState.IDLE  # an axis with an error refuses to arm

    client.odrive(1, Cmd.CLEAR_ERRORS, cs.encode_clear_errors())
    assert client.heartbeat(1, until=lambda hb: hb.axis_error == 0).axis_state == AxisState.IDLE
    client.odrive(1, Cmd.SET_AXIS_STATE, cs.encode_set_axis_state(AxisState.CLOSED_LOOP_CONTROL))
    client.heartbeat(1, until=lambda hb: hb.axis_state == AxisState.CLOSED_LOOP_CONTROL)
    client.encoder(1, until=lambda pos, vel: vel == pytest.approx(1.0, abs=1e-4))


def test_odrive_answers_requests_06(vehicle, channel, client, start_node) -> None:
    node = start_node(odrive(vehicle, channel))
    node.set_bus(voltage_v=22.5, current_a=3.0)
    assert cs.decode_bus_voltage_current(client.request(1, Cmd.GET_BUS_VOLTAGE_CURRENT)) == (22.5, 3.0)
    assert cs.decode_version(client.request(1, Cmd.GET_VERSION)).fw_minor == 6
    assert cs.decode_floats(client.request(1, Cmd.GET_TEMPERATURE), 2) == (30.0, 30.0)
    client.odrive(1, Cmd.GET_ENCODER_ESTIMATES)  # an empty data frame is a request too
    assert cs.decode_encoder_estimates(client.odrive_reply(1, Cmd.GET_ENCODER_ESTIMATES)) == (0.0, 0.0)
    node.inject_error(cs.OdriveError.DRV_FAULT)
    assert cs.decode_get_error(client.request(1, Cmd.GET_ERROR)) == (0x20, 0)  # it was not armed: no disarm


def test_odrive_firmware_05_errors_and_heartbeat_flags(vehicle, channel, client, start_node) -> None:
    node = start_node(odrive(vehicle, channel, firmware="0.5"))
    client.arm_velocity(1, 1.0)
    client.heartbeat(1, firmware="0.5", until=lambda hb: hb.axis_state == AxisState.CLOSED_LOOP_CONTROL)
    node.inject_error(cs.MotorError05.DRV_FAULT, kind="motor")
    hb = client.heartbeat(1, firmware="0.5", until=lambda hb: hb.axis_error != 0)
    assert (hb.axis_error, hb.axis_state, hb.motor_error_flag) == (cs.AxisError05.MOTOR_FAILED, AxisState.IDLE, True)
    assert cs.decode_motor_error(client.request(1, Cmd.GET_MOTOR_ERROR)) == cs.MotorError05.DRV_FAULT
    client.odrive(1, Cmd.CLEAR_ERRORS, cs.encode_clear_errors(firmware="0.5"))
    hb = client.heartbeat(1, firmware="0.5", until=lambda hb: hb.axis_error == 0)
    assert not hb.motor_error_flag
    client.odrive(1, Cmd.ESTOP)
    assert client.heartbeat(1, firmware="0.5", until=lambda hb: hb.axis_error != 0).axis_error == 0x4000
    with pytest.raises(ValueError, match="firmware 0.5"):
        start_node(odrive(vehicle, channel, node_id=2)).inject_error(1, kind="motor")


def test_odrive_reboot_restores_saved_config_and_zeroes_position(vehicle, channel, client, start_node) -> None:
    node = start_node(odrive(vehicle, channel))
    client.arm_velocity(1, 2.0)
    client.encoder(1, until=lambda pos, vel: pos > 0.5)
    client.odrive(1, Cmd.SET_LIMITS, cs.encode_set_limits(1.0, 5.0))
    client.odrive(1, Cmd.REBOOT, cs.encode_reboot())
    client.heartbeat(1, until=lambda hb: hb.axis_state == AxisState.IDLE)
    pos, vel = client.encoder(1, until=lambda pos, vel: vel == 0.0)
    assert abs(pos) < 0.05 and node.config.vel_limit == 2.0  # Set_Limits was not saved
    assert node.config.control_mode == ControlMode.POSITION_CONTROL

    client.arm_velocity(1, 2.0)
    client.encoder(1, until=lambda pos, vel: pos > 0.5)
    client.odrive(1, Cmd.SET_LIMITS, cs.encode_set_limits(1.0, 5.0))
    client.odrive(1, Cmd.REBOOT, cs.encode_reboot(cs.RebootAction.SAVE_CONFIGURATION))
    client.odrive(1, Cmd.REBOOT, cs.encode_reboot())
    client.heartbeat(1, until=lambda hb: hb.axis_state == AxisState.IDLE)
    assert abs(client.encoder(1, until=lambda pos, vel: vel == 0.0)[0]) < 0.05
    assert (node.config.vel_limit, node.config.control_mode) == (1.0, ControlMode.VELOCITY_CONTROL)


def test_odrive_faults_silence_garbage_and_error_frames(vehicle, channel, client, start_node) -> None:
    node = start_node(odrive(vehicle, channel))
    client.heartbeat(1)
    node.stop_answering(True)
    client.drain()
    assert client.none_within(lambda m: m.arbitration_id >> 5 == 1, 0.4)
    client.send(cs.make_request(1, Cmd.GET_BUS_VOLTAGE_CURRENT))
    assert client.none_within(lambda m: m.arbitration_id >> 5 == 1, 0.3)
    node.stop_answering(False)
    client.heartbeat(1)

    node.inject_garbage(1)
    bad = client.wait_for(lambda m: m.arbitration_id == 0x21 and m.dlc == 3, what="a truncated heartbeat")
    with pytest.raises(cs.CanSimpleError, match="Heartbeat: needs 8 data bytes, got 3"):
        cs.decode_heartbeat(bad.data)
    node.send_error_frames(2)
    assert client.wait_for(lambda m: m.is_error_frame, what="an error frame").arbitration_id == 0x80

    client.odrive(1, Cmd.SET_INPUT_VEL, b"\x00\x00")  # truncated: counted and dropped, the node carries on
    client.odrive(7, Cmd.SET_AXIS_STATE, cs.encode_set_axis_state(8))  # another node's frame
    wait_until(lambda: node.dropped == 1, message="the truncated frame to be dropped")
    client.heartbeat(1)
    # the request sent while it was cut off never reached it, nor did node 7's frame
    received = [r.message for r in node.history if r.direction == "rx"]
    assert [(m.arbitration_id, bytes(m.data)) for m in received] == [(0x2D, b"\x00\x00")]


def test_two_odrives_drive_and_turn_a_differential_vehicle(vehicle, channel, client, start_node) -> None:
    start_node(odrive(vehicle, channel, side="left", node_id=0))
    start_node(odrive(vehicle, channel, side="right", node_id=1))
    for node_id in (0, 1):
        client.arm_velocity(node_id, 1.0)
    wait_until(lambda: vehicle.snapshot().north > 0.5, message="the vehicle to drive north")
    truth = vehicle.snapshot()  # the two nodes started a tick apart, so only the rates are exact
    assert truth.yaw_rate == pytest.approx(0.0, abs=1e-9) and truth.speed == pytest.approx(CIRCUMFERENCE)
    client.odrive(1, Cmd.SET_INPUT_VEL, cs.encode_set_input_vel(-1.0))
    wait_until(lambda: vehicle.snapshot().yaw_rate == pytest.approx(2 * CIRCUMFERENCE / vehicle.track_width),
               message="the vehicle to spin clockwise on the spot")


# ==== VESC ================================================================================
def test_vesc_duty_and_rpm_drive_the_wheel_and_status_follows_the_odometer(vehicle, channel, client,
                                                                           start_node) -> None:
    node = start_node(vesc(vehicle, channel, timeout_s=0))
    client.vesc(5, PacketId.SET_DUTY, 0.1)  # 700 ERPM -> 100 rpm of the wheel
    wait_until(lambda: node.output == pytest.approx(700 / 7 / 60 * CIRCUMFERENCE), message="the wheel speed")
    status = client.status(5, PacketId.STATUS, until=lambda s: s.erpm == 700)
    assert status.duty == pytest.approx(0.1)
    tacho = client.status(5, PacketId.STATUS_5, until=lambda s: s.tachometer > 60).tachometer
    assert tacho <= vehicle.snapshot().wheel_left_m / CIRCUMFERENCE * 7 * 6 + 1  # 6 counts per electrical rev
    assert client.status(5, PacketId.STATUS_5).voltage_in_v == 24.0
    assert client.status(5, PacketId.STATUS_4).temp_fet_c == 30.0

    for _ in range(3):
        client.vesc(5, PacketId.SET_RPM, -1050)  # 1.57 m/s, under max_speed
    client.status(5, PacketId.STATUS, until=lambda s: s.erpm == -1050)
    assert node.mode == "rpm" and node.output < 0


def test_vesc_command_timeout_releases_the_motor(vehicle, channel, client, start_node) -> None:
    clock = SteppedClock()   # the node's time moves only when the test moves it: load cannot starve it
    node = start_node(vesc(vehicle, channel, timeout_s=0.4, clock=clock))

    def command() -> None:
        heard = received(node)
        client.vesc(5, PacketId.SET_DUTY, 0.1)
        wait_until(lambda: received(node) > heard, message="the node to take the command")

    command()
    for _ in range(3):   # a command every 0.35 s for over twice the timeout: never released
        client.drain()
        clock.advance(0.35)
        client.status(5, PacketId.STATUS)   # a cyclic frame: the control tick (timeout first) ran 0.35 s on
        assert node.mode == "duty"
        command()
    wait_until(lambda: vehicle.snapshot().wheel_left_m > 0, message="the wheel driven")
    clock.advance(0.41)   # then no command for just over the timeout
    wait_until(lambda: node.mode == "released", message="the VESC timeout")
    assert node.timeouts == [clock()] and node.output == 0.0
    clock.run()
    client.status(5, PacketId.STATUS, until=lambda s: s.erpm == 0 and s.duty == 0)


def test_vesc_app_configuration_over_can_buffers_sets_the_timeout(vehicle, channel, client, start_node) -> None:
    node = start_node(vesc(vehicle, channel, timeout_s=1.0))
    assembler = vc.BufferAssembler()

    def comm(payload: bytes) -> bytes:
        for frame in vc.buffer_frames(5, 200, payload):
            client.send(frame)
        while True:   # the answer comes in buffers addressed to our id 200
            msg = client.wait_for(lambda m: m.is_extended_id and m.arbitration_id & 0xFF == 200, what="an answer")
            done = assembler.feed(msg.arbitration_id >> 8, msg.data)
            if done is not None:
                assert done[0] == 5
                return done[2]

    answer = comm(bytes([vc.CommPacket.GET_APPCONF]))
    assert answer[0] == vc.CommPacket.GET_APPCONF and len(answer) > 256   # long enough for FILL_RX_BUFFER_LONG
    assert vc.appconf_timeout_ms(answer[1:], controller_id=5) == 1000
    ack = comm(bytes([vc.CommPacket.SET_APPCONF]) + vc.appconf_with_timeout(answer[1:], 300, controller_id=5))
    assert ack == bytes([vc.CommPacket.SET_APPCONF]) and node.timeout_s == 0.3 and node.appconf_writes == 1
    assert vc.appconf_timeout_ms(comm(bytes([vc.CommPacket.GET_APPCONF]))[1:], controller_id=5) == 300

    client.vesc(5, PacketId.SET_DUTY, 0.1)   # one command, then nothing: released after 0.3 s
    wait_until(lambda: len(node.timeouts) == 1, message="the new timeout to release the motor")
    assert node.mode == "released" and node.output == 0.0

    node.freeze_config(True)   # acknowledged, not applied
    assert comm(bytes([vc.CommPacket.SET_APPCONF]) + vc.appconf_with_timeout(answer[1:], 800, controller_id=5)) \
        == bytes([vc.CommPacket.SET_APPCONF])
    assert node.timeout_s == 0.3 and node.appconf_writes == 2


def test_vesc_addressing_broadcast_and_ping(vehicle, channel, client, start_node) -> None:
    node = start_node(vesc(vehicle, channel, status_messages=(1, 2, 3, 4, 5, 6)))
    for packet in vc.STATUS_PACKETS:
        client.status(5, packet)
    client.vesc(6, PacketId.SET_DUTY, 0.2)  # another VESC's command
    client.status(5, PacketId.STATUS)
    assert node.mode == "released"
    client.vesc(vc.BROADCAST_ID, PacketId.SET_DUTY, 0.2)
    wait_until(lambda: node.mode == "duty", message="the broadcast command")
    client.send(vc.make_frame(5, PacketId.PING, bytes([9])))
    pong = client.wait_for(lambda m: m.arbitration_id == vc.ext_id(PacketId.PONG, 9), what="PONG")
    assert bytes(pong.data) == bytes([5, 0])


def test_vesc_thruster_current_and_position_commands() -> None:
    boat = SimVehicle(origin_lat=52.0, origin_lon=5.0, model="twin_thruster")
    boat.start()
    channel = f"can-test-{uuid.uuid4().hex[:8]}"
    bus = can.Bus(interface="virtual", channel=channel)
    node = VescCanNode(boat, side="right", controller_id=3, interface="virtual", channel=channel, direction=-1)
    assert node.drive == "thruster"
    node.start()
    try:
        client = Client(bus)
        client.vesc(3, PacketId.SET_DUTY, 0.5)
        wait_until(lambda: node.output == -0.5, message="the thrust of a mirrored thruster")
        client.vesc(3, PacketId.SET_RPM, 3500)
        assert client.status(3, PacketId.STATUS, until=lambda s: s.erpm == 3500).duty == 0.5
        client.status(3, PacketId.STATUS_5, until=lambda s: s.tachometer > 100)
        client.vesc(3, PacketId.SET_CURRENT, 12.5)
        status = client.status(3, PacketId.STATUS, until=lambda s: s.current_a == 12.5)
        assert status.erpm == 0 and node.output == 0.0  # no torque model: the motor holds still
        client.vesc(3, PacketId.SET_POS, 123.0)
        assert client.status(3, PacketId.STATUS_4, until=lambda s: s.pid_pos_deg == 123.0)
    finally:
        node.stop()
        bus.shutdown()
        boat.stop()
    with pytest.raises(ValueError, match="differential"):
        OdriveCanNode(boat, side="left", node_id=1, interface="virtual", channel=channel)


def test_vesc_fault_silence_and_garbage(vehicle, channel, client, start_node) -> None:
    node = start_node(vesc(vehicle, channel, timeout_s=0))
    client.vesc(5, PacketId.SET_DUTY, 0.1)
    client.status(5, PacketId.STATUS, until=lambda s: s.erpm == 700)
    node.set_fault(FaultCode.OVER_TEMP_FET)
    client.status(5, PacketId.STATUS, until=lambda s: s.erpm == 0 and s.duty == 0)
    client.vesc(5, PacketId.SET_DUTY, 0.1)  # ignored while the fault is latched
    client.status(5, PacketId.STATUS)
    assert node.mode == "released" and node.output == 0.0
    node.set_fault(FaultCode.NONE)
    client.vesc(5, PacketId.SET_DUTY, 0.1)
    client.status(5, PacketId.STATUS, until=lambda s: s.erpm == 700)

    node.stop_answering(True)
    client.drain()
    assert client.none_within(lambda m: m.is_extended_id and m.arbitration_id & 0xFF == 5, 0.4)
    node.stop_answering(False)
    client.status(5, PacketId.STATUS)

    node.inject_garbage(1)
    bad = client.wait_for(lambda m: m.arbitration_id == 0x905 and m.dlc == 3, what="a truncated STATUS")
    with pytest.raises(vc.VescCanError, match="needs 8 data bytes"):
        vc.decode_status(PacketId.STATUS, bad.data)
    client.send(vc.make_frame(5, PacketId.SET_DUTY, b"\x01"))
    wait_until(lambda: node.dropped == 1, message="the truncated command to be dropped")
    client.status(5, PacketId.STATUS, until=lambda s: s.erpm == 700)


# ==== across processes on udp_multicast ===================================================
@pytest.fixture
def udp_port() -> int:
    return private_udp_port()


@pytest.fixture
def udp_client(udp_port: int) -> Iterator[Client]:
    bus = can.Bus(interface="udp_multicast", channel=GROUP, port=udp_port)
    yield Client(bus)
    bus.shutdown()


@pytest.fixture
def node_process(tmp_path: Path, udp_port: int) -> Iterator[Callable[..., subprocess.Popen]]:
    procs: list[subprocess.Popen] = []

    def run(module: str, *args: str) -> subprocess.Popen:
        log = open(tmp_path / f"{module}.log", "wb")
        proc = subprocess.Popen([sys.executable, "-m", f"u2sa_hw.mocks.{module}", "--interface", "udp_multicast",
                                 "--channel", GROUP, "--port", str(udp_port), *args],
                                cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
        procs.append(proc)
        return proc

    yield run
    for proc in procs:
        proc.terminate()
        proc.wait(timeout=10)
    for proc, log in zip(procs, sorted(tmp_path.glob("*.log"))):
        assert proc.returncode == 0, log.read_text()


def test_odrive_node_in_another_process(udp_client, node_process) -> None:
    node_process("odrive_node", "--node-id", "4")
    assert udp_client.heartbeat(4, timeout=20).axis_state == AxisState.IDLE
    udp_client.arm_velocity(4, 1.0)
    udp_client.heartbeat(4, until=lambda hb: hb.axis_state == AxisState.CLOSED_LOOP_CONTROL)
    udp_client.encoder(4, until=lambda pos, vel: vel == pytest.approx(1.0, abs=1e-4) and pos > 0.2)
    assert cs.decode_bus_voltage_current(udp_client.request(4, Cmd.GET_BUS_VOLTAGE_CURRENT)) == (24.0, 0.0)


def test_vesc_node_in_another_process(udp_client, node_process) -> None:
    node_process("vesc_node", "--controller-id", "12", "--timeout", "0")
    udp_client.status(12, PacketId.STATUS, timeout=20)
    udp_client.vesc(12, PacketId.SET_DUTY, 0.1)
    udp_client.status(12, PacketId.STATUS, until=lambda s: s.erpm == 700)
    udp_client.status(12, PacketId.STATUS_5, until=lambda s: s.tachometer > 100)


def test_udp_multicast_node_ignores_its_own_echoes(vehicle, udp_port, udp_client, start_node) -> None:
    # the node hears its own heartbeats and estimates back on udp_multicast; they must not feed
    # its watchdog nor enter its history as received frames
    node = start_node(OdriveCanNode(vehicle, side="left", node_id=1, interface="udp_multicast", channel=GROUP,
                                    bus_options={"port": udp_port}, watchdog_timeout_s=0.3, encoder_hz=100))
    udp_client.heartbeat(1, timeout=10)
    udp_client.arm_velocity(1, 1.0)
    udp_client.heartbeat(1, until=lambda hb: hb.axis_state == AxisState.CLOSED_LOOP_CONTROL)
    hb = udp_client.heartbeat(1, until=lambda hb: hb.axis_error != 0)
    assert hb.axis_error == cs.OdriveError.WATCHDOG_TIMER_EXPIRED
    received = [r.message for r in node.history if r.direction == "rx"]
    assert [m.arbitration_id & 0x1F for m in received] == [Cmd.SET_CONTROLLER_MODE, Cmd.SET_AXIS_STATE,
                                                           Cmd.SET_INPUT_VEL]
