"""`u2sa install --root` / `u2sa uninstall`: the staged tree, idempotence, user changes, removal."""

from __future__ import annotations

import functools
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from u2sa_hw.install.deploy import install as deploy_install
from u2sa_hw.install.deploy import uninstall
from u2sa_hw.install.manifest import MANIFEST_PATH, load_manifest
from u2sa_hw.install.system import InstallError
from u2sa_hw.bus.lcm_url import DEFAULT_RECV_BUF_SIZE

U2SA = Path(sys.executable).with_name("u2sa")
# These tests stage in seconds: a venv sharing this environment's packages, not one built with pip
# (the default with --root, tests/test_systemd_image.py).
install = functools.partial(deploy_install, venv="shared")
PROFILE = """\
# a comment that the installed profile does not keep
[vehicle]
name = "rover"
system_id = 3
lcm_url = "udpm://239.255.76.67:7667?ttl=0"
config_dir = "params"
log_dir = "logs"

[services.estimator]
kind = "state_estimator"

[services.gps]
kind = "gps_nmea"
config = "elsewhere/gps.toml"

[services.hsm]
kind = "hsm"

[services.spare]
kind = "state_estimator"
enabled = false

[services.rudder]
kind = "pwm_servo"
settings = { channels = [{ name = "rudder" }] }

[services.wheels]
kind = "odrive_can"

[devices.gps]
address = "serial:///dev/u2sa/gps?baud=9600&usb=1546:01A7&serial=A1B2"

[devices.rudder]
address = "pwm://pwmchip0/0"
service = "rudder"

[devices.wheels]
address = "can://socketcan/can0?bitrate=1000000"
"""


@pytest.fixture()
def vehicle(tmp_path: Path) -> Path:
    src = tmp_path / "src"
    (src / "params").mkdir(parents=True)
    (src / "elsewhere").mkdir()
    (src / "params" / "estimator.toml").write_text("sensor_timeout_s = 3.0\n")
    (src / "elsewhere" / "gps.toml").write_text("stale_after_s = 2.0\n")
    path = src / "vehicle.toml"
    path.write_text(PROFILE)
    return path


@pytest.fixture()
def root(tmp_path: Path) -> Path:
    """A staging root with the host's users (so useradd --prefix has something to add to)."""
    r = tmp_path / "root"
    (r / "etc").mkdir(parents=True)
    for name in ("passwd", "group", "shadow", "gshadow", "login.defs"):
        if Path("/etc", name).exists():
            shutil.copy2(Path("/etc", name), r / "etc" / name)
    return r


def entries(path: Path) -> dict[str, list[str]]:
    return {line.split(":")[0]: line.split(":") for line in path.read_text().splitlines() if line}


def snapshot(root: Path) -> dict[str, tuple[float, int]]:
    return {str(p): (p.lstat().st_mtime_ns, p.lstat().st_mode) for p in root.rglob("*") if "venv" not in p.parts}


def test_install_stages_units_configs_rules_users_and_links(vehicle: Path, root: Path) -> None:
    tree = install(vehicle=vehicle, root=root)
    assert tree.changed
    units = root / "etc/systemd/system"
    for name in ("u2sa@.service", "u2sa.target", "u2sa-hsm.service", "u2sa-multicast-lo.service"):
        assert (units / name).is_file(), name
    assert not (units / "u2sa@recorder.service.d").exists()  # this vehicle has no recorder
    wants = units / "u2sa.target.wants"
    assert sorted(os.listdir(wants)) == ["u2sa-hsm.service", "u2sa@estimator.service", "u2sa@gps.service",
                                         "u2sa@rudder.service", "u2sa@wheels.service"]
    # Only the service whose device address is a sysfs PWM chip gets a writable /sys.
    # (and, as an actuator driver, the safety chain's real-time and watchdog-signal drop-ins)
    assert sorted(os.listdir(units / "u2sa@rudder.service.d")) == ["30-realtime.conf", "31-command-source.conf",
                                                                  "50-pwm-sysfs.conf"]
    assert not (units / "u2sa@wheels.service.d/50-pwm-sysfs.conf").exists()
    assert "ProtectKernelTunables=no" in (units / "u2sa@rudder.service.d/50-pwm-sysfs.conf").read_text()
    assert not (units / "u2sa@gps.service.d").exists()
    assert os.readlink(wants / "u2sa@gps.service") == "/etc/systemd/system/u2sa@.service"
    assert os.readlink(units / "multi-user.target.wants/u2sa.target") == "/etc/systemd/system/u2sa.target"
    # Profile: directories pointed at the vehicle's, service configs all in /etc/u2sa/config.
    from u2sa_hw.profile.loader import load_profile

    installed = root / "etc/u2sa/vehicle.toml"
    text = installed.read_text()
    assert "a comment that" not in text and "installed by `u2sa install`" in text
    prof = load_profile(installed)
    # config_dir stays relative: /etc/u2sa/config on the vehicle, inside the tree when staged.
    assert (prof.config_dir, prof.log_dir, prof.data_dir) == (installed.parent / "config", Path("/var/log/u2sa"),
                                                             Path("/var/lib/u2sa"))
    assert tomllib.loads(text)["vehicle"]["config_dir"] == "config"
    assert prof.config_path_for("gps") == installed.parent / "config/gps.toml"
    assert prof.system_id == 3 and prof.devices["gps"]["address"].startswith("serial:///dev/u2sa/gps")
    cfg = root / "etc/u2sa/config"
    assert (cfg / "estimator.toml").read_text() == "sensor_timeout_s = 3.0\n"
    assert (cfg / "gps.toml").read_text() == "stale_after_s = 2.0\n"
    # Users and groups in the staged tree; the config dir belongs to group u2sa, setgid, group-writable.
    passwd, group = entries(root / "etc/passwd"), entries(root / "etc/group")
    assert passwd["u2sa"][5:] == ["/var/lib/u2sa", "/usr/sbin/nologin"]
    for g in ("i2c", "gpio", "dialout"):
        assert "u2sa" in group[g][3].split(","), g
    st = cfg.stat()
    assert st.st_gid == int(group["u2sa"][2]) and st.st_mode & 0o7777 == 0o2770
    # udev rules: static ones and the profile's device addresses.
    rules = (root / "etc/udev/rules.d/65-u2sa-vehicle.rules").read_text()
    assert ('SUBSYSTEM=="tty", ATTRS{idVendor}=="1546", ATTRS{idProduct}=="01a7", ATTRS{serial}=="A1B2", '
            'SYMLINK+="u2sa/gps"') in rules
    assert 'KERNEL=="can0", ENV{U2SA_CAN_BITRATE}="1000000"' in rules
    assert (root / "etc/udev/rules.d/60-u2sa-permissions.rules").is_file()
    # The shared venv runs this project with an interpreter the services can reach.
    py = root / "opt/u2sa/venv/bin/python"
    done = subprocess.run([str(py), "-c", "import u2sa_hw.cli, lcm; print(u2sa_hw.__version__)"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert not os.path.realpath(py).startswith(("/root", "/home"))
    manifest = load_manifest(root)
    assert manifest is not None and "u2sa" in manifest.users
    assert manifest.units_enabled == sorted(["u2sa.target", "u2sa@estimator.service", "u2sa@gps.service",
                                             "u2sa@rudder.service", "u2sa@wheels.service", "u2sa-hsm.service"])


def test_second_install_changes_nothing_and_says_so(vehicle: Path, root: Path) -> None:
    first = subprocess.run([str(U2SA), "install", "--vehicle", str(vehicle), "--root", str(root),
                            "--venv", "shared"], capture_output=True, text=True, timeout=120)
    assert first.returncode == 0, first.stderr
    before = snapshot(root)
    manifest = (root / MANIFEST_PATH.lstrip("/")).read_bytes()
    second = subprocess.run([str(U2SA), "install", "--vehicle", str(vehicle), "--root", str(root),
                             "--venv", "shared"], capture_output=True, text=True, timeout=120)
    assert second.returncode == 0, second.stderr
    assert second.stdout.strip() == "nothing to do: everything is already installed as this profile wants"
    assert snapshot(root) == before
    assert (root / MANIFEST_PATH.lstrip("/")).read_bytes() == manifest


def test_the_log_directory_exists_for_the_services_and_the_hsm_before_any_unit_starts(vehicle: Path,
                                                                                      root: Path) -> None:
    """/var/log/u2sa is u2sa:u2sa 0770 (the HSM, uid 0 without capabilities, writes through its group),
    declared for systemd-tmpfiles, and no unit of another user than u2sa lets systemd manage it."""
    install(vehicle=vehicle, root=root)
    tmpfiles = (root / "etc/tmpfiles.d/u2sa.conf").read_text()
    assert "d /var/log/u2sa 0770 u2sa u2sa -\n" in tmpfiles
    passwd = entries(root / "etc/passwd")
    st = (root / "var/log/u2sa").stat()
    assert (st.st_uid, st.st_gid) == (int(passwd["u2sa"][2]), int(passwd["u2sa"][3]))
    assert st.st_mode & 0o7777 == 0o770
    units = root / "etc/systemd/system"
    hsm = (units / "u2sa-hsm.service").read_text().splitlines()
    assert "User=root" in hsm and "Group=u2sa" in hsm and "ReadWritePaths=/var/log/u2sa" in hsm
    # never the services' directories (systemd would chown them to root at each HSM start)
    assert not [line for line in hsm if line.split("=")[0] == "LogsDirectory"], hsm
    assert [line for line in hsm if line.startswith("StateDirectory=")] == ["StateDirectory=u2sa-hsm"], hsm
    assert "LogsDirectoryMode=0770" in (units / "u2sa@.service").read_text().splitlines()
    manifest = load_manifest(root)
    assert manifest is not None and "/var/log/u2sa" in manifest.dirs
    assert "/etc/tmpfiles.d/u2sa.conf" in manifest.files
    # The kernel's cap on receive buffers, raised to what the transport asks for.
    assert f"net.core.rmem_max = {DEFAULT_RECV_BUF_SIZE}\n" in (root / "etc/sysctl.d/60-u2sa-lcm.conf").read_text()
    assert "/etc/sysctl.d/60-u2sa-lcm.conf" in manifest.files
    # A second install finds both as wanted; one whose owner or mode drifted is put back.
    before = snapshot(root)
    again = install(vehicle=vehicle, root=root)
    assert not again.changed, [str(c) for c in again.changes if c.action != "unchanged"]
    assert snapshot(root) == before
    os.chown(root / "var/log/u2sa", 0, 0)
    (root / "var/log/u2sa").chmod(0o750)
    fixed = install(vehicle=vehicle, root=root)
    assert [str(c) for c in fixed.changes if c.action != "unchanged"] == ["updated   /var/log/u2sa  (mode/owner)"]
    st = (root / "var/log/u2sa").stat()
    assert (st.st_uid, st.st_gid, st.st_mode & 0o7777) == (int(passwd["u2sa"][2]), int(passwd["u2sa"][3]), 0o770)
    # An hsm.log that systemd chowned to u2sa under an earlier install goes back to root:u2sa.
    hsm_log = root / "var/log/u2sa/hsm.log"
    hsm_log.write_text("a log line\n")
    os.chown(hsm_log, int(passwd["u2sa"][2]), int(passwd["u2sa"][3]))
    install(vehicle=vehicle, root=root)
    assert (hsm_log.stat().st_uid, hsm_log.stat().st_gid) == (0, int(passwd["u2sa"][3]))
    assert not install(vehicle=vehicle, root=root).changed
    # Uninstall keeps the logs (only --purge removes them) but not the tmpfiles declaration.
    uninstall(root=root)
    assert (root / "var/log/u2sa/hsm.log").is_file() and not (root / "etc/tmpfiles.d").exists()
    assert not (root / "etc/sysctl.d").exists()


def test_a_config_the_user_changed_is_kept_and_the_new_default_goes_beside_it(vehicle: Path, root: Path) -> None:
    install(vehicle=vehicle, root=root)
    cfg = root / "etc/u2sa/config"
    (cfg / "gps.toml").write_text("stale_after_s = 3.0\n")  # the user's change (e.g. u2sa param set)
    (vehicle.parent / "elsewhere/gps.toml").write_text("stale_after_s = 4.0\n")  # a new default
    (vehicle.parent / "params/estimator.toml").write_text("sensor_timeout_s = 5.0\n")  # untouched by the user
    tree = install(vehicle=vehicle, root=root)
    assert (cfg / "gps.toml").read_text() == "stale_after_s = 3.0\n"
    assert (cfg / "gps.toml.new").read_text() == "stale_after_s = 4.0\n"
    assert (cfg / "estimator.toml").read_text() == "sensor_timeout_s = 5.0\n"
    assert not (cfg / "estimator.toml.new").exists()
    assert any(c.action == "kept" and c.path == "/etc/u2sa/config/gps.toml" for c in tree.changes)
    # Again: nothing changes; the user's file still wins.
    assert not install(vehicle=vehicle, root=root).changed
    # The user adopts the default: the .new file goes away and the config is install's again.
    (cfg / "gps.toml").write_text("stale_after_s = 4.0\n")
    install(vehicle=vehicle, root=root)
    assert not (cfg / "gps.toml.new").exists()
    (vehicle.parent / "elsewhere/gps.toml").write_text("stale_after_s = 5.0\n")
    install(vehicle=vehicle, root=root)
    assert (cfg / "gps.toml").read_text() == "stale_after_s = 5.0\n"


def test_every_recorder_gets_the_recorder_dropin_whatever_its_name(vehicle: Path, root: Path) -> None:
    """The drop-in follows the kind: a recorder named logbook gets it, an estimator named recorder does not."""
    vehicle.write_text(PROFILE + '\n[services.logbook]\nkind = "recorder"\n\n'
                       '[services.recorder]\nkind = "state_estimator"\n')
    install(vehicle=vehicle, root=root)
    units = root / "etc/systemd/system"
    dropin = (units / "u2sa@logbook.service.d/10-recorder.conf").read_text().splitlines()
    assert {"[Service]", "Nice=5", "IOSchedulingClass=best-effort", "TimeoutStopSec=15s"} <= set(dropin), dropin
    assert os.listdir(units / "u2sa@logbook.service.d") == ["10-recorder.conf"]
    assert os.listdir(units / "u2sa@recorder.service.d") == ["20-after-recorder.conf"]
    assert (units / "u2sa.target.wants/u2sa@logbook.service").is_symlink()
    # Every other enabled service (the HSM too) starts after the recorder is ready, so recordings replay.
    for unit in ("u2sa@estimator.service", "u2sa@gps.service", "u2sa@recorder.service", "u2sa-hsm.service"):
        after = (units / f"{unit}.d/20-after-recorder.conf").read_text().splitlines()
        assert "[Unit]" in after and "After=u2sa@logbook.service" in after, (unit, after)
    assert not (units / "u2sa@spare.service.d").exists()   # disabled: nothing to order
    # Renamed: the drop-in moves with the service, nothing is left under the old name.
    vehicle.write_text(PROFILE + '\n[services.blackbox]\nkind = "recorder"\n')
    tree = install(vehicle=vehicle, root=root)
    assert (units / "u2sa@blackbox.service.d/10-recorder.conf").read_text().splitlines() == \
        [line.replace("u2sa@logbook", "u2sa@blackbox") for line in dropin]
    assert not (units / "u2sa@logbook.service.d").exists()
    assert any(c.action == "removed" and c.path.endswith("u2sa@logbook.service.d/10-recorder.conf")
               for c in tree.changes)
    assert "After=u2sa@blackbox.service" in (units / "u2sa@gps.service.d/20-after-recorder.conf").read_text()
    # No recorder left: no ordering left either.
    vehicle.write_text(PROFILE)
    install(vehicle=vehicle, root=root)
    assert not list(units.glob("*.d/20-after-recorder.conf"))


def test_a_service_dropped_from_the_profile_is_disabled(vehicle: Path, root: Path) -> None:
    install(vehicle=vehicle, root=root)
    vehicle.write_text(PROFILE.replace('[services.gps]\nkind = "gps_nmea"', '[services.gps]\nkind = "gps_nmea"\n'
                                       "enabled = false"))
    tree = install(vehicle=vehicle, root=root)
    assert not (root / "etc/systemd/system/u2sa.target.wants/u2sa@gps.service").exists()
    assert any(c.action == "removed" and c.path.endswith("u2sa@gps.service") for c in tree.changes)


def test_uninstall_keeps_configs_and_purge_removes_everything(vehicle: Path, root: Path) -> None:
    install(vehicle=vehicle, root=root)
    (root / "var/log/u2sa/gps.log").write_text("a log line\n")
    uninstall(root=root)
    assert not (root / "etc/tmpfiles.d/u2sa.conf").exists()
    assert not (root / "etc/systemd/system/u2sa@.service").exists()
    assert not (root / "etc/systemd/system/u2sa.target.wants").exists()
    assert not (root / "etc/udev/rules.d/60-u2sa-permissions.rules").exists()
    assert os.listdir(root / "opt/u2sa") == ["install-manifest.json"]  # now listing only what was kept
    assert (root / "etc/u2sa/vehicle.toml").is_file() and (root / "etc/u2sa/config/gps.toml").is_file()
    assert (root / "var/log/u2sa/gps.log").is_file()
    assert "u2sa" in entries(root / "etc/passwd")
    with pytest.raises(InstallError, match="nothing to uninstall"):
        uninstall(root=root)
    (root / "etc/u2sa/config/gps.toml").write_text("stale_after_s = 6.0\n")
    install(vehicle=vehicle, root=root)  # still knows the config was changed by the user
    assert (root / "etc/u2sa/config/gps.toml").read_text() == "stale_after_s = 6.0\n"
    uninstall(root=root, purge=True)
    assert not (root / "etc/u2sa").exists() and not (root / "var/log/u2sa").exists()
    assert "u2sa" not in entries(root / "etc/passwd")
    assert "i2c" not in entries(root / "etc/group") and "dialout" in entries(root / "etc/group")
    left = [p for p in root.rglob("*") if p not in (root / "etc", root / "var", root / "var/log")
            and not (p.parent == root / "etc" and p.is_file())]
    assert left == [], left  # only the user database files the fixture put there (and their backups)


@pytest.mark.parametrize("change, message", [
    ('[services.hsm]\nkind = "hsm"', "[services.monitor]\nkind = \"hsm\"", ),
    ("usb=1546:01A7", "usb=15x6:01A7"),
    ("bitrate=1000000", "bitrate=fast"),
    ("[services.spare]", "[services.'bad name']"),
])
def test_a_bad_profile_is_refused_before_anything_is_written(vehicle: Path, root: Path, change: str,
                                                            message: str) -> None:
    old, new = change, message
    vehicle.write_text(PROFILE.replace(old, new).replace("enabled = false", "enabled = true"))
    with pytest.raises(InstallError) as err:
        install(vehicle=vehicle, root=root)
    assert str(vehicle) in str(err.value)
    assert sorted(p.name for p in (root / "etc").iterdir()) == sorted(
        n for n in ("passwd", "group", "shadow", "gshadow", "login.defs") if Path("/etc", n).exists())


def test_sysusers_declaration_creates_the_user_and_groups(tmp_path: Path, vehicle: Path, root: Path) -> None:
    if shutil.which("systemd-sysusers") is None:
        pytest.skip("systemd-sysusers is not installed")
    install(vehicle=vehicle, root=root)
    image = tmp_path / "image"
    (image / "etc").mkdir(parents=True)
    done = subprocess.run(["systemd-sysusers", f"--root={image}", str(root / "etc/sysusers.d/u2sa.conf")],
                          capture_output=True, text=True, timeout=30)
    assert done.returncode == 0, done.stderr
    passwd, group = entries(image / "etc/passwd"), entries(image / "etc/group")
    assert passwd["u2sa"][6] == "/usr/sbin/nologin"
    assert all("u2sa" in group[g][3].split(",") for g in ("dialout", "i2c", "gpio"))
    assert group["u2sa-pilot"][3] == ""   # the RC mux's unit's group alone: the service user is not in it


def test_install_makes_the_bus_key_root_u2sa_0640_once_and_keeps_an_existing_one(vehicle: Path, root: Path) -> None:
    from u2sa_hw.bus.key import read_key

    tree = install(vehicle=vehicle, root=root)
    key_file = root / "etc/u2sa/bus.key"
    assert any(c.action == "created" and c.path == "/etc/u2sa/bus.key" for c in tree.changes)
    group = entries(root / "etc/group")
    st = key_file.stat()
    assert (st.st_uid, st.st_gid, st.st_mode & 0o7777) == (0, int(group["u2sa"][2]), 0o640)
    key = read_key(key_file)
    assert key.hex() not in (root / "etc/u2sa/vehicle.toml").read_text()   # never in the world-readable profile
    key_file.chmod(0o644)   # drifted: the key is kept, its mode put back
    again = install(vehicle=vehicle, root=root)
    assert not again.changed and read_key(key_file) == key
    assert key_file.stat().st_mode & 0o7777 == 0o640
    uninstall(root=root)
    assert read_key(key_file) == key   # kept with the configs; --purge removes /etc/u2sa


def test_u2sa_key_rotate_import_and_show_on_a_staged_key(vehicle: Path, root: Path) -> None:
    install(vehicle=vehicle, root=root)
    key_file = root / "etc/u2sa/bus.key"
    u2sa = [sys.executable, "-m", "u2sa_hw.cli", "key"]
    env = {k: v for k, v in os.environ.items() if k != "U2SA_BUS_KEY_FILE"}
    old = subprocess.run([*u2sa, "show", "--file", str(key_file)], capture_output=True, text=True, env=env)
    assert old.returncode == 0 and len(old.stdout.strip()) == 64
    rotated = subprocess.run([*u2sa, "rotate", "--file", str(key_file)], capture_output=True, text=True, env=env)
    assert rotated.returncode == 0, rotated.stderr
    new = subprocess.run([*u2sa, "show", "--file", str(key_file)], capture_output=True, text=True, env=env).stdout
    assert new != old.stdout
    st = key_file.stat()
    assert (st.st_uid, st.st_mode & 0o7777) == (0, 0o640 if os.geteuid() == 0 else 0o600)
    back = subprocess.run([*u2sa, "import", "-", "--file", str(key_file)], input=old.stdout, capture_output=True,
                          text=True, env=env)
    assert back.returncode == 0, back.stderr
    assert subprocess.run([*u2sa, "show", "--file", str(key_file)], capture_output=True, text=True,
                          env=env).stdout == old.stdout
    bad = subprocess.run([*u2sa, "import", "-", "--file", str(key_file)], input="0123\n", capture_output=True,
                         text=True, env=env)
    assert bad.returncode == 1 and bad.stderr.count("\n") == 1 and "64 hex digits" in bad.stderr
    assert "Traceback" not in bad.stderr


RC_MUX = ('\n[services.mux]\nkind = "rc_mux"\n'
          'settings = { channels = "throttle=5,steering=6,mode=13", enable_line = 21 }\n'
          '[devices.mux]\naddress = "gpio://gpiochip0/5,6,13,21"\n')


def test_install_makes_the_pilot_pair_that_only_the_rc_muxs_unit_reads(vehicle: Path, root: Path) -> None:
    """pilot.key root:u2sa-pilot 0040 (not even root's own bits), pilot.pub root:root 0644, the group u2sa-pilot
    without the user u2sa in it, and the drop-in giving that group to the RC mux's unit and no other."""
    from u2sa_hw.bus.pilot import pilot_key_id, public_of, read_signer, read_verifier
    from u2sa_hw.bus.key import parse_key

    vehicle.write_text(PROFILE + RC_MUX)
    tree = install(vehicle=vehicle, root=root)
    etc = root / "etc/u2sa"
    group = entries(root / "etc/group")
    assert "u2sa-pilot" in group and group["u2sa-pilot"][3] == "", group["u2sa-pilot"]   # no member, u2sa least
    assert "u2sa-pilot" not in [g for g, e in group.items() if "u2sa" in e[3].split(",")]
    pilot_gid = int(group["u2sa-pilot"][2])
    st = (etc / "pilot.key").stat()
    assert (st.st_uid, st.st_gid, st.st_mode & 0o7777) == (0, pilot_gid, 0o040)
    st = (etc / "pilot.pub").stat()
    assert (st.st_uid, st.st_gid, st.st_mode & 0o7777) == (0, 0, 0o644)
    assert [str(c) for c in tree.changes if c.path.startswith("/etc/u2sa/pilot")] == [
        "created   /etc/u2sa/pilot.key  (the pilot's private key, root:u2sa-pilot 0040: only the RC mux's unit "
        "reads it)",
        "created   /etc/u2sa/pilot.pub  (the pilot's public key; copy it beside a laptop's bus key to check RC_MODE)"]
    assert "created   group u2sa-pilot" in [str(c).strip() for c in tree.changes]
    # A pair: what the key signs, the public key checks.
    signer, verifier = read_signer(etc / "pilot.key"), read_verifier(etc / "pilot.pub")
    assert signer.id == verifier.id and verifier.check(signer.sign(b"RC_MODE"), b"RC_MODE")
    # The RC mux's unit alone gets the group, added to the template's list, and the key back in reach.
    units = root / "etc/systemd/system"
    assert [p.relative_to(units).as_posix() for p in sorted(units.glob("*.d/32-pilot-key.conf"))] == \
        ["u2sa@mux.service.d/32-pilot-key.conf"]
    dropin = (units / "u2sa@mux.service.d/32-pilot-key.conf").read_text().splitlines()
    assert [line for line in dropin if not line.startswith("#")] == \
        ["[Service]", "SupplementaryGroups=u2sa-pilot", "InaccessiblePaths="]
    assert not [p for p in units.rglob("*") if p.is_file() and p.name != "32-pilot-key.conf"
                and any("u2sa-pilot" in line for line in p.read_text().splitlines() if not line.startswith("#"))]
    for unit in ("u2sa@.service", "u2sa-hsm.service"):
        lines = (units / unit).read_text().splitlines()
        assert "InaccessiblePaths=-/etc/u2sa/pilot.key" in lines, unit
        assert next(line for line in lines if line.startswith("ExecStart=")).endswith(" --unit"), unit
    sysusers = (root / "etc/sysusers.d/u2sa.conf").read_text().splitlines()
    assert "g u2sa-pilot -" in sysusers and "m u2sa u2sa-pilot" not in sysusers
    # Again: nothing to do. Drifted: the key is kept, owner and mode put back, and said.
    assert not install(vehicle=vehicle, root=root).changed
    key = (etc / "pilot.key").read_bytes()
    os.chown(etc / "pilot.key", 0, 0)
    (etc / "pilot.key").chmod(0o644)
    os.chown(etc / "pilot.pub", 0, pilot_gid)
    (etc / "pilot.pub").chmod(0o664)
    fixed = install(vehicle=vehicle, root=root)
    assert [str(c) for c in fixed.changes if c.action != "unchanged"] == [
        "updated   /etc/u2sa/pilot.key  (the existing pilot key is kept; owner and mode root:u2sa-pilot 0040 again)",
        "updated   /etc/u2sa/pilot.pub  (owner and mode root:root 0644 again)"]
    assert (etc / "pilot.key").read_bytes() == key
    st = (etc / "pilot.key").stat()
    assert (st.st_uid, st.st_gid, st.st_mode & 0o7777) == (0, pilot_gid, 0o040)
    st = (etc / "pilot.pub").stat()
    assert (st.st_uid, st.st_gid, st.st_mode & 0o7777) == (0, 0, 0o644)
    # A lost pilot.pub is made again from the key (laptops holding it keep checking), not a new pair.
    (etc / "pilot.pub").unlink()
    install(vehicle=vehicle, root=root)
    assert (etc / "pilot.key").read_bytes() == key
    seed = parse_key(key, source="pilot.key")
    assert read_verifier(etc / "pilot.pub").id == pilot_key_id(public_of(seed)) == verifier.id
    # Not the rc mux any more: its drop-in goes; the pair stays (every receiver checks RC_MODE with pilot.pub).
    vehicle.write_text(PROFILE)
    install(vehicle=vehicle, root=root)
    assert not list(units.glob("*.d/32-pilot-key.conf"))
    # Uninstall keeps the pair with the configs, --purge removes it and the group install made.
    uninstall(root=root)
    assert (etc / "pilot.key").read_bytes() == key and (etc / "pilot.pub").is_file()
    uninstall(root=root, purge=True)
    assert not etc.exists() and "u2sa-pilot" not in entries(root / "etc/group")


def test_install_warns_when_the_service_user_is_in_the_pilot_group(vehicle: Path, root: Path) -> None:
    install(vehicle=vehicle, root=root)
    text = (root / "etc/group").read_text()
    (root / "etc/group").write_text(text.replace("\nu2sa-pilot:x:" + entries(root / "etc/group")["u2sa-pilot"][2]
                                                 + ":\n", "\nu2sa-pilot:x:"
                                                 + entries(root / "etc/group")["u2sa-pilot"][2] + ":u2sa\n"))
    assert entries(root / "etc/group")["u2sa-pilot"][3] == "u2sa"
    tree = install(vehicle=vehicle, root=root)
    assert [w for w in tree.warnings if "u2sa-pilot" in w] == [
        f"{root}/etc/group: the user u2sa is in the group u2sa-pilot, so every service could read "
        "/etc/u2sa/pilot.key and sign as the pilot; fix: sudo gpasswd -d u2sa u2sa-pilot (only the RC mux's unit "
        "gets the group, from its drop-in 32-pilot-key.conf)"]


def test_a_tree_without_a_user_database_gets_a_pilot_key_only_root_reads(vehicle: Path, tmp_path: Path) -> None:
    bare = tmp_path / "bare"
    tree = install(vehicle=vehicle, root=bare)
    st = (bare / "etc/u2sa/pilot.key").stat()
    assert (st.st_uid, st.st_gid, st.st_mode & 0o7777) == (0, 0, 0o600)
    assert any(str(c).startswith("created   /etc/u2sa/pilot.key  (the pilot's private key, root:root 0600 (no group "
                                 "u2sa-pilot yet)") for c in tree.changes)


def test_a_shared_venv_staged_with_root_warns_that_the_image_will_not_find_this_environment(
        vehicle: Path, root: Path) -> None:
    """--venv shared points into this machine's environment; a staged tree without it does not boot."""
    import sysconfig

    tree = install(vehicle=vehicle, root=root)
    site = sysconfig.get_paths()["purelib"]
    assert [w for w in tree.warnings if w.startswith("--venv shared")] == [
        f"--venv shared with --root: /opt/u2sa/venv points at this machine's {site}, which is not in "
        f"{root.resolve()}; booted anywhere else every unit fails with \"No module named 'u2sa_hw'\"; fix: --venv "
        "build (the default), which builds the venv inside the root"]


def test_help_says_the_venv_is_built_inside_the_root_by_default() -> None:
    shown = subprocess.run([str(U2SA), "install", "--help"], capture_output=True, text=True, timeout=60)
    assert shown.returncode == 0, shown.stderr
    text = " ".join(shown.stdout.split())
    assert "build (the default, also with --root" in text
    assert "builds the venv inside DIR (--venv build, the default)" in text


def test_relocate_venv_rewrites_the_scripts_and_pyvenv_cfg_to_the_vehicles_path(tmp_path: Path) -> None:
    from u2sa_hw.install.venv import relocate_venv

    venv = tmp_path / "root/opt/u2sa/venv"
    (venv / "bin").mkdir(parents=True)
    (venv / "pyvenv.cfg").write_text(f"home = /usr/bin\ncommand = /usr/bin/python3 -m venv {venv}\n")
    (venv / "bin/u2sa").write_text(f"#!{venv}/bin/python\nfrom u2sa_hw.cli import main\n")
    (venv / "bin/u2sa").chmod(0o755)
    (venv / "bin/activate").write_text(f'VIRTUAL_ENV="{venv}"\n')
    (venv / "bin/python").symlink_to("/usr/bin/python3")
    assert relocate_venv(venv, "/opt/u2sa/venv") == ["pyvenv.cfg", "activate", "u2sa"]
    assert (venv / "bin/u2sa").read_text().startswith("#!/opt/u2sa/venv/bin/python\n")
    assert (venv / "bin/u2sa").stat().st_mode & 0o777 == 0o755
    assert (venv / "bin/activate").read_text() == 'VIRTUAL_ENV="/opt/u2sa/venv"\n'
    assert (venv / "pyvenv.cfg").read_text().endswith("-m venv /opt/u2sa/venv\n")
    assert os.readlink(venv / "bin/python") == "/usr/bin/python3"
