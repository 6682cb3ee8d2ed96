"""`u2sa health` says why a service is not ok, from real service processes under `u2sa run` and an HSM."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path
from typing import Any

from conftest import wait_until
from supervision_helpers import Watch, hsm_profile, launch  # noqa: F401 - launch is a fixture

from u2sa_hw import channels as ch
from u2sa_hw import messages as m
from u2sa_hw.bus.client import BusClient
from u2sa_hw.service.health import health_reason, join_reasons
from u2sa_hw.launcher.children import u2sa_command


def u2sa(tmp: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*u2sa_command(), *args], cwd=tmp, capture_output=True, text=True, timeout=60,
                          env=dict(os.environ))


def test_reason_joins_each_part_once() -> None:
    port = "gps (/dev/u2sa/gps): cannot open; fix: check the cable"
    assert health_reason({"degraded_reason": "port down", "port_error": port}) == f"port down; {port}"
    assert health_reason({"silent_sensors": "gps,imu"}, "") == "silent sensors: gps,imu"
    assert health_reason({"pan.last_error": "went away", "winch.last_error": ""}) == "pan: went away"
    assert health_reason({"fix": "1"}, "") == ""
    assert join_reasons("no data for 2 s", "", "no data for 2 s") == "no data for 2 s"
    assert join_reasons("port down", "port down; fix: plug it in") == "port down; fix: plug it in"


def test_health_names_the_silent_sensor_and_the_missing_device_with_its_fix(
        tmp_path: Path, lcm_url: str, bus: BusClient, launch: Any) -> None:
    missing = tmp_path / "dev" / "gps"
    vehicle = hsm_profile(tmp_path, lcm_url, (
        '[services.gps]\nkind = "gps_nmea"\n'
        'settings = { health_interval_s = 0.2 }\n'
        f'[devices.gps]\naddress = "serial://{missing}?baud=9600"\n'
        # Data expected on STATE_INFO: a GPS that cannot open its port is restarted, then failed.
        '[services.gps.supervision]\ndata_channel = "STATE_INFO"\nstale_after_s = 1.0\nstartup_grace_s = 1.0\n\n'
        '[services.est]\nkind = "state_estimator"\nsettings = { health_interval_s = 0.2, sensor_timeout_s = 0.5 }\n'),
        startup_grace_s=10.0)
    watch = Watch(bus)
    launch(vehicle, "--grace", "3", "--watchdog", "0")
    wait_until(lambda: (s := watch.service_state("est")) and s.state == "ok", timeout=30,
               message="the HSM to see est ok")

    def compass_heard() -> bool:   # a compass that speaks, then falls silent
        heading = m.StateInformation().set(psi=0.5)
        heading.sensor_name, heading.reference_frame = "compass", "NED"
        bus.publish(ch.STATE_INFO, heading)
        return "compass" in watch.details.get("est", {}).get("sensors", "")

    wait_until(compass_heard, timeout=20, message="the estimator to know the compass")
    wait_until(lambda: (s := watch.service_state("est")) and s.state == "degraded", timeout=20,
               message="the estimator degraded by its silent compass")
    wait_until(lambda: (s := watch.service_state("gps")) and s.state == "failed", timeout=60,
               message="the GPS without its device restarted until failed")

    report = json.loads(u2sa(tmp_path, "health", "--vehicle", str(vehicle), "--json").stdout)
    rows = {s["name"]: s for s in report["services"]}
    assert rows["est"]["state"] == "degraded"
    assert "silent sensor compass: no message for" in rows["est"]["reason"]
    gps = rows["gps"]
    assert gps["state"] == "failed" and "no data on STATE_INFO" in gps["reason"]
    # What the driver said before it was given up on: the device, the error and the fix.
    assert f"gps ({missing}): cannot open" in gps["reason"] and "fix:" in gps["reason"]
    # The HSM's own message carries the driver's words too (other tools read SystemHealth).
    assert f"gps ({missing}): cannot open" in watch.service_state("gps").last_error

    table = u2sa(tmp_path, "health", "--vehicle", str(vehicle))
    assert table.returncode == 0, table.stderr
    lines = {line.split()[0]: line for line in table.stdout.splitlines()[2:] if line.strip()}
    assert "silent sensor compass" in lines["est"]
    assert "failed" in lines["gps"] and f"{missing}" in lines["gps"] and "fix:" in lines["gps"]
