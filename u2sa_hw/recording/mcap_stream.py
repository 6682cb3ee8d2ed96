"""The file under an MCAP writer, kept so that a full disk never leaves a cut, unindexed log.

:class:`TrackedMcapStream` is what :class:`~u2sa_hw.recording.mcap_log.McapFile` gives the
``mcap`` library's ``Writer`` to write into. It

- writes every buffer whole or raises :class:`OSError` (unbuffered: the error surfaces at
  the write that met it, and a short write is continued, never silently dropped);
- notes the records once they are on disk: each chunk with its message indexes (and so its
  message count per channel), each metadata and attachment record, and the schemas and
  channels its owner registers; :attr:`TrackedMcapStream.end` is the offset after the last
  complete unit, where the data section can be cut;
- keeps a **reserve**: space for the summary is allocated (``posix_fallocate``) ahead of the
  data, so a full disk (ENOSPC) or a file-size limit (EFBIG) fails the data write that would
  have eaten it, and the summary still fits. While the file is open it may end in up to
  ``RESERVE_STEP`` zero bytes (a reader of a killed recorder's file stops there, as at any
  cut); finishing trims them.

After a write error :meth:`TrackedMcapStream.tail` builds what ends the file at ``end`` (the
closing metadata, the data end, a summary indexing exactly what stays, the footer) and
:meth:`TrackedMcapStream.rewrite_end` writes it there.
"""

from __future__ import annotations

import errno
import io
import os
import struct
import zlib
from pathlib import Path

from mcap.data_stream import ReadDataStream, RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (Attachment, AttachmentIndex, Channel, ChunkIndex, DataEnd, Footer, McapRecord, Metadata,
                          MetadataIndex, Schema, Statistics, SummaryOffset)

MAGIC = b"\x89MCAP0\r\n"
RESERVE_STEP = 256 * 1024       # the reserve is extended this far past what it must cover, so rarely
METADATA_BUDGET = 4096          # room kept for the records written as a file is finished (u2sa_bus, signers)
_RECORD = struct.Struct("<BQ")            # opcode, length
_CHUNK = struct.Struct("<QQQI")           # message start and end time, uncompressed size and crc
_MESSAGE_INDEX = struct.Struct("<HI")     # channel id, bytes of (log time, offset) pairs
_FOOTER_HEAD = struct.Struct("<BQQQ")
_U32, _U64 = struct.Struct("<I"), struct.Struct("<Q")
# Data end, statistics without its per-channel counts, six summary offsets, footer, magic.
_FIXED_TAIL = 13 + 59 + 6 * 26 + 29 + len(MAGIC)
_CANNOT_RESERVE = {errno.EOPNOTSUPP, errno.EINVAL, errno.ENOSYS}


def record_size(record: McapRecord) -> int:
    """Bytes of *record* as written."""
    b = RecordBuilder()
    record.write(b)
    return b.count


class TrackedMcapStream:
    """The file an mcap ``Writer`` writes into, noting what a summary needs (module docstring).

    *reserve*: keep the summary's space allocated ahead of the data (off: a file system that
    cannot allocate ahead is simply written without one).
    """

    def __init__(self, path: Path, *, reserve: bool = True) -> None:
        self.path = path
        self._fh = open(path, "wb", buffering=0)   # unbuffered: a failing write fails where it happens
        self.pos = 0
        self.end = 0
        self.schemas: list[Schema] = []
        self.channels: list[Channel] = []
        self.chunks: list[tuple[ChunkIndex, dict[int, int]]] = []   # with messages per channel id
        self.metadata: list[MetadataIndex] = []
        self.attachments: list[AttachmentIndex] = []
        self._pending: tuple[ChunkIndex, dict[int, int]] | None = None   # a chunk awaiting its message indexes
        self._data_ended = False
        self._reserve = reserve
        self._allocated = 0
        self._summary_bytes = _FIXED_TAIL + METADATA_BUDGET

    # -- the stream the mcap Writer sees -------------------------------------------------------
    def write(self, data: bytes) -> int:
        """Write all of *data* (OSError when the disk refuses it or the reserve), then note its records."""
        view, start = memoryview(data), self.pos
        if view and self._reserve and not self._data_ended:
            # the summary so far, and the index of a chunk this write may hold
            self._allocate(start + len(view) + self._summary_bytes + 100 + 20 * len(self.channels))
        while self.pos - start < len(view):
            n = self._fh.write(view[self.pos - start:])
            if not n:
                raise OSError(errno.ENOSPC, f"{self.path}: the disk accepted no more bytes")
            self.pos += n
        self._note(start, view)
        return len(view)

    def tell(self) -> int:
        """Bytes written."""
        return self.pos

    def flush(self) -> None:
        """Nothing to do: writes are unbuffered (fsync is :meth:`sync`)."""

    def sync(self) -> None:
        """fsync the file."""
        os.fsync(self._fh.fileno())

    def trim(self) -> None:
        """Drop the reserve past what was written (the file is finished)."""
        if self._allocated > self.pos:
            self._fh.truncate(self.pos)
        self._allocated = self.pos

    def close(self) -> None:
        """Close the file."""
        self._fh.close()

    def _allocate(self, need: int) -> None:
        if need <= self._allocated:
            return
        fd = self._fh.fileno()
        try:
            os.posix_fallocate(fd, self._allocated, need + RESERVE_STEP - self._allocated)
            self._allocated = need + RESERVE_STEP
        except OSError as exc:
            if exc.errno in _CANNOT_RESERVE:
                self._reserve = False   # this file system cannot allocate ahead: write without a reserve
                return
            os.posix_fallocate(fd, self._allocated, need - self._allocated)   # OSError: the disk is full
            self._allocated = need

    # -- what the summary needs -----------------------------------------------------------------
    def add_summary_record(self, record: Schema | Channel) -> None:
        """A schema or channel the owner registered (it travels inside a chunk the stream does not open)."""
        (self.schemas if isinstance(record, Schema) else self.channels).append(record)   # type: ignore[arg-type]
        self._summary_bytes += record_size(record) + (10 if isinstance(record, Channel) else 0)

    @property
    def messages(self) -> int:
        """Messages in the complete chunks."""
        return sum(sum(counts.values()) for _index, counts in self.chunks)

    def _note(self, offset: int, data: memoryview) -> None:
        at = len(MAGIC) if offset == 0 else 0    # the mcap Writer writes the magic, then whole records
        while not self._data_ended and at + 9 <= len(data):
            opcode, length = _RECORD.unpack_from(data, at)
            where, body = offset + at, data[at + 9:at + 9 + length]
            at += 9 + length
            if opcode == Opcode.MESSAGE_INDEX and self._pending is not None:
                chunk, counts = self._pending
                channel, size = _MESSAGE_INDEX.unpack_from(body)
                chunk.message_index_offsets[channel] = where
                chunk.message_index_length += 9 + length
                counts[channel] = counts.get(channel, 0) + size // 16   # (log time, offset) per message
                continue
            self._commit(where)
            if opcode == Opcode.DATA_END:
                self._data_ended = True
            elif opcode == Opcode.CHUNK:
                start_ns, end_ns, uncompressed, _crc = _CHUNK.unpack_from(body)
                n = _U32.unpack_from(body, _CHUNK.size)[0]
                compression = bytes(body[_CHUNK.size + 4:_CHUNK.size + 4 + n]).decode()
                compressed = _U64.unpack_from(body, _CHUNK.size + 4 + n)[0]
                self._pending = (ChunkIndex(chunk_length=9 + length, chunk_start_offset=where, compression=compression,
                                            compressed_size=compressed, message_end_time=end_ns,
                                            message_index_length=0, message_index_offsets={},
                                            message_start_time=start_ns, uncompressed_size=uncompressed), {})
                continue   # complete once its message indexes are written
            elif opcode == Opcode.METADATA:
                name = ReadDataStream(io.BytesIO(body)).read_prefixed_string()
                self._add_index(self.metadata, MetadataIndex(offset=where, length=9 + length, name=name))
            elif opcode == Opcode.ATTACHMENT:
                a = Attachment.read(ReadDataStream(io.BytesIO(body)))
                self._add_index(self.attachments, AttachmentIndex(
                    offset=where, length=9 + length, log_time=a.log_time, create_time=a.create_time,
                    data_size=len(a.data), name=a.name, media_type=a.media_type))
            self.end = offset + at
        if self._pending is not None and self._pending[0].message_index_offsets:
            self._commit(offset + at)

    def _add_index(self, to: list, index: McapRecord) -> None:
        to.append(index)
        self._summary_bytes += record_size(index)

    def _commit(self, upto: int) -> None:
        if self._pending is not None:
            self.chunks.append(self._pending)
            self._summary_bytes += record_size(self._pending[0])
            self._pending = None
            self.end = upto

    # -- ending the file after a write error -----------------------------------------------------
    def drop_last_chunk(self) -> bool:
        """Move :attr:`end` back to the start of the last complete chunk (what followed it goes too); False if none."""
        if not self.chunks:
            return False
        self.end = self.chunks.pop()[0].chunk_start_offset
        self.metadata = [m for m in self.metadata if m.offset < self.end]
        self.attachments = [a for a in self.attachments if a.offset < self.end]
        return True

    def tail(self, metadata: dict[str, dict[str, str]], *, summary: bool) -> bytes:
        """What ends the file at :attr:`end`: *metadata* records, the data end, the summary (schemas,
        channels, statistics and indexes of what stays) when *summary*, the footer and the magic."""
        out = RecordBuilder()
        meta_index = list(self.metadata)
        for name, record in metadata.items():
            at = out.count
            Metadata(name=name, metadata=record).write(out)
            meta_index.append(MetadataIndex(offset=self.end + at, length=out.count - at, name=name))
        DataEnd(data_section_crc=0).write(out)
        head = out.end()
        start = self.end + len(head)
        s = RecordBuilder()
        offsets: list[SummaryOffset] = []
        if summary:
            counts: dict[int, int] = {}
            for _index, per in self.chunks:
                for channel, n in per.items():
                    counts[channel] = counts.get(channel, 0) + n
            stats = Statistics(attachment_count=len(self.attachments), channel_count=len(self.channels),
                               channel_message_counts=counts, chunk_count=len(self.chunks),
                               message_count=sum(counts.values()),
                               message_end_time=max((c.message_end_time for c, _ in self.chunks), default=0),
                               message_start_time=min((c.message_start_time for c, _ in self.chunks), default=0),
                               metadata_count=len(meta_index), schema_count=len(self.schemas))
            groups: tuple[tuple[int, list], ...] = (
                (Opcode.SCHEMA, self.schemas), (Opcode.CHANNEL, self.channels), (Opcode.STATISTICS, [stats]),
                (Opcode.CHUNK_INDEX, [c for c, _ in self.chunks]), (Opcode.ATTACHMENT_INDEX, self.attachments),
                (Opcode.METADATA_INDEX, meta_index))
            for opcode, records in groups:
                at = s.count
                for record in records:
                    record.write(s)
                offsets.append(SummaryOffset(group_opcode=opcode, group_start=start + at, group_length=s.count - at))
        offset_start = start + s.count if summary else 0
        for o in offsets:
            o.write(s)
        data = s.end()
        summary_start = start if data else 0
        crc = zlib.crc32(_FOOTER_HEAD.pack(Opcode.FOOTER, 20, summary_start, offset_start), zlib.crc32(data))
        Footer(summary_start=summary_start, summary_offset_start=offset_start, summary_crc=crc).write(out)
        return head + data + out.end() + MAGIC

    def rewrite_end(self, tail: bytes) -> None:
        """Write *tail* at :attr:`end` (into the reserve), cut the file after it and fsync (OSError: no room)."""
        self._data_ended = True   # the tail's records are not noted, nor reserved for
        self._fh.seek(self.end)
        self.pos = self.end
        self.write(tail)
        self._fh.truncate(self.pos)
        self._allocated = self.pos
        self.sync()
