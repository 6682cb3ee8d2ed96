"""The udev rules parse, the rule generated from a device address names /dev/u2sa/NAME for the
right device, and the CAN rule brings the address's interface up at its bitrate.

Two judges. Everywhere: a Python parser of udev(7)'s syntax (tests/udev_rules_syntax.py)
checks every rules file -- the static ones of udev/ and the 65-u2sa-vehicle.rules that
install generates from a profile -- and applies the generated SYMLINK rule to device
descriptions. Where ``udevadm`` exists and we are root (CI installs udev when it runs as
root; this development machine has none): udev itself, with ``udevadm test`` in a private
mount and network namespace where /etc/udev/rules.d holds only our rules, the system rule
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
from udev_rules_syntax import RulesSyntaxError, matches, parse_rules

from u2sa_hw.profile.devices import profile_devices
from u2sa_hw.install.udev import plan_devices, render_rules
from u2sa_hw.profile.loader import load_profile

UDEV_DIR = Path(__file__).resolve().parent.parent / "udev"

needs_udevadm = pytest.mark.skipif(
    shutil.which("udevadm") is None or os.geteuid() != 0 or shutil.which("unshare") is None,
    reason="needs udevadm (Debian: apt-get install udev), unshare and root; the Python syntax check ran instead")

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


PROFILE = """\
[vehicle]
name = "r"

[services.gps]
kind = "gps_nmea"

[devices.gps]
address = "serial:///dev/u2sa/gps?baud=9600&usb=1546:01A7&serial=GPS-1"

[services.compass]
kind = "compass_serial"

[devices.compass]
address = "serial:///dev/u2sa/compass?baud=4800&serial=FT4XYZ"

[services.motors]
kind = "odrive_can"

[devices.motors]
address = "can://socketcan/can0?bitrate=250000"
"""


def our_rules(tmp_path: Path) -> dict[str, str]:
    """The static rules and the vehicle rules install generates from PROFILE's device addresses."""
    profile = tmp_path / "vehicle.toml"
    profile.write_text(PROFILE)
    plan = plan_devices(profile_devices(load_profile(profile)), profile_path=profile)
    rules = {p.name: p.read_text() for p in sorted(UDEV_DIR.glob("*.rules"))}
    rules["65-u2sa-vehicle.rules"] = render_rules(plan, profile="/etc/u2sa/vehicle.toml").decode()
    return rules


def complaints(output: str) -> list[str]:
    """udev's parse complaints: lines 'FILE:LINE ...' about a rules file."""
    return [line for line in output.splitlines() if line.startswith("/etc/udev/rules.d/")]


@needs_udevadm
def test_every_rules_file_parses_without_complaint(tmp_path: Path) -> None:
    rules = our_rules(tmp_path)
    out = run_udevadm(tmp_path, rules)["can0"]
    for name in rules:
        assert f"Reading rules file: /etc/udev/rules.d/{name}" in out, out
    assert complaints(out) == []


@needs_udevadm
def test_can0_comes_up_at_the_profiles_bitrate_and_others_are_left_alone(tmp_path: Path) -> None:
    out = run_udevadm(tmp_path, our_rules(tmp_path))
    assert "run: '/sbin/ip link set can0 type can bitrate 250000 restart-ms 100'" in out["can0"], out["can0"]
    assert "run: '/sbin/ip link set can0 up'" in out["can0"]
    assert "run: '/sbin/ip link set can1" not in out["can1"]


@needs_udevadm
def test_the_check_catches_a_broken_rule(tmp_path: Path) -> None:
    rules = our_rules(tmp_path)
    rules["66-u2sa-local.rules"] = 'SUBSYSTEM=="tty", ATTRS{idVendor}=="0403" SYMLINK+="u2sa/x"\nBOGUS=="1"\n'
    found = complaints(run_udevadm(tmp_path, rules)["can0"])
    assert any(line.startswith("/etc/udev/rules.d/66-u2sa-local.rules:") for line in found), found


# ---------------------------------------------------------------- without udevadm -----------------
def test_every_rules_file_has_valid_syntax(tmp_path: Path) -> None:
    rules = our_rules(tmp_path)
    assert set(rules) == {"60-u2sa-permissions.rules", "70-u2sa-can.rules", "65-u2sa-vehicle.rules"}
    parsed = {name: parse_rules(text, file=name) for name, text in rules.items()}
    assert len(parsed["60-u2sa-permissions.rules"]) == 4 and len(parsed["70-u2sa-can.rules"]) == 1
    # the continued lines were joined into whole rules
    pwm_change = parsed["60-u2sa-permissions.rules"][3]
    assert [e.key for e in pwm_change.expressions] == ["SUBSYSTEM", "KERNEL", "ACTION", "ENV", "RUN"]
    assert [e.value for e in parsed["70-u2sa-can.rules"][0].assignments("RUN")] == [
        "/sbin/ip link set $name type can bitrate $env{U2SA_CAN_BITRATE} restart-ms 100", "/sbin/ip link set $name up"]


def test_the_generated_rule_links_u2sa_name_to_that_adapter_only(tmp_path: Path) -> None:
    rules = parse_rules(our_rules(tmp_path)["65-u2sa-vehicle.rules"], file="65-u2sa-vehicle.rules")
    links = [r for r in rules if r.assignments("SYMLINK")]
    assert len(links) == 2
    compass, gps = links   # sorted by device name
    assert [(e.op, e.value) for e in gps.assignments("SYMLINK")] == [("+=", "u2sa/gps")]   # /dev/u2sa/gps
    assert [e.value for e in gps.assignments("GROUP")] == ["dialout"]
    assert [e.value for e in gps.assignments("MODE")] == ["0660"]
    adapter = {"SUBSYSTEM": "tty", "ATTRS": {"idVendor": "1546", "idProduct": "01a7", "serial": "GPS-1"}}
    assert matches(gps, adapter)
    for other in ({**adapter, "ATTRS": {**adapter["ATTRS"], "serial": "GPS-2"}},          # a second receiver
                  {**adapter, "ATTRS": {**adapter["ATTRS"], "idVendor": "0403"}},
                  {**adapter, "SUBSYSTEM": "usb"}):
        assert not matches(gps, other), other
    # A serial number alone identifies the adapter (whatever its make): /dev/u2sa/compass.
    assert [e.value for e in compass.assignments("SYMLINK")] == ["u2sa/compass"]
    ftdi = {"SUBSYSTEM": "tty", "ATTRS": {"idVendor": "0403", "idProduct": "6001", "serial": "FT4XYZ"}}
    assert matches(compass, ftdi) and not matches(compass, {**ftdi, "ATTRS": {**ftdi["ATTRS"], "serial": "X"}})
    can = next(r for r in rules if any(e.key == "ENV" for e in r.expressions))
    assert matches(can, {"SUBSYSTEM": "net", "KERNEL": "can0"}) and not matches(can, {"SUBSYSTEM": "net",
                                                                                       "KERNEL": "can1"})
    assert [(e.attribute, e.value) for e in can.assignments("ENV")] == [("U2SA_CAN_BITRATE", "250000")]


@pytest.mark.parametrize(("line", "problem"), [
    ('BOGUS=="1"', "unknown key BOGUS"),
    ('SUBSYSTEM=="tty", GROUP+="dialout"', "GROUP does not take the operator +="),
    ('ACTION="add", RUN+="/bin/true"', "ACTION does not take the operator ="),
    ('SUBSYSTEM=="tty", MODE=0660', "MODE: the value must be in double quotes"),
    ('SUBSYSTEM=="tty, GROUP="dialout"', "expected ',' after SUBSYSTEM"),
    ('SUBSYSTEM=="tty", SYMLINK+="u2sa/x', "SYMLINK: unterminated quoted value"),
    ('SUBSYSTEM=="tty" SYMLINK+="u2sa/x"', "expected ',' after SUBSYSTEM"),
    ('ATTR=="1"', "ATTR needs an {attribute}"),
    ('KERNEL{x}=="can0"', "KERNEL takes no {attribute}"),
    ('IMPORT{shell}="x"', "the type must be one of"),
    ('SUBSYSTEM=="net", RUN+="/sbin/ip link set $nmae up"', "RUN: unknown substitution $nmae"),
    ('SUBSYSTEM=="tty", MODE="rw"', 'MODE="rw" is not an octal mode'),
    ('SUBSYSTEM=="tty", SYMLINK+="/dev/u2sa/x"', "must be relative to /dev"),
    ('SUBSYSTEM=="tty",', "a rule ends with ','"),
    ('SUBSYSTEM=="tty", \\', "continues"),
])
def test_the_syntax_check_refuses_what_udev_refuses(line: str, problem: str) -> None:
    text = f"# local rules\nSUBSYSTEM==\"tty\", GROUP=\"dialout\"\n{line}\n"
    with pytest.raises(RulesSyntaxError) as info:
        parse_rules(text, file="66-u2sa-local.rules")
    assert len(info.value.problems) == 1
    assert info.value.problems[0].startswith("66-u2sa-local.rules:3: ") and problem in info.value.problems[0]
