"""The bus commands of ``u2sa`` against real LCM multicast: topics, pub --rate, echo, transport errors."""

from __future__ import annotations

import json
import socket
import subprocess
import threading
from pathlib import Path
from typing import Iterator

import pytest
from conftest import U2SA, ServiceProcesses, wait_until

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture
def nav_traffic(bus: BusClient) -> Iterator[None]:
    """NAV_POINT published about 50 times a second while the test runs."""
    stop = threading.Event()

    def publish() -> None:
        nav = t.NavigationPoint()
        nav.subsystem, nav.x = "vehicle", 1.0
        while not stop.wait(0.02):  # pacing of the traffic, not synchronisation
            bus.publish(ch.NAV_POINT, nav)

    thread = threading.Thread(target=publish, daemon=True)
    thread.start()
    yield
    stop.set()
    thread.join(5)


def test_topics_lists_channel_type_rate_and_bandwidth(services: ServiceProcesses, nav_traffic: None) -> None:
    r = services.cli("topics", "--duration", "1")
    assert r.returncode == 0, r.stderr
    header, *rows = r.stdout.splitlines()
    assert header.split() == ["CHANNEL", "TYPE", "RATE", "Hz", "BANDWIDTH"]
    row = next(line.split() for line in rows if line.startswith("NAV_POINT "))
    assert row[1] == "NavigationPoint" and float(row[2]) > 0 and float(row[3]) > 0 and row[4].endswith("B/s")

    r = services.cli("topics", "--duration", "1", "--json")
    assert r.returncode == 0, r.stderr
    nav = next(x for x in json.loads(r.stdout) if x["channel"] == "NAV_POINT")
    assert nav["type"] == "NavigationPoint" and nav["messages"] >= 1
    assert nav["rate_hz"] > 0 and nav["bandwidth_Bps"] > 0


def test_pub_with_rate_and_count_publishes_n_stamped_messages(services: ServiceProcesses, bus: BusClient) -> None:
    got: list[t.PercentageCommand] = []
    bus.transport.subscribe(ch.ACTUATOR_CMD, t.ActuatorCommand, lambda _c, m: got.append(m))
    r = services.cli("pub", "ACTUATOR_CMD", "PercentageCommand", "base.actuator_name=left", "percentage=20",
                     "--rate", "50", "--count", "5")
    assert r.returncode == 0, r.stderr
    wait_until(lambda: len(got) >= 5, message="five commands")
    assert all(isinstance(m, t.PercentageCommand) and m.percentage == 20.0 for m in got)
    assert all(m.base.actuator_name == "left" for m in got)
    assert [m.base.header.sequence for m in got] == [1, 2, 3, 4, 5]
    assert len({m.base.header.source for m in got}) == 1


def _echo_one_nav_point(services: ServiceProcesses, bus: BusClient, *args: str) -> str:
    """Run ``u2sa echo NAV_POINT --count 1 ARGS`` while a NavigationPoint is published; its stdout."""
    proc = subprocess.Popen([*U2SA, "echo", "NAV_POINT", "--count", "1", "--timeout", "20", *args],
                            env=services.env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        nav = t.NavigationPoint()
        nav.subsystem, nav.x = "vehicle", 4.5

        def published_and_seen() -> bool:
            bus.publish(ch.NAV_POINT, nav)
            return proc.poll() is not None

        wait_until(published_and_seen, timeout=20, interval=0.2, message="echo to print a message")
        out, err = proc.communicate(timeout=10)
        assert proc.returncode == 0, err
        return out
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_echo_text_mode_prints_the_type_and_each_field(services: ServiceProcesses, bus: BusClient) -> None:
    lines = _echo_one_nav_point(services, bus).splitlines()
    assert lines[0] == "--- NAV_POINT NavigationPoint"
    assert "  x: 4.5" in lines and "  subsystem: vehicle" in lines
    assert any(line.startswith("  header.timestamp_us: ") for line in lines)


def test_echo_json_prints_fields_by_name(services: ServiceProcesses, bus: BusClient) -> None:
    obj = json.loads(_echo_one_nav_point(services, bus, "--json").splitlines()[0])
    assert obj["channel"] == "NAV_POINT" and obj["_type"] == "NavigationPoint" and obj["x"] == 4.5


def test_echo_with_timeout_and_no_traffic_is_one_line(services: ServiceProcesses) -> None:
    r = services.cli("echo", "NAV_POINT", "--timeout", "0.3")
    assert r.returncode == 1 and r.stderr == "u2sa: no message on NAV_POINT within 0.3 s\n"


def test_services_without_multicast_is_one_line_with_the_fix() -> None:
    if subprocess.run(["unshare", "-rn", "true"], capture_output=True).returncode != 0:
        pytest.skip("unshare -rn (a network namespace without routes) is not allowed here")
    r = subprocess.run(["unshare", "-rn", *U2SA, "services"], capture_output=True, text=True, timeout=60, cwd=REPO)
    assert r.returncode == 1 and r.stderr.count("\n") == 1, r.stderr
    assert r.stderr.startswith("u2sa: cannot open LCM at udpm://") and "multicast does not work" in r.stderr
    assert "ip route add 224.0.0.0/4 dev lo" in r.stderr


def test_a_port_held_by_another_program_is_one_line_naming_it(services: ServiceProcesses) -> None:
    port = int(services.url.split("?", 1)[0].rsplit(":", 1)[1])
    holder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    holder.bind(("0.0.0.0", port))  # without SO_REUSEADDR, as some programs do
    try:
        for args in (("services", "--timeout", "0.3"), ("param", "list", "x", "--timeout", "0.3"), ("echo", "X")):
            r = services.cli(*args)
            assert r.returncode == 1 and r.stderr.count("\n") == 1, (args, r.stderr)
            assert "Address already in use" in r.stderr and f"holds UDP port {port}" in r.stderr, r.stderr
    finally:
        holder.close()


def test_help_of_param_set_says_how_text_values_are_read(services: ServiceProcesses) -> None:
    r = services.cli("param", "--help")
    text = " ".join(r.stdout.split())
    assert r.returncode == 0 and "For a text field a quoted string gives its contents" in text
    assert "log_level" in text
    r = services.cli("service", "--help")
    text = " ".join(r.stdout.split())
    assert "Log level: --log-level, else the service's log_level config field" in text

