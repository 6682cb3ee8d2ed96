"""The geofence as pure geometry, in local NED metres about the vehicle's origin (docs/geofence.md).

A :class:`Fence` is inclusion and exclusion areas, each a polygon or a circle with a name
(``"field"``, ``"field.plan polygon 1"``). The vehicle may be where it is inside at least one
inclusion area (when there are any) and inside no exclusion area; the same rule as PX4 and
QGroundControl. Parsing (the profile's ``[geofence]`` and a ``.plan``'s ``geoFence``) is in
:mod:`u2sa_hw.geofence_parse`; this module only answers questions about points::

    fence.breach(x, y)              # None inside, else a Breach naming the area and why
    fence.clearance(x, y)           # how far (m) the point is from the nearest fence line (0 outside)
    fence.segment_breach(a, b)      # the first area a straight leg from a to b leaves or enters

A point exactly on a line counts as inside: the pre-arm check and the breach judge the line
itself, and the planner keeps ``margin_m`` away from it (:class:`FenceObstacle`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any, Sequence

POLYGON, CIRCLE = "polygon", "circle"
SEGMENT_STEP_M = 0.5   # a leg is sampled this finely (and at every vertex it passes) for segment_breach


@dataclass(frozen=True)
class FenceArea:
    """One inclusion or exclusion area: a polygon (``points`` as (north, east) m) or a circle."""

    name: str
    inclusion: bool
    kind: str
    points: tuple[tuple[float, float], ...] = ()
    center: tuple[float, float] = (0.0, 0.0)
    radius_m: float = 0.0

    @property
    def label(self) -> str:
        """``inclusion polygon 'field'``: what a reason names."""
        return f"{'inclusion' if self.inclusion else 'exclusion'} {self.kind} '{self.name}'"

    def contains(self, x: float, y: float) -> bool:
        """True when (x north, y east) is inside the area or on its line."""
        if self.kind == CIRCLE:
            return math.hypot(x - self.center[0], y - self.center[1]) <= self.radius_m + 1e-9
        if self.edge_distance(x, y) <= 1e-9:
            return True
        inside = False
        pts = self.points
        for (x1, y1), (x2, y2) in zip(pts, pts[1:] + pts[:1]):
            if (y1 > y) != (y2 > y):
                cross = x1 + (y - y1) * (x2 - x1) / (y2 - y1)
                if x < cross:
                    inside = not inside
        return inside

    def edge_distance(self, x: float, y: float) -> float:
        """Distance (m) from (x, y) to the area's line, inside or out."""
        if self.kind == CIRCLE:
            return abs(math.hypot(x - self.center[0], y - self.center[1]) - self.radius_m)
        pts = self.points
        return min(_segment_distance(x, y, a, b) for a, b in zip(pts, pts[1:] + pts[:1]))

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready (the log's ``geofence.json`` attachment)."""
        out: dict[str, Any] = {"name": self.name, "inclusion": self.inclusion, "kind": self.kind}
        if self.kind == CIRCLE:
            out.update(center=list(self.center), radius_m=self.radius_m)
        else:
            out["points"] = [list(p) for p in self.points]
        return out


def _segment_distance(x: float, y: float, a: tuple[float, float], b: tuple[float, float]) -> float:
    dx, dy = b[0] - a[0], b[1] - a[1]
    length2 = dx * dx + dy * dy
    u = 0.0 if length2 == 0 else max(0.0, min(1.0, ((x - a[0]) * dx + (y - a[1]) * dy) / length2))
    return math.hypot(x - (a[0] + u * dx), y - (a[1] + u * dy))


@dataclass(frozen=True)
class Breach:
    """Where a point breaks the fence: the area (for "outside every inclusion area", the nearest one) and why."""

    area: FenceArea
    what: str     # "outside inclusion polygon 'field'": the same for as long as the breach lasts
    reason: str   # with how far and where


@dataclass(frozen=True)
class Fence:
    """Inclusion and exclusion areas, where they came from, and the planner's margin (m)."""

    areas: tuple[FenceArea, ...]
    source: str = ""
    margin_m: float = 1.0
    extra: dict[str, Any] = field(default_factory=dict, compare=False)

    @property
    def inclusions(self) -> tuple[FenceArea, ...]:
        """The areas the vehicle must stay inside (one of them)."""
        return tuple(a for a in self.areas if a.inclusion)

    @property
    def exclusions(self) -> tuple[FenceArea, ...]:
        """The areas the vehicle must stay out of."""
        return tuple(a for a in self.areas if not a.inclusion)

    def names(self) -> str:
        """``'field', 'pond'``: every area's name, for a log line."""
        return ", ".join(f"'{a.name}'" for a in self.areas)

    def breach(self, x: float, y: float) -> Breach | None:
        """None when (x, y) is allowed, else the area it breaks: an exclusion it is inside, or the nearest
        inclusion area when it is inside none. A non-finite position breaches (fail safe)."""
        if not (math.isfinite(x) and math.isfinite(y)):
            first = self.areas[0]
            return Breach(first, "position not finite", f"position ({x}, {y}) is not finite: cannot tell it is "
                                                        "inside the fence")
        for area in self.exclusions:
            if area.contains(x, y):
                depth = area.edge_distance(x, y)
                return Breach(area, f"inside {area.label}", f"inside {area.label} ({depth:.1f} m in) at x {x:.1f}, "
                                                            f"y {y:.1f}")
        inclusions = self.inclusions
        if inclusions and not any(a.contains(x, y) for a in inclusions):
            nearest = min(inclusions, key=lambda a: a.edge_distance(x, y))
            return Breach(nearest, f"outside {nearest.label}", f"outside {nearest.label} "
                                   f"({nearest.edge_distance(x, y):.1f} m out) at x {x:.1f}, y {y:.1f}")
        return None

    def clearance(self, x: float, y: float) -> float:
        """Distance (m) from an allowed point to the nearest fence line it must not cross; 0 where not allowed."""
        if self.breach(x, y) is not None:
            return 0.0
        edges = [a.edge_distance(x, y) for a in self.exclusions]
        inside = [a.edge_distance(x, y) for a in self.inclusions if a.contains(x, y)]
        if inside:
            edges.append(max(inside))   # inside several inclusion areas: the line of the roomiest one counts
        return min(edges) if edges else math.inf

    def segment_breach(self, a: Sequence[float], b: Sequence[float]) -> tuple[float, Breach] | None:
        """The first point of the straight leg *a* -> *b* (north, east) that breaks the fence, as (metres along
        the leg, the breach), or None when the whole leg stays inside."""
        length = math.hypot(b[0] - a[0], b[1] - a[1])
        steps = max(1, math.ceil(length / SEGMENT_STEP_M))
        for i in range(steps + 1):
            u = i / steps
            hit = self.breach(a[0] + u * (b[0] - a[0]), a[1] + u * (b[1] - a[1]))
            if hit is not None:
                return u * length, hit
        return None

    def to_json(self) -> str:
        """The fence as JSON (local metres): what a log carries so ``u2sa log plot`` can draw it."""
        return json.dumps({"source": self.source, "margin_m": self.margin_m,
                           "areas": [a.as_dict() for a in self.areas]}, indent=1)

    @classmethod
    def from_json(cls, text: str | bytes) -> "Fence":
        """A fence written by :meth:`to_json`; ValueError (KeyError, TypeError) on anything else."""
        data = json.loads(text)
        areas = []
        for raw in data["areas"]:
            kind = raw["kind"]
            if kind == CIRCLE:
                areas.append(FenceArea(str(raw["name"]), bool(raw["inclusion"]), CIRCLE,
                                       center=(float(raw["center"][0]), float(raw["center"][1])),
                                       radius_m=float(raw["radius_m"])))
            elif kind == POLYGON:
                areas.append(FenceArea(str(raw["name"]), bool(raw["inclusion"]), POLYGON,
                                       points=tuple((float(p[0]), float(p[1])) for p in raw["points"])))
            else:
                raise ValueError(f"unknown fence area kind {kind!r}")
        return cls(tuple(areas), source=str(data.get("source", "")), margin_m=float(data.get("margin_m", 0.0)))


class FenceObstacle:
    """The fence as the planner's hard obstacles (:class:`u2sa_hw.services.planner.avoidance.Obstacle`'s
    interface): its distance from a point is the point's :meth:`Fence.clearance`, so the avoidance keeps its
    margin from every line, and a goal outside the fence is "inside" the obstacle (blocked, named)."""

    level = 3
    hard = True
    avoided = True
    message = None   # not a WORLD object

    def __init__(self, fence: Fence) -> None:
        self.fence = fence
        self.uid = f"the geofence ({fence.names()}): outside it"

    def distance(self, x: float, y: float) -> float:
        """Distance (m) from (x, y) to the nearest fence line; 0 outside the fence."""
        return self.fence.clearance(x, y)
