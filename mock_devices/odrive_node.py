"""A mock ODrive axis on CAN (CANSimple, firmware 0.5.x or 0.6.x) driving one SimVehicle wheel.

Behaves like the firmware as far as a driver can tell from the bus: it boots IDLE in
POSITION_CONTROL / PASSTHROUGH (the firmware defaults); Set_Axis_State CLOSED_LOOP_CONTROL
arms it unless an error is active; in VELOCITY_CONTROL, Set_Input_Vel (rev/s, limited to
vel_limit, ramped in VEL_RAMP) drives the wheel at ``vel * 2 pi r * direction`` m/s; in
POSITION_CONTROL a P loop (pos_gain) moves the wheel to Set_Input_Pos. Torque and voltage
control are not modelled: the wheel stays still. Heartbeat and encoder estimates are sent
cyclically; ``Get_*`` values are answered to an RTR (or empty) frame on their id.

As in the firmware (can_simple.cpp calls ``axis.watchdog_feed()`` for every frame on the
axis's id), any frame addressed to the node feeds the watchdog, RTR requests included. With
the watchdog enabled (``watchdog_timeout_s`` at construction is what odrivetool saved; with
firmware 0.6 a driver writes ``axis0.config.watchdog_timeout``/``enable_watchdog`` by RxSdo), a
closed-loop axis not fed for that long raises WATCHDOG_TIMER_EXPIRED and disarms; each expiry
is kept in ``watchdog_trips``. A feed counts from when the frame reached the bus interface (its
receive stamp: the kernel's on udp_multicast), not from when this thread got round to it: a real
controller is never starved of CPU, and a mock starved by a loaded machine must not trip on frames
that were on time. So a gap between two frames' stamps longer than the timeout trips it, and after
the node's own thread was held up (``SELF_STALL_S``) the tick waits one timeout for the frames that
queued meanwhile before it judges the silence. RxSdo reaches the endpoints of mock_devices/odrive_config.py
(this mock's own flat_endpoints table for its build MOCK_FW, not a real release's ids) and
answers reads with TxSdo; ``freeze_config(True)`` makes writes silently not apply. Any axis
error (watchdog, Estop, ``inject_error``) disarms to IDLE and stops the wheel; Clear_Errors
clears, Set_Axis_State re-arms.

Position estimates come from the vehicle's wheel odometer, velocity estimates from its rate
(see WheelOdometer), so the node agrees with every other sensor on the same SimVehicle.
What each command does is in mock_devices/odrive_commands.py (``OdriveCommands``, a mixin of the node).
``python -m u2sa_hw.mocks.odrive_node --help`` runs one node with its own vehicle.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from typing import Any, Callable, Mapping

import can

from u2sa_hw.mocks.can_node import MockCanNode, PeriodicSchedule, WheelOdometer, add_bus_arguments, bus_options, serve
from u2sa_hw.mocks.odrive_commands import OdriveCommands
from u2sa_hw.mocks.odrive_config import OdriveConfig
from u2sa_hw.mocks.vehicle_sim import SimVehicle
from u2sa_hw.protocols import odrive_cansimple as cs
from u2sa_hw.protocols.odrive_cansimple import AxisState, Cmd, ControlMode, InputMode, ProcedureResult

SELF_STALL_S = 0.1   # the node's own thread went this long (real time) between ticks: it was starved
NODE_SPEED_MARGIN = 1.25   # the node's own vel_limit over the speed its driver limits commands to


class OdriveCanNode(OdriveCommands, MockCanNode):
    """One ODrive axis with CANSimple on *interface*/*channel*, driving *side* of a differential vehicle."""

    def __init__(self, vehicle: SimVehicle, *, side: str, node_id: int, interface: str, channel: str,
                 bus_options: Mapping[str, Any] | None = None, firmware: str = "0.6",
                 wheel_radius_m: float = 0.1, direction: int = 1, heartbeat_hz: float = 10.0,
                 encoder_hz: float = 50.0, vel_limit: float = 2.0, current_limit: float = 10.0,
                 vel_ramp_rate: float = 1.0, pos_gain: float = 20.0,
                 control_mode: int = ControlMode.POSITION_CONTROL, input_mode: int = InputMode.PASSTHROUGH,
                 watchdog_timeout_s: float | None = None, bus_voltage_v: float = 24.0, encoder_cpr: int = 8192,
                 fet_temp_c: float = 30.0, motor_temp_c: float = 30.0, tick_hz: float = 100.0,
                 history_size: int = 10_000, clock: Callable[[], float] = time.monotonic) -> None:
        name = f"odrive-{side}-{node_id}"
        super().__init__(name=name, interface=interface, channel=channel, bus_options=bus_options,
                         tick_hz=tick_hz, history_size=history_size, clock=clock)
        if getattr(vehicle, "model", "differential") != "differential":
            raise ValueError(f"{name}: an ODrive wheel needs a 'differential' vehicle, not {vehicle.model!r}")
        if direction not in (1, -1):
            raise ValueError(f"{name}: direction must be 1 or -1, got {direction!r}")
        if not wheel_radius_m > 0:
            raise ValueError(f"{name}: wheel_radius_m must be > 0, got {wheel_radius_m!r}")
        cs.arbitration_id(node_id, 0)  # validates node_id
        self.vehicle = vehicle
        self.side = side
        self.firmware = cs.check_firmware(firmware)
        self.direction = direction
        self.circumference_m = 2.0 * math.pi * wheel_radius_m
        self.encoder_cpr = encoder_cpr
        self.bus_voltage_v = bus_voltage_v
        self.bus_current_a = 0.0
        self.fet_temp_c = fet_temp_c
        self.motor_temp_c = motor_temp_c
        self._heartbeat_hz = heartbeat_hz
        self._encoder_hz = encoder_hz
        self._factory = OdriveConfig(node_id=node_id, control_mode=control_mode, input_mode=input_mode,
                                     vel_limit=vel_limit, current_limit=current_limit, vel_ramp_rate=vel_ramp_rate,
                                     pos_gain=pos_gain, watchdog_timeout=watchdog_timeout_s or 0.0,
                                     enable_watchdog=watchdog_timeout_s is not None)
        self.watchdog_trips: list[float] = []  # the node's clock at each expiry
        self.sdo_log: list[tuple[float, int, int, bytes]] = []  # (t, opcode, endpoint, value bytes)
        self._saved = dataclasses.replace(self._factory)
        self._odometer = WheelOdometer(vehicle, side)
        self._wheel_speed = 0.0
        self._setters: dict[int, Callable[[bytes, float], None]] = self._setter_table()
        self._getters: dict[int, Callable[[], bytes]] = self._getter_table()
        self._boot()

    @classmethod
    def wiring_options(cls, wiring: Mapping[str, Any], *, node_id: int) -> dict[str, Any]:
        """The keywords one node of a service takes from its driver's declared wiring (the mock catalog's
        CAN builder): the id, the firmware, and a ``vel_limit`` above the speed the driver limits its
        commands to (``command_limit_turns_per_s``), so the driver's own limit is the one that acts."""
        return {"node_id": int(node_id), "firmware": str(wiring.get("firmware", "0.6")),
                "vel_limit": float(wiring.get("command_limit_turns_per_s", 2.0)) * NODE_SPEED_MARGIN}

    # ---- state -----------------------------------------------------------------------
    def _boot(self) -> None:
        """Power-on state: IDLE, no errors, saved configuration, encoder position 0."""
        self.config = dataclasses.replace(self._saved)
        self.axis_state = AxisState.IDLE
        self.axis_error = 0
        self.motor_error = self.encoder_error = self.controller_error = 0  # 0.5.x sub-errors
        self.disarm_reason = 0
        self.procedure_result = ProcedureResult.SUCCESS
        self.identify = False
        self.input_vel = self.input_torque = self.input_pos = self.vel_ff = 0.0
        self.vel_setpoint = 0.0
        self._pos_offset = 0.0
        self._traj_done = True
        self._last_feed = self._last_tick = 0.0
        self._last_tick_real = 0.0      # time.monotonic() at the last tick: the thread's own stalls
        self._judge_silence_from = 0.0  # the node's clock: no tick-judged expiry before this
        self._odometer.rebase()
        self._heartbeat = PeriodicSchedule(self._heartbeat_hz, start=self.clock())
        self._encoder = PeriodicSchedule(self._encoder_hz, start=self.clock())
        self._drive(0.0)

    @property
    def node_id(self) -> int:
        """The CAN node id in force (0.5.x Set_Axis_Node_ID changes it)."""
        return self.config.node_id

    @property
    def wheel_speed_mps(self) -> float:
        """The surface speed the node last commanded to the vehicle (m/s)."""
        return self._wheel_speed

    def _drive(self, vel_rev_s: float) -> None:
        speed = vel_rev_s * self.circumference_m * self.direction
        if speed != self._wheel_speed:
            self.vehicle.set_wheel_speed(self.side, speed)
            self._wheel_speed = speed

    def _estimates(self) -> tuple[float, float]:
        distance, speed = self._odometer.sample()
        k = self.direction / self.circumference_m
        return self._pos_offset + distance * k, speed * k

    def _error_bit(self, name: str) -> int:
        table = cs.OdriveError if self.firmware == "0.6" else cs.AxisError05
        return int(table[name])

    def _raise_error(self, bits: int) -> None:
        self.axis_error |= bits
        if self.axis_state == AxisState.CLOSED_LOOP_CONTROL:
            self.disarm_reason = self.axis_error
            self.axis_state = AxisState.IDLE
            self.vel_setpoint = 0.0
            self._drive(0.0)

    # ---- faults ----------------------------------------------------------------------
    def inject_error(self, code: int, *, kind: str = "axis") -> None:
        """Raise an error as the firmware would and disarm: *kind* "axis" sets Axis_Error bits;
        with firmware 0.5 "motor", "encoder" or "controller" set that sub-error and its axis bit."""
        with self._lock:
            if kind == "axis":
                self._raise_error(code)
                return
            if self.firmware != "0.5" or kind not in ("motor", "encoder", "controller"):
                raise ValueError(f"{self.name}: error kind {kind!r} needs firmware 0.5 and one of "
                                 f"motor/encoder/controller (0.6 has only axis errors)")
            setattr(self, f"{kind}_error", getattr(self, f"{kind}_error") | code)
            self._raise_error(int(cs.AxisError05[f"{kind.upper()}_FAILED"]))

    def set_bus(self, *, voltage_v: float, current_a: float) -> None:
        """What Get_Bus_Voltage_Current reports from now on (battery sag, an over-current)."""
        with self._lock:
            self.bus_voltage_v, self.bus_current_a = voltage_v, current_a

    def _garbage_frame(self) -> can.Message:
        return cs.make_frame(self.node_id, Cmd.HEARTBEAT, b"\x00\x00\x00")

    def _on_stop(self) -> None:
        self._drive(0.0)

    # ---- the bus ---------------------------------------------------------------------
    def _handle(self, msg: can.Message, now: float) -> bool:
        if msg.is_extended_id or msg.arbitration_id > 0x7FF:
            return False
        node, cmd = cs.split_arbitration_id(msg.arbitration_id)
        if node != self.node_id:
            return False
        arrival = self._arrival(msg, now)
        wd = self.config.watchdog_timeout if self.config.enable_watchdog else 0.0
        if self.axis_state == AxisState.CLOSED_LOOP_CONTROL and wd > 0 and arrival - self._last_feed > wd:
            self._expire(now)   # the frames' own stamps show a gap longer than the timeout
        self._last_feed = max(self._last_feed, arrival)
        data = bytes(msg.data)
        if msg.is_remote_frame or (not data and cmd in self._getters):
            getter = self._getters.get(cmd)
            if getter is not None:
                self._send(cs.make_frame(self.node_id, cmd, getter()))
            return True
        setter = self._setters.get(cmd)
        if setter is not None:
            setter(data, now)
        return True

    @staticmethod
    def _arrival(msg: can.Message, now: float) -> float:
        """When *msg* reached the bus interface, on the node's clock: *now* less the age of its receive
        stamp (wall time), or *now* when it has none or an implausible one."""
        if not msg.timestamp:
            return now
        age = time.time() - float(msg.timestamp)
        return now - age if 0.0 <= age < 5.0 else now

    def _expire(self, now: float) -> None:
        self.watchdog_trips.append(now)
        self._raise_error(self._error_bit("WATCHDOG_TIMER_EXPIRED"))

    # ---- control loop ----------------------------------------------------------------
    def _tick(self, now: float) -> None:
        dt = min(now - self._last_tick, 0.1) if self._last_tick else 0.0
        self._last_tick = now
        real = time.monotonic()
        wd = self.config.watchdog_timeout if self.config.enable_watchdog else 0.0
        if self._last_tick_real and real - self._last_tick_real > SELF_STALL_S:
            self._judge_silence_from = now + wd   # the frames that queued while this thread waited come first
        self._last_tick_real = real
        pos, vel = self._estimates()
        if (self.axis_state == AxisState.CLOSED_LOOP_CONTROL and wd > 0 and now - self._last_feed > wd
                and now >= self._judge_silence_from):
            self._expire(now)
        self._drive(self._setpoint(pos, dt) if self.axis_state == AxisState.CLOSED_LOOP_CONTROL else 0.0)
        if self._heartbeat.due(now):
            self._send(cs.make_frame(self.node_id, Cmd.HEARTBEAT, cs.encode_heartbeat(cs.Heartbeat(
                self.axis_error, self.axis_state, self.procedure_result, self._traj_done,
                motor_error_flag=bool(self.motor_error), encoder_error_flag=bool(self.encoder_error),
                controller_error_flag=bool(self.controller_error)), firmware=self.firmware)))
        if self._encoder.due(now):
            self._send(cs.make_frame(self.node_id, Cmd.GET_ENCODER_ESTIMATES, cs.encode_encoder_estimates(pos, vel)))

    def _setpoint(self, pos: float, dt: float) -> float:
        """The velocity setpoint (rev/s) the controller tracks this tick."""
        cfg = self.config
        if cfg.control_mode == ControlMode.VELOCITY_CONTROL:
            target = max(-cfg.vel_limit, min(cfg.vel_limit, self.input_vel))
            if cfg.input_mode == InputMode.VEL_RAMP:
                step = cfg.vel_ramp_rate * dt
                self.vel_setpoint += max(-step, min(step, target - self.vel_setpoint))
            else:
                self.vel_setpoint = target
        elif cfg.control_mode == ControlMode.POSITION_CONTROL:
            limit = cfg.traj_vel_limit if cfg.input_mode == InputMode.TRAP_TRAJ else cfg.vel_limit
            error = self.input_pos - pos
            self.vel_setpoint = max(-limit, min(limit, cfg.pos_gain * error + self.vel_ff))
            self._traj_done = self._traj_done or abs(error) < 1e-3
        else:
            self.vel_setpoint = 0.0  # torque and voltage control are not modelled
        return self.vel_setpoint


def main(argv: list[str] | None = None) -> None:
    """Run one node with its own SimVehicle until SIGTERM/SIGINT (for tests across processes)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_bus_arguments(parser)
    parser.add_argument("--node-id", type=int, required=True)
    parser.add_argument("--firmware", choices=cs.FIRMWARES, default="0.6")
    parser.add_argument("--watchdog", type=float, default=None, help="watchdog timeout in s (default off)")
    args = parser.parse_args(argv)
    vehicle = SimVehicle(origin_lat=0.0, origin_lon=0.0)
    node = OdriveCanNode(vehicle, side=args.side, node_id=args.node_id, interface=args.interface,
                         channel=args.channel, bus_options=bus_options(args), firmware=args.firmware,
                         watchdog_timeout_s=args.watchdog)
    serve(node, vehicle)


if __name__ == "__main__":
    main()
