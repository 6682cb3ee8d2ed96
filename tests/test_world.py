"""World Modeler: distances for every shape, the a-priori file, placement, association, expiry, the service."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from conftest import ServiceProcesses, wait_until

from u2sa_hw import channels as ch
from u2sa_hw import geo
from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.client import BusClient
from u2sa_hw.messages import as_type
from u2sa_hw.services.world.model import PlacementError, Pose, WorldModel, place_in_world
from u2sa_hw.services.world.shapes import cloud_points, distance_to_point
from u2sa_hw.services.world.xml import XmlFileError, parse_objects
from u2sa_hw.profile.vehicle import Origin

ORIGIN = Origin(lat=29.1895, lon=-81.0483, alt=10.0)


def obj(cls: type = t.ObjectDescription, *, uid: str = "", x: float = 0.0, y: float = 0.0, z: float = 0.0,
        frame: str = "NED", source: str = "lidar", **fields: object) -> object:
    o = cls()
    base = as_type(o, t.ObjectDescription)
    base.uid, base.x, base.y, base.z, base.reference_frame, base.source = uid, x, y, z, frame, source
    for k, v in fields.items():
        setattr(o, k, v)
    return o


def cloud(points: list[tuple[float, float, float]], **kw: object) -> t.PointCloud:
    c = obj(t.PointCloud, **kw)
    for az, el, dist in points:
        p = t.CloudPoint()
        p.azimuth, p.elevation, p.distance = az, el, dist
        c.points.append(p)
    c.num_points = len(c.points)
    return c


# -- distances --------------------------------------------------------------------------------------
def test_distance_to_point_for_every_shape() -> None:
    assert distance_to_point(obj(x=3, y=4), 0, 0) == pytest.approx(5.0)
    assert distance_to_point(obj(x=3, y=4, z=-12), 0, 0, 0) == pytest.approx(13.0)
    circle = obj(t.Circle, x=10, y=0, radius=2.0)
    assert distance_to_point(circle, 0, 0) == pytest.approx(8.0) and distance_to_point(circle, 11, 0.5) == 0.0
    assert distance_to_point(circle, 10, 0, 3.0) == pytest.approx(3.0)         # above a flat disc
    rect = obj(t.Rectangle, x=0, y=0, length=10.0, width=2.0, heading=math.pi / 2)  # long axis east-west
    assert distance_to_point(rect, 0, 4.9) == 0.0 and distance_to_point(rect, 0, 7) == pytest.approx(2.0)
    assert distance_to_point(rect, 4, 0) == pytest.approx(3.0)
    assert distance_to_point(rect, 4, 8) == pytest.approx(math.hypot(3, 3))
    square = obj(t.Polygon, vx=[0.0, 4.0, 4.0, 0.0], vy=[0.0, 0.0, 4.0, 4.0], num_vertices=4)
    assert distance_to_point(square, 2, 2) == 0.0 and distance_to_point(square, 2, 7) == pytest.approx(3.0)
    assert distance_to_point(square, -3, -4) == pytest.approx(5.0)
    line = obj(t.Polygon, vx=[0.0, 10.0], vy=[0.0, 0.0], num_vertices=2)
    assert distance_to_point(line, 5, 2) == pytest.approx(2.0)
    sphere = obj(t.Sphere, x=0, y=0, z=-10, sphere_radius=3.0)
    assert distance_to_point(sphere, 0, 0, 0) == pytest.approx(7.0) and distance_to_point(sphere, 5, 0) == 2.0
    rocks = cloud([(0.0, 0.0, 5.0), (math.pi / 2, 0.0, 2.0)], x=1, y=1)
    assert cloud_points(rocks)[1] == pytest.approx((1.0, 3.0, 0.0))
    assert distance_to_point(rocks, 1, 4) == pytest.approx(1.0) and distance_to_point(rocks, 6, 1) == 0.0
    up = cloud([(0.0, math.pi / 2, 4.0)])
    assert distance_to_point(up, 0, 0, -4.0) == pytest.approx(0.0, abs=1e-9)   # elevation up is -z (NED)
    with pytest.raises(TypeError):
        distance_to_point(t.Health(), 0, 0)


# -- the a-priori file ---------------------------------------------------------------------------------
WORLD = """\
<world>
  <Circle><uid>Circle1</uid><x>4</x><y>8</y><radius>1.5</radius></Circle>
  <rectangle>
    <uid>dock</uid><reference>Global</reference><lat>29.1897</lat><lon>-81.0481</lon>
    <length>12</length><width>3</width><heading unit="deg">90</heading><level>2</level><type>pier</type>
  </rectangle>
  <Polygon><uid>island</uid>
    <vertex><x>20</x><y>0</y></vertex><vertex><x>24</x><y>0</y></vertex><vertex><x>22</x><y>6</y></vertex>
  </Polygon>
  <Sphere><uid>balloon</uid><x>0</x><y>30</y><z>-10</z><radius>2</radius></Sphere>
  <PointCloud><uid>rocks</uid><x>-10</x><y>-10</y>
    <point><azimuth unit="deg">90</azimuth><distance>2</distance></point>
  </PointCloud>
  <Object><uid>post</uid><x>3</x><y>3</y></Object>
</world>
"""


def test_a_priori_objects_parse_and_are_placed_in_ned() -> None:
    objects = parse_objects(WORLD, source="w.xml", origin=ORIGIN)
    assert [type(o).__name__ for o in objects] == ["Circle", "Rectangle", "Polygon", "Sphere", "PointCloud",
                                                    "ObjectDescription"]
    circle, dock, island, balloon, rocks, post = objects
    assert circle.radius == 1.5 and circle.base.base.uid == "Circle1" and circle.base.base.level == 3
    assert circle.base.shape_type == "circle" and circle.base.base.source == "a-priori"
    assert dock.base.base.reference_frame == "GEODETIC" and dock.heading == pytest.approx(math.pi / 2)
    assert dock.base.base.object_type == "pier" and dock.base.base.level == 2
    assert (island.base.base.x, island.base.base.y) == pytest.approx((22.0, 2.0))   # the vertices' mean
    assert balloon.sphere_radius == 2.0 and rocks.points[0].azimuth == pytest.approx(math.pi / 2)

    model = WorldModel(origin=ORIGIN)
    for o in objects:
        model.add_a_priori(o)
    placed = model.tracked["dock"].obj
    north, east, down = geo.geodetic_to_ned(29.1897, -81.0481, origin=ORIGIN)
    assert (placed.base.base.x, placed.base.base.y, placed.base.base.z) == pytest.approx((north, east, 0.0))
    assert placed.base.base.reference_frame == "NED"
    assert model.expire(now=1e9) == [] and len(model.objects()) == 6                 # never expire


# The thesis's Circle example (3.2.3.3), copied from its text: a uid and a position, no radius.
THESIS_CIRCLE = """\
<Circle>
  <uid>Circle1</uid>
  <x>4</x>
  <y>8</y>
</Circle>
"""


def test_the_thesis_circle_example_loads_as_a_point_or_with_the_default_radius() -> None:
    (circle,) = parse_objects(f"<world>\n{THESIS_CIRCLE}</world>", source="w.xml", origin=ORIGIN)
    assert isinstance(circle, t.Circle) and circle.base.base.uid == "Circle1" and circle.radius == 0.0
    assert (circle.base.base.x, circle.base.base.y, circle.base.base.reference_frame) == (4.0, 8.0, "NED")
    assert distance_to_point(circle, 4.0, 11.0) == pytest.approx(3.0)             # a point
    (circle,) = parse_objects(f"<world>{THESIS_CIRCLE}</world>", source="w.xml", origin=ORIGIN, default_radius=1.5)
    assert circle.radius == 1.5 and distance_to_point(circle, 4.0, 11.0) == pytest.approx(1.5)
    sphere, = parse_objects("<world><Sphere><uid>s</uid><x>1</x><y>1</y></Sphere></world>", source="w.xml",
                            origin=ORIGIN, default_radius=2.0)
    assert sphere.sphere_radius == 2.0
    with pytest.raises(ValueError, match="default radius must be >= 0"):
        parse_objects(f"<world>{THESIS_CIRCLE}</world>", source="w.xml", origin=ORIGIN, default_radius=-1.0)


@pytest.mark.parametrize(("text", "line", "element", "words"), [
    ("<world>\n<Circle><x>1</x><y>1</y><radius>1</radius></Circle></world>", 2, "Circle", "has no <uid>"),
    ("<world>\n<Triangle/></world>", 2, "Triangle", "unknown object class"),
    ("<world>\n<Polygon><uid>p</uid>\n<vertex><x>1</x></vertex></Polygon></world>", 3, "vertex",
     "needs <x> and <y> together"),
    ("<world>\n<Circle><uid>a</uid><x>1</x><y>1</y><radius>0</radius></Circle></world>", 2, "radius",
     "greater than 0"),
    ("<world>\n<Object><uid>a</uid><x>1</x><y>1</y></Object>\n<Object><uid>a</uid><x>2</x><y>1</y></Object>"
     "</world>", 3, "Object", "duplicate uid 'a' (also on line 2)"),
    ("<world>\n<Object><uid>a</uid><lat>1</lat><lon>1</lon></Object></world>", 2, "lat",
     "need <reference>Global</reference>"),
    ("<world>\n<Object><uid>a</uid><x>1</x><y>1</y><level>7</level></Object></world>", 2, "level",
     "must be 0, 1, 2 or 3"),
    ("<world><Circle>\n<uid>a</uid></world>", 2, "Circle", "mismatched tag"),
])
def test_malformed_objects_name_file_line_and_element(text: str, line: int, element: str, words: str) -> None:
    with pytest.raises(XmlFileError) as err:
        parse_objects(text, source="w.xml", origin=ORIGIN)
    e = err.value
    assert (e.source, e.line, e.element) == ("w.xml", line, element), str(e)
    assert words in str(e)


# -- placement, association, expiry ---------------------------------------------------------------------
def test_body_frame_objects_are_placed_with_the_pose() -> None:
    pose = Pose(north=100.0, east=50.0, down=0.0, psi=math.pi / 2)           # facing east
    ahead = place_in_world(obj(x=10.0, y=2.0, frame="FRD"), pose=pose, origin=ORIGIN)
    assert (ahead.x, ahead.y) == pytest.approx((98.0, 60.0)) and ahead.reference_frame == "NED"
    rect = place_in_world(obj(t.Rectangle, x=5.0, frame="FRD", length=4.0, width=1.0, heading=0.0),
                          pose=pose, origin=ORIGIN)
    assert rect.heading == pytest.approx(math.pi / 2) and distance_to_point(rect, 100.0, 56.9) == 0.0
    poly = place_in_world(obj(t.Polygon, frame="FRD", vx=[1.0, 2.0, 2.0], vy=[0.0, 0.0, 1.0], num_vertices=3),
                          pose=pose, origin=ORIGIN)
    assert list(poly.vx) == pytest.approx([100.0, 100.0, 99.0]) and list(poly.vy) == pytest.approx([51.0, 52.0, 52.0])
    pts = cloud_points(place_in_world(cloud([(0.0, 0.0, 3.0)], frame="FRD"), pose=pose, origin=ORIGIN))
    assert pts[0] == pytest.approx((100.0, 53.0, 0.0))                        # 3 m ahead = 3 m east
    with pytest.raises(PlacementError, match="no recent STATE_ESTIMATE"):
        place_in_world(obj(frame="FRD"), pose=None, origin=ORIGIN)
    with pytest.raises(PlacementError, match="unknown reference_frame 'UTM17'"):
        place_in_world(obj(frame="UTM17"), pose=pose, origin=ORIGIN)


def test_association_by_uid_and_by_source_and_proximity_then_expiry() -> None:
    model = WorldModel(origin=ORIGIN, expiry_s=2.0, association_radius_m=1.0)
    pose = Pose(0.0, 0.0, 0.0, 0.0)
    model.observe(obj(uid="buoy", x=5.0, frame="FRD", source="camera"), now=0.0, pose=pose)
    model.observe(obj(uid="buoy", x=5.4, frame="FRD", source="camera"), now=0.5, pose=pose)
    assert len(model.tracked) == 1 and model.tracked["buoy"].updates == 2 and model.tracked["buoy"].obj.x == 5.4
    first = model.observe(obj(x=20.0, y=1.0), now=0.5, pose=pose)            # no uid: a new object
    assert first.uid == "lidar-1"
    again = model.observe(obj(x=20.6, y=1.2), now=1.0, pose=pose)            # same source, 0.63 m away
    assert again.uid == "lidar-1" and model.stats.by_proximity == 1
    other = model.observe(obj(x=20.6, y=1.2, source="sonar"), now=1.0, pose=pose)   # another source
    far = model.observe(obj(x=25.0, y=1.0), now=1.0, pose=pose)
    assert other.uid == "sonar-2" and far.uid == "lidar-3"
    circle = model.observe(obj(t.Circle, x=20.5, y=1.0, radius=1.0), now=1.0, pose=pose)   # another type
    assert circle.uid == "lidar-4"
    assert sorted(model.expire(now=2.6)) == ["buoy"]                         # last seen at 0.5
    assert sorted(model.expire(now=3.1)) == ["lidar-1", "lidar-3", "lidar-4", "sonar-2"]
    assert model.stats.expired == 5 and model.tracked == {}


# -- the service over real LCM -----------------------------------------------------------------------
def test_service_places_merges_expires_and_publishes(services: ServiceProcesses, bus: BusClient,
                                                     tmp_path: Path) -> None:
    thesis_circle = THESIS_CIRCLE.replace("Circle1", "thesis")
    (tmp_path / "objects.xml").write_text(WORLD.replace("</world>", thesis_circle + "</world>"))
    vehicle = tmp_path / "vehicle.toml"
    vehicle.write_text(f"[vehicle]\norigin = {{ lat = {ORIGIN.lat}, lon = {ORIGIN.lon}, alt = {ORIGIN.alt} }}\n"
                       "[services.world]\nkind = \"world_modeler\"\n"
                       "settings = { objects_file = \"objects.xml\", publish_rate_hz = 10.0, expiry_s = 1.0, "
                       "default_radius_m = 0.8 }\n")
    world: list[object] = []
    summaries: list[t.WorldSummary] = []
    bus.transport.subscribe(ch.WORLD, t.ObjectDescription, lambda _c, msg: world.append(msg))
    bus.transport.subscribe(ch.WORLD_SUMMARY, t.WorldSummary, lambda _c, msg: summaries.append(msg))
    services.start("world", "--vehicle", str(vehicle))
    wait_until(lambda: summaries and summaries[-1].num_objects == 7, timeout=20, message="the a-priori objects")
    assert {type(o).__name__ for o in world} == {"Circle", "Rectangle", "Polygon", "Sphere", "PointCloud",
                                                  "ObjectDescription"}
    thesis = next(o for o in world if isinstance(o, t.Circle) and o.base.base.uid == "thesis")
    assert thesis.radius == 0.8                                          # the configured default_radius_m

    estimate = t.StateInformation().set(x=10.0, y=20.0, psi=math.pi)       # facing south
    estimate.sensor_name = "state_estimator"

    def seen_buoy() -> bool:
        bus.publish(ch.STATE_ESTIMATE, estimate)
        bus.publish(ch.OBJECTS, obj(t.Circle, uid="buoy7", x=4.0, y=0.0, frame="FRD", source="camera", radius=0.5))
        return any(isinstance(o, t.Circle) and o.base.base.uid == "buoy7" for o in world[-8:])

    wait_until(seen_buoy, timeout=10, message="the camera's buoy on WORLD")
    buoy = next(o for o in reversed(world) if isinstance(o, t.Circle) and o.base.base.uid == "buoy7")
    assert (buoy.base.base.x, buoy.base.base.y) == pytest.approx((6.0, 20.0)) and buoy.radius == 0.5
    assert buoy.base.base.reference_frame == "NED" and buoy.base.base.source == "camera"
    assert "buoy7" in summaries[-1].uids
    wait_until(lambda: summaries[-1].num_objects == 7 and "buoy7" not in summaries[-1].uids, timeout=10,
               message="the buoy to expire, the a-priori objects to stay")
