"""Distance from a point to an object, for every object type (thesis 3.2.3.5 ``distance to point``).

The thesis asks each Object Description subclass to compute the distance from a point to
its closest point; LCM types carry no methods, so the functions live here, chosen by the
message's type and, for an extension this module does not know, by its nearest known
ancestor (a ``Buoy`` extending ``Circle`` is measured as a circle). The planner imports
:func:`distance_to_point`.

The point must be in the object's frame (the world modeler publishes everything in local
NED). With ``z`` None the distance is horizontal: the object's footprint on the x-y plane
(what a ground vehicle or a boat needs). With ``z`` given it is 3-D; flat shapes (circle,
rectangle, polygon) are then taken as lying in the plane ``z = centre z``.

Geometry (angles in radians):

- ``ObjectDescription``: a point at the centre (x, y, z).
- ``Circle``: radius about the centre; 0 inside.
- ``Rectangle``: ``length`` along ``heading`` (clockwise from north / the x axis),
  ``width`` across it, centred on the centre; 0 inside.
- ``Polygon``: vertices ``vx``, ``vy`` in absolute coordinates of the same frame; 0 inside,
  else the distance to the nearest edge. Fewer than 3 vertices: a polyline.
- ``Sphere``: ``sphere_radius`` about the centre (its footprint is a disc when horizontal).
- ``PointCloud``: the nearest of its points; each point is (azimuth clockwise from the x
  axis, elevation up, distance) from the centre, which for a cloud is where the points
  were measured from (the sensor). An empty cloud is its centre.
"""

from __future__ import annotations

import math
from typing import Any, Callable

from u2sa_hw import lcmtypes as t
from u2sa_hw.messages import REGISTRY, as_type

Point3 = tuple[float, float, float]


def centre(obj: Any) -> Point3:
    """The (x, y, z) centre of any Object Description or extension."""
    base = as_type(obj, t.ObjectDescription)
    return base.x, base.y, base.z


def cloud_points(cloud: t.PointCloud) -> list[Point3]:
    """The points of *cloud* as (x, y, z) in the cloud's frame (z down)."""
    cx, cy, cz = centre(cloud)
    out = []
    for p in cloud.points[:cloud.num_points]:
        horizontal = p.distance * math.cos(p.elevation)
        out.append((cx + horizontal * math.cos(p.azimuth), cy + horizontal * math.sin(p.azimuth),
                    cz - p.distance * math.sin(p.elevation)))
    return out


def _combine(horizontal: float, dz: float | None) -> float:
    return horizontal if dz is None else math.hypot(horizontal, dz)


def _dz(obj: Any, z: float | None) -> float | None:
    return None if z is None else z - centre(obj)[2]


def _point(obj: Any, x: float, y: float, z: float | None) -> float:
    cx, cy, _ = centre(obj)
    return _combine(math.hypot(x - cx, y - cy), _dz(obj, z))


def _circle(obj: t.Circle, x: float, y: float, z: float | None) -> float:
    cx, cy, _ = centre(obj)
    return _combine(max(0.0, math.hypot(x - cx, y - cy) - obj.radius), _dz(obj, z))


def _rectangle(obj: t.Rectangle, x: float, y: float, z: float | None) -> float:
    cx, cy, _ = centre(obj)
    dx, dy = x - cx, y - cy
    c, s = math.cos(obj.heading), math.sin(obj.heading)
    along, across = dx * c + dy * s, -dx * s + dy * c
    out_along = max(0.0, abs(along) - obj.length / 2.0)
    out_across = max(0.0, abs(across) - obj.width / 2.0)
    return _combine(math.hypot(out_along, out_across), _dz(obj, z))


def segment_distance(px: float, py: float, ax: float, ay: float, bx: float, by: float) -> float:
    """Distance from point p to the segment a-b."""
    abx, aby = bx - ax, by - ay
    length2 = abx * abx + aby * aby
    u = 0.0 if length2 == 0.0 else max(0.0, min(1.0, ((px - ax) * abx + (py - ay) * aby) / length2))
    return math.hypot(px - (ax + u * abx), py - (ay + u * aby))


def point_in_polygon(px: float, py: float, xs: list[float], ys: list[float]) -> bool:
    """Even-odd ray casting: True when (px, py) is inside the polygon (xs, ys)."""
    inside = False
    n = len(xs)
    j = n - 1
    for i in range(n):
        if (ys[i] > py) != (ys[j] > py):
            cross_x = xs[i] + (py - ys[i]) * (xs[j] - xs[i]) / (ys[j] - ys[i])
            if px < cross_x:
                inside = not inside
        j = i
    return inside


def _polygon(obj: t.Polygon, x: float, y: float, z: float | None) -> float:
    n = min(obj.num_vertices, len(obj.vx), len(obj.vy))
    xs, ys = list(obj.vx[:n]), list(obj.vy[:n])
    if n == 0:
        return _point(obj, x, y, z)
    if n >= 3 and point_in_polygon(x, y, xs, ys):
        horizontal = 0.0
    elif n == 1:
        horizontal = math.hypot(x - xs[0], y - ys[0])
    else:
        edges = range(n) if n >= 3 else range(n - 1)
        horizontal = min(segment_distance(x, y, xs[i], ys[i], xs[(i + 1) % n], ys[(i + 1) % n]) for i in edges)
    return _combine(horizontal, _dz(obj, z))


def _sphere(obj: t.Sphere, x: float, y: float, z: float | None) -> float:
    cx, cy, cz = centre(obj)
    if z is None:
        return max(0.0, math.hypot(x - cx, y - cy) - obj.sphere_radius)
    return max(0.0, math.dist((x, y, z), (cx, cy, cz)) - obj.sphere_radius)


def _cloud(obj: t.PointCloud, x: float, y: float, z: float | None) -> float:
    points = cloud_points(obj)
    if not points:
        return _point(obj, x, y, z)
    if z is None:
        return min(math.hypot(x - px, y - py) for px, py, _ in points)
    return min(math.dist((x, y, z), p) for p in points)


DISTANCE_FUNCTIONS: dict[type, Callable[..., float]] = {
    t.Circle: _circle,
    t.Rectangle: _rectangle,
    t.Polygon: _polygon,
    t.Sphere: _sphere,
    t.PointCloud: _cloud,
    t.ObjectDescription: _point,
}


def distance_to_point(obj: Any, x: float, y: float, z: float | None = None) -> float:
    """Distance (m) from (x, y[, z]) to the closest point of *obj*; 0 inside. Horizontal when *z* is None."""
    for cls in REGISTRY.ancestry(type(obj)):
        fn = DISTANCE_FUNCTIONS.get(cls)
        if fn is not None:
            return fn(as_type(obj, cls), x, y, z)
    raise TypeError(f"{type(obj).__name__} is not an ObjectDescription or an extension of one")
