"""Reading U2SA MCAP logs sequentially, complete or truncated, and recovering them.

A log cut short by SIGKILL or a power cut has no summary; reading it record by record
yields everything up to the last complete chunk (the recorder closes a chunk every
second). :func:`recover` rewrites such a file as a valid, indexed log.

The pilot's messages (RC_MODE, MANUAL_CMD) are stored with their signature trailer (their MCAP
channel's metadata ``pilot_trailer``, u2sa_hw.recording.mcap_log): :meth:`LogFile.messages` and
:meth:`LogFile.selected` give every reader the payload without it, as on any other channel, so a
decoder, a comparison or an export never sees it; ``LogMessage.trailer`` holds it and
``selected(raw=True)`` gives the data as stored (u2sa_hw.recording.pilot_check checks it).
:func:`recover` copies the data as stored.
"""

from __future__ import annotations

import re
import stat
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Chunk, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from u2sa_hw.recording.chunk_parse import chunk_message_tuples, chunk_records

MAGIC = b"\x89MCAP0\r\n"
PILOT_TRAILER_KEY = "pilot_trailer"   # channel metadata (u2sa_hw.recording.mcap_log): bytes of trailer per message
PILOT_TAG = b"U2P1"                   # how the pilot's trailer ends (u2sa_hw.bus.auth.PILOT_TAG, not imported:
                                      # a reader of logs needs none of the bus's key handling)


def trailer_length(channel: Channel) -> int:
    """How many bytes at the end of each message of *channel* are the pilot's trailer (0: none)."""
    value = channel.metadata.get(PILOT_TRAILER_KEY, "") if channel.metadata else ""
    if not value:
        return 0
    try:
        n = int(value)
    except ValueError:
        return 0
    return n if 0 < n <= 1024 else 0


def split_trailer(data: bytes, n: int) -> tuple[bytes, bytes]:
    """(payload, trailer) of a message whose channel keeps *n* bytes of pilot trailer; one that does not
    end in the pilot's tag is all payload (and the pilot check finds it unsigned)."""
    if n and len(data) >= n and data.endswith(PILOT_TAG):
        return data[:-n], data[-n:]
    return data, b""


class _SequentialReader(StreamReader):
    """mcap's StreamReader, message indexes skipped unparsed: a sequential read never uses them, and
    parsing their entries one field at a time is most of what a --fast replay spends outside the chunks."""

    def _read_record(self, opcode: int, length: int) -> Any:
        if opcode == Opcode.MESSAGE_INDEX:
            self._stream.read(length)
            return None
        return super()._read_record(opcode, length)


class LogError(ValueError):
    """A log cannot be read; the message names the file and what to do."""


@dataclass(frozen=True)
class LogMessage:
    """One recorded message (LCM in u2sa logs; another tool's file may hold JSON, CDR, ...)."""

    channel: str
    log_time_ns: int
    data: bytes
    type_name: str
    encoding: str = "lcm"     # the MCAP channel's message encoding
    schema_id: int = 0        # the channel's schema (0: none), in ``LogFile.contents.schemas``
    trailer: bytes = b""      # the pilot's signature trailer kept after *data* (RC_MODE, MANUAL_CMD), else b""


@dataclass
class ChannelSummary:
    """Counts and times of one channel (and type) in a log."""

    channel: str
    type_name: str
    count: int = 0
    first_ns: int = 0
    last_ns: int = 0


@dataclass
class LogContents:
    """Everything in a log except the messages (filled while scanning)."""

    path: Path
    profile: str = ""
    library: str = ""
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    attachments: dict[str, bytes] = field(default_factory=dict)
    attachment_records: list[Attachment] = field(default_factory=list)   # with their times and media types
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    complete: bool = False
    problem: str = ""


class LogFile:
    """A log on disk, read record by record."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        try:
            with open(self.path, "rb") as fh:
                head = fh.read(len(MAGIC))
        except FileNotFoundError:
            raise LogError(f"{self.path}: no such file") from None
        except IsADirectoryError:
            raise LogError(f"{self.path}: is a directory; give a .mcap file") from None
        if head != MAGIC:
            what = "empty" if not head else "not an MCAP file (wrong magic bytes)"
            raise LogError(f"{self.path}: {what}; u2sa logs are MCAP files written by u2sa record or the recorder")
        self.contents = LogContents(self.path)

    def records(self) -> Iterator[Message]:
        """Every Message record in file order; fills :attr:`contents` on the way.

        A truncated or corrupt tail ends the scan and is described in ``contents.problem``.
        """
        channels = self.contents.channels

        def from_chunk(chunk: Chunk) -> Iterator[Message]:
            for record in chunk_records(chunk):
                if isinstance(record, Message):
                    if record.channel_id in channels:
                        yield record
                else:
                    self._note(record)

        def alone(record: Message) -> Iterator[Message]:
            if record.channel_id in channels:
                yield record

        yield from self._scan(from_chunk, alone)

    def selected(self, wanted: Callable[[str], bool], *, raw: bool = False) -> Iterator[tuple[str, int, bytes]]:
        """``(channel, log time ns, data)`` of the messages on channels *wanted* accepts, in file order.

        :meth:`records` for a reader that skips most of a log (a replay): *wanted* is asked once per
        channel, and a message of another channel costs no object. Fills :attr:`contents` the same way.
        *data* is the payload, a pilot trailer cut off, unless *raw*: then the data as stored.
        """
        channels = self.contents.channels
        topics: dict[int, str | None] = {}
        cuts: dict[int, int] = {}   # channel id -> its pilot trailer's length, for the channels that keep one

        def keep(channel_id: int) -> bool:
            topic = topics.get(channel_id, "")
            if topic == "":
                ch = channels.get(channel_id)
                if ch is None:
                    return False   # a channel not (yet) declared: records() leaves it out too
                topic = topics[channel_id] = ch.topic if wanted(ch.topic) else None
                n = 0 if raw else trailer_length(ch)
                if n:
                    cuts[channel_id] = n
            return topic is not None

        def from_chunk(chunk: Chunk) -> Iterator[tuple[str, int, bytes]]:
            for channel_id, log_time, data in chunk_message_tuples(chunk, keep, self._note):
                if cuts and channel_id in cuts:
                    data = split_trailer(data, cuts[channel_id])[0]
                yield topics[channel_id], log_time, data

        def alone(record: Message) -> Iterator[tuple[str, int, bytes]]:
            if keep(record.channel_id):
                data = record.data
                if cuts and record.channel_id in cuts:
                    data = split_trailer(data, cuts[record.channel_id])[0]
                yield topics[record.channel_id], record.log_time, data

        yield from self._scan(from_chunk, alone)

    def _scan(self, from_chunk: Callable[[Chunk], Iterator[Any]], alone: Callable[[Message], Iterator[Any]]
              ) -> Iterator[Any]:
        c = self.contents
        with open(self.path, "rb") as fh:
            try:
                for record in _SequentialReader(fh, emit_chunks=True, record_size_limit=1 << 30).records:
                    if isinstance(record, Chunk):
                        yield from from_chunk(record)
                    elif isinstance(record, Message):
                        yield from alone(record)
                    else:
                        self._note(record)
            except Exception as exc:  # noqa: BLE001 - any failure here is a damaged tail; report, keep what was read
                c.problem = _describe(exc)

    def _note(self, record: Any) -> None:
        """Fill :attr:`contents` from a record that is not a message."""
        c = self.contents
        if isinstance(record, Schema):
            c.schemas[record.id] = record
        elif isinstance(record, Channel):
            c.channels[record.id] = record
        elif isinstance(record, Metadata):
            c.metadata[record.name] = dict(record.metadata)
        elif isinstance(record, Attachment):
            c.attachments[record.name] = bytes(record.data)
            c.attachment_records.append(record)
        elif isinstance(record, Header):
            c.profile, c.library = record.profile, record.library
        elif isinstance(record, Footer):
            c.complete = True

    def messages(self, channel: str | None = None) -> Iterator[LogMessage]:
        """Every message in file order, optionally only channels fully matching the regex *channel*.

        A pilot trailer kept after a message's payload is in ``trailer``, not in ``data``.
        """
        pattern = re.compile(channel) if channel else None
        c = self.contents
        for record in self.records():
            ch = c.channels[record.channel_id]
            if pattern is None or pattern.fullmatch(ch.topic):
                schema = c.schemas.get(ch.schema_id)
                n = trailer_length(ch)
                data, trailer = split_trailer(record.data, n) if n else (record.data, b"")
                yield LogMessage(ch.topic, record.log_time, data, schema.name if schema else "?",
                                 ch.message_encoding, ch.schema_id, trailer)

    def scan(self) -> "LogSummary":
        """Read the whole log once and summarise it."""
        per: dict[tuple[str, str], ChannelSummary] = {}
        first: int | None = None    # a log time of 0 is a time like any other (other tools' logs start there)
        last = 0
        total = 0
        for msg in self.messages():
            key = (msg.channel, msg.type_name)
            s = per.get(key)
            if s is None:
                s = per[key] = ChannelSummary(msg.channel, msg.type_name, first_ns=msg.log_time_ns)
            s.count += 1
            s.last_ns = msg.log_time_ns
            first = msg.log_time_ns if first is None else min(first, msg.log_time_ns)
            last = max(last, msg.log_time_ns)
            total += 1
        return LogSummary(self.contents, sorted(per.values(), key=lambda s: s.channel), first or 0, last, total)


@dataclass
class LogSummary:
    """What ``u2sa log info`` shows."""

    contents: LogContents
    channels: list[ChannelSummary]
    start_ns: int
    end_ns: int
    messages: int

    @property
    def duration_s(self) -> float:
        """Seconds between the first and the last message."""
        return (self.end_ns - self.start_ns) / 1e9 if self.messages else 0.0

    @property
    def devices(self) -> list[str]:
        """Devices with raw I/O in the log (``RAW.<device>`` channels)."""
        return sorted({c.channel[4:] for c in self.channels if c.channel.startswith("RAW.")})


def _describe(exc: Exception) -> str:
    name = type(exc).__name__
    if isinstance(exc, (EOFError, struct.error)) or name in ("EndOfFile",):
        return "truncated: the file ends inside a record (the recorder was killed or lost power)"
    return f"corrupt data after the last readable record ({name}: {exc})"


def recover(src: Path | str, dst: Path | str) -> tuple[int, str]:
    """Rewrite *src* (possibly truncated) as a valid indexed log at *dst*; return (messages, problem).

    Every readable record is kept: schemas (a channel without one, schema id 0, stays
    schemaless), channels with their metadata, messages with their log/publish times and
    sequence numbers, attachments with their times and media types, and metadata (a
    ``recovered_from`` entry added), also when the file holds no message at all. The output
    is written to a temporary file beside *dst* and renamed when complete, so a failure never
    leaves an invalid file at *dst*; it gets *src*'s permission bits.
    """
    import os
    import tempfile

    from mcap.writer import CompressionType, Writer

    log = LogFile(src)
    dst = Path(dst)
    if dst.resolve() == log.path.resolve():
        raise LogError(f"{dst}: recover writes a new file; give an output path other than the input")
    if not dst.parent.is_dir():
        raise LogError(f"{dst}: the directory {dst.parent} does not exist")
    count = 0
    fd, tmp_name = tempfile.mkstemp(prefix=f".{dst.name}.", suffix=".part", dir=dst.parent)
    tmp = Path(tmp_name)
    try:
        with os.fdopen(fd, "wb") as out:
            writer = Writer(out, compression=CompressionType.ZSTD)
            started = False
            schema_ids: dict[int, int] = {0: 0}     # 0: no schema
            channel_ids: dict[int, int] = {}

            def start() -> None:
                c = log.contents
                writer.start(profile=c.profile, library=c.library or "u2sa-hw recover")
                for name, meta in c.metadata.items():
                    writer.add_metadata(name, {**meta, "recovered_from": str(log.path)})
                for a in c.attachment_records:
                    writer.add_attachment(create_time=a.create_time, log_time=a.log_time, name=a.name,
                                          media_type=a.media_type, data=bytes(a.data))

            for msg_rec in log.records():
                c = log.contents
                if not started:
                    start()
                    started = True
                ch = c.channels[msg_rec.channel_id]
                if ch.schema_id not in schema_ids:
                    s = c.schemas.get(ch.schema_id)
                    if s is None:
                        raise LogError(f"{log.path}: channel {ch.topic!r} names schema {ch.schema_id}, which the file "
                                       "does not hold; the file is damaged before its first message")
                    schema_ids[ch.schema_id] = writer.register_schema(s.name, s.encoding, s.data)
                if ch.id not in channel_ids:
                    channel_ids[ch.id] = writer.register_channel(ch.topic, ch.message_encoding,
                                                                 schema_ids[ch.schema_id], dict(ch.metadata))
                writer.add_message(channel_ids[ch.id], msg_rec.log_time, msg_rec.data, msg_rec.publish_time,
                                   msg_rec.sequence)
                count += 1
            if not started:
                start()   # no message: the metadata and attachments are still worth keeping
            writer.finish()
        tmp.chmod(stat.S_IMODE(log.path.stat().st_mode))   # mkstemp made it 0600
        tmp.replace(dst)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return count, log.contents.problem
