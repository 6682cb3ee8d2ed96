"""`u2sa check --probe` against the mocks: real ptys, real Unix sockets, python-can udp_multicast.

The mocks of an example profile run in a real `u2sa mock` process and the probes open
them as they open hardware. A pty ignores the baud rate, so a wrong baud cannot be shown
on one: a mock sending garbage and a mock sending bad checksums stand in, and the report
must say so and must not claim that another baud works.
"""

from __future__ import annotations

import json
import signal
import subprocess
import threading
from dataclasses import replace
from pathlib import Path
from typing import Iterator

import pytest

from conftest import REPO, U2SA
from u2sa_hw.mocks.bno055_chip import Bno055Chip
from u2sa_hw.mocks.gpio_chip import MockGpioChip
from u2sa_hw.mocks.i2c_bus import MockI2cBus
from u2sa_hw.mocks.pty_serial import PtySerialDevice
from u2sa_hw.check.probe import ProbeResult, probe_profile, probe_target
from u2sa_hw.check.targets import Target
from u2sa_hw.ports.can.probe import socketcan_state
from u2sa_hw.ports.gpio.port import open_gpio
from u2sa_hw.ports.pwm.port import make_sysfs_pwm_tree
from u2sa_hw.ports.serial.probe import judge, xor_checksum
from u2sa_hw.bus.udp_ports import private_udp_port
from u2sa_hw.profile.loader import load_profile

WINDOW_S = 1.5


def sentence(body: str, *, good: bool = True) -> bytes:
    """``$body*hh`` CR LF with its XOR checksum (off by one when not *good*)."""
    check = xor_checksum(body.encode()) ^ (0 if good else 1)
    return f"${body}*{check:02X}\r\n".encode()


@pytest.fixture
def mock_process(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[Path]:
    """`u2sa mock` for the example named by the test's parameter; yields the simulation profile it writes."""
    example = REPO / "examples" / request.param / "vehicle.toml"
    proc = subprocess.Popen([*U2SA, "mock", "--vehicle", str(example), "--run-dir", str(tmp_path / "run"),
                             "--can-port", str(private_udp_port(span=2))],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO,
                            stdin=subprocess.DEVNULL)
    found: list[str] = []
    ready = threading.Event()

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            found.append(line)
            if line.startswith("simulation profile: "):
                ready.set()
        ready.set()

    threading.Thread(target=read, daemon=True).start()
    try:
        assert ready.wait(60) and proc.poll() is None, "".join(found)
        yield Path(next(line for line in found if line.startswith("simulation profile: ")).split(": ", 1)[1].strip())
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)


EXPECTED = {   # example -> device -> words its probe line must hold
    "ground_vehicle": {"gps": ["NMEA", "100% good checksums"], "compass": ["NMEA", "100% good checksums"],
                       "imu": ["MPU-9250", "WHO_AM_I 0x71 as expected"], "wheels": ["simulated", "node(s) 0, 1"],
                       "pan": ["PCA9685 answers", "MODE1"], "rc": ["exist and are free"]},
    "boat": {"gps": ["NMEA", "100% good checksums"], "compass": ["OS5000", "100% good checksums"],
             "imu": ["BNO055", "CHIP_ID 0xa0 as expected"], "thrusters": ["simulated", "VESC status frames"],
             "rc": ["exist and are free"]},
}


@pytest.mark.parametrize("mock_process", sorted(EXPECTED), indirect=True)
def test_probe_of_an_example_against_its_mocks(mock_process: Path, request: pytest.FixtureRequest) -> None:
    example = request.node.callspec.params["mock_process"]
    results = {r.device: r for r in probe_profile(load_profile(mock_process), seconds=WINDOW_S)}
    assert set(results) == set(EXPECTED[example]), results
    for device, words in EXPECTED[example].items():
        line = str(results[device])
        assert results[device].ok and line.startswith("probe ok"), line
        assert all(word in line for word in words), f"{line} lacks one of {words}"
    can = next(r for r in results.values() if r.port == "can")
    assert can.details["nodes"], can
    # the command line: the offline check of the simulation profile is clean, then one probe per device
    done = subprocess.run([*U2SA, "check", "--vehicle", str(mock_process), "--probe", "--json", "--seconds",
                           str(WINDOW_S)], capture_output=True, text=True, timeout=120, cwd=REPO)
    report = json.loads(done.stdout)
    assert done.returncode == 0 and report["ok"] and report["problems"] == [], done.stdout + done.stderr
    assert {p["device"] for p in report["probes"]} == set(EXPECTED[example])
    # a node the profile would name but no controller answers as: not heard, the probe fails
    target = next(t for t in _targets(mock_process) if t.port == "can")
    missing = probe_target(replace(target, params={**target.params, "nodes": [*target.params["nodes"], 9]}),
                           seconds=WINDOW_S)
    assert not missing.ok and "node(s) 9 not heard" in missing.text


def _targets(profile: Path) -> list[Target]:
    from u2sa_hw.check.targets import profile_targets

    return profile_targets(load_profile(profile))


def test_check_probe_cli_prints_one_line_per_device(tmp_path: Path) -> None:
    gps = PtySerialDevice(link_path=tmp_path / "gps", name="gps")
    gps.start()
    stop = threading.Event()
    writer = threading.Thread(target=_repeat, args=(gps, sentence("GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,"
                                                                  "545.4,M,46.9,M,,"), stop), daemon=True)
    writer.start()
    profile = tmp_path / "vehicle.toml"
    profile.write_text(f'[vehicle]\nname = "bench"\n\n[services.gps]\nkind = "gps_nmea"\ndevice = "gps"\n\n'
                       f'[devices.gps]\naddress = "serial://{tmp_path}/gps?baud=9600"\nservice = "gps"\n')
    try:
        done = subprocess.run([*U2SA, "check", "--vehicle", str(profile), "--probe", "--seconds", str(WINDOW_S)],
                              capture_output=True, text=True, timeout=120, cwd=REPO)
    finally:
        stop.set()
        writer.join(5)
        gps.stop()
    assert done.returncode == 0, done.stdout + done.stderr
    probe_lines = [line for line in done.stdout.splitlines() if line.startswith("probe ")]
    assert len(probe_lines) == 1 and "probe ok   gps: serial" in probe_lines[0] and "NMEA" in probe_lines[0]
    assert "1 device(s) probed, 0 failed" in done.stdout


def _repeat(device: PtySerialDevice, data: bytes, stop: threading.Event, period_s: float = 0.05) -> None:
    while not stop.wait(period_s):
        device.write(data)


def _serial_target(path: Path, *, protocol: str = "NMEA") -> Target:
    return Target("gps", "gps", "serial", f"{path}?baud=9600", {"path": str(path), "baud": 9600,
                                                                 "protocol": protocol})


def _probe_while(device: PtySerialDevice, send: callable, target: Target) -> ProbeResult:
    stop = threading.Event()

    def loop() -> None:
        while not stop.wait(0.05):
            send()

    thread = threading.Thread(target=loop, daemon=True)
    thread.start()
    try:
        return probe_target(target, seconds=WINDOW_S)
    finally:
        stop.set()
        thread.join(5)


def test_a_serial_mock_sending_garbage_is_reported_and_no_baud_is_claimed(tmp_path: Path) -> None:
    device = PtySerialDevice(link_path=tmp_path / "gps", name="gps", seed=7)
    device.start()
    try:
        result = _probe_while(device, lambda: device.inject_garbage(64), _serial_target(tmp_path / "gps"))
    finally:
        device.stop()
    assert not result.ok
    assert "9600 baud: garbage" in result.text or "9600 baud: binary" in result.text, result.text
    assert "no other common baud" in result.text and "set baud=" not in result.text


def test_bad_checksums_are_counted(tmp_path: Path) -> None:
    device = PtySerialDevice(link_path=tmp_path / "gps", name="gps")
    device.start()
    bad = sentence("GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W", good=False)
    try:
        result = _probe_while(device, lambda: device.write(bad), _serial_target(tmp_path / "gps"))
    finally:
        device.stop()
    assert not result.ok
    assert "9600 baud: NMEA" in result.text and " 0% good checksums" in result.text, result.text


def test_a_silent_port_says_so(tmp_path: Path) -> None:
    device = PtySerialDevice(link_path=tmp_path / "gps", name="gps")
    device.start()
    try:
        result = probe_target(_serial_target(tmp_path / "gps"), seconds=0.5)
    finally:
        device.stop()
    assert not result.ok and "silent" in result.text


def test_a_missing_serial_device_fails_with_the_fix(tmp_path: Path) -> None:
    result = probe_target(_serial_target(tmp_path / "nothing"), seconds=0.5)
    assert not result.ok and "nothing" in result.address and result.text


def test_judge_tells_the_protocols_apart() -> None:
    nmea = b"x\n" + sentence("GPGGA,1,2,3") * 5 + sentence("GPGSA,1", good=False) + b"cut"
    report = judge(nmea, seconds=1.0)
    assert (report.protocol, report.nmea_good, report.nmea_bad) == ("NMEA", 5, 1)
    assert report.works and report.good_share == pytest.approx(5 / 6)   # the cut first and last lines not counted
    assert not judge(b"\n" + sentence("GPGGA,1") * 3 + sentence("GPGSA,1", good=False) * 2 + b"\n",
                     seconds=1.0).works   # 60 % good: below the 80 % that works
    os5000 = b"\n" + sentence("C320.5P0.2R-18.3T19.0") * 4 + b"\n"
    assert judge(os5000, seconds=1.0).protocol == "OS5000" and judge(os5000, seconds=1.0).works
    binary = bytes(range(256)) * 8
    assert judge(binary, seconds=1.0).protocol == "binary"
    assert judge(b"", seconds=1.0).protocol == "silent"


def test_i2c_probe_names_a_wrong_chip_and_an_empty_address(tmp_path: Path) -> None:
    bus = MockI2cBus(socket_path=str(tmp_path / "i2c.sock"))
    bus.add(Bno055Chip(address=0x68))
    with bus:
        mpu = Target("imu", "imu", "i2c", "0x68", {"bus": bus.address, "address": 0x68, "chip": "mpu"})
        wrong = probe_target(mpu, seconds=0.1)
        assert not wrong.ok and "WHO_AM_I reads" in wrong.text and "0x71 (MPU-9250)" in wrong.text
        bno = probe_target(replace(mpu, params={**mpu.params, "chip": "bno055"}), seconds=0.1)
        assert bno.ok and "CHIP_ID 0xa0 as expected" in bno.text
        empty = probe_target(replace(mpu, params={**mpu.params, "address": 0x69}), seconds=0.1)
        assert not empty.ok and "0x69" in str(empty)


def test_gpio_probe_reports_missing_and_held_lines(tmp_path: Path) -> None:
    chip = MockGpioChip(socket_path=str(tmp_path / "chip.sock"), num_lines=32)
    chip.start()
    try:
        target = Target("rc", "rc", "gpio", "chip", {"chip": f"mock:{tmp_path / 'chip.sock'}", "lines": [5, 6]})
        assert probe_target(target, seconds=0.1).ok
        holder = open_gpio(device="other", chip=f"mock:{tmp_path / 'chip.sock'}", inputs=[5])
        try:
            held = probe_target(replace(target, params={**target.params, "lines": [5, 40]}), seconds=0.1)
        finally:
            holder.close()
        assert not held.ok and "40 do not exist" in held.text and "5 by" in held.text, held.text
    finally:
        chip.stop()


def test_pwm_probe_checks_the_channel_exists(tmp_path: Path) -> None:
    chip = make_sysfs_pwm_tree(tmp_path / "pwmchip0", npwm=2)
    target = Target("servo", "pan", "pwm", "pwmchip0/1", {"chip": str(chip), "channel": 1})
    assert probe_target(target, seconds=0.1).ok
    beyond = probe_target(replace(target, params={"chip": str(chip), "channel": 5}), seconds=0.1)
    assert not beyond.ok and "0..1" in beyond.text
    assert not probe_target(replace(target, params={"chip": str(tmp_path / "none"), "channel": 0}), seconds=0.1).ok


def test_a_device_whose_kind_has_no_probe_gets_a_line_saying_so() -> None:
    """A port kind without a probe (here a made-up spi) is not left out unsaid: one "probe skip" line, not a failure."""
    result = probe_target(Target("lidar", "lidar", "spi", "spi://0/0"), seconds=0.1)
    assert result.ok and not result.probed
    assert str(result) == ("probe skip lidar: spi spi://0/0: no probe for kind spi: not looked at (check it by hand; a "
                           "probe for the kind goes in u2sa_hw/ports/spi/probe.py, see docs/adding-a-device.md, 'A port kind')")
    assert result.to_dict()["probed"] is False


def test_check_probe_says_no_probe_for_a_kind_the_targets_do_not_know(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """targets.py chooses the probe by the address kind; a kind it has no entry for (a new port kind: pwm taken out
    here) is still a target, and u2sa check --probe prints its "no probe for kind" line beside the others."""
    from u2sa_hw.check import targets
    from u2sa_hw.cli import main

    pwm = make_sysfs_pwm_tree(tmp_path / "pwmchip0", npwm=4)
    gpio = MockGpioChip(socket_path=str(tmp_path / "gpiochip0.sock"), num_lines=8)
    profile = tmp_path / "vehicle.toml"
    profile.write_text(f'[vehicle]\nname = "bench"\n\n[services.pan]\nkind = "pwm_servo"\n'
                       'settings = { channels = [{ name = "pan", device = "pan" }] }\n\n'
                       '[services.lamp]\nkind = "gpio_output"\nsettings = { outputs = "lamp=5" }\n\n'
                       f'[devices.pan]\naddress = "mock+pwm://{pwm}/3"\n\n'
                       f'[devices.lamp]\naddress = "mock+gpio://{tmp_path}/gpiochip0.sock/5"\n')
    monkeypatch.setattr(targets, "TARGETS", {k: v for k, v in targets.TARGETS.items() if k != "pwm"})
    gpio.start()
    try:
        assert {r.device: r.probed for r in probe_profile(load_profile(profile), seconds=0.1)} == {"pan": False,
                                                                                                "lamp": True}
        assert main(["check", "--vehicle", str(profile), "--probe", "--seconds", "0.1"]) == 0
    finally:
        gpio.stop()
    out = capsys.readouterr().out
    assert out.splitlines()[-1].endswith("1 device(s) probed, 0 failed, 1 with no probe for their kind")
    lines = [line for line in out.splitlines() if line.startswith("probe ")]
    assert sorted(lines) == [
        f"probe ok   lamp: gpio mock+gpio://{tmp_path}/gpiochip0.sock/5: 8 lines; line(s) 5 exist and are free",
        f"probe skip pan: pwm mock+pwm://{pwm}/3: no probe for kind pwm: not looked at (check it by hand; a probe for "
        "the kind goes in u2sa_hw/ports/pwm/probe.py, see docs/adding-a-device.md, 'A port kind')"]


IP_SHOW = """\
3: lo: <NOARP,UP,LOWER_UP,ECHO> mtu 16 qdisc pfifo_fast state UP mode DEFAULT group default qlen 10
    link/can  promiscuity 0 minmtu 0 maxmtu 0
    can state ERROR-PASSIVE (berr-counter tx 128 rx 3) restart-ms 100
          bitrate 500000 sample-point 0.875
          re-started bus-errors arbit-lost error-warn error-pass bus-off
          2          41         0          2          1          1
"""


def test_socketcan_state_reads_state_bitrate_and_counters() -> None:
    def fake_ip(*_args: object, **_kwargs: object) -> subprocess.CompletedProcess[str]:
        return subprocess.CompletedProcess([], 0, IP_SHOW, "")

    healthy, text = socketcan_state("lo", run=fake_ip)   # lo stands in for the interface's sysfs directory
    assert not healthy, "an ERROR-PASSIVE controller is not healthy"
    assert "state ERROR-PASSIVE" in text and "500000 bit/s" in text and "tx/rx error counters 128/3" in text
    assert "bus errors 41, bus-off 1" in text
    missing, why = socketcan_state("can-none-here")
    assert not missing and "no interface can-none-here" in why


def test_probe_reads_device_addresses_of_every_kind(tmp_path: Path) -> None:
    """A profile of the new form: each [devices.NAME] address opened by its scheme (mock+i2c, mock+gpio, mock+pwm)."""
    from u2sa_hw.mocks.mpu9250_chip import Mpu9250Chip

    bus = MockI2cBus(socket_path=str(tmp_path / "i2c-1.sock"))
    bus.add(Mpu9250Chip(address=0x68))
    chip = MockGpioChip(socket_path=str(tmp_path / "gpiochip0.sock"), num_lines=32)
    pwm = make_sysfs_pwm_tree(tmp_path / "pwmchip0", npwm=4)
    profile = tmp_path / "vehicle.toml"
    profile.write_text(f"""\
[vehicle]
name = "bench"

[services.imu]
kind = "imu_mpu9250"

[services.lamp]
kind = "gpio_output"

[services.pan]
kind = "pwm_servo"

[devices.imu]
address = "mock+i2c://{tmp_path}/i2c-1.sock/0x68"
service = "imu"

[devices.lamp]
address = "mock+gpio://{tmp_path}/gpiochip0.sock/17,27"
service = "lamp"

[devices.pan]
address = "mock+pwm://{pwm}/3"
service = "pan"
""")
    chip.start()
    try:
        with bus:
            results = {r.device: r for r in probe_profile(load_profile(profile), seconds=0.2)}
    finally:
        chip.stop()
    assert set(results) == {"imu", "lamp", "pan"}, results
    assert results["imu"].ok and "WHO_AM_I 0x71 as expected" in results["imu"].text
    assert results["lamp"].ok and "line(s) 17, 27 exist and are free" in results["lamp"].text
    assert results["pan"].ok and "channel 3 of 4 exists" in results["pan"].text
    assert all(r.address.startswith("mock+") for r in results.values())


class UartAt:
    """A serial port opened at *rate* on a line whose device sends NMEA at *device_baud*: at the right rate
    the sentences, at any other the framing garbage a UART makes of them (no line ends, high bytes).

    ``read`` behaves like pyserial's with a timeout: one chunk per call, paced by the port's timeout.
    """

    def __init__(self, rate: int, *, device_baud: int, opened: list[int], closed: list[int]) -> None:
        self.rate, self.device_baud, self.closed = rate, device_baud, closed
        self._tick = threading.Event()   # never set: read() waits its timeout, as a quiet port does
        self._n = 0
        opened.append(rate)

    def read(self, size: int) -> bytes:
        self._tick.wait(0.01)
        self._n += 1
        if self.rate == self.device_baud:
            return sentence(f"GPGGA,1235{self._n % 60:02d},4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,")
        return bytes((0x80 + (self._n * 37 + i * 11) % 127) for i in range(48))

    def close(self) -> None:
        self.closed.append(self.rate)


def test_the_serial_probe_names_the_baud_that_works_when_the_configured_one_sees_garbage(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A pty ignores the baud, so a fake opener plays the UART: the receiver talks at 38400, the address says 9600."""
    import u2sa_hw.ports

    opened: list[int] = []
    closed: list[int] = []

    def open_serial(path: str, *, device: str, baudrate: int, timeout: float) -> UartAt:
        assert (path, device) == ("/dev/u2sa/gps", "gps")
        return UartAt(baudrate, device_baud=38400, opened=opened, closed=closed)

    monkeypatch.setattr(u2sa_hw.ports, "open_serial", open_serial, raising=False)
    target = Target("gps", "gps", "serial", "serial:///dev/u2sa/gps?baud=9600",
                    {"path": "/dev/u2sa/gps", "baud": 9600, "protocol": "NMEA"})
    result = probe_target(target, seconds=0.3)
    assert not result.ok   # it does not work as configured
    assert result.text.startswith("9600 baud: binary: ") and "no sentence; " in result.text, result.text
    assert "; at 38400 baud: NMEA" in result.text and "100% good checksums" in result.text, result.text
    assert result.text.endswith("set baud=38400 in the address"), result.text
    assert opened == [9600, 4800, 19200, 38400] and closed == opened   # each baud opened afresh, each closed
    assert str(result).startswith("probe FAIL gps: serial serial:///dev/u2sa/gps?baud=9600: 9600 baud: binary")


@pytest.mark.parametrize("chip, words", [
    ("/dev/gpiochip9", ["device 'rc': no GPIO chip /dev/gpiochip9 (No such file or directory)", "gpiodetect",
                        "[devices.rc] address, e.g. gpio://gpiochip0/5,6"]),
    ("mock:{tmp}/nochip.sock", ["device 'rc': no mock GPIO chip at {tmp}/nochip.sock", "u2sa mock"]),
])
def test_a_missing_gpio_chip_names_the_device_the_chip_and_the_fix(tmp_path: Path, chip: str,
                                                                    words: list[str]) -> None:
    target = Target("rc", "rc", "gpio", "gpio://gpiochip9/5,6", {"chip": chip.format(tmp=tmp_path), "lines": [5, 6]})
    result = probe_target(target, seconds=0.1)
    assert not result.ok
    for word in words:
        assert word.format(tmp=tmp_path) in result.text, result.text
    assert "fix: " in result.text
