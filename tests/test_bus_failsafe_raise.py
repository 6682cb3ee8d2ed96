"""A failsafe raise is never lost to clock skew or to a system id (docs/security.md, docs/safety.md).

An HSM (a failsafe holder: it reports the sources it holds in its health and relays the
operator's failsafe) runs as its own process on real multicast with the session's key and
the system id 1. The operator's ``u2sa`` runs as another process whose wall clock is a
minute behind the vehicle's, as a laptop without NTP is: ``failsafe raise`` must hold the
failsafe and say who confirmed it, ``stop`` must be heard. Packets signed on a clock a
minute behind, without learning the vehicle's: a raise is held, a clear, a stop and a config
change are dropped as replays, and so is the same raise sent twice. A raise naming system id 255 (a ground station) is held; a
clear naming it is dropped as foreign. With nothing running, ``failsafe raise`` exits 1 and
says nothing confirmed it; ``stop nosuch`` says nothing answered; ``echo`` of a channel
never seen says so after its default timeout and names the channels heard.
"""

from __future__ import annotations

import subprocess
import sys
import time
import uuid
from pathlib import Path
from typing import Any, Iterator

import pytest
from conftest import ServiceProcesses, wait_until
from supervision_helpers import hsm_profile

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.auth import BusAuth
from u2sa_hw.bus.client import BusClient
from u2sa_hw.bus.transport import Transport

BEHIND_S = 60   # three times the replay window
# The u2sa command on a machine whose wall clock is BEHIND_S behind: time.time_ns is what signing reads.
SKEWED_CLI = (
    "import sys, time\n"
    "_real = time.time_ns\n"
    f"time.time_ns = lambda: _real() - {BEHIND_S} * 1_000_000_000\n"
    "from u2sa_hw.cli import main\n"
    "sys.exit(main(sys.argv[1:]))\n"
)


class Holder:
    """The HSM's newest health details and every Failsafe on the bus, from the test's own client."""

    def __init__(self, bus: BusClient) -> None:
        self.details: dict[str, str] = {}
        self.failsafes: list[t.Failsafe] = []
        bus.transport.subscribe(ch.HEALTH, t.Health, self._on_health)
        bus.transport.subscribe(ch.FAILSAFE, t.Failsafe, lambda _c, m: self.failsafes.append(m))

    def _on_health(self, _c: str, msg: t.Health) -> None:
        if msg.name == "hsm":
            self.details = {kv.key: kv.value for kv in msg.details}

    def holds(self) -> set[str]:
        return {s for s in self.details.get("failsafe_sources", "").split(",") if s}

    def wait_holds(self, predicate: Any, message: str) -> set[str]:
        wait_until(lambda: "failsafe_sources" in self.details and predicate(self.holds()), timeout=30,
                   message=f"{message} (the HSM holds {sorted(self.holds())})")
        return self.holds()


@pytest.fixture
def hsm(tmp_path: Path, lcm_url: str, services: ServiceProcesses, bus: BusClient) -> Iterator[tuple[Path, Holder]]:
    profile = hsm_profile(tmp_path, lcm_url, "", startup_grace_s=10.0)
    profile.write_text(profile.read_text().replace('name = "bench"\n', 'name = "bench"\nsystem_id = 1\n'))
    holder = Holder(bus)
    services.start("hsm", "--vehicle", str(profile))
    holder.wait_holds(lambda held: True, "the HSM reporting its health")
    yield profile, holder


def skewed_cli(services: ServiceProcesses, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", SKEWED_CLI, *args], cwd=services.workdir, env=services.env(),
                          capture_output=True, text=True, timeout=60)


def skewed_sender(url: str) -> Transport:
    """A signed transport whose clock is BEHIND_S behind and that never verifies (so never learns the vehicle's)."""
    tx = Transport(url, name="laptop", system_id=0)
    assert tx.auth is not None, "the test session signs (conftest sets a bus key)"
    tx.auth = BusAuth(tx.auth.keyring, wall_us=lambda: time.time_ns() // 1000 - BEHIND_S * 1_000_000)
    return tx


def failsafe(*, active: bool, source: str, system_id: int = 0, service: str = "") -> t.Failsafe:
    msg = t.Failsafe()
    msg.active, msg.reason, msg.service = active, f"test {source}", service
    msg.header.source, msg.header.system_id = source, system_id
    return msg


def test_the_operators_raise_from_a_laptop_a_minute_behind_is_held_and_confirmed(
        services: ServiceProcesses, hsm: tuple[Path, Holder]) -> None:
    _, holder = hsm
    raised = skewed_cli(services, "failsafe", "raise", "--reason", "swimmer")
    assert raised.returncode == 0, raised.stderr
    assert "confirmed by" in raised.stdout, raised.stdout
    holder.wait_holds(lambda held: "operator" in held, "the HSM holding the operator's failsafe")
    cleared = skewed_cli(services, "failsafe", "clear")
    assert cleared.returncode == 0, cleared.stderr
    holder.wait_holds(lambda held: "operator" not in held, "the clear (sent after the clock sync) heard")


def test_a_raise_signed_a_minute_behind_is_held_but_a_clear_stop_and_change_are_replays(
        services: ServiceProcesses, hsm: tuple[Path, Holder], bus: BusClient) -> None:
    _, holder = hsm
    laptop = skewed_sender(services.url)
    wire = Transport(services.url, name="wire", security="open")   # sends captured bytes as they are
    try:
        assert laptop.auth is not None
        raise_packet = laptop.auth.sign(ch.FAILSAFE, failsafe(active=True, source="laptop").encode())
        assert wire.publish_bytes(ch.FAILSAFE, raise_packet)
        holder.wait_holds(lambda held: "laptop" in held, "the stale raise held")
        assert wire.publish_bytes(ch.FAILSAFE, raise_packet)   # the same raise again: not above its last counter
        # the same sender, newer counters, still a minute behind: every other kind of message is a replay
        stop = t.StopCommand()
        stop.all = True
        change = t.ConfigChange()
        change.request_id, change.target, change.field, change.value = uuid.uuid4().hex, "hsm", "health_interval_s", "5"
        assert laptop.publish(ch.FAILSAFE, failsafe(active=False, source="laptop"))
        assert laptop.publish(ch.STOP, stop)
        assert laptop.publish(ch.CONFIG_CHANGE, change)
        wait_until(lambda: all(f"{c}: replayed {n}" in holder.details.get("bus_rejected", "")
                               for c, n in ((ch.FAILSAFE, 2), (ch.STOP, 1), (ch.CONFIG_CHANGE, 1))), timeout=30,
                   message=f"the three counted as replayed ({holder.details.get('bus_rejected')!r})")
        assert "laptop" in holder.holds(), "a clear outside the window must not lower the failsafe"
        assert bus.discover(timeout=1.0, name="hsm"), "the stale stop must not stop the HSM"
    finally:
        laptop.stop()
        wire.stop()
    # a clear from the vehicle's clock lowers it
    assert bus.publish(ch.FAILSAFE, failsafe(active=False, source="operator", service="laptop"))
    holder.wait_holds(lambda held: "laptop" not in held, "the in-window operator clear heard")


def test_a_raise_naming_another_system_id_is_held_but_its_clear_is_foreign(
        services: ServiceProcesses, hsm: tuple[Path, Holder], bus: BusClient) -> None:
    _, holder = hsm
    assert bus.publish(ch.FAILSAFE, failsafe(active=True, source="ground", system_id=255))
    holder.wait_holds(lambda held: "ground" in held, "the raise from system 255 held")
    assert bus.publish(ch.FAILSAFE, failsafe(active=False, source="ground", system_id=255))
    wait_until(lambda: f"{ch.FAILSAFE}: foreign 1" in holder.details.get("bus_rejected", ""), timeout=30,
               message=f"the foreign clear counted ({holder.details.get('bus_rejected')!r})")
    assert "ground" in holder.holds(), "another system's clear must not lower the failsafe"
    assert bus.publish(ch.FAILSAFE, failsafe(active=False, source="operator", service="ground", system_id=1))
    holder.wait_holds(lambda held: "ground" not in held, "this vehicle's operator clear heard")


def test_stop_from_a_laptop_a_minute_behind_is_heard(services: ServiceProcesses, hsm: tuple[Path, Holder]) -> None:
    stopped = skewed_cli(services, "stop", "hsm", "--timeout", "20")
    assert stopped.returncode == 0, stopped.stderr
    assert "stopped hsm" in stopped.stdout
    services.procs[0].wait(timeout=30)


def test_a_raise_nobody_confirms_exits_1_and_says_so(services: ServiceProcesses) -> None:
    r = services.cli("failsafe", "raise", "--timeout", "0.3")
    assert r.returncode == 1 and r.stderr.count("\n") == 1, r.stderr
    assert "failsafe raise NOT confirmed after 3 sends" in r.stderr and "the HSM did not relay it" in r.stderr
    assert "nothing signed with this bus key was heard" in r.stderr and "NOT safe" in r.stderr
    assert "every actuator neutral" not in r.stdout


def test_stop_of_a_service_nobody_runs_says_nothing_answered(services: ServiceProcesses) -> None:
    r = services.cli("stop", "nosuch")
    assert r.returncode == 1 and r.stderr.count("\n") == 1, r.stderr
    assert r.stderr.startswith("u2sa: nothing answered: no service 'nosuch' answered discovery"), r.stderr


def test_echo_of_a_channel_never_seen_says_so_and_names_what_was_heard(
        services: ServiceProcesses, hsm: tuple[Path, Holder]) -> None:
    r = services.cli("echo", "NO_SUCH_CHANNEL")   # the default timeout, not forever
    assert r.returncode == 1 and r.stderr.count("\n") == 1, r.stderr
    assert r.stderr.startswith("u2sa: no message on NO_SUCH_CHANNEL within 5 s; heard: "), r.stderr
    assert ch.HEALTH in r.stderr and "--wait" in r.stderr
