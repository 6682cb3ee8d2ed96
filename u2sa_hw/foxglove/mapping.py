"""LCM messages -> Foxglove topics, the same for the live bridge and ``u2sa log export``.

Every message goes out as JSON on its (channel, type) topic with our own JSON Schema
(``u2sa_hw.foxglove.lcm_json``). Some also give well-known messages Foxglove's panels read:

- ``/location/<channel>`` (``foxglove.LocationFix``, Map panel): ``StateInformation`` on
  ``STATE_ESTIMATE`` and ``STATE_INFO`` with a position; geodetic ones directly, local NED
  ones through the vehicle's origin (none without one: :attr:`FoxgloveMapper.notes` says so).
- ``/tf`` (``foxglove.FrameTransform``) and ``/pose`` (``foxglove.PoseInFrame``): the
  estimate as ``world`` -> ``base_link``. ``world`` is east-north-up about the origin
  (Foxglove's 3D panel has z up), ``base_link`` forward-left-up, so NED (x north, y east,
  z down, heading psi clockwise from north) becomes (y, x, -z) with yaw pi/2 - psi.
- ``/scene/world``, ``/scene/mission``, ``/scene/nav`` (``foxglove.SceneUpdate``, 3D panel):
  world objects (gone from ``WORLD_SUMMARY``: deleted), waypoints with their threshold
  circles, and the planned navigation point.
- ``/health`` (``u2sa.HealthTable``): a row per service (``health_table``), for a Table panel;
  sent on every HSM ``SystemHealth``. So that the table fills without an HSM too, a
  service's own ``Health`` sends it when no ``SystemHealth`` came for :data:`HSM_SILENT_NS`
  (log time; the HSM's last view is then dropped: "no HSM heard"), at most once per
  :data:`HEALTH_TABLE_PERIOD_NS`. With an HSM running, the table is its alone.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any, Callable

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.foxglove import health_table
from u2sa_hw.foxglove import wellknown as wk
from u2sa_hw.foxglove.lcm_json import finite, schema_bytes, topic_for
from u2sa_hw.geo import geodetic_to_ned, ned_to_geodetic
from u2sa_hw.messages import as_type, to_dict
from u2sa_hw.services.world.model import GEODETIC_FRAMES, place_in_world
from u2sa_hw.profile.vehicle import Origin

LOCATION_CHANNELS = (ch.STATE_INFO, ch.STATE_ESTIMATE)
WORLD_FRAME, BODY_FRAME = "world", "base_link"
OBSTACLE = wk.rgba(0.75, 0.22, 0.17, 0.45)
WAYPOINT, WAYPOINT_DONE = wk.rgba(0.12, 0.38, 0.55, 1.0), wk.rgba(0.5, 0.5, 0.5, 0.8)
NAV = wk.rgba(0.95, 0.55, 0.1, 1.0)
OBSTACLE_HEIGHT_M = 1.0
HEALTH_TABLE_PERIOD_NS = 1_000_000_000   # /health from services' own Health: at most this often ...
HSM_SILENT_NS = 3_000_000_000            # ... and only after this long without a SystemHealth (the HSM sends 1/s)


@dataclass(frozen=True)
class Topic:
    """A Foxglove topic: its name and schema (JSON Schema text)."""

    name: str
    schema_name: str
    schema: bytes


def _wk_topic(name: str, schema: dict[str, Any]) -> Topic:
    return Topic(name, schema["title"], json.dumps(schema).encode())


TF = _wk_topic("/tf", wk.FRAME_TRANSFORM)
POSE = _wk_topic("/pose", wk.POSE_IN_FRAME)
SCENE_WORLD = _wk_topic("/scene/world", wk.SCENE_UPDATE)
SCENE_MISSION = _wk_topic("/scene/mission", wk.SCENE_UPDATE)
SCENE_NAV = _wk_topic("/scene/nav", wk.SCENE_UPDATE)
LOG = _wk_topic("/log", wk.LOG)
HEALTH = _wk_topic("/health", health_table.SCHEMA)
LOCATION = {c: _wk_topic(f"/location/{c}", wk.LOCATION_FIX) for c in LOCATION_CHANNELS}

Output = tuple[Topic, dict[str, Any]]


def location_fix(msg: Any, origin: Origin | None, t_ns: int) -> dict[str, Any] | None:
    """A LocationFix for a StateInformation with a finite position, or None.

    LocationFix allows numbers only: a NaN or infinite position gives no fix, a non-finite
    sigma makes the covariance unknown (type 0).
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
    return {"timestamp": wk.stamp(t_ns), "frame_id": msg.sensor_name, "latitude": lat, "longitude": lon,
            "altitude": alt, "position_covariance": cov, "position_covariance_type": 2 if known else 0}


def _is_object(msg: Any) -> bool:
    try:
        as_type(msg, t.ObjectDescription)
    except TypeError:
        return False
    return True


def _finite_all(*values: float) -> bool:
    return all(isinstance(v, (int, float)) and math.isfinite(v) for v in values)


class FoxgloveMapper:
    """Turns decoded LCM messages into Foxglove topics and payloads; keeps the state a scene needs."""

    def __init__(self, *, origin: Origin | None) -> None:
        self.origin = origin
        self.health = health_table.HealthTable()
        self._health_sent_ns: int | None = None   # log time of the latest /health
        self._hsm_heard_ns: int | None = None     # ... of the latest SystemHealth (or the first Health, before one)
        self._objects: set[str] = set()
        # Why a well-known topic stayed empty, counted: {"no origin: local estimate without a map position": n}
        self.notes: dict[str, int] = {}

    def _note(self, why: str) -> None:
        self.notes[why] = self.notes.get(why, 0) + 1

    def map(self, channel: str, msg: Any, t_ns: int, *, wanted: Callable[[Topic], bool] | None = None) -> list[Output]:
        """Every (topic, payload) that *msg*, received on *channel* at *t_ns*, gives.

        *wanted* (the live bridge: does a client listen?) skips building the JSON copy of the
        message itself when it says no; the well-known outputs are built always (they keep state).
        """
        cls = type(msg)
        own = Topic(topic_for(channel, cls), f"u2sa.{cls.__name__}", schema_bytes(cls))
        out: list[Output] = [(own, finite(to_dict(msg)))] if wanted is None or wanted(own) else []
        if isinstance(msg, t.StateInformation) and channel in LOCATION_CHANNELS:
            fix = location_fix(msg, self.origin, t_ns)
            if fix is not None:
                out.append((LOCATION[channel], fix))
            elif msg.reference_frame in ("NED", "") and self.origin is None and msg.has("x"):
                self._note("no geodetic origin: local NED positions give no map fix")
            if channel == ch.STATE_ESTIMATE:
                out.extend(self._estimate(msg, t_ns))
        elif channel == ch.WORLD and _is_object(msg):
            scene = self._object(msg, t_ns)
            if scene is not None:
                out.append((SCENE_WORLD, scene))
        elif channel == ch.WORLD_SUMMARY and isinstance(msg, t.WorldSummary):
            gone = sorted(self._objects - set(msg.uids))
            self._objects -= set(gone)
            if gone:
                out.append((SCENE_WORLD, {"deletions": [{"timestamp": wk.stamp(t_ns), "type": 0, "id": f"object/{u}"}
                                                        for u in gone], "entities": []}))
        elif channel == ch.GOALS and isinstance(msg, t.Waypoint):
            scene = self._waypoint(msg, t_ns)
            if scene is not None:
                out.append((SCENE_MISSION, scene))
        elif channel == ch.NAV_POINT and isinstance(msg, t.NavigationPoint):
            if _finite_all(msg.x, msg.y, msg.z):
                e, n, u = msg.y, msg.x, -msg.z
                label = f"nav {msg.speed:.1f} m/s, {msg.distance_to_goal:.1f} m to {msg.goal_uid}"
                ent = wk.entity("nav_point", WORLD_FRAME, t_ns, spheres=[
                    {"pose": wk.pose(e, n, u), "size": wk.vec(0.6, 0.6, 0.6), "color": NAV}],
                    texts=[wk.text(label, e, n, u + 1.0, NAV)])
                out.append((SCENE_NAV, {"deletions": [], "entities": [finite(ent)]}))
        elif channel == ch.HEALTH and isinstance(msg, t.Health):
            self.health.on_health(msg)
            if self._table_from_services(t_ns):
                out.append(self._health_table(t_ns))
        elif channel == ch.SYSTEM_HEALTH and isinstance(msg, t.SystemHealth):
            self.health.on_system(msg)
            self._hsm_heard_ns = t_ns
            out.append(self._health_table(t_ns))
        return out

    def _table_from_services(self, t_ns: int) -> bool:
        """Whether a service's Health at *t_ns* sends /health: the HSM silent, and none sent for a period."""
        if self._hsm_heard_ns is None:
            self._hsm_heard_ns = t_ns   # the silence is counted from the first Health
        if t_ns - self._hsm_heard_ns < HSM_SILENT_NS:
            return False
        self.health.system = None   # the HSM's last view is stale: its rows fall back to each service's own
        return self._health_sent_ns is None or not 0 <= t_ns - self._health_sent_ns < HEALTH_TABLE_PERIOD_NS

    def _health_table(self, t_ns: int) -> Output:
        self._health_sent_ns = t_ns
        return HEALTH, finite(self.health.message())

    def _estimate(self, msg: Any, t_ns: int) -> list[Output]:
        if not (msg.has("x") and msg.has("y")):
            return []
        if msg.reference_frame == "GEODETIC":
            if self.origin is None:
                return []
            north, east, down = geodetic_to_ned(msg.x, msg.y, msg.get("z"), origin=self.origin)
        elif msg.reference_frame in ("NED", ""):
            north, east, down = msg.x, msg.y, msg.get("z", 0.0)
        else:
            return []
        roll, pitch, psi = msg.get("phi", 0.0), msg.get("theta", 0.0), msg.get("psi", 0.0)
        if not _finite_all(north, east, down, roll, pitch, psi):
            return []
        rotation = wk.quaternion(roll, -pitch, math.pi / 2 - psi)
        translation = wk.vec(east, north, -down)
        stamp = wk.stamp(t_ns)
        return [(TF, {"timestamp": stamp, "parent_frame_id": WORLD_FRAME, "child_frame_id": BODY_FRAME,
                      "translation": translation, "rotation": rotation}),
                (POSE, {"timestamp": stamp, "frame_id": WORLD_FRAME,
                        "pose": {"position": translation, "orientation": rotation}})]

    def _enu(self, frame: str, x: float, y: float, z: float) -> tuple[str, float, float, float] | None:
        """(frame id, x, y, z) in Foxglove's frames of a point in one of our reference frames."""
        if frame == "GEODETIC":
            if self.origin is None:
                self._note("no geodetic origin: geodetic objects and waypoints are not in the 3D scene")
                return None
            x, y, z = geodetic_to_ned(x, y, z, origin=self.origin)
            frame = "NED"
        if frame in ("NED", "LOCAL", ""):
            return WORLD_FRAME, y, x, -z
        if frame == "FRD":
            return BODY_FRAME, x, -y, -z
        return None

    def _object(self, msg: Any, t_ns: int) -> dict[str, Any] | None:
        base = as_type(msg, t.ObjectDescription)
        if base.reference_frame.strip().upper() in GEODETIC_FRAMES and self.origin is not None:
            msg = place_in_world(msg, pose=None, origin=self.origin)   # a polygon's vertices too, as the world does
            base = as_type(msg, t.ObjectDescription)
        place = self._enu(base.reference_frame, base.x, base.y, base.z if math.isfinite(base.z) else 0.0)
        if place is None or not _finite_all(*place[1:]):
            return None
        frame, x, y, z = place
        prims: dict[str, list[dict[str, Any]]] = {"texts": [wk.text(base.uid, x, y, z + OBSTACLE_HEIGHT_M + 0.3,
                                                                    OBSTACLE)]}
        h = OBSTACLE_HEIGHT_M
        if isinstance(msg, t.Circle | t.Sphere):
            r = max(msg.radius if isinstance(msg, t.Circle) else msg.sphere_radius, 0.15)
            if isinstance(msg, t.Circle):
                prims["cylinders"] = [{"pose": wk.pose(x, y, z + h / 2), "size": wk.vec(2 * r, 2 * r, h),
                                       "bottom_scale": 1.0, "top_scale": 1.0, "color": OBSTACLE}]
            else:
                prims["spheres"] = [{"pose": wk.pose(x, y, z), "size": wk.vec(2 * r, 2 * r, 2 * r),
                                     "color": OBSTACLE}]
        elif isinstance(msg, t.Rectangle):
            prims["cubes"] = [{"pose": wk.pose(x, y, z + h / 2, yaw=math.pi / 2 - msg.heading),
                               "size": wk.vec(msg.length, msg.width, h), "color": OBSTACLE}]
        elif isinstance(msg, t.Polygon) and frame == WORLD_FRAME:
            pts = [wk.vec(e, n, z) for n, e in zip(msg.vx, msg.vy)]   # vertices are absolute NED (north, east)
            prims["lines"] = [wk.line(pts, OBSTACLE, loop=True, thickness=0.15)]
        else:
            prims["cubes"] = [{"pose": wk.pose(x, y, z + 0.25), "size": wk.vec(0.5, 0.5, 0.5), "color": OBSTACLE}]
        self._objects.add(base.uid)
        return finite({"deletions": [], "entities": [wk.entity(f"object/{base.uid}", frame, t_ns, **prims)]})

    def _waypoint(self, msg: Any, t_ns: int) -> dict[str, Any] | None:
        frame = "GEODETIC" if msg.reference_frame == "GLOBAL" else "NED"
        place = self._enu(frame, msg.x, msg.y, msg.z if math.isfinite(msg.z) else 0.0)
        if place is None or not _finite_all(*place[1:]):
            return None
        _, x, y, z = place
        colour = WAYPOINT_DONE if msg.base.completed else WAYPOINT
        uid = msg.base.uid
        prims: dict[str, list[dict[str, Any]]] = {
            "spheres": [{"pose": wk.pose(x, y, z), "size": wk.vec(0.5, 0.5, 0.5), "color": colour}],
            "texts": [wk.text(uid + (" (done)" if msg.base.completed else ""), x, y, z + 0.8, colour)]}
        if math.isfinite(msg.horizontal_threshold) and msg.horizontal_threshold > 0:
            prims["lines"] = [wk.circle_line(x, y, z, msg.horizontal_threshold, colour)]
        return {"deletions": [], "entities": [wk.entity(f"waypoint/{uid}", WORLD_FRAME, t_ns, **prims)]}
