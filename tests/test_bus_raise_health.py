"""Every failsafe raise accepted outside the replay window or naming another system id is visible
(issue 23): in the receiving service's Health (``bus_raises_accepted``: per kind its count, the last
one's sender and age), in ``u2sa health`` (one-shot, ``--json`` and ``--watch``) and in ``u2sa
services`` (stderr line, ``--json``), not only in one WARN line of the service's log.

A real HSM (system id 1) on real multicast with the session's key hears a raise signed on a clock
a minute behind (stale) from one laptop, then from a second one (the count grows, the last sender
changes), and a raise naming system id 255 (foreign). The commands run as real ``u2sa`` processes.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Iterator

import pytest
from conftest import ServiceProcesses, wait_until
from supervision_helpers import hsm_profile

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.auth import BusAuth
from u2sa_hw.bus.client import BusClient
from u2sa_hw.service.bus_handlers import parse_raises
from u2sa_hw.bus.transport import Transport

BEHIND_S = 60   # three times the replay window


class HsmHealth:
    """The HSM's newest Health details, from the test's own client."""

    def __init__(self, bus: BusClient) -> None:
        self.details: dict[str, str] = {}
        bus.transport.subscribe(ch.HEALTH, t.Health, self._on_health)

    def _on_health(self, _c: str, msg: t.Health) -> None:
        if msg.name == "hsm":
            self.details = {kv.key: kv.value for kv in msg.details}

    def raises(self) -> dict[str, dict[str, Any]]:
        """``{kind: entry}`` of its ``bus_raises_accepted``."""
        return {e["kind"]: e for e in parse_raises(self.details.get("bus_raises_accepted", ""))}

    def wait_raises(self, kind: str, count: int, sender: str) -> dict[str, Any]:
        def seen() -> dict[str, Any] | None:
            entry = self.raises().get(kind)
            return entry if entry and entry["count"] == count and entry["last_sender"] == sender else None

        return wait_until(seen, timeout=30, message=f"{count} {kind} raise(s), the last from {sender}, in the HSM's "
                          f"health (bus_raises_accepted = {self.details.get('bus_raises_accepted')!r})")


@pytest.fixture
def hsm(tmp_path: Path, lcm_url: str, services: ServiceProcesses, bus: BusClient) -> Iterator[HsmHealth]:
    profile = hsm_profile(tmp_path, lcm_url, "", startup_grace_s=10.0)
    profile.write_text(profile.read_text().replace('name = "bench"\n', 'name = "bench"\nsystem_id = 1\n'))
    health = HsmHealth(bus)
    services.start("hsm", "--vehicle", str(profile))
    wait_until(lambda: "failsafe_sources" in health.details, timeout=30, message="the HSM reporting its health")
    yield health


def skewed_sender(url: str, name: str) -> Transport:
    """A signed transport whose clock is BEHIND_S behind and that never verifies (so never learns the vehicle's)."""
    tx = Transport(url, name=name, system_id=0)
    assert tx.auth is not None, "the test session signs (conftest sets a bus key)"
    tx.auth = BusAuth(tx.auth.keyring, wall_us=lambda: time.time_ns() // 1000 - BEHIND_S * 1_000_000)
    return tx


def raise_msg(source: str, system_id: int = 0) -> t.Failsafe:
    msg = t.Failsafe()
    msg.active, msg.reason = True, f"test {source}"
    msg.header.source, msg.header.system_id = source, system_id
    return msg


def test_accepted_stale_and_foreign_raises_show_in_health_u2sa_health_and_u2sa_services(
        services: ServiceProcesses, hsm: HsmHealth, bus: BusClient) -> None:
    assert "bus_raises_accepted" not in hsm.details, "nothing accepted yet: nothing to say"
    laptops = [skewed_sender(services.url, f"laptop{i}") for i in (1, 2)]
    try:
        # Health: per kind the count, the last sender, its age
        assert laptops[0].publish(ch.FAILSAFE, raise_msg("laptop1"))
        first = hsm.wait_raises("stale", 1, laptops[0].sender)
        assert first["channel"] == ch.FAILSAFE and first["last_age_s"] >= 0
        assert laptops[1].publish(ch.FAILSAFE, raise_msg("laptop2"))
        hsm.wait_raises("stale", 2, laptops[1].sender)
        assert bus.publish(ch.FAILSAFE, raise_msg("ground", system_id=255))
        hsm.wait_raises("foreign", 1, bus.transport.sender)
        assert hsm.raises()["stale"]["count"] == 2, "a foreign raise is not counted as stale"
        stale_sender, foreign_sender = laptops[1].sender, bus.transport.sender
    finally:
        for tx in laptops:
            tx.stop()

    # u2sa health: one line per kind, after the table
    done = services.cli("health")
    assert done.returncode == 0, done.stderr
    lines = [x for x in done.stdout.splitlines() if x.startswith("hsm: accepted")]
    assert len(lines) == 2, done.stdout
    foreign, stale = lines   # sorted by the transport's counter name: raise_foreign, raise_stale
    assert stale.startswith("hsm: accepted 2 failsafe raises outside the replay window (last "), stale
    assert f" s ago, from sender {stale_sender}): a raise always fails safe; a sender whose clock is behind, " \
        "or a replay" in stale, stale
    assert foreign.startswith("hsm: accepted 1 failsafe raise naming another system id (last "), foreign
    assert f"from sender {foreign_sender}): a raise always fails safe" in foreign, foreign

    done = services.cli("health", "--json")
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    got = {e["kind"]: e for e in report["raises_accepted"] if e["service"] == "hsm"}
    assert set(got) == {"stale", "foreign"}, report["raises_accepted"]
    assert (got["stale"]["count"], got["stale"]["last_sender"], got["stale"]["channel"]) == (2, stale_sender,
                                                                                           ch.FAILSAFE)
    assert (got["foreign"]["count"], got["foreign"]["last_sender"]) == (1, foreign_sender)
    assert all(isinstance(e["last_age_s"], float) and e["last_age_s"] >= 0 for e in got.values())

    # u2sa health --watch: the HSM's row says it in its reason column
    done = services.cli("health", "--watch", "--interval", "0.3", "--count", "4", timeout=60)
    assert done.returncode == 0, done.stderr
    rows = {line.split()[0]: line for line in done.stdout.strip().split("\n\n")[-1].splitlines()[2:]}
    assert "accepted 1 failsafe raise naming another system id (last " in rows.get("hsm", ""), done.stdout
    assert f"from sender {foreign_sender})" in rows["hsm"], rows["hsm"]

    # u2sa services: a line per kind on stderr, and in --json
    done = services.cli("services")
    assert done.returncode == 0, done.stderr
    said = [x for x in done.stderr.splitlines() if x.startswith("u2sa: hsm: accepted")]
    assert len(said) == 2, done.stderr
    assert said[1].startswith("u2sa: hsm: accepted 2 failsafe raises outside the replay window (last "), said
    assert f"from sender {stale_sender}): a raise always fails safe" in said[1], said
    done = services.cli("services", "--json")
    assert done.returncode == 0, done.stderr
    (row,) = [r for r in json.loads(done.stdout) if r["name"] == "hsm"]
    assert {(e["kind"], e["count"], e["last_sender"]) for e in row["raises_accepted"]} == {
        ("stale", 2, stale_sender), ("foreign", 1, foreign_sender)}, row


def test_a_service_that_accepted_no_raise_says_nothing_of_raises(services: ServiceProcesses, hsm: HsmHealth,
                                                                  bus: BusClient) -> None:
    """A raise in the window from this vehicle is no exception: no detail, no line, an empty list."""
    assert bus.publish(ch.FAILSAFE, raise_msg("operator-test", system_id=1))
    wait_until(lambda: "operator-test" in hsm.details.get("failsafe_sources", ""), timeout=30,
               message="the in-window raise held")
    assert "bus_raises_accepted" not in hsm.details, hsm.details
    done = services.cli("health", "--json")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["raises_accepted"] == []
    done = services.cli("services")
    assert done.returncode == 0, done.stderr
    assert "accepted" not in done.stderr, done.stderr
