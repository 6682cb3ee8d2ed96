"""The struct-based chunk parser (u2sa_hw.recording.chunk_parse) and LogFile.selected read every
layout the same as the ``mcap`` library's own reader, and a damaged chunk ends the scan as before."""

from __future__ import annotations

from pathlib import Path

import pytest
from mcap.exceptions import EndOfFile
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.stream_reader import StreamReader, breakup_chunk
from test_log_layouts import LAYOUTS, write

from u2sa_hw.recording.chunk_parse import chunk_data, chunk_records
from u2sa_hw.recording.log_reader import LogFile


def _reference(path: Path) -> list[tuple[str, int, int, int, bytes]]:
    with path.open("rb") as fh:
        reader = make_reader(fh)
        return [(ch.topic, m.log_time, m.publish_time, m.sequence, m.data)
                for _s, ch, m in reader.iter_messages(log_time_order=False)]


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_records_and_selected_match_the_mcap_reader_on_every_layout(layout: str, tmp_path: Path) -> None:
    path = tmp_path / f"{layout}.mcap"
    LAYOUTS[layout](path)
    want = _reference(path)
    log = LogFile(path)
    got = [(log.contents.channels[m.channel_id].topic, m.log_time, m.publish_time, m.sequence, m.data)
           for m in log.records()]
    assert got == want and log.contents.complete and not log.contents.problem
    assert list(LogFile(path).selected(lambda _c: True)) == [(t, lt, d) for t, lt, _p, _s, d in want]
    only = list(LogFile(path).selected(lambda c: c == "/odom"))
    assert only == [(t, lt, d) for t, lt, _p, _s, d in want if t == "/odom"]


def test_chunk_records_equal_breakup_chunk_schemas_and_channels_included(tmp_path: Path) -> None:
    path = tmp_path / "log.mcap"
    write(path, json_channel=True, chunk_size=64)      # small chunks: schemas and channels inside them
    with path.open("rb") as fh:
        chunks = [r for r in StreamReader(fh, emit_chunks=True).records if isinstance(r, Chunk)]
    assert len(chunks) > 1
    for chunk in chunks:
        assert list(chunk_records(chunk)) == breakup_chunk(chunk)


def test_a_chunk_cut_inside_a_record_is_end_of_file_and_the_log_reports_it(tmp_path: Path) -> None:
    path = tmp_path / "log.mcap"
    write(path)
    with path.open("rb") as fh:
        chunk = next(r for r in StreamReader(fh, emit_chunks=True).records if isinstance(r, Chunk))
    whole = list(chunk_records(chunk))
    data = chunk_data(chunk)
    cut = Chunk(message_start_time=0, message_end_time=0, uncompressed_size=len(data) - 3, uncompressed_crc=0,
                compression="", data=data[:-3])
    with pytest.raises(EndOfFile):
        list(chunk_records(cut))
    assert len(whole) >= 3
    # a file cut inside its data: what was readable is kept and the problem is said
    damaged = tmp_path / "cut.mcap"
    damaged.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    log = LogFile(damaged)
    list(log.selected(lambda _c: True))
    assert "truncated" in log.contents.problem or "corrupt" in log.contents.problem


def test_a_sequential_read_skips_the_message_indexes_unparsed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "log.mcap"
    write(path, json_channel=True, chunk_size=64)      # many chunks, a message index per channel after each
    want = list(LogFile(path).selected(lambda _c: True))
    from mcap import records as mcap_records, stream_reader

    def parsed(_stream: object) -> None:
        raise AssertionError("a message index was parsed")

    monkeypatch.setattr(mcap_records.MessageIndex, "read", staticmethod(parsed))
    monkeypatch.setattr(stream_reader.MessageIndex, "read", staticmethod(parsed))
    log = LogFile(path)
    assert list(log.selected(lambda _c: True)) == want and len(want) > 3
    assert log.contents.complete and not log.contents.problem
