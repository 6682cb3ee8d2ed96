"""The Path Planner's state machine (thesis 3.2.3.4): one state per goal type.

Pure logic, free of the bus. The planner is in exactly one state at a time, chosen by the
type of the current goal: :class:`WaypointState` for a ``Waypoint``, :class:`IdleState`
when there is no goal, the mission has finished, or the goal is of a type no state
handles (a goal type someone added later arrives decoded as its base ``GoalInformation``,
thesis 8.2.5; the planner holds still and says so in its health rather than guess).

Adding a goal type (say a ``Loiter`` that extends ``Waypoint``) without editing u2sa-hw:

1. in your own package, an ``.lcm`` struct whose first field is ``u2sa_hw.lcmtypes.Waypoint
   base;`` (or ``GoalInformation``), compiled with ``lcm-gen -p``;
2. a module that writes the state and registers it at import::

       class LoiterState(WaypointState):
           name = "loiter"
           def step(self, ctx: PlanContext) -> Plan:
               ...   # return Plan.hold(...) or a Plan with the body-frame point to go to

       register_goal_state(Loiter, LoiterState)

3. name that module in the planner's ``goal_state_modules`` config list, or declare it in
   your package's ``u2sa_hw.goal_states`` entry-point group;
   :func:`load_goal_state_modules` imports them when the planner starts and refuses, naming
   the module, one that cannot be imported or registers nothing.

The state for a goal is looked up along the goal's ancestry, nearest type first, so a
``Loiter`` extending ``Waypoint`` without its own state is flown as a waypoint.
docs/core-services-planner-control.md has the complete example.
"""

from __future__ import annotations

import importlib
import math
import sys
from collections.abc import Iterable
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from typing import Any, ClassVar

from u2sa_hw import lcmtypes as t
from u2sa_hw.geo import ned_to_body
from u2sa_hw.messages import REGISTRY, as_type
from u2sa_hw.messages.registry import fingerprint_of
from u2sa_hw.services.planner.avoidance import AvoidanceSettings, Obstacle, choose_heading


@dataclass(frozen=True)
class Pose:
    """The vehicle's pose from the state estimate (local NED, heading clockwise from north)."""

    x: float
    y: float
    psi: float
    z: float | None = None

    @classmethod
    def from_estimate(cls, msg: t.StateInformation) -> Pose | None:
        """The pose in *msg*, or None when it lacks a finite x, y or psi."""
        if not (msg.has("x") and msg.has("y") and msg.has("psi")):
            return None
        if not all(math.isfinite(v) for v in (msg.x, msg.y, msg.psi)):
            return None
        z = msg.get("z")
        return cls(x=msg.x, y=msg.y, psi=msg.psi, z=z if z is not None and math.isfinite(z) else None)


@dataclass(frozen=True)
class GuidanceSettings:
    """How a goal is approached."""

    cruise_speed: float = 1.0          # m/s
    slowdown_radius_m: float = 3.0     # within this distance of the goal the speed ramps down...
    min_speed_fraction: float = 0.3    # ...to this fraction of cruise
    lookahead_m: float = 3.0           # distance of the navigation point along the chosen heading
    default_threshold_m: float = 2.0   # for a waypoint whose horizontal_threshold is not > 0
    avoidance: AvoidanceSettings = field(default_factory=AvoidanceSettings)


@dataclass
class PlanContext:
    """What a state sees in one cycle."""

    pose: Pose
    obstacles: list[Obstacle]
    settings: GuidanceSettings
    memory: dict[str, Any] = field(default_factory=dict)   # kept per state between cycles


@dataclass(frozen=True)
class Plan:
    """A state's decision for one cycle: a body-frame (FRD) point to head for, or a hold."""

    x: float = 0.0                 # forward, m
    y: float = 0.0                 # right, m
    z: float = 0.0                 # down, m (0 when the goal or the estimate has no z)
    speed: float = 0.0             # desired speed, m/s; 0 holds the vehicle
    distance_to_goal: float = -1.0   # horizontal, m; -1 without a goal
    reached: bool = False          # the goal's completion condition holds now
    note: str = ""                 # what the state is doing, for health ("avoiding", "blocked", ...)

    @classmethod
    def hold(cls, note: str, *, distance_to_goal: float = -1.0, reached: bool = False) -> Plan:
        """Stay put (speed 0, the point on the vehicle)."""
        return cls(distance_to_goal=distance_to_goal, reached=reached, note=note)


class GoalState:
    """Base of the planner's states: one instance per goal being worked on."""

    name: ClassVar[str] = "goal"

    def __init__(self, goal: Any) -> None:
        self.goal = goal

    @property
    def uid(self) -> str:
        """The goal's UID ('' for the idle state without a goal)."""
        return "" if self.goal is None else as_type(self.goal, t.GoalInformation).uid

    @classmethod
    def problem(cls, goal: Any) -> str | None:
        """Why this state cannot work on *goal* (then the planner idles), or None."""
        return None

    def step(self, ctx: PlanContext) -> Plan:
        """Decide this cycle's plan."""
        raise NotImplementedError


class IdleState(GoalState):
    """No goal to work on: hold still and say why."""

    name: ClassVar[str] = "idle"

    def __init__(self, goal: Any = None, *, reason: str = "no current goal") -> None:
        super().__init__(goal)
        self.reason = reason

    def step(self, ctx: PlanContext) -> Plan:
        """Always a hold."""
        return Plan.hold(self.reason)


class WaypointState(GoalState):
    """Drive to a LOCAL (NED) waypoint around the objects; reached within its thresholds.

    Reached when the horizontal distance is within ``horizontal_threshold`` and, when the
    waypoint has ``z`` and ``vertical_threshold`` and the estimate has ``z``, the vertical
    one within ``vertical_threshold`` too (inside the horizontal threshold it holds its
    position, ``z`` saying how far up or down is left). The waypoint's attitude
    (``phi``/``theta``/``psi``) and ``time`` are not used here: a goal state of your own
    can (docs/core-services-planner-control.md).
    """

    name: ClassVar[str] = "waypoint"

    @classmethod
    def problem(cls, goal: Any) -> str | None:
        """A waypoint needs x and y in the local frame (the service converts GLOBAL ones first)."""
        wp = as_type(goal, t.Waypoint)
        if not (wp.has("x") and wp.has("y")):
            return f"waypoint {wp.base.uid} has no x/y"
        if not all(math.isfinite(v) for v in (wp.x, wp.y, wp.horizontal_threshold)) or \
                (wp.has("z") and not math.isfinite(wp.z)):
            return f"waypoint {wp.base.uid} has a non-finite x, y, z or threshold"
        frame = wp.reference_frame.strip().upper()
        if frame not in ("", "LOCAL", "NED"):
            return f"waypoint {wp.base.uid} is in frame {wp.reference_frame!r}, not LOCAL"
        return None

    def step(self, ctx: PlanContext) -> Plan:
        """Head for the waypoint along the clear heading nearest its bearing; hold once inside the threshold."""
        wp = as_type(self.goal, t.Waypoint)
        pose, s = ctx.pose, ctx.settings
        dn, de = wp.x - pose.x, wp.y - pose.y
        distance = math.hypot(dn, de)
        threshold = wp.horizontal_threshold if wp.horizontal_threshold > 0 else s.default_threshold_m
        dz = wp.z - pose.z if wp.has("z") and pose.z is not None else 0.0
        if distance <= threshold:
            vertical = wp.get("vertical_threshold")
            if wp.has("z") and pose.z is not None and vertical is not None and math.isfinite(vertical) \
                    and abs(dz) > vertical:
                return Plan(z=dz, distance_to_goal=distance,
                            note=f"over the waypoint, {abs(dz):.1f} m {'down' if dz > 0 else 'up'} to go")
            return Plan.hold("arrived", distance_to_goal=distance, reached=True)
        steering = choose_heading(x=pose.x, y=pose.y, goal_x=wp.x, goal_y=wp.y, obstacles=ctx.obstacles,
                                  settings=s.avoidance, previous_deflection=ctx.memory.get("deflection", 0.0))
        ctx.memory["deflection"] = steering.deflection
        if steering.blocked:
            return Plan.hold(f"blocked: {steering.reason}", distance_to_goal=distance)
        ahead = min(s.lookahead_m, distance) if steering.deflection == 0.0 else s.lookahead_m
        fx, fy = ned_to_body(ahead * math.cos(steering.heading), ahead * math.sin(steering.heading), pose.psi)
        fraction = min(1.0, max(s.min_speed_fraction, distance / max(1e-6, s.slowdown_radius_m)))
        note = "to waypoint"
        if steering.soft_ignored:
            note = "through a level 0/2 object: no clear heading around it"
        elif steering.deflection != 0.0:
            note = f"avoiding ({math.degrees(steering.deflection):+.0f} deg)"
        return Plan(x=fx, y=fy, z=dz, speed=s.cruise_speed * fraction, distance_to_goal=distance, note=note)


GOAL_STATES: dict[type, type[GoalState]] = {
    t.Waypoint: WaypointState,
}
"""Goal type -> the state that works on it. Extend with :func:`register_goal_state`."""


GOAL_STATE_GROUP = "u2sa_hw.goal_states"
"""Entry-point group of modules that register goal states (``name = "package.module"``)."""


class GoalStateModuleError(ImportError):
    """A goal state module cannot be loaded; the message names the module and the fix."""


def register_goal_state(goal_type: type, state: type[GoalState]) -> None:
    """Make *state* the planner's state for goals of *goal_type* (and its extensions without their own).

    A goal type from outside u2sa-hw is added to the message registry, so the planner
    decodes it as itself rather than as its base.
    """
    if not (isinstance(state, type) and issubclass(state, GoalState)):
        raise TypeError(f"{state!r} is not a GoalState subclass")
    if not hasattr(goal_type, "_get_packed_fingerprint"):
        raise TypeError(f"{goal_type!r} is not an LCM type (generate it with lcm-gen -p)")
    if not REGISTRY.is_a(goal_type, t.GoalInformation):   # checked before it is registered for decoding
        raise TypeError(f"{goal_type.__name__} is not a goal: its first field must be 'base' of type "
                        "GoalInformation or an extension of it (Waypoint)")
    if REGISTRY.by_fingerprint(fingerprint_of(goal_type)) is None:
        REGISTRY.register(goal_type)
    GOAL_STATES[goal_type] = state


def _import_goal_module(name: str, *, origin: str) -> list[str]:
    """Import module *name*; the goal types it registered. GoalStateModuleError names it and the fix."""
    if not all(part.isidentifier() for part in name.split(".")):
        raise GoalStateModuleError(f"{origin}: {name!r} is not a module name (like team_goals.states)")
    already = name in sys.modules
    before = dict(GOAL_STATES)
    try:
        importlib.import_module(name)
    except ModuleNotFoundError as exc:
        if exc.name is not None and (name == exc.name or name.startswith(exc.name + ".")):
            raise GoalStateModuleError(f"{origin}: no module {name!r}: install its package into this Python "
                                       f"({sys.executable}) or put its directory on PYTHONPATH") from None
        raise GoalStateModuleError(f"{origin}: module {name!r} failed to import: {exc}") from exc
    except Exception as exc:  # noqa: BLE001 - any error inside the team's module, reported with its name
        raise GoalStateModuleError(f"{origin}: module {name!r} failed to import: {type(exc).__name__}: {exc}") from exc
    added = [goal.__name__ for goal, state in GOAL_STATES.items() if before.get(goal) is not state]
    if not added and not already:
        raise GoalStateModuleError(f"{origin}: module {name!r} registered no goal state; call "
                                   "register_goal_state(GoalType, StateClass) at its top level")
    return added


def load_goal_state_modules(modules: Iterable[str] = (), *, group: str | None = GOAL_STATE_GROUP
                            ) -> dict[str, list[str]]:
    """Import each of *modules* and every module of the entry-point *group*; module -> goal types registered.

    Each module registers its states with :func:`register_goal_state` when imported. An
    entry point names a module (``loiter = "team_goals.states"``). Raises
    :class:`GoalStateModuleError` naming the module (and the entry point) on any failure.
    """
    loaded: dict[str, list[str]] = {}
    for name in modules:
        name = str(name).strip()
        if name and name not in loaded:
            loaded[name] = _import_goal_module(name, origin="goal_state_modules")
    if group:
        for ep in entry_points(group=group):
            dist = getattr(ep.dist, "name", None) or "?"
            module = ep.value.partition(":")[0].strip()
            if module not in loaded:
                loaded[module] = _import_goal_module(module, origin=f"entry point {ep.name} = {ep.value!r} "
                                                                    f"of {dist} (group {group})")
    return loaded


def state_for(goal: Any) -> GoalState:
    """The state that works on *goal*: the registered state nearest in its ancestry, else idle with the reason."""
    if goal is None:
        return IdleState()
    for cls in REGISTRY.ancestry(type(goal)):
        state = GOAL_STATES.get(cls)
        if state is not None:
            problem = state.problem(goal)
            if problem is not None:
                return IdleState(goal, reason=f"unusable goal: {problem}")
            return state(goal)
    return IdleState(goal, reason=f"unsupported goal type {type(goal).__name__}")
