"""The geofence from the profile's ``[geofence]`` table and from a QGroundControl ``.plan``'s ``geoFence``.

```toml
[geofence]
plan = "field.plan"              # optional: the areas of this plan's geoFence (relative to the profile)
margin_m = 1.0                   # the path planner keeps this far inside every line

[[geofence.polygons]]            # any number; points as [lat, lon] degrees, or local = [[north, east], ...] m
name = "field"
inclusion = true                 # true: stay inside (default); false: stay out
points = [[29.18960, -81.04850], [29.18960, -81.04800], [29.18980, -81.04800]]

[[geofence.circles]]
name = "pond"
inclusion = false
center = [29.18970, -81.04820]   # or local_center = [north, east]
radius_m = 4.0
```

Latitudes and longitudes go through the profile's ``[vehicle] origin`` into local x north,
y east, as a plan's waypoints do. A plan's areas are named ``"field.plan polygon 1"``,
``"field.plan circle 2"``. Every mistake (a polygon with fewer than three corners, one whose
edges cross, zero area, a circle with a radius <= 0, a wrong type, an area over 10 km away)
is one :class:`FenceError` line naming the file, the area and the fix.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping

from u2sa_hw.geo import GeoOrigin, geodetic_to_ned
from u2sa_hw.geofence import CIRCLE, POLYGON, Fence, FenceArea
from u2sa_hw.profile.vehicle import ProfileError, VehicleProfile

MAX_VERTICES = 1000
FAR_M = 10_000.0              # geo.py's flat-earth projection holds within ~10 km
MAX_RADIUS_M = FAR_M
DEFAULT_MARGIN_M = 1.0
TABLE_KEYS = frozenset({"plan", "margin_m", "polygons", "circles"})
POLYGON_KEYS = frozenset({"name", "inclusion", "points", "local"})
CIRCLE_KEYS = frozenset({"name", "inclusion", "center", "local_center", "radius_m"})


class FenceError(ValueError):
    """A fence that cannot be used; one line naming the file, the area and the fix."""


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _pair(value: Any, what: str, where: str, *, geodetic: bool) -> tuple[float, float]:
    unit = "[latitude, longitude] in degrees" if geodetic else "[north, east] in metres"
    if not isinstance(value, (list, tuple)) or len(value) < 2 or not all(_number(v) for v in value[:2]):
        raise FenceError(f"{where}: {what} must be {unit}, got {str(value)[:60]}")
    a, b = float(value[0]), float(value[1])
    if geodetic and not (-90 <= a <= 90 and -180 <= b <= 180):
        raise FenceError(f"{where}: {what} {[a, b]} is not a latitude (-90..90) and a longitude (-180..180); a "
                         "point is [latitude, longitude]")
    return a, b


def _local(lat_lon: tuple[float, float], origin: GeoOrigin, where: str) -> tuple[float, float]:
    north, east, _ = geodetic_to_ned(lat_lon[0], lat_lon[1], origin=origin)
    if math.hypot(north, east) > FAR_M:
        raise FenceError(f"{where}: ({lat_lon[0]:.6f}, {lat_lon[1]:.6f}) is {math.hypot(north, east) / 1000:.0f} km "
                         f"from the vehicle's origin ({origin.lat:.6f}, {origin.lon:.6f}): a fence for another place, "
                         "or the profile's [vehicle] origin is wrong")
    return north, east


def _cross(o: tuple[float, float], a: tuple[float, float], b: tuple[float, float]) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def _segments_cross(p1: tuple[float, float], p2: tuple[float, float], q1: tuple[float, float],
                    q2: tuple[float, float]) -> bool:
    d1, d2, d3, d4 = _cross(q1, q2, p1), _cross(q1, q2, p2), _cross(p1, p2, q1), _cross(p1, p2, q2)
    return ((d1 > 0) != (d2 > 0)) and ((d3 > 0) != (d4 > 0)) and 0 not in (d1, d2, d3, d4)


def checked_polygon(points: list[tuple[float, float]], where: str) -> tuple[tuple[float, float], ...]:
    """*points* (local metres) as a polygon's corners: a closing corner equal to the first is dropped; fewer
    than three distinct corners, zero area or crossing edges are a FenceError."""
    pts = list(points)
    if len(pts) > 1 and math.dist(pts[0], pts[-1]) < 1e-6:
        pts.pop()   # written closed (first corner repeated): the polygon closes itself
    if len(pts) > MAX_VERTICES:
        raise FenceError(f"{where}: {len(pts)} corners; at most {MAX_VERTICES}: simplify the polygon")
    if len({(round(x, 3), round(y, 3)) for x, y in pts}) < 3:
        raise FenceError(f"{where}: a polygon needs at least 3 distinct corners, got {len(pts)}; add corners "
                         "(it closes itself: the last corner joins the first)")
    edges = list(zip(pts, pts[1:] + pts[:1]))
    for i, (a1, a2) in enumerate(edges):
        for j in range(i + 2, len(edges)):
            if i == 0 and j == len(edges) - 1:
                continue   # the first and last edges share the first corner
            b1, b2 = edges[j]
            if _segments_cross(a1, a2, b1, b2):
                raise FenceError(f"{where}: edges {i + 1} and {j + 1} cross (the corners are out of order); "
                                 "list the corners in order around the area")
    area = 0.5 * abs(sum(a[0] * b[1] - b[0] * a[1] for a, b in zip(pts, pts[1:] + pts[:1])))
    if area < 0.01:
        raise FenceError(f"{where}: the polygon has no area (its corners lie on one line); give corners that "
                         "enclose the area")
    return tuple(pts)


def checked_radius(value: Any, where: str) -> float:
    """A circle's radius: a finite number > 0 and <= 10 km."""
    if not _number(value) or not 0 < value <= MAX_RADIUS_M:
        raise FenceError(f"{where}: the radius must be a number of metres > 0 and <= {MAX_RADIUS_M:g}, got "
                         f"{value!r}")
    return float(value)


def plan_areas(fence: Any, *, source: str, origin: GeoOrigin) -> list[FenceArea]:
    """The areas of a plan's ``geoFence`` object (version 2: ``polygons`` and ``circles``), named after
    *source*'s file name; FenceError for anything malformed."""
    label = Path(source).name
    where = f"{source}: geoFence"
    if fence is None:
        return []
    if not isinstance(fence, dict):
        raise FenceError(f"{where}: must be an object {{\"version\": 2, \"polygons\": [...], \"circles\": [...]}}")
    if fence.get("polygon"):
        raise FenceError(f"{where}: a version-1 fence (\"polygon\"): open the plan in QGroundControl and save it "
                         "again (it writes version 2)")
    areas: list[FenceArea] = []
    for key, kind in (("polygons", POLYGON), ("circles", CIRCLE)):
        items = fence.get(key, [])
        if not isinstance(items, list):
            raise FenceError(f"{where}: \"{key}\" must be an array")
        for i, raw in enumerate(items):
            at = f"{where}.{key}[{i}] ({kind} {i + 1})"
            if not isinstance(raw, dict):
                raise FenceError(f"{at}: must be an object")
            inclusion = raw.get("inclusion", True)
            if not isinstance(inclusion, bool):
                raise FenceError(f"{at}: \"inclusion\" must be true or false, got {inclusion!r}")
            name = f"{label} {kind} {i + 1}"
            if kind == POLYGON:
                corners = raw.get("polygon")
                if not isinstance(corners, list):
                    raise FenceError(f"{at}: \"polygon\" must be an array of [latitude, longitude]")
                local = [_local(_pair(p, f"corner {n + 1}", at, geodetic=True), origin, at)
                         for n, p in enumerate(corners)]
                areas.append(FenceArea(name, inclusion, POLYGON, points=checked_polygon(local, at)))
            else:
                circle = raw.get("circle")
                if not isinstance(circle, dict):
                    raise FenceError(f"{at}: \"circle\" must be an object {{\"center\": [lat, lon], \"radius\": m}}")
                center = _local(_pair(circle.get("center"), "the center", at, geodetic=True), origin, at)
                areas.append(FenceArea(name, inclusion, CIRCLE, center=center,
                                       radius_m=checked_radius(circle.get("radius"), at)))
    return areas


def _unknown(table: Mapping[str, Any], known: frozenset[str], where: str) -> None:
    extra = sorted(set(table) - known)
    if extra:
        raise FenceError(f"{where}: unknown key '{extra[0]}' (known: {', '.join(sorted(known))})")


def _table_areas(table: Mapping[str, Any], where: str, origin: GeoOrigin) -> list[FenceArea]:
    areas: list[FenceArea] = []
    for key, kind, known in (("polygons", POLYGON, POLYGON_KEYS), ("circles", CIRCLE, CIRCLE_KEYS)):
        items = table.get(key, [])
        if not isinstance(items, list) or not all(isinstance(i, dict) for i in items):
            raise FenceError(f"{where}: '{key}' must be [[geofence.{key}]] tables")
        for i, raw in enumerate(items):
            at = f"{where}.{key}[{i}]"
            _unknown(raw, known, at)
            name = raw.get("name", f"{kind} {i + 1}")
            inclusion = raw.get("inclusion", True)
            if not isinstance(name, str) or not name.strip():
                raise FenceError(f"{at}: 'name' must be a non-empty string, got {name!r}")
            if not isinstance(inclusion, bool):
                raise FenceError(f"{at}: 'inclusion' must be true (stay inside) or false (stay out), got {inclusion!r}")
            at = f"{at} '{name}'"
            geo_key, local_key = ("points", "local") if kind == POLYGON else ("center", "local_center")
            if (geo_key in raw) == (local_key in raw):
                raise FenceError(f"{at}: give either '{geo_key}' (latitude, longitude) or '{local_key}' (north, east "
                                 "m about the origin), not both or neither")
            geodetic = geo_key in raw
            value = raw[geo_key] if geodetic else raw[local_key]
            if kind == POLYGON:
                if not isinstance(value, list):
                    raise FenceError(f"{at}: '{geo_key if geodetic else local_key}' must be a list of corners")
                pts = [_pair(p, f"corner {n + 1}", at, geodetic=geodetic) for n, p in enumerate(value)]
                local = [_local(p, origin, at) for p in pts] if geodetic else pts
                areas.append(FenceArea(name, inclusion, POLYGON, points=checked_polygon(local, at)))
            else:
                center = _pair(value, "the center", at, geodetic=geodetic)
                if geodetic:
                    center = _local(center, origin, at)
                areas.append(FenceArea(name, inclusion, CIRCLE, center=center,
                                       radius_m=checked_radius(raw.get("radius_m"), at)))
    return areas


def parse_geofence(table: Any, *, where: str, base_dir: Path, origin: GeoOrigin) -> Fence | None:
    """The fence of a profile's ``[geofence]`` table (None: no table, or one with no areas is an error);
    *where* names the table in errors, *base_dir* resolves ``plan``."""
    if table is None:
        return None
    if not isinstance(table, dict):
        raise FenceError(f"{where}: must be a table (see docs/geofence.md)")
    _unknown(table, TABLE_KEYS, where)
    margin = table.get("margin_m", DEFAULT_MARGIN_M)
    if not _number(margin) or not 0 <= margin <= 100:
        raise FenceError(f"{where}: 'margin_m' must be a number of metres >= 0 and <= 100, got {margin!r}")
    areas: list[FenceArea] = []
    sources: list[str] = []
    plan = table.get("plan")
    if plan is not None:
        if not isinstance(plan, str) or not plan.strip():
            raise FenceError(f"{where}: 'plan' must be the path of a QGroundControl .plan, got {plan!r}")
        path = Path(plan).expanduser()
        path = path if path.is_absolute() else base_dir / path
        areas += load_plan_fence(path, origin=origin, where=f"{where} plan")
        sources.append(str(path))
    areas += _table_areas(table, where, origin)
    if not areas:
        raise FenceError(f"{where}: no areas: add [[geofence.polygons]] or [[geofence.circles]], or plan = "
                         "\"FILE.plan\" with a geofence (or remove [geofence] for no fence)")
    names = [a.name for a in areas]
    if len(set(names)) != len(names):
        twice = next(n for n in names if names.count(n) > 1)
        raise FenceError(f"{where}: two areas are named '{twice}'; give each its own name")
    return Fence(tuple(areas), source=", ".join(sources) or where.split(" [", 1)[0], margin_m=float(margin))


def load_plan_fence(path: Path, *, origin: GeoOrigin, where: str) -> list[FenceArea]:
    """The areas of the geoFence of the .plan at *path*; FenceError when it is unreadable or holds no fence."""
    from u2sa_hw.services.mission.qgc_plan import PlanError, load_plan_text

    try:
        plan = load_plan_text(path.read_bytes(), source=str(path))
    except OSError as exc:
        raise FenceError(f"{where}: {path}: cannot read: {exc.strerror or exc}") from None
    except PlanError as exc:
        raise FenceError(f"{where}: {exc}") from None
    areas = plan_areas(plan.get("geoFence"), source=str(path), origin=origin)
    if not areas:
        raise FenceError(f"{where}: {path} has no geofence (no polygons or circles in its geoFence); draw the fence "
                         "in QGroundControl's Plan view (Fence) and save, or remove 'plan'")
    return areas


def profile_fence(profile: VehicleProfile) -> Fence | None:
    """The fence of a loaded :class:`~u2sa_hw.profile.vehicle.VehicleProfile` (None without ``[geofence]``);
    ProfileError names the file and the fix."""
    table = profile.raw.get("geofence")
    if table is None:
        return None
    base = profile.path.resolve().parent if profile.path else Path.cwd()
    where = f"{profile.path or 'the vehicle profile'} [geofence]"
    if "origin" not in (profile.raw.get("vehicle") or {}) and _uses_geodetic(table):
        raise ProfileError(f"{where}: the fence has latitudes and longitudes, which become local x/y about the "
                           "profile's [vehicle] origin, and it sets none: add origin = { lat = ..., lon = ..., "
                           "alt = ... } to [vehicle]")
    try:
        return parse_geofence(table, where=where, base_dir=base, origin=profile.origin)
    except FenceError as exc:
        raise ProfileError(str(exc)) from None


def _uses_geodetic(table: Any) -> bool:
    if not isinstance(table, dict):
        return False
    if table.get("plan") is not None:
        return True
    items = [*table.get("polygons", []), *table.get("circles", [])] if isinstance(table.get("polygons", []), list) \
        and isinstance(table.get("circles", []), list) else []
    return any(isinstance(i, dict) and ("points" in i or "center" in i) for i in items)
