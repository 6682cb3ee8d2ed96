"""Two hosts on one network: network namespaces joined by a veth pair, LCM with ttl=1 (DESIGN.md 9).

Host A runs a state estimator. Host B, with the same key, finds it with ``u2sa services``;
with another key or none, it is not answered, and A counts B's requests as forged or
unsigned. This is the laptop on the vehicle's WiFi of issue 11, made real.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import uuid
from pathlib import Path
from typing import Iterator

import pytest
from conftest import U2SA, wait_until

from u2sa_hw.bus_key import KEY_ENV, new_key, write_key
from u2sa_hw.udp_ports import private_udp_port

SERVICE = "state_estimator"


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, timeout=30)


class TwoHosts:
    """Namespaces ``a`` and ``b`` with 10.77.0.1 and 10.77.0.2 on a veth pair, multicast routed over it."""

    def __init__(self) -> None:
        tag = uuid.uuid4().hex[:6]
        self.ns = {"a": f"u2sa-a-{tag}", "b": f"u2sa-b-{tag}"}
        self.url = f"udpm://239.255.76.67:{private_udp_port()}?ttl=1"

    def __enter__(self) -> "TwoHosts":
        a, b = self.ns["a"], self.ns["b"]
        _ip("netns", "add", a)
        _ip("netns", "add", b)
        _ip("link", "add", "va", "netns", a, "type", "veth", "peer", "name", "vb", "netns", b)
        for name, dev, addr in ((a, "va", "10.77.0.1/24"), (b, "vb", "10.77.0.2/24")):
            _ip("-n", name, "link", "set", "lo", "up")
            _ip("-n", name, "addr", "add", addr, "dev", dev)
            _ip("-n", name, "link", "set", dev, "up")
            _ip("-n", name, "route", "add", "224.0.0.0/4", "dev", dev)
        return self

    def __exit__(self, *exc: object) -> None:
        for name in self.ns.values():
            subprocess.run(["ip", "netns", "del", name], capture_output=True, timeout=30)

    def command(self, host: str, *cmd: str) -> list[str]:
        """*cmd* run on *host*."""
        return ["ip", "netns", "exec", self.ns[host], *cmd]

    def env(self, key: Path | None, **extra: str) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items() if k != KEY_ENV}
        env.update({"U2SA_LCM_URL": self.url, "PYTHONUNBUFFERED": "1", **extra})
        if key is not None:
            env[KEY_ENV] = str(key)
        return env

    def services(self, host: str, key: Path | None, **extra: str) -> subprocess.CompletedProcess[str]:
        """``u2sa services --json`` on *host*."""
        return subprocess.run(self.command(host, *U2SA, "services", "--json", "--timeout", "1.5"),
                              env=self.env(key, **extra), capture_output=True, text=True, timeout=60)


def _cannot_run() -> str | None:
    if os.geteuid() != 0:
        return "network namespaces need root"
    if shutil.which("ip") is None:
        return "iproute2 (ip) is not installed"
    probe = subprocess.run(["ip", "netns", "add", f"u2sa-probe-{os.getpid()}"], capture_output=True)
    subprocess.run(["ip", "netns", "del", f"u2sa-probe-{os.getpid()}"], capture_output=True)
    return None if probe.returncode == 0 else f"ip netns add failed: {probe.stderr.decode().strip()}"


@pytest.fixture
def hosts(tmp_path: Path) -> Iterator[TwoHosts]:
    reason = _cannot_run()
    if reason:
        pytest.skip(reason)
    with TwoHosts() as two:
        yield two


def test_a_host_with_the_key_is_heard_and_one_without_is_not(hosts: TwoHosts, tmp_path: Path) -> None:
    key, other = tmp_path / "vehicle.key", tmp_path / "laptop.key"
    write_key(key, new_key(), group=None)
    write_key(other, new_key(), group=None)
    log = open(tmp_path / "a.stderr", "wb")
    service = subprocess.Popen(hosts.command("a", *U2SA, "service", SERVICE), cwd=tmp_path, env=hosts.env(key),
                               stdout=log, stderr=subprocess.STDOUT)
    try:
        def found_from_b() -> list[dict[str, object]]:
            r = hosts.services("b", key)
            return json.loads(r.stdout) if r.returncode == 0 else []

        listed = wait_until(found_from_b, timeout=60, message="host B to find the service on host A")
        assert [s["name"] for s in listed] == [SERVICE] and listed[0]["bus"].startswith("signed")

        wrong = hosts.services("b", other)
        assert wrong.returncode == 1 and "no service answered discovery" in wrong.stderr
        keyless = hosts.services("b", None, U2SA_BUS_SECURITY="open")
        assert keyless.returncode == 1

        def counted_on_a() -> str:
            r = hosts.services("a", key)
            rows = json.loads(r.stdout) if r.returncode == 0 else []
            text = rows[0]["rejected_by_channel"] if rows else ""
            return text if "U2SA_DISCOVERY: unsigned 1, forged 1" in text else ""

        wait_until(counted_on_a, timeout=30, message="host A to count B's forged and unsigned requests")
        assert service.poll() is None
    finally:
        service.terminate()
        try:
            service.wait(timeout=15)
        except subprocess.TimeoutExpired:
            service.kill()
            service.wait()
        log.close()



def test_a_single_board_vehicle_listens_on_loopback_only(hosts: TwoHosts, tmp_path: Path) -> None:
    """ttl=0 on host A: a stop from host B, signed with the vehicle's own key, never reaches it."""
    key = tmp_path / "vehicle.key"
    write_key(key, new_key(), group=None)
    local = hosts.url.replace("ttl=1", "ttl=0")
    log = open(tmp_path / "a.stderr", "wb")
    service = subprocess.Popen(hosts.command("a", *U2SA, "service", SERVICE), cwd=tmp_path,
                               env=hosts.env(key, U2SA_LCM_URL=local), stdout=log, stderr=subprocess.STDOUT)
    try:
        def found_on_a() -> list[dict[str, object]]:
            r = subprocess.run(hosts.command("a", *U2SA, "services", "--json"), env=hosts.env(key, U2SA_LCM_URL=local),
                               capture_output=True, text=True, timeout=60)
            return json.loads(r.stdout) if r.returncode == 0 else []

        first = wait_until(found_on_a, timeout=60, message="the service on A to answer on A")
        stop = subprocess.run(hosts.command("b", *U2SA, "stop", "--all", "--timeout", "1"), env=hosts.env(key),
                              capture_output=True, text=True, timeout=60)
        assert "Traceback" not in stop.stderr
        again = found_on_a()
        assert service.poll() is None and [s["pid"] for s in again] == [s["pid"] for s in first]
        assert not any("U2SA_STOP" in str(s["rejected_by_channel"]) for s in again)   # not even heard
    finally:
        service.terminate()
        try:
            service.wait(timeout=15)
        except subprocess.TimeoutExpired:
            service.kill()
            service.wait()
        log.close()


def test_a_multi_board_vehicle_listens_on_the_interface_its_profile_names(hosts: TwoHosts, tmp_path: Path) -> None:
    """ttl=1 and bus_interface = "lo" on host A: host B, with the key, on the veth, neither hears it nor is heard."""
    key = tmp_path / "vehicle.key"
    write_key(key, new_key(), group=None)
    _ip("-n", hosts.ns["a"], "link", "set", "lo", "multicast", "on")
    profile = tmp_path / "vehicle.toml"
    profile.write_text(f'[vehicle]\nname = "two-boards"\nlcm_url = "{hosts.url}"\nbus_interface = "lo"\n'
                       f'[services.{SERVICE}]\nkind = "{SERVICE}"\n')
    log = open(tmp_path / "a.stderr", "wb")
    service = subprocess.Popen(hosts.command("a", *U2SA, "service", SERVICE, "--vehicle", str(profile)),
                               cwd=tmp_path, env=hosts.env(key), stdout=log, stderr=subprocess.STDOUT)
    try:
        def found_on_a() -> list[dict[str, object]]:
            r = subprocess.run(hosts.command("a", *U2SA, "services", "--json", "--vehicle", str(profile)),
                               env=hosts.env(key), capture_output=True, text=True, timeout=60)
            return json.loads(r.stdout) if r.returncode == 0 else []

        first = wait_until(found_on_a, timeout=60, message="the service on A to answer on A's lo")
        from_b = hosts.services("b", key)          # the same key and URL, on the veth: not the vehicle's network
        assert from_b.returncode == 1 and "no service answered discovery" in from_b.stderr
        stop = subprocess.run(hosts.command("b", *U2SA, "stop", "--all", "--timeout", "1"), env=hosts.env(key),
                              capture_output=True, text=True, timeout=60)
        assert "Traceback" not in stop.stderr
        again = found_on_a()
        assert service.poll() is None and [s["pid"] for s in again] == [s["pid"] for s in first]
    finally:
        service.terminate()
        try:
            service.wait(timeout=15)
        except subprocess.TimeoutExpired:
            service.kill()
            service.wait()
        log.close()
