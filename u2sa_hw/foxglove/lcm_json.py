"""Our own types as JSON for Foxglove: a JSON Schema per LCM type and one topic per (channel, type).

A channel can carry several types (``RAW.rc``: RawGpioEdge and RawGpioWrite; ``WORLD``:
Circle, Rectangle, Polygon): a Foxglove channel has one schema, so each type gets a topic of
its own: the LCM channel's name for its declared base type, ``<CHANNEL>/<Type>`` for any other.
"""

from __future__ import annotations

import json
import math
from functools import lru_cache
from typing import Any

from u2sa_hw.channels import base_type
from u2sa_hw.messages import REGISTRY

# JSON has no NaN or infinity: they are written as null, so a float field is a number or null
_FLOAT = ["number", "null"]
_JSON_TYPES: dict[str, Any] = {"int8_t": "integer", "int16_t": "integer", "int32_t": "integer", "int64_t": "integer",
                               "byte": "integer", "float": _FLOAT, "double": _FLOAT, "string": "string",
                               "boolean": "boolean"}


def json_schema(cls: type) -> dict[str, Any]:
    """A JSON Schema (draft 2020-12 compatible) for the JSON form (``to_dict``) of LCM type *cls*."""
    props: dict[str, Any] = {"_type": {"type": "string", "const": cls.__name__}}
    for name, lcm_type, dims in zip(cls.__slots__, cls.__typenames__, cls.__dimensions__):
        if lcm_type in _JSON_TYPES:
            if lcm_type == "byte" and dims is not None:
                props[name] = {"type": "string", "description": "bytes as hex"}
                continue
            item: dict[str, Any] = {"type": _JSON_TYPES[lcm_type]}
            if _JSON_TYPES[lcm_type] is _FLOAT:
                item["description"] = ("null where the value is NaN or infinite, or absent (a presence-vector "
                                       "field whose bit is clear)" if name in getattr(cls, "PRESENCE_FIELDS", ())
                                       else "null where the value is NaN or infinite")
        else:
            item = json_schema(REGISTRY.by_name(lcm_type.rsplit(".", 1)[1]))
        props[name] = {"type": "array", "items": item} if dims is not None else item
    return {"title": f"u2sa.{cls.__name__}", "type": "object", "properties": props,
            "required": ["_type", *cls.__slots__], "additionalProperties": False}


@lru_cache(maxsize=None)
def schema_bytes(cls: type) -> bytes:
    """:func:`json_schema` of *cls*, serialised once."""
    return json.dumps(json_schema(cls)).encode()


def topic_for(channel: str, cls: type) -> str:
    """The Foxglove topic of messages of *cls* on LCM *channel* (see the module docstring)."""
    return channel if base_type(channel) is cls else f"{channel}/{cls.__name__}"


def finite(value: Any) -> Any:
    """*value* with NaN and infinite floats replaced by None (JSON has neither)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [finite(v) for v in value]
    return value
