"""``u2sa replay --compare`` on an edited log and ``u2sa replay-check DIR``: a GPS epoch cut out of a
recorded log is reported as exactly one deletion (the other fixes still match), and the gate
replays a directory of logs with a progress line per log, one table, and the exit status; a log
that fails in any way is that log's result, and --vehicle gives logs without a profile one.

What a replay is held against here is a replay of the unedited log, never the live recording's own
outputs: the live drivers read their mock devices on a machine whose load the log does not hold (a GPS
epoch the live driver read in two parts goes out as a fix and a supplement, where a replay, which groups
by the recorded stamps, publishes one fix: tests/test_record_sim_replay.py, HELD_UP), so a live recording is
no exact reference. A replay is: two replays of the same input give the same messages (test_replay.py)."""

from __future__ import annotations

import bisect
import json
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Callable, Iterable, Iterator

import pytest
from conftest import REPO
from mcap.reader import make_reader
from mcap.writer import Writer
from test_replay import record_driver_log

from u2sa_hw.hil.compare import compare_logs
from u2sa_hw.hil.player import header_source

from u2sa_hw.channels import base_type
from u2sa_hw.lcmtypes import RawSerial, StateInformation
from u2sa_hw.messages import REGISTRY
from u2sa_hw.recording.log_reader import LogFile
from u2sa_hw.recording.mcap_log import McapLogWriter, RunInfo

U2SA = [sys.executable, "-m", "u2sa_hw.cli"]
SENTENCE = re.compile(rb"\$[A-Z]{2}([A-Z]{3}),([0-9A-Z.]*)[^\r\n]*\r?\n")
UTC = re.compile(rb"\d{6}(\.\d*)?")   # the time field of GGA, RMC, GST, ZDA (VTG and GSA have none)
SERVICES = {"gps", "compass"}   # the driver log's replayed services


@pytest.fixture(scope="module")
def driver_log(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    yield record_driver_log(tmp_path_factory.mktemp("recorded"), gps_epochs=25, compass_epochs=40)


@pytest.fixture(scope="module")
def reference(driver_log: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The outputs of a ``--fast`` replay of the unedited driver log: the clean reference (module docstring)."""
    out = tmp_path_factory.mktemp("reference") / "reference.mcap"
    res = run("replay", str(driver_log), "--fast", "-o", str(out), cwd=out.parent)
    assert res.returncode == 0, res.stdout + res.stderr
    return out


@pytest.fixture(scope="module")
def clean_log(driver_log: Path, reference: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The driver log with the replay's outputs as its recorded ones: a log whose replay is "same" whatever
    the load was while it was recorded (its input and profile are the live recording's)."""
    out = tmp_path_factory.mktemp("clean") / "clean.mcap"
    with_outputs_of(driver_log, reference, out)
    return out


def outputs(data: bytes, topic: str) -> bool:
    """True for a message ``--compare`` compares (u2sa_hw.hil.compare.load_streams): a replayed service's, not raw
    device I/O, not the contract channels."""
    if topic.startswith(("U2SA_", "RAW.")):
        return False
    msg, _ = REGISTRY.decode(data, base_type(topic))
    return header_source(msg) in SERVICES


def with_outputs_of(log: Path, replay: Path, dst: Path) -> None:
    """Copy *log* with its recorded outputs of SERVICES replaced by *replay*'s, each at the log time of the
    raw input chunk its time stamp is (a replayed driver stamps a message with its input's recorded stamp,
    which went through float seconds: it may be 1 us short)."""
    inputs: dict[int, int] = {}   # a raw chunk's header stamp (us) -> its log time
    with log.open("rb") as f:
        for _s, channel, message in make_reader(f).iter_messages():
            if channel.topic.startswith("RAW."):
                raw, _ = REGISTRY.decode(message.data, base_type(channel.topic))
                inputs.setdefault(raw.header.timestamp_us, message.log_time)
    stamps = sorted(inputs)
    replayed: list[tuple[str, int, bytes]] = []
    with replay.open("rb") as f:
        for _s, channel, message in make_reader(f).iter_messages():
            if outputs(message.data, channel.topic):
                msg, _ = REGISTRY.decode(message.data, base_type(channel.topic))
                stamp = msg.header.timestamp_us
                found = stamps[bisect.bisect_left(stamps, stamp):][:1]
                assert found and found[0] - stamp <= 1, f"{channel.topic} stamped {stamp}: no raw input chunk is"
                replayed.append((channel.topic, inputs[found[0]], message.data))
    assert replayed, f"{replay}: the replay published no outputs of {sorted(SERVICES)}"
    copy_log(log, dst, lambda topic, data: None if outputs(data, topic) else data, extra=replayed)


def copy_log(src: Path, dst: Path, edit: Callable[[str, bytes], bytes | None], *, attachments: bool = True,
             extra: Iterable[tuple[str, int, bytes]] = ()) -> None:
    """Copy an MCAP record by record (schemas, channels, messages, attachments unless not *attachments*,
    metadata); *edit* gets each message's channel and data and returns the data to write (None: leave the
    message out); *extra* messages (channel, log time, data) on channels of *src* are added in log time
    order (after the messages of *src* of the same time)."""
    with src.open("rb") as f_in, dst.open("wb") as f_out:
        reader = make_reader(f_in)
        header = reader.get_header()
        writer = Writer(f_out)
        writer.start(profile=header.profile, library=header.library)
        summary = reader.get_summary()
        assert summary is not None
        schema_ids = {sid: writer.register_schema(s.name, s.encoding, s.data) for sid, s in summary.schemas.items()}
        channel_ids = {cid: writer.register_channel(c.topic, c.message_encoding, schema_ids.get(c.schema_id, 0),
                                                    dict(c.metadata)) for cid, c in summary.channels.items()}
        topics = {c.topic: channel_ids[cid] for cid, c in summary.channels.items()}
        messages = [(message.log_time, 0, channel_ids[channel.id], message.publish_time, message.sequence,
                     edit(channel.topic, message.data))
                    for _schema, channel, message in reader.iter_messages(log_time_order=False)]
        messages += [(log_time, 1, topics[topic], log_time, 0, data) for topic, log_time, data in extra]
        for log_time, _, channel_id, publish_time, sequence, data in sorted(messages, key=lambda m: m[:2]):
            if data is not None:
                writer.add_message(channel_id, log_time, data, publish_time, sequence)
        for attachment in reader.iter_attachments() if attachments else ():
            writer.add_attachment(attachment.create_time, attachment.log_time, attachment.name,
                                  attachment.media_type, attachment.data)
        for metadata in reader.iter_metadata():
            writer.add_metadata(metadata.name, dict(metadata.metadata))
        writer.finish()


def gps_times(log: Path) -> list[bytes]:
    """The UTC times of the GGA sentences the GPS sent in *log*, in order."""
    times: list[bytes] = []
    with log.open("rb") as f:
        for _s, channel, message in make_reader(f).iter_messages():
            if channel.topic == "RAW.gps":
                raw, _ = REGISTRY.decode(message.data, base_type("RAW.gps"))
                times += [m.group(2) for m in SENTENCE.finditer(bytes(raw.data)) if m.group(1) == b"GGA"]
    return times


def without_epoch(log: Path, out: Path, utc: bytes, stamps: list[int] | None = None) -> int:
    """Copy *log* with the whole GPS epoch stamped *utc* removed: its timed sentences and the untimed
    ones (VTG, GSA) that follow them until the next epoch's first timed sentence; returns how many.
    *stamps* gets the header stamps (us) of the raw chunks that held them."""
    removed = 0
    inside = False

    def keep(m: re.Match) -> bytes:
        nonlocal removed, inside
        if UTC.fullmatch(m.group(2)):
            inside = m.group(2) == utc
        if inside:
            removed += 1
            return b""
        return m.group(0)

    def edit(topic: str, data: bytes) -> bytes:
        if topic != "RAW.gps":
            return data
        raw, _ = REGISTRY.decode(data, base_type("RAW.gps"))
        assert isinstance(raw, RawSerial)
        kept = SENTENCE.sub(keep, bytes(raw.data))
        if kept == bytes(raw.data):
            return data
        if stamps is not None:
            stamps.append(raw.header.timestamp_us)
        raw.data, raw.length = kept, len(kept)
        return raw.encode()

    copy_log(log, out, edit)
    return removed


def run(*args: str, cwd: Path, timeout: float = 240) -> subprocess.CompletedProcess:
    return subprocess.run([*U2SA, *args], cwd=cwd, capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "PYTHONPATH": str(REPO)})


def stream(report: dict, key: str) -> dict:
    return next(s for s in report["streams"] if s["stream"] == key)


def test_a_gps_epoch_removed_from_the_log_is_one_deletion_and_the_rest_match(driver_log: Path, reference: Path,
                                                                            tmp_path: Path) -> None:
    times = gps_times(driver_log)
    assert len(times) >= 10
    edited = tmp_path / "edited.mcap"
    cut: list[int] = []
    assert without_epoch(driver_log, edited, times[len(times) // 2], cut) >= 1
    out = tmp_path / "out.mcap"
    res = run("replay", str(edited), "--fast", "--compare", "--json", "-o", str(out), cwd=tmp_path)
    # against the live recording (the CLI's own comparison): the fix is missing, so the GPS stream differs
    assert res.returncode == 1, res.stdout + res.stderr
    assert not stream(json.loads(res.stdout), "STATE_INFO [gps]")["ok"], res.stdout

    # against a replay of the unedited log: exactly the cut epoch's fix is missing, the rest is the same
    report = compare_logs(reference, out, services=SERVICES, rate=None).to_dict()
    assert {s["stream"] for s in report["streams"]} == {"STATE_INFO [gps]", "STATE_INFO [compass]"}, report
    gps = stream(report, "STATE_INFO [gps]")
    assert (gps["deleted"], gps["inserted"], gps["different"]) == (1, 0, 0), gps
    assert gps["matched"] == gps["replayed"] == gps["recorded"] - 1 >= 8, gps
    [event] = gps["events"]
    assert event["kind"] == "deleted", gps
    fixes = [msg for m in LogFile(reference).messages("STATE_INFO")
             if header_source(msg := REGISTRY.decode(m.data, base_type(m.channel))[0]) == "gps"]
    deleted = fixes[event["index"]].header.timestamp_us   # a replayed fix carries its input's recorded stamp
    assert min(cut) - 1 <= deleted <= max(cut), (deleted, cut)   # (1 us: with_outputs_of)
    compass = stream(report, "STATE_INFO [compass]")
    assert compass["ok"] and compass["matched"] == compass["recorded"] == compass["replayed"] >= 20, compass


def test_replay_check_replays_a_directory_with_progress_a_table_and_the_exit_status(driver_log: Path,
                                                                                     clean_log: Path,
                                                                                     tmp_path: Path) -> None:
    logs = tmp_path / "logs"
    logs.mkdir()
    # the driver log with a replay's outputs (clean_log): "same" holds whatever the live drivers made of it
    copy_log(clean_log, logs / "a-clean.mcap", lambda _t, d: d)
    times = gps_times(clean_log)
    without_epoch(clean_log, logs / "b-cut.mcap", times[len(times) // 2])
    (logs / "c-damaged.mcap").write_bytes(b"\x89MCAP0\r\n" + b"\0" * 40)
    copy_log(clean_log, logs / "d-no-profile.mcap", lambda _t, d: d, attachments=False)   # u2sa record, no --vehicle
    # A profile the replay does not expect ([services] a number): whatever error that raises is this log's
    # result, and the logs after it are still checked.
    writer = McapLogWriter(logs, path=logs / "0-odd-profile.mcap", run=RunInfo(attachments={"vehicle.toml":
                                                                                               b"services = 5\n"}))
    writer.write("STATE_INFO", StateInformation().encode(), 1)
    writer.close()
    res = run("replay-check", str(logs), cwd=tmp_path, timeout=400)
    assert res.returncode == 2, res.stdout + res.stderr      # a log that cannot be replayed wins
    assert re.search(r"\[1/5\] .*0-odd-profile\.mcap: FAILED in [\d.]+ s: \S", res.stderr), res.stderr
    assert re.search(r"\[2/5\] .*a-clean\.mcap: same", res.stderr), res.stderr
    assert re.search(r"\[3/5\] .*b-cut\.mcap: DIFFERENT", res.stderr), res.stderr
    assert re.search(r"\[4/5\] .*c-damaged\.mcap: FAILED", res.stderr), res.stderr
    assert re.search(r"\[5/5\] .*d-no-profile\.mcap: FAILED .*give the profile with --vehicle FILE", res.stderr)
    assert "replay-check: 5 logs: 1 same, 1 different, 3 could not be replayed" in res.stdout

    # --vehicle FILE (the profile the log was recorded with) replays the log that carries none
    for name in ("0-odd-profile.mcap", "c-damaged.mcap"):
        (logs / name).unlink()
    res = run("replay-check", str(logs), "--json", "--vehicle", str(driver_log.parent / "vehicle.toml"),
              cwd=tmp_path, timeout=400)
    assert res.returncode == 1, res.stdout + res.stderr
    results = {Path(r["log"]).name: r for r in json.loads(res.stdout)}
    assert results["a-clean.mcap"]["status"] == "same" and results["b-cut.mcap"]["status"] == "DIFFERENT"
    assert results["d-no-profile.mcap"]["status"] == "same", results["d-no-profile.mcap"]


def test_replay_check_refuses_a_directory_without_logs(tmp_path: Path) -> None:
    res = run("replay-check", str(tmp_path), cwd=tmp_path, timeout=60)
    assert res.returncode == 2 and "no .mcap logs" in res.stderr
    res = run("replay-check", str(tmp_path / "nope"), cwd=tmp_path, timeout=60)
    assert res.returncode == 2 and "not a directory" in res.stderr
    res = run("replay-check", str(tmp_path), "--vehicle", str(tmp_path / "none.toml"), cwd=tmp_path, timeout=60)
    assert res.returncode == 2 and "none.toml: no such file" in res.stderr
