"""The one simulated vehicle that every mock sensor samples and every mock actuator drives.

Planar kinematics on flat ground or a calm surface: roll and pitch stay 0 and ``down`` stays
at its start value, so the vehicle's state is a pose (north, east, yaw) plus a surge speed
``u`` (m/s, body x) and a yaw rate ``r`` (rad/s, clockwise positive). Three drive models:

``differential``  skid-steer rover. The left/right surface speeds (what the wheel motors
                  report) take effect at once: u = (vl + vr) / 2, r = (vl - vr) / track_width.
``twin_thruster`` boat with a thruster each side. First-order surge and yaw with linear drag:
                  du/dt = (max_speed * (tl + tr) / 2 - u) / BOAT_SURGE_TAU_S,
                  dr/dt = (max_yaw_rate * (tl - tr) / 2 - r) / BOAT_YAW_TAU_S,
                  with max_yaw_rate = max_speed / track_width (a slower turn than wheels give).
``ackermann``     car-like bicycle model about the rear axle: the throttle sets a speed target
                  that u follows with ACKERMANN_SPEED_TAU_S, r = u * tan(steer) / wheel_base.

Accelerations are what a strapdown accelerometer at the reference point reads, in body FRD:
specific force = kinematic acceleration - gravity, so at rest accel_z = -g. With roll = pitch
= 0 that is (du/dt, u * r, -g): turning right (r > 0) while moving forward pulls +y.

Geodetic positions come from NED with a local flat-earth (equirectangular) projection about
the origin using the WGS84 meridian and prime-vertical radii of curvature at the origin's
latitude. Within a few kilometres of the origin the error is centimetres, far below GPS
noise; it is exact as a round trip (``ned_to_geodetic`` and ``geodetic_to_ned`` invert each
other). Angles in radians, yaw and course clockwise from north in [-pi, pi).

Everything is deterministic: no randomness here (sensor noise is each mock device's own,
seeded); ``t`` is simulation time, which ``start()`` advances in step with the monotonic
clock and ``step(dt)`` advances by exactly dt.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

from u2sa_hw import geo
from u2sa_hw.profile.vehicle import Origin
GRAVITY = 9.80665  # standard gravity, m/s^2

BOAT_SURGE_TAU_S = 2.0
BOAT_YAW_TAU_S = 1.0
ACKERMANN_SPEED_TAU_S = 0.5
ACKERMANN_MAX_STEER_RAD = math.radians(35.0)

MODELS = ("differential", "twin_thruster", "ackermann")
SIDES = ("left", "right")


def ned_to_geodetic(north: float, east: float, down: float, *, origin_lat: float, origin_lon: float,
                    origin_alt: float = 0.0) -> tuple[float, float, float]:
    """(lat deg, lon deg, alt m) of a NED point (m) about the origin: the runtime's own projection."""
    return geo.ned_to_geodetic(north, east, down, origin=Origin(origin_lat, origin_lon, origin_alt))


def geodetic_to_ned(lat: float, lon: float, alt: float, *, origin_lat: float, origin_lon: float,
                    origin_alt: float = 0.0) -> tuple[float, float, float]:
    """(north, east, down) in m about the origin of a geodetic point; inverse of ned_to_geodetic."""
    return geo.geodetic_to_ned(lat, lon, alt, origin=Origin(origin_lat, origin_lon, origin_alt))


wrap_angle = geo.wrap_angle


@dataclass(frozen=True)
class VehicleTruth:
    """The simulated vehicle's true state at one instant (SI units, NED world, FRD body)."""

    t: float
    north: float
    east: float
    down: float
    lat: float
    lon: float
    alt: float
    v_north: float
    v_east: float
    v_down: float
    speed: float
    course: float
    roll: float
    pitch: float
    yaw: float
    roll_rate: float
    pitch_rate: float
    yaw_rate: float
    accel_x: float
    accel_y: float
    accel_z: float
    wheel_left_m: float
    wheel_right_m: float


def _finite(name: str, value: float) -> float:
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"SimVehicle: {name} must be a finite number, got {value!r}")
    return value


class SimVehicle:
    """A deterministic planar vehicle (see the module docstring for the models); thread-safe."""

    def __init__(self, *, origin_lat: float, origin_lon: float, origin_alt: float = 0.0,
                 model: str = "differential", track_width: float = 0.5, wheel_base: float = 0.6,
                 max_speed: float = 2.0, start_north: float = 0.0, start_east: float = 0.0,
                 start_yaw: float = 0.0) -> None:
        if model not in MODELS:
            raise ValueError(f"SimVehicle: unknown model {model!r}; use one of {', '.join(MODELS)}")
        for name, value in (("track_width", track_width), ("wheel_base", wheel_base), ("max_speed", max_speed)):
            if not _finite(name, value) > 0:
                raise ValueError(f"SimVehicle: {name} must be > 0, got {value!r}")
        self.origin_lat = _finite("origin_lat", origin_lat)
        self.origin_lon = _finite("origin_lon", origin_lon)
        self.origin_alt = _finite("origin_alt", origin_alt)
        self.model = model
        self.track_width = float(track_width)
        self.wheel_base = float(wheel_base)
        self.max_speed = float(max_speed)
        self._lock = threading.Lock()
        self._t = 0.0
        self._north = _finite("start_north", start_north)
        self._east = _finite("start_east", start_east)
        self._down = 0.0
        self._yaw = wrap_angle(_finite("start_yaw", start_yaw))
        self._u = 0.0
        self._r = 0.0
        self._du = 0.0
        self._wheel = {"left": 0.0, "right": 0.0}
        self._odometer = {"left": 0.0, "right": 0.0}
        self._cmd = {"left": 0.0, "right": 0.0}  # wheel speeds (m/s) or thrust fractions
        self._steer = 0.0
        self._throttle = 0.0
        self._push = (0.0, 0.0)   # (north, east) m/s the world adds: a slope, mud, a current
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    # ---- actuator inputs -------------------------------------------------------------
    def _require(self, model: str, call: str) -> None:
        if self.model != model:
            raise ValueError(f"SimVehicle: {call} needs model '{model}' but this vehicle is '{self.model}'; "
                             f"drive it with the {self.model} inputs or configure model = '{model}'")

    @staticmethod
    def _side(side: str) -> str:
        if side not in SIDES:
            raise ValueError(f"SimVehicle: side must be 'left' or 'right', got {side!r}")
        return side

    def set_wheel_speed(self, side: str, speed_mps: float) -> None:
        """Set one side's surface speed in m/s (differential), clamped to +-max_speed."""
        self._require("differential", "set_wheel_speed")
        v = max(-self.max_speed, min(self.max_speed, _finite("speed_mps", speed_mps)))
        with self._lock:
            self._cmd[self._side(side)] = v

    def set_thrust(self, side: str, fraction: float) -> None:
        """Set one thruster's thrust as a fraction -1..1 of full (twin_thruster), clamped."""
        self._require("twin_thruster", "set_thrust")
        f = max(-1.0, min(1.0, _finite("fraction", fraction)))
        with self._lock:
            self._cmd[self._side(side)] = f

    def set_steering(self, angle_rad: float) -> None:
        """Set the front-wheel steering angle in rad, positive right (ackermann), clamped to +-35 deg."""
        self._require("ackermann", "set_steering")
        a = max(-ACKERMANN_MAX_STEER_RAD, min(ACKERMANN_MAX_STEER_RAD, _finite("angle_rad", angle_rad)))
        with self._lock:
            self._steer = a

    def set_throttle(self, fraction: float) -> None:
        """Set the throttle as a fraction -1..1 of max_speed (ackermann), clamped."""
        self._require("ackermann", "set_throttle")
        f = max(-1.0, min(1.0, _finite("fraction", fraction)))
        with self._lock:
            self._throttle = f

    # ---- dynamics --------------------------------------------------------------------
    def set_push(self, north_mps: float, east_mps: float) -> None:
        """Move the vehicle this fast over the ground whatever its inputs (a slope, mud, a current; 0, 0: none).
        The wheels' odometry does not see it; the GPS does."""
        with self._lock:
            self._push = (_finite("north_mps", north_mps), _finite("east_mps", east_mps))

    def _rates(self, dt: float) -> tuple[float, float]:
        """New (u, r) after dt under the current inputs; caller holds the lock."""
        u, r = self._u, self._r
        if self.model == "differential":
            vl, vr = self._cmd["left"], self._cmd["right"]
            return (vl + vr) / 2.0, (vl - vr) / self.track_width
        if self.model == "twin_thruster":
            tl, tr = self._cmd["left"], self._cmd["right"]
            max_yaw_rate = self.max_speed / self.track_width
            # exact discretisation of the first-order lag, stable for any dt
            ku, kr = 1.0 - math.exp(-dt / BOAT_SURGE_TAU_S), 1.0 - math.exp(-dt / BOAT_YAW_TAU_S)
            u += (self.max_speed * (tl + tr) / 2.0 - u) * ku
            r += (max_yaw_rate * (tl - tr) / 2.0 - r) * kr
            return u, r
        u += (self.max_speed * self._throttle - u) * (1.0 - math.exp(-dt / ACKERMANN_SPEED_TAU_S))
        return u, u * math.tan(self._steer) / self.wheel_base

    def step(self, dt: float) -> None:
        """Advance the simulation by *dt* seconds (> 0) under the current inputs."""
        dt = _finite("dt", dt)
        if dt <= 0:
            raise ValueError(f"SimVehicle.step: dt must be > 0 s, got {dt!r}")
        with self._lock:
            u, r = self._rates(dt)
            yaw0 = self._yaw
            if abs(r) > 1e-9:  # exact arc for constant u, r over the step
                self._north += u / r * (math.sin(yaw0 + r * dt) - math.sin(yaw0))
                self._east += u / r * (math.cos(yaw0) - math.cos(yaw0 + r * dt))
            else:
                self._north += u * math.cos(yaw0) * dt
                self._east += u * math.sin(yaw0) * dt
            self._north += self._push[0] * dt
            self._east += self._push[1] * dt
            self._yaw = wrap_angle(yaw0 + r * dt)
            self._du = (u - self._u) / dt
            self._u, self._r = u, r
            half = r * self.track_width / 2.0  # turning right: left side is the outer one
            self._wheel = {"left": u + half, "right": u - half}
            for side in SIDES:
                self._odometer[side] += self._wheel[side] * dt
            self._t += dt

    def snapshot(self) -> VehicleTruth:
        """The current true state."""
        with self._lock:
            u, r, yaw = self._u, self._r, self._yaw
            v_north, v_east = u * math.cos(yaw) + self._push[0], u * math.sin(yaw) + self._push[1]
            speed = abs(u) if self._push == (0.0, 0.0) else math.hypot(v_north, v_east)
            course = wrap_angle(math.atan2(v_east, v_north)) if speed > 1e-9 else yaw
            lat, lon, alt = ned_to_geodetic(self._north, self._east, self._down, origin_lat=self.origin_lat,
                                            origin_lon=self.origin_lon, origin_alt=self.origin_alt)
            return VehicleTruth(
                t=self._t, north=self._north, east=self._east, down=self._down, lat=lat, lon=lon, alt=alt,
                v_north=v_north, v_east=v_east, v_down=0.0, speed=speed, course=course,
                roll=0.0, pitch=0.0, yaw=yaw, roll_rate=0.0, pitch_rate=0.0, yaw_rate=r,
                accel_x=self._du, accel_y=u * r, accel_z=-GRAVITY,
                wheel_left_m=self._odometer["left"], wheel_right_m=self._odometer["right"])

    # ---- real-time running -----------------------------------------------------------
    def start(self, rate_hz: float = 100.0) -> None:
        """Step the simulation on a thread at *rate_hz*, keeping simulation time with the clock."""
        rate_hz = _finite("rate_hz", rate_hz)
        if rate_hz <= 0:
            raise ValueError(f"SimVehicle.start: rate_hz must be > 0, got {rate_hz!r}")
        if self._thread is not None:
            raise RuntimeError("SimVehicle.start: already running; call stop() first")
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, args=(1.0 / rate_hz,), name="SimVehicle", daemon=True)
        self._thread.start()

    def _run(self, dt: float) -> None:
        next_tick = time.monotonic() + dt
        while not self._stop.wait(max(0.0, next_tick - time.monotonic())):
            self.step(dt)
            next_tick += dt
            if time.monotonic() - next_tick > 1.0:
                next_tick = time.monotonic() + dt  # stalled (debugger, suspend): do not replay the gap

    def stop(self) -> None:
        """Stop the stepping thread (the state is kept; start() resumes)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None

    @property
    def running(self) -> bool:
        """True while start() has the stepping thread going."""
        return self._thread is not None
