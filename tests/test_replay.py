"""u2sa replay: a driver-level log recorded here (mock GPS and compass on ptys, the real drivers
as processes with record_raw, the recorder's capture) is replayed into the real drivers through
replay devices, compared with --compare, changed with --set, replayed twice, and refused when
damaged."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Iterator

import pytest
import tomli_w
from can_mock_harness import GROUP, Commander, MockCanProcess
from conftest import REPO, wait_until
from recorded_sim import held_up

from u2sa_hw.hil.compare import load_streams
from u2sa_hw.hil.compare_stream import align, compare_stream
from u2sa_hw.hil.compare_values import Sample, values_equal
from u2sa_hw.hil.progress import format_duration, progress_line
from u2sa_hw.hil.replay_plan import ReplayError, build_plan, parse_overrides
from u2sa_hw.profile.devices import resolve_devices
from u2sa_hw.mocks.i2c_bus import MockI2cBus
from u2sa_hw.mocks.mpu9250_chip import Mpu9250Chip
from u2sa_hw.mocks.nmea_gps import NmeaGpsDevice
from u2sa_hw.mocks.serial_compass import NmeaCompassDevice
from u2sa_hw.mocks.vehicle_sim import SimVehicle
from u2sa_hw.bus.client import BusClient
from u2sa_hw.lcmtypes import RawSerial
from u2sa_hw.recording.mcap_log import McapLogWriter, RunInfo
from u2sa_hw.services.recorder.capture import BusCapture
from u2sa_hw.services.recorder.service import run_info
from u2sa_hw.bus.transport import Transport
from u2sa_hw.profile.loader import load_profile
from u2sa_hw.bus.udp_ports import private_lcm_url, private_udp_port

GGA_TIME = re.compile(rb"\$[A-Z]{2}GGA,(\d{6}(?:\.\d*)?),")
ORIGIN = {"lat": 29.1895, "lon": -81.0483, "alt": 10.0}
U2SA = [sys.executable, "-m", "u2sa_hw.cli"]


def _url() -> str:
    return private_lcm_url()


def record_driver_log(workdir: Path, *, gps_epochs: int = 12, compass_epochs: int = 24) -> Path:
    """Record a log with the GPS and compass drivers tapping their raw input; returns its path.

    The log holds at least *gps_epochs* whole GPS epochs (counted by their GGA time, not by chunks: a
    loaded machine splits an epoch over reads) and *compass_epochs* raw compass chunks."""
    url = _url()
    dev = workdir / "dev"
    profile_path = workdir / "vehicle.toml"
    profile_path.write_text(tomli_w.dumps({
        "vehicle": {"name": "testrover", "system_id": 7, "origin": ORIGIN, "lcm_url": url},
        "services": {
            "gps": {"kind": "gps_nmea", "settings": {"record_raw": True}},
            "compass": {"kind": "compass_serial", "settings": {"record_raw": True, "device_name": "hdg"}},
            "state_estimator": {"kind": "state_estimator"}},
        "devices": {"gps": {"address": f"serial://{dev / 'gps'}?baud=9600"},
                    "hdg": {"address": f"serial://{dev / 'compass'}?baud=4800"}}}))
    profile = load_profile(profile_path)
    vehicle = SimVehicle(origin_lat=ORIGIN["lat"], origin_lon=ORIGIN["lon"], origin_alt=ORIGIN["alt"])
    vehicle.set_wheel_speed("left", 1.0)
    vehicle.set_wheel_speed("right", 1.3)
    vehicle.start()
    gps = NmeaGpsDevice(vehicle, link_path=dev / "gps", rate_hz=5, seed=1)
    compass = NmeaCompassDevice(vehicle, link_path=dev / "compass", rate_hz=10, sentences=("HDG", "XDR"), seed=2)
    transport = Transport(url, name="test-recorder")
    log_path = workdir / "run.mcap"
    capture = BusCapture(transport, McapLogWriter(workdir, path=log_path, run=run_info(profile, url)))
    capture.start()
    epochs: set[bytes] = set()   # GPS epochs seen (a chunk may hold part of one, or be a recorded silence)
    transport.subscribe("RAW.gps", RawSerial, lambda _c, raw: epochs.update(GGA_TIME.findall(bytes(raw.data))))
    transport.start()
    gps.start()
    compass.start()
    env = dict(os.environ, PYTHONPATH=str(REPO), U2SA_LCM_URL=url)
    procs = [subprocess.Popen([*U2SA, "service", name, "--vehicle", str(profile_path)], cwd=workdir, env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) for name in ("gps", "compass")]
    try:
        per = capture.stats.per_channel
        # one epoch more than asked: the last one seen may be cut by the stop
        wait_until(lambda: len(epochs) > gps_epochs and per.get("RAW.hdg", 0) >= compass_epochs,
                   timeout=60, message="raw GPS and compass input recorded")
    finally:
        gps.stop()
        compass.stop()
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait(timeout=60)   # a stop on a loaded machine (make test once saw gps exceed 10 s): no timing here
        capture.stop()
        transport.stop()
        vehicle.stop()
    return log_path


def record_imu_log(workdir: Path, *, samples: int = 80) -> Path:
    """Record a log of the MPU-9250 driver (I2C, record_raw) sampling a mock chip on a turning rover."""
    url = _url()
    vehicle = SimVehicle(origin_lat=ORIGIN["lat"], origin_lon=ORIGIN["lon"], origin_alt=ORIGIN["alt"])
    vehicle.set_wheel_speed("left", 1.0)
    vehicle.set_wheel_speed("right", 0.6)
    vehicle.start(rate_hz=200)
    sockets = Path(tempfile.mkdtemp(prefix="rpi2c", dir="/tmp"))  # Unix socket paths must stay short
    i2c = MockI2cBus(socket_path=str(sockets / "bus.sock"))
    i2c.add(Mpu9250Chip(vehicle=vehicle, seed=3))
    profile_path = workdir / "vehicle.toml"
    profile_path.write_text(tomli_w.dumps({
        "vehicle": {"name": "testrover", "system_id": 7, "origin": ORIGIN, "lcm_url": url},
        "services": {"imu": {"kind": "imu_mpu9250", "settings": {
            "record_raw": True, "rate_hz": 50.0, "calibrate_samples": 20}}},
        "devices": {"imu": {"address": f"mock+i2c://{i2c.socket_path}/0x68"}}}))
    transport = Transport(url, name="test-recorder")
    log_path = workdir / "imu.mcap"
    capture = BusCapture(transport, McapLogWriter(workdir, path=log_path,
                                                  run=run_info(load_profile(profile_path), url)))
    capture.start()
    transport.start()
    i2c.start()
    env = dict(os.environ, PYTHONPATH=str(REPO), U2SA_LCM_URL=url)
    proc = subprocess.Popen([*U2SA, "service", "imu", "--vehicle", str(profile_path)], cwd=workdir, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_until(lambda: capture.stats.per_channel.get("STATE_INFO", 0) >= samples, timeout=30,
                   message="IMU samples recorded")
    finally:
        proc.terminate()
        proc.wait(timeout=10)
        capture.stop()
        transport.stop()
        i2c.stop()
        vehicle.stop()
        shutil.rmtree(sockets, ignore_errors=True)
    return log_path


def record_can_log(workdir: Path, *, outputs: int = 120) -> Path:
    """Record a log of the ODrive driver (CAN, record_raw) driving two mock nodes under Percentage Commands."""
    url = _url()
    port = private_udp_port()
    nodes = [{"side": "left", "node_id": 0, "vel_limit": 10.0}, {"side": "right", "node_id": 1, "vel_limit": 10.0}]
    mock = MockCanProcess({"kind": "odrive", "port": port, "nodes": nodes}, repo=REPO, log=workdir / "mock.log")
    profile_path = workdir / "vehicle.toml"
    profile_path.write_text(tomli_w.dumps({
        "vehicle": {"name": "testrover", "system_id": 7, "origin": ORIGIN, "lcm_url": url},
        "services": {"wheels": {"kind": "odrive_can", "settings": {
            "node_ids": [0, 1], "record_raw": True, "command_timeout_s": 0.0, "rc_gating": False}}},
        "devices": {"wheels": {"address": f"can://udp_multicast/{GROUP}?port={port}"}}}))
    transport = Transport(url, name="test-recorder")
    log_path = workdir / "can.mcap"
    capture = BusCapture(transport, McapLogWriter(workdir, path=log_path,
                                                  run=run_info(load_profile(profile_path), url)))
    capture.start()
    transport.start()
    client = BusClient(url)
    commander = Commander(client)
    env = dict(os.environ, PYTHONPATH=str(REPO), U2SA_LCM_URL=url)
    proc = subprocess.Popen([*U2SA, "service", "wheels", "--vehicle", str(profile_path)], cwd=workdir, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        commander.hold(left=40.0, right=60.0)
        odometry = lambda: capture.stats.per_channel.get("STATE_INFO", 0)  # noqa: E731
        wait_until(lambda: odometry() >= outputs // 2, timeout=30, message="odometry recorded")
        commander.hold(left=-20.0, right=30.0)
        wait_until(lambda: odometry() >= outputs, timeout=30, message="more odometry recorded")
    finally:
        commander.close()
        proc.terminate()
        proc.wait(timeout=10)
        capture.stop()
        transport.stop()
        client.close()
        mock.stop()
    return log_path


@pytest.fixture(scope="module")
def can_log(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """One recorded CAN motor log shared by the tests of this module."""
    yield record_can_log(tmp_path_factory.mktemp("recorded-can"))


@pytest.fixture(scope="module")
def imu_log(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """One recorded I2C IMU log shared by the tests of this module."""
    yield record_imu_log(tmp_path_factory.mktemp("recorded-imu"))


@pytest.fixture(scope="module")
def driver_log(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """One recorded driver-level log shared by the tests of this module."""
    yield record_driver_log(tmp_path_factory.mktemp("recorded"))


def replay_cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.pop("U2SA_LCM_URL", None)
    return subprocess.run([*U2SA, "replay", *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=120)


# ------------------------------------------------------------------ planning and pure parts --------
def test_devices_map_to_the_services_that_name_them(driver_log: Path) -> None:
    plan = build_plan(driver_log)
    assert {d.name: d.service for d in plan.devices.values()} == {"gps": "gps", "hdg": "compass"}
    assert sorted(plan.services) == ["compass", "gps"]
    assert plan.devices["hdg"].kind == "serial" and plan.devices["hdg"].records > 0
    # a recorded service without a kind claims its own name and the channel names its settings give
    claims = resolve_devices({"services": {"servo": {}}}, configs={"servo": {"channels": [{"name": "rudder"}]}},
                             strict=False).users
    assert claims == {"servo": ("servo",), "rudder": ("servo",)}
    with_estimator = build_plan(driver_log, extra_services=["state_estimator"], overrides=["gps.heading_sigma_deg=2"])
    assert with_estimator.services["gps"].overrides == {"heading_sigma_deg": 2.0}
    assert "state_estimator" in with_estimator.services


@pytest.mark.parametrize("overrides, expected", [
    (["gps.nope=1"], "has no config field 'nope'"),
    (["gps.uere_m=fast"], "expects float"),
    (["uere_m=9"], "expected SERVICE.FIELD=VALUE"),
    (["radar.range=9"], "service 'radar' is not replayed"),
])
def test_bad_overrides_are_refused_with_the_reason(driver_log: Path, overrides: list[str], expected: str) -> None:
    with pytest.raises(ReplayError, match=expected):
        build_plan(driver_log, overrides=overrides)
    assert parse_overrides(["gps.position_frame=GEODETIC"]) == {"gps": {"position_frame": "GEODETIC"}}


def test_alignment_skips_a_cut_message_at_the_start_and_floats_compare_within_tolerance() -> None:
    def s(x: float) -> Sample:
        return Sample(0, "StateInformation", {"x": x, "sensor_name": "gps"})

    rec = [s(v) for v in (0.5, 1.0, 2.0, 3.0)]
    rep = [s(v) for v in (1.0, 2.0, 3.0 + 1e-9)]
    assert [p.kind for p in align(rec, rep, tolerance=1e-6)] == ["deleted", "match", "match", "match"]
    report = compare_stream("STATE_INFO [gps]", rec, rep, tolerance=1e-6, edge=1, rate=None, time_tolerance_s=1)
    assert report.ok and report.matched == 3 and report.notes
    strict = compare_stream("STATE_INFO [gps]", rec, rep, tolerance=1e-6, edge=0, rate=None, time_tolerance_s=1)
    assert not strict.ok and strict.deleted == 1 and strict.matched == 3 and strict.differing == 0
    assert values_equal(float("nan"), float("nan"), 0.0) and not values_equal(1.0, 1.1, 0.01)
    assert format_duration(3725) == "1:02:05" and "ETA 0:03" in progress_line(10, 20, 3.0)


# ------------------------------------------------------------------ replay end to end -------------
def test_fast_replay_reproduces_the_recorded_outputs(driver_log: Path, tmp_path: Path) -> None:
    out = tmp_path / "replayed.mcap"
    res = replay_cli(str(driver_log), "--fast", "--compare", "-o", str(out), cwd=tmp_path)
    assert "STATE_INFO [gps]" in res.stdout and "STATE_INFO [compass]" in res.stdout
    held = held_up(driver_log)
    if "gps" in held:   # the loaded recording machine split a live epoch: the GPS row is reported, not gated
        print(f"gps held up while recording ({held['gps']}):\n{res.stdout}")
        assert res.returncode in (0, 1), res.stdout + res.stderr
        assert any(line.startswith("STATE_INFO [compass]") and line.rstrip().endswith("same")
                   for line in res.stdout.splitlines()), res.stdout
    else:
        assert res.returncode == 0, res.stdout + res.stderr
        assert "compare: OK" in res.stdout
    streams = load_streams(out, sources={"gps", "compass"})
    recorded = load_streams(driver_log, sources={"gps", "compass"})
    # as many as the recording holds, but for the first and last (compare's edge notes); how many that is
    # depends on the recording machine's load
    for key in ("STATE_INFO [gps]", "STATE_INFO [compass]"):
        assert len(recorded[key]) >= 5 and abs(len(streams[key]) - len(recorded[key])) <= 2, \
            (key, len(streams[key]), len(recorded[key]))
    assert not (tmp_path / "replayed.mcap").with_suffix(".replay.mcap").exists()


def test_a_changed_setting_is_reported_and_fails_the_comparison(driver_log: Path, tmp_path: Path) -> None:
    res = replay_cli(str(driver_log), "--fast", "--compare", "--set", "gps.position_frame=GEODETIC",
                     "-o", str(tmp_path / "geo.mcap"), cwd=tmp_path)
    assert res.returncode == 1, res.stdout + res.stderr
    rows = {line.split()[1].strip("[]"): line for line in res.stdout.splitlines() if line.startswith("STATE_INFO")}
    assert rows["gps"].endswith("DIFFERENT") and rows["compass"].endswith("same")
    assert "reference_frame: differs" in res.stdout and "DIFFERENT 1 of 2 streams" in res.stdout


def test_two_replays_give_the_same_messages(driver_log: Path, tmp_path: Path) -> None:
    outs = [tmp_path / "one.mcap", tmp_path / "two.mcap"]
    for out in outs:
        res = replay_cli(str(driver_log), "--fast", "-o", str(out), cwd=tmp_path)
        assert res.returncode == 0, res.stdout + res.stderr
        assert "replayed" in res.stdout and "x real time" in res.stdout
    one, two = (load_streams(o, sources={"gps", "compass"}) for o in outs)
    assert one.keys() == two.keys() == {"STATE_INFO [gps]", "STATE_INFO [compass]"}
    for key in one:
        assert [s.fields for s in one[key]] == [s.fields for s in two[key]], key


def test_timed_replay_of_a_window_compares_with_timing(driver_log: Path, tmp_path: Path) -> None:
    # the window starts where the log does: a compass replayed from inside a log learns its burst order
    # again, so its first bursts there come sentence by sentence (docs/replay.md, Determinism)
    res = replay_cli(str(driver_log), "--rate", "2", "--start", "0", "--end", "2.5", "--compare",
                     "--time-tolerance", "5", "--edge", "2", "--services", "state_estimator",
                     "-o", str(tmp_path / "w.mcap"), cwd=tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "--rate 2" in res.stdout and "timing not checked" not in res.stdout
    summary = res.stdout.splitlines()[0]  # a core service ran on the replayed sensors' output
    assert "starting 3 services" in summary and "state_estimator" in summary.split("messages from")[1]
    gps_row = next(line for line in res.stdout.splitlines() if line.startswith("STATE_INFO [gps]"))
    assert "/" in gps_row.split()[-2]  # TIME p50/max filled in


def test_damaged_logs_get_a_clear_error(driver_log: Path, tmp_path: Path) -> None:
    data = driver_log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    res = replay_cli(str(cut), "--fast", cwd=tmp_path)
    assert res.returncode == 2 and "truncated" in res.stderr and "u2sa log recover" in res.stderr
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x00garbage" * 100)
    res = replay_cli(str(junk), cwd=tmp_path)
    assert res.returncode == 2 and "not an MCAP file" in res.stderr
    bare = tmp_path / "bare.mcap"  # recorded without a vehicle profile: nothing says who drives RAW.gps
    writer = McapLogWriter(tmp_path, path=bare, run=RunInfo())
    for record in load_raw(driver_log):
        writer.write(*record)
    writer.close()
    res = replay_cli(str(bare), cwd=tmp_path)
    assert res.returncode == 2 and "--vehicle" in res.stderr, res.stderr
    assert not list(Path(tmp_path).glob("*.replay.mcap"))


def load_raw(path: Path) -> list[tuple[str, bytes, int]]:
    from u2sa_hw.recording.log_reader import LogFile

    return [(m.channel, m.data, m.log_time_ns) for m in LogFile(path).messages(r"RAW\..*")]


def test_i2c_reads_replay_into_the_imu_driver(imu_log: Path, tmp_path: Path) -> None:
    res = replay_cli(str(imu_log), "--fast", "--compare", "-o", str(tmp_path / "imu.mcap"), cwd=tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    row = next(line for line in res.stdout.splitlines() if line.startswith("STATE_INFO [imu]"))
    recorded, replayed = (int(v) for v in row.split()[2:4])
    assert recorded == replayed >= 80 and row.endswith("same")
    # the recorded gyro counts were taken at 500 deg/s full scale; read as 1000 deg/s they double
    res = replay_cli(str(imu_log), "--fast", "--compare", "--set", "imu.gyro_range_dps=1000",
                     "-o", str(tmp_path / "imu1000.mcap"), cwd=tmp_path)
    assert res.returncode == 1, res.stdout + res.stderr
    assert "psi_dot: differs" in res.stdout and "write" in res.stderr  # the config write differs from the log's


def log_with_a_pause(src: Path, dst: Path, pause_s: float) -> None:
    """A copy of *src* with every message from the middle of its window on *pause_s* later (a recorded pause)."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with src.open("rb") as f_in, dst.open("wb") as f_out:
        reader = make_reader(f_in)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        middle = (summary.statistics.message_start_time + summary.statistics.message_end_time) // 2
        writer = Writer(f_out)
        header = reader.get_header()
        writer.start(profile=header.profile, library=header.library)
        schemas = {sid: writer.register_schema(x.name, x.encoding, x.data) for sid, x in summary.schemas.items()}
        channels = {cid: writer.register_channel(c.topic, c.message_encoding, schemas.get(c.schema_id, 0),
                                                 dict(c.metadata)) for cid, c in summary.channels.items()}
        for _schema, channel, message in reader.iter_messages(log_time_order=True):
            shift = int(pause_s * 1e9) if message.log_time >= middle else 0
            writer.add_message(channels[channel.id], message.log_time + shift, message.data,
                               message.publish_time + shift, message.sequence)
        for attachment in reader.iter_attachments():
            writer.add_attachment(attachment.create_time, attachment.log_time, attachment.name,
                                  attachment.media_type, attachment.data)
        for metadata in reader.iter_metadata():
            writer.add_metadata(metadata.name, dict(metadata.metadata))
        writer.finish()


def test_a_timed_i2c_replay_holds_the_imu_reads_for_the_player(imu_log: Path, tmp_path: Path) -> None:
    """--rate 1: each recorded data read is released at its recorded time and the driver, sampling at its
    own rate, waits when it is ahead: through a recorded 3 s pause too, longer than the launcher's 2 s
    watchdog (which the replay leaves off for a driver whose reads it holds)."""
    paused = tmp_path / "paused.mcap"
    log_with_a_pause(imu_log, paused, 3.0)
    res = replay_cli(str(paused), "--rate", "1", "--compare", "-o", str(tmp_path / "imu.mcap"), cwd=tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    row = next(line for line in res.stdout.splitlines() if line.startswith("STATE_INFO [imu]"))
    recorded, replayed = (int(v) for v in row.split()[2:4])
    assert recorded == replayed >= 80 and row.endswith("same"), row
    assert "device imu" not in res.stderr, res.stderr   # no read without a recorded answer, no write unlike them


def test_can_frames_replay_into_the_motor_driver_with_its_commands(can_log: Path, tmp_path: Path) -> None:
    res = replay_cli(str(can_log), "--fast", "--compare", "-o", str(tmp_path / "can.mcap"), cwd=tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    row = next(line for line in res.stdout.splitlines() if line.startswith("STATE_INFO [wheels]"))
    recorded, replayed = (int(v) for v in row.split()[2:4])
    assert recorded == replayed >= 120 and row.endswith("same")
    # the driver subscribes to ACTUATOR_CMD: the recorded commands were played to it on the replay bus
    from u2sa_hw.recording.log_reader import LogFile

    assert sum(1 for _ in LogFile(tmp_path / "can.mcap").messages("ACTUATOR_CMD")) > 10
    res = replay_cli(str(can_log), "--fast", "--compare", "--set", "wheels.wheel_radius_m=[0.2, 0.2]",
                     "-o", str(tmp_path / "can2.mcap"), cwd=tmp_path)
    assert res.returncode == 1 and "x_dot: differs" in res.stdout, res.stdout + res.stderr


def test_a_service_that_dies_ends_the_replay_with_its_reason(driver_log: Path, tmp_path: Path) -> None:
    # a value its field refuses never gets as far as a start: one line, exit 2, nothing replayed
    res = replay_cli(str(driver_log), "--fast", "--set", "gps.position_frame=XYZ", "-o", str(tmp_path / "x.mcap"),
                     cwd=tmp_path)
    assert res.returncode == 2 and res.stderr.strip().splitlines() == [
        "u2sa: --set gps.position_frame=XYZ: field 'position_frame' must be one of \"NED\", \"GEODETIC\" (any case); "
        "got \"XYZ\""], res.stderr
    # values each field takes but the driver cannot start with (a singular soft-iron matrix)
    res = replay_cli(str(driver_log), "--fast", "--set", "compass.mag_matrix=[0,0,0,0,0,0,0,0,0]",
                     "-o", str(tmp_path / "x.mcap"), cwd=tmp_path)
    assert res.returncode == 2   # the replay failed (1 would mean "outputs differ")
    assert "service 'compass' died during the replay" in res.stderr and "mag_matrix" in res.stderr, res.stderr
    kept = res.stderr.rsplit("replay files kept in ", 1)[1].strip(" )\n")
    assert (Path(kept) / "config" / "compass.toml").read_text().count("mag_matrix = [") == 1
    shutil.rmtree(kept, ignore_errors=True)


def test_the_replay_ends_only_once_each_service_took_what_was_republished_to_it() -> None:
    """The end of a replay waits for every service's health to count the recorded messages republished to it
    (a servo driver's last command, its only output a write, was lost on a loaded machine), then settle_s."""
    import threading

    from u2sa_hw.hil.replay_watch import ReplayWatch

    watch = ReplayWatch({"servos", "wheels"})   # only the end-of-run wait: no log, no services
    abort = threading.Event()
    watch.last_output = 0.0
    watch.listeners = {"ACTUATOR_CMD": {"servos", "wheels"}, "FAILSAFE": set()}
    watch.heard = {"servos": {"ACTUATOR_CMD": 3}, "wheels": {"ACTUATOR_CMD": 2}}
    sent = {"ACTUATOR_CMD": 3, "FAILSAFE": 1}
    assert watch.behind(sent) == [("wheels", "ACTUATOR_CMD")]   # nobody takes FAILSAFE from the bus here
    ended = threading.Event()
    waiter = threading.Thread(target=lambda: (watch.settle(sent, 0.0, abort=abort, reason=str), ended.set()),
                              daemon=True)
    waiter.start()
    assert not ended.wait(0.3)   # the wheels' health still counts 2 of the 3
    watch.heard = {"servos": {"ACTUATOR_CMD": 3}, "wheels": {"ACTUATOR_CMD": 4}}   # (it hears live ones too)
    assert ended.wait(10.0) and watch.behind(sent) == []
