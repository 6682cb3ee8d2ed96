"""An honest simulation: the simulated RC mux switches only the PWM outputs wired through it,
every actuator kind moves the vehicle, and a profile whose devices cannot move it is refused.

Real parts: the PCA9685 and sysfs PWM mocks written through the real PWM ports, the RC
receiver's pulse trains and the mux on a mock GPIO chip socket, the enable line driven by
a GPIO client of that socket.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from conftest import REPO, U2SA, wait_until
from u2sa_hw.mocks.launcher import MockLauncher
from u2sa_hw.mocks.sim_context import DeviceError
from u2sa_hw.ports.opener import open_port
from u2sa_hw.profile.loader import load_profile

ACKERMANN = """
[vehicle]
origin = { lat = 29.1895, lon = -81.0483 }

[services.rc]
kind = "rc_mux"
settings = { channels = "throttle=5,steering=6,mode=13", enable_line = 21 }

[services.drive]
kind = "pwm_servo"
settings = { channels = [
  { name = "steering" },
  { name = "throttle" },
  { name = "pan" } ] }

[services.contactor]
kind = "gpio_output"
settings = { outputs = "motor_power=4,lamp=5" }

[safety]
hardware_mux = { steering = "steering", throttle = "throttle" }

[simulation]
model = "ackermann"

[devices.rc]
address = "gpio://gpiochip0/5,6,13,21"
mock = "rc_receiver"

[devices.steering]
address = "pca9685://1/0x40/0"
mock = "pca9685"

[devices.throttle]
address = "pca9685://1/0x40/1"
mock = "pca9685"

[devices.pan]
address = "pwm://pwmchip0/0"
mock = "sysfs_pwm"

[devices.contactor]
address = "gpio://gpiochip1/4,5"
mock = "gpio_chip"
drives = { motor_power = "enable" }
"""


def profile(tmp_path: Path, text: str) -> MockLauncher:
    path = tmp_path / "vehicle.toml"
    path.write_text(text)
    return MockLauncher(load_profile(path), device_dir=tmp_path / "dev", check_inputs=True)


def test_the_mux_switches_only_the_pwm_outputs_wired_through_it(tmp_path: Path) -> None:
    mocks = profile(tmp_path, ACKERMANN)
    mocks.start()
    vehicle, outputs = mocks.vehicle, mocks.outputs
    addresses = mocks.addresses   # each device's mock address: what a driver would open
    steering = open_port(addresses["steering"], device="steering")
    throttle = open_port(addresses["throttle"], device="throttle")
    pan = open_port(addresses["pan"], device="pan")
    power = open_port(addresses["contactor"], device="contactor", outputs={4: 1})
    try:
        for channel, us in ((steering, 1900), (throttle, 1800), (pan, 1700)):
            channel.set_pulse_us(us)
            channel.enable(True)
        mocks.set_sticks(throttle=0.0, steering=-1.0)   # the pilot holds full left, no throttle
        # manual: the mux passes the pilot's pulses to steering and throttle; the pan is not behind it
        wait_until(lambda: outputs.current("steering").value == -100.0, message="the pilot's steering at the servo")
        assert outputs.current("throttle").neutral and outputs.current("pan").value == 40.0
        assert vehicle.snapshot().speed == 0.0
        enable = open_port(addresses["rc"], device="rc", outputs={21: 1})
        mocks.set_mode_switch(True)
        wait_until(lambda: abs(outputs.current("throttle").value - 60.0) < 1,
                   message="the SBC's throttle through the mux")
        assert abs(outputs.current("steering").value - 80.0) < 1   # PCA9685 counts: not exactly
        wait_until(lambda: vehicle.snapshot().speed > 0.5 and vehicle.snapshot().yaw_rate > 0,
                   message="the vehicle to drive and turn right under the PWM outputs")
        power.set(4, 0)   # the contactor opens: the motor stops whatever the ESC is told
        wait_until(lambda: vehicle.snapshot().speed < 0.05, message="the contactor to stop the vehicle")
        assert outputs.current("motor_power").neutral and not outputs.current("throttle").neutral
        power.set(4, 1)
        mocks.signal_loss(True)   # no pulses: the mux goes to the pilot's side, which carries none
        wait_until(lambda: outputs.current("throttle").value == 0.0 and outputs.current("steering").value == 0.0,
                   message="no pulse on the muxed outputs")
        assert outputs.current("pan").value == 40.0   # not behind the mux: the SBC still drives it
        enable.close()
    finally:
        for channel in (steering, throttle, pan):
            channel.close()
        power.close()
        mocks.stop()


def test_can_motors_are_never_gated_by_the_simulated_mux(tmp_path: Path) -> None:
    text = ACKERMANN[:ACKERMANN.index("[services.drive]")] + '[simulation]\nmodel = "differential"\n' \
        '[devices.rc]\naddress = "gpio://gpiochip0/5,6,13,21"\nmock = "rc_receiver"\n'
    path = tmp_path / "vehicle.toml"
    path.write_text(text)
    mocks = MockLauncher(load_profile(path), device_dir=tmp_path / "dev")
    mocks.start()
    try:
        assert mocks.context.muxes[0][1].selected == "rc"   # manual: the mux selects the pilot
        for side in ("left", "right"):   # what an ODrive or VESC node is given as its vehicle
            mocks.context.motor_input(f"{side}_wheel").set_wheel_speed(side, 1.0)
        wait_until(lambda: mocks.vehicle.snapshot().speed > 0.9, message="the CAN motors to move the vehicle in manual")
        assert mocks.outputs.current("left_wheel").value == 50.0   # % of the 2 m/s top speed
        mocks.actuated.hold(True)
        wait_until(lambda: mocks.vehicle.snapshot().speed == 0.0, message="the held vehicle to stop")
    finally:
        mocks.stop()


@pytest.mark.parametrize("change, error", [
    ((('  { name = "throttle" },\n', ""), ('[devices.throttle]\naddress = "pca9685://1/0x40/1"\nmock = "pca9685"\n', "")),
     r"vehicle.toml: \[simulation\] model = 'ackermann' moves by steering and throttle, but no device drives "
     r"throttle .*drives = \{ <channel> = \"throttle\" \}"),
    ((('hardware_mux = { steering = "steering", throttle = "throttle" }', 'hardware_mux = { motor_power = "throttle" }'),),
     r"\[safety\] hardware_mux: 'motor_power' is not a PWM output"),
    ((('drives = { motor_power = "enable" }', 'drives = { motor_power = "throttle" }'),),
     r"drives.motor_power = 'throttle': a GPIO output can only drive \"enable\""),
    ((('drives = { motor_power = "enable" }', 'drives = { horn = "enable" }'),),
     r"devices.contactor\]: drives names horn, which service 'contactor' does not have"),
])
def test_a_profile_whose_outputs_cannot_move_the_vehicle_is_refused(tmp_path: Path,
                                                                      change: tuple[tuple[str, str], ...],
                                                                      error: str) -> None:
    text = ACKERMANN
    for old, new in change:
        assert old in text, old
        text = text.replace(old, new)
    with pytest.raises(DeviceError, match=error):
        profile(tmp_path, text)


BOAT = """
[vehicle]
origin = { lat = 29.1895, lon = -81.0483 }

[services.thrusters]
kind = "pwm_servo"
settings = { channels = [
  { name = "left_thruster" },
  { name = "right_thruster", reverse = true } ] }

[simulation]
model = "twin_thruster"

[devices.left_thruster]
address = "pwm://pwmchip0/0"
mock = "sysfs_pwm"
drives = { left_thruster = "left" }

[devices.right_thruster]
address = "pwm://pwmchip0/1"
mock = "sysfs_pwm"
drives = { right_thruster = "right" }
"""


def test_a_servo_driven_boat_moves_under_its_sysfs_pwm_thrusters(tmp_path: Path) -> None:
    mocks = profile(tmp_path, BOAT)
    mocks.start()
    left = open_port(mocks.addresses["left_thruster"], device="left")
    right = open_port(mocks.addresses["right_thruster"], device="right")
    try:
        left.set_pulse_us(2000)    # full ahead
        right.set_pulse_us(1000)   # full ahead too: the right ESC is mounted reversed (reverse = true)
        for channel in (left, right):
            channel.enable(True)
        wait_until(lambda: mocks.vehicle.snapshot().speed > 0.5, message="both thrusters to push the boat ahead")
        assert abs(mocks.vehicle.snapshot().yaw_rate) < 0.05
        assert mocks.outputs.current("right_thruster").value == 100.0
        left.enable(False)         # no pulse: that ESC stops, the boat turns towards it
        wait_until(lambda: mocks.vehicle.snapshot().yaw_rate < -0.2, message="the boat to turn left")
        assert mocks.outputs.current("left_thruster").neutral
    finally:
        left.close()
        right.close()
        mocks.stop()


def test_u2sa_sim_refuses_a_car_whose_throttle_nothing_drives_before_anything_starts(tmp_path: Path) -> None:
    car = tmp_path / "car"
    shutil.copytree(REPO / "examples" / "ackermann_rover", car, ignore=shutil.ignore_patterns("data", "logs"))
    text = (car / "vehicle.toml").read_text()
    throttle = next(line for line in text.splitlines() if '{ name = "throttle"' in line)
    text = text.replace(throttle + "\n", "").replace("throttle = \"throttle\" }", "}").replace(", }", " }")
    (car / "vehicle.toml").write_text(text)
    proc = subprocess.run([*U2SA, "sim", "--vehicle", str(car / "vehicle.toml"), "--out", str(tmp_path / "out")],
                          cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    # one refusal line (the check's warnings, e.g. a device no mock drives, may stand before it)
    error = [line for line in proc.stderr.strip().splitlines() if not line.startswith("u2sa sim: warning: ")]
    assert len(error) == 1 and error[0].startswith(f"u2sa: sim: {car / 'vehicle.toml'}: [simulation] model = "
                                                   "'ackermann' moves by steering and throttle, but no device "
                                                   "drives throttle")
    assert not (tmp_path / "out" / "logs").exists() or not any((tmp_path / "out" / "logs").iterdir())
