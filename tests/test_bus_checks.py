"""``u2sa check`` warns where the bus would be heard beyond the vehicle (u2sa_hw/check/bus_checks.py).

ttl >= 1 without ``bus_interface`` is checked from the profile alone, through ``u2sa check``.
The ``lo`` warning depends on the machine: it runs in a new network namespace (whose ``lo``
has no MULTICAST flag, like a fresh host's) as the user nobody, then again with the flag on.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import uuid
from pathlib import Path

import pytest
from conftest import U2SA, unprivileged

from u2sa_hw.bus.listen import route_interface
from u2sa_hw.check.bus_checks import check_bus
from u2sa_hw.check.problem import Collector


def _check(profile: Path) -> list[dict[str, str]]:
    done = subprocess.run([*U2SA, "check", "--vehicle", str(profile), "--json"], capture_output=True, text=True,
                          timeout=120, cwd=profile.parent)
    assert "Traceback" not in done.stderr, done.stderr
    return json.loads(done.stdout)["problems"]


def test_ttl1_without_bus_interface_is_a_warning_naming_the_key_and_the_fix(tmp_path: Path) -> None:
    url = "udpm://239.255.76.67:7667?ttl=1"
    profile = tmp_path / "vehicle.toml"
    profile.write_text(f'[vehicle]\nname = "two-boards"\nlcm_url = "{url}"\n')
    (problem,) = [p for p in _check(profile) if p["key"] == "vehicle.bus_interface"]
    assert problem["severity"] == "warning" and "ttl >= 1 but no bus_interface" in problem["message"]
    assert f"(here {route_interface(url)})" in problem["message"] and 'bus_interface = "eth0"' in problem["fix"]
    profile.write_text(f'[vehicle]\nname = "two-boards"\nlcm_url = "{url}"\nbus_interface = "eth0"\n')
    assert not [p for p in _check(profile) if p["key"].startswith("vehicle.bus_interface")]
    out = Collector(profile)
    check_bus({"lcm_url": "udpm://239.255.76.67:7667?ttl=0"}, out)   # ttl=0 needs no interface (lo)
    assert not [p for p in out.problems if p.key == "vehicle.bus_interface"]


def test_route_interface_is_the_longest_prefix_route_of_the_group(tmp_path: Path) -> None:
    routes = tmp_path / "route"
    routes.write_text("Iface\tDestination\tGateway\tFlags\tRefCnt\tUse\tMetric\tMask\tMTU\tWindow\tIRTT\n"
                      "eth0\t00000000\t0102000A\t0003\t0\t0\t0\t00000000\t0\t0\t0\n"       # default
                      "wlan0\t000000E0\t00000000\t0001\t0\t0\t0\t000000F0\t0\t0\t0\n")     # 224.0.0.0/4
    assert route_interface("udpm://239.255.76.67:7667?ttl=0", route_file=str(routes)) == "wlan0"
    routes.write_text(routes.read_text().splitlines()[0] + "\n")
    assert route_interface("udpm://239.255.76.67:7667", route_file=str(routes)) == "the default route's interface"


CHECK_LO = """\
from pathlib import Path
from u2sa_hw.check.bus_checks import check_bus
from u2sa_hw.check.problem import Collector
out = Collector(Path("vehicle.toml"))
check_bus({}, out)
print("|".join(str(p) for p in out.problems))
"""


def test_ttl0_warns_when_lo_cannot_carry_multicast_and_the_check_is_not_root() -> None:
    if os.geteuid() != 0 or shutil.which("ip") is None or shutil.which("setpriv") is None:
        pytest.skip("needs root, ip and setpriv (a network namespace, and the user nobody in it)")
    ns = f"u2sa-chk-{uuid.uuid4().hex[:6]}"
    if subprocess.run(["ip", "netns", "add", ns], capture_output=True).returncode != 0:
        pytest.skip("ip netns add failed")
    try:
        subprocess.run(["ip", "-n", ns, "link", "set", "lo", "up"], check=True, timeout=30)
        nobody = ["ip", "netns", "exec", ns, *unprivileged([sys.executable, "-c", CHECK_LO])]

        def warned() -> str:
            return subprocess.run(nobody, capture_output=True, text=True, timeout=60, cwd="/").stdout.strip()

        text = warned()
        assert text.startswith("warning: vehicle.toml [vehicle.lcm_url]: ttl=0, but lo has no MULTICAST flag"), text
        assert "fix: sudo ip link set lo multicast on" in text
        subprocess.run(["ip", "-n", ns, "link", "set", "lo", "multicast", "on"], check=True, timeout=30)
        assert warned() == ""
    finally:
        subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=30)
