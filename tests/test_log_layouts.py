"""The log tools on any MCAP file, not only the recorder's: files of every layout the format
allows are built with the ``mcap`` library's own writer (chunked or not, compressed or not,
with or without message indexes and summary, an unknown record and a padded record,
schemaless JSON channels, attachments or metadata only, a first message at log time 0) and
``u2sa log info``, ``echo``, ``recover`` and ``export`` give a correct answer or one clear line
(and a non-zero exit when there is nothing to show, recover or export)."""

from __future__ import annotations

import io
import json
import os
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

import pytest
from conftest import REPO
from mcap.reader import make_reader
from mcap.writer import CompressionType, IndexType, Writer

from u2sa_hw.lcmtypes import StateInformation

U2SA = [sys.executable, "-m", "u2sa_hw.cli"]
SECOND = 1_000_000_000


def state(x: float) -> bytes:
    msg = StateInformation().set(x=x)          # x present: an absent field reads as null (issue 26)
    msg.sensor_name = "gps"
    return msg.encode()


def write(path: Path, *, messages: bool = True, t0: int = 5 * SECOND, json_channel: bool = False,
          attachments: bool = True, **writer_options: object) -> None:
    """Three STATE_INFO messages 1 s apart from *t0* (and three JSON ones), a metadata record and an attachment."""
    with path.open("wb") as f:
        w = Writer(f, **writer_options)
        w.start(profile="", library="another tool 1.0")
        sid = w.register_schema("StateInformation", "lcm", b"")
        cid = w.register_channel("STATE_INFO", "lcm", sid)
        jid = w.register_channel("/odom", "json", 0) if json_channel else None
        if messages:
            for i in range(3):
                w.add_message(cid, t0 + i * SECOND, state(float(i)), t0 + i * SECOND, sequence=10 + i)
                if jid is not None:
                    w.add_message(jid, t0 + i * SECOND, json.dumps({"v": i}).encode(), t0 + i * SECOND, i)
        w.add_metadata("site", {"lake": "Lily"})
        if attachments:
            w.add_attachment(create_time=1, log_time=2, name="notes.txt", media_type="text/plain", data=b"calm day")
        w.finish()


def record(opcode: int, content: bytes) -> bytes:
    return struct.pack("<BQ", opcode, len(content)) + content


def with_unknown_and_padded_records(path: Path) -> None:
    """An unchunked, summary-less file with a private-opcode record after the header and a
    Metadata record padded with bytes a newer writer might add (readers must skip both)."""
    buf = io.BytesIO()
    w = Writer(buf, use_chunking=False, index_types=IndexType.NONE, repeat_channels=False, repeat_schemas=False,
               use_statistics=False, use_summary_offsets=False)
    w.start(profile="", library="padder")
    sid = w.register_schema("StateInformation", "lcm", b"")
    cid = w.register_channel("STATE_INFO", "lcm", sid)
    for i in range(3):
        w.add_message(cid, 5 * SECOND + i * SECOND, state(float(i)), 0, sequence=10 + i)
    w.finish()
    data = buf.getvalue()
    magic = 8
    header_len = struct.unpack_from("<Q", data, magic + 1)[0]
    after_header = magic + 9 + header_len
    name, key, value = b"pad", b"k", b"v"
    meta = struct.pack("<I", len(name)) + name + struct.pack("<I", 4 + len(key) + 4 + len(value))
    meta += struct.pack("<I", len(key)) + key + struct.pack("<I", len(value)) + value
    extra = record(0x80, b"private record of another tool") + record(0x0C, meta + b"\0" * 7)
    path.write_bytes(data[:after_header] + extra + data[after_header:])


LAYOUTS: dict[str, Callable[[Path], None]] = {
    "chunked-zstd-indexed": lambda p: write(p),
    "chunked-lz4": lambda p: write(p, compression=CompressionType.LZ4),
    "chunked-uncompressed": lambda p: write(p, compression=CompressionType.NONE),
    "unchunked": lambda p: write(p, use_chunking=False),
    "no-index-no-summary": lambda p: write(p, index_types=IndexType.NONE, repeat_channels=False,
                                           repeat_schemas=False, use_statistics=False, use_summary_offsets=False),
    "schemaless-json-channel": lambda p: write(p, json_channel=True),
    "first-message-at-time-0": lambda p: write(p, t0=0),
    "unknown-and-padded-records": with_unknown_and_padded_records,
}


def u2sa(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([*U2SA, *args], cwd=cwd, capture_output=True, text=True, timeout=60,
                          env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_info_echo_and_recover_on_every_layout(layout: str, tmp_path: Path) -> None:
    f = tmp_path / f"{layout}.mcap"
    LAYOUTS[layout](f)
    info = u2sa("log", "info", str(f), "--json", cwd=tmp_path)
    assert info.returncode == 0, info.stderr
    data = json.loads(info.stdout)
    json_msgs = 3 if layout == "schemaless-json-channel" else 0
    assert data["messages"] == 3 + json_msgs and data["duration_s"] == pytest.approx(2.0), data
    state_row = next(r for r in data["channels"] if r["channel"] == "STATE_INFO")
    assert state_row["count"] == 3 and state_row["rate_hz"] == pytest.approx(1.5)

    echo = u2sa("log", "echo", str(f), "STATE_INFO", "--json", cwd=tmp_path)
    assert echo.returncode == 0, echo.stderr
    xs = [json.loads(line)["x"] for line in echo.stdout.splitlines()]
    assert xs == [0.0, 1.0, 2.0]

    out = tmp_path / "out.mcap"
    rec = u2sa("log", "recover", str(f), "-o", str(out), cwd=tmp_path)
    assert rec.returncode == 0, rec.stdout + rec.stderr
    with out.open("rb") as fh:
        reader = make_reader(fh)
        got = [(c.topic, m.sequence, m.log_time) for _s, c, m in reader.iter_messages(log_time_order=False)
               if c.topic == "STATE_INFO"]
        t0 = got[0][2]
        assert [(t, s) for t, s, _ in got] == [("STATE_INFO", 10), ("STATE_INFO", 11), ("STATE_INFO", 12)]
        assert [lt - t0 for *_, lt in got] == [0, SECOND, 2 * SECOND]
        assert reader.get_summary() is not None     # indexed
        if layout == "schemaless-json-channel":
            summary = reader.get_summary()
            assert {c.topic: c.schema_id for c in summary.channels.values()}["/odom"] == 0


def test_echo_prints_json_channels_of_other_tools_and_names_what_it_cannot_decode(tmp_path: Path) -> None:
    f = tmp_path / "mixed.mcap"
    write(f, json_channel=True)
    res = u2sa("log", "echo", str(f), "/odom", "--json", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert [json.loads(line)["json"]["v"] for line in res.stdout.splitlines()] == [0, 1, 2]
    with f.open("wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2", library="x")
        cid = w.register_channel("/scan", "cdr", w.register_schema("sensor_msgs/msg/LaserScan", "ros2msg", b""))
        w.add_message(cid, 1, b"\0\1\0\0" + b"\7" * 20, 1)
        w.finish()
    res = u2sa("log", "echo", str(f), "/scan", cwd=tmp_path)
    assert res.returncode == 0 and "24 bytes of cdr (u2sa decodes LCM and JSON only)" in res.stdout, res
    assert "truncated" not in res.stdout + res.stderr


def test_echo_of_a_channel_not_in_the_log_lists_the_channels(tmp_path: Path) -> None:
    f = tmp_path / "a.mcap"
    write(f, json_channel=True)
    res = u2sa("log", "echo", str(f), "NOPE", cwd=tmp_path)
    assert res.returncode == 1
    assert "no channel matches 'NOPE'" in res.stderr and "/odom, STATE_INFO" in res.stderr


def test_recover_keeps_metadata_and_attachments_of_a_file_without_messages_and_exits_1(tmp_path: Path) -> None:
    f = tmp_path / "meta-only.mcap"
    write(f, messages=False)
    out = tmp_path / "out.mcap"
    res = u2sa("log", "recover", str(f), "-o", str(out), cwd=tmp_path)
    assert res.returncode == 1 and "no message could be recovered" in res.stderr, res
    with out.open("rb") as fh:
        reader = make_reader(fh)
        assert [a.name for a in reader.iter_attachments()] == ["notes.txt"]
        assert {m.name: m.metadata["lake"] for m in reader.iter_metadata()} == {"site": "Lily"}
        (a,) = list(reader.iter_attachments())
        assert (a.media_type, a.create_time, a.log_time, a.data) == ("text/plain", 1, 2, b"calm day")
    info = u2sa("log", "info", str(f), cwd=tmp_path)
    assert info.returncode == 0 and "0 messages" in info.stdout


def test_recover_never_leaves_an_invalid_file(tmp_path: Path) -> None:
    f = tmp_path / "bad.mcap"
    data = bytearray((tmp_path / "x").write_bytes(b"") or b"")
    buf = io.BytesIO()
    w = Writer(buf, use_chunking=False, index_types=IndexType.NONE, use_summary_offsets=False)
    w.start(profile="", library="x")
    cid = w.register_channel("STATE_INFO", "lcm", 7)     # names a schema the file never holds
    w.add_message(cid, 1, state(1.0), 1)
    w.finish()
    data = buf.getvalue()
    f.write_bytes(data)
    out = tmp_path / "out.mcap"
    res = u2sa("log", "recover", str(f), "-o", str(out), cwd=tmp_path)
    assert res.returncode == 1 and "names schema 7" in res.stderr, res
    assert not out.exists() and not list(tmp_path.glob(".out.mcap.*"))


def test_lcm_self_test_packets_are_named_not_unknown(tmp_path: Path) -> None:
    from u2sa_hw.recording.mcap_log import McapLogWriter

    writer = McapLogWriter(tmp_path, path=tmp_path / "selftest.mcap")
    writer.write("LCM_SELF_TEST", b"lcm self test", 5)
    writer.write("STATE_INFO", state(1.0), 6)
    writer.close()
    res = u2sa("log", "info", str(tmp_path / "selftest.mcap"), "--json", cwd=tmp_path)
    types = {r["channel"]: r["type"] for r in json.loads(res.stdout)["channels"]}
    assert types == {"LCM_SELF_TEST": "lcm_self_test", "STATE_INFO": "StateInformation"}, types


def cdr_only(path: Path) -> None:
    """Another stack's log: five ROS 2 CDR messages, nothing u2sa can decode."""
    with path.open("wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2", library="x")
        cid = w.register_channel("/scan", "cdr", w.register_schema("sensor_msgs/msg/LaserScan", "ros2msg", b""))
        for i in range(5):
            w.add_message(cid, i * SECOND, b"\0\1\0\0" + b"\7" * 20, i * SECOND)
        w.finish()


def lcm_garbage(path: Path) -> None:
    """A channel that says lcm, holding bytes that are not LCM."""
    with path.open("wb") as fh:
        w = Writer(fh)
        w.start(profile="", library="x")
        cid = w.register_channel("FOO", "lcm", w.register_schema("Bar", "lcm", b""))
        w.add_message(cid, 0, b"hello world, not lcm at all", 0)
        w.add_message(cid, 10, b"\x01\x02", 10)
        w.finish()


@pytest.mark.parametrize("make, says", [
    (cdr_only, "nothing to export: 5 cdr messages (5 on /scan): u2sa turns LCM into JSON and copies JSON, it "
               "cannot convert cdr"),
    (lcm_garbage, "nothing to export: 2 LCM messages could not be decoded"),
    (lambda p: write(p, messages=False), "nothing to export: the log holds no messages"),
])
def test_export_of_a_log_with_nothing_to_convert_exits_1_with_one_line_and_writes_nothing(
        make: Callable[[Path], None], says: str, tmp_path: Path) -> None:
    f, out = tmp_path / "in.mcap", tmp_path / "fox.mcap"
    make(f)
    out.write_bytes(b"an earlier export")
    res = u2sa("log", "export", str(f), "--foxglove", str(out), cwd=tmp_path)
    assert res.returncode == 1 and says in res.stderr, res
    assert len(res.stderr.strip().splitlines()) == 1 and "wrote" not in res.stdout
    assert out.read_bytes() == b"an earlier export" and sorted(p.name for p in tmp_path.iterdir()) == ["fox.mcap",
                                                                                                    "in.mcap"]


def test_export_copies_json_channels_and_converts_lcm_from_log_time_0(tmp_path: Path) -> None:
    f, out = tmp_path / "mixed.mcap", tmp_path / "fox.mcap"
    write(f, json_channel=True, t0=0)
    res = u2sa("log", "export", str(f), "--foxglove", str(out), cwd=tmp_path)
    assert res.returncode == 0, res
    with out.open("rb") as fh:
        got: dict[str, list[tuple[int, bytes]]] = {}
        for _s, c, m in make_reader(fh).iter_messages(log_time_order=False):
            got.setdefault(c.topic, []).append((m.log_time, m.data))
    assert got["/odom"] == [(i * SECOND, json.dumps({"v": i}).encode()) for i in range(3)]   # as they were
    assert [(t, json.loads(d)["x"]) for t, d in got["STATE_INFO"]] == [(i * SECOND, float(i)) for i in range(3)]
    umask = os.umask(0)
    os.umask(umask)
    assert out.stat().st_mode & 0o777 == 0o666 & ~umask   # a new file's usual mode, not the temporary's 0600


def test_export_takes_a_log_starting_at_time_0_as_starting_there_for_its_service_log_lines(tmp_path: Path) -> None:
    from u2sa_hw.recording.foxglove import export_foxglove

    f = tmp_path / "t0.mcap"
    with f.open("wb") as fh:
        w = Writer(fh)
        w.start(profile="", library="x")
        cid = w.register_channel("STATE_INFO", "lcm", w.register_schema("StateInformation", "lcm", b""))
        for t in (0, 1000 * SECOND):    # a first message at 0, the next long after
            w.add_message(cid, t, state(1.0), t)
        w.finish()
    logs = tmp_path / "logs"
    logs.mkdir()
    stamp = time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(3))   # 3 s into the log
    (logs / "gps.log").write_text(f"{stamp}.000 INFO     gps [1] opened the port\n")
    report = export_foxglove(f, tmp_path / "fox.mcap", log_dir=logs)
    assert report.counts.get("/log") == 1, report


def test_echo_of_a_channel_none_of_whose_messages_decode_exits_1(tmp_path: Path) -> None:
    f = tmp_path / "garbage.mcap"
    lcm_garbage(f)
    res = u2sa("log", "echo", str(f), "FOO", cwd=tmp_path)
    assert res.returncode == 1 and res.stdout == ""
    assert "none of the 2 messages on FOO could be decoded as LCM" in res.stderr.splitlines()[-1]


def test_recover_keeps_the_mode_of_the_file_it_recovers(tmp_path: Path) -> None:
    f, out = tmp_path / "run.mcap", tmp_path / "out.mcap"
    write(f)
    f.chmod(0o640)
    res = u2sa("log", "recover", str(f), "-o", str(out), cwd=tmp_path)
    assert res.returncode == 0, res
    assert out.stat().st_mode & 0o777 == 0o640
