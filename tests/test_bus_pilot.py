"""The pilot's switch outranks every other sender, between real processes (issue 23).

An actuator (``pwm_servo`` on a sysfs-shaped PWM tree, gated by the pilot's switch) runs as
its own process. The test is the pilot: it holds the session's pilot key, as the RC mux does,
and keeps the switch at manual with the sticks centred. An attacker process holds the
vehicle's bus key and an operator key, but not the pilot's: it sends RC_MODE (autonomous,
armed, enabled), MANUAL_CMD (full) and ACTUATOR_CMD (full), HMAC-signed with both keys and
with an invented pilot signature. The ESC never leaves neutral, and the actuator counts the
drops as denied and forged. The path is shown to work first: the pilot's own sticks move it.

Also here: an operator key is denied on STATE_INFO by a real estimator, and a stop captured
before a service restarted is not obeyed after it.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import uuid
from pathlib import Path
from typing import Any, Iterator

import pytest
from conftest import U2SA, ServiceProcesses, wait_until
from gpio_driver_harness import BusCollector, pwm_duty_us
from serial_driver_harness import start_driver

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.auth import BusAuth, Keyring
from u2sa_hw.bus.client import BusClient
from u2sa_hw.bus.key import KEY_ENV, key_path, new_key, write_key
from u2sa_hw.bus.keyring import OPERATOR_KEY_ENV, OPERATORS_DIR
from u2sa_hw.ports.pwm.port import make_sysfs_pwm_tree
from u2sa_hw.bus.transport import Transport

ROUNDS = 150

ATTACKER = """\
import sys, time
from pathlib import Path
from u2sa_hw import channels as ch, lcmtypes as t
from u2sa_hw.bus.auth import _TAIL, MAC_BYTES, PILOT_TAG, PILOT_TRAILER_LEN, TAG, BusAuth, Keyring
from u2sa_hw.bus.transport import Transport

url, bus_key, operator_key, rounds = sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3]), int(sys.argv[4])
wire = Transport(url, name="attacker", security="open")          # sends the bytes it is given
vehicle = BusAuth(Keyring(bus_key, operator_file=""))
operator = BusAuth(Keyring(bus_key, operator_file=operator_key))

def hmac_signed(auth, channel, payload):        # what the code before issue 23 accepted on the pilot's channels
    key = auth.keyring.signing
    tail = _TAIL.pack(auth.sender, auth.now(), key.id)
    return payload + tail + key.mac(channel.encode() + b"\\0", payload + tail)[:MAC_BYTES] + TAG

def fake_pilot(channel, payload):
    tail = _TAIL.pack(b"attacker", vehicle.now(), b"\\0\\0\\0\\0")
    return payload + tail + bytes(PILOT_TRAILER_LEN - len(tail) - len(PILOT_TAG)) + PILOT_TAG

mode = t.RcMode(); mode.mode, mode.mode_name, mode.armed, mode.autonomy_enabled = 1, "AUTONOMOUS", True, True
full = t.PercentageCommand(); full.base.actuator_name, full.percentage = "esc", 100.0
for _ in range(rounds):
    for channel, msg in ((ch.RC_MODE, mode), (ch.MANUAL_CMD, full)):
        payload = msg.encode()
        for packet in (hmac_signed(vehicle, channel, payload), hmac_signed(operator, channel, payload),
                       fake_pilot(channel, payload)):
            assert wire.publish_bytes(channel, packet)
    payload = full.encode()
    assert wire.publish_bytes(ch.ACTUATOR_CMD, vehicle.sign(ch.ACTUATOR_CMD, payload))     # vehicle role: heard
    assert wire.publish_bytes(ch.ACTUATOR_CMD, operator.sign(ch.ACTUATOR_CMD, payload))    # operator role: denied
    time.sleep(0.01)                                                                        # about 100 Hz
"""


@pytest.fixture()
def operator_key() -> Iterator[Path]:
    """An operator key the vehicle (this session's key directory) accepts, removed afterwards."""
    path = key_path(None).parent / OPERATORS_DIR / f"test-{uuid.uuid4().hex[:8]}.key"
    write_key(path, new_key(), group=None)
    yield path
    path.unlink(missing_ok=True)


def attacker_keys(tmp_path: Path, operator: Path) -> tuple[Path, dict[str, str]]:
    """The bus key and the pilot's public key, not its private one: what a laptop or a team script holds."""
    home = tmp_path / "attacker"
    home.mkdir()
    shutil.copy(key_path(None), home / "bus.key")
    shutil.copy(key_path(None).parent / "pilot.pub", home / "pilot.pub")
    env = dict(os.environ, **{KEY_ENV: str(home / "bus.key"), OPERATOR_KEY_ENV: str(operator)})
    return home / "bus.key", env


class Pilot:
    """The RC mux's part: RC_MODE (manual, armed) at 20 Hz and the sticks on MANUAL_CMD, signed with the pilot key."""

    def __init__(self, bus: BusClient) -> None:
        self.bus = bus
        self.stick = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="pilot", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        mode = t.RcMode()
        mode.mode, mode.mode_name, mode.armed = 0, "MANUAL", True
        while not self._stop.wait(0.05):
            assert self.bus.transport.publish(ch.RC_MODE, mode)
            sticks = t.PercentageCommand()
            sticks.base.actuator_name, sticks.percentage = "esc", self.stick
            assert self.bus.transport.publish(ch.MANUAL_CMD, sticks)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)


def test_with_the_switch_at_manual_no_holder_of_the_bus_or_an_operator_key_moves_an_actuator(
        services: ServiceProcesses, bus: BusClient, tmp_path: Path, operator_key: Path) -> None:
    pwm = make_sysfs_pwm_tree(tmp_path / "pwmchip0", npwm=1)
    profile = tmp_path / "vehicle.toml"
    profile.write_text(f'[vehicle]\nname = "rover"\nlcm_url = "{services.url}"\nlog_dir = "logs"\n'
                       '[services.drive]\nkind = "pwm_servo"\nsettings = { health_interval_s = 0.2, '
                       'channels = [{ name = "esc" }] }\n'
                       f'[devices.esc]\naddress = "mock+pwm://{pwm}/0"\n')
    col = BusCollector(bus).listen(ch.HEALTH, t.Health)

    def duty_us() -> float:
        return pwm_duty_us(pwm)

    proc = start_driver(services, profile, "drive")
    pilot = Pilot(bus)
    try:
        wait_until(lambda: duty_us() == 1500.0, timeout=30, message="the ESC neutral at start")
        pilot.stick = 100.0                                        # the pilot's own sticks move it: the path works
        wait_until(lambda: duty_us() == 2000.0, timeout=30, message="the pilot's sticks to move the ESC")
        pilot.stick = 0.0
        wait_until(lambda: duty_us() == 1500.0, timeout=30, message="the sticks centred")

        bus_key, env = attacker_keys(tmp_path, operator_key)
        attacker = subprocess.Popen([sys.executable, "-c", ATTACKER, services.url, str(bus_key), str(operator_key),
                                     str(ROUNDS)], env=env, stderr=subprocess.PIPE, text=True)
        seen = set()
        while attacker.poll() is None:                              # the duty, every 2 ms while it attacks
            seen.add(duty_us())
            try:
                attacker.wait(timeout=0.002)
            except subprocess.TimeoutExpired:
                pass
        assert attacker.returncode == 0, attacker.stderr.read() if attacker.stderr else ""
        seen.add(duty_us())
        assert seen == {1500.0}, f"the ESC moved under the attack: {sorted(seen)}"

        health = col.health_of("drive", lambda d: all(
            f"{channel}: " in d.get("bus_rejected", "") for channel in (ch.RC_MODE, ch.MANUAL_CMD, ch.ACTUATOR_CMD)),
            since=0, timeout=30, message="the actuator to count the attacker's drops")
        rejected = dict(part.split(": ", 1) for part in health["bus_rejected"].split("; "))
        for channel in (ch.RC_MODE, ch.MANUAL_CMD):
            assert "denied" in rejected[channel] and "forged" in rejected[channel], rejected
        assert "denied" in rejected[ch.ACTUATOR_CMD], rejected
        assert health["failsafe"] == "False" and proc.poll() is None
        listed = services.cli("services", "--json")                # the operator sees the denials, per service
        assert listed.returncode == 0, listed.stderr
        row = next(r for r in json.loads(listed.stdout) if r["name"] == "drive")
        assert row["denied"] >= 3 and row["bad_signature"] >= 2, row
        pilot.stick = -100.0                                        # and the pilot still drives
        wait_until(lambda: duty_us() == 1000.0, timeout=30, message="the pilot's sticks after the attack")
    finally:
        pilot.stop()


def test_an_operator_key_is_denied_on_state_info_by_a_real_estimator(services: ServiceProcesses, bus: BusClient,
                                                                    operator_key: Path, tmp_path: Path) -> None:
    services.start("state_estimator")
    wait_until(lambda: bus.discover(timeout=0.5, name="state_estimator"), timeout=30, message="the estimator")
    col = BusCollector(bus).listen(ch.HEALTH, t.Health)
    laptop = Transport(services.url, name="laptop", security="open")
    operator = BusAuth(Keyring(key_path(None), operator_file=operator_key))
    try:
        state = t.StateInformation().set(x=1000.0, y=1000.0)
        assert laptop.publish_bytes(ch.STATE_INFO, operator.sign(ch.STATE_INFO, state.encode()))
        col.health_of("state_estimator", lambda d: "STATE_INFO: denied 1" in d.get("bus_rejected", ""),
                      since=0, timeout=30, message="the estimator to deny the operator's STATE_INFO")
    finally:
        laptop.stop()


def test_a_stop_signed_before_a_service_restarted_is_not_obeyed_after_it(services: ServiceProcesses,
                                                                        bus: BusClient) -> None:
    name = "state_estimator"
    first = services.start(name)
    found = wait_until(lambda: bus.discover(timeout=0.5, name=name), timeout=30, message=f"{name} to answer")
    stop = t.StopCommand()
    stop.name = name
    captured: dict[str, Any] = {}
    sniffer = Transport(services.url, name="sniffer", security="open")
    # plain LCM under the transport: what is on the wire, trailer and all
    sniffer.raw_lcm().subscribe(ch.STOP, lambda _c, data: captured.setdefault("packet", data))
    sniffer.start()
    try:
        assert bus.transport.publish(ch.STOP, stop)
        assert first.wait(timeout=30) == 0, "the signed stop was not obeyed"
        wait_until(lambda: "packet" in captured, timeout=10, message="the stop on the wire")
        restarted = services.start(name)
        wait_until(lambda: any(r.pid != found[0].pid for r in bus.discover(timeout=0.5, name=name)),
                   timeout=30, message=f"the restarted {name}")
        col = BusCollector(bus).listen(ch.HEALTH, t.Health)
        wire = Transport(services.url, name="replayer", security="open")
        try:
            assert wire.publish_bytes(ch.STOP, captured["packet"])     # the capture, inside the 20 s window
            col.health_of(name, lambda d: "U2SA_STOP: replayed 1" in d.get("bus_rejected", ""),
                          since=0, timeout=30, message="the restarted service to drop the old stop")
        finally:
            wire.stop()
        assert restarted.poll() is None, "the restarted service obeyed a stop signed before it started"
        assert bus.transport.publish(ch.STOP, stop)                   # a new stop is obeyed
        assert restarted.wait(timeout=30) == 0
    finally:
        sniffer.stop()


def test_a_ground_station_with_an_operator_key_sets_parameters_and_stops_a_service(
        services: ServiceProcesses, bus: BusClient, operator_key: Path, tmp_path: Path) -> None:
    name = "state_estimator"
    proc = services.start(name)
    wait_until(lambda: bus.discover(timeout=0.5, name=name), timeout=30, message=f"{name} to answer")
    stranger = tmp_path / "stranger.key"                      # an operator key the vehicle was never given
    write_key(stranger, new_key(), group=None)
    env = {**services.env(), OPERATOR_KEY_ENV: str(stranger)}
    refused = subprocess.run([*U2SA, "param", "set", name, "health_interval_s", "0.4"], env=env,
                             capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert refused.returncode != 0, refused.stdout
    env[OPERATOR_KEY_ENV] = str(operator_key)
    changed = subprocess.run([*U2SA, "param", "set", name, "health_interval_s", "0.4"], env=env,
                             capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert changed.returncode == 0, changed.stdout + changed.stderr
    stopped = subprocess.run([*U2SA, "stop", name], env=env, capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert stopped.returncode == 0, stopped.stdout + stopped.stderr
    assert proc.wait(timeout=30) == 0
