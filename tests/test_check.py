"""`u2sa check` offline: every problem of a profile at once, one line each, and the exit codes.

Real files in a temporary directory, the real service registry and the real CLI in a
subprocess. Nothing is opened but files.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import pytest

from conftest import REPO, U2SA, unprivileged
from u2sa_hw.check import ERROR, WARNING, Problem, check_profile, errors_of

EXAMPLES = sorted((REPO / "examples").glob("*/vehicle.toml"))


CLEAN = """\
[vehicle]
name = "bench"
log_level = "info"
config_dir = "config"

[services.estimator]
kind = "state_estimator"
settings = { publish_rate_hz = 20.0 }

[services.world]
kind = "world_modeler"

[services.hsm]
kind = "hsm"
"""

MISTAKES = """\
[vehicle]
name = "bad"
log_levle = "info"
log_level = "loud"
config_dir = "config"
origin = { lat = 129.0, lon = 0.0 }

[services.planner]
kind = "path_planer"

[services.gps]
kind = "compass_serial"
devcie = "gnss"
settings = { port = "/dev/ttyUSB0", heading_sigma_deg = "1", health_interval_s = inf }

[services.gps.supervision]
heartbeat_timout_s = 3.0
data_channel = "STATE_INFOO"

[services.compass]
kind = "compass_serial"
settings = { port = "/dev/ttyUSB1" }

[services.imu]
kind = "state_estimator"

[services.mission]
kind = "mission_manager"
settings = { mission_file = "missing.xml" }

[services.world]
kind = "world_modeler"
settings = { objects_file = "objects.xml" }

[services.est]
kind = "state_estimator"
settings = { mode = "kalmann" }

[simulaton]
x = 1

[safety]
hardware_mux = { rudder = "steering" }
"""

# (file name or "" for the profile, key, a word of the message) for each mistake above
EXPECTED = [
    ("", "simulaton", "did you mean 'simulation'"),
    ("", "vehicle.log_levle", "did you mean 'log_level'"),
    ("", "vehicle.log_level", "loud"),
    ("", "vehicle.origin.lat", "129"),
    ("", "services.planner.kind", "did you mean 'path_planner'"),
    ("", "services.gps.devcie", "did you mean 'device'"),
    ("", "services.gps.settings.port", "is the old form"),
    ("", "services.gps.settings.heading_sigma_deg", "float"),
    ("", "services.gps.settings.health_interval_s", "inf"),
    ("", "services.gps.supervision.heartbeat_timout_s", "did you mean 'heartbeat_timeout_s'"),
    ("", "services.gps.supervision.data_channel", "did you mean 'STATE_INFO'"),
    ("compass.toml", "declination_deg", "east"),
    ("compass.toml", "bogus", "bogus"),
    ("est.toml", "", "not UTF-8"),
    ("", "services.mission.settings.mission_file", "does not exist"),
    ("objects.xml", "", ""),
    ("", "services.est.settings", "kalmann"),
    ("", "safety", "'rudder'"),   # checked too, although the loader stops at the unknown keys above
]


def write(tmp: Path, profile: str, files: dict[str, bytes] | None = None) -> Path:
    """The profile and its side files in *tmp*; returns the profile's path."""
    (tmp / "config").mkdir(exist_ok=True)
    for name, data in (files or {}).items():
        (tmp / name).write_bytes(data)
    path = tmp / "vehicle.toml"
    path.write_text(profile)
    return path


def mistakes(tmp: Path) -> Path:
    return write(tmp, MISTAKES, {"config/compass.toml": b'declination_deg = "east"\nbogus = 1\n',
                                 "config/est.toml": b"\xff\xfe\x00binary",
                                 "objects.xml": b"<objects><object>"})


def u2sa(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*U2SA, *args], capture_output=True, text=True, timeout=120, cwd=REPO, env=env)


def test_one_profile_with_many_mistakes_lists_every_one(tmp_path: Path) -> None:
    problems = check_profile(mistakes(tmp_path))
    for file, key, word in EXPECTED:
        found = [p for p in problems if p.file.endswith(file or "vehicle.toml") and word in str(p)
                 and (p.key == key or key and p.key.startswith(key + "."))]
        assert found, f"no problem for {file or 'the profile'} [{key}] mentioning {word!r}:\n" + \
            "\n".join(map(str, problems))
    assert all(p.fix for p in errors_of(problems)), "every error says what to do"
    assert all("\n" not in str(p) for p in problems)
    bogus = next(p for p in problems if p.key == "bogus")
    assert bogus.severity == WARNING   # a config file may hold a newer version's field: kept, reported
    assert len(errors_of(problems)) >= len(EXPECTED) - 1


def test_problem_is_one_line_with_file_key_and_fix() -> None:
    p = Problem(ERROR, "v.toml", "services.gps.kind", "unknown service kind 'gsp'", "use gps_nmea")
    assert str(p) == "error: v.toml [services.gps.kind]: unknown service kind 'gsp'; fix: use gps_nmea"
    assert p.is_error and not Problem(WARNING, "v.toml", "", "x", "y").is_error
    with pytest.raises(AttributeError):
        p.key = "other"   # frozen: another module holds these


OBJECTS_XML = (REPO / "examples/ground_vehicle/objects.xml").read_text()
FILES = """\
[vehicle]
name = "bench"
config_dir = "config"

[services.mission]
kind = "mission_manager"
settings = { mission_file = 42, loop = "notes.txt" }

[services.world]
kind = "world_modeler"
settings = { objects_file = "maps" }

[services.bridge]
kind = "foxglove_bridge"
"""


def test_the_files_a_kind_declares_are_checked_where_their_value_is(tmp_path: Path) -> None:
    """A declared file setting (field(..., file=...)) that names no file is an error on the file and key its value
    is in, with the fix; a non-string value is a type error; a setting not declared a file is not looked at as
    one (loop = "notes.txt" is the mission manager's own problem, not a missing file)."""
    (tmp_path / "maps").mkdir()
    path = write(tmp_path, FILES, {"config/bridge.toml": b'token_file = "secrets/token"\n'})
    problems = check_profile(path)
    by_key = {(Path(p.file).name, p.key): p for p in errors_of(problems)}
    token = by_key[("bridge.toml", "token_file")]
    assert "secrets/token" in token.message and "does not exist" in token.message and "add the file" in token.fix
    objects = by_key[("vehicle.toml", "services.world.settings.objects_file")]
    assert "maps" in objects.message and "not a regular file" in objects.message
    typed = by_key[("vehicle.toml", "services.mission.settings.mission_file")]
    assert "str" in typed.message and "42" in typed.message
    assert not [p for p in problems if "notes.txt" in p.message and "exist" in p.message]
    (tmp_path / "secrets").mkdir()
    (tmp_path / "secrets/token").write_text("a-token-of-twenty-four-chars\n")
    (tmp_path / "maps").rmdir()
    (tmp_path / "maps").write_text(OBJECTS_XML)
    fixed = tmp_path / "vehicle.toml"
    fixed.write_text(FILES.replace("mission_file = 42, ", ""))
    left = check_profile(fixed)
    assert not [p for p in left if "maps" in str(p) or "token" in str(p)], "\n".join(map(str, left))


def test_clean_profile_has_no_problem_and_exits_0(tmp_path: Path) -> None:
    path = write(tmp_path, CLEAN)
    assert check_profile(path) == []
    done = u2sa("check", "--vehicle", str(path))
    assert done.returncode == 0, done.stdout + done.stderr
    assert "0 error(s), 0 warning(s)" in done.stdout


def test_errors_exit_1_and_every_error_is_printed(tmp_path: Path) -> None:
    path = mistakes(tmp_path)
    done = u2sa("check", "--vehicle", str(path))
    assert done.returncode == 1
    lines = [line for line in done.stdout.splitlines() if line.startswith(("error: ", "warning: "))]
    assert len(lines) == len(check_profile(path))
    assert any("[services.planner.kind]" in line and "path_planner" in line for line in lines)


def test_warnings_do_not_fail(tmp_path: Path) -> None:
    path = write(tmp_path, CLEAN.replace('config_dir = "config"', 'config_dir = "nowhere"'))
    problems = check_profile(path)
    assert [p.key for p in problems] == ["vehicle.config_dir"] and problems[0].severity == WARNING
    assert u2sa("check", "--vehicle", str(path)).returncode == 0


def test_json_lists_the_problems(tmp_path: Path) -> None:
    done = u2sa("check", "--vehicle", str(mistakes(tmp_path)), "--json")
    assert done.returncode == 1
    report = json.loads(done.stdout)
    assert report["ok"] is False and report["probes"] == []
    keys = {p["key"] for p in report["problems"]}
    assert {"services.planner.kind", "vehicle.log_levle"} <= keys
    assert set(report["problems"][0]) == {"severity", "file", "key", "message", "fix"}


def test_unreadable_profiles_are_one_error_each(tmp_path: Path) -> None:
    missing = check_profile(tmp_path / "none.toml")
    assert len(missing) == 1 and "not found" in missing[0].message
    (tmp_path / "bin.toml").write_bytes(b"[vehicle]\nname = \"\xff\"\n")
    binary = check_profile(tmp_path / "bin.toml")
    assert len(binary) == 1 and "not UTF-8" in binary[0].message and binary[0].file.endswith("bin.toml")
    (tmp_path / "bad.toml").write_text("[vehicle\n")
    assert "not valid TOML" in check_profile(tmp_path / "bad.toml")[0].message
    assert u2sa("check", "--vehicle", str(tmp_path / "none.toml")).returncode == 1


def test_no_profile_given_is_a_usage_error(tmp_path: Path) -> None:
    import os

    env = {k: v for k, v in os.environ.items() if k != "U2SA_VEHICLE"}
    done = subprocess.run([*U2SA, "check"], capture_output=True, text=True, timeout=60, cwd=tmp_path, env=env)
    if Path("/etc/u2sa/vehicle.toml").exists():
        pytest.skip("this machine has an installed profile, the default")
    assert done.returncode == 2 and "--vehicle" in done.stderr


SERIAL = CLEAN + """
[services.gps]
kind = "gps_nmea"
device = "gps"

[devices.gps]
address = "{address}"
service = "gps"
"""


def test_a_dev_u2sa_link_nothing_creates_is_an_error_with_the_rule_line(tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    rules = tmp_path / "rules.d"
    rules.mkdir()
    monkeypatch.setenv("U2SA_UDEV_RULES_DIRS", str(rules))
    path = write(tmp_path, SERIAL.replace("{address}", "serial:///dev/u2sa/gps?baud=9600"))
    errors = [p for p in errors_of(check_profile(path)) if "/dev/u2sa/gps" in p.message]
    assert len(errors) == 1, "\n".join(map(str, check_profile(path)))
    assert 'SYMLINK+="u2sa/gps"' in errors[0].fix and "usb=" in errors[0].fix
    (rules / "65-u2sa-vehicle.rules").write_text('SUBSYSTEM=="tty", ATTRS{idVendor}=="1546", '
                                                 'ATTRS{idProduct}=="01a7", SYMLINK+="u2sa/gps"\n')
    assert not [p for p in check_profile(path) if "/dev/u2sa/gps" in p.message]
    (rules / "65-u2sa-vehicle.rules").unlink()
    path = write(tmp_path, SERIAL.replace("{address}", "serial:///dev/u2sa/gps?baud=9600&usb=1546:01a7"))
    assert not [p for p in check_profile(path) if "/dev/u2sa/gps" in p.message]


TWO_ADAPTERS = CLEAN + """
[services.gps]
kind = "gps_nmea"

[devices.gps]
address = "serial:///dev/u2sa/gps?baud=9600&usb=0403:6001{gps}"

[services.compass]
kind = "compass_serial"
settings = { format = "nmea" }

[devices.compass]
address = "serial:///dev/u2sa/compass?baud=9600&usb=0403:6001{compass}"
"""


def two_adapters(gps: str, compass: str) -> str:
    return TWO_ADAPTERS.replace("{gps}", gps).replace("{compass}", compass)


@pytest.mark.parametrize("gps, compass, to_change", [("", "", ["gps", "compass"]),
                                                     ("&serial=A1", "", ["compass"]),
                                                     ("", "&serial=A1", ["gps"]),
                                                     ("&serial=A1", "&serial=A1", None)])
def test_two_serial_devices_udev_cannot_tell_apart_are_an_error_naming_both_and_the_fix(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, gps: str, compass: str, to_change: list[str] | None) -> None:
    """One make of adapter (usb=0403:6001) for the GPS and the compass: without a serial number on each,
    the two rules install writes both match one adapter and /dev/u2sa/gps may be the compass."""
    monkeypatch.setenv("U2SA_UDEV_RULES_DIRS", str(tmp_path / "no-rules"))
    path = write(tmp_path, two_adapters(gps, compass))
    errors = errors_of(check_profile(path))
    assert len(errors) == 1, "\n".join(map(str, errors))
    line = str(errors[0])
    assert errors[0].key == f"devices.{(to_change or ['compass'])[-1]}.address", line
    assert (f"devices 'gps' (usb=0403:6001{gps}) and 'compass' (usb=0403:6001{compass}) have "
            "USB identities that do not tell their adapters apart: the udev rules install writes for /dev/u2sa/gps "
            "and /dev/u2sa/compass both match one adapter, so either link may point at the wrong device") in line
    assert "udevadm info -q property -n /dev/ttyUSB0 | grep ID_SERIAL_SHORT" in errors[0].fix
    if to_change:
        names = " and ".join(f"'{n}'" for n in to_change)
        assert f"fix: give each its adapter's own serial number: add &serial=SERIAL to the address of {names}, " \
               f"e.g. serial:///dev/u2sa/{to_change[0]}?baud=9600&usb=0403:6001&serial=SERIAL" in line
    else:
        assert "set serial= of 'gps' and 'compass' to the serial number of each one's own adapter" in line


def test_one_make_of_adapter_with_a_serial_number_each_is_fine(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("U2SA_UDEV_RULES_DIRS", str(tmp_path / "no-rules"))
    path = write(tmp_path, two_adapters("&serial=A1", "&serial=B2"))
    assert check_profile(path) == []
    # Each udev rule then matches its own adapter only; and a serial number alone tells adapters apart too.
    path = write(tmp_path, two_adapters("&serial=A1", "&serial=B2").replace("usb=0403:6001&", ""))
    assert check_profile(path) == []
    # A mock (u2sa sim) has no adapter: nothing to tell apart.
    path = write(tmp_path, two_adapters("", "").replace("serial:///dev/u2sa/", "mock+serial:///run/"))
    assert errors_of(check_profile(path)) == []


OLD_IMU = CLEAN + """
[services.imu]
kind = "imu_mpu9250"
settings = { bus = 1 }
"""


def test_an_old_form_setting_is_one_error_naming_the_new_form(tmp_path: Path) -> None:
    """The old profile form (an address spread over driver settings) is retired: each old key is one error that
    names it and the new form, as text or as a number, in the settings or the service's config file; nothing
    also says the device has no address."""
    new_form = ('name a device instead: [devices.imu] address = "i2c://1/0x68" and device = "imu" '
                '(docs/ports.md)')
    for written in ("bus = 1", 'bus = "1"'):
        path = write(tmp_path, OLD_IMU.replace("bus = 1", written))
        assert [str(p) for p in check_profile(path)] == [
            f"error: {path} [services.imu.settings.bus]: 'bus' is the old form; fix: {new_form}"], written
    # In the service's config file: the line is on that file.
    path = write(tmp_path, OLD_IMU.replace("settings = { bus = 1 }\n", ""), {"config/imu.toml": b'bus = "2"\n'})
    problems = check_profile(path)
    assert [(p.severity, p.file, p.key, p.fix) for p in problems] == [
        ("error", str(tmp_path / "config/imu.toml"), "bus", new_form)], problems
    # The service names another device: the fix names that one.
    path = write(tmp_path, CLEAN + '\n[services.gps]\nkind = "gps_nmea"\n'
                 'settings = { device = "gnss", port = "/dev/ttyUSB0" }\n')
    assert [str(p) for p in check_profile(path)] == [
        f"error: {path} [services.gps.settings.port]: 'port' is the old form; fix: name a device instead: "
        '[devices.gnss] address = "serial:///dev/ttyUSB0?baud=9600" and device = "gnss" (docs/ports.md)']


def test_an_old_form_device_table_key_names_the_address_parameter(tmp_path: Path) -> None:
    path = write(tmp_path, CLEAN + '\n[services.gps]\nkind = "gps_nmea"\n\n[devices.gps]\n'
                 'address = "serial:///dev/u2sa/gps?baud=9600"\nusb = { vendor = "1546", product = "01a7" }\n')
    usb = [p for p in errors_of(check_profile(path)) if p.key.startswith("devices.gps.")
           and p.key != "devices.gps.address"]   # (the address's own: nothing creates /dev/u2sa/gps)
    assert [(p.key, p.message) for p in usb] == [("devices.gps.usb", "'usb' is the old form")], usb
    assert "usb=1546:01a7" in usb[0].fix and "docs/ports.md" in usb[0].fix


def test_a_setting_of_another_kind_with_an_old_form_name_is_not_the_old_form(tmp_path: Path) -> None:
    """Only a driver's (a kind with a device setting) unknown key is the old form: an IMU's chip is its own
    setting, and a service that opens no device gets the usual unknown-key error."""
    path = write(tmp_path, CLEAN + '\n[services.imu]\nkind = "imu_mpu9250"\nsettings = { chip = "mpu6500" }\n'
                 '\n[devices.imu]\naddress = "i2c://1/0x68"\n')
    assert errors_of(check_profile(path)) == []
    path = write(tmp_path, CLEAN.replace("settings = { publish_rate_hz = 20.0 }", "settings = { port = 1 }"))
    errors = errors_of(check_profile(path))
    assert [p.key for p in errors] == ["services.estimator.settings.port"], errors
    assert "is not a setting of this service" in errors[0].message


def test_for_sim_a_device_without_a_mock_names_the_device_and_the_mock(tmp_path: Path) -> None:
    path = write(tmp_path, SERIAL.replace("{address}", "serial:///dev/u2sa/gps?baud=9600"))
    errors = errors_of(check_profile(path, for_sim=True))
    assert [p.key for p in errors] == ["devices.gps"], "\n".join(map(str, errors))
    assert "device 'gps' of service 'gps'" in errors[0].message and 'mock = "nmea_gps"' in errors[0].fix
    assert not any("/dev/u2sa" in p.message for p in errors)   # the mock stands in: no udev rule needed


@pytest.mark.parametrize("example", EXAMPLES, ids=lambda p: p.parent.name)
def test_each_example_profile_checks_clean(example: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Clean for u2sa sim, and on a vehicle with no udev rules of its own: the examples' serial addresses
    carry their adapters' USB ids, from which install writes the rules that make /dev/u2sa/gps and compass.

    Without those ids exactly those two links are errors, each with the rule line to add, until an
    installed rule makes them.
    """
    assert errors_of(check_profile(example, for_sim=True)) == []
    rules = tmp_path / "rules.d"
    rules.mkdir()
    monkeypatch.setenv("U2SA_UDEV_RULES_DIRS", str(rules))   # this machine's own rules do not matter
    errors = errors_of(check_profile(example))
    assert errors == [], "\n".join(map(str, errors))
    copy = tmp_path / "example"
    shutil.copytree(example.parent, copy)
    text = (copy / "vehicle.toml").read_text()
    assert "&usb=1546:01a7" in text and "&usb=0403:6001" in text
    (copy / "vehicle.toml").write_text(text.replace("&usb=1546:01a7", "").replace("&usb=0403:6001", ""))
    unmade = errors_of(check_profile(copy / "vehicle.toml"))
    assert sorted(p.message.split()[2].rstrip(":") for p in unmade) == ["/dev/u2sa/compass", "/dev/u2sa/gps"], \
        "\n".join(map(str, unmade))
    assert all('SYMLINK+="u2sa/' in p.fix for p in unmade)
    (rules / "66-u2sa-local.rules").write_text(
        'SUBSYSTEM=="tty", ATTRS{idVendor}=="1546", ATTRS{idProduct}=="01a7", SYMLINK+="u2sa/gps"\n'
        'SUBSYSTEM=="tty", ATTRS{idVendor}=="0403", ATTRS{idProduct}=="6001", SYMLINK+="u2sa/compass"\n')
    errors = errors_of(check_profile(copy / "vehicle.toml"))
    assert errors == [], "\n".join(map(str, errors))


def test_run_refuses_a_profile_with_errors_and_lists_them(tmp_path: Path) -> None:
    done = u2sa("run", "--vehicle", str(mistakes(tmp_path)))
    assert done.returncode == 1
    assert "nothing was started" in done.stderr
    assert "[services.planner.kind]" in done.stderr and "[vehicle.log_levle]" in done.stderr


def test_sim_refuses_a_device_without_a_mock_at_start(tmp_path: Path) -> None:
    path = write(tmp_path, SERIAL.replace("{address}", "serial:///dev/u2sa/gps?baud=9600"))
    done = u2sa("sim", "--vehicle", str(path), "--out", str(tmp_path / "out"), "--timeout", "30")
    assert done.returncode == 1, done.stdout + done.stderr
    assert "[devices.gps]" in done.stderr and 'mock = "nmea_gps"' in done.stderr
    assert not (tmp_path / "out" / "services.log").exists()   # refused before anything started


def test_sim_shows_a_service_device_error_on_the_console_once() -> None:
    """While the stack starts, each service's health error (a missing device and its fix) is printed, once."""
    import io

    from u2sa_hw.simulation.progress import BusSnapshot, ProgressLine
    from u2sa_hw.simulation.readiness import say_errors

    out = io.StringIO()
    progress = ProgressLine(out, interactive=False)   # only the console half: no profile, no mocks, no bus
    said: dict[str, str] = {}
    error = "gps (serial:///dev/u2sa/gps?baud=9600): no such device; fix: plug it in or check the address"
    snap = BusSnapshot()
    snap.health.update({"gps": ("error", error, 0.0), "imu": ("ok", "", 0.0), "other": ("error", "x", 0.0)})
    say_errors(snap, ["gps", "imu"], said, progress.event)
    say_errors(snap, ["gps", "imu"], said, progress.event)
    assert out.getvalue().count("! gps error: " + error) == 1
    assert "imu" not in out.getvalue() and "other" not in out.getvalue()


def test_run_force_goes_past_errors_but_never_past_a_safety_error(tmp_path: Path) -> None:
    done = u2sa("run", "--vehicle", str(mistakes(tmp_path)), "--force")   # MISTAKES has a [safety] error too
    assert done.returncode == 1 and "nothing was started" in done.stderr
    assert "[safety]: hardware_mux: no service has an actuator 'rudder'" in done.stderr, done.stderr


def test_a_secret_file_this_user_cannot_read_is_a_warning_and_a_mission_an_error() -> None:
    """Installed root:u2sa 0640, a token is unreadable to a user outside the group u2sa: the services read it as
    u2sa, so the check says it could not look (warning); a mission the user cannot read stays an error."""
    workdir = Path(tempfile.mkdtemp(prefix="u2sa-secret-"))
    try:
        profile = write(workdir, FILES.replace("mission_file = 42, ", 'mission_file = "mission.xml", ')
                        .replace('objects_file = "maps"', 'objects_file = ""'),
                        {"config/bridge.toml": b'token_file = "token"\n', "token": b"a-token-of-twenty-four-chars\n",
                         "mission.xml": (REPO / "examples/ground_vehicle/mission.xml").read_bytes()})
        for path in (workdir, workdir / "config", profile, workdir / "config/bridge.toml"):
            os.chmod(path, 0o755 if path.is_dir() else 0o644)
        os.chmod(workdir / "token", 0o600)
        os.chmod(workdir / "mission.xml", 0o600)
        code = textwrap.dedent(f"""\
            from u2sa_hw.check import check_profile
            for p in check_profile({str(profile)!r}):
                print(p.severity, p.file, p.message)
            """)
        done = subprocess.run(unprivileged([sys.executable, "-c", code]), capture_output=True, text=True, timeout=120,
                              env=dict(os.environ, PYTHONPATH=str(REPO)), cwd="/")
        assert done.returncode == 0, done.stderr
        lines = done.stdout.splitlines()
        assert any(line.startswith(f"warning {workdir / 'token'} a secret this user cannot read") for line in lines), \
            done.stdout
        assert any(line.startswith(f"error {workdir / 'mission.xml'}") for line in lines), done.stdout
    finally:
        shutil.rmtree(workdir, ignore_errors=True)


def test_a_device_with_no_address_is_one_error(tmp_path: Path) -> None:
    """The RC mux's device table without an address: the driver's own check names the missing line (with a
    gpio example); the device list does not say it a second time (with a serial example)."""
    path = write(tmp_path, CLEAN + '\n[services.rc]\nkind = "rc_mux"\nsettings = { channels = "mode=13" }\n'
                 '\n[devices.rc]\nmock = "rc_receiver"\n')
    errors = [p for p in errors_of(check_profile(path)) if "'rc'" in p.message]
    assert len(errors) == 1, "\n".join(map(str, errors))
    assert "no address: add [devices.rc] address" in errors[0].message and "gpio://" in errors[0].message
    assert "serial:///dev/u2sa/rc" not in str(errors[0])
