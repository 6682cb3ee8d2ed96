"""The recorder service and `u2sa record` / `u2sa log`: real processes, real MCAP files."""

from __future__ import annotations

import json
import signal
import textwrap
from pathlib import Path

from conftest import ServiceProcesses, wait_until
from mcap.reader import make_reader

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus_client import BusClient
from u2sa_hw.recording.log_reader import LogFile


def _profile(tmp: Path, url: str, **recorder: str) -> Path:
    settings = ", ".join(f'{k} = "{v}"' for k, v in recorder.items())
    path = tmp / "vehicle.toml"
    path.write_text(textwrap.dedent(f"""\
        [vehicle]
        name = "testbot"
        system_id = 7
        lcm_url = "{url}"
        [services.recorder]
        kind = "recorder"
        settings = {{ {settings} }}
        """))
    return path


def _recorder_files(tmp: Path) -> list[Path]:
    return sorted((tmp / "data" / "recordings").glob("*.mcap"))


def _count(path: Path, channel: str) -> int:
    return sum(1 for _ in LogFile(path).messages(channel))


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
    import subprocess
    import sys

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
