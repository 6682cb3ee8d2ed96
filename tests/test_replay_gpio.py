"""u2sa replay of GPIO and PWM drivers: a log of the RC mux driver (a mock GPIO chip with an RC
receiver producing pulses and the mux, the real driver as a process with record_raw) and a log of
the PWM servo driver (a sysfs-shaped tree, commanded over the bus) are replayed into the real
drivers and compared; a changed setting is reported."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Iterator

import pytest
import tomli_w
from conftest import REPO, wait_until
from gpio_driver_harness import BusCollector

from u2sa_hw.hil.replay_plan import build_plan
from u2sa_hw.mocks.gpio_chip import MockGpioChip
from u2sa_hw.mocks.rc_receiver import MuxMock, RcReceiverMock
from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.ports.pwm.port import make_sysfs_pwm_tree
from u2sa_hw.recording.log_reader import LogFile
from u2sa_hw.recording.mcap_log import McapLogWriter
from u2sa_hw.services.recorder.capture import BusCapture
from u2sa_hw.services.recorder.service import run_info
from u2sa_hw.bus.transport import Transport
from u2sa_hw.bus.udp_ports import private_lcm_url
from u2sa_hw.profile.loader import load_profile

U2SA = [sys.executable, "-m", "u2sa_hw.cli"]
RC_LINES = {"throttle": 5, "steering": 6, "mode": 13}
ENABLE, SELECT = 21, 20
MODE_MANUAL, MODE_AUTONOMOUS = 0, 1


class Recording:
    """A private bus, a profile with one service, the recorder's capture and the driver as a process."""

    def __init__(self, workdir: Path, *, name: str, kind: str, settings: dict, devices: dict[str, str]) -> None:
        self.url = private_lcm_url()
        self.workdir = workdir
        self.profile = workdir / "vehicle.toml"
        self.profile.write_text(tomli_w.dumps({
            "vehicle": {"name": "testrover", "system_id": 7, "lcm_url": self.url},
            "services": {name: {"kind": kind, "settings": {"health_interval_s": 0.2, "record_raw": True,
                                                           **settings}}},
            "devices": {device: {"address": address} for device, address in devices.items()}}))
        self.name = name
        self.log = workdir / f"{name}.mcap"
        self.transport = Transport(self.url, name="test-recorder")
        self.capture = BusCapture(self.transport, McapLogWriter(workdir, path=self.log,
                                                                run=run_info(load_profile(self.profile), self.url)))
        self.bus = BusClient(self.url)
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        self.capture.start()
        self.transport.start()
        env = dict(os.environ, PYTHONPATH=str(REPO), U2SA_LCM_URL=self.url)
        self.proc = subprocess.Popen([*U2SA, "service", self.name, "--vehicle", str(self.profile)],
                                     cwd=self.workdir, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def stop(self) -> None:
        self.capture.stop()   # first: the driver's last words at its stop are not part of the run
        self.transport.stop()
        if self.proc is not None:
            self.proc.terminate()
            self.proc.wait(timeout=10)
        self.bus.close()


def record_rc_log(workdir: Path) -> Path:
    """The RC mux driver on recorded pulses: manual, a throttle change, the pilot's switch to autonomous."""
    sockets = Path(tempfile.mkdtemp(prefix="rprc", dir="/tmp"))   # Unix socket paths must stay short
    chip = MockGpioChip(socket_path=str(sockets / "gpio.sock"), release_level=None).start()
    rc = RcReceiverMock(chip, lines=RC_LINES, frame_hz=50).start()
    mux = MuxMock(chip, rc, enable_line=ENABLE, select_line=SELECT).start()
    rec = Recording(workdir, name="rc", kind="rc_mux", settings={
        "channels": "throttle=5,steering=6,mode=13", "mode_channel": "mode",
        "enable_line": ENABLE, "select_line": SELECT, "debounce_frames": 3, "signal_timeout_ms": 400.0,
        "publish_hz": 10.0}, devices={"rc": f"mock+gpio://{chip.socket_path}"})
    col = BusCollector(rec.bus).listen(ch.RC_MODE, t.RcMode)
    try:
        rec.start()
        col.wait_for(ch.RC_MODE, lambda m: m.mode == MODE_MANUAL and list(m.pulse_us) == [1500, 1500, 1000],
                     timeout=30, message="the pilot's manual mode")
        rc.set_pulse("throttle", 1623)
        first = col.count(ch.RC_MODE)
        col.wait_for(ch.RC_MODE, lambda m: m.pulse_us[0] == 1623, message="the new throttle width")
        wait_until(lambda: sum(m.pulse_us[0] == 1623 for m in col.since(ch.RC_MODE, first)) >= 3,
                   message="the new width held for a few messages")
        rc.set_mode_switch(True)
        col.wait_for(ch.RC_MODE, lambda m: m.mode == MODE_AUTONOMOUS and m.autonomy_enabled,
                     message="autonomous and enabled")
        wait_until(lambda: mux.selected == "autonomous", message="the mux to select autonomous")
        after = col.count(ch.RC_MODE)
        wait_until(lambda: col.count(ch.RC_MODE) >= after + 5, message="a few more RcMode messages")
    finally:
        rec.stop()
        mux.stop()
        rc.stop()
        chip.stop()
        shutil.rmtree(sockets, ignore_errors=True)
    return rec.log


def command(bus: BusClient, actuator: str, percent: float) -> None:
    msg = t.PercentageCommand()
    msg.base.actuator_name, msg.percentage = actuator, percent
    bus.publish(ch.ACTUATOR_CMD, msg)


def duty(chip: Path, channel: int) -> int:
    try:
        return int((chip / f"pwm{channel}" / "duty_cycle").read_text())
    except (OSError, ValueError):
        return -1


def record_pwm_log(workdir: Path) -> Path:
    """The PWM servo driver on a sysfs-shaped tree under a sequence of Percentage Commands."""
    chip = make_sysfs_pwm_tree(workdir / "pwmchip0", npwm=4)
    rec = Recording(workdir, name="servos", kind="pwm_servo", settings={
        "command_timeout_s": 0.0, "rc_gating": False, "channels": [
            {"name": "rudder"}, {"name": "throttle", "min_us": 1100.0, "max_us": 1900.0}]},
        devices={"rudder": f"mock+pwm://{chip}/0", "throttle": f"mock+pwm://{chip}/1"})
    try:
        rec.start()
        wait_until(lambda: duty(chip, 1) == 1_500_000, timeout=30, message="the servos at neutral")
        wait_until(lambda: rec.bus.discover(timeout=0.3, name="servos"), timeout=20, message="the driver subscribed")
        for percent, rudder_ns, throttle_ns in ((50, 1_750_000, 1_700_000), (-100, 1_000_000, 1_100_000),
                                                (20, 1_600_000, 1_580_000), (0, 1_500_000, 1_500_000)):
            command(rec.bus, "rudder", percent)
            command(rec.bus, "throttle", percent)
            wanted = (rudder_ns, throttle_ns)
            wait_until(lambda wanted=wanted: (duty(chip, 0), duty(chip, 1)) == wanted,
                       message=f"{percent} % on both channels")
        wait_until(lambda: rec.capture.stats.per_channel.get("RAW.throttle", 0) >= 6, message="the writes recorded")
    finally:
        rec.stop()
    return rec.log


@pytest.fixture(scope="module")
def rc_log(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    yield record_rc_log(tmp_path_factory.mktemp("recorded-rc"))


@pytest.fixture(scope="module")
def pwm_log(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    yield record_pwm_log(tmp_path_factory.mktemp("recorded-pwm"))


def replay_cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.pop("U2SA_LCM_URL", None)
    return subprocess.run([*U2SA, "replay", *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=180)


def rows(stdout: str) -> dict[str, str]:
    """The comparison table's rows by stream."""
    return {line.split("  ")[0].strip(): line for line in stdout.splitlines()
            if line.startswith(("RC_MODE", "RAW.")) and line.rstrip().endswith(("same", "DIFFERENT", "new"))}


def test_rc_log_plans_a_gpio_device_of_the_rc_service(rc_log: Path) -> None:
    plan = build_plan(rc_log)
    assert plan.devices["rc"].kind == "gpio" and plan.devices["rc"].service == "rc"
    assert {"RawGpioEdge", "RawGpioWrite"} <= plan.devices["rc"].types and not plan.notes


def test_recorded_edges_replay_into_the_rc_mux_driver_with_no_difference(rc_log: Path, tmp_path: Path) -> None:
    out = tmp_path / "rc-replay.mcap"
    res = replay_cli(str(rc_log), "--fast", "--compare", "-o", str(out), cwd=tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "(--fast)" in res.stdout   # edges carry their recorded stamps: no forced --rate 1
    table = rows(res.stdout)
    assert table["RC_MODE [rc]"].endswith("same") and table["RAW.rc [rc]"].endswith("same"), res.stdout
    assert "compare: OK" in res.stdout
    # the replayed driver measured the recorded pulses and followed the pilot's switch
    modes = [t.RcMode.decode(m.data) for m in LogFile(out).messages(ch.RC_MODE)]
    assert any(list(m.pulse_us) == [1623, 1500, 1000] and m.mode == MODE_MANUAL for m in modes)
    assert any(m.mode == MODE_AUTONOMOUS and m.autonomy_enabled and list(m.pulse_us) == [1623, 1500, 2000]
               for m in modes)
    writes = [t.RawGpioWrite.decode(m.data) for m in LogFile(out).messages(r"RAW\.rc")
              if m.type_name == "RawGpioWrite"]
    # the last one (enable low) came when the input ended: the replay goes on past the recording
    assert [(w.line, w.value) for w in writes][:2] == [(ENABLE, 0), (ENABLE, 1)]


def test_a_changed_rc_setting_is_reported(rc_log: Path, tmp_path: Path) -> None:
    # the pilot's 2000 us switch position no longer counts as autonomous
    res = replay_cli(str(rc_log), "--compare", "--set", "rc.autonomous_above_us=2100",
                     "-o", str(tmp_path / "rc2.mcap"), cwd=tmp_path)
    assert res.returncode == 1, res.stdout + res.stderr
    table = rows(res.stdout)
    assert table["RC_MODE [rc]"].endswith("DIFFERENT")
    assert "mode: differs" in res.stdout
    # the enable decision also reads the system's health (pre-arm checks): reported, not gated on
    assert "decided from the whole system's health" in res.stdout and "autonomy_enabled in" in res.stdout
    # the enable line never went high: the recording's last write has no counterpart (within --edge 1 a note)
    assert "RAW.rc [rc]: note: 1 message(s) without a counterpart among the first or last 1" in res.stdout
    res = replay_cli(str(rc_log), "--compare", "--edge", "0", "--set", "rc.autonomous_above_us=2100",
                     "-o", str(tmp_path / "rc3.mcap"), cwd=tmp_path)
    assert res.returncode == 1 and rows(res.stdout)["RAW.rc [rc]"].endswith("DIFFERENT"), res.stdout


def test_recorded_commands_replay_into_the_pwm_servo_driver_with_no_difference(pwm_log: Path,
                                                                               tmp_path: Path) -> None:
    plan = build_plan(pwm_log)
    assert {d.name: (d.kind, d.service) for d in plan.devices.values()} == {
        "rudder": ("pwm", "servos"), "throttle": ("pwm", "servos")}
    out = tmp_path / "pwm-replay.mcap"
    res = replay_cli(str(pwm_log), "--fast", "--compare", "-o", str(out), cwd=tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    table = rows(res.stdout)
    assert table["RAW.rudder [servos]"].endswith("same") and table["RAW.throttle [servos]"].endswith("same")
    duties = [t.RawPwmWrite.decode(m.data).duty_ns for m in LogFile(out).messages(r"RAW\.throttle")]
    assert duties[-4:] == [1_700_000, 1_100_000, 1_580_000, 1_500_000]


def test_a_changed_pwm_setting_is_reported(pwm_log: Path, tmp_path: Path) -> None:
    reversed_rudder = '[{name = "rudder", reverse = true}, {name = "throttle", min_us = 1100.0, max_us = 1900.0}]'
    res = replay_cli(str(pwm_log), "--fast", "--compare", "--set", f"servos.channels={reversed_rudder}",
                     "-o", str(tmp_path / "pwm2.mcap"), cwd=tmp_path)
    assert res.returncode == 1, res.stdout + res.stderr
    table = rows(res.stdout)
    assert table["RAW.rudder [servos]"].endswith("DIFFERENT") and table["RAW.throttle [servos]"].endswith("same")
    assert "duty_ns: differs" in res.stdout
