"""`u2sa install` yields a vehicle that runs: the files its services name, udev rules and CAN bring-up from
device addresses, the offline check first, and `u2sa uninstall` undoing exactly what install did."""

from __future__ import annotations

import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from u2sa_hw.install.deploy import install, uninstall
from u2sa_hw.install.system import InstallError
from u2sa_hw.profile.loader import load_profile

U2SA = Path(sys.executable).with_name("u2sa")
REPO = Path(__file__).resolve().parent.parent
EXAMPLES = sorted(p.parent.name for p in (REPO / "examples").glob("*/vehicle.toml"))
MISSION = (REPO / "examples/ground_vehicle/mission.xml").read_text()
OBJECTS = (REPO / "examples/ground_vehicle/objects.xml").read_text()

PROFILE = """\
[vehicle]
name = "rover"
origin = { lat = 29.1895, lon = -81.0483, alt = 10.0 }

[services.gps]
kind = "gps_nmea"

[devices.gps]
address = "serial:///dev/u2sa/gps?baud=9600&usb=1546:01a7&serial=A1B2"

[services.mission]
kind = "mission_manager"

[services.world]
kind = "world_modeler"

[services.hsm]
kind = "hsm"
"""


def u2sa(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(U2SA), *args], capture_output=True, text=True, timeout=180,
                          env={**os.environ, **(env or {})})


def staged_check_env(root: Path) -> dict[str, str]:
    """`u2sa check` looking at the staged tree's udev rules instead of this machine's."""
    dirs = [root / d for d in ("etc/udev/rules.d", "run/udev/rules.d", "lib/udev/rules.d", "usr/lib/udev/rules.d")]
    return {"U2SA_UDEV_RULES_DIRS": ":".join(map(str, dirs))}


@pytest.fixture()
def vehicle(tmp_path: Path) -> Path:
    """A profile whose mission is beside it and whose a-priori objects are outside its directory."""
    src = tmp_path / "src"
    (src / "config").mkdir(parents=True)
    (tmp_path / "shared").mkdir()
    (src / "missions").mkdir()
    (src / "missions" / "harbour.xml").write_text(MISSION)
    (tmp_path / "shared" / "objects.xml").write_text(OBJECTS)
    (src / "config" / "mission.toml").write_text('# the mission\nmission_file = "missions/harbour.xml"\n')
    (src / "config" / "world.toml").write_text('objects_file = "../shared/objects.xml"\n')
    path = src / "vehicle.toml"
    path.write_text(PROFILE)
    return path


def test_root_is_created_and_the_named_files_are_installed_and_named_by_the_installed_configs(
        vehicle: Path, tmp_path: Path) -> None:
    root = tmp_path / "not" / "yet" / "there"
    done = u2sa("install", "--vehicle", str(vehicle), "--root", str(root), "--venv", "shared")
    assert done.returncode == 0, done.stderr
    etc = root / "etc/u2sa"
    # Beside the profile at the same relative place: the config keeps its text, comments too.
    assert (etc / "missions/harbour.xml").read_text() == MISSION
    assert (etc / "config/mission.toml").read_text() == '# the mission\nmission_file = "missions/harbour.xml"\n'
    # Outside the profile's directory: under files/SERVICE, and the installed config names that copy.
    assert (etc / "files/world/objects.xml").read_text() == OBJECTS
    assert tomllib.loads((etc / "config/world.toml").read_text()) == {"objects_file": "files/world/objects.xml"}
    installed = load_profile(etc / "vehicle.toml")
    assert installed.resolve_path("files/world/objects.xml") == etc / "files/world/objects.xml"
    # The services resolve them in the staged tree as they will on the vehicle: the check loads both.
    check = u2sa("check", "--vehicle", str(etc / "vehicle.toml"), env=staged_check_env(root))
    assert check.returncode == 0, check.stdout + check.stderr
    # Once installed, a file is the user's like a config: changed on the vehicle, it is kept.
    (etc / "missions/harbour.xml").write_text(MISSION + "<!-- changed on the vehicle -->\n")
    again = u2sa("install", "--vehicle", str(vehicle), "--root", str(root), "--venv", "shared")
    assert again.returncode == 0 and "kept      /etc/u2sa/missions/harbour.xml" in again.stdout
    assert "changed on the vehicle" in (etc / "missions/harbour.xml").read_text()


def test_a_missing_named_file_is_refused_and_force_installs_the_rest_and_exits_1(vehicle: Path,
                                                                                 tmp_path: Path) -> None:
    (vehicle.parent / "missions/harbour.xml").unlink()
    root = tmp_path / "root"
    refused = u2sa("install", "--vehicle", str(vehicle), "--root", str(root), "--venv", "shared")
    assert refused.returncode == 1 and "refusing to install" in refused.stderr and "--force" in refused.stderr
    assert "mission_file" in refused.stderr and "harbour.xml" in refused.stderr
    assert not root.exists()                       # nothing written, not even the root
    forced = u2sa("install", "--vehicle", str(vehicle), "--root", str(root), "--venv", "shared", "--force")
    assert forced.returncode == 1, forced.stdout + forced.stderr
    assert "not done:" in forced.stderr and "harbour.xml" in forced.stderr
    assert (root / "etc/u2sa/vehicle.toml").is_file() and (root / "etc/u2sa/files/world/objects.xml").is_file()


def test_a_dev_u2sa_link_nothing_creates_is_refused_with_the_rule_line_and_a_local_rule_makes_it(
        vehicle: Path, tmp_path: Path) -> None:
    vehicle.write_text(PROFILE.replace("?baud=9600&usb=1546:01a7&serial=A1B2", "?baud=9600"))
    root = tmp_path / "root"
    with pytest.raises(InstallError) as err:
        install(vehicle=vehicle, root=root, venv="shared")
    text = str(err.value)
    assert "/dev/u2sa/gps" in text and 'SYMLINK+="u2sa/gps"' in text and "66-u2sa-local.rules" in text
    forced = install(vehicle=vehicle, root=root, force=True, venv="shared")
    assert any("/dev/u2sa/gps" in f for f in forced.failures)
    rules = (root / "etc/udev/rules.d/65-u2sa-vehicle.rules").read_text()
    assert "u2sa/gps" not in rules
    # The user's own rule (as the error says) makes the link: install goes through, and leaves the rule alone.
    local = root / "etc/udev/rules.d/66-u2sa-local.rules"
    local.write_text('SUBSYSTEM=="tty", ATTRS{idVendor}=="0403", ATTRS{idProduct}=="6001", SYMLINK+="u2sa/gps"\n')
    tree = install(vehicle=vehicle, root=root, venv="shared")
    assert tree.failures == []
    uninstall(root=root, purge=True)
    assert local.read_text().startswith('SUBSYSTEM=="tty"')


def test_can_interfaces_get_their_bitrate_from_the_address(vehicle: Path, tmp_path: Path) -> None:
    vehicle.write_text(PROFILE + '\n[services.wheels]\nkind = "odrive_can"\n\n'
                       '[devices.wheels]\naddress = "can://socketcan/can1?bitrate=250000"\n')
    root = tmp_path / "root"
    tree = install(vehicle=vehicle, root=root, venv="shared")
    rules = (root / "etc/udev/rules.d/65-u2sa-vehicle.rules").read_text().splitlines()
    assert 'SUBSYSTEM=="net", KERNEL=="can1", ENV{U2SA_CAN_BITRATE}="250000"' in rules
    assert ('SUBSYSTEM=="tty", ATTRS{idVendor}=="1546", ATTRS{idProduct}=="01a7", ATTRS{serial}=="A1B2", '
            'SYMLINK+="u2sa/gps", GROUP="dialout", MODE="0660"') in rules
    bringup = (root / "etc/udev/rules.d/70-u2sa-can.rules").read_text()
    assert "bitrate $env{U2SA_CAN_BITRATE}" in bringup and "ip link set $name up" in bringup
    assert not tree.failures
    # Without a bitrate the interface is left as configured, and install says so.
    vehicle.write_text(vehicle.read_text().replace("?bitrate=250000", ""))
    tree = install(vehicle=vehicle, root=root, venv="shared")
    assert "can1" not in (root / "etc/udev/rules.d/65-u2sa-vehicle.rules").read_text()
    assert any(c.action == "skipped" and "can1" in c.path for c in tree.changes)


def _tree(root: Path) -> dict[str, tuple[str, bytes | str]]:
    out: dict[str, tuple[str, bytes | str]] = {}
    for p in sorted(root.rglob("*")):
        rel = str(p.relative_to(root))
        if p.is_symlink():
            out[rel] = ("link", os.readlink(p))
        elif p.is_file():
            out[rel] = ("file", p.read_bytes())
        else:
            out[rel] = ("dir", "")
    return out


def test_uninstall_undoes_exactly_what_install_did(vehicle: Path, tmp_path: Path) -> None:
    """What was there before stays byte for byte; what install made goes; configs and named files stay
    until --purge."""
    root = tmp_path / "root"
    (root / "etc/udev/rules.d").mkdir(parents=True)
    (root / "etc/udev/rules.d/99-other.rules").write_text('SUBSYSTEM=="tty", GROUP="dialout"\n')
    (root / "etc/systemd/system").mkdir(parents=True)
    (root / "etc/systemd/system/other.service").write_text("[Service]\nExecStart=/bin/true\n")
    (root / "opt/other").mkdir(parents=True)
    before = _tree(root)
    assert u2sa("install", "--vehicle", str(vehicle), "--root", str(root), "--venv", "shared").returncode == 0
    assert (root / "etc/u2sa/missions/harbour.xml").is_file()
    done = u2sa("uninstall", "--root", str(root))
    assert done.returncode == 0, done.stderr
    after = _tree(root)
    assert {k: v for k, v in after.items() if k in before} == before
    kept = sorted(set(after) - set(before))
    assert "etc/u2sa/missions/harbour.xml" in kept and "etc/u2sa/config/world.toml" in kept
    assert not [k for k in kept if k.startswith(("etc/systemd", "etc/udev", "etc/sysctl", "opt/u2sa/venv"))], kept
    purged = u2sa("uninstall", "--root", str(root), "--purge")
    assert purged.returncode == 0, purged.stderr
    assert _tree(root) == before


def test_uninstall_of_a_root_that_does_not_exist_says_so(tmp_path: Path) -> None:
    done = u2sa("uninstall", "--root", str(tmp_path / "nowhere"))
    assert done.returncode == 1 and "no such directory" in done.stderr and "Traceback" not in done.stderr


def test_only_declared_file_settings_are_references_and_a_name_clash_goes_under_files(tmp_path: Path) -> None:
    """What a kind declares a file (field(..., file=...)) is copied, nothing else: the mission manager's
    loop = "file" and a gps setting are words, even beside an existing file called "file"; a declared file
    outside the profile's directory whose place is taken goes under files/SERVICE."""
    from u2sa_hw.install.referenced import find_references

    src = tmp_path / "src"
    (src / "config").mkdir(parents=True)
    (src / "mission.xml").write_text(MISSION)
    (src / "file").write_text("not a mission\n")
    (tmp_path / "mission.xml").write_text(MISSION + "<!-- another -->\n")
    (src / "config/mission.toml").write_text('mission_file = "mission.xml"\nloop = "file"\n')
    (src / "config/world.toml").write_text(f'objects_file = "{tmp_path / "mission.xml"}"\n')
    (src / "config/gps.toml").write_text('device = "file"\nnotes = "mission.xml"\n')
    (src / "vehicle.toml").write_text(PROFILE)
    refs, missing = find_references(load_profile(src / "vehicle.toml"), taken=set())
    assert missing == []
    assert sorted((r.service, r.key, r.dest, r.value, r.secret) for r in refs) == [
        ("mission", "mission_file", "/etc/u2sa/mission.xml", "mission.xml", False),
        ("world", "objects_file", "/etc/u2sa/files/world/mission.xml", "files/world/mission.xml", False)]
    # A declared file naming nothing is a problem naming the service, the setting, the path and the fix.
    (src / "config/world.toml").write_text('objects_file = "nowhere.xml"\n')
    refs, missing = find_references(load_profile(src / "vehicle.toml"), taken={"/etc/u2sa/mission.xml"})
    assert len(missing) == 1, missing
    assert all(word in missing[0] for word in ("world.toml", "service world", "objects_file", str(src / "nowhere.xml"),
                                               "fix:"))
    assert [(r.dest, r.value) for r in refs] == [("/etc/u2sa/files/mission/mission.xml", "files/mission/mission.xml")]


def test_a_file_named_by_a_secret_and_a_plain_setting_is_installed_as_a_secret(tmp_path: Path) -> None:
    from u2sa_hw.install.referenced import Reference, installed_files

    pem = tmp_path / "bridge.pem"
    refs = [Reference("fox", "tls_cert", False, pem, "/etc/u2sa/bridge.pem", "bridge.pem", secret=False),
            Reference("fox", "tls_key", False, pem, "/etc/u2sa/bridge.pem", "bridge.pem", secret=True)]
    assert installed_files(refs) == {"/etc/u2sa/bridge.pem": (pem, True)}
    assert installed_files(refs[:1]) == {"/etc/u2sa/bridge.pem": (pem, False)}


BRIDGE = """
[services.bridge]
kind = "foxglove_bridge"
settings = { token_file = "../secrets/token", tls_cert = "../secrets/bridge.pem", tls_key = "../secrets/bridge.key" }
"""


def test_secret_files_are_installed_root_u2sa_0640_and_the_installed_profile_names_the_copies(
        vehicle: Path, tmp_path: Path) -> None:
    """The bridge's token, certificate and key (declared file="secret") land root:u2sa 0640 whatever their mode in
    the source; a copy loosened on the vehicle is kept but gets its mode back. Missions stay 0644."""
    secrets = tmp_path / "secrets"
    secrets.mkdir()
    for name, text in (("token", "a-token-of-twenty-four-chars\n"), ("bridge.pem", "CERT\n"), ("bridge.key", "KEY\n")):
        (secrets / name).write_text(text)
        (secrets / name).chmod(0o644)
    vehicle.write_text(PROFILE + BRIDGE)
    root = tmp_path / "root"
    (root / "etc").mkdir(parents=True)
    for name in ("passwd", "group", "shadow", "gshadow", "login.defs"):   # useradd --prefix adds u2sa to these
        if Path("/etc", name).exists():
            (root / "etc" / name).write_bytes(Path("/etc", name).read_bytes())
    install(vehicle=vehicle, root=root, venv="shared")
    etc = root / "etc/u2sa"
    gid = next(int(line.split(":")[2]) for line in (root / "etc/group").read_text().splitlines()
               if line.startswith("u2sa:"))
    for name in ("token", "bridge.pem", "bridge.key"):
        st = (etc / "files/bridge" / name).stat()
        assert (st.st_mode & 0o7777, st.st_uid, st.st_gid) == (0o640, 0, gid), name
    assert (etc / "missions/harbour.xml").stat().st_mode & 0o7777 == 0o644
    installed = load_profile(etc / "vehicle.toml")
    assert installed.services["bridge"].settings == {"token_file": "files/bridge/token",
                                                     "tls_cert": "files/bridge/bridge.pem",
                                                     "tls_key": "files/bridge/bridge.key"}
    assert installed.resolve_path(installed.services["bridge"].settings["token_file"]) == etc / "files/bridge/token"
    token = etc / "files/bridge/token"
    token.write_text("another-token-of-twenty-four\n")
    token.chmod(0o644)
    again = install(vehicle=vehicle, root=root, venv="shared")
    assert token.stat().st_mode & 0o7777 == 0o640 and token.read_text() == "another-token-of-twenty-four\n"
    assert any(c.path == "/etc/u2sa/files/bridge/token" and c.action == "updated" for c in again.changes)
    assert (etc / "files/bridge/token.new").stat().st_mode & 0o7777 == 0o640


@pytest.mark.parametrize("example", EXAMPLES)
def test_a_staged_install_of_each_example_passes_u2sa_check_against_the_staged_tree(example: str,
                                                                                    tmp_path: Path) -> None:
    """As on a vehicle: where the example's serial addresses carry no USB id, the user's rule makes the link
    (the line the check asks for); then install goes through and the installed profile checks clean."""
    from u2sa_hw.profile.devices import profile_devices
    from u2sa_hw.install.udev import links_made, plan_devices

    source = REPO / "examples" / example / "vehicle.toml"
    root = tmp_path / "root"
    plan = plan_devices(profile_devices(load_profile(source)), profile_path=source,
                        made_elsewhere=links_made([]))
    if plan.unmade:
        (root / "etc/udev/rules.d").mkdir(parents=True)
        (root / "etc/udev/rules.d/66-u2sa-local.rules").write_text("".join(
            f'SUBSYSTEM=="tty", ATTRS{{idVendor}}=="0403", ATTRS{{idProduct}}=="6001", ATTRS{{serial}}=="{name}", '
            f'SYMLINK+="{path[len("/dev/"):]}"\n' for name, path in plan.unmade))
    done = u2sa("install", "--vehicle", str(source), "--root", str(root), "--venv", "shared")
    assert done.returncode == 0, done.stdout + done.stderr
    installed = root / "etc/u2sa/vehicle.toml"
    check = u2sa("check", "--vehicle", str(installed), env=staged_check_env(root))
    assert check.returncode == 0, check.stdout + check.stderr
    # Every CAN interface comes up at its bitrate (the issue: can0 never came up).
    assert not plan.can_without_bitrate
    rules = (root / "etc/udev/rules.d/65-u2sa-vehicle.rules").read_text()
    for channel, bitrate in plan.can_channels.items():
        assert f'SUBSYSTEM=="net", KERNEL=="{channel}", ENV{{U2SA_CAN_BITRATE}}="{bitrate}"' in rules
    # The mission and objects the example's services name are on the staged vehicle.
    for name in ("mission.xml", "objects.xml"):
        assert (root / "etc/u2sa" / name).read_bytes() == (source.parent / name).read_bytes()
