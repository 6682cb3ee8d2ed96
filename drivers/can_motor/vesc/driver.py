"""VESC motor controllers over CAN (VESC mode, extended ids) as one Actuator.

One service drives one or more VESCs on one bus, each a controller id mapped to an actuator
name (``actuators``/``controller_ids``/``directions``/``wheel_radius_m``). A Percentage
Command becomes SET_DUTY (``mode = "duty"``: ``percent / 100 * max_duty``) or SET_RPM
(``mode = "rpm"``: ``percent / 100 * max_erpm`` electrical RPM), times the direction.

The VESC releases its motor when no command arrives for its app ``timeout_msec``, so the
setpoint is re-sent every ``command_period_s`` (default 50 ms) for as long as the service
runs, and a dead or hung driver stops the motors within that timeout. With ``hw_watchdog``
the driver reads the app configuration of every VESC over CAN (COMM_GET_APPCONF, answered
to ``host_id``), and when its timeout_msec is not ``hw_watchdog_timeout_s`` writes it back
changed (COMM_SET_APPCONF: the VESC stores it in flash, so this happens once) and reads it
again; the outcome is the ``hw_watchdog`` health detail.

Neutral (stop, kill, command timeout, failsafe) is ``SET_CURRENT 0`` (``neutral =
"release"``: the motor coasts) or zero in the command mode (``neutral = "zero"``: duty 0 /
0 ERPM, which brakes). The STATUS frames (1: ERPM, current, duty; 4: temperatures, input
current; 5: tachometer, input voltage; the rest if enabled) go into health; a controller
with no STATUS for ``silent_after_s`` is 'silent'. A VESC fault is not in any STATUS frame,
so a motor that is commanded (at least ``stall_percent``) but turns slower than
``stall_erpm`` for ``stall_after_s`` is reported as not following its command.

Wheel odometry: speed from STATUS ERPM (``odometry_source = "velocity"``) or travel from the
STATUS_5 tachometer (``"position"``), with ``pole_pairs`` and ``gear_ratio`` (motor turns
per wheel turn). A STATUS with an ERPM beyond ``max_motor_erpm`` or a duty cycle outside
-1..1 is impossible: dropped, counted (``out_of_range_kinds``) and logged once. See
docs/drivers-can.md.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Callable

if TYPE_CHECKING:
    import can   # python-can loads when the port opens (u2sa_hw/ports/can/port.py)

from u2sa_hw.config.fields import MAX_TIMEOUT_S, field
from u2sa_hw.protocols import vesc_can as vc
from u2sa_hw.protocols.vesc_can import PacketId

from u2sa_hw.drivers.can_motor.common import CanMotorService
from u2sa_hw.drivers.can_motor.settings import MotorSpec
from u2sa_hw.drivers.can_motor.watchdog import WatchdogStep, check_hw_watchdog, watchdog_summary
from u2sa_hw.drivers.can_motor.declarations import VescDeclarations
from u2sa_hw.drivers.value_ranges import ValueDrops

MODES = {"duty": PacketId.SET_DUTY, "rpm": PacketId.SET_RPM}
_BUFFER_PACKETS = frozenset({PacketId.FILL_RX_BUFFER, PacketId.FILL_RX_BUFFER_LONG, PacketId.PROCESS_RX_BUFFER,
                             PacketId.PROCESS_SHORT_BUFFER})
NEUTRALS = ("release", "zero")
TACHO_COUNTS_PER_EREV = 6
WD_REPLY_S = 1.0  # an app configuration is ~50 frames each way
WD_TRIES = 3
_WATCHDOG_FIELDS = frozenset({"hw_watchdog", "hw_watchdog_timeout_s", "host_id", "command_period_s"})


def _unwrap_i32(delta: int) -> int:
    return (delta + 0x80000000) % 0x100000000 - 0x80000000


class VescMotor:
    """What the driver knows about one VESC (mutated under the service's lock)."""

    def __init__(self, spec: MotorSpec) -> None:
        self.spec = spec
        self.percent = 0.0
        self.last_status: float | None = None
        self.silent = False
        self.silent_events = 0
        self.status: dict[int, Any] = {}  # STATUS number -> its latest dataclass
        self.tacho_raw: int | None = None
        self.tacho_total = 0  # unwrapped tachometer counts since start
        self.stall_since: float | None = None
        self.stalled = False
        self.stall_events = 0
        self.next_command = 0.0
        self.wd = WatchdogStep()
        self.wrote = False  # the app configuration was written once this session


class VescCanMotor(VescDeclarations, CanMotorService):
    """VESCs on CAN as actuators, with STATUS monitoring and odometry."""

    ID_FIELD = "controller_ids"
    CONFIG = (
        field("controller_ids", [0, 1], "VESC CAN id per actuator (0..254)", item_type=int, ge=0,
              le=vc.BROADCAST_ID - 1),
        field("mode", "duty", "duty: SET_DUTY; rpm: SET_RPM (speed control in the VESC)", choices=MODES),
        field("max_duty", 0.95, "duty cycle at 100 % in duty mode (0..1)", gt=0, le=1),
        field("max_erpm", 7000.0, "electrical RPM at 100 % in rpm mode", gt=0, le=1000000.0),
        field("neutral", "release", "release: SET_CURRENT 0 (coast); zero: 0 in the command mode (brake)", choices=NEUTRALS),
        field("pole_pairs", 7, "motor pole pairs (ERPM / pole pairs = motor RPM), for the odometry", ge=1, le=100),
        field("gear_ratio", 1.0, "motor turns per wheel turn, for the odometry", gt=0, le=1000.0),
        field("stall_after_s", 1.0, "commanded but not turning for this long -> reported (0: never)", ge=0, le=MAX_TIMEOUT_S),
        field("stall_percent", 10.0, "commands below this |%| are never a stall", ge=0, le=100),
        field("stall_erpm", 50.0, "slower than this |ERPM| counts as not turning", ge=0, le=1000000.0),
        field("hw_watchdog", True, "set and check each VESC's timeout_msec (it releases the motor when this "
                                   "driver dies or hangs)", remote=False),
        field("hw_watchdog_timeout_s", 0.3, "VESC command timeout (s); more than twice command_period_s", gt=0,
              le=1.0),
        field("host_id", 254, "this driver's CAN id: the VESCs answer configuration reads to it (not a VESC's id)", ge=0, le=254),
        field("max_motor_erpm", 100000.0, "the fastest a motor can turn (ERPM; the firmware's default l_max_erpm): "
                                          "a STATUS beyond it is impossible, dropped and counted", gt=0, le=1000000.0),
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.vescs: dict[str, VescMotor] = {}
        self._by_id: dict[int, VescMotor] = {}
        self._assembler = vc.BufferAssembler()
        self.out_of_range = ValueDrops(self.logger, device=self.device_name, what="impossible")
        self._wd_busy: VescMotor | None = None  # the one VESC a configuration request is out to
        self._wd_deadline = 0.0
        self._make_vescs()

    def check_settings(self, get: Callable[[str], Any]) -> None:
        """The shared combinations, then the watchdog timeout against the command period and the host id
        against the VESCs' ids (each field's own choices and bounds are declared)."""
        super().check_settings(get)
        check_hw_watchdog(get, self._fail)
        host = get("host_id")
        if host in get("controller_ids"):
            raise self._fail(f"host_id must be a CAN id 0..254 that no VESC uses (controller_ids "
                             f"{get('controller_ids')!r}), got {host!r}; give host_id an unused id (default 254)")

    def _make_vescs(self) -> None:
        self.vescs = {n: VescMotor(spec) for n, spec in self.motors.items()}
        self._by_id = {m.spec.can_id: m for m in self.vescs.values()}

    def on_config_change(self, name: str, value: Any) -> None:
        """New controllers for the id/name fields; mode and scales apply at the next re-send."""
        super().on_config_change(name, value)
        with self.lock:
            if name in ("actuators", "controller_ids", "directions", "wheel_radius_m"):
                self._build()
                self._make_vescs()
            if name in _WATCHDOG_FIELDS:
                for motor in self.vescs.values():
                    motor.wd, motor.wrote = WatchdogStep(), False
                self._wd_busy = None

    # -- frames -------------------------------------------------------------------------------
    def handle_frame(self, msg: can.Message, now: float) -> None:
        """STATUS frames of our controllers; anything else (commands, our own echoes) is ignored."""
        if not msg.is_extended_id or msg.is_remote_frame or msg.arbitration_id > 0xFFFF:
            return
        packet, controller = vc.split_ext_id(msg.arbitration_id)
        if controller == self.config.get("host_id") and packet in _BUFFER_PACKETS:
            done = self._assembler.feed(packet, bytes(msg.data))
            if done is not None:
                self._on_comm(done[0], done[2], now)
            return
        motor = self._by_id.get(controller)
        if motor is None or packet not in vc.STATUS_NUMBER:
            return
        status = vc.decode_status(packet, bytes(msg.data))
        if isinstance(status, vc.Status1) and not self._plausible(status):
            return
        number = vc.STATUS_NUMBER[PacketId(packet)]
        motor.status[number] = status
        motor.last_status = now
        if motor.silent:
            motor.silent = False
            self.logger.info("%s answering again", self._label(motor))
        cfg = self.config
        erev_per_turn = cfg.get("pole_pairs") * cfg.get("gear_ratio")
        metres_per_erev = 2.0 * math.pi * motor.spec.radius_m * motor.spec.direction / erev_per_turn
        if isinstance(status, vc.Status1):
            self._check_stall(motor, status.erpm, now)
            self.wheel_sample(motor.spec.name, self.frame_time(msg), speed_mps=status.erpm / 60.0 * metres_per_erev)
        elif isinstance(status, vc.Status5):
            if motor.tacho_raw is not None:
                motor.tacho_total += _unwrap_i32(status.tachometer - motor.tacho_raw)
            motor.tacho_raw = status.tachometer
            self.wheel_sample(motor.spec.name, self.frame_time(msg),
                              position_m=motor.tacho_total / TACHO_COUNTS_PER_EREV * metres_per_erev)

    def _plausible(self, status: vc.Status1) -> bool:
        """A STATUS whose ERPM the motor can turn at and whose duty cycle is one (else dropped, counted)."""
        top = self.config.get("max_motor_erpm")
        drops = self.out_of_range
        return drops.check("erpm", status.erpm, -top, top, unit=" ERPM") is not None \
            and drops.check("duty", status.duty, *vc.DUTY_RANGE) is not None

    def _check_stall(self, motor: VescMotor, erpm: float, now: float) -> None:
        cfg = self.config
        limit = cfg.get("stall_after_s")
        commanded = abs(motor.percent) >= max(cfg.get("stall_percent"), 1e-9)
        if not limit or not commanded or abs(erpm) >= cfg.get("stall_erpm"):
            if motor.stalled:
                self.logger.info("%s follows its command again", self._label(motor))
            motor.stall_since, motor.stalled = None, False
            return
        if motor.stall_since is None:
            motor.stall_since = now
        elif not motor.stalled and now - motor.stall_since > limit:
            motor.stalled = True
            motor.stall_events += 1
            self.error(f"{self._label(motor)}: commanded {motor.percent:.0f} % but turning at {erpm:.0f} ERPM for "
                       f"{now - motor.stall_since:.1f} s (a VESC fault, a stall or a blocked wheel; VESC Tool shows "
                       "the fault code)")

    def _label(self, motor: VescMotor) -> str:
        return f"VESC {motor.spec.name} (id {motor.spec.can_id} on {self.device_name})"

    # -- periodic work ------------------------------------------------------------------------
    def tick(self, now: float) -> None:
        """Notice silent controllers; re-send every setpoint once its period is due."""
        for motor in self.vescs.values():
            last = motor.last_status if motor.last_status is not None else self.started_at
            if now - last > self.config.get("silent_after_s") and not motor.silent and self.judging_silence:
                motor.silent = True
                motor.silent_events += 1
                motor.stall_since = None
                heard = "never heard" if motor.last_status is None else f"no STATUS for {now - last:.1f} s"
                self.error(f"{self._label(motor)}: node silent ({heard}); check power, wiring, its CAN id and that "
                           "VESC Tool's CAN status messages (1, 4, 5) are enabled")
                if self.odometry is not None:
                    self.odometry.reset()
            if now >= motor.next_command:
                self._send_setpoint(motor, now)
        self._watchdog_tick(now)

    # -- the VESC's command timeout (timeout_msec) ---------------------------------------------------
    def _watchdog_tick(self, now: float) -> None:
        """One configuration request on the bus at a time: time it out, or start the next one."""
        busy = self._wd_busy
        if busy is not None:
            if now < self._wd_deadline:
                return
            self._wd_busy = None
            if busy.wd.tries >= WD_TRIES:
                busy.wd.settle("error", f"no answer to COMM_GET_APPCONF after {busy.wd.tries} tries; check that "
                                        "App Settings > General > CAN Mode is VESC and host_id is free, or set "
                                        "the timeout in VESC Tool (App Settings > General > Timeout)")
                self.error(f"{self._label(busy)}: watchdog {busy.wd.text}")
        if self._wd_busy is not None:
            return
        for motor in self.vescs.values():
            if motor.wd.settled or motor.silent or motor.last_status is None:
                continue
            if not self.config.get("hw_watchdog"):
                motor.wd.settle("off", "off (hw_watchdog = false): timeout_msec left as it is in the VESC")
                self.logger.warning("%s: hw_watchdog is off; timeout_msec is neither set nor checked",
                                    self._label(motor))
                continue
            motor.wd.tries += 1
            self._comm_request(motor, bytes([vc.CommPacket.GET_APPCONF]), now)
            return

    def _comm_request(self, motor: VescMotor, payload: bytes, now: float) -> None:
        self._wd_busy, self._wd_deadline = motor, now + WD_REPLY_S
        for frame in vc.buffer_frames(motor.spec.can_id, self.config.get("host_id"), payload):
            self.send(frame)

    def _on_comm(self, sender: int, payload: bytes, now: float) -> None:
        """A COMM packet a VESC sent to host_id: the app configuration, or the write's acknowledgement."""
        motor = self._by_id.get(sender)
        if motor is None or motor is not self._wd_busy or not payload:
            return
        self._wd_busy = None
        wd, label = motor.wd, self._label(motor)
        wanted = round(float(self.config.get("hw_watchdog_timeout_s")) * 1000)
        if payload[0] == vc.CommPacket.SET_APPCONF:
            self._comm_request(motor, bytes([vc.CommPacket.GET_APPCONF]), now)  # read it back
            return
        if payload[0] != vc.CommPacket.GET_APPCONF:
            return
        appconf = payload[1:]
        try:
            have = vc.appconf_timeout_ms(appconf, controller_id=motor.spec.can_id)
        except vc.VescCanError as exc:
            wd.settle("error", f"cannot read timeout_msec: {exc}; set it in VESC Tool (App Settings > General > "
                               f"Timeout = {wanted} ms) and turn hw_watchdog off")
            self.error(f"{label}: watchdog {wd.text}")
            return
        if have == wanted:
            wd.settle("on", f"on {have / 1000:.2f} s (read back)")
            self.logger.info("%s: watchdog %s", label, wd.text)
        elif not motor.wrote:
            motor.wrote = True
            self.logger.warning("%s: timeout_msec is %d ms, writing %d ms into its app configuration (stored in "
                                "its flash)", label, have, wanted)
            self._comm_request(motor, bytes([vc.CommPacket.SET_APPCONF]) +
                               vc.appconf_with_timeout(appconf, wanted, controller_id=motor.spec.can_id), now)
        else:
            wd.settle("error", f"read back timeout_msec {have} ms after writing {wanted} ms; set it in VESC Tool "
                               f"(App Settings > General > Timeout = {wanted} ms, then write the app configuration)")
            self.error(f"{label}: watchdog {wd.text}")

    def _send_setpoint(self, motor: VescMotor, now: float) -> None:
        cfg = self.config
        motor.next_command = now + cfg.get("command_period_s")
        if motor.percent == 0.0 and cfg.get("neutral") == "release":
            payload, packet = vc.encode_set_current(0.0), PacketId.SET_CURRENT
        else:
            packet = MODES[cfg.get("mode")]
            scale = cfg.get("max_duty") if packet == PacketId.SET_DUTY else cfg.get("max_erpm")
            payload = vc.encode_command(packet, motor.percent / 100.0 * scale * motor.spec.direction)
        self.send(vc.make_frame(motor.spec.can_id, packet, payload))

    # -- actuator ----------------------------------------------------------------------------------
    def set_output(self, name: str, percent: float) -> None:
        """Remember *percent* for actuator *name* and send it now."""
        motor = self.vescs[name]
        if (motor.percent == 0.0) != (percent == 0.0):
            motor.stall_since = None
        motor.percent = percent
        self._send_setpoint(motor, self.now())

    def zero_outputs(self) -> None:
        """Every controller to neutral, sent now."""
        for motor in self.vescs.values():
            motor.percent = 0.0
            motor.stall_since = None
            self._send_setpoint(motor, self.now())

    def release(self) -> None:
        """SET_CURRENT 0 to every controller: the motors coast whatever ``neutral`` says."""
        for motor in self.vescs.values():
            self.send(vc.make_frame(motor.spec.can_id, PacketId.SET_CURRENT, vc.encode_set_current(0.0)))

    def on_port_lost(self) -> None:
        """The bus is gone: tachometer continuity and odometry start again."""
        for motor in self.vescs.values():
            motor.tacho_raw = None
        self._wd_busy = None
        if self.odometry is not None:
            self.odometry.reset()

    # -- health ----------------------------------------------------------------------------------
    def problems(self, now: float) -> list[str]:
        """Silent controllers and motors that do not follow their command."""
        out = []
        for motor in self.vescs.values():
            name = f"{motor.spec.name} (id {motor.spec.can_id})"
            if motor.silent:
                out.append(f"{name} node silent")
            elif motor.stalled:
                out.append(f"{name} not turning")
            if motor.wd.state == "error":
                out.append(f"{name} watchdog {motor.wd.text.split(';')[0]}")
        return out

    def motor_details(self) -> dict[str, Any]:
        """Per controller (keys ``<actuator>.<what>``): setpoint and the latest STATUS values."""
        now = self.now()
        details: dict[str, Any] = {"mode": self.config.get("mode"), **self.out_of_range.details("out_of_range"),
                                   "odometry_rejected": self.odometry.rejected if self.odometry else 0,
                                   "hw_watchdog": watchdog_summary(
            {n: m.wd.text for n, m in self.vescs.items()})}
        for name, motor in self.vescs.items():
            d: dict[str, Any] = {
                "id": motor.spec.can_id,
                "phase": "silent" if motor.silent else "waiting" if motor.last_status is None
                else "stalled" if motor.stalled else "ok",
                "setpoint_percent": f"{motor.percent:.1f}",
                "status_age_s": "" if motor.last_status is None else f"{now - motor.last_status:.2f}",
                "silent_events": motor.silent_events, "stall_events": motor.stall_events,
                "hw_watchdog": motor.wd.text,
            }
            s1, s4, s5 = motor.status.get(1), motor.status.get(4), motor.status.get(5)
            if s1 is not None:
                d.update(erpm=f"{s1.erpm:.0f}", current_a=f"{s1.current_a:.1f}", duty=f"{s1.duty:.3f}")
            if s4 is not None:
                d.update(temp_fet_c=f"{s4.temp_fet_c:.1f}", temp_motor_c=f"{s4.temp_motor_c:.1f}",
                         current_in_a=f"{s4.current_in_a:.1f}")
            if s5 is not None:
                d.update(tachometer=s5.tachometer, voltage_in_v=f"{s5.voltage_in_v:.1f}")
            details.update({f"{name}.{k}": v for k, v in d.items()})
        return details
