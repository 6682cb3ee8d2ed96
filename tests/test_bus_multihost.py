"""Two hosts on one network: network namespaces joined by a veth pair, LCM with ttl=1 (DESIGN.md 9).

Host A runs a state estimator. Host B, with the same key, finds it with ``u2sa services``;
with another key or none, it is not answered, and A counts B's requests as forged or
unsigned. This is the laptop on the vehicle's WiFi of issue 11, made real.

Where a vehicle listens (docs/security.md): host B publishes signed stops straight at a
service of A that should listen on ``lo`` only. A listener of A's own on the veth proves each
stop reached host A; a discovery request that the service answers afterwards (its socket
queue is first in, first out) proves the service never got it. A new namespace's ``lo`` has
no MULTICAST flag, like a fresh Linux host's: a service run as root sets it; one that may
not (run as ``nobody``) refuses to start with the vehicle's key, and with a run's own key
starts, says where it listens, and obeys a holder of that key on the LAN.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import uuid
from pathlib import Path
from typing import Iterator

import pytest
from conftest import U2SA, unprivileged, wait_until

from u2sa_hw.bus.key import KEY_ENV, new_key, write_key
from u2sa_hw.bus.udp_ports import private_udp_port

SERVICE = "state_estimator"
IFF_MULTICAST = 0x1000

# Host B, with the key: a signed StopCommand(all) every 0.2 s (a rate, not a wait) until killed.
STOPS = """\
import sys, time
from u2sa_hw import channels as ch, lcmtypes as t
from u2sa_hw.bus.transport import Transport

tx = Transport(sys.argv[1], name="laptop")
stop = t.StopCommand()
stop.all, stop.header.source = True, "laptop"
while True:
    tx.publish(ch.STOP, stop)
    print("sent", flush=True)
    time.sleep(0.2)
"""


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

    def lo_multicast(self, host: str) -> bool:
        """True when *host*'s ``lo`` has its MULTICAST flag."""
        out = subprocess.run(["ip", "netns", "exec", self.ns[host], "cat", "/sys/class/net/lo/flags"],
                             capture_output=True, text=True, check=True, timeout=30).stdout
        return bool(int(out, 16) & IFF_MULTICAST)


class Stops:
    """Host B sending signed stops at the group; host A hearing them on its veth (not where a vehicle listens)."""

    def __init__(self, hosts: TwoHosts, key: Path, workdir: Path) -> None:
        self.out = workdir / "heard-on-a.out"
        ttl1 = hosts.url.replace("ttl=0", "ttl=1")
        with open(self.out, "wb") as out:   # LCM's default interface on A: the veth, where B's packets arrive
            self.heard = subprocess.Popen(hosts.command("a", *U2SA, "echo", "U2SA_STOP", "--wait", "--count", "1"),
                                          env=hosts.env(key, U2SA_LCM_URL=ttl1, U2SA_BUS_ANY_INTERFACE="1"),
                                          stdout=out, stderr=subprocess.STDOUT)
        self.sender = subprocess.Popen(hosts.command("b", sys.executable, "-c", STOPS, ttl1), env=hosts.env(key),
                                       stdout=subprocess.PIPE, stderr=subprocess.STDOUT)

    def wait_heard_on_a(self) -> None:
        """Until host A's network stack delivered one of B's signed stops (to the listener on its veth)."""
        wait_until(lambda: "--- U2SA_STOP StopCommand" in self.out.read_text(errors="replace"), timeout=60,
                   message="host A to receive a signed stop from host B on its veth")

    def close(self) -> None:
        for proc in (self.sender, self.heard):
            _end(proc)


def _end(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.terminate()
    try:
        proc.wait(timeout=15)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def _shared_dir() -> Path:
    """A directory the user nobody may read and write (pytest's tmp_path is root's only)."""
    path = Path(tempfile.mkdtemp(prefix="u2sa-mh-", dir="/tmp"))
    path.chmod(0o777)
    return path


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
    """ttl=0 on host A, run as root: lo gets its MULTICAST flag, and B's signed stops never reach the service."""
    key = tmp_path / "vehicle.key"
    write_key(key, new_key(), group=None)
    local = hosts.url.replace("ttl=1", "ttl=0")
    assert not hosts.lo_multicast("a"), "a new namespace's lo has no MULTICAST flag, like a fresh host's"
    log = open(tmp_path / "a.stderr", "wb")
    service = subprocess.Popen(hosts.command("a", *U2SA, "service", SERVICE), cwd=tmp_path,
                               env=hosts.env(key, U2SA_LCM_URL=local), stdout=log, stderr=subprocess.STDOUT)
    stops: Stops | None = None
    try:
        def found_on_a() -> list[dict[str, object]]:
            r = subprocess.run(hosts.command("a", *U2SA, "services", "--json"), env=hosts.env(key, U2SA_LCM_URL=local),
                               capture_output=True, text=True, timeout=60)
            return json.loads(r.stdout) if r.returncode == 0 else []

        first = wait_until(found_on_a, timeout=60, message="the service on A to answer on A")
        assert hosts.lo_multicast("a"), "the service, run as root, set lo's MULTICAST flag"
        assert first[0]["listen"] == "", first
        stops = Stops(hosts, key, tmp_path)
        stops.wait_heard_on_a()
        again = found_on_a()    # asked after the stop reached host A: a service that got it answers no more
        assert service.poll() is None and [s["pid"] for s in again] == [s["pid"] for s in first]
        assert not any("U2SA_STOP" in str(s["rejected_by_channel"]) for s in again)   # not even heard
    finally:
        if stops is not None:
            stops.close()
        _end(service)
        log.close()
    assert "stop requested over the bus" not in (tmp_path / "a.stderr").read_text()


def test_without_lo_multicast_a_service_with_the_vehicles_key_refuses_to_start(hosts: TwoHosts) -> None:
    """ttl=0 on host A, lo without its flag, a service that may not set it (nobody): exit 3 with the line and fix."""
    shared = _shared_dir()
    try:
        key = shared / "vehicle.key"
        write_key(key, new_key(), group=None)
        key.chmod(0o644)
        local = hosts.url.replace("ttl=1", "ttl=0")
        profile = shared / "vehicle.toml"
        profile.write_text(f'[vehicle]\nname = "rover"\nlcm_url = "{local}"\nbus_key = "{key}"\nlog_dir = "logs"\n'
                           f'[services.{SERVICE}]\nkind = "{SERVICE}"\n')
        profile.chmod(0o644)       # for nobody, whatever the umask
        env = hosts.env(None)      # the profile's key: the vehicle's, which a ground station may hold too
        as_nobody = unprivileged([*U2SA, "service", SERVICE, "--vehicle", str(profile)])
        done = subprocess.run(hosts.command("a", *as_nobody), cwd=shared, env=env, capture_output=True, text=True,
                              timeout=120)
        assert done.returncode == 3, done.stdout + done.stderr
        line = next(x for x in (done.stdout + done.stderr).splitlines() if "refusing to start" in x)
        assert f"refusing to start '{SERVICE}': bus listens on va, not lo: sudo ip link set lo multicast on" in line
        assert str(key) in line and "Traceback" not in done.stderr
        assert not hosts.lo_multicast("a")
    finally:
        shutil.rmtree(shared, ignore_errors=True)


def test_without_lo_multicast_a_run_key_service_starts_and_says_where_it_listens(hosts: TwoHosts) -> None:
    """The same with a key of the run's own ($U2SA_BUS_KEY_FILE): it starts, health says it listens on va,
    and a holder of that key on the LAN is obeyed (what docs/security.md says of this case)."""
    shared = _shared_dir()
    key = shared / "run.key"
    write_key(key, new_key(), group=None)
    key.chmod(0o644)
    local = hosts.url.replace("ttl=1", "ttl=0")
    log = open(shared / "a.stderr", "wb")
    service = subprocess.Popen(hosts.command("a", *unprivileged([*U2SA, "service", SERVICE])), cwd=shared,
                               env=hosts.env(key, U2SA_LCM_URL=local), stdout=log, stderr=subprocess.STDOUT)
    stops: Stops | None = None
    try:
        def found_on_a() -> list[dict[str, object]]:
            r = subprocess.run(hosts.command("a", *unprivileged([*U2SA, "services", "--json"])), cwd=shared,
                               env=hosts.env(key, U2SA_LCM_URL=local), capture_output=True, text=True, timeout=60)
            return json.loads(r.stdout) if r.returncode == 0 else []

        def listed_with_listen() -> list[dict[str, object]]:
            rows = found_on_a()
            return rows if rows and rows[0]["listen"] else []

        first = wait_until(listed_with_listen, timeout=60,
                           message="the service on A to answer, saying where it listens")
        assert str(first[0]["listen"]).startswith("bus listens on va, not lo: sudo ip link set lo multicast on")
        table = subprocess.run(hosts.command("a", *unprivileged([*U2SA, "services"])), cwd=shared,
                               env=hosts.env(key, U2SA_LCM_URL=local), capture_output=True, text=True, timeout=60)
        assert f"u2sa: {SERVICE}: bus listens on va, not lo" in table.stderr, table.stderr
        assert not hosts.lo_multicast("a")
        stops = Stops(hosts, key, shared)
        assert service.wait(timeout=60) == 0, "B's signed stop, heard on the veth, stopped it"
    finally:
        if stops is not None:
            stops.close()
        _end(service)
        log.close()
        shutil.rmtree(shared, ignore_errors=True)


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
    stops: Stops | None = None
    try:
        def found_on_a() -> list[dict[str, object]]:
            r = subprocess.run(hosts.command("a", *U2SA, "services", "--json", "--vehicle", str(profile)),
                               env=hosts.env(key), capture_output=True, text=True, timeout=60)
            return json.loads(r.stdout) if r.returncode == 0 else []

        first = wait_until(found_on_a, timeout=60, message="the service on A to answer on A's lo")
        from_b = hosts.services("b", key)          # the same key and URL, on the veth: not the vehicle's network
        assert from_b.returncode == 1 and "no service answered discovery" in from_b.stderr
        stops = Stops(hosts, key, tmp_path)
        stops.wait_heard_on_a()
        again = found_on_a()
        assert service.poll() is None and [s["pid"] for s in again] == [s["pid"] for s in first]
        assert not any("U2SA_STOP" in str(s["rejected_by_channel"]) for s in again)
    finally:
        if stops is not None:
            stops.close()
        _end(service)
        log.close()
