"""The records inside an MCAP chunk, parsed with ``struct`` instead of record by record in Python.

The ``mcap`` library's ``breakup_chunk`` reads every field of every record through a stream
object: about 4 µs a message, most of a log replay's reading. A chunk is one buffer once
decompressed, so its messages can be sliced out of it directly (the layout is the MCAP
specification's: opcode u8, record length u64, then for a Message channel id u16, sequence
u32, log time u64, publish time u64 and the data, all little-endian). Schema and Channel
records inside a chunk, rare, are still read by ``mcap``'s own classes; other opcodes are
skipped, as ``breakup_chunk`` does. A record that runs past the chunk's end raises
``mcap.exceptions.EndOfFile``, as a truncated file does.

*keep* (a callable taking a channel id) lets a reader skip the messages of channels it does
not want without making an object for each: :meth:`LogFile.selected` uses it.
"""

from __future__ import annotations

import struct
from io import BytesIO
from typing import Any, Callable, Iterator

from mcap import stream_reader
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile, UnsupportedCompressionError
from mcap.records import Channel, Chunk, Message, Schema

__all__ = ["chunk_data", "chunk_records", "chunk_message_tuples"]

_OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE = 0x03, 0x04, 0x05
_RECORD_HEAD = struct.Struct("<BQ")           # opcode, length
_MESSAGE_HEAD = struct.Struct("<HIQQ")        # channel id, sequence, log time, publish time
_HEAD, _MSG = _RECORD_HEAD.size, _MESSAGE_HEAD.size


def chunk_data(chunk: Chunk) -> bytes:
    """The chunk's records, decompressed (zstd, lz4 or none, as ``mcap`` reads them)."""
    if chunk.compression == "zstd":
        if stream_reader.zstandard is None:
            raise UnsupportedCompressionError("zstandard")
        return stream_reader.zstandard.decompress(chunk.data, chunk.uncompressed_size)
    if chunk.compression == "lz4":
        if stream_reader.lz4 is None:
            raise UnsupportedCompressionError("lz4")
        return stream_reader.lz4.decompress(chunk.data)
    if chunk.compression:
        raise UnsupportedCompressionError(chunk.compression)
    return bytes(chunk.data)


def _walk(data: bytes) -> Iterator[tuple[int, int, int]]:
    """``(opcode, body start, body end)`` of each record in *data*."""
    pos, end = 0, len(data)
    head = _RECORD_HEAD.unpack_from
    while pos < end:
        if pos + _HEAD > end:
            raise EndOfFile()
        opcode, length = head(data, pos)
        start = pos + _HEAD
        pos = start + length
        if pos > end:
            raise EndOfFile()
        yield opcode, start, pos


def _other(opcode: int, data: bytes, start: int, stop: int) -> Schema | Channel | None:
    if opcode == _OP_SCHEMA:
        return Schema.read(ReadDataStream(BytesIO(data[start:stop])))
    if opcode == _OP_CHANNEL:
        return Channel.read(ReadDataStream(BytesIO(data[start:stop])))
    return None   # an opcode a chunk may hold in a later version of the format: skipped


def _parsed(chunk: Chunk) -> Iterator[tuple[tuple[int, int, int, int] | None, Any, int, int]]:
    """Per record: a message's head (channel id, sequence, log time, publish time) with the chunk's data
    and where its payload lies in it, or None with a Schema or Channel record."""
    data = chunk_data(chunk)
    msg_head = _MESSAGE_HEAD.unpack_from
    for opcode, start, stop in _walk(data):
        if opcode == _OP_MESSAGE:
            if stop - start < _MSG:
                raise EndOfFile()
            yield msg_head(data, start), data, start + _MSG, stop
        else:
            record = _other(opcode, data, start, stop)
            if record is not None:
                yield None, record, 0, 0


def chunk_records(chunk: Chunk) -> Iterator[Message | Schema | Channel]:
    """The chunk's Schema, Channel and Message records in order (what ``mcap``'s breakup_chunk gives)."""
    for head, body, start, stop in _parsed(chunk):
        if head is None:
            yield body
        else:
            channel_id, sequence, log_time, publish_time = head
            yield Message(channel_id=channel_id, sequence=sequence, log_time=log_time, publish_time=publish_time,
                          data=body[start:stop])


def chunk_message_tuples(chunk: Chunk, keep: Callable[[int], bool],
                         on_record: Callable[[Schema | Channel], None]) -> Iterator[tuple[int, int, bytes]]:
    """``(channel id, log time, data)`` of the chunk's messages on channels *keep* accepts; Schema and
    Channel records go to *on_record* first (a channel must be known before *keep* is asked about it)."""
    for head, body, start, stop in _parsed(chunk):
        if head is None:
            on_record(body)
        elif keep(head[0]):
            yield head[0], head[2], body[start:stop]
