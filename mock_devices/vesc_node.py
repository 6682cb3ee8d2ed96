"""A mock VESC motor controller on CAN (VESC mode, extended ids) driving one SimVehicle side.

SET_DUTY and SET_RPM drive the motor: the electrical speed is ``duty * max_erpm`` or the
commanded ERPM (limited to +-max_erpm). On a ``differential`` vehicle that turns a wheel
(``erpm / pole_pairs / gear_ratio`` rev/min of a wheel of radius wheel_radius_m, times
direction); on a ``twin_thruster`` vehicle it sets that side's thrust to
``erpm / max_erpm * direction``. SET_CURRENT(_REL), the brake and handbrake commands and
SET_POS are accepted and reported (current in STATUS, position in STATUS_4) but hold the
motor still: the mock has no torque model.

Like the firmware's app-config ``timeout_msec`` (timeout.c), a motor that gets no command
for ``timeout_s`` is released (the mock stops the wheel / thruster; each expiry is kept in
``timeouts``); 0 disables the timeout. COMM_GET_APPCONF and COMM_SET_APPCONF arrive in CAN
buffers (FILL_RX_BUFFER.. PROCESS_RX_BUFFER) and are answered the same way to the sender's
id; the app configuration is serialized as the firmware does up to timeout_msec (the rest is
filler), so a driver reads and writes timeout_s over CAN. ``freeze_config(True)`` acknowledges
a SET_APPCONF without applying it; ``answer_comm = False`` ignores COMM packets (a VESC whose
CAN mode is not VESC).
The STATUS frames chosen in ``status_messages`` (1..6; default 1, 4 and 5, as VESC Tool's
"CAN Status Message Mode") are sent at ``status_hz``. ERPM and the tachometer (6 counts per
electrical revolution) come from the vehicle's wheel odometer on a differential vehicle, and
from the commanded speed on a boat (a propeller has no odometer). PING is answered with PONG.
``python -m u2sa_hw.mocks.vesc_node --help`` runs one node with its own vehicle.
"""

from __future__ import annotations

import argparse
import math
import struct
import time
from typing import Any, Callable, Iterable, Mapping

import can

from u2sa_hw.mocks.can_node import MockCanNode, PeriodicSchedule, WheelOdometer, add_bus_arguments, bus_options, serve
from u2sa_hw.mocks.vehicle_sim import SimVehicle
from u2sa_hw.protocols import vesc_can as vc
from u2sa_hw.protocols.vesc_can import FaultCode, PacketId

DRIVES = ("wheel", "thruster")
HW_TYPE_VESC = 0
APPCONF_SIGNATURE = 0x4D4F434B  # this mock's own; a real firmware's changes with its version
APPCONF_FILLER = 290  # bytes after timeout_msec, so an answer needs FILL_RX_BUFFER_LONG too
_BUFFER_PACKETS = frozenset({PacketId.FILL_RX_BUFFER, PacketId.FILL_RX_BUFFER_LONG, PacketId.PROCESS_RX_BUFFER,
                             PacketId.PROCESS_SHORT_BUFFER})
_MODES = {PacketId.SET_DUTY: "duty", PacketId.SET_RPM: "rpm", PacketId.SET_CURRENT: "current",
          PacketId.SET_CURRENT_REL: "current", PacketId.SET_CURRENT_BRAKE: "brake",
          PacketId.SET_CURRENT_BRAKE_REL: "brake", PacketId.SET_CURRENT_HANDBRAKE: "brake",
          PacketId.SET_CURRENT_HANDBRAKE_REL: "brake", PacketId.SET_POS: "pos"}
_RELATIVE = frozenset({PacketId.SET_CURRENT_REL, PacketId.SET_CURRENT_BRAKE_REL, PacketId.SET_CURRENT_HANDBRAKE_REL})


def _wrap_i32(value: float) -> int:
    return (int(value) + 0x80000000) % 0x100000000 - 0x80000000


class VescCanNode(MockCanNode):
    """One VESC with CAN id *controller_id* on *interface*/*channel*, driving *side* of the vehicle."""

    def __init__(self, vehicle: SimVehicle, *, side: str, controller_id: int, interface: str, channel: str,
                 bus_options: Mapping[str, Any] | None = None, drive: str | None = None, pole_pairs: int = 7,
                 gear_ratio: float = 1.0, wheel_radius_m: float = 0.1, direction: int = 1,
                 max_erpm: float = 7000.0, max_current_a: float = 50.0, timeout_s: float = 0.5,
                 status_hz: float = 50.0, status_messages: Iterable[int] = (1, 4, 5), voltage_in_v: float = 24.0,
                 temp_fet_c: float = 30.0, temp_motor_c: float = 28.0, tick_hz: float = 100.0,
                 history_size: int = 10_000, clock: Callable[[], float] = time.monotonic) -> None:
        name = f"vesc-{side}-{controller_id}"
        super().__init__(name=name, interface=interface, channel=channel, bus_options=bus_options,
                         tick_hz=tick_hz, history_size=history_size, clock=clock)
        if drive is None:
            drive = "thruster" if getattr(vehicle, "model", "differential") == "twin_thruster" else "wheel"
        if drive not in DRIVES:
            raise ValueError(f"{name}: drive must be 'wheel' or 'thruster', got {drive!r}")
        if direction not in (1, -1):
            raise ValueError(f"{name}: direction must be 1 or -1, got {direction!r}")
        for label, value in (("pole_pairs", pole_pairs), ("gear_ratio", gear_ratio),
                             ("wheel_radius_m", wheel_radius_m), ("max_erpm", max_erpm)):
            if not value > 0:
                raise ValueError(f"{name}: {label} must be > 0, got {value!r}")
        if not 0 <= controller_id < vc.BROADCAST_ID:
            raise ValueError(f"{name}: controller_id must be 0..254 (255 is broadcast), got {controller_id}")
        statuses = tuple(status_messages)
        if not set(statuses) <= {1, 2, 3, 4, 5, 6}:
            raise ValueError(f"{name}: status_messages must be numbers 1..6, got {statuses!r}")
        self.vehicle = vehicle
        self.side = side
        self.controller_id = controller_id
        self.drive = drive
        self.pole_pairs = pole_pairs
        self.gear_ratio = gear_ratio
        self.circumference_m = 2.0 * math.pi * wheel_radius_m
        self.direction = direction
        self.max_erpm = max_erpm
        self.max_current_a = max_current_a
        self.timeout_s = timeout_s
        self.voltage_in_v = voltage_in_v
        self.temp_fet_c = temp_fet_c
        self.temp_motor_c = temp_motor_c
        self.status_messages = statuses
        self.fault_code = FaultCode.NONE
        self.mode = "released"
        self.command_value = 0.0  # the last command's value in its own unit (duty, ERPM, A, deg)
        self._last_command = 0.0
        self._output = 0.0
        self._erpm_target = 0.0
        self._tacho_counts = 0.0  # integrated from the commanded speed (thruster drive)
        self._last_tick = 0.0
        self._status = PeriodicSchedule(status_hz, start=self.clock())
        self._assembler = vc.BufferAssembler()
        self.timeouts: list[float] = []  # the node's clock at each command timeout that released the motor
        self.appconf_writes = 0
        self.answer_comm = True
        self._odometer = WheelOdometer(vehicle, side) if drive == "wheel" else None

    @classmethod
    def wiring_options(cls, wiring: Mapping[str, Any], *, node_id: int) -> dict[str, Any]:
        """The keywords one node of a service takes from its driver's declared wiring (the mock catalog's
        CAN builder): the controller id and the ERPM scale the driver converts speeds with."""
        return {"controller_id": int(node_id), "max_erpm": float(wiring.get("max_erpm", 7000.0)),
                "pole_pairs": int(wiring.get("pole_pairs", 7)), "gear_ratio": float(wiring.get("gear_ratio", 1.0))}

    # ---- faults ----------------------------------------------------------------------
    def set_fault(self, code: int) -> None:
        """Latch a firmware fault (mc_fault_code): the motor is released and commands are ignored
        until ``set_fault(0)``. The fault is not in any STATUS frame; a driver sees the motor stop."""
        with self._lock:
            self.fault_code = FaultCode(code)
            if self.fault_code != FaultCode.NONE:
                self._release()

    def _garbage_frame(self) -> can.Message:
        return vc.make_frame(self.controller_id, PacketId.STATUS, b"\x00\x01\x02")

    def _on_stop(self) -> None:
        self._release()

    # ---- motor -----------------------------------------------------------------------
    @property
    def output(self) -> float:
        """What the node last gave the vehicle: wheel surface speed (m/s) or thrust fraction."""
        return self._output

    def _release(self) -> None:
        self.mode = "released"
        self.command_value = 0.0
        self._set_erpm(0.0)

    def _set_erpm(self, erpm: float) -> None:
        self._erpm_target = erpm
        if self.drive == "thruster":
            output = erpm / self.max_erpm * self.direction
            if output != self._output:
                self.vehicle.set_thrust(self.side, output)
        else:
            output = erpm / (self.pole_pairs * self.gear_ratio) / 60.0 * self.circumference_m * self.direction
            if output != self._output:
                self.vehicle.set_wheel_speed(self.side, output)
        self._output = output

    def _command_erpm(self) -> float:
        if self.mode == "duty":
            return self.command_value * self.max_erpm
        if self.mode == "rpm":
            return max(-self.max_erpm, min(self.max_erpm, self.command_value))
        return 0.0

    # ---- the bus ---------------------------------------------------------------------
    def _handle(self, msg: can.Message, now: float) -> bool:
        if not msg.is_extended_id or msg.is_remote_frame or msg.arbitration_id > 0xFFFF:
            return False
        packet, target = vc.split_ext_id(msg.arbitration_id)
        if target not in (self.controller_id, vc.BROADCAST_ID):
            return False
        if packet in _BUFFER_PACKETS:
            if target == self.controller_id and self.answer_comm:
                done = self._assembler.feed(packet, msg.data)
                if done is not None:
                    self._comm(*done)
            return True
        if packet == PacketId.PING:
            if msg.data:  # byte 0: the sender's id, which the PONG goes to
                self._send(vc.make_frame(msg.data[0], PacketId.PONG, bytes([self.controller_id, HW_TYPE_VESC])))
            return True
        if packet not in vc.COMMAND_SCALES:
            return packet not in vc.STATUS_NUMBER  # other VESCs' status is not for us
        value = vc.decode_command(packet, msg.data)
        if self.fault_code != FaultCode.NONE:
            return True
        if packet in _RELATIVE:
            value *= self.max_current_a
        self.mode = _MODES[PacketId(packet)]
        self.command_value = value
        self._last_command = now
        self._set_erpm(self._command_erpm())
        return True

    def appconf(self) -> bytes:
        """The app configuration as COMM_GET_APPCONF returns it."""
        head = struct.pack(">IBIf", APPCONF_SIGNATURE, self.controller_id, round(self.timeout_s * 1000), 0.0)
        return head + bytes(APPCONF_FILLER)

    def _comm(self, sender: int, send: int, payload: bytes) -> None:
        """One COMM packet from *sender*: the app configuration is read and written here."""
        command = payload[0]
        if command == vc.CommPacket.GET_APPCONF:
            answer = bytes([command]) + self.appconf()
        elif command == vc.CommPacket.SET_APPCONF:
            timeout_ms = vc.appconf_timeout_ms(payload[1:], controller_id=self.controller_id)
            self.appconf_writes += 1
            if not self.config_frozen:
                self.timeout_s = timeout_ms / 1000.0
            answer = bytes([command])
        else:
            return  # other COMM packets are not modelled
        if send == vc.SEND_REPLY:
            for frame in vc.buffer_frames(sender, self.controller_id, answer, send=1):
                self._send(frame)

    # ---- control loop ----------------------------------------------------------------
    def _tick(self, now: float) -> None:
        dt = min(now - self._last_tick, 0.1) if self._last_tick else 0.0
        self._last_tick = now
        if self.mode != "released" and self.timeout_s > 0 and now - self._last_command > self.timeout_s:
            self.timeouts.append(now)
            self._release()
        self._set_erpm(self._command_erpm())
        self._tacho_counts += self._erpm_target / 60.0 * dt * 6.0
        if self._status.due(now):
            for number in self.status_messages:
                status = self._status_message(number)
                self._send(vc.make_frame(self.controller_id, vc.status_packet_id(status), vc.encode_status(status)))

    def _measured(self) -> tuple[float, float]:
        """(ERPM, tachometer counts) as the motor's own sensing would report them."""
        if self._odometer is None:
            return self._erpm_target, self._tacho_counts
        distance, speed = self._odometer.sample()
        erev_per_m = self.direction / self.circumference_m * self.gear_ratio * self.pole_pairs
        return speed * erev_per_m * 60.0, distance * erev_per_m * 6.0

    def _status_message(self, number: int) -> vc.StatusMessage:
        erpm, tacho = self._measured()
        current = self.command_value if self.mode == "current" else 0.0
        if number == 1:
            return vc.Status1(erpm=erpm, current_a=current, duty=self._erpm_target / self.max_erpm)
        if number == 2:
            return vc.Status2(amp_hours=0.0, amp_hours_charged=0.0)
        if number == 3:
            return vc.Status3(watt_hours=0.0, watt_hours_charged=0.0)
        if number == 4:
            rotor_deg = (tacho / 6.0 / self.pole_pairs) % 1.0 * 360.0
            pid_pos = self.command_value % 360.0 if self.mode == "pos" else rotor_deg
            return vc.Status4(temp_fet_c=self.temp_fet_c, temp_motor_c=self.temp_motor_c, current_in_a=0.0,
                              pid_pos_deg=pid_pos)
        if number == 5:
            return vc.Status5(tachometer=_wrap_i32(tacho), voltage_in_v=self.voltage_in_v)
        return vc.Status6(adc1_v=0.0, adc2_v=0.0, adc3_v=0.0, ppm=0.0)


def main(argv: list[str] | None = None) -> None:
    """Run one node with its own SimVehicle until SIGTERM/SIGINT (for tests across processes)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_bus_arguments(parser)
    parser.add_argument("--controller-id", type=int, required=True)
    parser.add_argument("--model", choices=("differential", "twin_thruster"), default="differential")
    parser.add_argument("--timeout", type=float, default=0.5, help="command timeout in s (0 = off)")
    args = parser.parse_args(argv)
    vehicle = SimVehicle(origin_lat=0.0, origin_lon=0.0, model=args.model)
    node = VescCanNode(vehicle, side=args.side, controller_id=args.controller_id, interface=args.interface,
                       channel=args.channel, bus_options=bus_options(args), timeout_s=args.timeout)
    serve(node, vehicle)


if __name__ == "__main__":
    main()
