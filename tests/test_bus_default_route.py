"""A ``ttl`` >= 1 bus without ``bus_interface`` is visible, not quiet (issue 11 audit, docs/security.md).

LCM then joins the group on the default route's interface, which may be the WiFi: every host
there that has the key can command the vehicle. A multi-board profile may mean it, so the
service starts, but with the vehicle's key it logs a warning at start and its health carries
the line (``bus_listen``), which ``u2sa services`` prints. With a key of the run's own (what
``u2sa sim`` and the tests hand their services) no other host has the key: nothing is said.
Real processes over real multicast (ttl=1 on this machine's default route).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from conftest import ServiceProcesses, wait_until
from gpio_driver_harness import BusCollector

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.bus.key import KEY_ENV
from u2sa_hw.bus.listen import default_route_note, route_interface
from u2sa_hw.bus.udp_ports import private_lcm_url


def test_the_note_is_only_for_ttl_1_without_an_interface(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("U2SA_BUS_ANY_INTERFACE", raising=False)
    url = "udpm://239.255.76.67:7667?ttl=1"
    note = default_route_note(url, None)
    assert note.startswith(f"bus listens on {route_interface(url)}") and "without bus_interface" in note
    assert 'bus_interface = "eth0"' in note and "\n" not in note
    assert default_route_note(url, "eth0") == ""
    assert default_route_note("udpm://239.255.76.67:7667?ttl=0", None) == ""
    assert default_route_note("udpm://239.255.76.67:7667", None) == ""
    assert default_route_note("memq://", None) == ""
    monkeypatch.setenv("U2SA_BUS_ANY_INTERFACE", "1")      # the diagnosis switch ignores bus_interface: said
    assert "U2SA_BUS_ANY_INTERFACE is set" in default_route_note(url, "eth0")


def _profile(path: Path, url: str, name: str, bus_key: str | None) -> Path:
    key = f'bus_key = "{bus_key}"\n' if bus_key else ""
    path.mkdir()
    profile = path / "vehicle.toml"
    profile.write_text(f'[vehicle]\nname = "rover"\nlcm_url = "{url}"\n{key}log_dir = "logs"\n'
                       f'[services.{name}]\nkind = "state_estimator"\nsettings = {{ health_interval_s = 0.2 }}\n')
    return profile


def test_ttl_1_without_bus_interface_is_warned_and_in_health_with_the_vehicle_key_only(
        services: ServiceProcesses, tmp_path: Path) -> None:
    url = private_lcm_url(options="ttl=1")
    vehicle_key = os.environ[KEY_ENV]     # named by the profile: the vehicle's key (a ground station may hold it)
    with_vehicle_key = _profile(tmp_path / "vehicle", url, "est_vehicle", vehicle_key)
    with_run_key = _profile(tmp_path / "run", url, "est_run", None)   # only $U2SA_BUS_KEY_FILE: the run's own
    bus = BusClient(url)
    try:
        col = BusCollector(bus).listen(ch.HEALTH, t.Health)
        services.start("est_vehicle", "--vehicle", str(with_vehicle_key))
        services.start("est_run", "--vehicle", str(with_run_key))
        said = col.health_of("est_vehicle", lambda d: d.get("bus_listen"), timeout=30,
                             message="est_vehicle's health to say where its bus listens")
        line = said["bus_listen"]
        assert f"bus listens on {route_interface(url)}" in line and "ttl=1 without bus_interface" in line, line
        assert said["status"] == "ok"                  # said, not refused
        quiet = col.health_of("est_run", lambda d: True, timeout=30, message="est_run's health")
        assert "bus_listen" not in quiet, quiet

        log = wait_until(lambda: (p := tmp_path / "vehicle" / "logs" / "est_vehicle.log").exists() and p.read_text(),
                         timeout=10, message="est_vehicle's log")
        assert sum("without bus_interface" in x and "WARN" in x.upper() for x in log.splitlines()) == 1, log
        run_log = (tmp_path / "run" / "logs" / "est_run.log").read_text()
        assert "without bus_interface" not in run_log

        listed = services.cli("services", "--vehicle", str(with_vehicle_key))
        assert listed.returncode == 0, listed.stderr
        assert f"u2sa: est_vehicle: {line}" in listed.stderr
        assert "est_run:" not in listed.stderr
    finally:
        bus.close()
