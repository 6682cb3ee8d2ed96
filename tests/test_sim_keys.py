"""The pilot's sticks: keys on a terminal move the RC receiver mock's pulses; the pilot waits for the IMU.

``u2sa mock`` runs on a real pty (its stdin and stdout a terminal, as a user's are), and the
keys reach the receiver's pulse trains on a mock GPIO chip socket.
"""

from __future__ import annotations

import os
import pty
import select
import subprocess
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from conftest import U2SA
from u2sa_hw.mocks.launcher import MockLauncher
from u2sa_hw.simulation.keys import StickKeys
from u2sa_hw.simulation.progress import BusSnapshot
from u2sa_hw.simulation.readiness import SimFailure, not_ready
from u2sa_hw.bus.udp_ports import private_udp_port
from u2sa_hw.profile.loader import load_profile

RC = """
[vehicle]
origin = { lat = 29.1895, lon = -81.0483 }

[services.rc]
kind = "rc_mux"
settings = { channels = "throttle=5,steering=6,mode=13", enable_line = 21 }

[devices.rc]
address = "gpio://gpiochip0/5,6,13,21"
mock = "rc_receiver"
"""


def test_keys_move_the_sticks_and_flip_the_switch(tmp_path: Path) -> None:
    (tmp_path / "vehicle.toml").write_text(RC)
    mocks = MockLauncher(load_profile(tmp_path / "vehicle.toml"), device_dir=tmp_path / "dev")
    rc = mocks.context.rc_receivers["rc"]
    keys = StickKeys(lambda: mocks, say=lambda _text: None)
    for key in "wwwd":
        keys.press(key)
    assert rc.pulse_us("throttle") == 1650.0 and rc.pulse_us("steering") == 1550.0
    assert keys.press("m") == "pilot: mode switch AUTONOMOUS" and rc.pulse_us("mode") == 2000.0
    assert keys.press(" ").startswith("sticks: throttle +0.0, steering +0.0") and rc.pulse_us("throttle") == 1500.0
    assert keys.press("l") == "RC link LOST" and rc.signal_lost
    assert keys.press("?") is None


def _read_until(fd: int, text: str, *, timeout: float = 30.0) -> str:
    seen, deadline = "", time.monotonic() + timeout
    while text not in seen:
        left = deadline - time.monotonic()
        if left <= 0:
            pytest.fail(f"u2sa mock did not print {text!r}; it printed:\n{seen}")
        ready, _, _ = select.select([fd], [], [], left)
        if ready:
            try:
                seen += os.read(fd, 4096).decode(errors="replace")
            except OSError:   # the child closed the terminal
                break
    return seen


def test_u2sa_mock_reads_single_keys_from_a_terminal(tmp_path: Path) -> None:
    (tmp_path / "vehicle.toml").write_text(RC)
    controller, terminal = pty.openpty()
    proc = subprocess.Popen([*U2SA, "mock", "--vehicle", str(tmp_path / "vehicle.toml"), "--run-dir",
                             str(tmp_path / "sim"), "--can-port", str(private_udp_port())],
                            stdin=terminal, stdout=terminal, stderr=terminal, close_fds=True)
    os.close(terminal)
    try:
        assert "w/s throttle, a/d steering" in _read_until(controller, "Ctrl-C stops the mocks")
        os.write(controller, b"w")   # no Enter: the terminal is in cbreak mode
        _read_until(controller, "sticks: throttle +0.1, steering +0.0")
        os.write(controller, b"m")
        _read_until(controller, "pilot: mode switch AUTONOMOUS")
        os.write(controller, b"q")
        assert proc.wait(timeout=15) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        os.close(controller)


def test_the_pilot_waits_for_the_imu_and_says_when_it_never_calibrates() -> None:
    health = {"imu": ("degraded", "gyro bias: waiting for rest (moving)", 0.0), "gps": ("ok", "", 0.0)}
    snap = BusSnapshot(estimate=(0.0, 0.0, 0.0, 0.1, 0.0), status=SimpleNamespace(finished=False, num_goals=2),
                       rc=SimpleNamespace(mode=0, mode_name="MANUAL"), health=health)
    said: list[str] = []
    shown: dict[str, str] = {}

    def check(waited_s: float) -> list[str]:
        return not_ready(snap, names=["imu", "gps"], imus=["imu"], waited_s=waited_s, said=shown, say=said.append)

    missing = check(0.0)
    assert missing == ["IMU calibrating at rest: imu (gyro bias: waiting for rest (moving))"]
    assert said == ["  ! imu degraded: gyro bias: waiting for rest (moving)"]   # said once on the console
    check(1.0)
    assert len(said) == 1
    with pytest.raises(SimFailure, match=r"IMU imu did not calibrate at rest within 45 s \(health: gyro bias"):
        check(60.0)   # a minute later, still not calibrated
    health["imu"] = ("ok", "", 0.0)
    assert check(60.0) == []
