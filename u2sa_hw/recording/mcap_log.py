"""Writing LCM traffic into MCAP logs: chunked (zstd or lz4), indexed, with statistics.

LCM bytes are stored unchanged (message encoding ``lcm``; on a signed bus the verified
payload, without its trailer, but for the pilot's channels, below), each type's ``.lcm``
definition is its schema, and the vehicle profile and configs travel as attachments
and metadata. :meth:`McapLogWriter.flush` closes the chunk in progress and fsyncs, so
calling it every second bounds what a SIGKILL or power cut can lose to that second.
Files rotate by size and duration with timestamped names.

Who signed each message: an MCAP channel per (topic, type, signer), whose metadata
``signer`` is the sender id (16 hex digits) of the process that signed it; each finished
file gets a ``u2sa_signers`` metadata record naming, per signer, the header sources it
signed as (``gps``, ``u2sa-cli-1234``). See docs/recording.md.

The pilot's messages (RC_MODE, MANUAL_CMD) keep their 88-byte Ed25519 trailer, as they crossed
the bus, so that a replay can check them later: their MCAP channel's metadata
``pilot_trailer = "88"`` says that every message's data ends with it, and the ``u2sa`` metadata
record names the pilot's public key (``pilot_key``, hex) and its id (``pilot_key_id``). Readers
of :mod:`u2sa_hw.recording.log_reader` get the payload without it (and the trailer apart);
an LCM decoder of another tool ignores the trailing bytes anyway.

A full disk never leaves a cut file: the summary's space is reserved ahead of the data, and
after a write error :meth:`McapFile.close` ends the file at its last complete chunk with a
summary indexing what stays (:mod:`u2sa_hw.recording.mcap_stream`).
"""

from __future__ import annotations

import errno
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from mcap.records import Channel, Schema
from mcap.writer import CompressionType, Writer

from u2sa_hw import __version__
from u2sa_hw.messages import REGISTRY
from u2sa_hw.recording.log_reader import PILOT_TRAILER_KEY
from u2sa_hw.recording.mcap_stream import TrackedMcapStream
from u2sa_hw.recording.schemas import MESSAGE_ENCODING, SCHEMA_ENCODING, schema_text

PROFILE = "u2sa"
# Packets on the bus that are not LCM types, by their first 8 bytes: LCM's own self-test
# (lcm_create sends "lcm self test" on LCM_SELF_TEST to check that multicast loops back).
FOREIGN_PACKETS = {b"lcm self": "lcm_self_test"}
BUS_METADATA = "u2sa_bus"   # metadata record written as each file is finished (BusCapture.bus_metadata)
SIGNERS_METADATA = "u2sa_signers"   # signer id -> the header sources it signed as, per file
SIGNER_KEY = "signer"               # channel metadata: the sender id that signed its messages
# PILOT_TRAILER_KEY, channel metadata: every message's data ends with this many bytes of the pilot's
# signature trailer (u2sa_hw.bus.auth.PILOT_TRAILER_LEN), kept so that a replay can check it
# (u2sa_hw.recording.pilot_check); the readers cut it off (u2sa_hw.recording.log_reader).
COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


@dataclass
class RunInfo:
    """What a log says about the run: stored as metadata ``u2sa`` and attachments."""

    vehicle: str = ""
    system_id: int = 0
    lcm_url: str = ""
    attachments: dict[str, bytes] = field(default_factory=dict)  # name -> file contents
    bus_security: str = ""    # "signed" or "open": what the recorder's transport verified
    bus_key_id: str = ""      # the public id of the key it verified with (never the key)
    # The pilot's public key (hex) the recorder verified RC_MODE and MANUAL_CMD with, and its id:
    # a replay checks the kept pilot trailers with it. Empty when it had none (an open bus). Never a private key.
    pilot_key: str = ""
    pilot_key_id: str = ""

    def metadata(self) -> dict[str, str]:
        """The ``u2sa`` metadata record."""
        return {"vehicle": self.vehicle, "system_id": str(self.system_id), "lcm_url": self.lcm_url,
                "host": socket.gethostname(), "u2sa_hw_version": __version__,
                "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "bus_security": self.bus_security,
                "bus_key_id": self.bus_key_id, "pilot_key": self.pilot_key, "pilot_key_id": self.pilot_key_id}


def header_timestamp_ns(data: bytes) -> int | None:
    """The ``header.timestamp_us`` of an encoded u2sa message in ns (the publisher's wall clock when it
    published), or None when it is not one or has no time: every type starts with its Header."""
    at = 8 + 4   # fingerprint, system_id (int32)
    if len(data) < at + 8:
        return None
    stamp_us = int.from_bytes(data[at:at + 8], "big", signed=True)
    return stamp_us * 1000 if stamp_us > 0 else None


def header_source(data: bytes) -> str:
    """The ``header.source`` of an encoded u2sa message ("" when it is not one): every type starts with its Header."""
    at = 8 + 12   # fingerprint, system_id (int32), timestamp_us (int64)
    if len(data) < at + 4:
        return ""
    n = int.from_bytes(data[at:at + 4], "big")
    if n < 1 or at + 4 + n > len(data):
        return ""
    return data[at + 4:at + 3 + n].decode("utf-8", "replace")


def timestamped_name(prefix: str, *, when: float | None = None) -> str:
    """``<prefix>-YYYYmmdd-HHMMSS.mcap`` in local time (a second file in the same second gets ``_001``,
    ``_002``, ... before ``.mcap``, so the names sort in recording order)."""
    return f"{prefix}-{time.strftime('%Y%m%d-%H%M%S', time.localtime(when))}.mcap"


class McapFile:
    """One open MCAP file with schema/channel ids per (channel, type).

    Fails safe: after a write error (a full disk, at a write, a flush or while finishing) the
    file is not left cut inside a record: :meth:`close` cuts it back to its last complete chunk
    and ends it there with a summary indexing what stays. :attr:`error` is the error,
    :attr:`lost` the messages :meth:`write` took that are not in the file, :attr:`cut_short`
    says what happened ("" when the file was finished normally).
    """

    def __init__(self, path: Path, *, compression: str, chunk_size: int, run: RunInfo) -> None:
        self.path = path
        self._stream = TrackedMcapStream(path)
        self._writer = Writer(self._stream, chunk_size=chunk_size, compression=COMPRESSION[compression])
        self._schemas: dict[bytes, int] = {}
        self._channels: dict[tuple[str, int, str, int], int] = {}
        self.signers: dict[str, set[str]] = {}    # signer -> header sources seen from it
        self.messages = 0
        self.lost = 0
        self.error: OSError | None = None
        self.cut_short = ""
        self._closed = False
        self.opened = time.monotonic()
        try:
            self._writer.start(profile=PROFILE, library=f"u2sa-hw {__version__}")
            self._writer.add_metadata("u2sa", run.metadata())
            now = time.time_ns()
            for name, data in run.attachments.items():
                self._writer.add_attachment(create_time=now, log_time=now, name=name,
                                            media_type="application/toml", data=data)
        except OSError as exc:   # a full disk already: leave a valid (empty) file, not a cut one
            self.error = exc
            try:
                self.close()
            except OSError:
                pass
            raise

    def _schema_id(self, fingerprint: bytes) -> int:
        sid = self._schemas.get(fingerprint)
        if sid is None:
            cls = REGISTRY.by_fingerprint(fingerprint)
            if cls is not None:
                name, text = cls.__name__, schema_text(cls).encode()
            elif fingerprint in FOREIGN_PACKETS:   # not an LCM type: a packet LCM itself sends
                name, text = FOREIGN_PACKETS[fingerprint], b""
            else:  # a type this build does not know: keep the bytes, name the fingerprint
                name, text = f"unknown_{fingerprint.hex()}", b""
            sid = self._writer.register_schema(name, SCHEMA_ENCODING, text)
            self._stream.add_summary_record(Schema(id=sid, name=name, encoding=SCHEMA_ENCODING, data=text))
            self._schemas[fingerprint] = sid
        return sid

    def write(self, channel: str, data: bytes, log_time_ns: int, signer: str = "", trailer: int = 0) -> None:
        """Append one LCM message (*signer*: the verified sender id that signed it, "" on an open bus).

        *trailer*: *data* ends with that many bytes of the pilot's signature trailer (its MCAP
        channel says so in ``pilot_trailer``); 0: *data* is the payload alone.
        """
        if self.error is not None:
            raise OSError(self.error.errno, f"{self.path}: not writable after an earlier error ({self.error})")
        try:
            sid = self._schema_id(data[:8]) if len(data) >= 8 else self._schema_id(b"")
            key = (channel, sid, signer, trailer)
            cid = self._channels.get(key)
            if cid is None:
                meta = {SIGNER_KEY: signer} if signer else {}
                if trailer:
                    meta[PILOT_TRAILER_KEY] = str(trailer)
                cid = self._writer.register_channel(topic=channel, message_encoding=MESSAGE_ENCODING, schema_id=sid,
                                                    metadata=meta)
                self._stream.add_summary_record(Channel(id=cid, topic=channel, message_encoding=MESSAGE_ENCODING,
                                                        schema_id=sid, metadata=meta))
                self._channels[key] = cid
                if signer:
                    self.signers.setdefault(signer, set()).add(header_source(data))
            self._writer.add_message(channel_id=cid, log_time=log_time_ns, data=data, publish_time=log_time_ns)
        except OSError as exc:
            self.error = exc
            raise
        self.messages += 1

    def flush(self) -> None:
        """Close the chunk in progress, write it out and fsync."""
        try:
            self._writer.flush()
            self._stream.sync()
        except OSError as exc:
            self.error = exc
            raise

    def close(self, metadata: dict[str, dict[str, str]] | None = None) -> None:
        """Write *metadata* records (what is known only at the end), the summary (indexes, statistics), and close.

        After a write error (earlier, or now) the file ends at its last complete chunk instead
        (:meth:`_end_early`); OSError only when even that could not be written.
        """
        if self._closed:
            return
        self._closed = True
        records = dict(metadata or {})
        if self.signers:
            records[SIGNERS_METADATA] = {signer: ", ".join(sorted(s for s in sources if s))
                                         for signer, sources in sorted(self.signers.items())}
        try:
            if self.error is None:
                try:
                    for name, record in records.items():
                        self._writer.add_metadata(name, record)
                    self._writer.finish()
                    self._stream.trim()
                    self._stream.sync()
                    return
                except OSError as exc:
                    self.error = exc
            written = {m.name for m in self._stream.metadata}
            self._end_early({name: r for name, r in records.items() if name not in written})
        finally:
            self._stream.close()

    def _end_early(self, metadata: dict[str, dict[str, str]]) -> None:
        """End the file after a write error: cut back to the last complete chunk, then write the closing
        *metadata* and a full summary there, else the summary alone, else only the footer (a valid
        file readers scan); when not even that fits, drop the last chunk to make room and try again."""
        s, dropped = self._stream, 0
        while True:
            for meta, summary in ((metadata, True), ({}, True), ({}, False)):
                try:
                    s.rewrite_end(s.tail(meta, summary=summary))
                except OSError:
                    continue
                self.lost = self.messages - s.messages
                self.cut_short = (f"{self.path}: {self.error}; the file ends at its last complete chunk: "
                                  f"{s.messages} messages kept, {self.lost} lost"
                                  + (f" ({dropped} complete chunks dropped to make room)" if dropped else "")
                                  + ("" if summary else "; no room for its summary: readers scan it"))
                return
            if not s.drop_last_chunk():
                self.lost = self.messages - s.messages
                raise OSError(errno.ENOSPC, f"{self.path}: no room even for a footer after {self.error}")
            dropped += 1

    @property
    def size(self) -> int:
        """Bytes written so far."""
        return self._stream.pos


class McapLogWriter:
    """Writes a sequence of rotated MCAP files into a directory."""

    def __init__(self, directory: Path | str, *, prefix: str = "u2sa", compression: str = "zstd",
                 chunk_size: int = 1 << 20, rotate_size_mb: float = 0.0, rotate_duration_s: float = 0.0,
                 run: RunInfo | None = None, path: Path | str | None = None) -> None:
        if compression not in COMPRESSION:
            raise ValueError(f"compression must be one of {', '.join(COMPRESSION)}, not {compression!r}")
        self.directory = Path(directory)
        self.prefix = prefix
        self.compression = compression
        self.chunk_size = chunk_size
        self.rotate_size = int(rotate_size_mb * 1e6)
        self.rotate_duration = rotate_duration_s
        self.run = run or RunInfo()
        self._fixed_path = Path(path) if path else None
        self.files: list[Path] = []
        self.current: McapFile | None = None
        self.messages = 0
        self.lost = 0                     # messages write() took that a write error cut off (in no file)
        self.cut_short: list[str] = []    # a line per file a write error ended early (McapFile.cut_short)
        # Metadata written into each file as it is finished (the recorder's bus drop counts).
        self.closing_metadata: Callable[[], dict[str, dict[str, str]]] | None = None

    def _open(self) -> McapFile:
        self.directory.mkdir(parents=True, exist_ok=True)
        if self._fixed_path is not None and not self.files:
            path = self._fixed_path
        else:
            base = self._fixed_path.stem if self._fixed_path else self.prefix
            first = self.directory / timestamped_name(base)
            path, n = first, 1
            while path.exists() or path in self.files:   # a second file within one second
                path = first.with_name(f"{first.stem}_{n:03d}.mcap")
                n += 1
        self.files.append(path)
        return McapFile(path, compression=self.compression, chunk_size=self.chunk_size, run=self.run)

    def write(self, channel: str, data: bytes, log_time_ns: int, signer: str = "", trailer: int = 0) -> None:
        """Append one message (signed by *signer*; *trailer*: see :meth:`McapFile.write`), rotating first
        when the current file is full or old."""
        if self.current is None:
            self.current = self._open()
        elif self._due_for_rotation(self.current):
            old = self._finish()
            if old.error is not None:
                raise old.error   # the disk is full: no new file
            self.current = self._open()
        self.current.write(channel, data, log_time_ns, signer, trailer)
        self.messages += 1

    def _due_for_rotation(self, f: McapFile) -> bool:
        if self.rotate_size and f.size >= self.rotate_size:
            return True
        return bool(self.rotate_duration and time.monotonic() - f.opened >= self.rotate_duration)

    def flush(self) -> None:
        """Flush the current file (chunk closed, fsynced)."""
        if self.current is not None:
            self.current.flush()

    def close(self) -> None:
        """Finish the current file (after a write error: end it at its last complete chunk, see McapFile)."""
        if self.current is not None:
            self._finish()

    def _finish(self) -> McapFile:
        f, self.current = self.current, None
        assert f is not None
        try:
            f.close(self._closing())
        finally:
            self.lost += f.lost
            if f.cut_short:
                self.cut_short.append(f.cut_short)
        return f

    def _closing(self) -> dict[str, dict[str, str]]:
        return self.closing_metadata() if self.closing_metadata is not None else {}

    def describe(self) -> dict[str, Any]:
        """Figures for health."""
        return {"file": str(self.current.path) if self.current else "", "files": len(self.files),
                "messages": self.messages}
