"""The service contract end to end: real `u2sa service` processes over real LCM multicast."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import threading
import tomllib
from pathlib import Path
from typing import Any, Iterator

import pytest
from conftest import U2SA, ServiceProcesses, unprivileged, wait_until

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.service.contract import U2SAService

REPO = Path(__file__).resolve().parent.parent


def _discover(bus: BusClient, name: str) -> t.DiscoveryResponse | None:
    found = bus.discover(timeout=0.5, name=name)
    return found[0] if found else None


def test_discover_param_estimate_and_stop_by_name(services: ServiceProcesses, bus: BusClient) -> None:
    proc = services.start("state_estimator")
    wait_until(lambda: _discover(bus, "state_estimator"), timeout=20, message="the estimator to answer discovery")

    listed = json.loads(services.cli("services", "--json").stdout)
    est = next(s for s in listed if s["name"] == "state_estimator")
    assert est["type"] == "state_estimator" and est["status"] == "ok" and est["pid"] == proc.pid
    assert {"channel": "STATE_ESTIMATE", "type": "StateInformation"} in est["publishes"]
    assert {"channel": "STATE_INFO", "type": "StateInformation"} in est["subscribes"]

    params = json.loads(services.cli("param", "list", "state_estimator", "--json").stdout)
    assert params["sensor_timeout_s"] == 2.0 and params["mode"] == "ekf"
    cfg_file = services.workdir / ".u2sa" / "config" / "state_estimator.toml"
    assert not cfg_file.exists()
    r = services.cli("param", "set", "state_estimator", "sensor_timeout_s", "4.5")
    assert r.returncode == 0, r.stderr
    assert tomllib.loads(cfg_file.read_text())["sensor_timeout_s"] == 4.5
    before = cfg_file.read_bytes()
    r = services.cli("param", "set", "state_estimator", "sensor_timeout_s", "true")
    assert r.returncode == 1 and "expects float, got bool" in r.stderr
    assert cfg_file.read_bytes() == before
    assert services.cli("param", "get", "state_estimator", "sensor_timeout_s").stdout.strip() == "4.5"

    estimates: list[t.StateInformation] = []
    bus.transport.subscribe(ch.STATE_ESTIMATE, t.StateInformation, lambda _c, msg: estimates.append(msg))
    info = t.StateInformation().set(x=3.0, psi=1.25)
    info.sensor_name = "gps"
    bus.publish(ch.STATE_INFO, info)
    wait_until(lambda: estimates, message="a STATE_ESTIMATE")
    est_msg = estimates[-1]
    assert {"x", "psi"} <= set(est_msg.present_fields()) and not est_msg.has("y")  # the EKF adds rates, sigmas
    assert est_msg.x == 3.0 and est_msg.psi == 1.25
    assert est_msg.header.source == "state_estimator" and est_msg.header.sequence >= 1

    r = services.cli("stop", "state_estimator")
    assert r.returncode == 0, r.stderr
    assert proc.wait(timeout=10) == 0


def test_stop_all(services: ServiceProcesses, bus: BusClient) -> None:
    a = services.start("est_a", "--kind", "state_estimator")
    b = services.start("est_b", "--kind", "state_estimator")
    wait_until(lambda: len(bus.discover(timeout=0.5)) == 2, timeout=20, message="two services")
    r = services.cli("stop", "--all")
    assert r.returncode == 0 and "est_a, est_b" in r.stdout, r.stderr
    assert a.wait(timeout=10) == 0 and b.wait(timeout=10) == 0


def test_malformed_packets_are_counted_and_the_service_lives(services: ServiceProcesses, bus: BusClient) -> None:
    services.start("state_estimator")
    wait_until(lambda: _discover(bus, "state_estimator"), timeout=20, message="the estimator")
    health: list[t.Health] = []
    bus.transport.subscribe(ch.HEALTH, t.Health, lambda _c, msg: health.append(msg))
    good = t.StateInformation().set(y=2.0).encode()
    bus.transport.publish_bytes(ch.STATE_INFO, b"\x00garbage-bytes-that-are-no-message")
    bus.transport.publish_bytes(ch.STATE_INFO, good[:30])                 # truncated
    bus.transport.publish_bytes(ch.STATE_INFO, t.Health().encode())       # wrong type
    bus.transport.publish_bytes(ch.STATE_INFO, good)

    def malformed() -> int:
        return max((h.malformed for h in health if h.name == "state_estimator"), default=0)

    wait_until(lambda: malformed() >= 3, timeout=10, message="health to report 3 malformed messages")
    stats = next(c for c in health[-1].channels if c.channel == ch.STATE_INFO and c.direction == "in")
    assert stats.messages >= 1 and stats.malformed >= 3
    assert _discover(bus, "state_estimator").status == "ok"
    log = (services.workdir / ".u2sa" / "logs" / "state_estimator.log").read_text()
    assert log.count("dropping malformed message on STATE_INFO") == 1  # logged once per channel


def test_health_fields(services: ServiceProcesses, bus: BusClient) -> None:
    config = services.workdir / "est.toml"
    config.write_text("health_interval_s = 0.2\n")
    proc = services.start("state_estimator", "--config", str(config))
    health: list[t.Health] = []
    bus.transport.subscribe(ch.HEALTH, t.Health, lambda _c, msg: health.append(msg))
    wait_until(lambda: [h for h in health if h.status == "ok"], timeout=20, message="a health message")
    h = next(h for h in health if h.status == "ok")
    assert h.pid == proc.pid and h.host == socket.gethostname() and h.rss_bytes > 10_000_000
    assert h.uptime_s >= 0 and h.service_type == "state_estimator"
    assert any(kv.key == "loop_age_s" for kv in h.details)

    assert _discover(bus, "state_estimator")
    sample = t.StateInformation().set(x=1.0, y=2.0, x_sigma=1.0, y_sigma=1.0)
    sample.sensor_name = "gps"

    def busy_health() -> bool:  # work for the service, so its CPU % is above zero
        for _ in range(200):
            bus.publish(ch.STATE_INFO, sample)
        return any(x.cpu_percent > 0 for x in health)

    wait_until(busy_health, timeout=30, interval=0.05, message="a health message with cpu_percent > 0")
    bus.transport.publish_bytes(ch.STATE_INFO, b"\x00not-a-message")

    def out_count(msg: t.Health, channel: str) -> int:
        return next((c.messages for c in msg.channels if c.channel == channel and c.direction == "out"), 0)

    latest = wait_until(lambda: next((x for x in reversed(health) if x.last_error), None), timeout=20,
                        message="health with last_error")
    assert latest.last_error.startswith("malformed message on STATE_INFO")
    assert out_count(latest, ch.HEALTH) >= 1 and out_count(latest, ch.DISCOVERY_RESPONSE) >= 1
    assert out_count(latest, ch.STATE_ESTIMATE) >= 1
    ins = {c.channel: c.messages for c in latest.channels if c.direction == "in"}
    assert ins[ch.STATE_INFO] >= 200 and ins[ch.DISCOVERY_REQUEST] >= 1


def test_sigint_stops_the_service_with_exit_status_0(services: ServiceProcesses, bus: BusClient) -> None:
    proc = services.start("state_estimator")
    wait_until(lambda: _discover(bus, "state_estimator"), timeout=20, message="the estimator")
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=10) == 0
    assert "state_estimator stopped" in (services.workdir / ".u2sa" / "logs" / "state_estimator.log").read_text()


def test_passthrough_estimate_holds_the_union_of_two_messages(services: ServiceProcesses, bus: BusClient) -> None:
    """Switched to pass-through with a quoted TOML string, as `param get` prints it."""
    services.start("state_estimator")
    wait_until(lambda: _discover(bus, "state_estimator"), timeout=20, message="the estimator")
    r = services.cli("param", "set", "state_estimator", "mode", '"passthrough"')
    assert r.returncode == 0, r.stderr
    cfg_file = services.workdir / ".u2sa" / "config" / "state_estimator.toml"
    assert tomllib.loads(cfg_file.read_text())["mode"] == "passthrough"
    assert services.cli("param", "get", "state_estimator", "mode").stdout.strip() == '"passthrough"'

    estimates: list[t.StateInformation] = []
    bus.transport.subscribe(ch.STATE_ESTIMATE, t.StateInformation, lambda _c, msg: estimates.append(msg))
    gps = t.StateInformation().set(x=3.0, y=-4.0)
    gps.sensor_name = "gps"
    bus.publish(ch.STATE_INFO, gps)
    wait_until(lambda: estimates, message="the first estimate")
    assert set(estimates[0].present_fields()) == {"x", "y"}
    compass = t.StateInformation().set(psi=1.25, x=5.0)
    compass.sensor_name = "compass"
    bus.publish(ch.STATE_INFO, compass)
    wait_until(lambda: len(estimates) >= 2, message="the second estimate")
    union = estimates[1]
    assert set(union.present_fields()) == {"x", "y", "psi"}
    assert (union.x, union.y, union.psi) == (5.0, -4.0, 1.25)  # the newer x, the older y


def test_log_level_from_the_config_file_checked_and_changed_live(services: ServiceProcesses,
                                                                  bus: BusClient) -> None:
    config = services.workdir / "cfg" / "est.toml"
    config.parent.mkdir()
    config.write_text('log_level = "warn"\n')
    services.start("state_estimator", "--config", str(config))
    wait_until(lambda: _discover(bus, "state_estimator"), timeout=20, message="the estimator")
    log_file = services.workdir / ".u2sa" / "logs" / "state_estimator.log"
    assert " INFO " not in log_file.read_text()  # "started" is info: the file's warn applies from the start

    before = config.read_bytes()
    r = services.cli("param", "set", "state_estimator", "log_level", "verbose")
    assert r.returncode == 1 and "field 'log_level' must be one of" in r.stderr
    assert '"debug", "info", "warn", "warning", "error"' in r.stderr and config.read_bytes() == before

    assert services.cli("param", "set", "state_estimator", "log_level", "info").returncode == 0
    wait_until(lambda: "log level is now info" in log_file.read_text(), message="the info level")
    for args in (("log_level", "warning"), ("sensor_timeout_s", "3.5"), ("log_level", '"debug"')):
        r = services.cli("param", "set", "state_estimator", *args)
        assert r.returncode == 0, r.stderr
    wait_until(lambda: "log level is now debug" in log_file.read_text(), message="the debug level")
    text = log_file.read_text()
    assert "'sensor_timeout_s' changed" not in text  # logged at info while the level was warning
    assert tomllib.loads(config.read_text())["log_level"] == "debug"
    assert _discover(bus, "state_estimator").status == "ok"


def test_a_profile_with_an_unknown_log_level_is_refused_by_every_command(tmp_path: Path) -> None:
    """Checked when the profile loads: u2sa run and install too, not only u2sa service (whose children
    would otherwise crash-loop under the launcher)."""
    from u2sa_hw.profile.vehicle import ProfileError
    from u2sa_hw.profile.loader import load_profile

    profile = tmp_path / "vehicle.toml"
    profile.write_text('[vehicle]\nname = "x"\nlog_level = "verbose"\n\n[services.est]\nkind = "state_estimator"\n')
    with pytest.raises(ProfileError, match=r"vehicle.toml \[vehicle\]: log_level: unknown log level 'verbose'"):
        load_profile(profile)
    for cmd in (["run"], ["service", "est"]):
        r = subprocess.run([*U2SA, *cmd, "--vehicle", str(profile)], capture_output=True, text=True, timeout=60)
        assert r.returncode != 0 and r.stderr.count("\n") == 1 and "unknown log level 'verbose'" in r.stderr, r.stderr


def test_param_set_on_an_unwritable_config_file_fails_with_the_reason(services: ServiceProcesses,
                                                                      bus: BusClient) -> None:
    """The service runs as nobody (root ignores permissions) with its config in a read-only directory."""
    workdir = Path(tempfile.mkdtemp(prefix="u2sa-ro-svc-"))
    try:
        os.chmod(workdir, 0o777)  # the service's logs go here
        ro_dir = workdir / "ro"
        ro_dir.mkdir()
        config = ro_dir / "state_estimator.toml"
        config.write_text("sensor_timeout_s = 2.5\n")
        os.chmod(config, 0o444)
        os.chmod(ro_dir, 0o555)
        cmd = unprivileged([*U2SA, "service", "state_estimator", "--config", str(config)])
        log = open(services.workdir / "ro-service.stderr", "wb")
        proc = subprocess.Popen(cmd, cwd=workdir, env=services.env(PYTHONPATH=str(REPO)), stdout=log,
                                stderr=subprocess.STDOUT)
        services.procs.append(proc)
        wait_until(lambda: _discover(bus, "state_estimator"), timeout=30, message="the estimator run as nobody")
        r = services.cli("param", "set", "state_estimator", "sensor_timeout_s", "4.5")
        assert r.returncode == 1
        assert f"state_estimator refused: cannot write {config}: Permission denied; the file is unchanged" in r.stderr
        assert r.stderr.count("\n") == 1
        assert config.read_text() == "sensor_timeout_s = 2.5\n"
        assert services.cli("param", "get", "state_estimator", "sensor_timeout_s").stdout.strip() == "2.5"
    finally:
        services.stop_all()
        os.chmod(workdir / "ro", 0o755)
        shutil.rmtree(workdir)


@contextlib.contextmanager
def notify_socket() -> Iterator[tuple[str, list[str]]]:
    """An abstract-namespace datagram socket like systemd's: its ``@name`` and the states received."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    name = f"u2sa-test-notify-{os.getpid()}-{id(sock)}"
    sock.bind("\0" + name)
    sock.settimeout(0.2)
    received: list[str] = []
    done = threading.Event()

    def reader() -> None:
        while not done.is_set():
            try:
                received.append(sock.recv(4096).decode())
            except TimeoutError:
                continue

    thread = threading.Thread(target=reader, daemon=True)
    thread.start()
    try:
        yield "@" + name, received
    finally:
        done.set()
        thread.join(5)
        sock.close()


def test_sd_notify_ready_watchdog_stopping_on_abstract_socket(services: ServiceProcesses) -> None:
    with notify_socket() as (name, received):
        proc = services.start("state_estimator", NOTIFY_SOCKET=name, WATCHDOG_USEC="200000")
        wait_until(lambda: "READY=1" in received, timeout=20, message="READY=1")
        wait_until(lambda: received.count("WATCHDOG=1") >= 3, timeout=10, message="watchdog pings")
        assert any(r.startswith("STATUS=") for r in received)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
        wait_until(lambda: "STOPPING=1" in received, timeout=5, message="STOPPING=1")


def test_service_log_file_line_format(services: ServiceProcesses, bus: BusClient) -> None:
    services.start("state_estimator")
    wait_until(lambda: _discover(bus, "state_estimator"), timeout=20, message="the estimator")
    log = services.workdir / ".u2sa" / "logs" / "state_estimator.log"
    # it answers discovery as its bus starts, a moment before it logs that it started
    wait_until(lambda: "started" in log.read_text(), timeout=20, message="the estimator's first log line")
    line = log.read_text().splitlines()[0]
    import re

    match = re.fullmatch(r"(\d{4}-\d\d-\d\dT[\d:.]+) (\w+) +(\S+) \[(\d+)\] (.*)", line)
    assert match, line
    assert match.group(2) == "INFO" and match.group(3) == "state_estimator" and "started" in match.group(5)


def test_unknown_kind_and_no_service_errors_are_one_line(services: ServiceProcesses) -> None:
    r = services.cli("service", "no_such_thing")
    assert r.returncode != 0 and r.stderr.count("\n") == 1 and "unknown service kind 'no_such_thing'" in r.stderr
    r = services.cli("services", "--timeout", "0.3")
    assert r.returncode == 1 and "no service answered discovery" in r.stderr
    r = services.cli("param", "list", "ghost", "--timeout", "0.3")
    assert r.returncode == 1 and "service 'ghost' did not answer" in r.stderr
    r = services.cli("stop", "ghost")
    assert r.returncode == 1 and "service 'ghost' answered" in r.stderr


def test_help_on_every_subcommand(services: ServiceProcesses) -> None:
    for cmd in (["--help"], ["service", "--help"], ["services", "--help"], ["topics", "--help"],
                ["echo", "--help"], ["pub", "--help"], ["param", "--help"], ["param", "set", "--help"],
                ["stop", "--help"]):
        r = services.cli(*cmd)
        assert r.returncode == 0 and "usage: u2sa" in r.stdout, cmd


def test_pub_rejects_bad_field_with_message(services: ServiceProcesses) -> None:
    r = services.cli("pub", "STATE_INFO", "StateInformation", "x=abc")
    assert r.returncode == 2 and "field x: expected double, got 'abc'" in r.stderr
    r = services.cli("pub", "STATE_INFO", "NoSuchType")
    assert r.returncode == 1 and "unknown message type 'NoSuchType'" in r.stderr


# -- the contract in one process -------------------------------------------------------------

@contextlib.contextmanager
def running(service: U2SAService) -> Iterator[U2SAService]:
    """Start *service*, run its loop on a thread, stop and release it afterwards."""
    service.start()
    thread = threading.Thread(target=service.run, daemon=True)
    thread.start()
    try:
        yield service
    finally:
        service.stop()
        thread.join(10)
        assert not thread.is_alive(), "the run loop did not end on stop"
        service.kill()
        service.transport.stop()


class ObjectsService(U2SAService):
    """Subscribes OBJECTS to the default callback and GOALS to its own list; publishes WORLD."""

    def setup(self) -> None:
        self.goals: list[Any] = []
        self.register_subscriber(ch.OBJECTS, t.ObjectDescription)
        self.register_subscriber(ch.GOALS, t.GoalInformation, self.goals.append)
        self.register_publisher(ch.WORLD, t.ObjectDescription)


def _channels(infos: Any) -> dict[str, str]:
    return {i.channel: i.type_name for i in infos}


def test_discovery_lists_are_complete_from_the_first_reply_and_unregistering_withdraws(
        tmp_path: Path, lcm_url: str, bus: BusClient) -> None:
    with running(ObjectsService("objects", config_path=tmp_path / "o.toml")) as svc:
        first = bus.discover(timeout=5, name="objects")[0]
        assert _channels(first.subscribes) == {
            ch.DISCOVERY_REQUEST: "DiscoveryRequest", ch.STOP: "StopCommand", ch.CONFIG_REQUEST: "ConfigRequest",
            ch.CONFIG_CHANGE: "ConfigChange", ch.OBJECTS: "ObjectDescription", ch.GOALS: "GoalInformation"}
        assert _channels(first.publishes) == {
            ch.DISCOVERY_RESPONSE: "DiscoveryResponse", ch.CONFIG_RESPONSE: "ConfigResponse", ch.HEALTH: "Health",
            ch.WORLD: "ObjectDescription"}
        assert [c.channel for c in first.subscribes] == sorted(c.channel for c in first.subscribes)

        goal = t.GoalInformation()
        bus.publish(ch.GOALS, goal)
        wait_until(lambda: svc.goals, message="a goal through the subscription")
        svc.unregister_subscriber(ch.GOALS)
        svc.unregister_publisher(ch.WORLD)
        later = bus.discover(timeout=5, name="objects")[0]
        assert ch.GOALS not in _channels(later.subscribes) and ch.WORLD not in _channels(later.publishes)
        bus.publish(ch.GOALS, goal)
        # The service handles packets in order: once it answered the discovery sent after the
        # goal, the goal would have been delivered if the subscription were still there.
        assert bus.discover(timeout=5, name="objects")
        assert len(svc.goals) == 1 and svc.transport.rx[ch.GOALS].messages == 1


def test_unhandled_message_types_warn_once_then_count(tmp_path: Path, lcm_url: str, bus: BusClient,
                                                       caplog: pytest.LogCaptureFixture) -> None:
    health: list[t.Health] = []
    bus.transport.subscribe(ch.HEALTH, t.Health, lambda _c, m: health.append(m))
    with caplog.at_level(logging.WARNING, logger="u2sa.objects"):
        with running(ObjectsService("objects", config_path=tmp_path / "o.toml")) as svc:
            for uid in ("a", "b", "c"):
                obj = t.ObjectDescription()
                obj.uid = uid
                bus.publish(ch.OBJECTS, obj)
            wait_until(lambda: svc.transport.rx[ch.OBJECTS].messages >= 3, message="three objects")
            svc.publish_health()
            wait_until(lambda: any(kv.key == "unhandled" for h in health for kv in h.details), message="health")
    details = {kv.key: kv.value for kv in health[-1].details}
    assert details["unhandled"] == "ObjectDescription:3"
    warnings = [r for r in caplog.records if "unhandled message type ObjectDescription" in r.getMessage()]
    assert len(warnings) == 1 and warnings[0].levelno == logging.WARNING


def test_publish_keeps_a_measurement_timestamp_unless_restamped(tmp_path: Path, lcm_url: str,
                                                                 bus: BusClient) -> None:
    got: list[t.NavigationPoint] = []
    bus.transport.subscribe(ch.NAV_POINT, t.NavigationPoint, lambda _c, m: got.append(m))
    with running(U2SAService("stamper", config_path=tmp_path / "s.toml")) as svc:
        nav = t.NavigationPoint()
        nav.header.timestamp_us = 1_000_000  # a measurement time, long ago
        svc.publish(ch.NAV_POINT, nav)
        nav.header.timestamp_us = 1_000_000
        svc.publish(ch.NAV_POINT, nav, restamp=True)
        nav.header.timestamp_us = 0
        svc.publish(ch.NAV_POINT, nav)
        wait_until(lambda: len(got) >= 3, message="three navigation points")
    assert got[0].header.timestamp_us == 1_000_000
    assert got[1].header.timestamp_us > 1_000_000_000_000_000 and got[2].header.timestamp_us > 1_000_000_000_000_000
    assert [g.header.sequence for g in got] == [1, 2, 3] and {g.header.source for g in got} == {"stamper"}


class SlowLoopService(U2SAService):
    """A loop whose period (an hour) is far longer than the watchdog timeout."""

    iterations = 0

    def run(self) -> None:
        while self.wait(3600.0):
            self.iterations += 1


def test_watchdog_pings_while_the_loop_waits_longer_than_watchdog_usec(tmp_path: Path, lcm_url: str,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    with notify_socket() as (name, received):
        monkeypatch.setenv("NOTIFY_SOCKET", name)
        monkeypatch.setenv("WATCHDOG_USEC", "200000")
        monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
        with running(SlowLoopService("slow", config_path=tmp_path / "slow.toml")) as svc:
            wait_until(lambda: received.count("WATCHDOG=1") >= 5, timeout=30, message="watchdog pings")
            assert svc.iterations == 0  # all of them from inside one wait
