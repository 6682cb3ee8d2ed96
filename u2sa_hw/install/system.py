"""The system side of ``u2sa install``: users and groups, sysctl and tmpfiles, systemd and udev reloads.

Users and groups are made with ``groupadd``/``useradd --system`` (``--prefix ROOT`` when
staging into a tree that has an ``etc/passwd``; a tree without one gets only the
sysusers.d file ``/etc/sysusers.d/u2sa.conf``, from which ``systemd-sysusers`` creates
them on the target's first boot).

The venv under ``/opt/u2sa/venv`` is made by :mod:`u2sa_hw.install.venv`.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

from u2sa_hw.bus.pilot import PILOT_GROUP
from u2sa_hw.install.files import InstallTree

SERVICE_USER = "u2sa"
DEVICE_GROUPS = ("dialout", "i2c", "gpio")
# Groups install makes that the service user is NOT a member of: u2sa-pilot (the group of
# /etc/u2sa/pilot.key) is given to the RC mux's unit alone, by its drop-in 32-pilot-key.conf.
UNIT_ONLY_GROUPS = (PILOT_GROUP,)


class InstallError(RuntimeError):
    """Install cannot go on; the message names what failed and the fix."""


def run_tool(cmd: list[str], *, what: str, env: dict[str, str] | None = None, cwd: Path | None = None) -> str:
    """Run *cmd* (at most 10 min) and return its output; InstallError naming *what* when it is missing or fails."""
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env, cwd=cwd)
    except FileNotFoundError:
        raise InstallError(f"{what}: {cmd[0]} not found; install it (Debian: apt-get install "
                           f"{'passwd' if 'add' in cmd[0] else cmd[0]})") from None
    if done.returncode != 0:
        raise InstallError(f"{what}: {' '.join(cmd)} failed ({done.returncode}): "
                           f"{(done.stderr or done.stdout).strip()[-800:]}")
    return done.stdout


def _names(path: Path) -> dict[str, list[str]]:
    try:
        return {line.split(":")[0]: line.split(":") for line in path.read_text().splitlines() if ":" in line}
    except FileNotFoundError:
        return {}


def user_database(root: Path) -> Path | None:
    """The etc directory whose passwd/group install manages, or None when *root* has none."""
    etc = root / "etc"
    return etc if (etc / "passwd").is_file() and (etc / "group").is_file() else None


def ensure_users(tree: InstallTree) -> None:
    """Create the groups u2sa, dialout, i2c, gpio, u2sa-pilot and the system user u2sa where missing.

    The user u2sa is a member of the device groups, never of u2sa-pilot: only the RC mux's
    unit gets that group (SupplementaryGroups= in its drop-in), so only it reads pilot.key."""
    etc = user_database(tree.root)
    if etc is None:
        tree.note("skipped", "users and groups",
                  f"{tree.root}/etc has no passwd/group; systemd-sysusers creates them from "
                  "/etc/sysusers.d/u2sa.conf on first boot")
        return
    prefix = [] if tree.root == Path("/") else ["--prefix", str(tree.root)]
    groups = _names(etc / "group")
    for group in (SERVICE_USER, *DEVICE_GROUPS, *UNIT_ONLY_GROUPS):
        if group in groups:
            if group in tree.old.groups:
                tree.new.groups.append(group)
            continue
        run_tool(["groupadd", "--system", *prefix, group], what=f"creating group {group}")
        tree.new.groups.append(group)
        tree.note("created", f"group {group}")
    if SERVICE_USER in _names(etc / "passwd"):
        if SERVICE_USER in tree.old.users:
            tree.new.users.append(SERVICE_USER)
        return
    run_tool(["useradd", "--system", *prefix, "--gid", SERVICE_USER, "--groups", ",".join(DEVICE_GROUPS),
          "--home-dir", "/var/lib/u2sa", "--no-create-home", "--shell", "/usr/sbin/nologin",
          "--comment", "U2SA vehicle services", SERVICE_USER], what=f"creating user {SERVICE_USER}")
    tree.new.users.append(SERVICE_USER)
    tree.note("created", f"user {SERVICE_USER}", f"groups {SERVICE_USER}, {', '.join(DEVICE_GROUPS)}")


def remove_users(tree: InstallTree) -> None:
    """Delete the user and the groups that install created (uninstall --purge)."""
    etc = user_database(tree.root)
    if etc is None:
        return
    prefix = [] if tree.root == Path("/") else ["--prefix", str(tree.root)]
    for user in tree.old.users:
        if user in _names(etc / "passwd"):
            run_tool(["userdel", *prefix, user], what=f"removing user {user}")
            tree.note("removed", f"user {user}")
    for group in tree.old.groups:
        if group in _names(etc / "group"):
            run_tool(["groupdel", *prefix, group], what=f"removing group {group}")
            tree.note("removed", f"group {group}")


def owner_ids(root: Path, group: str = SERVICE_USER) -> tuple[int, int] | None:
    """``(0, gid of group)`` from the tree's group file, for root:u2sa files; None if unknown."""
    etc = user_database(root)
    if etc is None:
        return None
    entry = _names(etc / "group").get(group)
    return (0, int(entry[2])) if entry and len(entry) > 2 and entry[2].isdigit() else None


def group_members(root: Path, group: str) -> list[str]:
    """The users the tree's group file lists as members of *group* (empty when unknown)."""
    etc = user_database(root)
    entry = _names(etc / "group").get(group) if etc is not None else None
    return [m for m in entry[3].split(",") if m] if entry and len(entry) > 3 else []


def user_ids(root: Path, user: str = SERVICE_USER) -> tuple[int, int] | None:
    """``(uid, gid)`` of *user* from the tree's passwd file, for files the services own; None if unknown."""
    etc = user_database(root)
    if etc is None:
        return None
    entry = _names(etc / "passwd").get(user)
    if not entry or len(entry) < 4 or not (entry[2].isdigit() and entry[3].isdigit()):
        return None
    return int(entry[2]), int(entry[3])


def apply_tmpfiles(tree: InstallTree, conf: str, *, changed: bool) -> None:
    """``systemd-tmpfiles --create CONF`` on this system when it or its paths changed (never with --root)."""
    if tree.root != Path("/") or not changed:
        return
    if shutil.which("systemd-tmpfiles") is None:
        tree.note("skipped", f"systemd-tmpfiles --create {conf}", "systemd-tmpfiles is not installed")
        return
    run_tool(["systemd-tmpfiles", "--create", conf], what=f"applying {conf}")
    tree.note("updated", conf, "applied (systemd-tmpfiles --create)")


def apply_sysctl(tree: InstallTree, conf: str, *, changed: bool) -> None:
    """``sysctl -p CONF`` on this system when it changed (never with --root); a refusal is noted, not fatal.

    A kernel that refuses (a container without the right) still reads the file at the next boot.
    """
    if tree.root != Path("/") or not changed:
        return
    if shutil.which("sysctl") is None:
        tree.note("skipped", f"sysctl -p {conf}", "sysctl is not installed; the setting applies from next boot")
        return
    done = subprocess.run(["sysctl", "-p", conf], capture_output=True, text=True, timeout=60)
    if done.returncode != 0:
        tree.note("skipped", f"sysctl -p {conf}", f"refused ({(done.stderr or done.stdout).strip()[-200:]}); "
                  "it applies from next boot")
        return
    tree.note("updated", conf, "applied (sysctl -p)")


def reload_systemd(tree: InstallTree, *, units_changed: bool) -> None:
    """``systemctl daemon-reload`` when units changed and systemd runs here (never with --root)."""
    if tree.root != Path("/") or not units_changed:
        return
    if not Path("/run/systemd/system").is_dir():
        tree.note("skipped", "systemctl daemon-reload", "systemd is not running")
        return
    run_tool(["systemctl", "daemon-reload"], what="reloading systemd")
    tree.note("updated", "systemd", "daemon-reload")


def reload_udev(tree: InstallTree, *, rules_changed: bool, can_channels: list[str] = ()) -> None:
    """``udevadm control --reload`` and a change trigger for the device classes the rules cover; an add
    trigger for each CAN interface of the profile that is there, so it comes up at its bitrate now."""
    if tree.root != Path("/") or not rules_changed:
        return
    if shutil.which("udevadm") is None or not Path("/run/udev/control").exists():
        tree.note("skipped", "udevadm control --reload", "udevd is not running; the rules apply from next boot")
        return
    run_tool(["udevadm", "control", "--reload"], what="reloading udev rules")
    run_tool(["udevadm", "trigger", "--action=change", "--subsystem-match=tty", "--subsystem-match=i2c-dev",
          "--subsystem-match=gpio", "--subsystem-match=pwm"], what="applying udev rules to present devices")
    tree.note("updated", "udev", "rules reloaded and triggered")
    for channel in can_channels:
        if not Path("/sys/class/net", channel).exists():
            tree.note("skipped", f"CAN {channel}", "not present now; it comes up at its bitrate when it appears")
            continue
        if _link_up(channel):
            # Never touch a live bus: motor controllers may be listening. The rule applies at the next boot or replug.
            tree.note("skipped", f"CAN {channel}", "up already, left alone; the profile's bitrate applies at the "
                      f"next boot (or now: ip link set {channel} down && udevadm trigger --action=add "
                      f"--sysname-match={channel})")
            continue
        # 70-u2sa-can.rules acts on "add": set the bitrate (the interface is down) and bring it up.
        run_tool(["udevadm", "trigger", "--action=add", "--settle", f"--sysname-match={channel}",
              "--subsystem-match=net"], what=f"bringing {channel} up at its bitrate")
        tree.note("updated", f"CAN {channel}", "set to the profile's bitrate and up")


def _link_up(interface: str) -> bool:
    """Whether the network interface is administratively up (IFF_UP in /sys/class/net/IF/flags)."""
    try:
        return bool(int(Path("/sys/class/net", interface, "flags").read_text(), 16) & 0x1)
    except (OSError, ValueError):
        return False
