"""Export a U2SA log to an MCAP file Foxglove can show: JSON messages with JSON schemas.

Foxglove cannot decode LCM, so every message is rewritten as JSON with a JSON Schema
derived from its LCM type. State Information on ``STATE_ESTIMATE`` and ``STATE_INFO``
also yields a ``foxglove.LocationFix`` on ``/location/<channel>`` (a well-known schema
the Map panel shows): geodetic messages directly, local NED ones through the log's
vehicle origin (from its ``vehicle.toml`` attachment).
"""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer

from u2sa_hw.channels import base_type
from u2sa_hw.geo import ned_to_geodetic
from u2sa_hw.messages import REGISTRY, MalformedMessage, to_dict
from u2sa_hw.recording.log_reader import LogFile
from u2sa_hw.vehicle import Origin

# JSON has no NaN or infinity: the export writes them as null, so a float field is a number or null
_FLOAT = ["number", "null"]
_JSON_TYPES: dict[str, Any] = {"int8_t": "integer", "int16_t": "integer", "int32_t": "integer", "int64_t": "integer",
                               "byte": "integer", "float": _FLOAT, "double": _FLOAT, "string": "string",
                               "boolean": "boolean"}
LOCATION_CHANNELS = ("STATE_ESTIMATE", "STATE_INFO")

LOCATION_FIX_SCHEMA: dict[str, Any] = {
    "title": "foxglove.LocationFix",
    "description": "A navigation satellite fix for any Global Navigation Satellite System",
    "type": "object",
    "properties": {
        "timestamp": {"type": "object", "properties": {"sec": {"type": "integer", "minimum": 0},
                                                      "nsec": {"type": "integer", "minimum": 0}}},
        "frame_id": {"type": "string"},
        "latitude": {"type": "number"},
        "longitude": {"type": "number"},
        "altitude": {"type": "number"},
        "position_covariance": {"type": "array", "items": {"type": "number"}, "minItems": 9, "maxItems": 9},
        "position_covariance_type": {"type": "integer", "minimum": 0, "maximum": 3},
    },
}


def json_schema(cls: type) -> dict[str, Any]:
    """A JSON Schema (draft 2020-12 compatible) for the JSON form of LCM type *cls*."""
    props: dict[str, Any] = {"_type": {"type": "string", "const": cls.__name__}}
    for name, lcm_type, dims in zip(cls.__slots__, cls.__typenames__, cls.__dimensions__):
        if lcm_type in _JSON_TYPES:
            item: dict[str, Any] = {"type": _JSON_TYPES[lcm_type]}
            if _JSON_TYPES[lcm_type] is _FLOAT:
                item["description"] = "null where the value is NaN or infinite"
            if lcm_type == "byte" and dims is not None:
                props[name] = {"type": "string", "description": "bytes as hex"}
                continue
        else:
            item = json_schema(REGISTRY.by_name(lcm_type.rsplit(".", 1)[1]))
        props[name] = {"type": "array", "items": item} if dims is not None else item
    return {"title": f"u2sa.{cls.__name__}", "type": "object", "properties": props,
            "required": list(cls.__slots__)}


def _origin(log: LogFile) -> Origin | None:
    data = log.contents.attachments.get("vehicle.toml")
    if not data:
        return None
    try:
        o = tomllib.loads(data.decode()).get("vehicle", {}).get("origin")
        return Origin(float(o["lat"]), float(o["lon"]), float(o.get("alt", 0.0))) if o else None
    except (tomllib.TOMLDecodeError, KeyError, TypeError, ValueError, UnicodeDecodeError):
        return None


def location_fix(msg: Any, origin: Origin | None, log_time_ns: int) -> dict[str, Any] | None:
    """A LocationFix for a State Information with a finite position, or None.

    Foxglove's LocationFix schema allows only numbers, so a message whose position (or
    altitude) is NaN or infinite gives no fix, and a non-finite sigma makes the covariance
    unknown (type 0).
    """
    if not (msg.has("x") and msg.has("y")):
        return None
    if msg.reference_frame == "GEODETIC":
        lat, lon, alt = msg.x, msg.y, (msg.z if msg.has("z") else 0.0)
    elif origin is not None and msg.reference_frame in ("NED", ""):
        lat, lon, alt = ned_to_geodetic(msg.x, msg.y, msg.get("z", 0.0), origin=origin)
    else:
        return None
    if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in (lat, lon, alt)):
        return None
    sx, sy = msg.get("x_sigma"), msg.get("y_sigma")
    known = sx is not None and sy is not None and math.isfinite(sx) and math.isfinite(sy)
    cov = [0.0] * 9
    if known:
        cov[0], cov[4] = sy * sy, sx * sx  # ENU order: east, north
    sec, nsec = divmod(log_time_ns, 1_000_000_000)
    return {"timestamp": {"sec": sec, "nsec": nsec}, "frame_id": msg.sensor_name, "latitude": lat,
            "longitude": lon, "altitude": alt, "position_covariance": cov,
            "position_covariance_type": 2 if known else 0}


def _finite(value: Any) -> Any:
    """JSON has no NaN/inf: replace them with null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value


def export_foxglove(src: Path | str, dst: Path | str) -> dict[str, int]:
    """Write a JSON copy of log *src* to *dst*; return message counts per output channel."""
    log = LogFile(src)
    counts: dict[str, int] = {}
    with open(dst, "wb") as out:
        writer = Writer(out, compression=CompressionType.ZSTD)
        writer.start(profile="", library="u2sa-hw foxglove export")
        schema_ids: dict[str, int] = {}
        channel_ids: dict[str, int] = {}
        origin: Origin | None = None
        origin_read = False

        def emit(topic: str, schema_name: str, schema: dict[str, Any], payload: dict[str, Any], t_ns: int) -> None:
            if schema_name not in schema_ids:
                schema_ids[schema_name] = writer.register_schema(schema_name, "jsonschema", json.dumps(schema).encode())
            if topic not in channel_ids:
                channel_ids[topic] = writer.register_channel(topic, "json", schema_ids[schema_name])
            writer.add_message(channel_ids[topic], t_ns, json.dumps(_finite(payload)).encode(), t_ns)
            counts[topic] = counts.get(topic, 0) + 1

        for m in log.messages():
            if not origin_read:
                origin, origin_read = _origin(log), True
            try:
                msg, _ = REGISTRY.decode(m.data, base_type(m.channel))
            except MalformedMessage:
                continue
            cls = type(msg)
            emit(m.channel, f"u2sa.{cls.__name__}", json_schema(cls), to_dict(msg), m.log_time_ns)
            if m.channel in LOCATION_CHANNELS and cls.__name__ == "StateInformation":
                fix = location_fix(msg, origin, m.log_time_ns)
                if fix is not None:
                    emit(f"/location/{m.channel}", "foxglove.LocationFix", LOCATION_FIX_SCHEMA, fix, m.log_time_ns)
        for name, meta in log.contents.metadata.items():
            writer.add_metadata(name, meta)
        writer.finish()
    return counts
