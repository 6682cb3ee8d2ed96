"""The authenticated bus between real processes over real multicast (issue 11, docs/security.md).

A state estimator runs as its own process with the session's key. Another process without
the key (an open transport, as a laptop on the WiFi would be) and one with the wrong key
send a stop, a config change, a failsafe clear, an actuator command and a STATE_INFO: the
service obeys none, counts each per channel in its health and keeps running. The services
that act are sent the same: a ``pwm_servo`` actuator on a sysfs-shaped PWM tree moves nothing
for a forged or unsigned ACTUATOR_CMD, and keeps a raised failsafe through a forged and an
unsigned clear. A captured signed packet sent again is dropped as replayed; a rotated key is
picked up without a restart; a restarted service is heard at once; a duplicate refuses to start,
and of two started at once exactly one stays.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import uuid
from pathlib import Path
from typing import Any

import lcm
import pytest
from conftest import ServiceProcesses, wait_until
from gpio_driver_harness import BusCollector, pwm_duty_us
from serial_driver_harness import start_driver

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.bus.auth import TAG, TRAILER_LEN, BusAuth, Keyring, keyring_for
from u2sa_hw.bus.key import KEY_ENV, key_path, new_key, write_key
from u2sa_hw.ports.pwm.port import make_sysfs_pwm_tree
from u2sa_hw.service.bus_handlers import DUPLICATE_PROBE_S, PROBE_ENV, Instance, health_instance, process_start_us
from u2sa_hw.bus.transport import Transport

SERVICE = "state_estimator"

FORGER = """\
import sys
from u2sa_hw import channels as ch, lcmtypes as t
from u2sa_hw.bus.transport import Transport

tx = Transport(sys.argv[1], name="laptop")    # open, or signed with the wrong key: the environment says
stop = t.StopCommand(); stop.all = True
change = t.ConfigChange(); change.request_id, change.target = "forged", sys.argv[2]
change.field, change.value = "health_interval_s", "0.25"
failsafe = t.Failsafe()
command = t.PercentageCommand(); command.base.actuator_name = "left"; command.percentage = 100.0
state = t.StateInformation().set(x=1000.0, y=1000.0, psi=3.0)
for channel, msg in ((ch.STOP, stop), (ch.CONFIG_CHANGE, change), (ch.FAILSAFE, failsafe),
                     (ch.ACTUATOR_CMD, command), (ch.STATE_INFO, state)):
    assert tx.publish(channel, msg), channel
"""
FORGED_CHANNELS = (ch.STOP, ch.CONFIG_CHANGE, ch.FAILSAFE, ch.ACTUATOR_CMD, ch.STATE_INFO)


class HealthLog:
    """The latest Health of every service, from a transport of the test's own."""

    def __init__(self, bus: BusClient) -> None:
        self.latest: dict[str, t.Health] = {}
        self._lock = threading.Lock()
        bus.transport.subscribe(ch.HEALTH, t.Health, self._on_health)

    def _on_health(self, _c: str, msg: t.Health) -> None:
        with self._lock:
            self.latest[msg.name] = msg

    def details(self, name: str) -> dict[str, str]:
        with self._lock:
            msg = self.latest.get(name)
        return {kv.key: kv.value for kv in msg.details} if msg else {}


def run_forger(url: str, env: dict[str, str]) -> None:
    subprocess.run([sys.executable, "-c", FORGER, url, SERVICE], env=env, check=True, timeout=60)


def start_estimator(services: ServiceProcesses, bus: BusClient) -> t.DiscoveryResponse:
    services.start(SERVICE)
    found = wait_until(lambda: bus.discover(timeout=0.5, name=SERVICE), timeout=30, message=f"{SERVICE} to answer")
    return found[0]


def test_forged_commands_and_data_from_processes_without_the_key_are_ignored_and_counted(
        services: ServiceProcesses, bus: BusClient, tmp_path: Path) -> None:
    health = HealthLog(bus)
    heard: list[str] = []
    for channel in FORGED_CHANNELS:   # a signed listener of the test's own hears none of them either
        bus.transport.subscribe(channel, None, lambda c, _d: heard.append(c), raw=True)
    first = start_estimator(services, bus)
    before = bus.get_config(SERVICE)
    assert before is not None and before.ok

    keyless = {k: v for k, v in os.environ.items() if k != KEY_ENV}
    run_forger(services.url, {**keyless, "U2SA_BUS_SECURITY": "open"})
    wrong = tmp_path / "wrong.key"
    write_key(wrong, new_key(), group=None)
    run_forger(services.url, {**keyless, KEY_ENV: str(wrong)})

    expected = {"U2SA_STOP: unsigned 1, forged 1", "U2SA_CONFIG_SET: unsigned 1, forged 1",
                "STATE_INFO: unsigned 1, forged 1"}
    wait_until(lambda: expected <= set(health.details(SERVICE).get("bus_rejected", "").split("; ")), timeout=30,
               message="the estimator's health to count the forged packets")
    assert health.details(SERVICE)["bus_security"].startswith("signed (key ")
    assert services.procs[0].poll() is None, "the forged stop stopped the service"
    after = bus.get_config(SERVICE)
    assert after is not None
    assert {f.name: f.value for f in after.fields}["health_interval_s"] == \
        {f.name: f.value for f in before.fields}["health_interval_s"]
    assert bus.discover(timeout=1.0, name=SERVICE)[0].pid == first.pid
    assert heard == []
    assert {c: bus.transport.rx[c].unsigned for c in FORGED_CHANNELS} == {c: 1 for c in FORGED_CHANNELS}
    assert {c: bus.transport.rx[c].forged for c in FORGED_CHANNELS} == {c: 1 for c in FORGED_CHANNELS}
    log = (services.workdir / ".u2sa" / "logs" / f"{SERVICE}.log").read_text()
    assert log.count("dropping unsigned message on U2SA_STOP") == 1

    shown = services.cli("health", "--json", "--timeout", "3")
    services_json = services.cli("services", "--json")
    assert services_json.returncode == 0, services_json.stderr
    listed = {s["name"]: s for s in json.loads(services_json.stdout)}
    assert listed[SERVICE]["bus"].startswith("signed") and listed[SERVICE]["rejected"] >= 6, listed
    assert shown.returncode in (0, 1)


def test_a_captured_signed_packet_sent_again_is_dropped_as_replayed(services: ServiceProcesses, bus: BusClient) -> None:
    health = HealthLog(bus)
    start_estimator(services, bus)
    sniffer = lcm.LCM(services.url)           # a plain LCM socket: what anyone on the network captures
    captured: list[bytes] = []
    sniffer.subscribe(ch.CONFIG_CHANGE, lambda _c, data: captured.append(data))
    done = threading.Event()

    def sniff() -> None:
        while not done.is_set() and not captured:
            sniffer.handle_timeout(100)

    thread = threading.Thread(target=sniff, daemon=True)
    thread.start()
    r = services.cli("param", "set", SERVICE, "health_interval_s", "0.5")
    assert r.returncode == 0, r.stderr
    thread.join(30)
    done.set()
    assert captured, "the sniffer captured no config change"
    r = services.cli("param", "set", SERVICE, "health_interval_s", "0.75")
    assert r.returncode == 0, r.stderr

    # Sent again byte for byte (an open transport adds no trailer; ttl=0 sends on lo, where the vehicle listens).
    Transport(services.url, name="replayer", security="open").publish_bytes(ch.CONFIG_CHANGE, captured[0])
    wait_until(lambda: "U2SA_CONFIG_SET: replayed 1" in health.details(SERVICE).get("bus_rejected", ""), timeout=30,
               message="the estimator to count the replayed config change")
    current = bus.get_config(SERVICE)
    assert current is not None
    assert {f.name: f.value for f in current.fields}["health_interval_s"] == "0.75"


def test_a_rotated_key_is_used_without_a_restart(services: ServiceProcesses, tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    key = tmp_path / "vehicle.key"
    write_key(key, new_key(), group=None)
    monkeypatch.setenv(KEY_ENV, str(key))
    proc = services.start(SERVICE, U2SA_BUS_KEY_FILE=str(key))

    def listed() -> list[dict[str, Any]]:
        r = subprocess.run([sys.executable, "-m", "u2sa_hw.cli", "services", "--json"], env=services.env(
            U2SA_BUS_KEY_FILE=str(key)), capture_output=True, text=True, timeout=30)
        assert r.returncode in (0, 1), r.stderr    # 1: nobody answered (yet)
        return json.loads(r.stdout) if r.returncode == 0 else []

    first = wait_until(listed, timeout=30, message="the service to answer with the first key")
    old_id = subprocess.run([sys.executable, "-m", "u2sa_hw.cli", "key", "show", "--id", "--file", str(key)],
                            capture_output=True, text=True, check=True).stdout.strip()
    rotated = subprocess.run([sys.executable, "-m", "u2sa_hw.cli", "key", "rotate", "--file", str(key)],
                             capture_output=True, text=True, timeout=30)
    assert rotated.returncode == 0, rotated.stderr
    assert old_id not in rotated.stdout

    def on_new_key() -> list[dict[str, Any]]:
        now = listed()
        return [s for s in now if s["name"] == SERVICE and s["bus"].endswith(f"{rotated.stdout.split()[2]})")]

    again = wait_until(on_new_key, timeout=30, message="the service to answer signed with the rotated key")
    assert again[0]["pid"] == first[0]["pid"] and proc.poll() is None


def test_a_restarted_service_is_heard_at_once(services: ServiceProcesses, bus: BusClient) -> None:
    first = start_estimator(services, bus)
    r = services.cli("stop", SERVICE)
    assert r.returncode == 0, r.stderr
    services.procs[0].wait(timeout=30)
    # The same client, which heard the first process's counters, hears the second's at once.
    second = start_estimator(services, bus)
    assert second.pid != first.pid


def test_an_open_bus_is_said_at_start_and_in_discovery(services: ServiceProcesses, tmp_path: Path) -> None:
    profile = tmp_path / "vehicle.toml"
    profile.write_text(f'[vehicle]\nname = "bench"\nlcm_url = "{services.url}"\nbus_security = "open"\n'
                       f'[services.{SERVICE}]\nkind = "{SERVICE}"\n')
    services.start(SERVICE, "--vehicle", str(profile))
    client = BusClient(services.url, security="open", name=f"open-{uuid.uuid4().hex[:6]}")
    try:
        wait_until(lambda: client.discover(timeout=0.5, name=SERVICE), timeout=30, message="the open service")
    finally:
        client.close()
    r = services.cli("services", "--vehicle", str(profile), "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)[0]["bus"] == "open"
    log = wait_until(lambda: (p := tmp_path / "logs" / f"{SERVICE}.log").exists() and p.read_text(), timeout=10)
    assert "the bus is open" in log


def duplicate_line(services: ServiceProcesses, log_name: str) -> str:
    out = (services.workdir / f"{log_name}.stderr").read_text()
    assert "Traceback" not in out, out
    lines = [x for x in out.splitlines() if "already runs on this bus" in x]
    assert len(lines) == 1, out
    return lines[0]


def test_a_duplicate_service_refuses_to_start_naming_the_other(services: ServiceProcesses, bus: BusClient) -> None:
    first = start_estimator(services, bus)     # discoverable before the second starts
    second = services.start(SERVICE, **{PROBE_ENV: str(DUPLICATE_PROBE_S)})   # the default probe (0.3 s, its
    # request sent 3 times; the suite's services listen 0.25 s), then the watch
    assert second.wait(timeout=30) == 3
    line = duplicate_line(services, SERVICE)
    assert f"pid {first.pid} on host {first.host}" in line and f"u2sa stop {SERVICE}" in line
    assert services.procs[0].poll() is None
    assert bus.discover(timeout=1.0, name=SERVICE)[0].pid == first.pid


def test_a_duplicate_the_probe_missed_stops_once_it_hears_the_first(services: ServiceProcesses,
                                                                   bus: BusClient) -> None:
    # As on a loaded board where the first answers after the probe: here the second skips its
    # probe, starts, and hears the first's Health in its watch. The newer stops; the first runs on.
    first = start_estimator(services, bus)
    second = services.start(SERVICE, **{PROBE_ENV: "0"})
    assert second.wait(timeout=30) == 3
    out = (services.workdir / f"{SERVICE}.stderr").read_text()
    assert f"started, pid {second.pid}" in out, out          # it did start: the watch found the first
    line = duplicate_line(services, SERVICE)
    assert f"pid {first.pid} on host {first.host}, heard after this one started" in line, line
    assert services.procs[0].poll() is None
    assert bus.discover(timeout=1.0, name=SERVICE)[0].pid == first.pid


AT_THE_BARRIER = """\
import os, sys
from pathlib import Path
from u2sa_hw.cli import main
Path(sys.argv[1]).touch()      # imported and at the barrier
os.read(0, 1)                  # the test's go, written to both at once
sys.exit(main(["service", sys.argv[2]]))
"""


@pytest.mark.parametrize("probe", ["default probe", "no probe"])
def test_two_of_one_name_started_at_once_leave_exactly_one(services: ServiceProcesses, bus: BusClient,
                                                           probe: str) -> None:
    # Neither answers the other's probe (neither runs yet): both start, hear each other's Health,
    # and the newer (the later process start, then the larger pid, then sender id) stops.
    heard: dict[int, Any] = {}

    def on_health(_c: str, msg: t.Health) -> None:
        if msg.name == SERVICE and msg.status != "stopping" and msg.pid not in heard:
            heard[msg.pid] = health_instance(msg, bus.transport.last_sender)

    bus.transport.subscribe(ch.HEALTH, t.Health, on_health)
    env = services.env(**{PROBE_ENV: "0" if probe == "no probe" else str(DUPLICATE_PROBE_S)})
    procs = []
    for i in (1, 2):
        log = open(services.workdir / f"twin{i}.stderr", "wb")
        procs.append(subprocess.Popen([sys.executable, "-c", AT_THE_BARRIER, str(services.workdir / f"twin{i}.ready"),
                                       SERVICE], cwd=services.workdir, env=env, stdin=subprocess.PIPE,
                                      stdout=log, stderr=subprocess.STDOUT))
    services.procs.extend(procs)
    wait_until(lambda: all((services.workdir / f"twin{i}.ready").exists() for i in (1, 2)), timeout=30,
               message="both at the barrier")
    for p in procs:
        p.stdin.write(b"g")
        p.stdin.close()
    wait_until(lambda: any(p.poll() is not None for p in procs), timeout=30, message="one of the two to stop")
    stopped = [p for p in procs if p.poll() is not None]
    assert len(stopped) == 1 and stopped[0].returncode == 3, [p.returncode for p in procs]
    loser = stopped[0]
    survivor = procs[1 - procs.index(loser)]
    line = duplicate_line(services, f"twin{procs.index(loser) + 1}")
    answers = wait_until(lambda: bus.discover(timeout=0.5, name=SERVICE), timeout=30, message="the survivor")
    assert [a.pid for a in answers] == [survivor.pid] and survivor.poll() is None
    assert f"pid {survivor.pid} on host {answers[0].host}" in line, line
    if "heard after this one started" in line:   # both ran (always without the probe): the newer stopped
        if {loser.pid, survivor.pid} <= set(heard):   # (each sends a Health as it starts; the test heard them)
            assert heard[loser.pid] > heard[survivor.pid], heard
    else:                     # the survivor ran (and sent its Health) before the loser's probe ended
        assert probe == "default probe", line


def test_services_a_launcher_started_take_its_start_so_a_whole_newer_run_gives_way() -> None:
    # Every child of one `u2sa run` (U2SA_RUN_ID set, the launcher its parent) reports the run's start and
    # pid: of two runs of one profile started together, all of the newer run's duplicates are the newer.
    show = ("from u2sa_hw.service.bus_handlers import own_instance\n"
            "class T: sender = 'ab'\n"
            "i = own_instance(T()); print(i.started_us, i.stack_pid, i.pid)")
    env = {k: v for k, v in os.environ.items() if k != "U2SA_RUN_ID"}
    for run_id, stack_is_parent in ((None, False), ("1", True)):
        out = subprocess.run([sys.executable, "-c", show], env={**env, **({"U2SA_RUN_ID": run_id} if run_id else {})},
                             capture_output=True, text=True, check=True, timeout=60).stdout.split()
        started, stack, pid = (int(x) for x in out)
        if stack_is_parent:
            assert stack == os.getpid() and started == process_start_us(os.getpid())
        else:
            assert stack == pid != os.getpid() and started >= process_start_us(os.getpid())
    newer, older = Instance(2_000_000, 10, "aa"), Instance(1_000_000, 99, "ff")
    assert newer > older                                   # the later start
    assert Instance(1, 11, "") > Instance(1, 10, "ff")     # then the larger stack pid
    assert Instance(1, 10, "ab") > Instance(1, 10, "aa")   # then the larger sender id


def test_a_key_holder_with_another_system_id_is_dropped_as_foreign_and_shown(services: ServiceProcesses,
                                                                            bus: BusClient) -> None:
    # A second stack signed with the same key (a fleet sharing one, a sim given --bus-key) but
    # another vehicle's system id: its stop and config change are dropped, counted and shown.
    health = HealthLog(bus)
    first = start_estimator(services, bus)     # the default profile: system id 1
    other = Transport(services.url, name="vehicle-2")    # the session's key
    stop = t.StopCommand()
    stop.all = True
    change = t.ConfigChange()
    change.request_id, change.target, change.field, change.value = "other", SERVICE, "health_interval_s", "0.25"
    for msg, channel in ((stop, ch.STOP), (change, ch.CONFIG_CHANGE)):
        msg.header.system_id, msg.header.source = 2, "vehicle-2"
        assert other.publish(channel, msg)
    other.stop()
    expected = {"U2SA_STOP: foreign 1", "U2SA_CONFIG_SET: foreign 1"}
    wait_until(lambda: expected <= set(health.details(SERVICE).get("bus_rejected", "").split("; ")), timeout=30,
               message="the estimator's health to count the foreign packets")
    assert services.procs[0].poll() is None, "another vehicle's stop stopped the service"
    config = bus.get_config(SERVICE)
    assert config is not None and {f.name: f.value for f in config.fields}["health_interval_s"] != "0.25"
    assert bus.discover(timeout=1.0, name=SERVICE)[0].pid == first.pid

    listed = services.cli("services", "--json")
    assert listed.returncode == 0, listed.stderr
    row = {s["name"]: s for s in json.loads(listed.stdout)}[SERVICE]
    assert row["foreign"] == 2 and row["bad_signature"] == 0, row
    table = services.cli("services")
    header, line = table.stdout.splitlines()[0], next(x for x in table.stdout.splitlines() if x.startswith(SERVICE))
    assert "BAD SIG" in header and "FOREIGN" in header
    assert line.split()[5:8] == ["signed", "0", "2"], line     # BUS, BAD SIG, FOREIGN


def test_garbage_truncated_and_huge_counter_trailers_are_counted_never_raised(services: ServiceProcesses,
                                                                              bus: BusClient) -> None:
    health = HealthLog(bus)
    first = start_estimator(services, bus)
    stop = t.StopCommand()
    stop.all = True
    payload = stop.encode()
    signer = BusAuth(keyring_for(key_path(None)))                         # the vehicle's key: a real signature
    future = BusAuth(keyring_for(key_path(None)), wall_us=lambda: 2 ** 64 - 10)   # ... on a counter out of range
    packets = [payload + os.urandom(TRAILER_LEN - len(TAG)) + TAG,       # a garbage trailer: forged
               signer.sign(ch.STOP, payload)[:-7],                       # a truncated one: unsigned
               b"\x01\x02\x03",                                          # not even a fingerprint: unsigned
               future.sign(ch.STOP, payload)]                            # a huge counter: replayed
    wire = Transport(services.url, name="garbage", security="open")     # sends the bytes as they are
    for packet in packets:
        assert wire.publish_bytes(ch.STOP, packet)
    wire.stop()
    wait_until(lambda: "U2SA_STOP: unsigned 2, forged 1, replayed 1" in health.details(SERVICE).get("bus_rejected", ""),
               timeout=30, message="the estimator to count the damaged packets")
    assert services.procs[0].poll() is None
    assert bus.discover(timeout=1.0, name=SERVICE)[0].pid == first.pid
    log = (services.workdir / ".u2sa" / "logs" / f"{SERVICE}.log").read_text()
    assert "Traceback" not in log and log.count("dropping unsigned message on U2SA_STOP") == 1


# ------------------------------------------------------------------ the services that act ---------
class Forger:
    """A laptop on the network: unsigned packets, and packets signed with a key that is not the vehicle's."""

    def __init__(self, url: str, wrong_key: Path) -> None:
        write_key(wrong_key, new_key(), group=None)
        self.wire = Transport(url, name="laptop", security="open")      # sends the bytes as they are
        self.wrong = BusAuth(Keyring(wrong_key))

    def send(self, channel: str, msg: Any) -> None:
        payload = msg.encode()
        assert self.wire.publish_bytes(channel, payload)                          # unsigned
        assert self.wire.publish_bytes(channel, self.wrong.sign(channel, payload))   # forged

    def close(self) -> None:
        self.wire.stop()


def test_an_actuator_moves_for_no_forged_command_and_keeps_its_failsafe_through_forged_clears(
        services: ServiceProcesses, bus: BusClient, tmp_path: Path) -> None:
    pwm = make_sysfs_pwm_tree(tmp_path / "pwmchip0", npwm=1)
    profile = tmp_path / "vehicle.toml"          # a bench: no RC gating, no dead-man, so a command would stick
    profile.write_text(f'[vehicle]\nname = "bench"\nlcm_url = "{services.url}"\nlog_dir = "logs"\n'
                       '[services.drive]\nkind = "pwm_servo"\nsettings = { health_interval_s = 0.2, '
                       'command_timeout_s = 0.0, rc_gating = false, channels = [{ name = "esc" }] }\n'
                       f'[devices.esc]\naddress = "mock+pwm://{pwm}/0"\n')
    col = BusCollector(bus).listen(ch.HEALTH, t.Health)

    def duty_us() -> float:
        return pwm_duty_us(pwm)

    def drive(predicate: Any, message: str) -> dict[str, str]:
        return col.health_of("drive", predicate, since=col.count(ch.HEALTH), timeout=30, message=message)

    proc = start_driver(services, profile, "drive")
    forger = Forger(services.url, tmp_path / "laptop.key")
    command = t.PercentageCommand()
    command.base.actuator_name, command.percentage = "esc", 100.0
    try:
        wait_until(lambda: duty_us() == 1500.0, timeout=30, message="the ESC neutral at start")
        drive(lambda d: d["failsafe"] == "False", "the actuator's health")

        forger.send(ch.ACTUATOR_CMD, command)
        dropped = drive(lambda d: "ACTUATOR_CMD: unsigned 1, forged 1" in d.get("bus_rejected", ""),
                        "the actuator to count the forged and unsigned commands")
        assert (dropped["commands"], dropped["ignored"]) == ("0", "0"), "a forged command reached the gate"
        assert duty_us() == 1500.0, "a forged 100 % moved the ESC"
        bus.publish(ch.ACTUATOR_CMD, command)      # the vehicle's key: obeyed (the path works)
        wait_until(lambda: duty_us() == 2000.0, timeout=30, message="the signed command to move the ESC")

        raised = t.Failsafe()
        raised.active, raised.reason, raised.header.source = True, "swimmer near the vehicle", "operator"
        bus.publish(ch.FAILSAFE, raised)
        drive(lambda d: d["failsafe"] == "True" and d["failsafe_sources"] == "operator", "the failsafe held")
        wait_until(lambda: duty_us() == 1500.0, timeout=30, message="neutral on the failsafe")

        clear = t.Failsafe()                        # the operator's clear of every source, forged and unsigned
        clear.active, clear.service, clear.header.source = False, "*", "operator"
        forger.send(ch.FAILSAFE, clear)
        held = drive(lambda d: "FAILSAFE: unsigned 1, forged 1" in d.get("bus_rejected", ""),
                     "the actuator to count the forged and unsigned clears")
        assert held["failsafe"] == "True" and held["failsafe_sources"] == "operator", held
        forger.send(ch.ACTUATOR_CMD, command)
        drive(lambda d: "ACTUATOR_CMD: unsigned 2, forged 2" in d.get("bus_rejected", ""), "the second forgeries")
        assert duty_us() == 1500.0

        bus.publish(ch.FAILSAFE, clear)             # signed: obeyed
        drive(lambda d: d["failsafe"] == "False", "the signed clear lowering the failsafe")
        assert proc.poll() is None
    finally:
        forger.close()
