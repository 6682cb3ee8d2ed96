"""Export a U2SA log to an MCAP file Foxglove can show, with the live bridge's mapping.

Foxglove cannot decode LCM, so every message is rewritten as JSON with a JSON Schema per
(channel, type) pair, and the well-known messages Foxglove's Map, 3D, Table and Log panels
read are added (``u2sa_hw.foxglove.mapping``): the same topics and schemas as
``u2sa foxglove`` shows live, so one layout serves both. Local positions reach the map
through the vehicle origin in the log's ``vehicle.toml``; service log lines come from a
log directory (``u2sa_hw.foxglove.logs``).
"""

from __future__ import annotations

import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from mcap.writer import CompressionType, Writer

from u2sa_hw.channels import base_type
from u2sa_hw.foxglove.logs import read_log_dir
from u2sa_hw.foxglove.mapping import LOG, FoxgloveMapper, Topic
from u2sa_hw.messages import REGISTRY, MalformedMessage
from u2sa_hw.recording.log_reader import LogFile
from u2sa_hw.profile.vehicle import Origin

# Log lines this long before the first or after the last message still belong to the run.
LOG_MARGIN_NS = 5_000_000_000


@dataclass
class ExportReport:
    """What an export wrote: messages per topic, why some well-known topics are empty, undecodable count,
    and the messages of encodings it cannot turn into JSON, per (encoding, topic)."""

    counts: dict[str, int] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    undecodable: int = 0
    skipped: dict[tuple[str, str], int] = field(default_factory=dict)


def log_origin(log: LogFile) -> tuple[Origin | None, str]:
    """The vehicle origin of a log (read after its first message), or None and why there is none."""
    data = log.contents.attachments.get("vehicle.toml")
    if not data:
        return None, ("the log has no vehicle.toml (recorded without --vehicle), so it has no geodetic origin: "
                      "local positions cannot be placed on the map (record with --vehicle PROFILE)")
    try:
        o = tomllib.loads(data.decode()).get("vehicle", {}).get("origin")
        if o:
            return Origin(float(o["lat"]), float(o["lon"]), float(o.get("alt", 0.0))), ""
    except (tomllib.TOMLDecodeError, KeyError, TypeError, ValueError, UnicodeDecodeError) as exc:
        return None, f"the log's vehicle.toml has an unreadable [vehicle] origin ({exc}): no map of local positions"
    return None, "the log's vehicle.toml has no [vehicle] origin: local positions cannot be placed on the map"


def export_foxglove(src: Path | str, dst: Path | str, *, log_dir: Path | None = None) -> ExportReport:
    """Write a Foxglove copy of log *src* to *dst*, with the lines of *log_dir*'s service logs."""
    log = LogFile(src)
    report = ExportReport()
    with open(dst, "wb") as out:
        writer = Writer(out, compression=CompressionType.ZSTD)
        writer.start(profile="", library="u2sa-hw foxglove export")
        schema_ids: dict[tuple[str, bytes], int] = {}
        channel_ids: dict[str, int] = {}

        def emit(topic: Topic, payload: dict, t_ns: int) -> None:
            cid = channel_ids.get(topic.name)
            if cid is None:
                key = (topic.schema_name, topic.schema)
                if key not in schema_ids:
                    schema_ids[key] = writer.register_schema(topic.schema_name, "jsonschema", topic.schema)
                cid = channel_ids[topic.name] = writer.register_channel(topic.name, "json", schema_ids[key])
            writer.add_message(cid, t_ns, json.dumps(payload, allow_nan=False).encode(), t_ns)
            report.counts[topic.name] = report.counts.get(topic.name, 0) + 1

        mapper: FoxgloveMapper | None = None
        no_origin = ""
        first: int | None = None   # a log time of 0 is a time like any other
        last = 0
        passed: dict[str, int] = {}   # JSON channels of other tools, copied as they are: topic -> channel id
        for m in log.messages():
            if mapper is None:   # the attachments precede the first message
                origin, no_origin = log_origin(log)
                mapper = FoxgloveMapper(origin=origin)
            first, last = m.log_time_ns if first is None else min(first, m.log_time_ns), max(last, m.log_time_ns)
            if m.encoding.lower() == "json":
                if m.channel not in passed:
                    schema = log.contents.schemas.get(m.schema_id)
                    sid = (writer.register_schema(schema.name, schema.encoding, schema.data)
                           if schema is not None and schema.encoding == "jsonschema" else 0)
                    passed[m.channel] = writer.register_channel(m.channel, "json", sid)
                writer.add_message(passed[m.channel], m.log_time_ns, m.data, m.log_time_ns)
                report.counts[m.channel] = report.counts.get(m.channel, 0) + 1
                continue
            if m.encoding.lower() not in ("lcm", ""):   # cdr, protobuf, ...: nothing here decodes them
                key = (m.encoding, m.channel)
                report.skipped[key] = report.skipped.get(key, 0) + 1
                continue
            try:
                msg, _ = REGISTRY.decode(m.data, base_type(m.channel))
            except MalformedMessage:
                report.undecodable += 1
                continue
            for topic, payload in mapper.map(m.channel, msg, m.log_time_ns):
                emit(topic, payload, m.log_time_ns)
        if log_dir is not None and first is not None:
            for t_ns, entry in read_log_dir(log_dir, start_ns=first - LOG_MARGIN_NS, end_ns=last + LOG_MARGIN_NS):
                emit(LOG, entry, t_ns)
        for name, meta in log.contents.metadata.items():
            writer.add_metadata(name, meta)
        writer.finish()
    if mapper is not None and mapper.notes:
        report.notes.extend(f"{why} ({n} messages)" for why, n in sorted(mapper.notes.items()))
    if no_origin and not any(t.startswith("/location/STATE_ESTIMATE") for t in report.counts):
        report.notes.insert(0, f"no map of the estimate: {no_origin}")
    if log_dir is None:
        report.notes.append("no service log lines (/log): give the run's log directory with --logs DIR")
    elif LOG.name not in report.counts:
        report.notes.append(f"no service log lines (/log): {log_dir} has no *.log lines within the log's time span")
    return report
