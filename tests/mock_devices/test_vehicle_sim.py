"""SimVehicle kinematics, its accelerometer view and the NED <-> geodetic conversion."""

from __future__ import annotations

import math

import pytest
from conftest import wait_until

from u2sa_hw.mocks.vehicle_sim import (GRAVITY, SimVehicle, geodetic_to_ned, ned_to_geodetic,
                                      wrap_angle)

ORIGIN = dict(origin_lat=29.1895, origin_lon=-81.0483, origin_alt=10.0)


def run(vehicle: SimVehicle, seconds: float, dt: float = 0.01) -> None:
    for _ in range(round(seconds / dt)):
        vehicle.step(dt)


def test_straight_line_north_then_east() -> None:
    v = SimVehicle(**ORIGIN)
    v.set_wheel_speed("left", 1.0)
    v.set_wheel_speed("right", 1.0)
    run(v, 10.0)
    s = v.snapshot()
    assert s.north == pytest.approx(10.0, abs=1e-9)
    assert s.east == pytest.approx(0.0, abs=1e-9)
    assert (s.speed, s.v_north, s.yaw, s.yaw_rate, s.course) == pytest.approx((1.0, 1.0, 0.0, 0.0, 0.0))
    assert (s.accel_x, s.accel_y, s.accel_z) == pytest.approx((0.0, 0.0, -GRAVITY))
    assert (s.wheel_left_m, s.wheel_right_m) == pytest.approx((10.0, 10.0))
    assert s.t == pytest.approx(10.0)

    east = SimVehicle(**ORIGIN, start_yaw=math.pi / 2, start_north=5.0)
    east.set_wheel_speed("left", 2.0)
    east.set_wheel_speed("right", 2.0)
    run(east, 3.0)
    e = east.snapshot()
    assert (e.north, e.east, e.v_east) == pytest.approx((5.0, 6.0, 2.0), abs=1e-9)
    assert e.course == pytest.approx(math.pi / 2)


def test_speed_change_shows_as_forward_acceleration() -> None:
    v = SimVehicle(**ORIGIN)
    v.step(0.1)
    v.set_wheel_speed("left", 0.5)
    v.set_wheel_speed("right", 0.5)
    v.step(0.1)
    assert v.snapshot().accel_x == pytest.approx(5.0)  # 0 -> 0.5 m/s in 0.1 s
    v.step(0.1)
    assert v.snapshot().accel_x == pytest.approx(0.0)


def test_turning_in_place_keeps_position_and_turns_clockwise_for_left_forward() -> None:
    v = SimVehicle(**ORIGIN, track_width=0.5)
    v.set_wheel_speed("left", 0.5)
    v.set_wheel_speed("right", -0.5)
    run(v, 0.5)
    s = v.snapshot()
    assert s.yaw_rate == pytest.approx(2.0)  # (vl - vr) / track_width
    assert s.yaw == pytest.approx(1.0)
    assert (s.north, s.east, s.speed, s.accel_y) == pytest.approx((0.0, 0.0, 0.0, 0.0), abs=1e-12)
    assert (s.wheel_left_m, s.wheel_right_m) == pytest.approx((0.25, -0.25))
    run(v, 2.0)  # 5 rad total: wrapped into [-pi, pi)
    assert v.snapshot().yaw == pytest.approx(wrap_angle(5.0))
    assert -math.pi <= v.snapshot().yaw < math.pi


def test_circle_has_centripetal_acceleration_and_closes() -> None:
    v = SimVehicle(**ORIGIN, track_width=0.5)
    v.set_wheel_speed("left", 1.0)
    v.set_wheel_speed("right", 0.5)  # u = 0.75 m/s, r = 1 rad/s, radius 0.75 m, to the right
    run(v, math.pi / 2, dt=math.pi / 2 / 1000)
    s = v.snapshot()
    assert (s.north, s.east) == pytest.approx((0.75, 0.75), abs=1e-9)
    assert s.accel_y == pytest.approx(0.75)  # u * r, pointing right (toward the centre)
    run(v, 3 * math.pi / 2, dt=math.pi / 2 / 1000)
    s = v.snapshot()
    assert (s.north, s.east) == pytest.approx((0.0, 0.0), abs=1e-9)


def test_twin_thruster_boat_settles_to_max_speed_and_turns_toward_weaker_side() -> None:
    boat = SimVehicle(**ORIGIN, model="twin_thruster", max_speed=2.0, track_width=0.8)
    boat.set_thrust("left", 1.0)
    boat.set_thrust("right", 1.0)
    run(boat, 1.0)
    early = boat.snapshot()
    assert 0.0 < early.speed < 2.0 and early.accel_x > 0.0
    run(boat, 24.0)
    s = boat.snapshot()
    assert s.speed == pytest.approx(2.0, rel=1e-3)
    assert s.accel_x == pytest.approx(0.0, abs=1e-3)
    boat.set_thrust("right", 0.0)
    run(boat, 20.0)
    s = boat.snapshot()
    assert s.yaw_rate == pytest.approx(2.0 / 0.8 * 0.5, rel=1e-3)  # max_speed / track_width * (tl - tr) / 2
    assert s.speed == pytest.approx(1.0, rel=1e-3)


def test_ackermann_yaw_rate_follows_bicycle_model() -> None:
    car = SimVehicle(**ORIGIN, model="ackermann", wheel_base=0.6, max_speed=2.0)
    car.set_throttle(0.5)
    car.set_steering(0.2)
    run(car, 10.0)
    s = car.snapshot()
    assert s.speed == pytest.approx(1.0, rel=1e-4)
    assert s.yaw_rate == pytest.approx(1.0 * math.tan(0.2) / 0.6, rel=1e-4)
    car.set_steering(1.5)  # clamped to 35 deg
    car.step(0.01)
    assert car.snapshot().yaw_rate == pytest.approx(car.snapshot().speed * math.tan(math.radians(35)) / 0.6)


def test_inputs_of_another_model_and_bad_values_are_refused() -> None:
    with pytest.raises(ValueError, match="unknown model 'hovercraft'"):
        SimVehicle(**ORIGIN, model="hovercraft")
    rover = SimVehicle(**ORIGIN)
    with pytest.raises(ValueError, match="set_thrust needs model 'twin_thruster'"):
        rover.set_thrust("left", 0.5)
    with pytest.raises(ValueError, match="side must be 'left' or 'right'"):
        rover.set_wheel_speed("middle", 0.5)
    with pytest.raises(ValueError, match="finite"):
        rover.set_wheel_speed("left", float("nan"))
    with pytest.raises(ValueError, match="dt must be > 0"):
        rover.step(0.0)
    with pytest.raises(ValueError, match="track_width must be > 0"):
        SimVehicle(**ORIGIN, track_width=0.0)
    rover.set_wheel_speed("left", 99.0)  # clamped to max_speed
    rover.step(0.1)
    assert rover.snapshot().wheel_left_m == pytest.approx(0.2)  # 2.0 m/s for 0.1 s
    assert rover.snapshot().speed == pytest.approx(1.0)


def test_same_inputs_give_identical_states() -> None:
    def drive() -> object:
        v = SimVehicle(**ORIGIN, model="twin_thruster")
        v.set_thrust("left", 0.7)
        v.set_thrust("right", -0.2)
        run(v, 3.0)
        return v.snapshot()

    assert drive() == drive()


@pytest.mark.parametrize("lat0,lon0,alt0", [(29.1895, -81.0483, 10.0), (-33.87, 151.21, 0.0),
                                            (64.1, -21.9, 120.0), (0.0, 179.9999, 0.0)])
def test_geodetic_round_trip(lat0: float, lon0: float, alt0: float) -> None:
    origin = dict(origin_lat=lat0, origin_lon=lon0, origin_alt=alt0)
    for n, e, d in [(0.0, 0.0, 0.0), (1234.5, -678.9, -3.0), (-2500.0, 2500.0, 12.5)]:
        lat, lon, alt = ned_to_geodetic(n, e, d, **origin)
        assert alt == pytest.approx(alt0 - d)
        assert geodetic_to_ned(lat, lon, alt, **origin) == pytest.approx((n, e, d), abs=1e-6)


def test_geodetic_scale_matches_wgs84_at_the_equator() -> None:
    # one degree of latitude at the equator is a(1 - e^2) * pi / 180 = 110574.27 m,
    # one degree of longitude is a * pi / 180 = 111319.49 m
    lat, lon, _ = ned_to_geodetic(110574.27, 111319.49, 0.0, origin_lat=0.0, origin_lon=0.0)
    assert (lat, lon) == pytest.approx((1.0, 1.0), abs=1e-6)


def test_snapshot_geodetic_agrees_with_ned() -> None:
    v = SimVehicle(**ORIGIN, start_north=100.0, start_east=-50.0)
    s = v.snapshot()
    assert geodetic_to_ned(s.lat, s.lon, s.alt, **ORIGIN) == pytest.approx((100.0, -50.0, 0.0), abs=1e-6)
    assert s.alt == pytest.approx(10.0)


def test_start_runs_the_simulation_on_a_thread_until_stop() -> None:
    v = SimVehicle(**ORIGIN)
    v.set_wheel_speed("left", 1.0)
    v.set_wheel_speed("right", 1.0)
    v.start(rate_hz=200)
    try:
        assert v.running
        wait_until(lambda: v.snapshot().t > 0.2, message="simulation time to advance")
    finally:
        v.stop()
    frozen = v.snapshot()
    assert not v.running
    assert frozen.north == pytest.approx(frozen.t, rel=1e-6)  # 1 m/s straight north
    assert v.snapshot() == frozen
