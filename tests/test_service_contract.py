"""The service contract end to end: real `u2sa service` processes over real LCM multicast."""

from __future__ import annotations

import json
import os
import signal
import socket
import threading
import tomllib
from pathlib import Path

from conftest import ServiceProcesses, wait_until

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus_client import BusClient


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
    proc = services.start("state_estimator")
    health: list[t.Health] = []
    bus.transport.subscribe(ch.HEALTH, t.Health, lambda _c, msg: health.append(msg))
    wait_until(lambda: [h for h in health if h.status == "ok"], timeout=20, message="a health message")
    h = next(h for h in health if h.status == "ok")
    assert h.pid == proc.pid and h.host == socket.gethostname() and h.rss_bytes > 10_000_000
    assert h.uptime_s >= 0 and h.service_type == "state_estimator"
    assert any(kv.key == "loop_age_s" for kv in h.details)


def test_sd_notify_ready_watchdog_stopping_on_abstract_socket(services: ServiceProcesses) -> None:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    name = f"u2sa-test-notify-{os.getpid()}-{id(sock)}"
    sock.bind("\0" + name)
    sock.settimeout(0.5)
    received: list[str] = []
    done = threading.Event()

    def reader() -> None:
        while not done.is_set():
            try:
                received.append(sock.recv(4096).decode())
            except TimeoutError:
                continue

    threading.Thread(target=reader, daemon=True).start()
    try:
        proc = services.start("state_estimator", NOTIFY_SOCKET="@" + name, WATCHDOG_USEC="200000")
        wait_until(lambda: "READY=1" in received, timeout=20, message="READY=1")
        wait_until(lambda: received.count("WATCHDOG=1") >= 3, timeout=10, message="watchdog pings")
        assert any(r.startswith("STATUS=") for r in received)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
        wait_until(lambda: "STOPPING=1" in received, timeout=5, message="STOPPING=1")
    finally:
        done.set()
        sock.close()


def test_service_log_file_line_format(services: ServiceProcesses, bus: BusClient) -> None:
    services.start("state_estimator")
    wait_until(lambda: _discover(bus, "state_estimator"), timeout=20, message="the estimator")
    line = (services.workdir / ".u2sa" / "logs" / "state_estimator.log").read_text().splitlines()[0]
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


def test_echo_json_prints_fields_by_name(services: ServiceProcesses, bus: BusClient, tmp_path: Path) -> None:
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-m", "u2sa_hw.cli", "echo", "NAV_POINT", "--count", "1", "--json",
                             "--timeout", "20"], env=services.env(), stdout=subprocess.PIPE, text=True)
    try:
        nav = t.NavigationPoint()
        nav.subsystem, nav.x = "vehicle", 4.5

        def published_and_seen() -> bool:
            bus.publish(ch.NAV_POINT, nav)
            return proc.poll() is not None

        wait_until(published_and_seen, timeout=20, interval=0.2, message="echo to print a message")
        obj = json.loads(proc.stdout.readline())
        assert obj["channel"] == "NAV_POINT" and obj["_type"] == "NavigationPoint" and obj["x"] == 4.5
    finally:
        proc.kill()
        proc.wait()
