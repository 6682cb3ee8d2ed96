"""ODrive motor controllers over CAN (CANSimple, firmware 0.5.x or 0.6.x) as one Actuator.

One service drives one or more ODrive axes on one bus, each a node id mapped to an actuator
name (``actuators``/``node_ids``/``directions``/``wheel_radius_m``). For every axis it:

- arms it once its heartbeat is heard: Clear_Errors (``clear_errors_on_start``, first time
  only), Set_Controller_Mode(VELOCITY_CONTROL, ``input_mode``), optionally Set_Limits,
  Set_Input_Vel, Set_Axis_State(CLOSED_LOOP_CONTROL); the heartbeat must then show closed
  loop, else the attempt is reported (state, procedure result, errors) and retried with a
  backoff doubling from ``arm_retry_s`` to 5 s;
- turns on the axis's own watchdog before arming it (``hw_watchdog``, see below);
- maps a Percentage Command to ``percent / 100 * max_turns_per_s * direction`` rev/s,
  sends it at once and re-sends it every ``command_period_s`` to every heard axis, armed or
  not (every frame to the axis feeds its watchdog while we are alive);
- watches the heartbeat: an axis error is reported (and cleared and re-armed only with
  ``rearm_on_error`` or a ``clear_errors = true`` config change), with one exception: a
  WATCHDOG_TIMER_EXPIRED alone that this driver's own stall explains (its loop sent nothing
  long enough to starve the watchdog: a slow board, a SIGSTOP) is no hardware fault, and is
  cleared, logged with the stall, once the axis is heard again and the pilot re-arms through
  manual (drivers/can_motor/odrive/latch.py, drivers/can_motor/stall_trip.py; docs/safety.md); a heartbeat that stops for
  ``silent_after_s`` makes the node 'silent' (degraded); when it comes back the axis is
  re-armed if it needs to be;
- reads encoder estimates (cyclic, or RTR-polled at ``encoder_poll_hz``) into the wheel
  odometry -- a velocity beyond ``max_motor_rpm`` or a position beyond float32's whole-turn
  range is impossible, dropped and counted (``out_of_range_kinds``) -- and polls bus
  voltage/current, temperatures and error details every ``status_poll_s`` for health.

The ODrive watchdog (``axis.config.enable_watchdog``/``watchdog_timeout``) disarms the axis
when no CAN frame reaches it for ``hw_watchdog_timeout_s``: the last line of defence when this
process dies or hangs. Firmware 0.6 can have it written and read back over CAN (endpoint ids
``watchdog_timeout_endpoint``/``enable_watchdog_endpoint`` of the build ``endpoints_fw``);
firmware 0.5 cannot, and the driver says so. See drivers/can_motor/odrive/watchdog.py, which does this;
drivers/can_motor/odrive/axis.py holds what is known about each axis.

Neutral is 0 rev/s (stop, kill, command timeout, failsafe); on FAILSAFE it also sends Estop
when ``estop_on_failsafe`` is set (cleared and re-armed when the failsafe ends). On stop the
axes are put in IDLE when ``idle_on_stop`` is set. See docs/drivers-can.md.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Callable

if TYPE_CHECKING:
    import can   # python-can loads when the port opens (u2sa_hw/ports/can/port.py)

from u2sa_hw.config.fields import MAX_RATE_HZ, MAX_TIMEOUT_S, field
from u2sa_hw.protocols import odrive_cansimple as cs
from u2sa_hw.protocols.odrive_cansimple import AxisState, Cmd, ControlMode, InputMode, ProcedureResult

from u2sa_hw.drivers.can_motor.common import CanMotorService
from u2sa_hw.drivers.can_motor.watchdog import WatchdogStep, check_hw_watchdog, watchdog_summary
from u2sa_hw.drivers.can_motor.declarations import OdriveDeclarations
from u2sa_hw.drivers.can_motor.odrive.axis import OdriveAxis, enum_name, error_names
from u2sa_hw.drivers.can_motor.odrive.latch import OdriveTripLatch
from u2sa_hw.drivers.can_motor.odrive.watchdog import WATCHDOG_FIELDS, OdriveWatchdogSetup
from u2sa_hw.drivers.value_ranges import ValueDrops

INPUT_MODES = {"passthrough": InputMode.PASSTHROUGH, "vel_ramp": InputMode.VEL_RAMP}
MAX_ARM_BACKOFF_S = 5.0
# frames an ODrive sends (anything else on its ids is a host's command, e.g. our own echo)
_REPLIES_06 = frozenset({Cmd.HEARTBEAT, Cmd.GET_ENCODER_ESTIMATES, Cmd.GET_BUS_VOLTAGE_CURRENT, Cmd.GET_ERROR,
                         Cmd.GET_TEMPERATURE, Cmd.GET_IQ, Cmd.GET_VERSION, Cmd.TX_SDO})
_REPLIES_05 = frozenset({Cmd.HEARTBEAT, Cmd.GET_ENCODER_ESTIMATES, Cmd.GET_BUS_VOLTAGE_CURRENT, Cmd.GET_IQ,
                         Cmd.GET_MOTOR_ERROR, Cmd.GET_ENCODER_ERROR, Cmd.GET_CONTROLLER_ERROR})


class OdriveCanMotor(OdriveTripLatch, OdriveDeclarations, CanMotorService):
    """ODrive axes on CAN (CANSimple) as actuators, with heartbeat/error monitoring and odometry."""

    ID_FIELD = "node_ids"
    CONFIG = (
        field("node_ids", [0, 1], "CANSimple node id per actuator (0..62; 63 is 0.6's \"unaddressed\")", item_type=int,
              ge=0, le=cs.MAX_NODE_ID - 1),
        field("firmware", "0.6", "0.6 (ODrive Pro, S1, Micro) or 0.5 (ODrive v3.x)", choices=cs.FIRMWARES),
        field("max_turns_per_s", 2.0, "motor speed at 100 % (rev/s); commands are limited to it", gt=0, le=1000.0),
        field("input_mode", "passthrough", "passthrough or vel_ramp (the ramp rate is the ODrive's vel_ramp_rate)", choices=INPUT_MODES),
        field("set_limits", False, "send Set_Limits(max_turns_per_s, current_limit_a) when arming"),
        field("current_limit_a", 10.0, "current limit sent with set_limits (A)", gt=0, le=1000.0),
        field("encoder_poll_hz", 0.0, "0: use the node's cyclic encoder estimates; > 0: request them by RTR this often", ge=0, le=MAX_RATE_HZ),
        field("status_poll_s", 1.0, "bus voltage/current, temperatures and error details requested this often (0: never)", ge=0, le=MAX_TIMEOUT_S),
        field("arm_retry_s", 0.5, "first wait before an arming attempt is retried (doubles up to 5 s)", gt=0, le=MAX_TIMEOUT_S),
        field("clear_errors_on_start", True, "send Clear_Errors before the first arming of each axis"),
        field("rearm_on_error", False, "clear an axis error by itself and re-arm (else wait for clear_errors)"),
        field("clear_errors", False, "set true to clear every axis's errors and re-arm (resets itself to false)"),
        field("estop_on_failsafe", False, "on FAILSAFE send Estop as well as 0 rev/s (cleared when it ends)"),
        field("idle_on_stop", True, "put the axes in IDLE when the service stops (else hold 0 rev/s)"),
        field("hw_watchdog", True, "turn on each axis's own watchdog (it disarms when this driver dies or hangs)",
              remote=False),
        field("hw_watchdog_timeout_s", 0.3, "axis watchdog timeout (s); more than twice command_period_s", gt=0,
              le=1.0),
        field("watchdog_timeout_endpoint", 0, "0.6: endpoint id of axis0.config.watchdog_timeout in the "
                                               "flat_endpoints.json of endpoints_fw (0: unknown)", ge=0, le=0xFFFF),
        field("enable_watchdog_endpoint", 0, "0.6: endpoint id of axis0.config.enable_watchdog (0: unknown)", ge=0,
              le=0xFFFF),
        field("endpoints_fw", "", "0.6: the firmware (Get_Version, e.g. 0.6.10) the endpoint ids are from"),
        field("max_motor_rpm", 6000.0, "the fastest a motor can turn (rpm): an encoder estimate beyond it is "
                                       "impossible, dropped and counted (out_of_range in health)", gt=0, le=100000.0),
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.firmware = self.config.get("firmware")
        self._estopped = False
        self._to_clear = ""   # what clears the latched errors, as judged at the last tick (with the reason)
        self.axes: dict[str, OdriveAxis] = {}
        self._by_node: dict[int, OdriveAxis] = {}
        self.out_of_range = ValueDrops(self.logger, device=self.device_name, what="impossible")
        self._watchdog_setup = OdriveWatchdogSetup(config=self.config, send=self.send, label=self._label,
                                                   report_error=self.error, logger=self.logger)
        self._make_axes()

    def check_settings(self, get: Callable[[str], Any]) -> None:
        """The shared combinations, then the watchdog timeout against the command period."""
        super().check_settings(get)
        check_hw_watchdog(get, self._fail)

    def _make_axes(self) -> None:
        retry = self.config.get("arm_retry_s")
        self.axes = {n: OdriveAxis(spec, arm_retry_s=retry) for n, spec in self.motors.items()}
        self._by_node = {a.spec.can_id: a for a in self.axes.values()}

    def on_config_change(self, name: str, value: Any) -> None:
        """Apply a change: new axes for the id/name fields, a clear request for clear_errors."""
        super().on_config_change(name, value)
        with self.lock:
            if name in ("actuators", "node_ids", "directions", "wheel_radius_m", "arm_retry_s"):
                self._build()
                self._make_axes()
            self.firmware = self.config.get("firmware")
            if name in WATCHDOG_FIELDS:
                for axis in self.axes.values():
                    axis.wd = WatchdogStep()
            if name == "clear_errors" and value:
                self.logger.info("clearing errors and re-arming every axis (clear_errors set)")
                self._clear_all()
                self.config.set("clear_errors", False)

    # -- frames -------------------------------------------------------------------------------
    def _frame(self, axis: OdriveAxis, cmd: int, data: bytes = b"") -> bool:
        return self.send(cs.make_frame(axis.spec.can_id, cmd, data))

    def _request(self, axis: OdriveAxis, cmd: int) -> bool:
        return self.send(cs.make_request(axis.spec.can_id, cmd))

    def handle_frame(self, msg: can.Message, now: float) -> None:
        """Heartbeats and replies from our nodes; everything else (our own echoes too) is ignored."""
        if msg.is_extended_id or msg.is_remote_frame or msg.arbitration_id > 0x7FF:
            return
        node, cmd = cs.split_arbitration_id(msg.arbitration_id)
        axis = self._by_node.get(node)
        if axis is None or cmd not in (_REPLIES_06 if self.firmware == "0.6" else _REPLIES_05):
            return
        data = bytes(msg.data)
        if cmd == Cmd.HEARTBEAT:
            self._heartbeat(axis, cs.decode_heartbeat(data, firmware=self.firmware), now)
        elif cmd == Cmd.GET_ENCODER_ESTIMATES:
            self._encoder_estimates(axis, *cs.decode_encoder_estimates(data), stamp=self.frame_time(msg))
        elif cmd == Cmd.GET_BUS_VOLTAGE_CURRENT:
            axis.bus = cs.decode_bus_voltage_current(data)
        elif self.firmware == "0.6" and cmd == Cmd.GET_VERSION:
            self._watchdog_setup.on_version(axis, cs.decode_version(data), now)
        elif self.firmware == "0.6" and cmd == Cmd.TX_SDO:
            self._watchdog_setup.on_tx_sdo(axis, *cs.decode_tx_sdo(data))
        elif self.firmware == "0.6" and cmd == Cmd.GET_ERROR:
            axis.errors["active_errors"], axis.errors["disarm_reason"] = cs.decode_get_error(data)
        elif self.firmware == "0.6" and cmd == Cmd.GET_TEMPERATURE:
            axis.temps = cs.decode_floats(data, 2, what="Get_Temperature")  # type: ignore[assignment]
        elif cmd == Cmd.GET_MOTOR_ERROR:  # 0.5
            axis.errors["motor_error"] = cs.decode_motor_error(data)
        elif cmd in (Cmd.GET_ENCODER_ERROR, Cmd.GET_CONTROLLER_ERROR):  # 0.5
            key = "encoder_error" if cmd == Cmd.GET_ENCODER_ERROR else "controller_error"
            axis.errors[key] = cs.decode_u32(data, what=cs.command_name(cmd, firmware="0.5"))

    def _encoder_estimates(self, axis: OdriveAxis, pos_turns: float, vel_turns_s: float, *, stamp: float) -> None:
        """Position and velocity within what an axis can report (else dropped, counted) into the odometry."""
        top = self.config.get("max_motor_rpm") / 60.0
        vel = self.out_of_range.check("encoder velocity", vel_turns_s, -top, top, unit=" turns/s")
        pos = self.out_of_range.check("encoder position", pos_turns, -cs.MAX_POSITION_TURNS, cs.MAX_POSITION_TURNS,
                                      unit=" turns")
        if vel is None and pos is None:
            return
        axis.pos_turns, axis.vel_turns_s = pos, vel
        metres_per_turn = 2.0 * math.pi * axis.spec.radius_m * axis.spec.direction
        self.wheel_sample(axis.spec.name, stamp, position_m=None if pos is None else pos * metres_per_turn,
                          speed_mps=None if vel is None else vel * metres_per_turn)

    def _heartbeat(self, axis: OdriveAxis, hb: cs.Heartbeat, now: float) -> None:
        prev = axis.heartbeat
        axis.heartbeat, axis.last_heartbeat = hb, now
        label = self._label(axis)
        if axis.silent:
            axis.silent = False
            axis.retry_now()
            axis.wd = WatchdogStep()  # it may have rebooted: settings written over CAN live in RAM
            self.logger.info("%s answering again (%s)", label, enum_name(AxisState, hb.axis_state))
        self.latch(axis, hb)
        if hb.axis_error and (prev is None or prev.axis_error != hb.axis_error):
            axis.error_events += 1
            self.error(f"{label}: axis error {error_names(hb.axis_error, firmware=self.firmware)} "
                       f"({enum_name(AxisState, hb.axis_state)}); {self.error_advice(axis)}")
        if axis.armed and axis.arming_since is not None:
            self.logger.info("%s armed (CLOSED_LOOP_CONTROL) after %d attempt(s)", label, axis.arm_attempts)
            axis.arming_since = None
            axis.retry_now()
        elif prev is not None and prev.axis_state == AxisState.CLOSED_LOOP_CONTROL and not axis.armed:
            self.logger.warning("%s left closed loop: now %s, error %s", label, enum_name(AxisState, hb.axis_state),
                                error_names(hb.axis_error, firmware=self.firmware))

    def _label(self, axis: OdriveAxis) -> str:
        return f"ODrive {axis.spec.name} (node {axis.spec.can_id} on {self.device_name})"

    # -- periodic work ------------------------------------------------------------------------
    def tick(self, now: float) -> None:
        """Estop/clear on failsafe edges; per axis: silence, arming, setpoint re-send, polls."""
        cfg = self.config
        if cfg.get("estop_on_failsafe"):
            if self.failsafe_active and not self._estopped:
                self._estopped = True
                self.logger.warning("failsafe: Estop to every axis")
                for axis in self.axes.values():
                    self._frame(axis, Cmd.ESTOP)
            elif not self.failsafe_active and self._estopped:
                self._estopped = False
                self.logger.info("failsafe over: clearing the Estop and re-arming")
                self._clear_all()
        for axis in self.axes.values():
            self.attribute_trip(axis)
            if self._check_silence(axis, now) or axis.heartbeat is None:
                continue
            if not axis.wd.settled:
                self._watchdog_setup.step(axis, now, firmware=self.firmware)
            if now >= axis.next_command:  # armed or not: every frame feeds the axis watchdog
                self._send_setpoint(axis, now)
            if not axis.armed:
                self._maybe_arm(axis, now)
            self._poll(axis, now)
        # judged here, with the degraded reason, not when health is read: a trip heard since the last tick is
        # attributed to a stall only at the next one, and health must not name the deliberate clear meanwhile
        self._to_clear = self.to_clear()

    def _clear_all(self) -> None:
        """Clear_Errors to every axis that is heard now; each re-arms at its next heartbeat."""
        for axis in self.axes.values():
            if axis.heartbeat is not None and not axis.silent:
                self._frame(axis, Cmd.CLEAR_ERRORS, cs.encode_clear_errors(firmware=self.firmware))
            axis.retry_now()

    def _check_silence(self, axis: OdriveAxis, now: float) -> bool:
        last = axis.last_heartbeat if axis.last_heartbeat is not None else self.started_at
        if now - last <= self.config.get("silent_after_s") or not self.judging_silence:
            return axis.silent
        if not axis.silent:
            axis.silent = True
            axis.silent_events += 1
            heard = "never heard" if axis.last_heartbeat is None else f"no heartbeat for {now - last:.1f} s"
            self.error(f"{self._label(axis)}: node silent ({heard}); check power, wiring and its node id")
            if self.odometry is not None:
                self.odometry.reset()
        return True

    def _send_setpoint(self, axis: OdriveAxis, now: float) -> None:
        axis.next_command = now + self.config.get("command_period_s")
        self._frame(axis, Cmd.SET_INPUT_VEL, cs.encode_set_input_vel(axis.target))

    def _maybe_arm(self, axis: OdriveAxis, now: float) -> None:
        cfg = self.config
        hb = axis.heartbeat
        if hb is None or now < axis.next_arm or (self.failsafe_active and cfg.get("estop_on_failsafe")):
            return
        if not axis.wd.settled:
            return  # the watchdog first; its set-up settles within WD_TRIES * WD_REPLY_S
        clear = (axis.arm_attempts == 0 and cfg.get("clear_errors_on_start")) \
            or (bool(hb.axis_error) and (cfg.get("rearm_on_error") or self.stall_trip_clears(axis, hb)))
        if hb.axis_error and not clear:
            return  # reported as an error until someone clears it
        if axis.arming_since is not None:
            axis.arm_failures += 1
            result = f", procedure result {enum_name(ProcedureResult, hb.procedure_result)}" \
                if self.firmware == "0.6" else ""
            self.error(f"{self._label(axis)}: not in closed loop {now - axis.arming_since:.1f} s after arming "
                       f"(state {enum_name(AxisState, hb.axis_state)}{result}, error "
                       f"{error_names(hb.axis_error, firmware=self.firmware)}); retrying in {axis.backoff:.1f} s")
        if clear:
            self._frame(axis, Cmd.CLEAR_ERRORS, cs.encode_clear_errors(firmware=self.firmware))
        self._frame(axis, Cmd.SET_CONTROLLER_MODE, cs.encode_set_controller_mode(
            ControlMode.VELOCITY_CONTROL, INPUT_MODES[cfg.get("input_mode")]))
        if cfg.get("set_limits"):
            self._frame(axis, Cmd.SET_LIMITS, cs.encode_set_limits(cfg.get("max_turns_per_s"),
                                                                   cfg.get("current_limit_a")))
        self._frame(axis, Cmd.SET_INPUT_VEL, cs.encode_set_input_vel(axis.target))
        self._frame(axis, Cmd.SET_AXIS_STATE, cs.encode_set_axis_state(AxisState.CLOSED_LOOP_CONTROL))
        axis.arm_attempts += 1
        axis.arming_since = axis.arming_since if axis.arming_since is not None else now
        axis.next_arm = now + axis.backoff
        axis.backoff = min(axis.backoff * 2.0, MAX_ARM_BACKOFF_S)

    def _poll(self, axis: OdriveAxis, now: float) -> None:
        cfg = self.config
        if cfg.get("encoder_poll_hz") > 0 and now >= axis.next_encoder_poll:
            axis.next_encoder_poll = now + 1.0 / cfg.get("encoder_poll_hz")
            self._request(axis, Cmd.GET_ENCODER_ESTIMATES)
        if cfg.get("status_poll_s") > 0 and now >= axis.next_poll:
            axis.next_poll = now + cfg.get("status_poll_s")
            self._request(axis, Cmd.GET_BUS_VOLTAGE_CURRENT)
            if self.firmware == "0.6":
                self._request(axis, Cmd.GET_TEMPERATURE)
                self._request(axis, Cmd.GET_ERROR)
            elif axis.heartbeat is not None:
                hb = axis.heartbeat
                for flag, cmd in ((hb.motor_error_flag, Cmd.GET_MOTOR_ERROR),
                                  (hb.encoder_error_flag, Cmd.GET_ENCODER_ERROR),
                                  (hb.controller_error_flag, Cmd.GET_CONTROLLER_ERROR)):
                    if flag:
                        self._request(axis, cmd)

    # -- actuator ----------------------------------------------------------------------------------
    def set_output(self, name: str, percent: float) -> None:
        """*percent* of max_turns_per_s in the axis's direction; sent now if the axis is armed."""
        axis = self.axes[name]
        limit = self.config.get("max_turns_per_s")
        axis.target = max(-limit, min(limit, percent / 100.0 * limit)) * axis.spec.direction
        if axis.armed and not axis.silent:
            self._send_setpoint(axis, self.now())

    def zero_outputs(self) -> None:
        """0 rev/s on every axis that is heard, sent now."""
        for axis in self.axes.values():
            axis.target = 0.0
            if axis.heartbeat is not None and not axis.silent:
                self._send_setpoint(axis, self.now())

    def release(self) -> None:
        """IDLE on every heard axis when idle_on_stop (the motor no longer holds 0 rev/s)."""
        if not self.config.get("idle_on_stop"):
            return
        for axis in self.axes.values():
            if axis.heartbeat is not None and not axis.silent:
                self._frame(axis, Cmd.SET_AXIS_STATE, cs.encode_set_axis_state(AxisState.IDLE))

    def on_port_lost(self) -> None:
        """The bus is gone: every axis must be heard (and armed) again."""
        for axis in self.axes.values():
            axis.heartbeat = None
            axis.arming_since = None
            axis.retry_now()
            axis.wd = WatchdogStep()
        if self.odometry is not None:
            self.odometry.reset()

    # -- health ----------------------------------------------------------------------------------
    def problems(self, now: float) -> list[str]:
        """Silent nodes, axis errors, axes not (yet) in closed loop."""
        out = []
        for axis in self.axes.values():
            hb, name = axis.heartbeat, f"{axis.spec.name} (node {axis.spec.can_id})"
            if axis.silent:
                out.append(f"{name} node silent")
            elif hb is not None and hb.axis_error:
                out.append(self.error_problem(axis, hb))
            elif hb is not None and not axis.armed:
                out.append(f"{name} not armed ({enum_name(AxisState, hb.axis_state)})")
            if axis.wd.state == "error":
                out.append(f"{name} watchdog {axis.wd.text.split(';')[0]}")
        return out

    def motor_details(self) -> dict[str, Any]:
        """Per axis (keys ``<actuator>.<what>``): state, errors, setpoint, estimates, bus, temperatures;
        ``to_clear``: what clears a latched error."""
        now = self.now()
        details: dict[str, Any] = {"firmware": self.firmware, "estopped": self._estopped,
                                   "to_clear": self._to_clear,
                                   **self.out_of_range.details("out_of_range"),
                                   "odometry_rejected": self.odometry.rejected if self.odometry else 0,
                                   "hw_watchdog": watchdog_summary({n: a.wd.text for n, a in self.axes.items()})}
        for name, axis in self.axes.items():
            hb = axis.heartbeat
            phase = "silent" if axis.silent else "waiting" if hb is None else "armed" if axis.armed \
                else "error" if hb.axis_error else "arming" if axis.arming_since is not None else "idle"
            d = {"node": axis.spec.can_id, "phase": phase,
                 "state": enum_name(AxisState, hb.axis_state) if hb else "",
                 "error": error_names(hb.axis_error, firmware=self.firmware) if hb else "",
                 "heartbeat_age_s": f"{now - axis.last_heartbeat:.2f}" if axis.last_heartbeat else "",
                 "silent_events": axis.silent_events, "error_events": axis.error_events,
                 "arm_attempts": axis.arm_attempts, "arm_failures": axis.arm_failures,
                 "stall_clears": axis.stall_clears,
                 "setpoint_turns_s": f"{axis.target:.3f}", "hw_watchdog": axis.wd.text,
                 "vel_turns_s": "" if axis.vel_turns_s is None else f"{axis.vel_turns_s:.3f}",
                 "pos_turns": "" if axis.pos_turns is None else f"{axis.pos_turns:.3f}"}
            if hb is not None and self.firmware == "0.6":
                d["procedure_result"] = enum_name(ProcedureResult, hb.procedure_result)
            if axis.bus is not None:
                d["bus_voltage_v"], d["bus_current_a"] = f"{axis.bus[0]:.2f}", f"{axis.bus[1]:.2f}"
            if axis.temps is not None:
                d["fet_temp_c"], d["motor_temp_c"] = f"{axis.temps[0]:.1f}", f"{axis.temps[1]:.1f}"
            for key, bits in axis.errors.items():
                d[key] = hex(bits)
            details.update({f"{name}.{k}": v for k, v in d.items()})
        return details
