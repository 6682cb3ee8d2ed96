"""The World Modeler's logic (thesis 3.2.3.3), free of the bus: place, associate, expire.

Every object is kept in the local NED frame. Where it comes from decides how it is placed
(:func:`place_in_world`), by its ``reference_frame``:

- ``NED`` / ``LOCAL`` / empty: as it is;
- ``GEODETIC`` / ``GLOBAL``: x = latitude, y = longitude (deg), z = altitude (m up), and
  polygon vertices vx = latitude, vy = longitude; converted about the profile origin;
- ``FRD`` / ``BODY``: relative to the vehicle (x forward, y right, z down) at the pose of
  the latest estimate; rotated by its heading and moved to its position. Rectangle
  headings and point-cloud azimuths turn with the vehicle. Roll and pitch are taken as
  level (a ground vehicle or a boat).

Association: an observation with a UID updates the object with that UID. Without one it
updates the nearest object of the same source and type whose centre is within
``association_radius_m``; otherwise it becomes a new object named ``<source>-<n>``.
Observed objects not seen for ``expiry_s`` are dropped; a-priori objects never expire.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

from u2sa_hw import lcmtypes as t
from u2sa_hw.geo import GeoOrigin, body_to_ned, geodetic_to_ned, wrap_angle
from u2sa_hw.messages import as_type

NED_FRAMES = frozenset({"", "NED", "LOCAL"})
GEODETIC_FRAMES = frozenset({"GEODETIC", "GLOBAL"})
BODY_FRAMES = frozenset({"FRD", "BODY"})


class PlacementError(ValueError):
    """An object cannot be placed in the world frame (no pose for a body-frame object, an unknown frame)."""


@dataclass(frozen=True)
class Pose:
    """Where the vehicle is: NED position (m) and heading psi (rad, clockwise from north)."""

    north: float
    east: float
    down: float
    psi: float

    @classmethod
    def from_estimate(cls, msg: t.StateInformation) -> "Pose | None":
        """The pose in a STATE_ESTIMATE, or None when it lacks x, y or psi (z defaults to 0)."""
        if not all(msg.has(n) for n in ("x", "y", "psi")) or msg.reference_frame.upper() not in NED_FRAMES:
            return None
        return cls(msg.x, msg.y, msg.get("z", 0.0), msg.psi)


def copy_message(msg: Any) -> Any:
    """A deep copy of an LCM message."""
    return type(msg).decode(msg.encode())


def place_in_world(obj: Any, *, pose: Pose | None, origin: GeoOrigin) -> Any:
    """A copy of *obj* in local NED (``reference_frame`` "NED"); :class:`PlacementError` if impossible."""
    out = copy_message(obj)
    base = as_type(out, t.ObjectDescription)
    frame = base.reference_frame.strip().upper()
    if frame in NED_FRAMES:
        pass
    elif frame in GEODETIC_FRAMES:
        base.x, base.y, base.z = geodetic_to_ned(base.x, base.y, base.z, origin=origin)
        if isinstance(out, t.Polygon):
            pts = [geodetic_to_ned(la, lo, origin=origin) for la, lo in zip(out.vx, out.vy)]
            out.vx, out.vy = [p[0] for p in pts], [p[1] for p in pts]
    elif frame in BODY_FRAMES:
        if pose is None:
            raise PlacementError(f"{type(obj).__name__} {base.uid or '(no uid)'} from {base.source or '?'} is in "
                                 "the body frame and there is no recent STATE_ESTIMATE with x, y and psi")
        dn, de = body_to_ned(base.x, base.y, pose.psi)
        base.x, base.y, base.z = pose.north + dn, pose.east + de, pose.down + base.z
        if isinstance(out, t.Polygon):
            pts = [body_to_ned(vx, vy, pose.psi) for vx, vy in zip(out.vx, out.vy)]
            out.vx, out.vy = [pose.north + p[0] for p in pts], [pose.east + p[1] for p in pts]
        elif isinstance(out, t.Rectangle):
            out.heading = wrap_angle(out.heading + pose.psi)
        elif isinstance(out, t.PointCloud):
            for p in out.points:
                p.azimuth = wrap_angle(p.azimuth + pose.psi)
    else:
        raise PlacementError(f"{type(obj).__name__} {base.uid or '(no uid)'} from {base.source or '?'}: unknown "
                             f"reference_frame {base.reference_frame!r} (use NED, GEODETIC or FRD)")
    base.reference_frame = "NED"
    return out


@dataclass
class TrackedObject:
    """One object of the world model."""

    uid: str
    obj: Any
    source: str
    a_priori: bool
    last_seen: float
    updates: int = 1


@dataclass
class WorldStats:
    """Counters for health."""

    observations: int = 0
    by_uid: int = 0
    by_proximity: int = 0
    new: int = 0
    expired: int = 0
    unplaceable: int = 0
    per_source: dict[str, int] = field(default_factory=dict)


class WorldModel:
    """Objects in local NED keyed by UID."""

    def __init__(self, *, origin: GeoOrigin, expiry_s: float = 5.0, association_radius_m: float = 1.0,
                 logger: logging.Logger | None = None) -> None:
        self.origin = origin
        self.expiry_s = expiry_s
        self.association_radius_m = association_radius_m
        self.logger = logger or logging.getLogger("u2sa.world")
        self.tracked: dict[str, TrackedObject] = {}
        self.stats = WorldStats()
        self._counter = 0

    def add_a_priori(self, obj: Any, *, now: float = 0.0) -> TrackedObject:
        """Add a known object (placed in NED; never expires)."""
        placed = place_in_world(obj, pose=None, origin=self.origin)
        base = as_type(placed, t.ObjectDescription)
        tracked = TrackedObject(uid=base.uid, obj=placed, source=base.source or "a-priori", a_priori=True,
                                last_seen=now)
        self.tracked[base.uid] = tracked
        return tracked

    def observe(self, obj: Any, *, now: float, pose: Pose | None) -> TrackedObject:
        """Place and associate an observation; :class:`PlacementError` when it cannot be placed."""
        base_in = as_type(obj, t.ObjectDescription)
        source = base_in.source or base_in.header.source or "?"
        self.stats.observations += 1
        self.stats.per_source[source] = self.stats.per_source.get(source, 0) + 1
        try:
            placed = place_in_world(obj, pose=pose, origin=self.origin)
        except PlacementError:
            self.stats.unplaceable += 1
            raise
        base = as_type(placed, t.ObjectDescription)
        uid = base.uid
        if uid:
            self.stats.by_uid += uid in self.tracked
        else:
            uid = self._nearest(placed, source)
            if uid is not None:
                self.stats.by_proximity += 1
            else:
                self._counter += 1
                uid = f"{source}-{self._counter}"
            base.uid = uid
        old = self.tracked.get(uid)
        if old is None:
            self.stats.new += 1
            self.logger.info("new object %s (%s) from %s", uid, type(placed).__name__, source)
            old = self.tracked[uid] = TrackedObject(uid=uid, obj=placed, source=source, a_priori=False, last_seen=now)
        else:
            old.obj, old.last_seen, old.updates = placed, now, old.updates + 1
            old.source = source
        return old

    def _nearest(self, placed: Any, source: str) -> str | None:
        base = as_type(placed, t.ObjectDescription)
        best, best_d = None, math.inf
        for tr in self.tracked.values():
            if tr.a_priori or tr.source != source or type(tr.obj) is not type(placed):
                continue
            other = as_type(tr.obj, t.ObjectDescription)
            d = math.hypot(other.x - base.x, other.y - base.y)
            if d <= self.association_radius_m and d < best_d:
                best, best_d = tr.uid, d
        return best

    def expire(self, now: float) -> list[str]:
        """Drop observed objects not seen for ``expiry_s`` (<= 0: never); return their UIDs."""
        if self.expiry_s <= 0:
            return []
        gone = [uid for uid, tr in self.tracked.items() if not tr.a_priori and now - tr.last_seen > self.expiry_s]
        for uid in gone:
            del self.tracked[uid]
            self.logger.info("object %s expired (not seen for %.1f s)", uid, self.expiry_s)
        self.stats.expired += len(gone)
        return gone

    def objects(self) -> list[Any]:
        """Every object (concrete types, NED), a-priori ones first."""
        return [tr.obj for tr in sorted(self.tracked.values(), key=lambda tr: not tr.a_priori)]

    def uids(self) -> list[str]:
        """The UIDs of every object, in the order of :meth:`objects`."""
        return [as_type(o, t.ObjectDescription).uid for o in self.objects()]
