"""The recorder keeps the pilot's signature with every RC_MODE and MANUAL_CMD and the pilot's public
key in the log's metadata; ``u2sa replay`` checks every recorded pilot message with it (issue 23).

A log of the real RC mux (a process signing RC_MODE with the session's pilot key, recorded by the
recorder's capture) replays with "checked ..., all signed" and compares the same; a copy whose one
RC_MODE trailer has a flipped bit is a finding of --compare; a copy made old-style (no trailers, no
key in the metadata) replays as before with a note; a copy whose recorded key is malformed gets a
one-line note. The session's own recorded simulation (the recorder service, u2sa sim --record)
carries the key and the trailers too. The copies are rewritten with the mcap library.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path
from typing import Any, Callable, Iterator

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer
from recorded_sim import recorded_sim
from test_replay_gpio import record_rc_log

from u2sa_hw.bus import auth as bus_auth
from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.key import KEY_ENV
from u2sa_hw.bus.pilot import pilot_key_id, pilot_paths, public_of
from u2sa_hw.recording import log_reader
from u2sa_hw.recording.log_reader import LogFile
from u2sa_hw.recording.pilot_check import check_log

from conftest import REPO, U2SA

TRAILER = bus_auth.PILOT_TRAILER_LEN


def session_pilot() -> tuple[bytes, bytes]:
    """(public key, private seed) of the session's pilot pair, beside $U2SA_BUS_KEY_FILE."""
    private, public = pilot_paths(Path(os.environ[KEY_ENV]))
    seed = bytes.fromhex(private.read_text().strip())
    pub = bytes.fromhex(public.read_text().strip())
    assert public_of(seed) == pub
    return pub, seed


def rewrite(src: Path, dst: Path, *, message: Callable[[str, int, bytes], bytes] = lambda _c, _i, d: d,
            channel_meta: Callable[[str, dict[str, str]], dict[str, str]] = lambda _c, m: m,
            metadata: Callable[[str, dict[str, str]], dict[str, str]] = lambda _n, m: m) -> None:
    """A copy of the MCAP log *src* at *dst*: each message's data (topic, index on its topic, data),
    each channel's metadata and each metadata record passed through the given functions."""
    with open(src, "rb") as f_in, open(dst, "wb") as f_out:
        reader = make_reader(f_in)
        header = reader.get_header()
        writer = Writer(f_out, compression=CompressionType.ZSTD)
        writer.start(profile=header.profile, library=header.library)
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, metadata(record.name, dict(record.metadata)))
        for a in reader.iter_attachments():
            writer.add_attachment(create_time=a.create_time, log_time=a.log_time, name=a.name,
                                  media_type=a.media_type, data=a.data)
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        counts: dict[str, int] = {}
        for schema, channel, msg in reader.iter_messages(log_time_order=False):
            if schema is not None and schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schemas.get(channel.schema_id, 0),
                    channel_meta(channel.topic, dict(channel.metadata)))
            index = counts.get(channel.topic, 0)
            counts[channel.topic] = index + 1
            writer.add_message(channels[channel.id], msg.log_time, message(channel.topic, index, msg.data),
                               msg.publish_time, msg.sequence)
        writer.finish()


def replay(log: Path, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.pop("U2SA_LCM_URL", None)
    return subprocess.run([*U2SA, "replay", str(log), "--fast", "-o", str(cwd / f"{log.stem}.replay.mcap"), *args],
                          cwd=cwd, env=env, capture_output=True, text=True, timeout=180)


def rc_rows(stdout: str) -> list[str]:
    return [line for line in stdout.splitlines() if line.startswith("RC_MODE [rc]")]


@pytest.fixture(scope="module")
def rc_log(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    yield record_rc_log(tmp_path_factory.mktemp("pilot-rc"))


def rc_modes(log: Path) -> list[Any]:
    return [m for m in LogFile(log).messages(ch.RC_MODE)]


def test_the_log_reader_and_the_bus_agree_on_the_pilot_trailer() -> None:
    assert log_reader.PILOT_TAG == bus_auth.PILOT_TAG


def test_the_recorder_keeps_the_pilot_trailers_and_the_public_key(rc_log: Path) -> None:
    public, seed = session_pilot()
    log = LogFile(rc_log)
    modes = list(log.messages(ch.RC_MODE))
    assert len(modes) >= 10
    meta = log.contents.metadata["u2sa"]
    assert meta["pilot_key"] == public.hex() and meta["pilot_key_id"] == pilot_key_id(public).hex()
    # the readers give the payload alone (it decodes) and the trailer apart, as it crossed the bus
    for m in modes:
        assert len(m.trailer) == TRAILER and m.trailer.endswith(bus_auth.PILOT_TAG), m
        assert bus_auth.check_pilot_packet(ch.RC_MODE, m.data + m.trailer, _verifier(public)) == bus_auth.OK
        t.RcMode.decode(m.data)
    assert all(c.metadata.get("pilot_trailer") == str(TRAILER)
               for c in log.contents.channels.values() if c.topic == ch.RC_MODE)
    # selected() (the player's) cuts it off too; raw=True gives the data as stored
    played = [d for c, _t, d in LogFile(rc_log).selected(lambda c: c == ch.RC_MODE)]
    stored = [d for c, _t, d in LogFile(rc_log).selected(lambda c: c == ch.RC_MODE, raw=True)]
    assert played == [m.data for m in modes] and stored == [m.data + m.trailer for m in modes]
    # other channels keep no trailer, and the private key is nowhere in the log
    assert not any(m.trailer for m in LogFile(rc_log).messages() if m.channel != ch.RC_MODE)
    assert seed not in rc_log.read_bytes() and seed.hex().encode() not in rc_log.read_bytes()
    check = check_log(rc_log)
    assert check.ok and check.checked == len(modes) and check.key_id == pilot_key_id(public).hex()


def _verifier(public: bytes) -> Any:
    from u2sa_hw.bus.pilot import PilotVerifier

    return PilotVerifier(public)


def test_a_replay_checks_the_recorded_pilot_messages_and_compares_the_same(rc_log: Path, tmp_path: Path) -> None:
    public, _ = session_pilot()
    n = len(rc_modes(rc_log))
    res = replay(rc_log, "--compare", cwd=tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    assert (f"pilot messages: {n} checked with the recorded pilot key {pilot_key_id(public).hex()}, all signed"
            in res.stdout), res.stdout
    assert rc_rows(res.stdout) and rc_rows(res.stdout)[0].endswith("same") and "compare: OK" in res.stdout
    # the replay's own log keeps its (replayed) RC mux's trailers: the comparison never saw them
    assert all(len(m.trailer) == TRAILER for m in rc_modes(tmp_path / f"{rc_log.stem}.replay.mcap"))


def test_a_flipped_bit_in_one_rc_mode_trailer_is_a_finding(rc_log: Path, tmp_path: Path) -> None:
    n = len(rc_modes(rc_log))
    bad = n // 2

    def flip(topic: str, index: int, data: bytes) -> bytes:
        if topic != ch.RC_MODE or index != bad:
            return data
        at = len(data) - 10   # inside the signature
        return data[:at] + bytes([data[at] ^ 0x01]) + data[at + 1:]

    copy = tmp_path / "flipped.mcap"
    rewrite(rc_log, copy, message=flip)
    check = check_log(copy)
    assert not check.ok and (check.forged, check.unsigned, check.checked) == (1, 0, n)
    res = replay(copy, "--compare", cwd=tmp_path)
    assert res.returncode == 1, res.stdout + res.stderr
    assert "Traceback" not in res.stderr
    failed = (f"pilot messages: 1 of {n} FAIL the check with the recorded pilot key {check.key_id} (forged 1): "
              "RC_MODE at t=")
    assert failed in res.stdout, res.stdout
    # the payloads are untouched: every stream is the same, the finding is the signature
    assert rc_rows(res.stdout)[0].endswith("same"), res.stdout
    assert f"compare: DIFFERENT: 1 of {n} recorded pilot messages fail the check" in res.stdout, res.stdout
    res = replay(copy, "--compare", "--json", cwd=tmp_path)
    assert res.returncode == 1, res.stdout + res.stderr
    report = json.loads(res.stdout)
    assert not report["ok"] and report["pilot"]["forged"] == 1
    assert report["pilot"]["failures"][0]["channel"] == "RC_MODE"


def test_a_log_from_before_pilot_signatures_replays_as_before_with_a_note(rc_log: Path, tmp_path: Path) -> None:
    copy = tmp_path / "old.mcap"
    rewrite(rc_log, copy,
            message=lambda topic, _i, d: d[:-TRAILER] if topic == ch.RC_MODE else d,
            channel_meta=lambda _c, m: {k: v for k, v in m.items() if k != "pilot_trailer"},
            metadata=lambda name, m: {k: v for k, v in m.items() if not k.startswith("pilot_")})
    assert not any(m.trailer for m in LogFile(copy).messages())
    res = replay(copy, "--compare", cwd=tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "pilot messages: not checked: this log has no pilot signatures (recorded before they existed)" \
        in res.stdout, res.stdout
    assert rc_rows(res.stdout)[0].endswith("same") and "compare: OK" in res.stdout


def test_a_malformed_recorded_pilot_key_is_a_one_line_note(rc_log: Path, tmp_path: Path) -> None:
    copy = tmp_path / "malformed.mcap"
    rewrite(rc_log, copy, metadata=lambda name, m: {**m, "pilot_key": "not-a-key"} if name == "u2sa" else m)
    res = replay(copy, cwd=tmp_path)
    assert res.returncode == 0 and "Traceback" not in res.stderr, res.stdout + res.stderr
    notes = [line for line in res.stdout.splitlines() if line.startswith("pilot messages:")]
    assert notes == ["pilot messages: not checked: the log's recorded pilot key is malformed "
                     "(pilot_key 'not-a-key' is not 64 hex digits)"], res.stdout
    # a key of the right length whose id is not the recorded one
    other = tmp_path / "other-key.mcap"
    rewrite(rc_log, other, metadata=lambda name, m: {**m, "pilot_key": "11" * 32} if name == "u2sa" else m)
    check = check_log(other)
    assert check.ok and not check.checked and "pilot_key_id" in check.note and "malformed" in check.note


def test_the_simulations_recorder_service_keeps_the_pilot_key_and_trailers(tmp_path_factory: pytest.TempPathFactory
                                                                            ) -> None:
    sim = recorded_sim(tmp_path_factory)
    log = LogFile(sim.log)
    modes = [m for m in log.messages(ch.RC_MODE)]
    manual = [m for m in log.messages(ch.MANUAL_CMD)]
    assert modes and all(len(m.trailer) == TRAILER for m in modes + manual)
    meta = log.contents.metadata["u2sa"]
    assert len(meta["pilot_key"]) == 64 and meta["pilot_key_id"] == pilot_key_id(bytes.fromhex(meta["pilot_key"])).hex()
    check = check_log(sim.log)
    assert check.ok and check.checked == len(modes) + len(manual) and check.key_id == meta["pilot_key_id"]
