"""The recorder service and `u2sa record` / `u2sa log`: real processes, real MCAP files."""

from __future__ import annotations

import json
import re
import shutil
import signal
import subprocess
import sys
import threading
from pathlib import Path
from types import SimpleNamespace

import pytest
import tomli_w
from conftest import ServiceProcesses, wait_until
from gpio_driver_harness import BusCollector
from mcap.reader import make_reader

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.recording.log_reader import LogError, LogFile
from u2sa_hw.recording.mcap_log import McapLogWriter
from u2sa_hw.services.recorder.capture import BusCapture
from u2sa_hw.bus.transport import Transport

TIMESTAMPED = re.compile(r"u2sa-\d{8}-\d{6}(_\d{3})?\.mcap")


def _profile(tmp: Path, url: str, **recorder: object) -> Path:
    path = tmp / "vehicle.toml"
    path.write_text(tomli_w.dumps({"vehicle": {"name": "testbot", "system_id": 7, "lcm_url": url},
                                   "services": {"recorder": {"kind": "recorder", "settings": recorder}}}))
    return path


def _recorder_files(tmp: Path) -> list[Path]:
    return sorted((tmp / "data" / "recordings").glob("*.mcap"))


def _count(path: Path, channel: str) -> int:
    """Messages of *channel* in the log so far (0 while the writer has not flushed even the magic bytes)."""
    try:
        return sum(1 for _ in LogFile(path).messages(channel))
    except LogError:
        return 0


def _state(i: int) -> t.StateInformation:
    s = t.StateInformation().set(x=float(i), psi=0.5)
    s.sensor_name = "gps"
    return s


def test_recorder_writes_indexed_log_with_schemas_and_profile(services: ServiceProcesses, bus: BusClient) -> None:
    vehicle = _profile(services.workdir, services.url)
    proc = services.start("recorder", "--vehicle", str(vehicle))
    wait_until(lambda: bus.discover(timeout=0.3, name="recorder"), timeout=20, message="the recorder")
    for i in range(50):
        bus.publish(ch.STATE_INFO, _state(i))
    raw = t.RawSerial()
    raw.device, raw.data, raw.length = "gps", b"$GPGGA,...*00\r\n", 15
    bus.publish("RAW.gps", raw)

    def recorded() -> int:
        files = _recorder_files(services.workdir)
        return files and _count(files[0], ch.STATE_INFO)

    wait_until(lambda: recorded() == 50, timeout=15, message="50 messages flushed to disk")
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=15) == 0
    path = _recorder_files(services.workdir)[0]
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary.statistics.channel_message_counts and summary.chunk_indexes
        schemas = {s.name: s for s in summary.schemas.values()}
        assert schemas["StateInformation"].encoding == "lcm"
        assert b"struct StateInformation" in schemas["StateInformation"].data
        assert b"struct Header" in schemas["StateInformation"].data
        channels = {c.topic: c for c in summary.channels.values()}
        assert channels[ch.STATE_INFO].message_encoding == "lcm" and "RAW.gps" in channels
        attachments = {a.name: a for a in reader.iter_attachments()}
        assert b'name = "testbot"' in attachments["vehicle.toml"].data
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        assert meta["u2sa"]["vehicle"] == "testbot" and meta["u2sa"]["system_id"] == "7"
        first = next(m for _s, c, m in reader.iter_messages(topics=[ch.STATE_INFO]))
        assert t.StateInformation.decode(first.data).x == 0.0  # bytes stored unchanged

    info = json.loads(services.cli("log", "info", str(path), "--json").stdout)
    assert info["complete"] and info["devices"] == ["gps"]
    counts = {c["channel"]: c["count"] for c in info["channels"]}
    assert counts[ch.STATE_INFO] == 50 and counts["RAW.gps"] == 1
    echo = services.cli("log", "echo", str(path), ch.STATE_INFO, "--json", "--count", "2").stdout.splitlines()
    assert [json.loads(line)["x"] for line in echo] == [0.0, 1.0]


def test_killed_recorder_log_recovers(services: ServiceProcesses, bus: BusClient) -> None:
    vehicle = _profile(services.workdir, services.url)
    proc = services.start("recorder", "--vehicle", str(vehicle))
    wait_until(lambda: bus.discover(timeout=0.3, name="recorder"), timeout=20, message="the recorder")
    for i in range(30):
        bus.publish(ch.STATE_INFO, _state(i))
    wait_until(lambda: _recorder_files(services.workdir) and _count(_recorder_files(services.workdir)[0],
                                                                   ch.STATE_INFO) == 30,
               timeout=15, message="the first second flushed")
    proc.kill()  # SIGKILL: no summary, no footer
    proc.wait(timeout=10)
    path = _recorder_files(services.workdir)[0]
    r = services.cli("log", "info", str(path))
    assert r.returncode == 0 and "NOT COMPLETE" in r.stdout and "u2sa log recover" in r.stdout
    out = services.workdir / "fixed.mcap"
    r = services.cli("log", "recover", str(path), "-o", str(out))
    assert r.returncode == 0 and "wrote" in r.stdout, r.stderr
    with open(out, "rb") as fh:
        reader = make_reader(fh)
        assert reader.get_summary().statistics.channel_message_counts
        xs = [t.StateInformation.decode(m.data).x for _s, _c, m in reader.iter_messages(topics=[ch.STATE_INFO])]
    assert xs == [float(i) for i in range(30)]


def test_record_command_with_filters_and_duration(services: ServiceProcesses, bus: BusClient) -> None:
    out = services.workdir / "cli.mcap"
    proc = subprocess.Popen([sys.executable, "-m", "u2sa_hw.cli", "record", "-o", str(out), "--exclude",
                             "U2SA_.*", "--duration", "30"], env=services.env(), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        def published_and_recorded() -> bool:
            bus.publish(ch.STATE_INFO, _state(1))
            bus.publish(ch.HEALTH, t.Health())
            return out.exists() and _count(out, ch.STATE_INFO) > 0

        wait_until(published_and_recorded, timeout=20, interval=0.2, message="the record command to write")
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=15)
        assert proc.returncode == 0, stderr
        assert "wrote" in stdout and str(out) in stdout
    finally:
        if proc.poll() is None:
            proc.kill()
    channels = {m.channel for m in LogFile(out).messages()}
    assert ch.STATE_INFO in channels and ch.HEALTH not in channels


def test_corrupt_and_missing_files_get_clear_errors(services: ServiceProcesses, tmp_path: Path) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"this is not mcap at all")
    r = services.cli("log", "info", str(junk))
    assert r.returncode == 1 and "junk.mcap: not an MCAP file" in r.stderr
    r = services.cli("log", "info", str(tmp_path / "none.mcap"))
    assert r.returncode == 1 and "none.mcap: no such file" in r.stderr
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    r = services.cli("log", "recover", str(empty))
    assert r.returncode == 1 and "empty.mcap: empty" in r.stderr


# ---------------------------------------------------------------- disk floor, queue, rotation ----
class StallingDisk:
    """A disk_usage stand-in: plenty of space until armed; then the next call blocks until
    released and reports *low* bytes free (the writer thread is held while the queue fills)."""

    def __init__(self, *, low: int) -> None:
        self.low = low
        self.armed = self.blocked = False
        self.release = threading.Event()

    def __call__(self, _path: Path) -> SimpleNamespace:
        if not self.armed:
            return SimpleNamespace(free=10 ** 15)
        self.blocked = True
        self.release.wait(30)
        return SimpleNamespace(free=self.low)


def test_disk_floor_with_a_full_queue_finishes_the_file_and_stop_returns(tmp_path: Path, lcm_url: str,
                                                                         bus: BusClient) -> None:
    disk = StallingDisk(low=10_000_000)
    transport = Transport(lcm_url, name="test-capture")
    path = tmp_path / "floor.mcap"
    capture = BusCapture(transport, McapLogWriter(tmp_path, path=path), queue_size=5, flush_interval_s=0.05,
                         min_free_mb=50, disk_usage=disk)
    capture.start()
    transport.start()
    stopper: threading.Thread | None = None
    try:
        for i in range(3):
            bus.publish(ch.STATE_INFO, _state(i))
        wait_until(lambda: capture.stats.written == 3, message="three messages written")
        disk.armed = True
        wait_until(lambda: disk.blocked, message="the writer checking the disk")
        for i in range(3, 20):
            bus.publish(ch.STATE_INFO, _state(i))
        wait_until(lambda: capture.queue_depth == 5 and capture.stats.dropped > 0,
                   message="a full queue and drops counted")
        disk.release.set()
        wait_until(lambda: capture.stats.stopped_reason, message="the recording stopped at the floor")
        assert "10 MB, below the 50 MB floor" in capture.stats.stopped_reason
        assert not capture.active
        stopper = threading.Thread(target=capture.stop)
        stopper.start()
        wait_until(lambda: not stopper.is_alive(), timeout=20, message="stop() to return")
    finally:
        disk.release.set()
        if stopper is None:
            capture.stop()
        transport.stop()
    with open(path, "rb") as fh:   # finished by the writer thread: summary and indexes, readable
        summary = make_reader(fh).get_summary()
        assert summary is not None and summary.chunk_indexes
        assert sum(summary.statistics.channel_message_counts.values()) == 3
    assert LogFile(path).contents is not None and _count(path, ch.STATE_INFO) == 3
    assert capture.stats.written == 3 and capture.stats.dropped >= 5 + 1   # the queued five were never written


def test_recorder_below_the_disk_floor_stays_up_and_says_why_in_health(services: ServiceProcesses,
                                                                       bus: BusClient) -> None:
    health = BusCollector(bus).listen(ch.HEALTH, t.Health)
    vehicle = _profile(services.workdir, services.url, min_free_mb=1e9, health_interval_s=0.2)
    proc = services.start("recorder", "--vehicle", str(vehicle))
    details = health.health_of("recorder", lambda d: d["status"] == "degraded", timeout=20,
                               message="the recorder degraded")
    assert "below the 1000000000 MB floor" in details["stopped"]
    assert "below the" in details["last_error"] and "recording stopped" in details["last_error"]
    assert proc.poll() is None
    assert not _recorder_files(services.workdir)    # stopped before the first message: no file at all


def test_recorder_rotates_by_size_into_timestamped_complete_files(services: ServiceProcesses,
                                                                  bus: BusClient) -> None:
    vehicle = _profile(services.workdir, services.url, rotate_size_mb=0.002, flush_interval_s=0.05)
    proc = services.start("recorder", "--vehicle", str(vehicle))
    wait_until(lambda: bus.discover(timeout=0.3, name="recorder"), timeout=20, message="the recorder")
    sent = 0

    def three_files() -> bool:
        nonlocal sent
        for _ in range(20):
            bus.publish(ch.STATE_INFO, _state(sent))
            sent += 1
        return len(_recorder_files(services.workdir)) >= 3

    wait_until(three_files, timeout=30, interval=0.05, message="three rotated files")
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=15) == 0
    files = _recorder_files(services.workdir)
    assert all(TIMESTAMPED.fullmatch(f.name) for f in files), [f.name for f in files]
    xs: list[float] = []
    for f in files:
        log = LogFile(f)
        xs += [t.StateInformation.decode(m.data).x for m in log.messages(ch.STATE_INFO)]
        assert log.contents.complete and "vehicle.toml" in log.contents.attachments, f
    assert xs == sorted(xs) and len(xs) > 20   # nothing lost or reordered across the rotations


def test_record_command_rotates_by_duration_with_lz4_chunks(services: ServiceProcesses, bus: BusClient) -> None:
    out = services.workdir / "run.mcap"
    proc = subprocess.Popen([sys.executable, "-m", "u2sa_hw.cli", "record", "-o", str(out), "--rotate-duration",
                             "0.5", "--compression", "lz4", "--include", "STATE_INFO"], env=services.env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        def three_files() -> bool:
            bus.publish(ch.STATE_INFO, _state(1))
            return len(list(services.workdir.glob("*.mcap"))) >= 3

        wait_until(three_files, timeout=30, interval=0.05, message="three files, one every 0.5 s")
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=15)
        assert proc.returncode == 0, stderr
    finally:
        if proc.poll() is None:
            proc.kill()
    rotated = sorted(p for p in services.workdir.glob("*.mcap") if p != out)
    assert out.exists() and len(rotated) >= 2
    assert all(re.fullmatch(r"run-\d{8}-\d{6}(_\d{3})?\.mcap", p.name) for p in rotated), rotated
    for path in [out, *rotated]:
        with open(path, "rb") as fh:
            summary = make_reader(fh).get_summary()
        assert summary.chunk_indexes and {c.compression for c in summary.chunk_indexes} == {"lz4"}, path
    assert str(out) in stdout and "0 dropped" in stdout


def test_record_command_below_min_free_stops_with_the_reason(services: ServiceProcesses) -> None:
    r = services.cli("record", "-o", str(services.workdir / "x.mcap"), "--min-free-mb", "1e12", "--duration", "20")
    assert r.returncode == 1
    assert "below the 1000000000000 MB floor" in r.stderr and "recording stopped" in r.stderr
    r = services.cli("record", "--queue-size", "0")
    assert r.returncode == 2 and "--queue-size" in r.stderr


def test_the_log_holds_verified_payloads_and_says_the_bus_was_signed(services: ServiceProcesses, bus: BusClient,
                                                                     tmp_path: Path) -> None:
    """A packet from a process without the key is not recorded but counted; the payloads carry no trailer."""
    out = services.workdir / "signed.mcap"
    vehicle = _profile(tmp_path, services.url)     # system id 7: a message naming another is foreign
    proc = subprocess.Popen([sys.executable, "-m", "u2sa_hw.cli", "record", "-o", str(out), "--include",
                             "STATE_INFO", "--duration", "60", "--vehicle", str(vehicle)], env=services.env(),
                            stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    keyless = {k: v for k, v in services.env().items() if k != "U2SA_BUS_KEY_FILE"}
    forger = ("import sys; from u2sa_hw.bus.transport import Transport; from u2sa_hw import lcmtypes as t; "
              "Transport(sys.argv[1], name='laptop', security='open').publish('STATE_INFO', "
              "t.StateInformation().set(x=666.0))")
    try:
        def recorded() -> bool:
            bus.publish(ch.STATE_INFO, _state(1))
            return out.exists() and _count(out, ch.STATE_INFO) > 0

        wait_until(recorded, timeout=20, interval=0.2, message="the record command to write a signed message")
        subprocess.run([sys.executable, "-c", forger, services.url], env=keyless, check=True, timeout=60)
        other = Transport(services.url, name="vehicle-2")   # the key, another vehicle's system id: foreign
        foreign = _state(777)
        foreign.header.system_id = 2
        other.publish(ch.STATE_INFO, foreign)
        other.stop()
        bus.publish(ch.STATE_INFO, _state(2))   # after the forgery on the wire: recorded once it is through
        wait_until(lambda: any(t.StateInformation.decode(m.data).x == 2.0 for m in LogFile(out).messages()
                               if m.channel == ch.STATE_INFO), timeout=20, interval=0.2, message="the message after the forgery")
        proc.send_signal(signal.SIGINT)
        _stdout, stderr = proc.communicate(timeout=15)
        assert proc.returncode == 0, stderr
    finally:
        if proc.poll() is None:
            proc.kill()
    messages = list(LogFile(out).messages())
    assert all(t.StateInformation.decode(m.data).x not in (666.0, 777.0) for m in messages)
    assert all(t.StateInformation.decode(m.data).encode() == m.data for m in messages)   # no trailer in the log
    info = json.loads(services.cli("log", "info", str(out), "--json").stdout)
    assert info["bus"]["security"] == "signed" and info["bus"]["dropped"]["unsigned"] == 1
    assert info["bus"]["dropped"]["foreign"] == 1
    # Who signed: each MCAP channel names its signer; the file's u2sa_signers record names its sources.
    with open(out, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    signers = {c.metadata.get("signer") for c in summary.channels.values() if c.topic == ch.STATE_INFO}
    assert signers == {bus.transport.sender}
    assert info["bus"]["signers"] == {bus.transport.sender: bus.name}
    text = services.cli("log", "info", str(out)).stdout
    assert "bus:         signed (key " in text and "STATE_INFO: unsigned 1, foreign 1" in text
    assert f"signers:     1 ({bus.transport.sender} {bus.name})" in text


# ---------------------------------------------------------------- a full disk (min_free_mb = 0) ----
# A child process fills its "disk": a file-size limit (RLIMIT_FSIZE, SIGXFSZ ignored: a write past it
# fails with EFBIG), or a real 256 kB tmpfs in a mount namespace of its own (ENOSPC; the file is
# copied out before the namespace goes). argv: mode, directory, output copy, then the job's own.
FULL_DISK_CHILD = r"""
import json, os, resource, shutil, signal, sys, time
from pathlib import Path
mode, disk, copy = sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3])
if mode == "rlimit":
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))
from u2sa_hw import lcmtypes as t
from u2sa_hw.recording.mcap_log import McapLogWriter

def state(i):
    s = t.StateInformation().set(x=float(i), psi=0.5)
    s.sensor_name = "gps"
    return s

path = disk / "full.mcap"
report = {}
if sys.argv[4] == "writer":        # flush every 25 messages: what is flushed before the error must stay
    writer = McapLogWriter(disk, path=path, chunk_size=4096)
    n = flushed = 0
    try:
        for n in range(10**6):
            writer.write("STATE_INFO", state(n).encode(), 10**9 + n * 10**6)
            if n % 25 == 24:
                writer.flush()
                flushed = n + 1
    except OSError as exc:
        report["error"] = str(exc)
    writer.close()
    report.update(taken=writer.messages, flushed=flushed, lost=writer.lost, cut=writer.cut_short)
else:                              # the recorder's capture, fed over the bus
    from u2sa_hw.services.recorder.capture import BusCapture
    from u2sa_hw.bus.transport import Transport
    url = sys.argv[5]
    transport = Transport(url, name="full-disk-recorder")
    capture = BusCapture(transport, McapLogWriter(disk, path=path, chunk_size=4096), min_free_mb=0,
                         flush_interval_s=0.05)
    capture.start()
    transport.start()
    publisher = Transport(url, name="full-disk-publisher")
    sent, deadline = 0, time.monotonic() + 120
    while not capture.stats.stopped_reason and time.monotonic() < deadline:
        publisher.publish("STATE_INFO", state(sent))
        sent += 1
        if sent % 100 == 0:   # let the recorder keep up (a lost UDP packet only ends this wait early)
            until = time.monotonic() + 2
            while capture.stats.received < sent - 50 and time.monotonic() < until:
                time.sleep(0.005)
    capture.stop()
    transport.stop()
    publisher.stop()
    s = capture.stats
    report.update(sent=sent, received=s.received, written=s.written, dropped=s.dropped, reason=s.stopped_reason)
shutil.copyfile(path, copy)
print(json.dumps(report))
"""


def _fill_the_disk(tmp_path: Path, mode: str, *job: str) -> tuple[dict, Path]:
    """Run FULL_DISK_CHILD; its report and the copy of the file it left."""
    disk, copy = tmp_path / "disk", tmp_path / "full.mcap"
    disk.mkdir()
    argv = [sys.executable, "-c", FULL_DISK_CHILD, mode, str(disk), str(copy), *job]
    if mode == "tmpfs":
        if shutil.which("unshare") is None:
            pytest.skip("no unshare: cannot mount a small tmpfs")
        probe = subprocess.run(["unshare", "-rm", "mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(disk)],
                               capture_output=True, text=True, timeout=30)
        if probe.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs in a mount namespace here: {probe.stderr.strip()}")
        argv = ["unshare", "-rm", "sh", "-c", 'mount -t tmpfs -o size=256k tmpfs "$0" && exec "$@"', str(disk), *argv]
    r = subprocess.run(argv, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    return json.loads(r.stdout.splitlines()[-1]), copy


def _complete_and_indexed(path: Path) -> list[float]:
    """The x of every message of a log that is complete and indexed (its statistics agree)."""
    log = LogFile(path)
    xs = [t.StateInformation.decode(m.data).x for m in log.messages(ch.STATE_INFO)]
    assert log.contents.complete and not log.contents.problem, log.contents.problem
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None and summary.chunk_indexes
        assert summary.statistics.message_count == len(xs)
        indexed = [t.StateInformation.decode(m.data).x for _s, _c, m in reader.iter_messages()]
    assert indexed == xs
    return xs


@pytest.mark.parametrize("mode", ["rlimit", "tmpfs"])
def test_a_full_disk_ends_the_log_at_its_last_complete_chunk_with_every_flushed_message(tmp_path: Path,
                                                                                         mode: str) -> None:
    report, path = _fill_the_disk(tmp_path, mode, "writer")
    assert ("File too large" if mode == "rlimit" else "No space left") in report["error"]
    xs = _complete_and_indexed(path)
    # every message flushed before the error reads back, in order, and none after a gap
    assert len(xs) >= report["flushed"] > 0 and xs == [float(i) for i in range(len(xs))]
    assert report["taken"] - report["lost"] == len(xs)
    assert report["cut"] and "ends at its last complete chunk" in report["cut"][0]
    info = subprocess.run([sys.executable, "-m", "u2sa_hw.cli", "log", "info", str(path), "--json"],
                          capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert json.loads(info.stdout)["complete"] and json.loads(info.stdout)["messages"] == len(xs)


def test_recorder_without_a_disk_floor_stops_at_a_full_disk_with_a_complete_log(tmp_path: Path, lcm_url: str) -> None:
    report, path = _fill_the_disk(tmp_path, "rlimit", "capture", lcm_url)
    assert "File too large; recording stopped" in report["reason"], report
    assert "ends at its last complete chunk" in report["reason"], report
    xs = _complete_and_indexed(path)
    assert report["written"] == len(xs) > 0 and xs == sorted(xs)
    assert report["written"] + report["dropped"] == report["received"]   # every message in the file or counted
