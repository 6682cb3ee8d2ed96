"""Foxglove's well-known message schemas, as JSON Schemas, and builders for their parts.

Foxglove recognises a well-known message by its schema *name* (``foxglove.LocationFix``)
whatever the encoding, so the live bridge and the export both send these as JSON with
the JSON Schema below (the subset of each schema's fields we fill, all of them required,
so a payload that validates is one the Map, 3D and Log panels can read).
"""

from __future__ import annotations

import math
from typing import Any

_NUM = {"type": "number"}
_STR = {"type": "string"}
TIME = {"type": "object", "properties": {"sec": {"type": "integer", "minimum": 0},
                                         "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}},
        "required": ["sec", "nsec"]}
VECTOR3 = {"type": "object", "properties": {"x": _NUM, "y": _NUM, "z": _NUM}, "required": ["x", "y", "z"]}
QUATERNION = {"type": "object", "properties": {"x": _NUM, "y": _NUM, "z": _NUM, "w": _NUM},
              "required": ["x", "y", "z", "w"]}
POSE = {"type": "object", "properties": {"position": VECTOR3, "orientation": QUATERNION},
        "required": ["position", "orientation"]}
COLOR = {"type": "object", "properties": {"r": _NUM, "g": _NUM, "b": _NUM, "a": _NUM}, "required": ["r", "g", "b", "a"]}


def _obj(title: str, props: dict[str, Any]) -> dict[str, Any]:
    return {"title": title, "type": "object", "properties": props, "required": list(props)}


def _list(item: dict[str, Any]) -> dict[str, Any]:
    return {"type": "array", "items": item}


LOCATION_FIX = _obj("foxglove.LocationFix", {
    "timestamp": TIME, "frame_id": _STR, "latitude": _NUM, "longitude": _NUM, "altitude": _NUM,
    "position_covariance": {"type": "array", "items": _NUM, "minItems": 9, "maxItems": 9},
    "position_covariance_type": {"type": "integer", "minimum": 0, "maximum": 3}})
FRAME_TRANSFORM = _obj("foxglove.FrameTransform", {
    "timestamp": TIME, "parent_frame_id": _STR, "child_frame_id": _STR, "translation": VECTOR3,
    "rotation": QUATERNION})
POSE_IN_FRAME = _obj("foxglove.PoseInFrame", {"timestamp": TIME, "frame_id": _STR, "pose": POSE})
LOG = _obj("foxglove.Log", {
    "timestamp": TIME, "level": {"type": "integer", "minimum": 0, "maximum": 5}, "message": _STR, "name": _STR,
    "file": _STR, "line": {"type": "integer", "minimum": 0}})
_CUBE = _obj("foxglove.CubePrimitive", {"pose": POSE, "size": VECTOR3, "color": COLOR})
_CYLINDER = _obj("foxglove.CylinderPrimitive", {"pose": POSE, "size": VECTOR3, "bottom_scale": _NUM,
                                                "top_scale": _NUM, "color": COLOR})
_LINE = _obj("foxglove.LinePrimitive", {
    "type": {"type": "integer", "minimum": 0, "maximum": 2}, "pose": POSE, "thickness": _NUM,
    "scale_invariant": {"type": "boolean"}, "points": _list(VECTOR3), "color": COLOR, "colors": _list(COLOR),
    "indices": _list({"type": "integer", "minimum": 0})})
_TEXT = _obj("foxglove.TextPrimitive", {"pose": POSE, "billboard": {"type": "boolean"}, "font_size": _NUM,
                                        "scale_invariant": {"type": "boolean"}, "color": COLOR, "text": _STR})
_ARROW = _obj("foxglove.ArrowPrimitive", {"pose": POSE, "shaft_length": _NUM, "shaft_diameter": _NUM,
                                          "head_length": _NUM, "head_diameter": _NUM, "color": COLOR})
_ENTITY = _obj("foxglove.SceneEntity", {
    "timestamp": TIME, "frame_id": _STR, "id": _STR, "lifetime": TIME, "frame_locked": {"type": "boolean"},
    "metadata": _list(_obj("foxglove.KeyValuePair", {"key": _STR, "value": _STR})),
    "arrows": _list(_ARROW), "cubes": _list(_CUBE), "spheres": _list(_CUBE), "cylinders": _list(_CYLINDER),
    "lines": _list(_LINE), "triangles": {"type": "array", "maxItems": 0}, "texts": _list(_TEXT),
    "models": {"type": "array", "maxItems": 0}})
SCENE_UPDATE = _obj("foxglove.SceneUpdate", {
    "deletions": _list(_obj("foxglove.SceneEntityDeletion", {
        "timestamp": TIME, "type": {"type": "integer", "minimum": 0, "maximum": 1}, "id": _STR})),
    "entities": _list(_ENTITY)})

SCHEMAS: dict[str, dict[str, Any]] = {s["title"]: s for s in (LOCATION_FIX, FRAME_TRANSFORM, POSE_IN_FRAME, LOG,
                                                               SCENE_UPDATE)}
LOG_LEVELS = {"DEBUG": 1, "INFO": 2, "WARN": 3, "WARNING": 3, "ERROR": 4, "CRITICAL": 5, "FATAL": 5}


def stamp(t_ns: int) -> dict[str, int]:
    """A foxglove Time from nanoseconds."""
    sec, nsec = divmod(max(0, int(t_ns)), 1_000_000_000)
    return {"sec": sec, "nsec": nsec}


def vec(x: float, y: float, z: float) -> dict[str, float]:
    """A Vector3."""
    return {"x": float(x), "y": float(y), "z": float(z)}


def quaternion(roll: float, pitch: float, yaw: float) -> dict[str, float]:
    """The quaternion of intrinsic Z-Y-X (yaw, pitch, roll) rotations in radians."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return {"x": sr * cp * cy - cr * sp * sy, "y": cr * sp * cy + sr * cp * sy,
            "z": cr * cp * sy - sr * sp * cy, "w": cr * cp * cy + sr * sp * sy}


def pose(x: float, y: float, z: float, *, yaw: float = 0.0) -> dict[str, Any]:
    """A Pose at (x, y, z) turned by *yaw* about z."""
    return {"position": vec(x, y, z), "orientation": quaternion(0.0, 0.0, yaw)}


def rgba(r: float, g: float, b: float, a: float = 1.0) -> dict[str, float]:
    """A Color (components 0..1)."""
    return {"r": r, "g": g, "b": b, "a": a}


def entity(entity_id: str, frame_id: str, t_ns: int, **primitives: list[dict[str, Any]]) -> dict[str, Any]:
    """A SceneEntity that lives until replaced or deleted, with the given primitive lists."""
    out: dict[str, Any] = {"timestamp": stamp(t_ns), "frame_id": frame_id, "id": entity_id,
                           "lifetime": {"sec": 0, "nsec": 0}, "frame_locked": False, "metadata": []}
    for kind in ("arrows", "cubes", "spheres", "cylinders", "lines", "triangles", "texts", "models"):
        out[kind] = primitives.get(kind, [])
    return out


def text(label: str, x: float, y: float, z: float, color: dict[str, float]) -> dict[str, Any]:
    """A billboard label of constant screen size."""
    return {"pose": pose(x, y, z), "billboard": True, "font_size": 14.0, "scale_invariant": True, "color": color,
            "text": label}


def circle_line(x: float, y: float, z: float, radius: float, color: dict[str, float], *,
                segments: int = 36) -> dict[str, Any]:
    """A horizontal circle of *radius* about (x, y, z) as a closed line."""
    pts = [vec(radius * math.cos(2 * math.pi * i / segments), radius * math.sin(2 * math.pi * i / segments), 0.0)
           for i in range(segments)]
    return line(pts, color, origin=(x, y, z), loop=True)


def line(points: list[dict[str, float]], color: dict[str, float], *, origin: tuple[float, float, float] = (0, 0, 0),
         loop: bool = False, thickness: float = 0.1) -> dict[str, Any]:
    """A line strip (or loop) through *points* about *origin*."""
    return {"type": 1 if loop else 0, "pose": pose(*origin), "thickness": thickness, "scale_invariant": False,
            "points": points, "color": color, "colors": [], "indices": []}
