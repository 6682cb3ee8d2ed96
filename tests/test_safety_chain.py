"""The safety chain: the software mux at each actuator, the [safety] table, the operator's failsafe.

The pure parts (the command gate, the table) run with an injected clock; the chain itself
runs as real processes: a mock RC receiver on a mock GPIO chip, the ``rc_mux`` service with
a manual mixer, and a ``pwm_servo`` actuator on a sysfs-shaped PWM tree (a PWM board not
wired through the hardware mux, so the software is its mux), over real LCM multicast.
"""

from __future__ import annotations

import shutil
import signal
import tempfile
from pathlib import Path
from typing import Any, Iterator

import pytest
import tomli_w
from can_mock_harness import Commander
from conftest import ServiceProcesses, wait_until
from gpio_driver_harness import BusCollector
from serial_driver_harness import start_driver

from u2sa_hw.mocks.gpio_chip import MockGpioChip
from u2sa_hw.mocks.rc_receiver import RcReceiverMock
from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.failsafe import FailsafeSources
from u2sa_hw.ports.pwm.port import make_sysfs_pwm_tree
from u2sa_hw.safety.config import parse_safety
from u2sa_hw.safety.gate import AUTONOMOUS, MANUAL, CommandGate
from u2sa_hw.safety.wiring import check_wiring
from u2sa_hw.profile.vehicle import ProfileError
from u2sa_hw.profile.loader import load_profile

RC_LINES = {"throttle": 5, "steering": 6, "mode": 13}
ENABLE = 21


def rc_mode(mode: int, *, enabled: bool = False, armed: bool = True, hold: bool = False) -> t.RcMode:
    msg = t.RcMode()
    msg.mode, msg.autonomy_enabled, msg.armed, msg.hold = mode, enabled, armed, hold
    msg.mode_name = {0: "manual", 1: "autonomous", 2: "no signal"}[mode]
    return msg


# ------------------------------------------------------------------ the gate, pure -----------
def test_the_gate_gives_authority_only_as_the_rc_mode_and_failsafes_allow() -> None:
    gate = CommandGate(rc_mode_timeout_s=0.25)
    assert gate.authority(0.0).source is None and "no RC_MODE" in gate.authority(0.0).why
    gate.on_rc_mode(rc_mode(0), 1.0)
    assert gate.authority(1.1).source == MANUAL
    assert gate.admit(MANUAL, 1.1) and not gate.admit(AUTONOMOUS, 1.1)
    assert gate.dropped == {"autonomous_in_manual": 1}
    assert gate.authority(1.3).source is None and "stale" in gate.authority(1.3).why, "RC_MODE 300 ms old"
    for msg, why in [(rc_mode(1, enabled=False), "not enabled"), (rc_mode(1, enabled=True, armed=False), "armed"),
                     (rc_mode(1, enabled=True, hold=True), "hold"), (rc_mode(2), "no signal")]:
        gate.on_rc_mode(msg, 2.0)
        auth = gate.authority(2.0)
        assert auth.source is None and why in auth.why
    gate.on_rc_mode(rc_mode(1, enabled=True), 3.0)
    assert gate.authority(3.0).source == AUTONOMOUS and not gate.admit(MANUAL, 3.0)
    gate.failsafes.apply(source="hsm", active=True, reason="gps failed")
    assert gate.authority(3.0).source is None and "hsm: gps failed" in gate.authority(3.0).why
    assert not gate.admit(AUTONOMOUS, 3.0) and gate.dropped["failsafe"] == 1


def test_the_gate_reports_each_change_of_authority_once() -> None:
    gate = CommandGate(rc_mode_timeout_s=0.25)
    assert gate.changed(0.0) is not None, "the first evaluation is a change: outputs start neutral"
    assert gate.changed(0.1) is None
    gate.on_rc_mode(rc_mode(0), 0.2)
    assert gate.changed(0.2).source == MANUAL
    gate.on_rc_mode(rc_mode(0), 0.3)
    assert gate.changed(0.3) is None
    assert gate.changed(0.6).source is None, "stale"
    assert gate.stale_rc_modes == 1, "each change to a stale RC_MODE is counted (a replay's held-up window)"
    assert gate.changed(0.7) is None and gate.stale_rc_modes == 1
    gate.on_rc_mode(rc_mode(2), 0.8)   # no signal: neutral too, but not stale
    assert gate.changed(0.8) is None and gate.stale_rc_modes == 1
    assert CommandGate(rc_mode_timeout_s=0.25, rc_gating=False).authority(0.0).source == AUTONOMOUS


def test_failsafes_are_held_per_source_and_the_operator_clears_any() -> None:
    fs = FailsafeSources()
    assert fs.apply(source="hsm", active=True, reason="gps failed").edge
    assert not fs.apply(source="estop", active=True, reason="pressed").edge
    assert fs.apply(source="u2sa-cli-1", active=False).cleared == () and fs.active, "a stranger's clear"
    assert fs.apply(source="estop", active=False).cleared == ("estop",)
    assert fs.active and set(fs.held()) == {"hsm"}
    assert fs.apply(source="operator", active=False, target="hsm").cleared == ("hsm",) and not fs.active
    fs.apply(source="hsm", active=True)
    fs.apply(source="operator", active=True, reason="swimmer")
    change = fs.apply(source="operator", active=False, target="*")
    assert set(change.cleared) == {"hsm", "operator"} and change.edge and not fs.active


# ------------------------------------------------------------------ the [safety] table ------
def write_vehicle(tmp_path: Path, *, safety: dict[str, Any], socket: str = "/tmp/none.sock",
                  pwm: Path | None = None, settings: dict[str, Any] | None = None) -> Path:
    """The cart: the RC mux on the mock GPIO chip at *socket*, two servos on the sysfs-shaped *pwm* chip."""
    pwm = pwm or tmp_path / "pwmchip0"
    profile = {
        "vehicle": {"name": "cart", "system_id": 3, "config_dir": "config", "log_dir": "logs", "data_dir": "data"},
        "services": {
            "rc": {"kind": "rc_mux", "settings": {"channels": "throttle=5,steering=6,mode=13",
                                                  "enable_line": ENABLE, "debounce_frames": 2,
                                                  "health_interval_s": 0.2}},
            "drive": {"kind": "pwm_servo", "settings": {"health_interval_s": 0.2, **(settings or {}), "channels": [
                {"name": "steer"}, {"name": "esc"}]}},
            "lamp": {"kind": "gpio_output", "enabled": False, "settings": {"outputs": "lamp=17"}},
        },
        "devices": {"rc": {"address": f"mock+gpio://{socket}"}, "lamp": {"address": f"mock+gpio://{socket}"},
                    "steer": {"address": f"mock+pwm://{pwm}/0"}, "esc": {"address": f"mock+pwm://{pwm}/1"}},
        "safety": safety,
    }
    path = tmp_path / "vehicle.toml"
    path.write_text(tomli_w.dumps(profile))
    return path


MIXER = {"kind": "ackermann", "steering": "steer", "throttle": "esc", "throttle_channel": "throttle",
         "steering_channel": "steering"}


@pytest.mark.parametrize("safety, words", [
    ({"manual_mixer": {**MIXER, "steering": "rudder"}}, ["manual_mixer", "rudder", "esc, steer"]),
    ({"manual_mixer": {k: v for k, v in MIXER.items() if k != "throttle_channel"}}, ["throttle_channel"]),
    ({"manual_mixer": {**MIXER, "steering_channel": "aux1"}}, ["steering_channel", "aux1", "throttle, steering, mode"]),
    ({"hardware_mux": {"steer": "steering"}, "manual_mixer": MIXER}, ["manual_mixer", "hardware mux"]),
    ({"hardware_mux": {"horn": "steering"}}, ["hardware_mux", "horn"]),
    ({"rc_mode_timeout_ms": "fast"}, ["rc_mode_timeout_ms", "number"]),
    ({"on_check_lost": "panic"}, ["on_check_lost", "neutral, hold"]),
    ({"manul_mixer": MIXER}, ["unknown key", "manul_mixer"]),
])
def test_a_bad_safety_table_is_one_line_naming_the_file_and_key(tmp_path: Path, safety: dict, words: list) -> None:
    path = write_vehicle(tmp_path, safety=safety)
    with pytest.raises(ProfileError) as err:
        check_wiring(load_profile(path))
    text = str(err.value)
    assert str(path) in text and "\n" not in text
    for word in words:
        assert word in text


def test_the_hardware_mux_switches_only_pwm_wires() -> None:
    with pytest.raises(ProfileError, match="hardware RC mux switches only PWM"):
        check_wiring(load_profile(Path(__file__).parents[1] / "examples/ground_vehicle/vehicle.toml"),
                     parse_safety({"hardware_mux": {"left_wheel": "throttle"}}, where="x"))


def test_the_example_profiles_declare_their_safety_chain() -> None:
    for name, wheels in [("ground_vehicle", ("left_wheel", "right_wheel")), ("boat", ("left_thruster", "right_thruster"))]:
        safety = check_wiring(load_profile(Path(__file__).parents[1] / "examples" / name / "vehicle.toml"))
        assert safety.manual_mixer is not None and set(safety.manual_mixer.actuators) == set(wheels)
        assert not safety.hardware_mux, "CAN motors cannot pass through a hardware mux"


# ------------------------------------------------------------------ the chain, real processes --
class Chain:
    """A mock RC receiver, the rc_mux service and a pwm_servo actuator on sysfs PWM."""

    def __init__(self, *, rc: RcReceiverMock, pwm: Path, procs: dict[str, Any], col: BusCollector,
                 bus: BusClient) -> None:
        self.rc, self.pwm, self.procs, self.col, self.bus = rc, pwm, procs, col, bus

    def duty_us(self, channel: int) -> float:
        try:
            return int((self.pwm / f"pwm{channel}" / "duty_cycle").read_text()) / 1000.0
        except (OSError, ValueError):
            return -1.0

    def wait_duty(self, channel: int, us: float, message: str) -> None:
        wait_until(lambda: abs(self.duty_us(channel) - us) < 1.0, timeout=15,
                   message=f"{message} (pwm{channel} {self.duty_us(channel)} us, want {us})")

    def mode(self, predicate: Any, message: str) -> t.RcMode:
        return self.col.wait_for(ch.RC_MODE, predicate, since=self.col.count(ch.RC_MODE), message=message)

    def drive_health(self, predicate: Any, message: str) -> dict[str, str]:
        return self.col.health_of("drive", predicate, since=self.col.count(ch.HEALTH), message=message)



@pytest.fixture
def chain(tmp_path: Path, services: ServiceProcesses, bus: BusClient) -> Iterator[Chain]:
    sockets = Path(tempfile.mkdtemp(prefix="u2sa-sc-", dir="/tmp"))
    chip = MockGpioChip(socket_path=str(sockets / "gpio.sock")).start()
    rc = RcReceiverMock(chip, lines=RC_LINES, frame_hz=50).start()
    pwm = make_sysfs_pwm_tree(tmp_path / "pwmchip0", npwm=2)
    profile = write_vehicle(tmp_path, safety={"manual_mixer": MIXER, "rc_mode_timeout_ms": 250}, socket=chip.socket_path,
                            pwm=pwm)
    col = BusCollector(bus).listen(ch.RC_MODE, t.RcMode).listen(ch.HEALTH, t.Health)
    col.listen(ch.MANUAL_CMD, t.ActuatorCommand)
    procs = {"drive": start_driver(services, profile, "drive"), "rc": start_driver(services, profile, "rc")}
    try:
        yield Chain(rc=rc, pwm=pwm, procs=procs, col=col, bus=bus)
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGCONT)
        services.stop_all()
        rc.stop()
        chip.stop()
        shutil.rmtree(sockets, ignore_errors=True)


def test_manual_wins_on_an_actuator_no_hardware_mux_can_cut(chain: Chain) -> None:
    # manual: the pilot's sticks drive the outputs through the Ackermann manual mixer
    chain.mode(lambda m: m.mode == 0 and m.armed, "manual, armed")
    chain.rc.set_pulse("steering", 2000)      # full right
    chain.rc.set_pulse("throttle", 1000)      # full reverse
    chain.wait_duty(0, 2000.0, "steering servo follows the stick")
    chain.wait_duty(1, 1000.0, "ESC follows the throttle stick")

    # a forged autonomous command in manual is dropped and counted; the pilot keeps the output
    control = Commander(chain.bus, period=0.05)
    try:
        control.hold(esc=100.0)
        details = chain.drive_health(lambda d: "autonomous_in_manual" in d["dropped"], "the forged commands counted")
        assert details["authority"] == "manual"
        assert chain.duty_us(1) != pytest.approx(2000.0, abs=1.0), "the forged 100 % never reached the ESC"
        chain.wait_duty(1, 1000.0, "the pilot keeps the ESC while the forged commands keep coming")

        # to autonomous: the pilot's setpoint ends at once, then autonomy drives
        control.hold(esc=40.0)
        chain.rc.set_mode_switch(True)
        chain.mode(lambda m: m.mode == 1 and m.autonomy_enabled and not m.blocked_by, "autonomy granted")
        chain.wait_duty(1, 1700.0, "the control system's command obeyed in autonomy")
        assert chain.duty_us(0) == pytest.approx(1500.0, abs=1.0), "the pilot's steering ended at the hand-over"

        # the RC service hangs: RC_MODE goes stale and the actuator goes neutral on its own
        chain.procs["rc"].send_signal(signal.SIGSTOP)
        chain.wait_duty(1, 1500.0, "neutral when RC_MODE is stale, though commands keep coming")
        details = chain.drive_health(lambda d: "stale" in d["neutral_because"], "the stale RC mode in health")
        assert details["authority"] == "none"
        chain.procs["rc"].send_signal(signal.SIGCONT)
        # the RC service saw no pulses while stopped: a signal loss, so autonomy waits for the pilot to re-arm
        back = chain.mode(lambda m: m.mode == 1 and not m.autonomy_enabled, "the RC service publishing, disarmed")
        assert "armed" in back.blocked_by and not back.armed
        stalls = chain.col.health_of("rc", lambda d: d["stalls"] != "0", message="the stall counted")["stalls"]
        assert stalls == "1"
        assert chain.duty_us(1) == pytest.approx(1500.0, abs=1.0)

        # back to manual: autonomy's setpoint ends at once, the sticks take over again
        chain.rc.set_mode_switch(False)
        chain.wait_duty(1, 1000.0, "the pilot's stick again in manual")
    finally:
        control.close()

    # the actuator's own dead-man: with the sticks' commands gone (no RC signal) it is neutral
    chain.rc.signal_loss(True)
    chain.wait_duty(1, 1500.0, "neutral on RC signal loss")
    chain.wait_duty(0, 1500.0, "steering neutral on RC signal loss")


def test_the_operator_raises_and_clears_a_failsafe_that_other_sources_cannot_clear(
        chain: Chain, services: ServiceProcesses) -> None:
    chain.mode(lambda m: m.mode == 0 and m.armed, "manual, armed")
    chain.rc.set_pulse("throttle", 2000)
    chain.wait_duty(1, 2000.0, "full throttle in manual")
    raised = services.cli("failsafe", "raise", "--reason", "swimmer near the vehicle")
    assert raised.returncode == 0, raised.stderr
    chain.wait_duty(1, 1500.0, "neutral on the operator's failsafe, even in manual")
    held = chain.mode(lambda m: m.mode == 0 and not m.armed, "disarmed while the failsafe is held, even at manual")
    assert "failsafe" in held.blocked_by
    refused = chain.bus.set_config("drive", "rc_gating", "false")
    assert refused is not None and not refused.ok and "not changed over the bus" in refused.error
    stranger = t.Failsafe()
    stranger.active, stranger.header.source = False, "u2sa-cli-someone"
    chain.bus.publish(ch.FAILSAFE, stranger)
    status = services.cli("failsafe", "status", "--timeout", "1.5")
    assert status.returncode == 1 and "operator" in status.stdout, status.stdout
    assert chain.duty_us(1) == pytest.approx(1500.0, abs=1.0), "a stranger's clear does not lower it"
    cleared = services.cli("failsafe", "clear")
    assert cleared.returncode == 0, cleared.stderr
    chain.wait_duty(1, 2000.0, "the pilot's throttle again once the operator cleared")
    chain.mode(lambda m: m.mode == 0 and m.armed, "armed again only once nobody holds a failsafe")


def test_a_refused_autonomy_never_starts_by_itself_when_the_check_passes(chain: Chain) -> None:
    chain.mode(lambda m: m.mode == 0 and m.armed, "manual, armed")
    chain.procs["drive"].send_signal(signal.SIGSTOP)          # a required service goes silent
    chain.mode(lambda m: "required service drive" in m.blocked_by, "the pre-arm check failing")
    chain.rc.set_mode_switch(True)
    refused = chain.mode(lambda m: m.mode == 1 and not m.armed, "autonomy refused, and disarmed")
    assert not refused.autonomy_enabled and "drive" in refused.blocked_by
    chain.procs["drive"].send_signal(signal.SIGCONT)          # the check passes again ...
    chain.mode(lambda m: m.mode == 1 and "drive" not in m.blocked_by, "the check holding again")
    later = chain.mode(lambda m: m.mode == 1, "another RC_MODE")
    assert not later.autonomy_enabled and not later.armed, "... but autonomy waits for the pilot"
    chain.rc.set_mode_switch(False)
    chain.mode(lambda m: m.mode == 0 and m.armed, "the pilot re-arms through manual")
    chain.rc.set_mode_switch(True)
    chain.mode(lambda m: m.mode == 1 and m.autonomy_enabled, "autonomy granted on the pilot's new attempt")


def test_run_and_install_refuse_a_mis_declared_safety_chain_before_anything_starts(
        tmp_path: Path, services: ServiceProcesses) -> None:
    path = write_vehicle(tmp_path, safety={"manual_mixer": {**MIXER, "throttle": "esc2"}})
    for args in (["run", "--vehicle", str(path)], ["install", "--vehicle", str(path), "--root", str(tmp_path / "root")]):
        done = services.cli(*args)
        assert done.returncode == 1 and done.stderr.count("\n") == 1, done.stderr
        assert "manual_mixer" in done.stderr and "throttle = 'esc2' is not an actuator" in done.stderr
    assert not (tmp_path / "root" / "etc").exists(), "install wrote nothing"
    bad_syntax = write_vehicle(tmp_path, safety={"hardware_mux": ["steer"]})
    with pytest.raises(ProfileError, match=r"\[safety\]: 'hardware_mux' must be a table"):
        load_profile(bad_syntax)   # the syntax is checked by every load, services included


def test_u2sa_health_names_why_autonomy_is_refused() -> None:
    from test_hsm_monitor import health

    from u2sa_hw.cli.health_cmd import autonomy_report

    report = autonomy_report({
        "gps": health("gps", 1, fix_type="2D"),
        "rc": health("rc", 2, mode="autonomous", autonomy_enabled="False", armed="True",
                     enable_blocked_by="pre-arm check failed: gps: no 3D fix (fix type 2D, 7 satellites)"),
    })
    assert report == [{"service": "rc", "granted": False, "mode": "autonomous", "armed": True, "hold": False,
                       "prearm_failed": "",
                       "blocked_by": "pre-arm check failed: gps: no 3D fix (fix type 2D, 7 satellites)"}]


def test_the_hsm_re_sends_the_operators_one_shot_failsafe_until_it_is_cleared(
        tmp_path: Path, lcm_url: str, services: ServiceProcesses, bus: BusClient) -> None:
    from supervision_helpers import hsm_profile

    vehicle = hsm_profile(tmp_path, lcm_url, "", startup_grace_s=10.0)
    col = BusCollector(bus).listen(ch.FAILSAFE, t.Failsafe).listen(ch.SYSTEM_HEALTH, t.SystemHealth)
    services.start("hsm", "--vehicle", str(vehicle))
    col.wait_for(ch.SYSTEM_HEALTH, lambda m: True, message="the HSM running", timeout=30)

    def operator_raises(since: int = 0) -> int:
        return sum(1 for m in col.since(ch.FAILSAFE, since) if m.header.source == "operator" and m.active)

    assert services.cli("failsafe", "raise", "--reason", "boat in the way").returncode == 0
    wait_until(lambda: operator_raises() >= 3, timeout=15, message="the operator's failsafe re-sent by the HSM")
    assert all(m.reason == "boat in the way" for m in col.since(ch.FAILSAFE) if m.header.source == "operator"
               and m.active)
    assert services.cli("failsafe", "clear").returncode == 0
    col.wait_for(ch.SYSTEM_HEALTH, lambda m: not m.failsafe, since=col.count(ch.SYSTEM_HEALTH),
                 message="no failsafe held after the clear", timeout=15)
    mark, health = col.count(ch.FAILSAFE), col.count(ch.SYSTEM_HEALTH)
    # eight more reports at 0.2 s: longer than the HSM's 1 s re-send period
    col.wait_for(ch.SYSTEM_HEALTH, lambda m: True, since=health + 8, message="eight more system health reports",
                 timeout=15)
    assert operator_raises(mark) == 0, "the HSM stopped re-sending once the operator cleared"
