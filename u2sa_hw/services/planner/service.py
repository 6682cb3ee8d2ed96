"""Path Planner service (requirement S4; thesis 3.2.3.4, 4.5.2.4, 4.6.2.3).

Subscribes ``STATE_ESTIMATE`` (the pose), ``GOALS`` (Waypoint, or any GoalInformation:
an unknown extension arrives as its base and leaves the planner idle, logged),
``MISSION_STATUS`` (which goal is current) and ``WORLD`` (objects in local NED, kept by
UID until they expire). On each estimate it runs the state of the current goal
(:mod:`.states`, steering around objects with :mod:`.avoidance`) and publishes a
``NavigationPoint`` on ``NAV_POINT`` -- and when no estimate made one for
``1 / control_rate_hz``, its run loop does (so the hold point and report re-sends go on): a point in the body frame (FRD: x forward, y right,
z down, metres from the vehicle) ``lookahead_m`` along the heading to take, with the
desired speed, the horizontal distance to the goal and the goal's UID. A reached goal is
reported on ``GOAL_REPORT`` (once, again after ``report_resend_s`` if still current).

The profile's geofence is planned inside (:mod:`.planner`). Without a fresh estimate nothing is published; with an estimate but no goal the point is a
hold (0, 0, 0, speed 0, distance -1, goal_uid ''). The bookkeeping is in :mod:`.planner`.
"""

from __future__ import annotations

import threading
import time
from typing import Any, ClassVar

from u2sa_hw import channels as ch
from u2sa_hw import lcmtypes as t
from u2sa_hw.config.fields import MAX_RATE_HZ, MAX_TIMEOUT_S, ConfigError, field
from u2sa_hw.geo import geodetic_to_ned
from u2sa_hw.geofence_parse import profile_fence
from u2sa_hw.service.contract import U2SAService
from u2sa_hw.services.planner.avoidance import AvoidanceSettings
from u2sa_hw.services.planner.planner import PathPlanner, PlannerTimings
from u2sa_hw.services.planner.states import GoalStateModuleError, GuidanceSettings, load_goal_state_modules


class PathPlannerService(U2SAService):
    """Turns the current goal, the pose and the world into navigation points."""

    SERVICE_TYPE: ClassVar[str] = "path_planner"
    CONFIG = (
        field("control_rate_hz", 20.0, "the least NAV_POINT publications per second (each estimate makes one too)", gt=0, le=MAX_RATE_HZ),
        field("subsystem", "vehicle", "the NavigationPoint's subsystem"),
        field("cruise_speed_m_s", 1.0, "desired speed toward a goal, m/s", gt=0, le=100.0),
        field("slowdown_radius_m", 3.0, "within this distance of a goal the speed ramps down, m", ge=0, le=10000.0),
        field("min_speed_fraction", 0.3, "the ramp's lowest fraction of the cruise speed", ge=0, le=1),
        field("lookahead_m", 3.0, "distance of the navigation point along the chosen heading, m", gt=0, le=10000.0),
        field("default_threshold_m", 2.0, "completion radius of a waypoint without a horizontal_threshold, m", gt=0, le=10000.0),
        field("clearance_margin_m", 1.0, "distance kept from avoided objects (half the vehicle's width + safety), m", ge=0, le=1000.0),
        field("avoidance_range_m", 10.0, "how far ahead candidate headings are checked against objects, m", gt=0, le=10000.0),
        field("heading_step_deg", 5.0, "spacing of the candidate headings, degrees", gt=0, le=180),
        field("hysteresis_deg", 15.0, "preference for the side already turned to, degrees", ge=0, le=180),
        field("estimate_timeout_s", 1.0, "an older STATE_ESTIMATE is not used: nothing is published", gt=0, le=MAX_TIMEOUT_S),
        field("object_expiry_s", 3.0, "an object not on WORLD for this long is forgotten (0: never)", ge=0, le=MAX_TIMEOUT_S),
        field("report_resend_s", 2.0, "resend a completion report if the goal is still current this long after", gt=0, le=MAX_TIMEOUT_S),
        field("goal_state_modules", [], "modules imported at start that register goal states (plus the "
              "u2sa_hw.goal_states entry points); see docs/core-services-planner-control.md", item_type=str),
    )

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self._load_goal_states()
        self._lock = threading.Lock()
        self._last_cycle = -float("inf")   # monotonic time of the latest planning cycle
        self._last_sent = -float("inf")    # ... and of the latest NAV_POINT
        self._sent: tuple[Any, ...] = ()
        fence = profile_fence(self.profile)
        self.planner = PathPlanner(guidance=self._guidance(), timings=self._timings(),
                                   subsystem=str(self.config.get("subsystem")), logger=self.logger, fence=fence)
        if fence is not None:
            self.logger.info("geofence: planning inside %s", fence.names())
        self.register_subscriber(ch.STATE_ESTIMATE, t.StateInformation, self._on_estimate)
        self.register_subscriber(ch.GOALS, t.GoalInformation, self._on_goal)
        self.register_subscriber(ch.MISSION_STATUS, t.MissionStatus, self._on_status)
        self.register_subscriber(ch.WORLD, t.ObjectDescription, self._on_object)
        self.register_publisher(ch.NAV_POINT, t.NavigationPoint)
        self.register_publisher(ch.GOAL_REPORT, t.GoalReport)

    # -- configuration -----------------------------------------------------------------------
    def _load_goal_states(self) -> None:
        """Import the goal state modules (config list and entry points); ConfigError naming a bad one."""
        modules = self.config.get("goal_state_modules")
        if isinstance(modules, str) or not all(isinstance(m, str) for m in modules):
            raise ConfigError(f"{self.name}: goal_state_modules must be a list of module names, like "
                              f"[\"team_goals.states\"], got {modules!r}")
        try:
            loaded = load_goal_state_modules(modules)
        except GoalStateModuleError as exc:
            where = f" (fix it in {self.config.path} or the vehicle profile's settings)" if modules else ""
            raise ConfigError(f"{self.name}: {exc}{where}") from None
        for module, goal_types in loaded.items():
            self.logger.info("goal state module %s: states for %s", module, ", ".join(goal_types) or "(already loaded)")

    def _guidance(self) -> GuidanceSettings:
        c = self.config.get
        avoidance = AvoidanceSettings(margin_m=float(c("clearance_margin_m")), range_m=float(c("avoidance_range_m")),
                                      heading_step_deg=float(c("heading_step_deg")),
                                      hysteresis_deg=float(c("hysteresis_deg")))
        return GuidanceSettings(cruise_speed=float(c("cruise_speed_m_s")),
                                slowdown_radius_m=float(c("slowdown_radius_m")),
                                min_speed_fraction=float(c("min_speed_fraction")), lookahead_m=float(c("lookahead_m")),
                                default_threshold_m=float(c("default_threshold_m")), avoidance=avoidance)

    def _timings(self) -> PlannerTimings:
        c = self.config.get
        return PlannerTimings(estimate_timeout_s=float(c("estimate_timeout_s")),
                              object_expiry_s=float(c("object_expiry_s")), report_resend_s=float(c("report_resend_s")))

    def on_config_change(self, name: str, value: Any) -> None:
        """Apply every setting live (the rate at the next cycle)."""
        with self._lock:
            self.planner.guidance = self._guidance()
            self.planner.timings = self._timings()
            self.planner.subsystem = str(self.config.get("subsystem"))

    # -- inputs ---------------------------------------------------------------------------------
    def _on_estimate(self, msg: t.StateInformation) -> None:
        with self._lock:
            now = time.monotonic()
            self.planner.on_estimate(msg, now)
            self._cycle(now)

    def _on_goal(self, msg: Any) -> None:
        if isinstance(msg, t.Waypoint) and msg.reference_frame.strip().upper() in ("GLOBAL", "GEODETIC"):
            msg = self._localised(msg)
        with self._lock:
            self.planner.on_goal(msg, time.monotonic())

    def _localised(self, wp: t.Waypoint) -> t.Waypoint:
        """A GLOBAL waypoint (x = lat, y = lon degrees, z = altitude up) in LOCAL NED about the origin."""
        if not (wp.has("x") and wp.has("y")):
            return wp
        origin = self.profile.origin
        north, east, _ = geodetic_to_ned(wp.x, wp.y, origin=origin)
        local = t.Waypoint.decode(wp.encode())
        local.reference_frame = "LOCAL"
        local.set(x=north, y=east)
        if wp.has("z"):
            local.set(z=origin.alt - wp.z)
        return local

    def _on_status(self, msg: t.MissionStatus) -> None:
        with self._lock:
            self.planner.on_status(msg, time.monotonic())

    def _on_object(self, msg: Any) -> None:
        with self._lock:
            self.planner.on_object(msg, time.monotonic())

    # -- output ----------------------------------------------------------------------------------
    def _cycle(self, now: float) -> None:
        """Plan once and publish the report and the point (under the lock, so cycles go out in order).

        A point equal to the one last sent (a hold) goes out at ``control_rate_hz`` only.
        """
        self._last_cycle = now
        cycle = self.planner.step(now)
        if cycle.report is not None:
            self.publish(ch.GOAL_REPORT, cycle.report)
        nav = cycle.nav
        if nav is None:
            return
        key = (nav.subsystem, nav.goal_uid, nav.x, nav.y, nav.z, nav.speed, nav.distance_to_goal)
        if key != self._sent or now - self._last_sent >= 1.0 / max(0.1, float(self.config.get("control_rate_hz"))):
            self._last_sent, self._sent = now, key
            self.publish(ch.NAV_POINT, nav)

    def run(self) -> None:
        """Plan when no estimate made a cycle for ``1 / control_rate_hz``."""
        while True:
            period = 1.0 / max(0.1, float(self.config.get("control_rate_hz")))
            with self._lock:
                now = time.monotonic()
                if now - self._last_cycle >= period:
                    self._cycle(now)
                due = self._last_cycle + period
            if not self.wait(max(0.0, due - time.monotonic())):
                return

    def health_details(self) -> dict[str, Any]:
        """State, goal, what the planner is doing or waiting for, object and report counts."""
        with self._lock:
            details = self.planner.summary()
        blocked = details["doing"].startswith("blocked") or details["doing"].startswith("waiting")
        if self.status in ("ok", "degraded"):
            self.status = "degraded" if blocked else "ok"
        return details

