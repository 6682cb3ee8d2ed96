"""Reading a recorded message's header without decoding it (u2sa_hw.recording.mcap_log): every u2sa type
starts with its Header (fingerprint, system_id, timestamp_us, source)."""

from __future__ import annotations

from u2sa_hw import lcmtypes as t
from u2sa_hw.recording.mcap_log import header_source, header_timestamp_ns


def _encoded(*, source: str, stamp_us: int) -> bytes:
    msg = t.RcMode()
    msg.header.system_id = 7
    msg.header.timestamp_us = stamp_us
    msg.header.source = source
    return msg.encode()


def test_the_header_time_and_source_are_read_from_the_encoded_bytes() -> None:
    data = _encoded(source="rc", stamp_us=1_733_000_000_123_456)
    assert header_timestamp_ns(data) == 1_733_000_000_123_456_000
    assert header_source(data) == "rc"


def test_no_time_or_too_few_bytes_is_none() -> None:
    assert header_timestamp_ns(_encoded(source="rc", stamp_us=0)) is None
    assert header_timestamp_ns(b"\x00" * 19) is None
    assert header_source(b"\x00" * 5) == ""
