"""The udev rules parse, and the CAN rule brings the profile's interface up at its bitrate.

udev itself judges the rules: ``udevadm test`` runs in a private mount and network
namespace where /etc/udev/rules.d holds only our rules (the static ones of udev/ and the
65-u2sa-vehicle.rules that install generates from a profile), the system rule
directories are empty, and a veth interface called can0 stands in for a CAN adapter
(sysfs remounted for that namespace). udev reports every unparsable line as
``FILE:LINE message``; there must be none, and the RUN lines for can0 must carry the
profile's bitrate.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

from u2sa_hw.install_units import render_vehicle_rules
from u2sa_hw.vehicle import load_profile

UDEV_DIR = Path(__file__).resolve().parent.parent / "udev"

pytestmark = pytest.mark.skipif(
    shutil.which("udevadm") is None or os.geteuid() != 0 or shutil.which("unshare") is None,
    reason="needs udevadm (Debian: apt-get install udev), unshare and root")

SCRIPT = """\
set -e
mount --make-rprivate /
mount -t tmpfs tmpfs /run
for d in /lib/udev/rules.d /usr/lib/udev/rules.d /usr/local/lib/udev/rules.d; do
  if [ -d "$d" ]; then mount -t tmpfs tmpfs "$d"; fi
done
mkdir -p /run/udev/rules.d
mount --bind "$RULES" /etc/udev/rules.d
mount --bind "$GROUP" /etc/group
ip link add can0 type veth peer name vpeer0
ip link add can1 type veth peer name vpeer1
mount -t sysfs sysfs /sys
echo "=== can0"
udevadm test --action=add /sys/class/net/can0 2>&1
echo "=== can1"
udevadm test --action=add /sys/class/net/can1 2>&1
"""


def run_udevadm(tmp_path: Path, rules: dict[str, str]) -> dict[str, str]:
    """udevadm test output for can0 and can1 with only *rules* installed."""
    rules_dir = tmp_path / "rules.d"
    rules_dir.mkdir()
    for name, text in rules.items():
        (rules_dir / name).write_text(text)
    group = tmp_path / "group"
    lines = Path("/etc/group").read_text().splitlines()
    have = {line.split(":")[0] for line in lines}
    lines += [f"{g}:x:{990 - i}:" for i, g in enumerate(("dialout", "i2c", "gpio")) if g not in have]
    group.write_text("\n".join(lines) + "\n")
    done = subprocess.run(["unshare", "--mount", "--net", "sh", "-c", SCRIPT], capture_output=True, text=True,
                          timeout=60, env={**os.environ, "RULES": str(rules_dir), "GROUP": str(group)})
    assert done.returncode == 0, done.stdout + done.stderr
    _, can0, can1 = done.stdout.split("=== can")
    return {"can0": can0, "can1": can1}


def our_rules(tmp_path: Path) -> dict[str, str]:
    profile = tmp_path / "vehicle.toml"
    profile.write_text("[vehicle]\nname = \"r\"\n[devices.gps]\n"
                       "usb = { vendor = \"1546\", product = \"01a7\", serial = \"GPS-1\", interface = \"00\" }\n"
                       "[devices.motors]\ncan = { channel = \"can0\", bitrate = 250000 }\n")
    rules = {p.name: p.read_text() for p in sorted(UDEV_DIR.glob("*.rules"))}
    rules["65-u2sa-vehicle.rules"] = render_vehicle_rules(load_profile(profile)).decode()
    return rules


def complaints(output: str) -> list[str]:
    """udev's parse complaints: lines 'FILE:LINE ...' about a rules file."""
    return [line for line in output.splitlines() if line.startswith("/etc/udev/rules.d/")]


def test_every_rules_file_parses_without_complaint(tmp_path: Path) -> None:
    rules = our_rules(tmp_path)
    out = run_udevadm(tmp_path, rules)["can0"]
    for name in rules:
        assert f"Reading rules file: /etc/udev/rules.d/{name}" in out, out
    assert complaints(out) == []


def test_can0_comes_up_at_the_profiles_bitrate_and_others_are_left_alone(tmp_path: Path) -> None:
    out = run_udevadm(tmp_path, our_rules(tmp_path))
    assert "run: '/sbin/ip link set can0 type can bitrate 250000 restart-ms 100'" in out["can0"], out["can0"]
    assert "run: '/sbin/ip link set can0 up'" in out["can0"]
    assert "run: '/sbin/ip link set can1" not in out["can1"]


def test_the_check_catches_a_broken_rule(tmp_path: Path) -> None:
    rules = our_rules(tmp_path)
    rules["66-u2sa-local.rules"] = 'SUBSYSTEM=="tty", ATTRS{idVendor}=="0403" SYMLINK+="u2sa/x"\nBOGUS=="1"\n'
    found = complaints(run_udevadm(tmp_path, rules)["can0"])
    assert any(line.startswith("/etc/udev/rules.d/66-u2sa-local.rules:") for line in found), found
