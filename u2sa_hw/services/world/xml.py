"""A-priori objects file (thesis 3.2.3.3): XML entries named by object class, in; messages out.

```xml
<world>
  <Circle>                                  <!-- the thesis's example (uid, x, y), plus a radius -->
    <uid>Circle1</uid>
    <x>4</x> <y>8</y>                       <!-- Local (default): NED metres about the origin -->
    <radius>1.5</radius>                    <!-- without it: the default radius (config, 0 = a point) -->
    <type>buoy</type>                       <!-- object_type (default: the class, lower case) -->
    <level>3</level>                        <!-- 0 unknown, 1 hindrance, 2 avoid if possible, 3 avoid at all costs (default) -->
  </Circle>
  <Rectangle>
    <uid>dock</uid>
    <reference>Global</reference>           <!-- Global: lat, lon in degrees, alt m above sea level -->
    <lat>29.1897</lat> <lon>-81.0481</lon>
    <length>12</length> <width>3</width>
    <heading unit="deg">45</heading>        <!-- length axis, clockwise from north; rad unless unit="deg" -->
  </Rectangle>
  <Polygon>                                 <!-- centre: <x>/<y> if given, else the vertices' mean -->
    <uid>island</uid>
    <vertex><x>20</x><y>0</y></vertex> <vertex><x>25</x><y>5</y></vertex> <vertex><x>20</x><y>8</y></vertex>
  </Polygon>
  <Sphere><uid>balloon</uid><x>0</x><y>30</y><z>-10</z><radius>2</radius></Sphere>
  <PointCloud>                              <!-- points from the centre: azimuth (clockwise from north), elevation, distance -->
    <uid>rocks</uid><x>-10</x><y>-10</y>
    <point><azimuth unit="deg">0</azimuth><elevation>0</elevation><distance>2</distance></point>
  </PointCloud>
  <Object><uid>post</uid><x>3</x><y>3</y></Object>   <!-- a plain point Object Description -->
</world>
```

A ``<Circle>`` or ``<Sphere>`` without ``<radius>`` -- the thesis's own Circle example has
none -- gets *default_radius* (the world modeler's ``default_radius_m``, 0 by default:
a point, which the planner still keeps its clearance margin from).
Class names are case-insensitive. Global entries use ``<lat>/<lon>/<alt>`` (vertices
``<vertex><lat/><lon/></vertex>``), Local ones ``<x>/<y>/<z>``; an absent altitude means
the origin's. The objects come back in their file frame (``NED`` or ``GEODETIC``); the world
model places them. Every error names the file, the line and the element.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from u2sa_hw import lcmtypes as t
from u2sa_hw.geo import GeoOrigin
from u2sa_hw.messages import as_type
from u2sa_hw.services.mission.xmltree import XmlFileError, XmlNode, parse_xml, read_xml_file

_COMMON = {"uid": False, "reference": False, "x": False, "y": False, "z": False, "lat": False, "lon": False,
           "alt": False, "type": False, "level": False}
SHAPES: dict[str, tuple[type, dict[str, bool]]] = {
    "object": (t.ObjectDescription, {}),
    "circle": (t.Circle, {"radius": False}),
    "rectangle": (t.Rectangle, {"length": False, "width": False, "heading": False}),
    "polygon": (t.Polygon, {"vertex": True}),
    "sphere": (t.Sphere, {"radius": False}),
    "pointcloud": (t.PointCloud, {"point": True}),
}
DEFAULT_LEVEL = 3


def _position(node: XmlNode, one: dict[str, XmlNode], *, geodetic: bool, origin: GeoOrigin,
              required: bool) -> tuple[float, float, float] | None:
    own, other = (("lat", "lon", "alt"), ("x", "y", "z")) if geodetic else (("x", "y", "z"), ("lat", "lon", "alt"))
    for tag in other:
        if tag in one:
            hint = "Global entries use <lat>, <lon>, <alt>" if geodetic else "<lat>/<lon> need <reference>Global</reference>"
            raise one[tag].error(f"not allowed here: {hint}")
    a, b, c = own
    if a not in one and b not in one:
        if required:
            raise node.error(f"has no position: give <{a}> and <{b}>")
        return None
    if (a in one) != (b in one):
        raise node.error(f"needs <{a}> and <{b}> together")
    z_default = origin.alt if geodetic else 0.0
    return one[a].number(), one[b].number(), one[c].number() if c in one else z_default


def _vertex(node: XmlNode, *, geodetic: bool, origin: GeoOrigin) -> tuple[float, float]:
    tags = node.only_children({"x": False, "y": False, "lat": False, "lon": False})
    pos = _position(node, {k: v[0] for k, v in tags.items()}, geodetic=geodetic, origin=origin, required=True)
    return pos[0], pos[1]


def _cloud_point(node: XmlNode) -> t.CloudPoint:
    tags = node.only_children({"azimuth": False, "elevation": False, "distance": False})
    if "azimuth" not in tags or "distance" not in tags:
        raise node.error("needs <azimuth> and <distance> (and optionally <elevation>)")
    p = t.CloudPoint()
    p.azimuth = tags["azimuth"][0].angle()
    p.elevation = tags["elevation"][0].angle() if "elevation" in tags else 0.0
    p.distance = tags["distance"][0].number()
    if p.distance < 0:
        raise tags["distance"][0].error("must not be negative")
    return p


def _radius(node: XmlNode, one: dict[str, XmlNode], default_radius: float) -> float:
    return one["radius"].positive() if "radius" in one else default_radius


def _object(node: XmlNode, origin: GeoOrigin, default_radius: float) -> Any:
    cls, extra = SHAPES[node.key]
    tags = node.only_children({**_COMMON, **extra})
    one = {k: v[0] for k, v in tags.items() if not {**_COMMON, **extra}[k]}
    if "uid" not in one:
        raise node.error("has no <uid> (a-priori objects need a unique name)")
    reference = one["reference"].word().lower() if "reference" in one else "local"
    if reference not in ("local", "global"):
        raise one["reference"].error(f"must be Local or Global, got {one['reference'].text!r}")
    geodetic = reference == "global"
    obj = cls()
    base = as_type(obj, t.ObjectDescription)
    base.uid = one["uid"].word()
    base.object_type = one["type"].word() if "type" in one else node.key
    base.level = DEFAULT_LEVEL
    if "level" in one:
        level = one["level"].number()
        if level not in (0, 1, 2, 3):
            raise one["level"].error(f"must be 0, 1, 2 or 3, got {one['level'].text!r}")
        base.level = int(level)
    base.reference_frame = "GEODETIC" if geodetic else "NED"
    base.source = "a-priori"
    if isinstance(obj, (t.Circle, t.Rectangle, t.Sphere, t.Polygon)):
        as_type(obj, t.ShapeDescription).shape_type = node.key
    pos = _position(node, one, geodetic=geodetic, origin=origin, required=not isinstance(obj, t.Polygon))
    if isinstance(obj, t.Circle):
        obj.radius = _radius(node, one, default_radius)
    elif isinstance(obj, t.Sphere):
        obj.sphere_radius = _radius(node, one, default_radius)
    elif isinstance(obj, t.Rectangle):
        obj.length = _required(node, one, "length").positive()
        obj.width = _required(node, one, "width").positive()
        obj.heading = one["heading"].angle() if "heading" in one else 0.0
    elif isinstance(obj, t.Polygon):
        vertices = [_vertex(v, geodetic=geodetic, origin=origin) for v in tags.get("vertex", [])]
        if len(vertices) < 3:
            raise node.error(f"needs at least 3 <vertex> elements, has {len(vertices)}")
        obj.vx, obj.vy = [v[0] for v in vertices], [v[1] for v in vertices]
        obj.num_vertices = len(vertices)
        if pos is None:
            pos = (sum(obj.vx) / len(vertices), sum(obj.vy) / len(vertices), origin.alt if geodetic else 0.0)
    elif isinstance(obj, t.PointCloud):
        obj.points = [_cloud_point(p) for p in tags.get("point", [])]
        obj.num_points = len(obj.points)
        if not obj.points:
            raise node.error("needs at least one <point>")
    base.x, base.y, base.z = pos
    return obj


def _required(node: XmlNode, one: dict[str, XmlNode], tag: str) -> XmlNode:
    if tag not in one:
        raise node.error(f"has no <{tag}>")
    return one[tag]


def objects_from_tree(root: XmlNode, *, origin: GeoOrigin, default_radius: float = 0.0) -> list[Any]:
    """The objects of a parsed ``<world>`` tree (UIDs checked unique; *default_radius* for circles without one)."""
    if default_radius < 0:
        raise ValueError(f"default radius must be >= 0 m, got {default_radius}")
    if root.key != "world":
        raise root.error("the root element must be <world>")
    out: list[Any] = []
    seen: dict[str, int] = {}
    for child in root.children:
        if child.key not in SHAPES:
            known = ", ".join(f"<{cls.__name__ if k != 'object' else 'Object'}>" for k, (cls, _) in SHAPES.items())
            raise child.error(f"unknown object class; known: {known}")
        obj = _object(child, origin, default_radius)
        uid = as_type(obj, t.ObjectDescription).uid
        if uid in seen:
            raise child.error(f"duplicate uid {uid!r} (also on line {seen[uid]})")
        seen[uid] = child.line
        out.append(obj)
    return out


def parse_objects(text: str | bytes, *, source: str, origin: GeoOrigin, default_radius: float = 0.0) -> list[Any]:
    """Parse a-priori objects XML *text*; *source* names it in errors."""
    return objects_from_tree(parse_xml(text, source=source), origin=origin, default_radius=default_radius)


def load_objects(path: Path | str, *, origin: GeoOrigin, default_radius: float = 0.0) -> list[Any]:
    """Read and parse the a-priori objects file at *path*."""
    return objects_from_tree(read_xml_file(path), origin=origin, default_radius=default_radius)


__all__ = ["XmlFileError", "load_objects", "parse_objects", "objects_from_tree", "SHAPES"]
